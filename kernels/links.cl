/* Link equations: what a distance link between two vertices asks of its ends, in the talk's PBD
 * form and in XPBD's compliant form (which also returns its Lagrange multiplier's increment; the
 * caller keeps the multipliers). Each returns corrections for the two ends; solve_link applies
 * them in place for the Gauss-Seidel solvers (wg_step.cl, coloured.cl), jacobi.cl gathers them per
 * vertex, and pack.cl spells the same arithmetic out across its lanes. Included by cloth.cl. */

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

/* Gauss-Seidel update of link l in place: R is its record (ends, type, rest length bits), p0 and
 * p1 its ends as loaded from X; both ends are stored back corrected. XPBD: compliance by type, and
 * the multiplier lam[l] accumulates its increment; PBD: stiffness by type, lam is not read. */
inline void solve_link(XS float4 *X, int4 R, float4 p0, float4 p1, __global const float *F, float h,
                       __global float *lam, int l)
{
    float3 d0, d1;
#if FEATURE_XPBD
    lam[l] += link_xpbd(p0, p1, as_float(R.w), link_alpha(F, R.z, h), lam[l], &d0, &d1);
#else
    link_pbd(p0, p1, as_float(R.w), F[CF_STIFFNESS + R.z], &d0, &d1);
#endif
    X[R.x] = (float4)(p0.xyz + d0, p0.w);
    X[R.y] = (float4)(p1.xyz + d1, p1.w);
}

/* solve_link for XPBD where every multiplier is 0 when read (compliance 0, or one iteration per
 * substep): link_xpbd's arithmetic with lam = 0, nothing kept. */
inline void solve_link_lamless(XS float4 *X, int4 R, float4 p0, float4 p1, __global const float *F, float h)
{
    float3 d0, d1;
    link_xpbd(p0, p1, as_float(R.w), link_alpha(F, R.z, h), 0.0f, &d0, &d1);
    X[R.x] = (float4)(p0.xyz + d0, p0.w);
    X[R.y] = (float4)(p1.xyz + d1, p1.w);
}
