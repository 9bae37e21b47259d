/* Link equations: what a distance link between two vertices asks of its ends, in the talk's PBD
 * form and in XPBD's compliant form (which also returns its Lagrange multiplier's increment; the
 * caller keeps the multipliers). Each returns corrections for the two ends; the caller loads and
 * stores. The solvers (wg_step.cl, coloured.cl, jacobi.cl) call these; pack.cl spells the same
 * arithmetic out across its lanes. Included by cloth.cl. */

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
