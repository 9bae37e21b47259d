/* Long-range attachments (server/sim/tethers.py), built with FEATURE_TETHERS only. Included by
 * cloth.cl.
 *
 * Tethers: a free vertex has up to TETHER_SLOTS tethers, one to each pin island (nearest island
 * first, -1 ends the list); it may be at most each tether's length (the geodesic rest distance to
 * the anchor, stored with the fabric) times the cloth's limit from that anchor, and further out
 * it is pulled back onto the sphere around it, slot by slot. The work-group solver and the CPU
 * pack solver apply them after predicting the substep, before the links (NvCloth's order), and
 * again after the links (finish_vertex); the coloured and Jacobi solvers after the links only.
 *
 * Long-range links: unilateral, hard links of a coarse hierarchy of the cloth (rest length times
 * the tether limit, never pushing apart), by colour, before the links of every iteration in the
 * work-group and pack solvers. */

inline float4 tether_vertex(float4 x, XS const float4 *X, __global const int *fb, __global const int *I,
                            __global const float *F, int v)
{
    __global const int *anc = fb + I[CI_OFF_ANCHOR] + ANCHOR_WORDS * v;
    const float limit = F[CF_TETHER_LIMIT];
    for (int t = 0; t < TETHER_SLOTS; ++t) {
        const int a = anc[2 * t];
        if (a < 0)
            break;
        const float lim = as_float(anc[2 * t + 1]) * limit;
        const float3 xa = X[a].xyz;
        const float3 d = x.xyz - xa;
        const float dist = length(d);
        if (dist > lim)
            x.xyz = xa + d * (lim / dist);
    }
    return x;
}

/* long-range link R (ends p0, p1 as loaded from X) no longer than its rest length times limit */
inline void solve_long_range(XS float4 *X, int4 R, float4 p0, float4 p1, float limit)
{
    const float3 d = p1.xyz - p0.xyz;
    const float L = dot(d, d);
    const float rl = as_float(R.w) * limit;
    const float w = p0.w + p1.w;
    if (L > rl * rl && L > EPS_LEN2 && w > EPS_DENOM) {
        const float k = (rl * rsqrt(L) - 1.0f) / w; /* < 0: pulls the ends together */
        X[R.x] = (float4)(p0.xyz - d * (k * p0.w), p0.w);
        X[R.y] = (float4)(p1.xyz + d * (k * p1.w), p1.w);
    }
}
