/* The device-encoded frame compacted on the device (protocol 1.5's variable-size predictive
 * states): encode_frame (encode.cl) writes each state into a slot of its largest size; these two
 * launches, right behind it on the same queue, write every publication's wire bytes back to back
 * into a second buffer, so the host copies exactly the bytes that go out and one small index.
 *
 * A frame is cut into pieces, one per encoded cloth (a row of the table, in the frame plan's row
 * order, which is the publications' order): the bytes in front of its state (a bundle's header
 * and its entry's header for a bundle's first cloth, the entry's header for the others, nothing
 * for a single state), then the state padded to 8 bytes. Every piece starts at a multiple of 8
 * in both buffers, so a publication is the run of its cloths' pieces (a single state: its piece
 * cut to the state's real size on the host).
 *
 *   compact_scan  one work-group: each work-item takes a contiguous share of the rows, reads
 *                 each state's real size (a predictive state's from its data_size field, the
 *                 others' from the table), sums its pieces' lengths; a scan of the work-items'
 *                 sums in local memory gives each share's start, and each work-item writes its
 *                 pieces' offsets. index[r] = piece r's byte offset in the compacted frame,
 *                 index[rows] = the compacted frame's size, index[rows + 1 + r] = state r's size.
 *   compact_copy  one work-group per piece: its 8-byte words copied to their offset.
 *
 * Build options (-D): CMP_WG (compact_scan's work-group size, a power of two), PH_SIZE (the
 * predictive header's data_size offset in a state, from drape.client.protocol as encode.cl's).
 */

#ifndef PH_SIZE
#error "compact.cl needs PH_SIZE (the data_size field's offset) as a -D option (see compact.py)"
#endif
#ifndef CMP_WG
#define CMP_WG 64
#endif

/* Table of pieces: CMP_ROW_WORDS uints per encoded cloth (parsed by compact.py, the one copy). */
#define CMP_ROW_WORDS 4
#define CMP_ROW_SRC 0    /* byte offset of the piece in the encoded frame (a multiple of 8) */
#define CMP_ROW_PREFIX 1 /* bytes in front of the state: bundle and entry headers (a multiple of 8) */
#define CMP_ROW_SIZE 2   /* the state's size; predictive: its bytes besides the data (header, normals) */
#define CMP_ROW_PRED 3   /* 1: a predictive state, whose data_size field adds to CMP_ROW_SIZE */

static uint state_size(__global const uchar *frame, __global const uint *row)
{
    uint size = row[CMP_ROW_SIZE];
    if (row[CMP_ROW_PRED]) {
        __global const uchar *f = frame + row[CMP_ROW_SRC] + row[CMP_ROW_PREFIX] + PH_SIZE;
        size += (uint)f[0] | ((uint)f[1] << 8) | ((uint)f[2] << 16) | ((uint)f[3] << 24);
    }
    return size;
}

__kernel __attribute__((reqd_work_group_size(CMP_WG, 1, 1))) void compact_scan(
    const uint rows,
    __global const uint *table,  /* CMP_ROW_WORDS per row */
    __global const uchar *frame, /* the encoded frame (slots of the largest size) */
    __global uint *index)        /* 2 rows + 1: offsets, total, sizes */
{
    __local uint part[CMP_WG];
    const uint lid = get_local_id(0);
    const uint per = (rows + CMP_WG - 1) / CMP_WG;
    const uint a = min(rows, lid * per), b = min(rows, a + per);
    uint sum = 0;
    for (uint r = a; r < b; ++r) {
        __global const uint *row = table + r * CMP_ROW_WORDS;
        const uint s = state_size(frame, row);
        index[rows + 1 + r] = s;
        sum += row[CMP_ROW_PREFIX] + ((s + 7u) & ~7u);
    }
    part[lid] = sum;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (uint d = 1; d < CMP_WG; d <<= 1) { /* inclusive scan of the shares (Hillis-Steele) */
        const uint v = lid >= d ? part[lid - d] : 0u;
        barrier(CLK_LOCAL_MEM_FENCE);
        part[lid] += v;
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    uint at = part[lid] - sum;
    for (uint r = a; r < b; ++r) {
        index[r] = at;
        at += table[r * CMP_ROW_WORDS + CMP_ROW_PREFIX] + ((index[rows + 1 + r] + 7u) & ~7u);
    }
    if (lid == CMP_WG - 1)
        index[rows] = part[lid];
}

__kernel void compact_copy(
    const uint rows,
    __global const uint *table,
    __global const ulong *frame,
    __global const uint *index,
    __global ulong *packed)      /* the compacted frame */
{
    const uint r = get_group_id(0);
    __global const uint *row = table + r * CMP_ROW_WORDS;
    const uint words = (row[CMP_ROW_PREFIX] + ((index[rows + 1 + r] + 7u) & ~7u)) >> 3;
    __global const ulong *src = frame + (row[CMP_ROW_SRC] >> 3);
    __global ulong *dst = packed + (index[r] >> 3);
    for (uint w = get_local_id(0); w < words; w += get_local_size(0))
        dst[w] = src[w];
}
