/* Inter-cloth collision of scenes (protocol 1.7): cloths of one scene kept apart from each other,
 * cloths of different scenes never interact. The same sums as drape.server.sim.scenes.inter_collide
 * (read it first), once per step after every cloth's own solve. Its own program, built and
 * launched only while a World has a scene of two cloths or more (drape.server.sim.opencl.scenes):
 * a World without scenes pays nothing, and cloth.cl is built as before.
 *
 * The scene cloths' vertices are numbered t = 0..nv-1 in one list, scene by scene, each scene's
 * cloths in the order they joined it: vidx[t] is vertex t's row of the World's position and
 * velocity buffers, vcl[t] its cloth k (0..ncl-1). Per cloth k, cinfo[k] = (vbase, n, scene,
 * first cloth of its scene, cloths of its scene, the scene's first t, the scene's end t, the
 * cloth's first t) and cpar[k] = (thickness x INTER_COLLISION_MARGIN, stiffness): the thickness
 * the solve keeps. A walk tells another scene's vertex (a shared bucket) and its own cloth's by
 * t's ranges, and reads a vertex's cloth and parameters only once it is within the reach of the
 * World's largest contact distance: a hash entry it passes costs its next and, if of another
 * cloth of its scene, its position.
 *
 * Each round (the contacts are found once, at the round's positions, and iterated):
 *   ic_bounds    one work-group per cloth: its box grown by half its thickness x IC_REACH
 *   ic_active    per cloth: whether its box meets another box of its scene (else it takes no part)
 *   ic_insert    every vertex's start position into xs0 (w: inverse mass), and every vertex of an
 *                active cloth into the bucket of (its cell, its scene): cells of edge 2 IC_REACH
 *                dmax (dmax the largest contact distance of the World), one linked list per
 *                bucket built with one atomic exchange per vertex (the heads are all -1 here:
 *                ic_finish of the step before, or the tables' rebuild, cleared them)
 *   ic_find      every free vertex of an active cloth walks the 2 x 2 x 2 cells around it (each
 *                bucket once) and lists the vertices of the other cloths of its scene closer than
 *                IC_REACH x their contact distance: its candidates, IC_LIST at most in nbr (more:
 *                its count says so, and the passes walk the hash for it instead); on the way it
 *                sums the first pass's contacts at the start positions (the candidates' positions
 *                it reads anyway) and writes that pass's result into xb: no launch of its own
 *   INTER_COLLISION_PASSES - 1 ic_pass, from xb into xa and back (Jacobi): every free vertex sums,
 *                over its candidates u closer than d = (th_k + th_u) / 2, k (d - |x - x_u|) w /
 *                (w + w_u) along (x - x_u) / |x - x_u| (+y for the cloth that joined first where
 *                they coincide), and writes its moved position
 *   (a contact within IC_SHOCK of +y moves its lower end less, not at all straight below, where
 *                the upper end is free: shock propagation, so a pile's weight reaches what its
 *                bottom rests on instead of sinking through it)
 *   ic_find and every ic_pass put a vertex they moved back out of its cloth's colliders (spheres,
 *                capsules, planes at their end pose, without friction: colliders.cl's
 *                collide_vertex, as the solvers' refinish_vertex calls it; cslot[k] is cloth k's
 *                row of the World's int table, -1 without the colliders feature), so that a pile's
 *                corrections never push its bottom cloth through what it rests on
 *   ic_finish    every vertex's last position into the World's positions, the displacement / dt
 *                added to its velocity, but no faster along it than before (inelastic); the
 *                bucket heads cleared for the next step
 * That round (ic_bounds to ic_finish: the candidates found at the round's start positions, then
 * INTER_COLLISION_PASSES / INTER_COLLISION_ROUNDS passes, 2) runs INTER_COLLISION_ROUNDS (4) times
 * a step, so that a pair the passes bring together from beyond the reach is seen in the next round.
 * Only the first round walks the hash for every vertex (ic_find, which keeps where each vertex
 * was, xs1). A later round's ic_insert marks the vertices that moved further than sk =
 * INTER_COLLISION_SKIN dmax since their list was found (mv; also those without a full list) and
 * lists them (moved, nmoved: one atomic per work-group of IC_CG, each group's vertices in order, so
 * that a GPU's warps walk neighbours, together); ic_rewalk walks the hash for those alone and adds
 * each to the extra list of the unmoved vertices it finds; ic_refind gives every unmoved vertex
 * the unmoved entries of its list and its extra list (see ic_refind for why that misses no pair in contact):
 * 27 launches a step (ic_rewalk in the 3 later rounds) whatever the number of scenes and cloths, their arguments set once
 * (ic_clear: every bucket head -1, once when the tables are rebuilt).
 */

#include "layout.h"
#ifndef EPS_LEN2
#define EPS_LEN2 1e-20f
#endif
#include "colliders.cl"

#ifndef INTER_COLLISION_PASSES
#define INTER_COLLISION_PASSES 8
#endif
#ifndef IC_LS
#define IC_LS 64 /* work-items of ic_bounds' groups: a power of 2 */
#endif
#ifndef IC_REACH
#define IC_REACH 1.5f /* candidates: pairs closer than IC_REACH x their contact distance at the step's start */
#endif
#ifndef IC_SHOCK
#define IC_SHOCK 0.7f /* a contact within this cosine of +y: its lower end does not yield */
#endif
#ifndef IC_CG
/* work-items of ic_insert's groups, whose lists are appended with one atomic: a power of 2 (1: an atomic a vertex) */
#define IC_CG 1
#endif
#ifndef IC_KEPT
#define IC_KEPT 0 /* ic_insert lists the vertices that did not move too, ic_refind runs over that list */
#endif
#if IC_KEPT && IC_CG == 1
#error "IC_KEPT needs ic_insert's groups (IC_CG > 1)"
#endif
#ifndef IC_LIST
#define IC_LIST 16 /* candidates listed per vertex (more: found again in the hash each pass) */
#endif

__kernel void ic_bounds(__global const float4 *pos, __global const int8 *cinfo, __global const float2 *cpar,
                        __global float4 *box)
{
    const int k = get_group_id(0), lid = get_local_id(0);
    const int8 ci = cinfo[k];
    __local float4 lo[IC_LS], hi[IC_LS];
    float4 a = (float4)(INFINITY), b = (float4)(-INFINITY);
    for (int v = lid; v < ci.s1; v += IC_LS) {
        const float4 x = pos[ci.s0 + v];
        a = fmin(a, x);
        b = fmax(b, x);
    }
    lo[lid] = a;
    hi[lid] = b;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = IC_LS / 2; s > 0; s >>= 1) {
        if (lid < s) {
            lo[lid] = fmin(lo[lid], lo[lid + s]);
            hi[lid] = fmax(hi[lid], hi[lid + s]);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == 0) {
        const float g = 0.5f * cpar[k].x * IC_REACH;
        box[2 * k] = (float4)(lo[0].xyz - g, 0.0f);
        box[2 * k + 1] = (float4)(hi[0].xyz + g, 0.0f);
    }
}

__kernel void ic_active(__global const int8 *cinfo, __global const float4 *box, __global int *active, int ncl)
{
    const int k = get_global_id(0);
    if (k >= ncl)
        return;
    const int8 ci = cinfo[k];
    const float3 alo = box[2 * k].xyz, ahi = box[2 * k + 1].xyz;
    int hit = 0;
    for (int j = ci.s3; j < ci.s3 + ci.s4 && !hit; ++j) {
        if (j == k)
            continue;
        const float3 blo = box[2 * j].xyz, bhi = box[2 * j + 1].xyz;
        hit = all(alo <= bhi) && all(blo <= ahi);
    }
    active[k] = hit;
}

__kernel void ic_clear(__global int *heads, int nb)
{
    const int b = get_global_id(0);
    if (b < nb)
        heads[b] = -1;
}

inline int ic_bucket(int3 c, int scene, uint mask)
{
    uint3 u = as_uint3(c);
    return (int)((u.x * 73856093u ^ u.y * 19349663u ^ u.z * 83492791u ^ (uint)scene * 2654435761u) & mask);
}

/* Every vertex's start position into xs0 and, of an active cloth, into its bucket; a later round
 * (later != 0) also marks (mv) and lists the vertices that must walk the hash again: those that
 * moved further than sk since their list was found, or have no full list, in moved[0..nmoved[0])
 * (ic_rewalk's work-items, one each), and with IC_KEPT (a GPU's) the others in moved[nv - 1 - i]
 * for i in 0..nmoved[1] (ic_refind's: without, it runs over every vertex, those that moved idle,
 * which PoCL's vectorised work-items do faster than through the list). Each list is appended by
 * one atomic per work-group of IC_CG, after a scan of the group's flags in local memory: a list
 * holds each group's vertices in their order, so that consecutive work-items of ic_rewalk and
 * ic_refind are neighbours of one cloth (the scene numbers a cloth's vertices in Morton order on a
 * GPU: IC_MORTON in drape.server.sim.opencl.scenes), that walk the same buckets (a warp's lanes
 * read the same entries) and write side by side, and the lists' two counters take one atomic per
 * group, not one per vertex (on a GPU, tens of thousands of work-items incrementing one counter
 * wait on each other). Launched over nv rounded up to IC_CG.
 * With IC_CG 1 (a CPU's) one atomic a vertex appends the first list, in the order they come. */
__kernel void ic_insert(__global const float4 *pos, __global const int *vidx, __global const int *vcl,
                        __global const int8 *cinfo, __global const int *active, __global int *heads,
                        __global int *next, __global float4 *xs0, int nv, float inv, uint mask,
                        __global const int *count, __global const float4 *xs1, __global int *mv, __global int *moved,
                        __global int *nmoved, float sk, int later)
{
#if IC_CG > 1
    __local int scan[IC_CG]; /* later rounds: the group's flags, scanned */
    __local int base[2];     /* where the group's vertices go in the two lists */
#endif
    const int t = get_global_id(0);
    int m = 0; /* must walk the hash again (later rounds) */
    if (t < nv) {
        const int k = vcl[t];
        const float4 x = pos[vidx[t]];
        xs0[t] = x;
        if (!active[k]) {
            if (later)
                mv[t] = 2; /* takes no part: in no list */
        } else {
            const int b = ic_bucket(convert_int3_sat_rtn(x.xyz * inv), cinfo[k].s2, mask);
            next[t] = atomic_xchg(&heads[b], t);
            if (later) { /* moved further than sk since its list was found, or without a full list */
                const int c = count[t];
                const float3 d = x.xyz - xs1[t].xyz;
                m = c < 0 || c > IC_LIST || !(dot(d, d) <= sk * sk);
                mv[t] = m;
            }
        }
    }
    if (!later)
        return; /* the same for every work-item of the launch */
#if IC_CG == 1 /* a CPU's: one atomic a vertex costs less than the scan's barriers */
    if (m)
        moved[atomic_inc(&nmoved[0])] = t;
#else
    const int lid = get_local_id(0);
    scan[lid] = m;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int s = 1; s < IC_CG; s <<= 1) { /* inclusive scan of the group's flags */
        const int v = lid >= s ? scan[lid - s] : 0;
        barrier(CLK_LOCAL_MEM_FENCE);
        scan[lid] += v;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (lid == IC_CG - 1) {
        base[0] = atomic_add(&nmoved[0], scan[lid]);
#if IC_KEPT
        const int t0 = t - lid, n = min(IC_CG, nv - t0); /* the group's vertices */
        base[1] = atomic_add(&nmoved[1], n - scan[lid]);
#endif
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    if (m)
        moved[base[0] + scan[lid] - 1] = t;
#if IC_KEPT
    else if (t < nv)
        moved[nv - 1 - (base[1] + lid - scan[lid])] = t;
#endif
#endif
}

/* x moved by corr, back out of cloth k's colliders at their end pose (cslot[k] < 0: none) */
inline float3 ic_keep_out(float3 x, float3 corr, int k, __global const int *cslot, __global const int *ci,
                          __global const float4 *coll)
{
    x += corr;
    const int s = cslot[k];
    if (s >= 0 && (corr.x != 0.0f || corr.y != 0.0f || corr.z != 0.0f)) {
        __global const int *I = ci + (long)s * CI_STRIDE;
        x = collide_vertex(x, x, coll, I[CI_COLL], I[CI_NCOLL], 1.0f, 1.0f, 0.0f);
    }
    return x;
}

/* The contact of vertex t (at x, cloth k, parameters pk) with vertex u at xu (cloth ku, pu); the
 * lower end of a contact within IC_SHOCK (a cosine) of +y has its inverse mass scaled down,
 * linearly to 0 straight below (shock propagation: drape.server.sim.scenes.shock). */
inline float3 ic_push(float4 x, int k, float2 pk, float4 xu, int ku, float2 pu)
{
    const float d = 0.5f * (pk.x + pu.x), st = 0.5f * (pk.y + pu.y);
    const float3 df = x.xyz - xu.xyz;
    const float dist2 = dot(df, df);
    if (!(dist2 < d * d) || !(st > 0.0f))
        return (float3)(0.0f);
    const float dist = sqrt(dist2);
    const float3 n = dist > 1e-12f ? df / dist : (float3)(0.0f, k < ku ? 1.0f : -1.0f, 0.0f);
    const float m = clamp((1.0f - fabs(n.y)) / (1.0f - IC_SHOCK), 0.0f, 1.0f);
    float w = x.w, wu = xu.w;
    if (n.y < 0.0f && wu > 0.0f)
        w *= m;
    else if (n.y > 0.0f && w > 0.0f)
        wu *= m;
    if (!(w > 0.0f))
        return (float3)(0.0f);
    return n * (st * (d - dist) * w / (w + wu));
}

/* Walks the hash (heads, next: entries at xs0) in the 2 x 2 x 2 cells around vertex t's start
 * position x0: with list != 0 lists its candidates after the count it is given (count returned,
 * IC_LIST at most stored, every nv-th int: candidate i of every vertex side by side, so that a
 * pass's work-items read them coalesced) and sums their contacts at the start positions (the first
 * pass's: the same candidates in the same order as a pass over the list), else sums its contacts
 * at x. */
inline int ic_walk(int t, int k, int8 ci, float2 pk, float4 x0, __global const float4 *xs0,
                   __global const int *vcl, __global const int8 *cinfo, __global const float2 *cpar,
                   __global const int *heads, __global const int *next, float inv, uint mask, float dmax,
                   __global int *list, int count, int nv, __global const float4 *x, float3 *corr,
                   __global const int *mv, __global int *xnbr, __global int *xcount)
{
    const int3 c0 = convert_int3_sat_rtn(x0.xyz * inv - 0.5f);
    const float rmax = 0.5f * IC_REACH * (pk.x + dmax) * 1.0001f; /* >= its every pair's reach */
    int seen[8];
    int nseen = 0;
    for (int dz = 0; dz < 2; ++dz)
        for (int dy = 0; dy < 2; ++dy)
            for (int dx = 0; dx < 2; ++dx) {
                const int b = ic_bucket(c0 + (int3)(dx, dy, dz), ci.s2, mask);
                int dup = 0;
                for (int i = 0; i < nseen; ++i)
                    dup |= seen[i] == b;
                if (dup)
                    continue;
                seen[nseen++] = b;
                for (int u = heads[b]; u >= 0; u = next[u]) {
                    if (u < ci.s5 || u >= ci.s6 || (u >= ci.s7 && u < ci.s7 + ci.s1))
                        continue; /* another scene's (a shared bucket), or its own cloth's */
                    const float4 xu = xs0[u];
                    const float3 df = x0.xyz - xu.xyz;
                    const float dd = dot(df, df);
                    if (!(dd < rmax * rmax))
                        continue;
                    const int ku = vcl[u];
                    const float2 pu = cpar[ku];
                    const float r = IC_REACH * 0.5f * (pk.x + pu.x);
                    if (!(dd < r * r))
                        continue;
                    if (list) {
                        if (count < IC_LIST)
                            list[(long)count * nv] = u;
                        ++count;
                        *corr += ic_push(x0, k, pk, xu, ku, pu); /* the first pass's, at the start */
                        if (xcount && mv[u] == 0) { /* a moved vertex: the unmoved one's list gets t */
                            const int s = atomic_inc(&xcount[u]);
                            if (s < IC_LIST)
                                xnbr[(long)s * nv + u] = t;
                        }
                    } else {
                        *corr += ic_push(x[t], k, pk, x[u], ku, pu);
                    }
                }
            }
    return count;
}

/* The step's first round: every free vertex of an active cloth walks the hash (count -1: of a
 * cloth that takes no part), its start position kept in xs1 (where its list was found). */
__kernel void ic_find(__global const float4 *xs0, __global const int *vcl, __global const int8 *cinfo,
                      __global const float2 *cpar, __global const int *active, __global const int *heads,
                      __global const int *next, __global int *nbr, __global int *count, __global float4 *xout,
                      __global const int *cslot, __global const int *ci, __global const float4 *coll, int nv,
                      float inv, uint mask, float dmax, __global float4 *xs1)
{
    const int t = get_global_id(0);
    if (t >= nv)
        return;
    const int k = vcl[t];
    const float4 x0 = xs0[t];
    int c = 0;
    float3 corr = (float3)(0.0f);
    const int act = active[k];
    if (act && x0.w > 0.0f)
        c = ic_walk(t, k, cinfo[k], cpar[k], x0, xs0, vcl, cinfo, cpar, heads, next, inv, mask, dmax, nbr + t, 0, nv,
                    xs0, &corr, 0, 0, 0);
    count[t] = act ? c : -1;
    xs1[t] = x0;
    xout[t] = (float4)(ic_keep_out(x0.xyz, corr, k, cslot, ci, coll), x0.w);
}

/* A later round's candidates. A vertex that moved (mv 1: further than sk since its list was found,
 * or without a full list) walks the hash (part 1, ic_rewalk: work-item i the i-th that moved, as
 * ic_insert listed them), lists what it finds and adds itself to the extra list (xnbr, xcount) of
 * each unmoved one it finds; one that did not move (part 0, after: with IC_KEPT work-item i the
 * i-th of the others, moved[nv - 1 - i], else work-item t vertex t) keeps the
 * entries of its list that did not move either and adds its extra list (or walks the hash, where
 * that overflowed). A pair is so listed by both ends or by neither, and one listed by neither was
 * further than the reach when either end last walked, the end that walked moving less than sk
 * since and the other less than 2 sk: with sk 0.1 contact distances (the reach's margin, 0.3, over
 * 3) it is not in contact at the round's start. */
__kernel void ic_refind(__global const float4 *xs0, __global const int *vcl, __global const int8 *cinfo,
                        __global const float2 *cpar, __global const int *active, __global const int *heads,
                        __global const int *next, __global int *nbr, __global int *count, __global float4 *xout,
                        __global const int *cslot, __global const int *ci, __global const float4 *coll, int nv,
                        float inv, uint mask, float dmax, __global float4 *xs1, __global const int *mv,
                        __global int *xnbr, __global int *xcount, __global const int *moved,
                        __global const int *nmoved, int part)
{
    const int i = get_global_id(0);
#if IC_KEPT
    if (i >= nmoved[part == 1 ? 0 : 1])
        return;
    const int t = part == 1 ? moved[i] : moved[nv - 1 - i];
#else
    if (i >= (part == 1 ? nmoved[0] : nv))
        return;
    const int t = part == 1 ? moved[i] : i;
    if (part == 0 && mv[t] == 1)
        return;
#endif
    const int k = vcl[t];
    const float4 x0 = xs0[t];
    int c = 0;
    float3 corr = (float3)(0.0f);
    const int act = active[k];
    if (act && x0.w > 0.0f) {
        const int8 cik = cinfo[k];
        const float2 pk = cpar[k];
        const int xc = part == 1 ? 0 : xcount[t];
        if (part == 1 || xc > IC_LIST) {
            const int p1 = part == 1; /* an unmoved one walks where its extra list overflowed */
            c = ic_walk(t, k, cik, pk, x0, xs0, vcl, cinfo, cpar, heads, next, inv, mask, dmax, nbr + t, 0, nv, xs0,
                        &corr, mv, p1 ? xnbr : 0, p1 ? xcount : 0);
            if (p1)
                xs1[t] = x0;
        } else {
            const int c1 = count[t]; /* 0..IC_LIST: else it moved */
            const float far = 0.5f * (pk.x + dmax) * 1.0001f;
            for (int j = 0; j < c1 + xc; ++j) {
                int u;
                if (j < c1) {
                    u = nbr[(long)j * nv + t];
                    if (mv[u])
                        continue; /* moved (in the extra list, if within the reach) or out */
                } else {
                    u = xnbr[(long)(j - c1) * nv + t];
                }
                if (c < IC_LIST)
                    nbr[(long)c * nv + t] = u;
                ++c;
                const float4 xu = xs0[u];
                const float3 df = x0.xyz - xu.xyz;
                if (dot(df, df) < far * far) {
                    const int ku = vcl[u];
                    corr += ic_push(x0, k, pk, xu, ku, cpar[ku]);
                }
            }
        }
    }
    if (part == 0)
        xcount[t] = 0;
    count[t] = act ? c : -1;
    xout[t] = (float4)(ic_keep_out(x0.xyz, corr, k, cslot, ci, coll), x0.w);
}

__kernel void ic_pass(__global const float4 *xs0, __global const float4 *xin, __global float4 *xout,
                      __global const int *vcl, __global const int8 *cinfo, __global const float2 *cpar,
                      __global const int *heads, __global const int *next, __global const int *nbr,
                      __global const int *count, __global const int *cslot, __global const int *ci,
                      __global const float4 *coll, int nv, float inv, uint mask, float dmax)
{
    const int t = get_global_id(0);
    if (t >= nv)
        return;
    const float4 x = xin[t];
    const int c = count[t];
    const int k = vcl[t];
    float3 corr = (float3)(0.0f);
    if (c > 0) {
        const float2 pk = cpar[k];
        if (c <= IC_LIST) {
            /* a candidate further than the contact distance with the World's largest thickness
             * (dmax) is passed without reading its cloth */
            const float far = 0.5f * (pk.x + dmax) * 1.0001f;
            for (int i = 0; i < c; ++i) {
                const int u = nbr[(long)i * nv + t];
                const float4 xu = xin[u];
                const float3 df = x.xyz - xu.xyz;
                if (dot(df, df) < far * far) {
                    const int ku = vcl[u];
                    corr += ic_push(x, k, pk, xu, ku, cpar[ku]);
                }
            }
        } else {
            ic_walk(t, k, cinfo[k], pk, xs0[t], xs0, vcl, cinfo, cpar, heads, next, inv, mask, dmax, 0, 0, nv, xin,
                    &corr, 0, 0, 0);
        }
    }
    xout[t] = (float4)(ic_keep_out(x.xyz, corr, k, cslot, ci, coll), x.w);
}

__kernel void ic_finish(__global float4 *pos, __global float4 *vel, __global const int *vidx,
                        __global const float4 *xs0, __global const float4 *x, __global int *heads, __global int *nmoved,
                        int nv, int nb, float inv_dt)
{
    const int t = get_global_id(0);
    for (int b = t; b < nb; b += nv)
        heads[b] = -1;
    if (t == 0)
        nmoved[0] = nmoved[1] = 0;
    if (t >= nv)
        return;
    const float3 d = x[t].xyz - xs0[t].xyz;
    if (d.x != 0.0f || d.y != 0.0f || d.z != 0.0f) {
        const int g = vidx[t];
        pos[g].xyz = x[t].xyz;
        /* inelastic: no faster along d than before (or 0): scenes.inelastic */
        const float3 v = vel[g].xyz, n = d / length(d), out = v + d * inv_dt;
        const float over = dot(out, n) - fmax(dot(v, n), 0.0f);
        vel[g].xyz = over > 0.0f ? out - n * over : out;
    }
}
