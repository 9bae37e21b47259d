/* The CPU pack solver: one work-item steps a *pack* of up to PACK_LANES cloths of one fabric.
 *
 * Included by cloth.cl when built with -DPACK_LANES=W (CPU devices only; a GPU build never sees
 * this file). The cloths of a pack share their links, colours, iterations and substeps, so the
 * link solve runs once for all of them: positions sit in local memory lane-interleaved
 * (vertex v, component k, cloth j at sx[4 v + k].s[j]) and every link is one W-wide vector
 * computation with contiguous loads and stores, no gathers, no barriers. Per-cloth parameters
 * (stiffness, compliance, inverse masses) are per lane. Vertex normals and areas (wind, the
 * normals feature) are computed across the lanes too, from the same triangles. Unused lanes hold
 * zero positions and inverse masses: their links correct nothing.
 *
 * Per-substep vertex phases. Vectorised (`vec`): XPBD cloths without wind or colliders whose
 * multipliers are all 0 when read (compliance 0, or one iteration per substep: the presets) keep
 * their velocities in the lanes too, in the local memory the multipliers would take (3 floats a
 * vertex, where the fabric has at least 3 links a vertex, as a grid with shear links has), and
 * prediction, tethers, long-range links and velocities run across the lanes; positions and
 * velocities go back to global memory once per step. Otherwise the phases run lane by lane on
 * global memory with the functions every solver calls (integrate.cl), so every feature means
 * exactly what it means in wg_step; only the tethers run across the lanes there too, on the
 * positions in local memory (before and after the links: on a 32 x 32 cape, whose colliders keep
 * it off the vector path, lane-by-lane tethers were half of a substep's time).
 *
 * Self-collision runs lane by lane on global memory after the links (selfcollide.cl), as in
 * wg_step; with it the vectorised phases are off.
 *
 * Arithmetic per lane is wg_step's in the same order: tethers after the prediction, then per
 * iteration the long-range links and the links by colour, then the tethers again (PBD: the
 * talk's k; XPBD: the multiplier per link, reset every substep, after the positions in local
 * memory; with every multiplier 0 when read, link_xpbd's arithmetic without them).
 */
#define PCAT_(a, b) a##b
#define PCAT(a, b) PCAT_(a, b)
#define floatP PCAT(float, PACK_LANES)
#define intP PCAT(int, PACK_LANES)
#define vloadP PCAT(vload, PACK_LANES)

/* Lane j's vertex v in the pack's positions seen as floats (sxf): component k at
 * sxf[(4 v + k) PACK_LANES + j], i.e. sx[4 v + k].s[j]. */
inline void lane_put3(__local float *sxf, int v, int j, float3 x)
{
    sxf[(4 * v + 0) * PACK_LANES + j] = x.x;
    sxf[(4 * v + 1) * PACK_LANES + j] = x.y;
    sxf[(4 * v + 2) * PACK_LANES + j] = x.z;
}

inline void lane_put(__local float *sxf, int v, int j, float4 x)
{
    lane_put3(sxf, v, j, x.xyz);
    sxf[(4 * v + 3) * PACK_LANES + j] = x.w;
}

inline float3 lane_get3(__local const float *sxf, int v, int j)
{
    return (float3)(sxf[(4 * v + 0) * PACK_LANES + j], sxf[(4 * v + 1) * PACK_LANES + j],
                    sxf[(4 * v + 2) * PACK_LANES + j]);
}

/* The head of pack_step's loops over the lanes' cloths, as the first statement of
 * `for (int j = 0; j < PACK_LANES; ++j) { ... }`: skips an unused lane, else declares lane j's
 * cloth tables I and F, its first vertex vbase and its positions X (global memory). */
#define LANE_CLOTH(j)                                                                              \
    if (slot[j] < 0)                                                                               \
        continue;                                                                                  \
    __global const int *I = ci + slot[j] * CI_STRIDE;                                              \
    __global const float *F = cf + slot[j] * CF_STRIDE;                                            \
    const int vbase = I[CI_VBASE];                                                                 \
    __global float4 *X = pos + vbase;

/* 1 / sqrt(L) and 1 / d to about an ulp: the hardware estimates (native_*) refined by one
 * Newton step each, for the link loops (rsqrt and / cost two and one divisions' time each) */
inline floatP pack_rsqrt(floatP L)
{
    const floatP r = native_rsqrt(L);
    return r * (1.5f - 0.5f * L * r * r);
}

inline floatP pack_recip(floatP d)
{
    const floatP r = native_recip(d);
    return r * (2.0f - d * r);
}

/* one float of every lane's cloth table as a vector (0 in unused lanes) */
inline floatP lane_floats(__global const float *cf, const int *slot, int off)
{
    float t[PACK_LANES];
    for (int j = 0; j < PACK_LANES; ++j)
        t[j] = slot[j] >= 0 ? cf[slot[j] * CF_STRIDE + off] : 0.0f;
    return vloadP(0, t);
}

#if FEATURE_WIND || FEATURE_NORMALS
/* every lane's vertex normals and areas (vertex_normal's, vectorised across the lanes: the
 * lanes share the triangles) from the positions in sx, written to nrm lane by lane */
inline void pack_normals(__local const floatP *sx, __global const int *fb, __global const int *I0, int nv,
                         const int *vb, __global float4 *nrm)
{
    __global const int *vto = fb + I0[CI_OFF_VTRIOFF];
    __global const int *vt = fb + I0[CI_OFF_VTRI];
    __global const int *tris = fb + I0[CI_OFF_TRIS];
    float t[4][PACK_LANES];
    for (int v = 0; v < nv; ++v) {
        floatP nx = (floatP)(0.0f), ny = (floatP)(0.0f), nz = (floatP)(0.0f), a = (floatP)(0.0f);
        for (int k = vto[v]; k < vto[v + 1]; ++k) {
            const int tr = vt[k];
            __local const floatP *P0 = sx + 4 * tris[3 * tr], *P1 = sx + 4 * tris[3 * tr + 1];
            __local const floatP *P2 = sx + 4 * tris[3 * tr + 2];
            const floatP ax = P1[0] - P0[0], ay = P1[1] - P0[1], az = P1[2] - P0[2];
            const floatP bx = P2[0] - P0[0], by = P2[1] - P0[1], bz = P2[2] - P0[2];
            const floatP fx = ay * bz - az * by, fy = az * bx - ax * bz, fz = ax * by - ay * bx;
            nx += fx;
            ny += fy;
            nz += fz;
            a += 0.5f * sqrt(fx * fx + fy * fy + fz * fz) / 3.0f;
        }
        const floatP len = sqrt(nx * nx + ny * ny + nz * nz);
        const intP ok = len > 1e-30f;
        PCAT(vstore, PACK_LANES)(select((floatP)(0.0f), nx / len, ok), 0, t[0]);
        PCAT(vstore, PACK_LANES)(select((floatP)(0.0f), ny / len, ok), 0, t[1]);
        PCAT(vstore, PACK_LANES)(select((floatP)(0.0f), nz / len, ok), 0, t[2]);
        PCAT(vstore, PACK_LANES)(a, 0, t[3]);
        for (int j = 0; j < PACK_LANES; ++j)
            if (vb[j] >= 0)
                nrm[vb[j] + v] = (float4)(t[0][j], t[1][j], t[2][j], t[3][j]);
    }
}
#endif

#if FEATURE_TETHERS
/* every free vertex's tethers across the lanes (the lanes share the anchors; a lane's pinned
 * vertex has none), slot by slot: no further than its length times the lane's limit from each */
inline void pack_tethers(__local floatP *sx, __global const int *anc, const floatP tlim, int nv)
{
    for (int v = 0; v < nv; ++v) {
        __global const int *A = anc + ANCHOR_WORDS * v;
        __local floatP *P = sx + 4 * v;
        for (int t = 0; t < TETHER_SLOTS; ++t) {
            const int a = A[2 * t];
            if (a < 0)
                break;
            const floatP lim = as_float(A[2 * t + 1]) * tlim;
            __local const floatP *Q = sx + 4 * a;
            const floatP ax = Q[0], ay = Q[1], az = Q[2];
            const floatP dx = P[0] - ax, dy = P[1] - ay, dz = P[2] - az;
            const floatP L = dx * dx + dy * dy + dz * dz;
            const intP over = (L > lim * lim) & (P[3] > 0.0f);
            const floatP f = select((floatP)(1.0f), lim * pack_rsqrt(L), over);
            P[0] = ax + dx * f;
            P[1] = ay + dy * f;
            P[2] = az + dz * f;
        }
    }
}
#endif

__kernel void pack_step(const float dt, __global const int *packs, __global const int *ci, __global const float *cf,
                        __global const int *fab, __global float4 *pos, __global float4 *vel, __global float4 *prev,
                        __global const float4 *target, __global float4 *nrm, __global const float4 *coll,
                        __local floatP *sx)
{
    __global const int *lanes = packs + get_group_id(0) * PACK_LANES;
    __global const int *I0 = ci + lanes[0] * CI_STRIDE;
    __global const int *fb = fab + I0[CI_FAB];
    __global const int *links = fb + I0[CI_OFF_LINKS];
    __global const int *cols = fb + I0[CI_OFF_COLOURS];
    const int nv = I0[CI_NVERTS], ncol = I0[CI_NCOLOURS], iters = I0[CI_ITERS], S = I0[CI_SUBSTEPS];
    const float h = dt / (float)S;
    int slot[PACK_LANES];
    for (int j = 0; j < PACK_LANES; ++j)
        slot[j] = lanes[j];
    int vb[PACK_LANES]; /* each lane's first vertex, -1 for an unused lane */
    for (int j = 0; j < PACK_LANES; ++j)
        vb[j] = slot[j] >= 0 ? ci[slot[j] * CI_STRIDE + CI_VBASE] : -1;
    __local float *sxf = (__local float *)sx;
#if FEATURE_XPBD
    const int nl = I0[CI_NLINKS];
    __local floatP *slam = sx + 4 * nv; /* the pack's multipliers follow its positions */
    floatP alpha[3];
    for (int t = 0; t < 3; ++t)
        alpha[t] = lane_floats(cf, slot, CF_COMPLIANCE + t) / (h * h);
    /* every multiplier 0 when read: compliance 0 in every lane, or one iteration */
    const int zero = !any((alpha[0] != 0.0f) | (alpha[1] != 0.0f) | (alpha[2] != 0.0f));
    const int lamless = iters == 1 || zero;
#if !FEATURE_WIND && !FEATURE_COLLIDERS && !FEATURE_SELF_COLLISION
    const int vec = lamless && nl >= 3 * nv; /* velocities in the multipliers' place */
#else
    const int vec = 0;
#endif
#else
    floatP kst[3];
    for (int t = 0; t < 3; ++t)
        kst[t] = lane_floats(cf, slot, CF_STIFFNESS + t);
    const int vec = 0;
#endif
#if FEATURE_TETHERS
    __global const int *lrl = fb + I0[CI_OFF_LRLINKS];
    __global const int *lrc = fb + I0[CI_OFF_LRCOLOURS];
    __global const int *anc = fb + I0[CI_OFF_ANCHOR];
    const floatP tlim = lane_floats(cf, slot, CF_TETHER_LIMIT);
#endif
    for (int j = 0; j < PACK_LANES; ++j) {
        if ((vb[j] >= 0) & (vec == 0)) { /* & : vec is a constant 0 in some builds (no -Wconstant-logical-operand) */
#if !FEATURE_WIND /* predict fills the used lanes; wind's normals need them before */
            continue;
#endif
        }
        for (int v = 0; v < nv; ++v)
            lane_put(sxf, v, j, vb[j] >= 0 ? pos[vb[j] + v] : (float4)(0.0f)); /* unused: zero, w 0 */
    }
    /* vec: the velocities, lane-interleaved like the positions (sv[3 v + k].s[j]); between the
     * prediction and the velocity update they hold the substep's start positions instead */
    __local floatP *sv = sx + 4 * nv;
    __local float *svf = (__local float *)sv;
    floatP gx = (floatP)(0.0f), gy = (floatP)(0.0f), gz = (floatP)(0.0f), keep = (floatP)(0.0f);
    if (vec) {
        for (int j = 0; j < PACK_LANES; ++j)
            for (int v = 0; v < nv; ++v) {
                const float4 u = vb[j] >= 0 ? vel[vb[j] + v] : (float4)(0.0f);
                svf[(3 * v + 0) * PACK_LANES + j] = u.x;
                svf[(3 * v + 1) * PACK_LANES + j] = u.y;
                svf[(3 * v + 2) * PACK_LANES + j] = u.z;
            }
        gx = lane_floats(cf, slot, CF_GRAVITY) * h;
        gy = lane_floats(cf, slot, CF_GRAVITY + 1) * h;
        gz = lane_floats(cf, slot, CF_GRAVITY + 2) * h;
        keep = ((floatP)(1.0f) - lane_floats(cf, slot, CF_DAMP_SUB)) / h;
    }

    for (int s = 0; s < S; ++s) {
        if (vec) {
            /* predict across the lanes: free vertices fall, pinned ones (inverse mass 0 in a used
             * lane) move toward their targets */
            const float frac = 1.0f / (float)(S - s);
            for (int v = 0; v < nv; ++v) {
                __local floatP *P = sx + 4 * v;
                __local floatP *V = sv + 3 * v;
                const floatP x = P[0], y = P[1], z = P[2], w = P[3];
                /* V: the velocity at the step's start, else the last substep's start positions
                 * (its velocity, (x - start) / h damped, computed here in the same pass) */
                const floatP ux = s ? (x - V[0]) * keep : V[0];
                const floatP uy = s ? (y - V[1]) * keep : V[1];
                const floatP uz = s ? (z - V[2]) * keep : V[2];
                const floatP vx = ux + gx, vy = uy + gy, vz = uz + gz;
                V[0] = x;
                V[1] = y;
                V[2] = z;
                floatP nx = x + vx * h, ny = y + vy * h, nz = z + vz * h;
                const intP pin = w == 0.0f;
                if (any(pin)) {
                    float t[3][PACK_LANES];
                    for (int j = 0; j < PACK_LANES; ++j) {
                        const float4 tg = vb[j] >= 0 ? target[vb[j] + v] : (float4)(0.0f);
                        t[0][j] = tg.x;
                        t[1][j] = tg.y;
                        t[2][j] = tg.z;
                    }
                    nx = select(nx, x + (vloadP(0, t[0]) - x) * frac, pin);
                    ny = select(ny, y + (vloadP(0, t[1]) - y) * frac, pin);
                    nz = select(nz, z + (vloadP(0, t[2]) - z) * frac, pin);
                }
                P[0] = nx;
                P[1] = ny;
                P[2] = nz;
            }
#if FEATURE_TETHERS
            pack_tethers(sx, anc, tlim, nv);
#endif
        } else {
#if FEATURE_WIND
            pack_normals(sx, fb, I0, nv, vb, nrm); /* sx holds the positions at the substep's start */
#endif
            /* per lane: predict on global memory, then into the lanes */
            for (int j = 0; j < PACK_LANES; ++j) {
                LANE_CLOTH(j)
                for (int v = 0; v < nv; ++v)
                    X[v] = predict_vertex(X[v], vel, prev, target, nrm, vbase + v, F, h, S - s);
                for (int v = 0; v < nv; ++v)
                    lane_put(sxf, v, j, X[v]);
            }
#if FEATURE_TETHERS
            pack_tethers(sx, anc, tlim, nv); /* across the lanes, as tether_vertex per lane */
#endif
#if FEATURE_XPBD
            if (!lamless)
                for (int l = 0; l < nl; ++l)
                    slam[l] = (floatP)(0.0f);
#endif
        }

        for (int it = 0; it < iters; ++it) {
#if FEATURE_TETHERS
            /* long-range links, coarsest first: unilateral and hard (tethers.cl) */
            for (int l = lrc[1]; l < lrc[1 + lrc[0]]; ++l) {
                const int4 R = vload4(l, lrl);
                __local floatP *A = sx + 4 * R.x;
                __local floatP *B = sx + 4 * R.y;
                const floatP x0 = A[0], y0 = A[1], z0 = A[2], w0 = A[3];
                const floatP x1 = B[0], y1 = B[1], z1 = B[2], w1 = B[3];
                const floatP dx = x1 - x0, dy = y1 - y0, dz = z1 - z0;
                const floatP L = dx * dx + dy * dy + dz * dz;
                const floatP rl = as_float(R.w) * tlim;
                const floatP w = w0 + w1;
                const intP ok = (L > rl * rl) & (L > EPS_LEN2) & (w > EPS_DENOM);
                const floatP k = select((floatP)(0.0f), (rl * pack_rsqrt(L) - 1.0f) * pack_recip(w), ok);
                const floatP k0 = k * w0, k1 = k * w1;
                A[0] = x0 - dx * k0;
                A[1] = y0 - dy * k0;
                A[2] = z0 - dz * k0;
                B[0] = x1 + dx * k1;
                B[1] = y1 + dy * k1;
                B[2] = z1 + dz * k1;
            }
#endif
#if FEATURE_XPBD
            if (lamless && zero) {
                /* compliance 0 in every lane: k = (rl / len - 1) / (im0 + im1), PBD's cost */
                for (int col = 0; col < ncol; ++col) {
                    const int end = cols[col + 1];
                    for (int l = cols[col]; l < end; ++l) {
                        const int4 R = vload4(l, links);
                        const float rl = as_float(R.w);
                        __local floatP *A = sx + 4 * R.x;
                        __local floatP *B = sx + 4 * R.y;
                        const floatP x0 = A[0], y0 = A[1], z0 = A[2], w0 = A[3];
                        const floatP x1 = B[0], y1 = B[1], z1 = B[2], w1 = B[3];
                        const floatP dx = x1 - x0, dy = y1 - y0, dz = z1 - z0;
                        const floatP L = dx * dx + dy * dy + dz * dz;
                        const floatP denom = w0 + w1;
                        const intP ok = (L > EPS_LEN2) & (denom > EPS_DENOM);
                        const floatP k = select((floatP)(0.0f), (rl * pack_rsqrt(L) - 1.0f) * pack_recip(denom), ok);
                        const floatP k0 = k * w0, k1 = k * w1;
                        A[0] = x0 - dx * k0;
                        A[1] = y0 - dy * k0;
                        A[2] = z0 - dz * k0;
                        B[0] = x1 + dx * k1;
                        B[1] = y1 + dy * k1;
                        B[2] = z1 + dz * k1;
                    }
                }
                continue;
            }
            if (lamless) {
                /* link_xpbd with every multiplier 0: k = -C / (im0 + im1 + a~) / len along d */
                for (int col = 0; col < ncol; ++col) {
                    const int end = cols[col + 1];
                    for (int l = cols[col]; l < end; ++l) {
                        const int4 R = vload4(l, links);
                        const float rl = as_float(R.w);
                        __local floatP *A = sx + 4 * R.x;
                        __local floatP *B = sx + 4 * R.y;
                        const floatP x0 = A[0], y0 = A[1], z0 = A[2], w0 = A[3];
                        const floatP x1 = B[0], y1 = B[1], z1 = B[2], w1 = B[3];
                        const floatP dx = x1 - x0, dy = y1 - y0, dz = z1 - z0;
                        const floatP L = dx * dx + dy * dy + dz * dz;
                        const floatP a = alpha[R.z];
                        const floatP denom = w0 + w1 + a;
                        const intP ok = (L > EPS_LEN2) & (denom > EPS_DENOM) & !isinf(a);
                        const floatP k = select((floatP)(0.0f), (rl * pack_rsqrt(L) - 1.0f) * pack_recip(denom), ok);
                        const floatP k0 = k * w0, k1 = k * w1;
                        A[0] = x0 - dx * k0;
                        A[1] = y0 - dy * k0;
                        A[2] = z0 - dz * k0;
                        B[0] = x1 + dx * k1;
                        B[1] = y1 + dy * k1;
                        B[2] = z1 + dz * k1;
                    }
                }
                continue;
            }
#endif
            for (int col = 0; col < ncol; ++col) {
                const int end = cols[col + 1];
                for (int l = cols[col]; l < end; ++l) {
                    const int4 R = vload4(l, links);
                    const float rl = as_float(R.w);
                    __local floatP *A = sx + 4 * R.x;
                    __local floatP *B = sx + 4 * R.y;
                    const floatP x0 = A[0], y0 = A[1], z0 = A[2], w0 = A[3];
                    const floatP x1 = B[0], y1 = B[1], z1 = B[2], w1 = B[3];
                    const floatP dx = x1 - x0, dy = y1 - y0, dz = z1 - z0;
                    const floatP L = dx * dx + dy * dy + dz * dz;
#if FEATURE_XPBD
                    const floatP a = alpha[R.z];
                    const floatP denom = w0 + w1 + a;
                    const intP ok = (L > EPS_LEN2) & (denom > EPS_DENOM) & !isinf(a);
                    const floatP len = sqrt(L);
                    const floatP lam = slam[l];
                    const floatP dl = select((floatP)(0.0f), (-(len - rl) - a * lam) / denom, ok);
                    const floatP ux = select((floatP)(0.0f), dx / len, ok); /* along the unit direction */
                    const floatP uy = select((floatP)(0.0f), dy / len, ok);
                    const floatP uz = select((floatP)(0.0f), dz / len, ok);
                    slam[l] = lam + dl;
                    const floatP k0 = w0 * dl, k1 = w1 * dl;
#else
                    const float rl2 = rl * rl;
                    const floatP denom = (w0 + w1) * (rl2 + L);
                    const floatP k = select((floatP)(0.0f), kst[R.z] * (rl2 - L) / denom, denom > EPS_DENOM);
                    const floatP ux = dx, uy = dy, uz = dz; /* along the link itself */
                    const floatP k0 = k * w0, k1 = k * w1;
#endif
                    A[0] = x0 + -ux * k0;
                    A[1] = y0 + -uy * k0;
                    A[2] = z0 + -uz * k0;
                    B[0] = x1 + ux * k1;
                    B[1] = y1 + uy * k1;
                    B[2] = z1 + uz * k1;
                }
            }
        }

        if (vec) {
#if FEATURE_TETHERS
            pack_tethers(sx, anc, tlim, nv); /* and after the links */
#endif
            if (s == S - 1) { /* the step's last start positions, for whoever reads prev */
                for (int j = 0; j < PACK_LANES; ++j)
                    if (vb[j] >= 0)
                        for (int v = 0; v < nv; ++v)
                            prev[vb[j] + v] = (float4)(svf[(3 * v + 0) * PACK_LANES + j],
                                                       svf[(3 * v + 1) * PACK_LANES + j],
                                                       svf[(3 * v + 2) * PACK_LANES + j],
                                                       sxf[(4 * v + 3) * PACK_LANES + j]);
                /* the step's velocities across the lanes: (x - start) / h, damped (the other
                 * substeps' are the next prediction's) */
                for (int v = 0; v < nv; ++v) {
                    __local floatP *P = sx + 4 * v;
                    __local floatP *V = sv + 3 * v;
                    V[0] = (P[0] - V[0]) * keep;
                    V[1] = (P[1] - V[1]) * keep;
                    V[2] = (P[2] - V[2]) * keep;
                }
            }
            continue;
        }
#if FEATURE_TETHERS
        pack_tethers(sx, anc, tlim, nv); /* after the links, across the lanes (finish_vertex's) */
#endif
        /* per lane: out of the lanes, then colliders, velocities[, self-collision] on global memory */
        for (int j = 0; j < PACK_LANES; ++j) {
            LANE_CLOTH(j)
            for (int v = 0; v < nv; ++v)
                X[v].xyz = lane_get3(sxf, v, j);
            for (int v = 0; v < nv; ++v) {
                const float4 x = finish_vertex(X[v], X, fb, I, F, vel, prev, coll, v, vbase + v, h, s, S, 0);
                X[v] = x;
#if (FEATURE_WIND || FEATURE_NORMALS) && !FEATURE_SELF_COLLISION
                lane_put3(sxf, v, j, x.xyz); /* the normals read the lanes */
#endif
            }
#if FEATURE_SELF_COLLISION /* after the colliders' friction; one work-item: its barriers are trivially uniform */
            self_collide(X, vel + vbase, (__global int *)(nrm + vbase), fb + I[CI_OFF_REST], nv, F[CF_THICKNESS],
                         F[CF_CONTACT_STIFFNESS], 0, 1);
            for (int v = 0; v < nv; ++v) {
                X[v] = refinish_vertex(X[v], I, F, vel, prev, coll, vbase + v, h, s, S);
#if FEATURE_WIND || FEATURE_NORMALS
                lane_put3(sxf, v, j, X[v].xyz); /* the normals read the lanes */
#endif
            }
#endif
        }
    }
    if (vec) /* positions and velocities back to global memory, once per step */
        for (int j = 0; j < PACK_LANES; ++j)
            if (vb[j] >= 0)
                for (int v = 0; v < nv; ++v) {
                    pos[vb[j] + v] = (float4)(lane_get3(sxf, v, j), sxf[(4 * v + 3) * PACK_LANES + j]);
                    vel[vb[j] + v] = (float4)(svf[(3 * v + 0) * PACK_LANES + j], svf[(3 * v + 1) * PACK_LANES + j],
                                              svf[(3 * v + 2) * PACK_LANES + j], 0.0f);
                }

#if FEATURE_NORMALS
    pack_normals(sx, fb, I0, nv, vb, nrm);
#endif
}
