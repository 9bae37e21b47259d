/* The frame encoded on the device: every published cloth's binary state (PROTOCOL.md section 9)
 * written straight into one packed output buffer laid out per publication (single states and
 * section 9.1 bundles), so the host reads back one buffer and publishes slices of it.
 *
 * The host (drape.server.sim.opencl.encode) writes every static word once into the output
 * buffer (magics, versions, header sizes, encodings, vertex counts, bundle entry tables, cloth
 * ids and their padding: kernels/static.cl); per tick encode_frame writes the dynamic fields (a
 * state's flags, tick, server time and bounds, a bundle header's tick and server time), the
 * vertex data and every other byte of each state it codes, the padding to 8 bytes included
 * (a predictive state's: its width bytes' padding too), so that the buffer needs no zero fill
 * when a plan change keeps it (bytes of a predictive slot past its real size are never sent).
 *
 * One work-group per encoded cloth (a row of the table), one launch for the whole frame:
 *   1. per-axis min/max of the cloth's positions reduced in local memory (NaN propagates, as in
 *      numpy's min/max, so a non-finite cloth shows as non-finite bounds);
 *   2. work-item 0 writes the header's dynamic fields (and its bundle's, if it opens one);
 *   3. every work-item encodes a strided share of the vertices, then of the normals.
 *
 * Encodings (byte-exact with drape.client.protocol.encode_state):
 *   float32  as is;
 *   float16  clamped to +-65504, IEEE half round-to-nearest-even (vstore_half_rte, or
 *            half4_rte with ENC_SOFT_HALF); normals unclamped;
 *   quant16  q = rint(clamp((x - min) * (65535 / (max - min)), 0, 65535)) evaluated in double
 *            from the float32 bounds (q = 0 where max == min); normals rint(clamp(n, -1, 1) * 32767).
 *            With ENC_FP64 0 (a device without cl_khr_fp64) the same formulas run in float and a
 *            value can differ from the reference by 1 (see encode.py, QUANT16_FP32_TOLERANCE).
 *
 *   predictive (1.5, PROTOCOL.md 9.2; byte-exact with drape.client.protocol.predictive.pack_frame):
 *            each vertex quantised on the step's grid (q = clamp(rint(x * inv_step)), float32
 *            product) into this tick's history slot qcur (3 ints per vertex, at the row's
 *            history base: the position-buffer vertex, or a decimated streams' encoder's own;
 *            the history is slots of `hcap` vertices, each one tick's grid values, the row's
 *            slots chosen per cloth by the host);
 *            the prediction of the order the host chose (0: none, 1: q1, 2: 2 q1 - q2 from the
 *            two states the decoders hold, the slots q1 and q2); the residual's
 *            neighbour difference zig-zagged; blocks of 32 symbols per axis, each block's width
 *            (bit length of the OR of its symbols), then every block's words at the offset the
 *            work-group's prefix sum of widths gives. A predictive state is written into a
 *            slot of its largest size (the plan's): one launch, no frame-wide prefix sum; its
 *            real size goes into its data_size field (and its bundle entry's state size), the
 *            normals (snorm16) follow its data and zeros pad it to 8 bytes. compact.cl then
 *            writes the frame's wire bytes back to back (two launches behind this one).
 *
 * Build options (-D): ENC_WG (work-group size, a power of two), ENC_FP64 (0/1), ENC_STRIDE
 * (floats per vertex in the position and normal buffers, xyz first: 4 for the world's float4
 * buffers, w ignored; 3 for packed xyz rows), ENC_SOFT_HALF (1: float16 by integer SIMD instead
 * of vstore_half_rte, faster on CPUs), and the protocol's header offsets and constants (below).
 */

/* Table of encoded cloths: ENC_ROW_WORDS uints per row (parsed by encode.py, the one copy). */
#define ENC_ROW_WORDS 10
#define ENC_ROW_VBASE 0      /* first vertex of the cloth in the positions / normals buffers */
#define ENC_ROW_N 1          /* vertex count */
#define ENC_ROW_ENC 2        /* protocol encoding id: 0 float32, 1 float16, 2 quant16 */
#define ENC_ROW_NORMALS 3    /* 1: normals follow the positions */
#define ENC_ROW_STATE 4      /* byte offset of the state payload in the output (a multiple of 8) */
#define ENC_ROW_BUNDLE 5     /* byte offset of the bundle header this cloth opens, or ENC_NONE */
#define ENC_ROW_CLOTH 6      /* index of the cloth in the plan (into the per-tick flags) */
#define ENC_ROW_ENTRY 7      /* predictive: byte offset of its bundle entry's state size, or ENC_NONE */
#define ENC_ROW_INVSTEP 8    /* predictive: float32 bits of 1 / step (predictive.inverse_step) */
#define ENC_ROW_HIST 9       /* predictive: first vertex of the cloth in the history slots */
#define ENC_NONE 4294967295
#define ENC_PRED_WORDS 4     /* predictive, per plan cloth (ulong): order, ref tick, ref2 tick, history slots */
#define ENC_SLOT_BITS 8      /* the slots word: this tick's slot, ref's << 8, ref2's << 16 */

/* Header field offsets and protocol constants come from drape.client.protocol (the one copy of
 * the wire layout): encode.py finds them in the protocol's structs and passes them as -D. */
#if !defined(ST_FLAGS) || !defined(ST_TICK) || !defined(ST_TIME) || !defined(ST_MIN) || !defined(ST_MAX) \
    || !defined(ST_DATA) || !defined(BH_TICK) || !defined(BH_TIME) || !defined(FLAG_NORMALS) \
    || !defined(FLOAT16_MAX) || !defined(QUANT_MAX) || !defined(SNORM_MAX) || !defined(ENC_PREDICTIVE) \
    || !defined(PH_ORDER) || !defined(PH_REF1) || !defined(PH_REF2) || !defined(PH_SIZE) || !defined(PH_DATA) \
    || !defined(BE_SIZE) || !defined(Q_CLAMP) || !defined(Q_LIMIT)
#error "encode.cl needs the protocol's header offsets and constants as -D options (see encode.py)"
#endif

#ifndef ENC_WG
#define ENC_WG 64
#endif
#ifndef ENC_FP64
#define ENC_FP64 0
#endif
#ifndef ENC_STRIDE
#define ENC_STRIDE 4
#endif
#ifndef ENC_SOFT_HALF
#define ENC_SOFT_HALF 0
#endif

#if ENC_STRIDE == 4
#define LOAD3(buf, i) (((__global const float4 *)(buf))[i].xyz)
#elif ENC_STRIDE == 3
#define LOAD3(buf, i) vload3((i), (buf))
#else
#error "ENC_STRIDE must be 4 (float4 vertices) or 3 (packed xyz)"
#endif

#if ENC_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif
/* No fused multiply-adds: the reference rounds every operation on its own. */
#pragma OPENCL FP_CONTRACT OFF

/* Lane-wise min / max that propagate NaN (numpy.minimum semantics) instead of ignoring it like
 * fmin: once an accumulator is NaN it stays NaN. float4 so that a CPU compiles them to SIMD
 * compares and blends (float3 scalarises). */
inline float4 nmin4(float4 a, float4 b) { return select(a, b, isnan(b) | (b < a)); }
inline float4 nmax4(float4 a, float4 b) { return select(a, b, isnan(b) | (b > a)); }

/* numpy.clip on every lane: NaN stays NaN. */
inline float4 clip4(float4 x, float lo, float hi)
{
    x = select(x, (float4)(lo), x < (float4)(lo));
    return select(x, (float4)(hi), x > (float4)(hi));
}

/* quant16 arithmetic in double (the reference's float64), or float without cl_khr_fp64 */
#if ENC_FP64
typedef double4 qreal4;
#define TO_QREAL4(x) convert_double4(x)
#else
typedef float4 qreal4;
#define TO_QREAL4(x) (x)
#endif

/* rint(clip((x - lo) * scale, 0, QUANT_MAX)): integral and in range, so the conversion is exact */
inline ushort4 quant4(float4 x, qreal4 lo, qreal4 scale)
{
    qreal4 d = (TO_QREAL4(x) - lo) * scale;
    d = select(d, (qreal4)(0), d < (qreal4)(0));
    d = select(d, (qreal4)(QUANT_MAX), d > (qreal4)(QUANT_MAX));
    return convert_ushort4(rint(d));
}

/* snorm16: rint(clip(n, -1, 1) * SNORM_MAX); clipping before the exact widening is the same */
inline short4 snorm4(float4 n)
{
    return convert_short4(rint(TO_QREAL4(clip4(n, -1.0f, 1.0f)) * (qreal4)(SNORM_MAX)));
}

/* float -> IEEE half bits, round to nearest even, on 4 lanes with integer SIMD: numpy's
 * npy_floatbits_to_halfbits bit for bit (subnormals, overflow to infinity, NaN payloads). For
 * CPUs, where vstore_half_rte is a scalar library routine; GPUs convert in hardware. */
inline ushort4 half4_rte(float4 x)
{
    uint4 f = as_uint4(x);
    uint4 sign = (f >> 16) & (uint4)(0x8000u);
    uint4 a = f & (uint4)(0x7fffffffu);
    uint4 one = (uint4)(1u), zero = (uint4)(0u);
    /* normal halves: rebias the exponent, round the 13 dropped bits (a carry may reach inf) */
    uint4 hn = (a - (uint4)(0x38000000u)) >> 13;
    uint4 rn = a & (uint4)(0x1fffu);
    hn += select(zero, one, (rn > (uint4)(0x1000u)) | ((rn == (uint4)(0x1000u)) & ((hn & one) == one)));
    /* subnormal halves (2^-25 < |x| < 2^-14): the significand shifted right by 126 - exponent */
    uint4 e = clamp(a >> 23, (uint4)(102u), (uint4)(125u));
    uint4 sh = (uint4)(126u) - e;
    uint4 m = (a & (uint4)(0x7fffffu)) | (uint4)(0x800000u);
    uint4 hs = m >> sh;
    uint4 rs = m & ((one << sh) - one);
    uint4 hv = one << (sh - one);
    hs += select(zero, one, (rs > hv) | ((rs == hv) & ((hs & one) == one)));
    uint4 h = select(hn, hs, a < (uint4)(0x38800000u));
    h = select(h, zero, a <= (uint4)(0x33000000u));
    h = select(h, (uint4)(0x7c00u), a >= (uint4)(0x477ff000u));
    uint4 nan = (uint4)(0x7c00u) + ((a & (uint4)(0x7fffffu)) >> 13);
    nan = select(nan, (uint4)(0x7c01u), nan == (uint4)(0x7c00u));
    h = select(h, nan, a > (uint4)(0x7f800000u));
    return convert_ushort4(h | sign);
}

#if ENC_SOFT_HALF
#define STORE_HALF3(x4, v, o) vstore3(half4_rte(x4).xyz, (v), (__global ushort *)(o))
#else
#define STORE_HALF3(x4, v, o) vstore_half3_rte((x4).xyz, (v), (o))
#endif

/* a vertex as float4 whose w repeats x (so that w, the world's inverse mass, never enters) */
inline float4 load4(__global const float *buf, uint i)
{
    float3 p = LOAD3(buf, i);
    return (float4)(p, p.x);
}

/* predictive: grid value of one coordinate, predictive.quantise (rint ties to even; the clamp
 * to +-2^27 exact in float, then to +-Q_LIMIT in int) */
inline int3 quantise3(float3 x, float inv)
{
    float3 q = rint(x * inv);
    q = clamp(q, (float3)(-(float)Q_CLAMP), (float3)((float)Q_CLAMP));
    return clamp(convert_int3(q), (int3)(-Q_LIMIT), (int3)(Q_LIMIT));
}

/* predictive: the residual of coordinate a of vertex v against the order's prediction */
inline int residual(__global const int *qc, __global const int *h1, __global const int *h2, uint i, uint order)
{
    int q = qc[i];
    if (order == 0)
        return q;
    if (order == 1)
        return q - h1[i];
    return q - (2 * h1[i] - h2[i]);
}

/* predictive: the 32 symbols of block b (axis b / nb) of a cloth of n vertices at vertex base vb
 * (each residual loaded once: the neighbour difference runs along the block) */
inline void block_symbols(__global const int *qc, __global const int *h1, __global const int *h2, uint vb, uint n,
                          uint nb, uint order, uint b, uint *z)
{
    uint a = b / nb;
    uint v0 = (b - a * nb) * 32;
    int prev = v0 > 0 ? residual(qc, h1, h2, (vb + v0 - 1) * 3 + a, order) : 0;
    for (uint j = 0; j < 32; j++) {
        uint v = v0 + j;
        if (v >= n) {
            z[j] = 0;
            continue;
        }
        int r = residual(qc, h1, h2, (vb + v) * 3 + a, order);
        int d = r - prev;
        prev = r;
        z[j] = ((uint)d << 1) ^ (uint)(d >> 31);
    }
}

/* zeros from byte `end` of a state up to the next multiple of 8 (the state starts at one): every
 * byte of a state is written on every encode, so a buffer kept across plans needs no zero fill */
inline void pad8(__global uchar *st, uint end)
{
    for (uint e = end; e & 7; e++)
        st[e] = 0;
}

__kernel void encode_frame(
    __global const float *pos,         /* ENC_STRIDE floats per vertex */
    __global const float *nrm,         /* the same layout; any buffer when no row has normals */
    __global const uint *table,        /* ENC_ROW_WORDS per row */
    __global const ushort *cloth_flags, /* per plan cloth, this tick's state flags */
    const ulong tick,
    const ulong time_ns,
    __global uchar *out,
    __global const ulong *pred,        /* predictive: per plan cloth ENC_PRED_WORDS */
    __global int *hist,                /* predictive: history slots of hcap vertices, 3 ints each */
    const uint hcap)
{
    __local float4 lmin[ENC_WG];
    __local float4 lmax[ENC_WG];
    __local uint lsum[ENC_WG + 1];
    const uint row = get_group_id(0);
    const uint lid = get_local_id(0);
    __global const uint *r = table + row * ENC_ROW_WORDS;
    const uint vbase = r[ENC_ROW_VBASE];
    const uint n = r[ENC_ROW_N];
    const uint enc = r[ENC_ROW_ENC];
    const uint has_nrm = r[ENC_ROW_NORMALS];
    const uint so = r[ENC_ROW_STATE];

    /* 1. bounds (lane w repeats x: the world's w, the inverse mass, never enters) */
    float4 mn = (float4)(INFINITY), mx = (float4)(-INFINITY);
    for (uint v = lid; v < n; v += ENC_WG) {
        float4 p = load4(pos, vbase + v);
        mn = nmin4(mn, p);
        mx = nmax4(mx, p);
    }
    lmin[lid] = mn;
    lmax[lid] = mx;
    barrier(CLK_LOCAL_MEM_FENCE);
    for (uint s = ENC_WG / 2; s > 0; s >>= 1) {
        if (lid < s) {
            lmin[lid] = nmin4(lmin[lid], lmin[lid + s]);
            lmax[lid] = nmax4(lmax[lid], lmax[lid + s]);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    float3 lo = n ? lmin[0].xyz : (float3)(0.0f);
    float3 hi = n ? lmax[0].xyz : (float3)(0.0f);

    /* 2. header */
    __global uchar *st = out + so;
    if (lid == 0) {
        ushort f = cloth_flags[r[ENC_ROW_CLOTH]];
        f = has_nrm ? (ushort)(f | FLAG_NORMALS) : (ushort)(f & ~FLAG_NORMALS);
        *(__global ushort *)(st + ST_FLAGS) = f;
        *(__global ulong *)(st + ST_TICK) = tick;
        *(__global ulong *)(st + ST_TIME) = time_ns;
        vstore3(lo, 0, (__global float *)(st + ST_MIN));
        vstore3(hi, 0, (__global float *)(st + ST_MAX));
        uint bo = r[ENC_ROW_BUNDLE];
        if (bo != ENC_NONE) {
            *(__global ulong *)(out + bo + BH_TICK) = tick;
            *(__global ulong *)(out + bo + BH_TIME) = time_ns;
        }
    }

    /* 3. vertex data, then normals, then zeros up to 8 bytes */
    __global uchar *data = st + ST_DATA;
    if (lid == 0 && enc != ENC_PREDICTIVE)
        pad8(st, ST_DATA + (enc == 0 ? 12u : 6u) * n * (has_nrm ? 2u : 1u));
    if (enc == 0) {
        __global float *o = (__global float *)data;
        for (uint v = lid; v < n; v += ENC_WG)
            vstore3(LOAD3(pos, vbase + v), v, o);
        if (has_nrm) {
            o += 3 * n;
            for (uint v = lid; v < n; v += ENC_WG)
                vstore3(LOAD3(nrm, vbase + v), v, o);
        }
    } else if (enc == 1) {
        __global half *o = (__global half *)data;
        for (uint v = lid; v < n; v += ENC_WG)
            STORE_HALF3(clip4(load4(pos, vbase + v), -(float)FLOAT16_MAX, (float)FLOAT16_MAX), v, o);
        if (has_nrm) {
            o += 3 * n;
            for (uint v = lid; v < n; v += ENC_WG)
                STORE_HALF3(load4(nrm, vbase + v), v, o);
        }
    } else if (enc == ENC_PREDICTIVE) {
        const float inv = as_float(r[ENC_ROW_INVSTEP]);
        const uint ci = r[ENC_ROW_CLOTH];
        __global const ulong *pc = pred + ENC_PRED_WORDS * ci;
        const uint order = (uint)pc[0];
        const uint slots = (uint)pc[3], smask = (1u << ENC_SLOT_BITS) - 1;
        __global int *qcur = hist + (size_t)3 * hcap * (slots & smask);
        __global const int *q1 = hist + (size_t)3 * hcap * ((slots >> ENC_SLOT_BITS) & smask);
        __global const int *q2 = hist + (size_t)3 * hcap * ((slots >> (2 * ENC_SLOT_BITS)) & smask);
        const uint hb = r[ENC_ROW_HIST];
        __global uchar *pd = st + PH_DATA;
        for (uint v = lid; v < n; v += ENC_WG)
            vstore3(quantise3(LOAD3(pos, vbase + v), inv), hb + v, qcur);
        barrier(CLK_GLOBAL_MEM_FENCE);
        const uint nb = (n + 31) / 32, nblk = 3 * nb;
        const uint head = 4 * ((nblk + 3) / 4);
        if (lid == 0)
            for (uint b = nblk; b < head; b++) /* the widths' zeros up to the first word */
                pd[b] = 0;
        /* each work-item a contiguous share of the blocks: their widths, then their words */
        const uint per = (nblk + ENC_WG - 1) / ENC_WG;
        const uint b0 = min(lid * per, nblk), b1 = min(b0 + per, nblk);
        uint wsum = 0;
        uint z[32];
        for (uint b = b0; b < b1; b++) {
            block_symbols(qcur, q1, q2, hb, n, nb, order, b, z);
            uint m = 0;
            for (uint j = 0; j < 32; j++)
                m |= z[j];
            uint w = 32 - clz(m);
            pd[b] = (uchar)w;
            wsum += w;
        }
        lsum[lid] = wsum;
        barrier(CLK_LOCAL_MEM_FENCE);
        if (lid == 0) {
            uint acc = 0;
            for (uint i = 0; i < ENC_WG; i++) {
                uint t = lsum[i];
                lsum[i] = acc;
                acc += t;
            }
            lsum[ENC_WG] = acc;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        __global uint *words = (__global uint *)(pd + head) + lsum[lid];
        for (uint b = b0; b < b1; b++) {
            uint w = pd[b];
            if (!w)
                continue;
            block_symbols(qcur, q1, q2, hb, n, nb, order, b, z);
            uint cur = 0, fill = 0;
            for (uint j = 0; j < 32; j++) {
                cur |= z[j] << fill;
                fill += w;
                if (fill >= 32) {
                    *words++ = cur;
                    fill -= 32;
                    cur = fill ? z[j] >> (w - fill) : 0u;
                }
            }
        }
        const uint dsize = head + 4 * lsum[ENC_WG];
        if (has_nrm) {
            __global short *on = (__global short *)(pd + dsize);
            for (uint v = lid; v < n; v += ENC_WG)
                vstore3(snorm4(load4(nrm, vbase + v)).xyz, v, on);
        }
        if (lid == 0) {
            st[PH_ORDER] = (uchar)order;
            *(__global ulong *)(st + PH_REF1) = pc[1];
            *(__global ulong *)(st + PH_REF2) = pc[2];
            *(__global uint *)(st + PH_SIZE) = dsize;
            const uint size = PH_DATA + dsize + (has_nrm ? 6 * n : 0);
            uint eo = r[ENC_ROW_ENTRY];
            if (eo != ENC_NONE)
                *(__global uint *)(out + eo) = size;
            pad8(st, size);
        }
    } else {
        float4 lo4 = (float4)(lo, lo.x), hi4 = (float4)(hi, hi.x);
        qreal4 l = TO_QREAL4(lo4);
        qreal4 e = TO_QREAL4(hi4) - l;
        qreal4 sc = select((qreal4)(0), (qreal4)(QUANT_MAX) / e, e > (qreal4)(0));
        __global ushort *o = (__global ushort *)data;
        for (uint v = lid; v < n; v += ENC_WG)
            vstore3(quant4(load4(pos, vbase + v), l, sc).xyz, v, o);
        if (has_nrm) {
            __global short *on = (__global short *)(o + 3 * n);
            for (uint v = lid; v < n; v += ENC_WG)
                vstore3(snorm4(load4(nrm, vbase + v)).xyz, v, on);
        }
    }
}
