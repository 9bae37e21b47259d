/* A frame plan's static bytes put into the device encoder's output buffer (frameplan.py's
 * FramePlan.static_at and static_words: the headers of every state and bundle and the bundle
 * entries with their ids, as 8-byte words at word offsets): a plan change uploads its words
 * (about 1 MB at 8192 predictive cloths), not its whole template (100 MB, nearly all zeros, made
 * on the host first), and fills nothing with zeros (encode.cl writes every other byte of every
 * state it codes, its padding included). */

__kernel void put_static(const uint count, __global const uint *at, __global const ulong *words,
                         __global ulong *out) {
    const size_t i = get_global_id(0);
    if (i < count) {
        out[at[i]] = words[i];
    }
}
