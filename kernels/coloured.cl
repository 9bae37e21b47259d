/* The coloured solver's link iterations (cl_links): one launch per colour batch and iteration,
 * over every cloth of a group at once, one work-item per link. Links of one colour share no
 * vertex, so a batch has no conflicts; the order of the batches is the reference's colour order
 * (Gauss-Seidel across colours). Built with USE_LOCAL=0 only. Included by cloth.cl. */

/* One colour batch of every cloth in the group: global id -> (cloth, link) through the
 * group's prefix table of link counts for this colour. */
__kernel void cl_links(const float dt, const int colour, const int it, const int ngc,
                       __global const int *prefix, __global const int *cloths, __global const int *ci,
                       __global const float *cf, __global const int *fab, __global float4 *pos,
                       __global float *lam_all)
{
    const int g = get_global_id(0);
    __global const int *P = prefix + colour * (ngc + 1);
    if (g >= P[ngc])
        return;
    int lo = 0, hi = ngc; /* largest j with P[j] <= g */
    while (hi - lo > 1) {
        int mid = (lo + hi) >> 1;
        if (P[mid] <= g)
            lo = mid;
        else
            hi = mid;
    }
    const int c = cloths[lo];
    __global const int *I = ci + c * CI_STRIDE;
    if (it >= I[CI_ITERS])
        return;
    __global const float *F = cf + c * CF_STRIDE;
    __global const int *fb = fab + I[CI_FAB];
    const int l = fb[I[CI_OFF_COLOURS] + colour] + (g - P[lo]);
    __global const int *L = fb + I[CI_OFF_LINKS] + LINK_WORDS * l;
    const int4 R = (int4)(L[0], L[1], L[2], L[3]);
    __global float4 *X = pos + I[CI_VBASE];
    float4 p0 = X[R.x], p1 = X[R.y];
    solve_link(X, R, p0, p1, F, dt / (float)I[CI_SUBSTEPS], lam_all + I[CI_LAM], l);
}
