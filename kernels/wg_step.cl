/* The work-group solver (wg_step): one work-group per cloth, every substep, iteration and colour
 * batch in one launch, the cloth's positions in local memory (USE_LOCAL=1, when it fits) or
 * global memory. Links of one colour share no vertex, so the group's work-items solve them in
 * parallel between barriers, which sit only where control flow is uniform across the group. The
 * GPU's default solver, and the CPU's with one work-item per cloth
 * where the pack solver (pack.cl) is off. With tethers: the tethers after each substep's
 * prediction and again after the links, and the long-range links before the links of each
 * iteration (tethers.cl). With self-collision: its passes after each substep's links
 * (selfcollide.cl). XPBD at
 * compliance 0 or with one iteration keeps no multipliers (every one is 0 when read). Included by
 * cloth.cl. */

#if FEATURE_XPBD
#define SOLVE(X, R, p0, p1, l)                                                                     \
    if (lamless)                                                                                   \
        solve_link_lamless(X, R, p0, p1, F, h);                                                    \
    else                                                                                           \
        solve_link(X, R, p0, p1, F, h, lam, l)
#else
#define SOLVE(X, R, p0, p1, l) solve_link(X, R, p0, p1, F, h, lam, l)
#endif

__kernel void wg_step(const float dt, __global const int *cloths, __global const int *ci, __global const float *cf,
                      __global const int *fab, __global float4 *pos, __global float4 *vel, __global float4 *prev,
                      __global const float4 *target, __global float4 *nrm, __global const float4 *coll,
                      __global float *lam_all
#if USE_LOCAL
                      , __local float4 *lx
#endif
)
{
    const int c = cloths[get_group_id(0)];
    __global const int *I = ci + c * CI_STRIDE;
    __global const float *F = cf + c * CF_STRIDE;
    __global const int *fb = fab + I[CI_FAB];
    __global const int *links = fb + I[CI_OFF_LINKS];
    __global const int *cols = fb + I[CI_OFF_COLOURS];
    const int vbase = I[CI_VBASE], nv = I[CI_NVERTS], ncol = I[CI_NCOLOURS];
    const int iters = I[CI_ITERS], S = I[CI_SUBSTEPS];
    const int lid = get_local_id(0), ls = get_local_size(0);
    const float h = dt / (float)S;
    __global float *lam = lam_all + I[CI_LAM]; /* XPBD's multipliers (PBD reads none) */
#if FEATURE_XPBD
    const int nl = I[CI_NLINKS];
    /* compliance 0 or one iteration: every multiplier is 0 when read, so none is kept (half the
     * link's memory traffic; the same arithmetic) */
    const int lamless = iters == 1 || (F[CF_COMPLIANCE] == 0.0f && F[CF_COMPLIANCE + 1] == 0.0f &&
                                       F[CF_COMPLIANCE + 2] == 0.0f);
#endif
#if FEATURE_TETHERS
    __global const int *lrl = fb + I[CI_OFF_LRLINKS];
    __global const int *lrc = fb + I[CI_OFF_LRCOLOURS];
    const float tlimit = F[CF_TETHER_LIMIT];
#endif
#if FEATURE_SELF_COLLISION
    __global const int *rest = fb + I[CI_OFF_REST];
#endif
#if USE_LOCAL
    XS float4 *X = lx;
    for (int v = lid; v < nv; v += ls)
        X[v] = pos[vbase + v];
    barrier(CLK_LOCAL_MEM_FENCE);
#else
    XS float4 *X = pos + vbase;
#endif

    for (int s = 0; s < S; ++s) {
#if FEATURE_WIND
        for (int v = lid; v < nv; v += ls)
            nrm[vbase + v] = vertex_normal(X, fb, I, v);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#endif
        for (int v = lid; v < nv; v += ls)
            X[v] = predict_vertex(X[v], vel, prev, target, nrm, vbase + v, F, h, S - s);
#if FEATURE_XPBD
        if (!lamless)
            for (int l = lid; l < nl; l += ls)
                lam[l] = 0.0f;
#endif
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#if FEATURE_TETHERS /* before the links (NvCloth's order); anchors are pinned: no tether moves them */
        for (int v = lid; v < nv; v += ls)
            if (X[v].w > 0.0f)
                X[v] = tether_vertex(X[v], X, fb, I, F, v);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#endif

        for (int it = 0; it < iters; ++it) {
#if FEATURE_TETHERS /* the long-range links first, coarsest first */
            for (int col = 0; col < lrc[0]; ++col) {
                for (int l = lrc[1 + col] + lid; l < lrc[2 + col]; l += ls) {
                    const int4 R = vload4(l, lrl);
                    solve_long_range(X, R, X[R.x], X[R.y], tlimit);
                }
                barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
            }
#endif
            for (int col = 0; col < ncol; ++col) {
                const int end = cols[col + 1];
                int l = cols[col] + lid;
                /* Links of one colour share no vertex, so a work-item may load several before
                 * storing any: LINK_UNROLL independent loads in flight hide memory latency. */
                for (; l + (LINK_UNROLL - 1) * ls < end; l += LINK_UNROLL * ls) {
                    int4 R[LINK_UNROLL];
                    float4 P0[LINK_UNROLL], P1[LINK_UNROLL];
                    for (int u = 0; u < LINK_UNROLL; ++u)
                        R[u] = vload4(l + u * ls, links);
                    for (int u = 0; u < LINK_UNROLL; ++u) {
                        P0[u] = X[R[u].x];
                        P1[u] = X[R[u].y];
                    }
                    for (int u = 0; u < LINK_UNROLL; ++u)
                        SOLVE(X, R[u], P0[u], P1[u], l + u * ls);
                }
                for (; l < end; l += ls) {
                    int4 R = vload4(l, links);
                    float4 p0 = X[R.x], p1 = X[R.y];
                    SOLVE(X, R, p0, p1, l);
                }
                barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
            }
        }
        for (int v = lid; v < nv; v += ls)
            X[v] = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S, 1);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#if FEATURE_SELF_COLLISION /* after the colliders' friction, which would take back its separation */
        self_collide(X, vel + vbase, (__global int *)(nrm + vbase), rest, nv, F[CF_THICKNESS],
                     F[CF_CONTACT_STIFFNESS], lid, ls);
        for (int v = lid; v < nv; v += ls)
            X[v] = refinish_vertex(X[v], I, F, vel, prev, coll, vbase + v, h, s, S);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#endif
    }

#if FEATURE_NORMALS
    for (int v = lid; v < nv; v += ls)
        nrm[vbase + v] = vertex_normal(X, fb, I, v);
#endif
#if USE_LOCAL
    for (int v = lid; v < nv; v += ls)
        pos[vbase + v] = X[v];
#endif
}
