/* Integration of one substep, per vertex: predict_vertex (gravity, wind, semi-implicit Euler, pins
 * moved toward their targets) before the link solve, finish_vertex ([tethers], colliders, the
 * velocity from the positions, damping) after it. Every solver calls both. Included by cloth.cl
 * after tethers.cl and colliders.cl. */

/* gravity (+ wind, from the vertex's normal and area in nrm), integrate, move pins toward their
 * targets; x is vertex gv's position */
inline float4 predict_vertex(float4 x, __global float4 *vel, __global float4 *prev, __global const float4 *target,
                             __global const float4 *nrm, int gv, __global const float *F, float h, int remaining)
{
    float3 aero = (float3)(0.0f);
#if FEATURE_WIND
    float4 na = nrm[gv];
    aero = aero_dv(vel[gv].xyz, na.xyz, na.w, x.w, h, F);
#endif
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

/* a vertex's velocity from its position x and its substep's start xp, damped (finish_vertex's last
 * step; a solver with self-collision takes it again after the passes that follow finish_vertex) */
inline float4 vertex_velocity(float4 x, float4 xp, float h, __global const float *F)
{
    return (float4)((x.xyz - xp.xyz) / h * (1.0f - F[CF_DAMP_SUB]), 0.0f);
}

/* after self-collision's passes (which follow finish_vertex): out of the colliders again at their
 * end pose, without friction (a pass may push a vertex into one), and the velocity again */
inline float4 refinish_vertex(float4 x, __global const int *I, __global const float *F, __global float4 *vel,
                              __global const float4 *prev, __global const float4 *coll, int gv, float h, int s, int S)
{
#if FEATURE_COLLIDERS
    if (x.w > 0.0f) {
        const float t1 = (float)(s + 1) / (float)S;
        x.xyz = collide_vertex(x.xyz, x.xyz, coll, I[CI_COLL], I[CI_NCOLL], t1, t1, 0.0f);
    }
#endif
    vel[gv] = vertex_velocity(x, prev[gv], h, F);
    return x;
}

/* tethers (where the solver applies them after the links: tethers = 1), colliders, velocity from
 * positions */
inline float4 finish_vertex(float4 x, XS const float4 *X, __global const int *fb, __global const int *I,
                            __global const float *F, __global float4 *vel, __global const float4 *prev,
                            __global const float4 *coll, int v, int gv, float h, int s, int S, int tethers)
{
    float4 xp = prev[gv];
    if (x.w > 0.0f) {
#if FEATURE_TETHERS
        if (tethers)
            x = tether_vertex(x, X, fb, I, F, v);
#endif
#if FEATURE_COLLIDERS
        x.xyz = collide_vertex(x.xyz, xp.xyz, coll, I[CI_COLL], I[CI_NCOLL], (float)s / (float)S,
                               (float)(s + 1) / (float)S, F[CF_FRICTION]);
#endif
    }
    vel[gv] = vertex_velocity(x, xp, h, F);
    return x;
}
