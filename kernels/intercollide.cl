/* Inter-cloth collision of scenes (protocol 1.7): cloths of one scene kept apart from each other,
 * cloths of different scenes never interact. The same sums as drape.server.sim.scenes.inter_collide
 * (read it first), once per step after every cloth's own solve. Its own program, built and
 * launched only while a World has a scene of two cloths or more (drape.server.sim.opencl.scenes):
 * a World without scenes pays nothing, and cloth.cl is built as before.
 *
 * The scene cloths' vertices are numbered t = 0..nv-1 in one list, scene by scene, each scene's
 * cloths in the order they joined it: vidx[t] is vertex t's row of the World's position and
 * velocity buffers, vcl[t] its cloth k (0..ncl-1). Per cloth k, cinfo[k] = (vbase, n, scene,
 * first cloth of its scene, cloths of its scene, -, -, -) and cpar[k] = (thickness x
 * INTER_COLLISION_MARGIN, stiffness): the thickness the solve keeps.
 *
 *   INTER_COLLISION_PASSES passes of
 *   ic_bounds    one work-group per cloth: its box grown by half its thickness (the broad phase)
 *   ic_active    per cloth: whether its box meets another box of its scene (else it takes no part)
 *   ic_clear     the spatial hash's bucket heads
 *   ic_insert    every vertex of an active cloth into the bucket of (its cell, its scene): cells
 *                of edge 2 dmax (dmax the largest contact distance of the World), one linked
 *                list per bucket built with one atomic exchange per vertex
 *   ic_contacts  every free vertex of an active cloth walks the 2 x 2 x 2 cells around it (each
 *                bucket once) and sums, over the vertices u of the other cloths of its scene
 *                closer than d = (th_k + th_u) / 2, k (d - |x - x_u|) w / (w + w_u) along
 *                (x - x_u) / |x - x_u| (+y for the cloth that joined first where they coincide)
 *   ic_apply     every vertex adds its sum to its position, and the sum / dt to its velocity
 */

#ifndef INTER_COLLISION_PASSES
#define INTER_COLLISION_PASSES 8
#endif
#ifndef IC_LS
#define IC_LS 64 /* work-items of ic_bounds' groups: a power of 2 */
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
        const float g = 0.5f * cpar[k].x;
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

__kernel void ic_insert(__global const float4 *pos, __global const int *vidx, __global const int *vcl,
                        __global const int8 *cinfo, __global const int *active, __global int *heads,
                        __global int *next, int nv, float inv, uint mask)
{
    const int t = get_global_id(0);
    if (t >= nv)
        return;
    const int k = vcl[t];
    if (!active[k])
        return;
    const int b = ic_bucket(convert_int3_sat_rtn(pos[vidx[t]].xyz * inv), cinfo[k].s2, mask);
    next[t] = atomic_xchg(&heads[b], t);
}

__kernel void ic_contacts(__global const float4 *pos, __global const int *vidx, __global const int *vcl,
                          __global const int8 *cinfo, __global const float2 *cpar, __global const int *active,
                          __global const int *heads, __global const int *next, __global float4 *delta, int nv,
                          float inv, uint mask)
{
    const int t = get_global_id(0);
    if (t >= nv)
        return;
    const int k = vcl[t];
    const float4 xv = pos[vidx[t]];
    float3 corr = (float3)(0.0f);
    if (active[k] && xv.w > 0.0f) {
        const int scene = cinfo[k].s2;
        const float2 pk = cpar[k];
        const int3 c0 = convert_int3_sat_rtn(xv.xyz * inv - 0.5f);
        int seen[8];
        int nseen = 0;
        for (int dz = 0; dz < 2; ++dz)
            for (int dy = 0; dy < 2; ++dy)
                for (int dx = 0; dx < 2; ++dx) {
                    const int b = ic_bucket(c0 + (int3)(dx, dy, dz), scene, mask);
                    int dup = 0;
                    for (int i = 0; i < nseen; ++i)
                        dup |= seen[i] == b;
                    if (dup)
                        continue;
                    seen[nseen++] = b;
                    for (int u = heads[b]; u >= 0; u = next[u]) {
                        const int ku = vcl[u];
                        if (ku == k || cinfo[ku].s2 != scene)
                            continue;
                        const float2 pu = cpar[ku];
                        const float d = 0.5f * (pk.x + pu.x), st = 0.5f * (pk.y + pu.y);
                        const float4 xu = pos[vidx[u]];
                        const float3 df = xv.xyz - xu.xyz;
                        const float dist2 = dot(df, df);
                        if (!(dist2 < d * d) || !(st > 0.0f))
                            continue;
                        const float dist = sqrt(dist2);
                        const float3 n = dist > 1e-12f ? df / dist : (float3)(0.0f, k < ku ? 1.0f : -1.0f, 0.0f);
                        corr += n * (st * (d - dist) * xv.w / (xv.w + xu.w));
                    }
                }
    }
    delta[t] = (float4)(corr, 0.0f);
}

__kernel void ic_apply(__global float4 *pos, __global float4 *vel, __global const int *vidx,
                       __global const float4 *delta, int nv, float inv_dt)
{
    const int t = get_global_id(0);
    if (t >= nv)
        return;
    const float3 d = delta[t].xyz;
    if (d.x != 0.0f || d.y != 0.0f || d.z != 0.0f) {
        const int g = vidx[t];
        pos[g].xyz += d;
        vel[g].xyz += d * inv_dt;
    }
}
