/* The vertex phases of the coloured and Jacobi solvers, one launch each per substep: cl_normals
 * (wind: before each substep; the normals feature: after the step), cl_predict (gravity, wind,
 * pins; resets the XPBD multipliers) and cl_finish (tethers, after the links in these solvers;
 * colliders, velocities); the link
 * iterations between them are coloured.cl's or jacobi.cl's. Built with USE_LOCAL=0 only.
 * Included by cloth.cl.
 *
 * They run over *chunks*: (cloth, first vertex) pairs of at most `chunk` vertices, so a big cloth
 * spreads over many work-groups and small ones take one each. No phase reads a vertex another
 * chunk writes in the same launch: normals are their own launch, tethers read pinned anchors,
 * which these phases never move. */

/* A chunk kernel's first lines: its work-group's chunk ck = (cloth c, first vertex), the cloth's
 * int table I and first vertex vbase, the end of the chunk's vertices v_end, and the work-item's
 * place in the group. CHUNK_PROLOGUE adds the cloth's float table F, fabric fb and substeps S. */
#define CHUNK_RANGE                                                                              \
    const int2 ck = chunks[get_group_id(0)];                                                     \
    const int c = ck.x;                                                                          \
    __global const int *I = ci + c * CI_STRIDE;                                                  \
    const int vbase = I[CI_VBASE];                                                               \
    const int v_end = min(ck.y + chunk, I[CI_NVERTS]);                                           \
    const int lid = get_local_id(0), ls = get_local_size(0);

#define CHUNK_PROLOGUE                                                                           \
    CHUNK_RANGE                                                                                  \
    __global const float *F = cf + c * CF_STRIDE;                                                \
    __global const int *fb = fab + I[CI_FAB];                                                    \
    const int S = I[CI_SUBSTEPS];

__kernel void cl_normals(const int chunk, __global const int2 *chunks, __global const int *ci,
                         __global const float *cf, __global const int *fab, __global const float4 *pos,
                         __global float4 *nrm)
{
    CHUNK_PROLOGUE
    for (int v = ck.y + lid; v < v_end; v += ls)
        nrm[vbase + v] = vertex_normal(pos + vbase, fb, I, v);
}

__kernel void cl_predict(const float dt, const int s, const int chunk, __global const int2 *chunks,
                         __global const int *ci, __global const float *cf, __global const int *fab,
                         __global float4 *pos, __global float4 *vel, __global float4 *prev,
                         __global const float4 *target, __global const float4 *nrm, __global float *lam_all)
{
    CHUNK_PROLOGUE
    const float h = dt / (float)S;
    __global float4 *X = pos + vbase;
    for (int v = ck.y + lid; v < v_end; v += ls)
        X[v] = predict_vertex(X[v], vel, prev, target, nrm, vbase + v, F, h, S - s);
#if FEATURE_XPBD
    if (ck.y == 0) { /* the cloth's first chunk resets its multipliers */
        __global float *lam = lam_all + I[CI_LAM];
        for (int l = lid; l < I[CI_NLINKS]; l += ls)
            lam[l] = 0.0f; /* Jacobi reads the first half on its first iteration */
    }
#endif
}

__kernel void cl_finish(const float dt, const int s, const int chunk, __global const int2 *chunks,
                        __global const int *ci, __global const float *cf, __global const int *fab,
                        __global float4 *pos, __global float4 *vel, __global const float4 *prev,
                        __global const float4 *coll)
{
    CHUNK_PROLOGUE
    const float h = dt / (float)S;
    __global float4 *X = pos + vbase;
    for (int v = ck.y + lid; v < v_end; v += ls)
        X[v] = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S, 1);
}
