/* Drape's cloth solvers: one step of many cloths, mirroring drape.server.reference.
 *
 * Build options (all -D):
 *   FEATURE_XPBD, FEATURE_TETHERS, FEATURE_COLLIDERS, FEATURE_WIND, FEATURE_NORMALS  (0/1)
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

#if USE_LOCAL
#define XS __local
#else
#define XS __global
#endif

/* ------------------------------------------------------------------------------------------ */
/* Link equations. Both return corrections for the two ends; the caller loads and stores. */

/* The talk's PBD link: k = kst (rl^2 - L) / ((im0 + im1)(rl^2 + L)), no square root. */
inline void link_pbd(float4 p0, float4 p1, float rl, float kst, float3 *d0, float3 *d1)
{
    float3 d = p1.xyz - p0.xyz;
    float L = dot(d, d);
    float rl2 = rl * rl;
    float denom = (p0.w + p1.w) * (rl2 + L);
    float k = denom > EPS_DENOM ? kst * (rl2 - L) / denom : 0.0f;
    *d0 = -d * (k * p0.w);
    *d1 = d * (k * p1.w);
}

/* XPBD distance constraint; returns the multiplier increment. */
inline float link_xpbd(float4 p0, float4 p1, float rl, float alpha, float lam, float3 *d0, float3 *d1)
{
    float3 d = p1.xyz - p0.xyz;
    float L = dot(d, d);
    float denom = p0.w + p1.w + alpha;
    /* compliance / h^2 past float range: infinitely soft, no correction (and no inf * 0) */
    if (!(L > EPS_LEN2) || !(denom > EPS_DENOM) || isinf(alpha)) {
        *d0 = (float3)(0.0f);
        *d1 = (float3)(0.0f);
        return 0.0f;
    }
    float len = sqrt(L);
    float3 n = d / len;
    float dl = (-(len - rl) - alpha * lam) / denom;
    *d0 = -n * (p0.w * dl);
    *d1 = n * (p1.w * dl);
    return dl;
}

inline float link_alpha(__global const float *F, int type, float h)
{
    return F[CF_COMPLIANCE + type] / (h * h);
}

/* ------------------------------------------------------------------------------------------ */
/* Per-vertex pieces */

inline float3 vertex_normal(XS const float4 *X, __global const int *fb, __global const int *I, int v, float *area)
{
    __global const int *vto = fb + I[CI_OFF_VTRIOFF];
    __global const int *vt = fb + I[CI_OFF_VTRI];
    __global const int *tris = fb + I[CI_OFF_TRIS];
    float3 n = (float3)(0.0f);
    float a = 0.0f;
    for (int k = vto[v]; k < vto[v + 1]; ++k) {
        int t = vt[k];
        float3 x0 = X[tris[3 * t]].xyz;
        float3 fn = cross(X[tris[3 * t + 1]].xyz - x0, X[tris[3 * t + 2]].xyz - x0);
        n += fn;
        a += 0.5f * length(fn) / 3.0f;
    }
    float len = length(n);
    *area = a;
    return len > 1e-30f ? n / len : (float3)(0.0f);
}

/* Velocity change from Bullet's aerodynamics over one substep: drag along the relative wind,
 * lift across it. The change is at most the relative wind speed, so drag never carries a
 * vertex past the wind's own velocity however strong the wind or long the step (explicit drag
 * would overshoot and blow up). */
inline float3 aero_dv(float3 vel, float3 n, float area, float invm, float h, __global const float *F)
{
    float3 wind = (float3)(F[CF_WIND], F[CF_WIND + 1], F[CF_WIND + 2]);
    float3 r = vel - wind;
    float rl = length(r);
    if (!(rl > 1e-12f))
        return (float3)(0.0f);
    float3 rh = r / rl;
    if (dot(n, r) < 0.0f)
        n = -n;
    float c = dot(n, rh);
    float rho = F[CF_RHO];
    float3 f = -0.5f * F[CF_DRAG] * rho * (rl * rl * area * c) * rh;
    float lift = F[CF_LIFT];
    if (lift > 0.0f && c > 0.0f && c < 0.9848f) {
        float s = sqrt(fmax(1.0f - c * c, 0.0f));
        f += 0.5f * lift * rho * (rl * area * s) * cross(cross(n, rh), rh);
    }
    float3 dv = f * (invm * h);
    float m = length(dv);
    return m > rl ? dv * (rl / m) : dv;
}

/* gravity (+ wind), integrate, move pins toward their targets */
inline float4 predict_vertex(float4 x, float3 aero, __global float4 *vel, __global float4 *prev,
                             __global const float4 *target, int gv, __global const float *F, float h, int remaining)
{
    prev[gv] = x;
    if (x.w > 0.0f) {
        float3 g = (float3)(F[CF_GRAVITY], F[CF_GRAVITY + 1], F[CF_GRAVITY + 2]);
        float4 v = vel[gv];
        float3 vv = v.xyz + g * h + aero;
        vel[gv] = (float4)(vv, 0.0f);
        x.xyz += vv * h;
    } else {
        x.xyz += (target[gv].xyz - x.xyz) / (float)remaining;
    }
    return x;
}

#if FEATURE_COLLIDERS
inline float3 friction(float3 x, float3 xp, float3 n, float pen, float3 cdisp, float mu)
{
    if (!(mu > 0.0f))
        return x;
    float3 rel = (x - xp) - cdisp;
    float3 tang = rel - n * dot(rel, n);
    float tl = length(tang);
    if (tl > 1e-12f)
        x -= tang * (fmin(mu * pen, tl) / tl);
    return x;
}

inline float3 collide_vertex(float3 x, float3 xp, __global const float4 *coll, int base, int ncoll,
                             float t0, float t1, float mu)
{
    for (int i = 0; i < ncoll; ++i) {
        __global const float4 *c = coll + (base + i) * COLLIDER_WORDS;
        float4 a0 = c[0], a1 = c[1], b0 = c[2], b1 = c[3];
        float4 q0 = a0 + (b0 - a0) * t0, q1 = a1 + (b1 - a1) * t0; /* pose at substep start */
        float4 p0 = a0 + (b0 - a0) * t1, p1 = a1 + (b1 - a1) * t1; /* pose at substep end */
        int kind = (int)round(b1.w);
        if (kind == COLLIDER_PLANE) {
            float nl = length(p0.xyz);
            float3 n = p0.xyz / fmax(nl, 1e-30f);
            float dist = dot(x, n) - p0.w;
            if (dist < 0.0f) {
                x -= n * dist;
                x = friction(x, xp, n, -dist, n * (p0.w - q0.w), mu);
            }
            continue;
        }
        float r = p0.w;
        float t = 0.0f;
        if (kind == COLLIDER_CAPSULE) {
            float3 axis = p1.xyz - p0.xyz;
            float aa = dot(axis, axis);
            t = aa > EPS_LEN2 ? clamp(dot(x - p0.xyz, axis) / aa, 0.0f, 1.0f) : 0.0f;
        }
        float3 centre = p0.xyz + t * (p1.xyz - p0.xyz);
        float3 d = x - centre;
        float d2 = dot(d, d);
        if (d2 < r * r) {
            float dist = sqrt(d2);
            float3 n = dist > 1e-12f ? d / dist : (float3)(0.0f, 1.0f, 0.0f);
            x = centre + n * r;
            float3 cdisp = centre - (q0.xyz + t * (q1.xyz - q0.xyz));
            x = friction(x, xp, n, r - dist, cdisp, mu);
        }
    }
    return x;
}
#endif

/* tethers, colliders, velocity from positions */
inline float4 finish_vertex(float4 x, XS const float4 *X, __global const int *fb, __global const int *I,
                            __global const float *F, __global float4 *vel, __global const float4 *prev,
                            __global const float4 *coll, int v, int gv, float h, int s, int S)
{
    float4 xp = prev[gv];
    if (x.w > 0.0f) {
#if FEATURE_TETHERS
        __global const int *anc = fb + I[CI_OFF_ANCHOR];
        int a = anc[ANCHOR_WORDS * v];
        if (a >= 0) {
            float lim = as_float(anc[ANCHOR_WORDS * v + 1]) * F[CF_TETHER_LIMIT];
            float3 xa = X[a].xyz;
            float3 d = x.xyz - xa;
            float dist = length(d);
            if (dist > lim)
                x.xyz = xa + d * (lim / dist);
        }
#endif
#if FEATURE_COLLIDERS
        x.xyz = collide_vertex(x.xyz, xp.xyz, coll, I[CI_COLL], I[CI_NCOLL], (float)s / (float)S,
                               (float)(s + 1) / (float)S, F[CF_FRICTION]);
#endif
    }
    vel[gv] = (float4)((x.xyz - xp.xyz) / h * (1.0f - F[CF_DAMP_SUB]), 0.0f);
    return x;
}

/* ------------------------------------------------------------------------------------------ */
/* Work-group solver: one work-group per cloth, every substep, iteration and colour batch in
 * one launch. Barriers sit only where control flow is uniform across the group. */

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
#if FEATURE_XPBD
    __global float *lam = lam_all + I[CI_LAM];
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
        for (int v = lid; v < nv; v += ls) {
            float area;
            float3 n = vertex_normal(X, fb, I, v, &area);
            nrm[vbase + v] = (float4)(n, area);
        }
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
#endif
        for (int v = lid; v < nv; v += ls) {
            float3 f = (float3)(0.0f);
#if FEATURE_WIND
            float4 na = nrm[vbase + v];
            f = aero_dv(vel[vbase + v].xyz, na.xyz, na.w, X[v].w, h, F);
#endif
            X[v] = predict_vertex(X[v], f, vel, prev, target, vbase + v, F, h, S - s);
        }
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
                    for (int u = 0; u < LINK_UNROLL; ++u) {
                        float3 d0, d1;
#if FEATURE_XPBD
                        int lu = l + u * ls;
                        float dl = link_xpbd(P0[u], P1[u], as_float(R[u].w), link_alpha(F, R[u].z, h), lam[lu], &d0, &d1);
                        lam[lu] += dl;
#else
                        link_pbd(P0[u], P1[u], as_float(R[u].w), F[CF_STIFFNESS + R[u].z], &d0, &d1);
#endif
                        X[R[u].x] = (float4)(P0[u].xyz + d0, P0[u].w);
                        X[R[u].y] = (float4)(P1[u].xyz + d1, P1[u].w);
                    }
                }
                for (; l < end; l += ls) {
                    int4 R = vload4(l, links);
                    float4 p0 = X[R.x], p1 = X[R.y];
                    float3 d0, d1;
#if FEATURE_XPBD
                    float dl = link_xpbd(p0, p1, as_float(R.w), link_alpha(F, R.z, h), lam[l], &d0, &d1);
                    lam[l] += dl;
#else
                    link_pbd(p0, p1, as_float(R.w), F[CF_STIFFNESS + R.z], &d0, &d1);
#endif
                    X[R.x] = (float4)(p0.xyz + d0, p0.w);
                    X[R.y] = (float4)(p1.xyz + d1, p1.w);
                }
                barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
            }
        }

        for (int v = lid; v < nv; v += ls)
            X[v] = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S);
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    }

#if FEATURE_NORMALS
    for (int v = lid; v < nv; v += ls) {
        float area;
        float3 n = vertex_normal(X, fb, I, v, &area);
        nrm[vbase + v] = (float4)(n, area);
    }
#endif
#if USE_LOCAL
    for (int v = lid; v < nv; v += ls)
        pos[vbase + v] = X[v];
#endif
}

#if !USE_LOCAL
/* ------------------------------------------------------------------------------------------ */
/* Vertex phases of the coloured and Jacobi strategies. They run over *chunks*: (cloth, first
 * vertex) pairs of at most `chunk` vertices, so a big cloth spreads over many work-groups and
 * small ones take one each. No phase reads a vertex another chunk writes in the same launch:
 * normals are their own launch, tethers read pinned anchors, which these phases never move. */

#define CHUNK_PROLOGUE                                                                           \
    const int2 ck = chunks[get_group_id(0)];                                                     \
    const int c = ck.x;                                                                          \
    __global const int *I = ci + c * CI_STRIDE;                                                  \
    __global const float *F = cf + c * CF_STRIDE;                                                \
    __global const int *fb = fab + I[CI_FAB];                                                    \
    const int vbase = I[CI_VBASE], S = I[CI_SUBSTEPS];                                           \
    const int v_end = min(ck.y + chunk, I[CI_NVERTS]);                                           \
    const int lid = get_local_id(0), ls = get_local_size(0);

__kernel void cl_normals(const int chunk, __global const int2 *chunks, __global const int *ci,
                         __global const float *cf, __global const int *fab, __global const float4 *pos,
                         __global float4 *nrm)
{
    CHUNK_PROLOGUE
    for (int v = ck.y + lid; v < v_end; v += ls) {
        float area;
        float3 n = vertex_normal(pos + vbase, fb, I, v, &area);
        nrm[vbase + v] = (float4)(n, area);
    }
}

__kernel void cl_predict(const float dt, const int s, const int chunk, __global const int2 *chunks,
                         __global const int *ci, __global const float *cf, __global const int *fab,
                         __global float4 *pos, __global float4 *vel, __global float4 *prev,
                         __global const float4 *target, __global const float4 *nrm, __global float *lam_all)
{
    CHUNK_PROLOGUE
    const float h = dt / (float)S;
    __global float4 *X = pos + vbase;
    for (int v = ck.y + lid; v < v_end; v += ls) {
        float3 f = (float3)(0.0f);
#if FEATURE_WIND
        float4 na = nrm[vbase + v];
        f = aero_dv(vel[vbase + v].xyz, na.xyz, na.w, X[v].w, h, F);
#endif
        X[v] = predict_vertex(X[v], f, vel, prev, target, vbase + v, F, h, S - s);
    }
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
        X[v] = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S);
}

/* One colour batch of every cloth in the group: global id -> (cloth, link) through the
 * group's prefix table of link counts for this colour. */
__kernel void cl_links(const float dt, const int colour, const int it, const int ngc,
                       __global const int *prefix, __global const int *cloths, __global const int *ci,
                       __global const float *cf, __global const int *fab, __global float4 *pos,
                       __global float *lam_all)
{
    const int g = get_global_id(0);
    __global const int *P = prefix + colour * (ngc + 1);
    if (g >= P[ngc])
        return;
    int lo = 0, hi = ngc; /* largest j with P[j] <= g */
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (P[mid] <= g)
            lo = mid;
        else
            hi = mid;
    }
    const int c = cloths[lo];
    __global const int *I = ci + c * CI_STRIDE;
    if (it >= I[CI_ITERS])
        return;
    __global const float *F = cf + c * CF_STRIDE;
    __global const int *fb = fab + I[CI_FAB];
    const int l = fb[I[CI_OFF_COLOURS] + colour] + (g - P[lo]);
    __global const int *L = fb + I[CI_OFF_LINKS] + LINK_WORDS * l;
    __global float4 *X = pos + I[CI_VBASE];
    int a = L[0], b = L[1], type = L[2];
    float rl = as_float(L[3]);
    float4 p0 = X[a], p1 = X[b];
    float3 d0, d1;
#if FEATURE_XPBD
    __global float *lam = lam_all + I[CI_LAM];
    float h = dt / (float)I[CI_SUBSTEPS];
    lam[l] += link_xpbd(p0, p1, rl, link_alpha(F, type, h), lam[l], &d0, &d1);
#else
    link_pbd(p0, p1, rl, F[CF_STIFFNESS + type], &d0, &d1);
#endif
    X[a] = (float4)(p0.xyz + d0, p0.w);
    X[b] = (float4)(p1.xyz + d1, p1.w);
}

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

/* pin targets sent this tick, gathered into one upload: target[index[i]] = value[i] */
__kernel void scatter_targets(const int n, __global const int *index, __global const float4 *value,
                              __global float4 *target)
{
    const int i = get_global_id(0);
    if (i < n)
        target[index[i]] = value[i];
}

/* the frame read back: row i of out = xyz of vertex src[i] (every cloth's rows back to back) */
__kernel void pack_rows(const int n, __global const int *src, __global const float4 *from, __global float *out)
{
    const int i = get_global_id(0);
    if (i < n)
        vstore3(from[src[i]].xyz, i, out);
}

/* copy positions of every chunk (closes an odd number of Jacobi iterations) */
__kernel void copy_positions(const int chunk, __global const int2 *chunks, __global const int *ci,
                             __global const float4 *src, __global float4 *dst)
{
    const int2 ck = chunks[get_group_id(0)];
    __global const int *I = ci + ck.x * CI_STRIDE;
    const int vbase = I[CI_VBASE], v_end = min(ck.y + chunk, I[CI_NVERTS]);
    for (int v = ck.y + get_local_id(0); v < v_end; v += get_local_size(0))
        dst[vbase + v] = src[vbase + v];
}
#endif

#if PACK_LANES && !USE_LOCAL
#include "pack.cl"
#endif
