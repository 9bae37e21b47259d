/* Colliders: spheres, capsules and planes moving linearly over the step (each slot holds the
 * previous and the current pose), pushing a vertex out and applying friction against the
 * collider's own motion. Built with FEATURE_COLLIDERS only. Included by cloth.cl.
 * The type ids are the protocol's (drape.client.protocol.COLLIDER_SHAPES: its row order; checked by
 * tests/client/test_protocol_tables.py). */
#define COLLIDER_SPHERE 0
#define COLLIDER_CAPSULE 1
#define COLLIDER_PLANE 2

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
