/* Transfers between the host and the merged vertex buffers: scatter_targets (before a step, the
 * pin targets sent since the last one, in one upload) and pack_rows (a frame read back: every
 * cloth's xyz rows back to back). Built with USE_LOCAL=0 only (the world builds them with its base
 * options, targets.py and frames.py). Included by cloth.cl. */

/* pin targets sent this tick, gathered into one upload: target[index[i]] = value[i] */
__kernel void scatter_targets(const int n, __global const int *index, __global const float4 *value,
                              __global float4 *target)
{
    const int i = get_global_id(0);
    if (i < n)
        target[index[i]] = value[i];
}

/* the frame read back: row i of out = xyz of vertex src[i] (every cloth's rows back to back) */
__kernel void pack_rows(const int n, __global const int *src, __global const float4 *from, __global float *out)
{
    const int i = get_global_id(0);
    if (i < n)
        vstore3(from[src[i]].xyz, i, out);
}
