/* Tethers: long-range attachments. A vertex may be at most its tether length (its rest distance
 * to its anchor, the nearest pinned vertex, stored with the fabric) times the cloth's limit from
 * that anchor; further out it is pulled back onto the sphere around it. Built with
 * FEATURE_TETHERS only; finish_vertex (integrate.cl) applies it. Included by cloth.cl. */

inline float4 tether_vertex(float4 x, XS const float4 *X, __global const int *fb, __global const int *I,
                            __global const float *F, int v)
{
    __global const int *anc = fb + I[CI_OFF_ANCHOR];
    int a = anc[ANCHOR_WORDS * v];
    if (a >= 0) {
        float lim = as_float(anc[ANCHOR_WORDS * v + 1]) * F[CF_TETHER_LIMIT];
        float3 xa = X[a].xyz;
        float3 d = x.xyz - xa;
        float dist = length(d);
        if (dist > lim)
            x.xyz = xa + d * (lim / dist);
    }
    return x;
}
