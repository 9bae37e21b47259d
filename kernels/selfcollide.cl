/* Self-collision (FEATURE_SELF_COLLISION, protocol 1.6): every vertex keeps the material's
 * thickness th from the cloth's other vertices that are further apart than th at rest (closer
 * ones are the cloth's own neighbourhood and never collide; NvCloth's rule). Called by wg_step
 * once per substep after the link iterations, by every work-item of the cloth's work-group.
 *
 * Each of SELF_COLLISION_PASSES passes rebuilds a spatial hash of the cloth and projects every
 * contact as a position constraint, Jacobi style (deterministic, the same sums as
 * drape.server.sim.collision.self_collide):
 *   grid   cells of edge th hashed into SC_CELLS buckets of local memory (layout.h); each bucket
 *          a linked list: its head in `heads`, a vertex's next in the w of its `S` row
 *   query  vertex v visits the 27 cells around its own; a vertex u of the bucket counts when it
 *          lies in that very cell (hash collisions never count a vertex twice), |x_v - x_u| < th
 *          and |rest_v - rest_u| > th; v moves by k (th - |d|) w_v / (w_v + w_u) along d / |d|
 *          (the rest-pose direction where the two coincide), its sum kept in the xyz of S
 *   apply  every free vertex adds its sum
 * S is the cloth's rows of the velocity buffer: between the links and finish_vertex, which writes
 * every row, nothing reads it (predict_vertex wrote it, finish_vertex overwrites it).
 * Included by cloth.cl. */

#ifndef SELF_COLLISION_PASSES
#define SELF_COLLISION_PASSES 2
#endif

inline int3 sc_cell(float3 p, float inv)
{
    return convert_int3_sat_rtn(p * inv);
}

inline int sc_bucket(int3 c)
{
    uint3 u = as_uint3(c);
    return (int)((u.x * 73856093u ^ u.y * 19349663u ^ u.z * 83492791u) & (uint)(SC_CELLS - 1));
}

inline float3 sc_rest(__global const int *rest, int v)
{
    return (float3)(as_float(rest[3 * v]), as_float(rest[3 * v + 1]), as_float(rest[3 * v + 2]));
}

inline void self_collide(XS float4 *X, __global float4 *S, __local int *heads, __global const int *rest, int nv,
                         float th, float k, int lid, int ls)
{
    if (!(th > 0.0f) || !(k > 0.0f)) /* the same for the whole group: no barrier is skipped by some */
        return;
    const float inv = 1.0f / th, th2 = th * th;
    for (int pass = 0; pass < SELF_COLLISION_PASSES; ++pass) {
        for (int c = lid; c < SC_CELLS; c += ls)
            heads[c] = -1;
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        for (int v = lid; v < nv; v += ls)
            S[v].w = as_float(atomic_xchg(&heads[sc_bucket(sc_cell(X[v].xyz, inv))], v));
        barrier(CLK_LOCAL_MEM_FENCE | CLK_GLOBAL_MEM_FENCE);
        for (int v = lid; v < nv; v += ls) {
            const float4 xv = X[v];
            float3 corr = (float3)(0.0f);
            if (xv.w > 0.0f) {
                const int3 cv = sc_cell(xv.xyz, inv);
                const float3 rv = sc_rest(rest, v);
                for (int dz = -1; dz <= 1; ++dz)
                    for (int dy = -1; dy <= 1; ++dy)
                        for (int dx = -1; dx <= 1; ++dx) {
                            const int3 cell = cv + (int3)(dx, dy, dz);
                            for (int u = heads[sc_bucket(cell)]; u >= 0; u = as_int(S[u].w)) {
                                if (u == v)
                                    continue;
                                const float4 xu = X[u];
                                const int3 cu = sc_cell(xu.xyz, inv);
                                if (cu.x != cell.x || cu.y != cell.y || cu.z != cell.z)
                                    continue;
                                const float3 d = xv.xyz - xu.xyz;
                                const float d2 = dot(d, d);
                                if (!(d2 < th2))
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
