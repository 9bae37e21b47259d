/* Layout of the per-cloth tables shared by the OpenCL kernels and the host.
 * drape.server.device parses the "#define NAME value" lines of this file, so it is the single
 * source of truth: change a number here and both sides follow. */
#ifndef DRAPE_LAYOUT_H
#define DRAPE_LAYOUT_H

/* int table: CI_STRIDE ints per cloth */
#define CI_STRIDE 24
#define CI_VBASE 0        /* first vertex of the cloth in the merged vertex buffers */
#define CI_NVERTS 1
#define CI_FAB 2          /* base of the cloth's fabric blob in the int arena */
#define CI_NLINKS 3
#define CI_NCOLOURS 4
#define CI_ITERS 5
#define CI_SUBSTEPS 6
#define CI_COLL 7         /* first collider slot */
#define CI_NCOLL 8
#define CI_NTRIS 9
#define CI_LAM 10         /* base of the cloth's XPBD multipliers (2 per link) */
#define CI_OFF_LINKS 11   /* offsets inside the fabric blob */
#define CI_OFF_COLOURS 12
#define CI_OFF_ANCHOR 13
#define CI_OFF_JORDER 14
#define CI_OFF_JOFF 15
#define CI_OFF_JADJ 16
#define CI_OFF_VTRIOFF 17
#define CI_OFF_VTRI 18
#define CI_OFF_TRIS 19
#define CI_OFF_LRLINKS 20  /* long-range links: LINK_WORDS records (type unused), by colour */
#define CI_OFF_LRCOLOURS 21 /* their colours: the count C, then C + 1 offsets */
#define CI_OFF_REST 22     /* rest positions: 3 floats (bits) per vertex (self-collision) */

/* float table: CF_STRIDE floats per cloth */
#define CF_STRIDE 24
#define CF_GRAVITY 0      /* 3 floats */
#define CF_WIND 3         /* 3 floats */
#define CF_DAMP_SUB 6     /* damping per substep: 1 - (1 - kDP)^(1/substeps) */
#define CF_STIFFNESS 7    /* 3 floats: structural, shear, bending */
#define CF_COMPLIANCE 10  /* 3 floats */
#define CF_FRICTION 13
#define CF_DRAG 14
#define CF_LIFT 15
#define CF_RHO 16
#define CF_TETHER_LIMIT 17
#define CF_CHEB_RHO 18     /* Chebyshev spectral-radius estimate for Jacobi, 0 = off */
#define CF_THICKNESS 19    /* self-collision: distance kept between non-neighbours, 0 = off */
#define CF_CONTACT_STIFFNESS 20 /* self-collision: share of a contact's depth corrected per pass */

/* fabric blob records */
#define LINK_WORDS 4      /* i0, i1, type, rest length (float bits) */
#define TETHER_SLOTS 4    /* tethers per vertex: one per pin island, nearest first */
#define ANCHOR_WORDS 8    /* TETHER_SLOTS x (anchor vertex or -1, tether length (float bits)) */
#define COLLIDER_WORDS 4  /* float4s per collider: previous pose (2 rows), current pose (2 rows) */

/* Collider type ids (row 1's w of a slot): defined in colliders.cl, each beside its shape's code */

#endif
