/* Colliders: spheres, capsules and planes moving linearly over the step (each slot holds the
 * previous and the current pose), pushing a vertex out and applying friction against the
 * collider's own motion. Built with FEATURE_COLLIDERS only. Included by cloth.cl.
 * Spheres and capsules are continuous (no tunnelling): the vertex's motion in the substep (xp ->
 * x) is walked against the collider moving from its pose at the substep's start to its pose at
 * the end, by conservative advancement (each step advances by the distance to the surface over
 * the largest speed of the vertex relative to the collider's axis, so it never passes the first
 * contact), at most CCD_STEPS steps; where it meets the surface (or the steps run out before the
 * end of the substep), the end position is put back onto the plane tangent to the collider at
 * that contact point, carried to the collider's end pose (the rest of the motion slides along the
 * surface). A discrete push-out at the end pose follows (what a rotating capsule leaves). Planes
 * are half-spaces: the discrete push-out along the normal is already the continuous answer.
 * The float64 reference is drape.server.sim.reference.collide.
 * The type ids are the protocol's (drape.client.protocol.COLLIDER_SHAPES: its row order; checked by
 * tests/client/test_protocol_tables.py). */
#ifndef CCD_STEPS
#define CCD_STEPS 12
#endif
#ifndef CCD_SLOP
#define CCD_SLOP 1e-5f
#endif
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

/* the point of a sphere's centre (cap = 0) or a capsule's axis a0 -> a1 closest to x; *t: its
 * parameter along the axis */
inline float3 axis_point(float3 x, float3 a0, float3 a1, int cap, float *t)
{
    float s = 0.0f;
    if (cap) {
        float3 axis = a1 - a0;
        float aa = dot(axis, axis);
        s = aa > EPS_LEN2 ? clamp(dot(x - a0, axis) / aa, 0.0f, 1.0f) : 0.0f;
    }
    *t = s;
    return a0 + s * (a1 - a0);
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
        int cap = kind == COLLIDER_CAPSULE;
        if (r > 0.0f) {
            /* continuous: the first contact along the substep's motion (conservative advancement) */
            float3 dx = x - xp;
            float L = length(dx - (p0.xyz - q0.xyz));
            if (cap)
                L = fmax(L, length(dx - (p1.xyz - q1.xyz)));
            float tau = 0.0f;
            float3 v = xp;
            float3 c = axis_point(v, q0.xyz, q1.xyz, cap, &t);
            float f = length(v - c) - r;
            for (int k = 0; k < CCD_STEPS && f >= CCD_SLOP; ++k) {
                if (!(f <= L * (1.0f - tau))) { /* no contact before the substep's end */
                    tau = 2.0f;
                    break;
                }
                tau += f / L;
                v = xp + dx * tau;
                c = axis_point(v, q0.xyz + (p0.xyz - q0.xyz) * tau, q1.xyz + (p1.xyz - q1.xyz) * tau, cap, &t);
                f = length(v - c) - r;
            }
            if (tau <= 1.0f) {
                float3 d = v - c;
                float dl = length(d);
                float3 n = dl > 1e-12f ? d / dl : (float3)(0.0f, 1.0f, 0.0f);
                float3 ce = p0.xyz + t * (p1.xyz - p0.xyz);
                float depth = dot(ce + n * r - x, n);
                if (depth > 0.0f) {
                    x += n * depth;
                    x = friction(x, xp, n, depth, ce - (q0.xyz + t * (q1.xyz - q0.xyz)), mu);
                }
            }
        }
        /* discrete: out of the collider at its end pose */
        float3 centre = axis_point(x, p0.xyz, p1.xyz, cap, &t);
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
