/* The Jacobi solver's link iterations: jacobi_iter, one launch per iteration, double-buffered
 * (every vertex gathers its links' corrections from one buffer and writes the other; XPBD keeps
 * two halves of multipliers likewise), optionally Chebyshev-accelerated, and copy_positions to
 * bring an odd number of iterations back into the positions. Built with USE_LOCAL=0 only.
 * Included by cloth.cl after chunks.cl (CHUNK_PROLOGUE, CHUNK_RANGE). */

/* Chebyshev semi-iterative weight of Jacobi iteration `it` (Wang 2015); 1 when off. */
inline float chebyshev_omega(float rho, int it)
{
    if (!(rho > 0.0f) || it == 0)
        return 1.0f;
    float w = 2.0f / (2.0f - rho * rho);
    for (int k = 1; k < it; ++k)
        w = 4.0f / (4.0f - rho * rho * w);
    return w;
}

/* Jacobi vertex solver: each vertex gathers its links from src and writes dst; vertices are
 * visited in the fabric's degree order so neighbouring work-items loop the same number of times. */
__kernel void jacobi_iter(const float dt, const int it, const int chunk, __global const int2 *chunks,
                          __global const int *ci, __global const float *cf, __global const int *fab,
                          __global const float4 *src, __global float4 *dst, __global float *lam_all)
{
    CHUNK_PROLOGUE
    __global const int *order = fb + I[CI_OFF_JORDER];
    __global const int *off = fb + I[CI_OFF_JOFF];
    __global const int *adj = fb + I[CI_OFF_JADJ];
    __global const int *links = fb + I[CI_OFF_LINKS];
    __global const float4 *Xs = src + vbase;
    __global float4 *Xd = dst + vbase;
    const bool active = it < I[CI_ITERS];
    const float omega = chebyshev_omega(F[CF_CHEB_RHO], it);
#if FEATURE_XPBD
    const int nl = I[CI_NLINKS];
    __global const float *lam_src = lam_all + I[CI_LAM] + (it & 1) * nl;
    __global float *lam_dst = lam_all + I[CI_LAM] + ((it + 1) & 1) * nl;
    const float h = dt / (float)S;
#endif
    for (int k = ck.y + lid; k < v_end; k += ls) {
        const int v = order[k];
        float4 p = Xs[v];
        if (!active) {
            Xd[v] = p;
#if FEATURE_XPBD
            for (int e = off[k]; e < off[k + 1]; ++e) {
                int l = adj[2 * e + 1];
                if (links[LINK_WORDS * l] == v)
                    lam_dst[l] = lam_src[l];
            }
#endif
            continue;
        }
        float3 acc = (float3)(0.0f);
        const int e0 = off[k], e1 = off[k + 1];
        for (int e = e0; e < e1; ++e) {
            int other = adj[2 * e], l = adj[2 * e + 1];
            __global const int *L = links + LINK_WORDS * l;
            bool first = L[0] == v;
            float4 q = Xs[other];
            float rl = as_float(L[3]);
            float3 d0, d1;
#if FEATURE_XPBD
            float dl = first ? link_xpbd(p, q, rl, link_alpha(F, L[2], h), lam_src[l], &d0, &d1)
                             : link_xpbd(q, p, rl, link_alpha(F, L[2], h), lam_src[l], &d1, &d0);
            if (first)
                lam_dst[l] = lam_src[l] + dl;
#else
            if (first)
                link_pbd(p, q, rl, F[CF_STIFFNESS + L[2]], &d0, &d1);
            else
                link_pbd(q, p, rl, F[CF_STIFFNESS + L[2]], &d1, &d0);
#endif
            acc += d0;
        }
        if (e1 > e0)
            p.xyz += acc * (JACOBI_OMEGA / (float)(e1 - e0));
        if (omega != 1.0f && p.w > 0.0f) {
            float4 before = Xd[v]; /* dst still holds this vertex's iterate before the last */
            p.xyz = omega * (p.xyz - before.xyz) + before.xyz;
        }
        Xd[v] = p;
    }
}

/* copy positions of every chunk (closes an odd number of Jacobi iterations) */
__kernel void copy_positions(const int chunk, __global const int2 *chunks, __global const int *ci,
                             __global const float4 *src, __global float4 *dst)
{
    CHUNK_RANGE
    for (int v = ck.y + lid; v < v_end; v += ls)
        dst[vbase + v] = src[vbase + v];
}
