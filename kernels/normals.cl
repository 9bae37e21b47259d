/* Vertex normals and areas: the area-weighted normal of a vertex's triangles and a third of their
 * area, from positions X (local or global memory, XS), as one float4 (normal, area): what the
 * solvers store in the normals buffer, which the wind feature's aerodynamics (wind.cl, before each
 * substep) and the normals feature's published normals (after the step) read. pack.cl computes
 * the same across its lanes. Included by cloth.cl. */

inline float4 vertex_normal(XS const float4 *X, __global const int *fb, __global const int *I, int v)
{
    __global const int *vto = fb + I[CI_OFF_VTRIOFF];
    __global const int *vt = fb + I[CI_OFF_VTRI];
    __global const int *tris = fb + I[CI_OFF_TRIS];
    float3 n = (float3)(0.0f);
    float a = 0.0f;
    for (int k = vto[v]; k < vto[v + 1]; ++k) {
        int t = vt[k];
        float3 x0 = X[tris[3 * t]].xyz;
        float3 fn = cross(X[tris[3 * t + 1]].xyz - x0, X[tris[3 * t + 2]].xyz - x0);
        n += fn;
        a += 0.5f * length(fn) / 3.0f;
    }
    float len = length(n);
    return (float4)(len > 1e-30f ? n / len : (float3)(0.0f), a);
}
