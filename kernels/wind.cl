/* Wind: Bullet's aerodynamic drag and lift on a vertex, from its normal and area (normals.cl) and
 * the cloth's wind, air density, drag and lift coefficients. Included by cloth.cl. */

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
