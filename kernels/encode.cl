/* The frame encoded on the device: every published cloth's binary state (PROTOCOL.md section 9)
 * written straight into one packed output buffer laid out per publication (single states and
 * section 9.1 bundles), so the host reads back one buffer and publishes slices of it.
 *
 * The host (drape.server.sim.opencl.encode) writes every static byte once into the output
 * buffer (magics, versions, header sizes, encodings, vertex counts, bundle entry tables, cloth
 * ids, zero padding); per tick encode_frame writes only the dynamic fields: a state's flags,
 * tick, server time and bounds, a bundle header's tick and server time, and the vertex data.
 *
 * One work-group per encoded cloth (a row of the table), one launch for the whole frame:
 *   1. per-axis min/max of the cloth's positions reduced in local memory (NaN propagates, as in
 *      numpy's min/max, so a non-finite cloth shows as non-finite bounds);
 *   2. work-item 0 writes the header's dynamic fields (and its bundle's, if it opens one);
 *   3. every work-item encodes a strided share of the vertices, then of the normals.
 *
 * Encodings (byte-exact with drape.client.protocol.encode_state):
 *   float32  as is;
 *   float16  clamped to +-65504, IEEE half round-to-nearest-even (vstore_half_rte); normals
 *            unclamped;
 *   quant16  q = rint(clamp((x - min) * (65535 / (max - min)), 0, 65535)) evaluated in double
 *            from the float32 bounds (q = 0 where max == min); normals rint(clamp(n, -1, 1) * 32767).
 *            With ENC_FP64 0 (a device without cl_khr_fp64) the same formulas run in float and a
 *            value can differ from the reference by 1 (see encode.py, QUANT16_FP32_TOLERANCE).
 *
 * Build options (-D): ENC_WG (work-group size, a power of two), ENC_FP64 (0/1), ENC_STRIDE
 * (floats per vertex in the position and normal buffers: 4 or 3), and the
 * protocol's header offsets and constants (below).
 * Positions and normals: ENC_STRIDE floats per vertex, xyz first: 4 for the world's float4
 * buffers (w ignored), 3 for packed xyz rows.
 */

/* Table of encoded cloths: ENC_ROW_WORDS uints per row (parsed by encode.py, the one copy). */
#define ENC_ROW_WORDS 8
#define ENC_ROW_VBASE 0      /* first vertex of the cloth in the positions / normals buffers */
#define ENC_ROW_N 1          /* vertex count */
#define ENC_ROW_ENC 2        /* protocol encoding id: 0 float32, 1 float16, 2 quant16 */
#define ENC_ROW_NORMALS 3    /* 1: normals follow the positions */
#define ENC_ROW_STATE 4      /* byte offset of the state payload in the output (a multiple of 8) */
#define ENC_ROW_BUNDLE 5     /* byte offset of the bundle header this cloth opens, or ENC_NONE */
#define ENC_ROW_CLOTH 6      /* index of the cloth in the plan (into the per-tick flags) */
#define ENC_NONE 4294967295

/* Header field offsets and protocol constants come from drape.client.protocol (the one copy of
 * the wire layout): encode.py finds them in the protocol's structs and passes them as -D. */
#if !defined(ST_FLAGS) || !defined(ST_TICK) || !defined(ST_TIME) || !defined(ST_MIN) || !defined(ST_MAX) \
    || !defined(ST_DATA) || !defined(BH_TICK) || !defined(BH_TIME) || !defined(FLAG_NORMALS) \
    || !defined(FLOAT16_MAX) || !defined(QUANT_MAX) || !defined(SNORM_MAX)
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

/* min / max that propagate NaN (numpy.minimum semantics) instead of ignoring it like fmin. */
inline float nmin(float a, float b) { return (isnan(b) || b < a) ? b : a; }
inline float nmax(float a, float b) { return (isnan(b) || b > a) ? b : a; }
inline float3 nmin3(float3 a, float3 b) { return (float3)(nmin(a.x, b.x), nmin(a.y, b.y), nmin(a.z, b.z)); }
inline float3 nmax3(float3 a, float3 b) { return (float3)(nmax(a.x, b.x), nmax(a.y, b.y), nmax(a.z, b.z)); }

/* numpy.clip: NaN stays NaN. */
inline float clipf(float x, float lo, float hi) { return x < lo ? lo : (x > hi ? hi : x); }

#if ENC_FP64
typedef double qreal;
#else
typedef float qreal;
#endif

inline ushort quant(float x, qreal lo, qreal scale)
{
    qreal d = ((qreal)x - lo) * scale;
    d = d < (qreal)0 ? (qreal)0 : (d > (qreal)QUANT_MAX ? (qreal)QUANT_MAX : d);
    return (ushort)rint(d);
}

inline short snorm(float n)
{
    qreal c = (qreal)clipf(n, -1.0f, 1.0f);
    return (short)rint(c * (qreal)SNORM_MAX);
}

__kernel void encode_frame(
    __global const float *pos,         /* ENC_STRIDE floats per vertex */
    __global const float *nrm,         /* the same layout; any buffer when no row has normals */
    __global const uint *table,        /* ENC_ROW_WORDS per row */
    __global const ushort *cloth_flags, /* per plan cloth, this tick's state flags */
    const ulong tick,
    const ulong time_ns,
    __global uchar *out)
{
    __local float4 lmin[ENC_WG];
    __local float4 lmax[ENC_WG];
    const uint row = get_group_id(0);
    const uint lid = get_local_id(0);
    __global const uint *r = table + row * ENC_ROW_WORDS;
    const uint vbase = r[ENC_ROW_VBASE];
    const uint n = r[ENC_ROW_N];
    const uint enc = r[ENC_ROW_ENC];
    const uint has_nrm = r[ENC_ROW_NORMALS];
    const uint so = r[ENC_ROW_STATE];

    /* 1. bounds */
    float3 mn = (float3)(INFINITY), mx = (float3)(-INFINITY);
    for (uint v = lid; v < n; v += ENC_WG) {
        float3 p = LOAD3(pos, vbase + v);
        mn = nmin3(mn, p);
        mx = nmax3(mx, p);
    }
    lmin[lid] = (float4)(mn, 0.0f);
    lmax[lid] = (float4)(mx, 0.0f);
    barrier(CLK_LOCAL_MEM_FENCE);
    for (uint s = ENC_WG / 2; s > 0; s >>= 1) {
        if (lid < s) {
            lmin[lid] = (float4)(nmin3(lmin[lid].xyz, lmin[lid + s].xyz), 0.0f);
            lmax[lid] = (float4)(nmax3(lmax[lid].xyz, lmax[lid + s].xyz), 0.0f);
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

    /* 3. vertex data, then normals */
    __global uchar *data = st + ST_DATA;
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
        for (uint v = lid; v < n; v += ENC_WG) {
            float3 p = LOAD3(pos, vbase + v);
            p = (float3)(clipf(p.x, -(float)FLOAT16_MAX, (float)FLOAT16_MAX), clipf(p.y, -(float)FLOAT16_MAX, (float)FLOAT16_MAX),
                         clipf(p.z, -(float)FLOAT16_MAX, (float)FLOAT16_MAX));
            vstore_half3_rte(p, v, o);
        }
        if (has_nrm) {
            o += 3 * n;
            for (uint v = lid; v < n; v += ENC_WG)
                vstore_half3_rte(LOAD3(nrm, vbase + v), v, o);
        }
    } else {
        qreal l[3] = {(qreal)lo.x, (qreal)lo.y, (qreal)lo.z};
        qreal e[3] = {(qreal)hi.x - l[0], (qreal)hi.y - l[1], (qreal)hi.z - l[2]};
        qreal sc[3];
        for (int a = 0; a < 3; a++)
            sc[a] = e[a] > (qreal)0 ? (qreal)QUANT_MAX / e[a] : (qreal)0;
        __global ushort *o = (__global ushort *)data;
        for (uint v = lid; v < n; v += ENC_WG) {
            float3 p = LOAD3(pos, vbase + v);
            vstore3((ushort3)(quant(p.x, l[0], sc[0]), quant(p.y, l[1], sc[1]), quant(p.z, l[2], sc[2])), v, o);
        }
        if (has_nrm) {
            __global short *on = (__global short *)(o + 3 * n);
            for (uint v = lid; v < n; v += ENC_WG) {
                float3 m = LOAD3(nrm, vbase + v);
                vstore3((short3)(snorm(m.x), snorm(m.y), snorm(m.z)), v, on);
            }
        }
    }
}
