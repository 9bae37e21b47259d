/* Drape's cloth solvers: one step of many cloths, mirroring drape.server.reference. This file is
 * the program the host builds (device.py); the parts live in the files it includes, in the order
 * below (each opens with what it does).
 *
 * Build options (all -D):
 *   FEATURE_XPBD, FEATURE_TETHERS, FEATURE_COLLIDERS, FEATURE_WIND, FEATURE_NORMALS  (0/1)
 *   FEATURE_SELF_COLLISION (0/1, given only when 1), SELF_COLLISION_PASSES (passes per substep)
 *   USE_LOCAL      1: wg_step keeps the cloth's positions in local memory (cloth must fit)
 *                  0: wg_step works on global memory, and the coloured/Jacobi kernels exist
 *   JACOBI_OMEGA   over-relaxation of the Jacobi vertex solver
 *   LINK_UNROLL    links a work-item loads before it stores any (memory-level parallelism)
 *   PACK_LANES     W > 0 (CPU devices only, with USE_LOCAL=0): pack_step (pack.cl) exists
 *
 * Positions are float4: xyz and the inverse mass in w (0 = pinned).
 * Strategies:
 *   wg_step                         one work-group per cloth, the whole step in one launch
 *   cl_predict / cl_links / cl_finish   coloured batches merged over every cloth of a group
 *   cl_predict / jacobi_iter / cl_finish   Jacobi vertex solver, double-buffered
 *   (vertex phases of those two run over vertex chunks; cl_normals is its own launch)
 *   pack_step                       CPU: one work-item per pack of W cloths of one fabric (pack.cl)
 */
#include "layout.h"

#ifndef FEATURE_XPBD
#define FEATURE_XPBD 0
#endif
#ifndef FEATURE_TETHERS
#define FEATURE_TETHERS 0
#endif
#ifndef FEATURE_COLLIDERS
#define FEATURE_COLLIDERS 0
#endif
#ifndef FEATURE_WIND
#define FEATURE_WIND 0
#endif
#ifndef FEATURE_NORMALS
#define FEATURE_NORMALS 0
#endif
#ifndef FEATURE_SELF_COLLISION
#define FEATURE_SELF_COLLISION 0
#endif
#ifndef USE_LOCAL
#define USE_LOCAL 0
#endif
#ifndef JACOBI_OMEGA
#define JACOBI_OMEGA 1.5f
#endif
#ifndef LINK_UNROLL
#define LINK_UNROLL 4
#endif
#ifndef PACK_LANES
#define PACK_LANES 0
#endif

#define EPS_LEN2 1e-20f
#define EPS_DENOM 1e-30f

/* XS: the address space of the positions the per-vertex pieces read (wg_step's local copy, or
 * global memory, the only kind the other solvers have) */
#if USE_LOCAL
#define XS __local
#else
#define XS __global
#endif

/* Per-link and per-vertex pieces every solver shares */
#include "links.cl"     /* link equations: PBD, XPBD */
#include "normals.cl"   /* vertex normals and areas */
#include "wind.cl"      /* aerodynamic drag and lift */
#if FEATURE_TETHERS
#include "tethers.cl"   /* long-range attachments to the pins */
#endif
#if FEATURE_COLLIDERS
#include "colliders.cl" /* spheres, capsules, planes, friction */
#endif
#include "integrate.cl" /* predict and finish a vertex's substep */
#if FEATURE_SELF_COLLISION
#include "selfcollide.cl" /* vertices of one cloth kept apart: a spatial hash per work-group */
#endif

/* The solvers (kernels) */
#include "wg_step.cl"   /* work-group solver: one work-group per cloth, one launch */
#if !USE_LOCAL
#include "chunks.cl"    /* coloured and Jacobi: vertex phases over chunks */
#include "coloured.cl"  /* coloured: one launch per colour batch */
#include "jacobi.cl"    /* Jacobi: double-buffered vertex iterations */
#include "transfer.cl"  /* pin targets in, frame rows out */
#endif
#if PACK_LANES && !USE_LOCAL
#include "pack.cl"      /* CPU: packs of cloths of one fabric, one vector lane each */
#endif
