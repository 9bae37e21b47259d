/* The work-group solver (wg_step): one work-group per cloth, every substep, iteration and colour
 * batch in one launch, the cloth's positions in local memory (USE_LOCAL=1, when it fits) or
 * global memory. Links of one colour share no vertex, so the group's work-items solve them in
 * parallel between barriers, which sit only where control flow is uniform across the group. The
 * GPU's default solver, and the CPU's with one work-item per cloth
 * where the pack solver (pack.cl) is off. Included by cloth.cl. */

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
        for (int l = lid; l < nl; l += ls)
            lam[l] = 0.0f;
#endif
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);

        for (int it = 0; it < iters; ++it) {
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
                        solve_link(X, R[u], P0[u], P1[u], F, h, lam, l + u * ls);
                }
                for (; l < end; l += ls) {
                    int4 R = vload4(l, links);
                    float4 p0 = X[R.x], p1 = X[R.y];
                    solve_link(X, R, p0, p1, F, h, lam, l);
                }
                barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
            }
        }

        for (int v = lid; v < nv; v += ls)
            X[v] = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
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
