/* Self-collision (FEATURE_SELF_COLLISION, protocol 1.6): every vertex keeps the material's
 * thickness th from the cloth's other vertices that are further apart than th at rest (closer
 * ones are the cloth's own neighbourhood and never collide; NvCloth's rule). Called once per
 * substep after the link iterations, tethers and colliders (finish_vertex: the colliders' friction
 * would take back the separation it makes), by every work-item of the cloth's work-group: wg_step's,
 * or cl_self_collide's (below: the coloured and Jacobi solvers, one work-group per cloth); the
 * caller then puts every vertex out of the colliders again and takes its velocity again
 * (integrate.cl's refinish_vertex).
 *
 * Each of SELF_COLLISION_PASSES passes rebuilds a spatial hash of the cloth and projects every
 * contact as a position constraint, Jacobi style (the same sums as
 * drape.server.sim.collision.self_collide, in another order):
 *   grid   cells of edge 2 th hashed into the largest power of 2 <= 4 nv buckets, each a linked
 *          list: its head in `heads`, a vertex's next in the w of its `S` row
 *   query  vertex v visits the 2 x 2 x 2 cells that hold every point within th of it, each
 *          bucket once (a vertex is in one bucket: none is counted twice); a vertex u counts when
 *          |x_v - x_u| < th and |rest_v - rest_u| > th, and v moves by k (th - |d|) w_v / (w_v + w_u)
 *          along d / |d| (the rest-pose direction where the two coincide), summed in the xyz of S
 *   apply  every free vertex adds its sum
 * Scratch, no buffer of its own: S is the cloth's rows of the velocity buffer (finish_vertex wrote
 * them, the caller overwrites every one after the passes, nothing reads them between), `heads` its rows
 * of the normals buffer (written before they are read: by the wind at each substep's start, by
 * the normals at the step's end; a cloth without either publishes none).
 * Included by cloth.cl. */

#ifndef SELF_COLLISION_PASSES
#define SELF_COLLISION_PASSES 2
#endif

inline int sc_bucket(int3 c, uint mask)
{
    uint3 u = as_uint3(c);
    return (int)((u.x * 73856093u ^ u.y * 19349663u ^ u.z * 83492791u) & mask);
}

inline float3 sc_rest(__global const int *rest, int v)
{
    return (float3)(as_float(rest[3 * v]), as_float(rest[3 * v + 1]), as_float(rest[3 * v + 2]));
}

inline void self_collide(XS float4 *X, __global float4 *S, __global int *heads, __global const int *rest, int nv,
                         float th, float k, int lid, int ls)
{
    if (!(th > 0.0f) || !(k > 0.0f)) /* the same for the whole group: no barrier is skipped by some */
        return;
    const float inv = 0.5f / th, th2 = th * th; /* cells of edge 2 th */
    const int nb = 1 << (31 - clz(4 * nv));     /* buckets: the largest power of 2 <= 4 nv */
    const uint mask = (uint)(nb - 1);
    for (int pass = 0; pass < SELF_COLLISION_PASSES; ++pass) {
        for (int b = lid; b < nb; b += ls)
            heads[b] = -1;
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        for (int v = lid; v < nv; v += ls)
            S[v].w = as_float(atomic_xchg(&heads[sc_bucket(convert_int3_sat_rtn(X[v].xyz * inv), mask)], v));
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        for (int v = lid; v < nv; v += ls) {
            const float4 xv = X[v];
            float3 corr = (float3)(0.0f);
            if (xv.w > 0.0f) {
                const float3 rv = sc_rest(rest, v);
                /* the 2 x 2 x 2 cells that hold every point within th of xv; each bucket once */
                const int3 c0 = convert_int3_sat_rtn(xv.xyz * inv - 0.5f);
                int seen[8];
                for (int q = 0; q < 8; ++q) {
                    const int b = sc_bucket(c0 + (int3)(q & 1, (q >> 1) & 1, q >> 2), mask);
                    int dup = 0;
                    for (int e = 0; e < q; ++e)
                        dup |= seen[e] == b;
                    seen[q] = b;
                    if (dup)
                        continue;
                    for (int u = heads[b]; u >= 0; u = as_int(S[u].w)) {
                        const float4 xu = X[u];
                        const float3 d = xv.xyz - xu.xyz;
                        const float d2 = dot(d, d);
                        if (!(d2 < th2) || u == v)
                            continue;
                        const float3 rd = rv - sc_rest(rest, u);
                        const float r2 = dot(rd, rd);
                        if (!(r2 > th2))
                            continue;
                        const float dist = sqrt(d2);
                        const float3 n = dist > 1e-12f ? d / dist : rd / sqrt(r2);
                        corr += n * (k * (th - dist) * xv.w / (xv.w + xu.w));
                    }
                }
            }
            vstore3(corr, 0, (__global float *)(S + v));
        }
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        for (int v = lid; v < nv; v += ls)
            if (X[v].w > 0.0f)
                X[v].xyz += S[v].xyz;
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
    }
}

#if !USE_LOCAL
/* The coloured and Jacobi solvers' self-collision: one work-group per cloth of the group (its
 * cloth list), launched after cl_finish (after the colliders' friction, which would take back its
 * separation), on global memory; then refinish_vertex, as the other solvers. */
__kernel void cl_self_collide(const float dt, const int s, __global const int *cloths, __global const int *ci,
                              __global const float *cf, __global const int *fab, __global float4 *pos,
                              __global float4 *vel, __global float4 *nrm, __global const float4 *prev,
                              __global const float4 *coll)
{
    const int c = cloths[get_group_id(0)];
    __global const int *I = ci + c * CI_STRIDE;
    __global const float *F = cf + c * CF_STRIDE;
    const int vbase = I[CI_VBASE], nv = I[CI_NVERTS], lid = get_local_id(0), ls = get_local_size(0);
    const int S = I[CI_SUBSTEPS];
    const float h = dt / (float)S;
    self_collide(pos + vbase, vel + vbase, (__global int *)(nrm + vbase), fab + I[CI_FAB] + I[CI_OFF_REST], nv,
                 F[CF_THICKNESS], F[CF_CONTACT_STIFFNESS], lid, ls);
    for (int v = lid; v < nv; v += ls)
        pos[vbase + v] = refinish_vertex(pos[vbase + v], I, F, vel, prev, coll, vbase + v, h, s, S);
}
#endif
