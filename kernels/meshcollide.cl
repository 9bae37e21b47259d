/* Triangle-mesh colliders (issue 22): cloth vertices kept out of a one-sided triangle mesh placed by
 * a rigid pose, at the cloth's thickness from its surface. The same steps as
 * drape.server.sim.meshes.collide_mesh (read its docstring first), once per step after every
 * cloth's own solve and the scenes' inter-cloth collision. Its own program, built and launched
 * only while a World has a cloth with a mesh (drape.server.sim.opencl.meshes): a World without
 * meshes pays nothing, and cloth.cl is built as before.
 *
 * Meshes (shared by every cloth that uses one: a scene's body is on the device once):
 *   mtri   4 float4 per triangle, in the mesh's frame: v0, e1 = v1 - v0, e2 = v2 - v0, unit normal
 *   mcell  per mesh, its grid's cell starts (cells + 1) into mlist; mlist: triangle indices
 *   minfo  int8 per mesh: (first triangle, triangles, first cell start, first list entry, dims x, y, z, -)
 *   mgeom  float4 per mesh: (grid origin xyz, 1 / cell edge)
 * Attachments (a cloth and a mesh; a cloth's own mesh and its scene's are launched apart):
 *   att    int4 per attachment: (first row in pos/vel, vertices, mesh, first row in start)
 *   apar   10 float4 per attachment: the pose at the step's start inverted (3 rows [R | t]),
 *          the pose now inverted (3 rows), the pose now (3 rows), (thickness, friction, fresh, -);
 *          fresh: 1 in the first step of a mesh set or re-posed (its deep vertices put out)
 *   start  the vertices' positions at the step's start (mc_save)
 * One work-group of MC_LS work-items per attachment, each a strided share of its vertices;
 * mc_collide is launched once per layer (a cloth's own meshes, then its scene's), from attachment
 * ``first``.
 */

#ifndef MC_LS
#define MC_LS 64
#endif
#ifndef MESH_PASSES
#define MESH_PASSES 2
#endif
#ifndef MESH_EDGE_TOLERANCE
#define MESH_EDGE_TOLERANCE 1e-5f
#endif
#ifndef MESH_SLIDES
#define MESH_SLIDES 2
#endif
#ifndef MESH_GUARD_BACKOFF
#define MESH_GUARD_BACKOFF 0.5f
#endif
#ifndef MESH_MAX_QUERY_CELLS
#define MESH_MAX_QUERY_CELLS 512
#endif
#ifndef MESH_DEEP_TIE
#define MESH_DEEP_TIE 1e-4f
#endif

__kernel void mc_save(__global const float4 *pos, __global const int4 *att, __global float4 *start)
{
    const int k = get_group_id(0), lid = get_local_id(0);
    const int4 a = att[k];
    for (int v = lid; v < a.y; v += MC_LS)
        start[a.w + v] = pos[a.x + v];
}

inline float3 xform(__global const float4 *m, float3 p)
{
    return (float3)(dot(m[0].xyz, p) + m[0].w, dot(m[1].xyz, p) + m[1].w, dot(m[2].xyz, p) + m[2].w);
}

/* the point of triangle (a, a + e1, a + e2) closest to p (Ericson's regions) */
inline float3 closest_on_triangle(float3 p, float3 a, float3 e1, float3 e2)
{
    const float3 ap = p - a;
    const float d1 = dot(e1, ap), d2 = dot(e2, ap);
    if (d1 <= 0.0f && d2 <= 0.0f)
        return a;
    const float3 bp = ap - e1;
    const float d3 = dot(e1, bp), d4 = dot(e2, bp);
    if (d3 >= 0.0f && d4 <= d3)
        return a + e1;
    const float vc = d1 * d4 - d3 * d2;
    if (vc <= 0.0f && d1 >= 0.0f && d3 <= 0.0f)
        return a + e1 * (d1 / (d1 - d3));
    const float3 cp = ap - e2;
    const float d5 = dot(e1, cp), d6 = dot(e2, cp);
    if (d6 >= 0.0f && d5 <= d6)
        return a + e2;
    const float vb = d5 * d2 - d1 * d6;
    if (vb <= 0.0f && d2 >= 0.0f && d6 <= 0.0f)
        return a + e2 * (d2 / (d2 - d6));
    const float va = d3 * d6 - d5 * d4;
    if (va <= 0.0f && (d4 - d3) >= 0.0f && (d5 - d6) >= 0.0f)
        return a + e1 + (e2 - e1) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    const float den = 1.0f / (va + vb + vc);
    return a + e1 * (vb * den) + e2 * (vc * den);
}

/* Every candidate triangle ti (index within the mesh) of the query box [lo, hi]: the triangles of
 * the grid cells it covers (a triangle may come more than once: see REPEAT), or every triangle of
 * the mesh when the box covers more than MESH_MAX_QUERY_CELLS cells. The body sees the query's
 * first cell c0 and the cell cc it walks. */
#define FOR_CANDIDATES(...)                                                                            \
    {                                                                                                  \
        const int3 c0 = max(convert_int3_sat_rtn((lo - org) * inv), (int3)(0));                            \
        const int3 c1 = min(convert_int3_sat_rtn((hi - org) * inv), dims - 1);                             \
        const int3 span = c1 - c0 + 1;                                                                 \
        if (span.x <= 0 || span.y <= 0 || span.z <= 0) { /* the box misses the grid: no triangle */   \
        } else if (span.x * span.y * span.z > MESH_MAX_QUERY_CELLS) {                                  \
            const int3 cc = c0; /* every triangle once: none a repeat */                               \
            for (int ti = 0; ti < mi.s1; ++ti) {                                                       \
                __VA_ARGS__                                                                            \
            }                                                                                          \
        } else {                                                                                       \
            for (int cz = c0.z; cz <= c1.z; ++cz)                                                      \
                for (int cy = c0.y; cy <= c1.y; ++cy)                                                  \
                    for (int cx = c0.x; cx <= c1.x; ++cx) {                                            \
                        const int3 cc = (int3)(cx, cy, cz);                                            \
                        const int cell = mi.s2 + cx + dims.x * (cy + dims.y * cz);                     \
                        const int e = mcell[cell + 1];                                                 \
                        for (int q = mcell[cell]; q < e; ++q) {                                        \
                            const int ti = mlist[mi.s3 + q];                                           \
                            __VA_ARGS__                                                                       \
                        }                                                                              \
                    }                                                                                  \
        }                                                                                              \
    }

/* In the walk of FOR_CANDIDATES, a triangle whose box starts at tlo comes again in a cell after its
 * first one in the query's cells: along some axis the walk is past the query's first cell and the
 * triangle reaches clearly (a thousandth of a cell: more than float32's rounding of the host's
 * float64 grid) into the cell before, which lists it too. At least one cell of the walk takes it
 * (the lowest that lists it, along each axis), now and then two near a cell's face. */
#define REPEAT(tlo) any((cc > c0) & (((tlo) - org) * inv < convert_float3(cc) - 1e-3f))

/* In a FOR_CANDIDATES walk, triangle ti (its first corner v0) kept as p's nearest within dmin (the
 * distance, triangle, closest point and normal in dmin, best, qbest, nbest), pd: p's signed
 * distance to its plane. A triangle is no nearer than its plane (most candidates end at the one
 * dot product that gave pd) nor than its box (the coplanar neighbours of a contact), and one seen
 * in an earlier cell of the walk is not tested again. */
#define NEAREST(p, pd, v0)                                                                             \
    if (fabs(pd) <= dmin) {                                                                            \
        const float3 e1 = T[4 * ti + 1].xyz, e2 = T[4 * ti + 2].xyz;                                   \
        const float3 tlo = fmin(v0, v0 + fmin(fmin(e1, e2), 0.0f));                                    \
        const float3 thi = fmax(v0, v0 + fmax(fmax(e1, e2), 0.0f));                                    \
        const float3 out = fmax(fmax(tlo - (p), (p) - thi), 0.0f);                                     \
        if (dot(out, out) <= dmin * dmin && !REPEAT(tlo)) {                                            \
            const float3 q = closest_on_triangle(p, v0, e1, e2);                                       \
            const float d = length((p) - q);                                                           \
            if (d < dmin || (d == dmin && ti < best && best != 0x7fffffff)) {                          \
                dmin = d;                                                                              \
                best = ti;                                                                             \
                qbest = q;                                                                             \
                nbest = T[4 * ti + 3].xyz;                                                             \
            }                                                                                          \
        }                                                                                              \
    }

/* The first triangle whose plane the segment a -> b crosses from its front to its back, inside the
 * triangle (within MESH_EDGE_TOLERANCE of its barycentric range; the lower index on a tie): its
 * normal, b's signed distance to its plane and the crossing's parameter along a -> b. With ``near``
 * the same walk also finds b's nearest triangle within h (dnear, inear, qnear, nnear: dmin, best,
 * qbest, nbest of NEAREST), as a thickness pass's own walk at b would (its box, b's grown by h,
 * lies inside the segment's, so its triangles are among the walk's): the first pass of a vertex
 * that crossed nothing walks no grid of its own. */
inline int first_crossing_near(float3 a, float3 b, float h, __global const float4 *T, __global const int *mcell,
                               __global const int *mlist, int8 mi, float3 org, float inv, int3 dims, float3 *nout,
                               float *dout, float *tout, const int near, float *dnear, int *inear, float3 *qnear,
                               float3 *nnear)
{
    const float3 lo = fmin(a, b) - h, hi = fmax(a, b) + h;
    float tbest = 2.0f;
    int bestx = 0x7fffffff;
    float dmin = h; /* b's nearest triangle within h (near), as a thickness pass at b finds it */
    int best = 0x7fffffff;
    float3 qbest = (float3)(0.0f), nbest = (float3)(0.0f);
    FOR_CANDIDATES({
        const float3 v0 = T[4 * ti].xyz, n = T[4 * ti + 3].xyz;
        const float da = dot(a - v0, n), db = dot(b - v0, n);
        if (near)
            NEAREST(b, db, v0)
        if (da >= 0.0f && db < 0.0f) {
            const float t = da / (da - db);
            if (t < tbest || (t == tbest && ti < bestx)) {
                const float3 e1 = T[4 * ti + 1].xyz, e2 = T[4 * ti + 2].xyz;
                const float3 w = a + t * (b - a) - v0;
                const float d00 = dot(e1, e1), d01 = dot(e1, e2), d11 = dot(e2, e2);
                const float d20 = dot(w, e1), d21 = dot(w, e2);
                const float det = d00 * d11 - d01 * d01;
                const float bv = (d11 * d20 - d01 * d21) / det, bw = (d00 * d21 - d01 * d20) / det;
                if (bv >= -MESH_EDGE_TOLERANCE && bw >= -MESH_EDGE_TOLERANCE && bv + bw <= 1.0f + MESH_EDGE_TOLERANCE) {
                    tbest = t;
                    bestx = ti;
                    *nout = n;
                    *dout = db;
                    *tout = t;
                }
            }
        }
    })
    if (near) {
        *dnear = dmin;
        *inear = best;
        *qnear = qbest;
        *nnear = nbest;
    }
    return tbest <= 1.0f;
}

inline int first_crossing(float3 a, float3 b, float h, __global const float4 *T, __global const int *mcell,
                          __global const int *mlist, int8 mi, float3 org, float inv, int3 dims, float3 *nout,
                          float *dout, float *tout)
{
    float *dnear = 0;
    int *inear = 0;
    float3 *qnear = 0, *nnear = 0;
    return first_crossing_near(a, b, h, T, mcell, mlist, mi, org, inv, dims, nout, dout, tout, 0, dnear, inear,
                               qnear, nnear);
}

/* The move s -> x of a point s outside the mesh, stopped MESH_GUARD_BACKOFF of the way to the first
 * surface it would enter (x as given if none): a push away from one face of a crease narrower
 * than twice the thickness would go through the other. The box's margin: the crossing point is on
 * the segment, so the cells its box covers hold the triangle (a little more for the edge slack). */
inline float3 guarded(float3 s, float3 x, __global const float4 *T, __global const int *mcell,
                      __global const int *mlist, int8 mi, float3 org, float inv, int3 dims)
{
    float3 n;
    float d, t;
    if (first_crossing(s, x, 1e-4f, T, mcell, mlist, mi, org, inv, dims, &n, &d, &t))
        return s + (MESH_GUARD_BACKOFF * t) * (x - s);
    return x;
}

__kernel void mc_collide(__global float4 *pos, __global float4 *vel, __global const float4 *start,
                         __global const int4 *att, __global const float4 *apar, __global const float4 *mtri,
                         __global const int *mcell, __global const int *mlist, __global const int8 *minfo,
                         __global const float4 *mgeom, const float inv_dt, const int first)
{
    const int k = first + get_group_id(0), lid = get_local_id(0);
    const int4 at = att[k];
    __global const float4 *P = apar + 10 * k;
    const float h = P[9].x, mu = P[9].y;
    const int fresh_mesh = P[9].z > 0.0f;
    const int8 mi = minfo[at.z];
    const float4 g = mgeom[at.z];
    const float3 org = g.xyz;
    const float inv = g.w;
    const int3 dims = (int3)(mi.s4, mi.s5, mi.s6);
    const float3 ghi = org + convert_float3(dims) / inv; /* the grid's far corner */
    __global const float4 *T = mtri + 4 * mi.s0;
    for (int v = lid; v < at.y; v += MC_LS) {
        const float4 x4 = pos[at.x + v];
        if (!(x4.w > 0.0f))
            continue;
        const float3 a = xform(P, start[at.w + v].xyz);
        const float3 b0 = xform(P + 3, x4.xyz);
        /* a motion whose box, grown by the thickness, misses the grid's meets no triangle: the
         * steps below would leave it as it is (most vertices of a cloth off the body) */
        if (any(fmax(a, b0) + h < org) || any(fmin(a, b0) - h > ghi))
            continue;
        float3 b = b0;
        float3 ncon = (float3)(0.0f); /* the last contact's normal and the pushes' total length */
        float pen = 0.0f;
        /* the first pass's nearest triangle, found by the first crossing test where nothing crossed
         * (fresh: b is where that test looked) */
        float ndmin = h;
        int nbi = 0x7fffffff, fresh = 0;
        float3 nq = (float3)(0.0f), nn = (float3)(0.0f);
        /* 1. continuous: the first front-to-back crossing of p -> b puts b onto that plane at the
         * thickness and the motion slides on from the contact (p: the contact at the thickness),
         * MESH_SLIDES times; a motion that still crosses then stops at its last contact */
        {
            float3 p = a, nb;
            float db, t;
            int k = 0;
            for (; k < MESH_SLIDES; ++k) {
                if (!first_crossing_near(p, b, h, T, mcell, mlist, mi, org, inv, dims, &nb, &db, &t, k == 0, &ndmin,
                                         &nbi, &nq, &nn)) {
                    fresh = k == 0;
                    break;
                }
                const float3 c = p + t * (b - p) + nb * h;
                b -= nb * (db - h);
                ncon = nb;
                pen += h - db;
                p = guarded(p, c, T, mcell, mlist, mi, org, inv, dims); /* the contact at the thickness, safely */
            }
            if (k == MESH_SLIDES && first_crossing(p, b, h, T, mcell, mlist, mi, org, inv, dims, &nb, &db, &t))
                b = p;
        }
        const float3 safe = b; /* outside: reached from the step's start by moves that entered nothing */
        /* 2. the thickness: push away from the closest triangle within h */
        for (int pass = 0; pass < MESH_PASSES; ++pass) {
            if (pass == 1 && pen > 0.0f && mu > 0.0f) {
                /* 3. friction against the (still, in its frame) mesh after the first pass: the
                 * tangential motion reduced by mu x pen, unless that move crosses the surface
                 * (a crease); the passes after it keep the thickness */
                const float3 rel = b - a;
                const float3 tang = rel - ncon * dot(rel, ncon);
                const float tl = length(tang);
                if (tl > 1e-12f) {
                    const float3 bf = b - tang * (fmin(mu * pen, tl) / tl);
                    float3 nf;
                    float df, tf;
                    if (!first_crossing(b, bf, h, T, mcell, mlist, mi, org, inv, dims, &nf, &df, &tf))
                        b = bf;
                }
            }
            float dmin = h;
            int best = 0x7fffffff;
            float3 qbest = (float3)(0.0f), nbest = (float3)(0.0f);
            if (pass == 0 && fresh) {
                dmin = ndmin;
                best = nbi;
                qbest = nq;
                nbest = nn;
            } else {
                const float3 lo = b - h, hi = b + h;
                FOR_CANDIDATES({
                    const float3 v0 = T[4 * ti].xyz;
                    NEAREST(b, dot(b - v0, T[4 * ti + 3].xyz), v0)
                })
            }
            if (best == 0x7fffffff && pass == 0 && fresh_mesh) {
                /* 5. deep: in a mesh's first step (set or re-posed onto the cloth), a vertex with
                 * no triangle within h looks for its nearest triangle anywhere (boxes growing by
                 * 4x, the whole mesh past MESH_MAX_QUERY_CELLS cells); behind that triangle's
                 * plane it is inside, and put out onto its front at the thickness below */
                float r = 4.0f * h;
                for (int grow = 0;; ++grow, r *= 4.0f) {
                    const float3 lo = b - r, hi = b + r;
                    const int3 s0 = max(convert_int3_sat_rtn((lo - org) * inv), (int3)(0));
                    const int3 s1 = min(convert_int3_sat_rtn((hi - org) * inv), dims - 1);
                    const int3 sp = s1 - s0 + 1;
                    /* a box over the whole grid (or walked as the whole mesh) takes any triangle */
                    /* (or the 12th box, 4^12 x 4 thicknesses: a NaN vertex ends here) */
                    const int whole = (all(s0 == 0) && all(s1 == dims - 1)) || sp.x * sp.y * sp.z > MESH_MAX_QUERY_CELLS
                                      || grow == 11;
                    dmin = whole ? MAXFLOAT : r;
                    FOR_CANDIDATES({
                        const float3 v0 = T[4 * ti].xyz;
                        NEAREST(b, dot(b - v0, T[4 * ti + 3].xyz), v0)
                    })
                    if (best != 0x7fffffff || whole)
                        break;
                }
                /* inside only if behind the plane of every triangle as near (within MESH_DEEP_TIE: a
                 * nearest point on an edge or corner is shared; outside a corner's region a point
                 * is in front of at least one of them), else nothing to do */
                if (best != 0x7fffffff) {
                    const float tie = dmin * (1.0f + MESH_DEEP_TIE) + 1e-6f;
                    const float3 lo = b - tie, hi = b + tie;
                    int inside = 1;
                    FOR_CANDIDATES({
                        const float3 v0 = T[4 * ti].xyz, n = T[4 * ti + 3].xyz;
                        if (fabs(dot(b - v0, n)) <= tie) {
                            const float3 q = closest_on_triangle(b, v0, T[4 * ti + 1].xyz, T[4 * ti + 2].xyz);
                            if (length(b - q) <= tie && !(dot(b - q, n) < 0.0f))
                                inside = 0;
                        }
                    })
                    if (!inside)
                        best = 0x7fffffff;
                }
            }
            if (best == 0x7fffffff) {
                if (pass == 0 && pen > 0.0f && mu > 0.0f)
                    continue; /* the friction of a continuous contact still comes */
                break;
            }
            const float3 dv = b - qbest;
            const int front = dot(dv, nbest) > 0.0f && dmin > 1e-9f;
            const float3 nb = qbest + (front ? dv / dmin : nbest) * h;
            pen += length(nb - b);
            ncon = front ? dv / dmin : nbest;
            b = nb;
        }
        /* 4. the guard: the passes' and friction's moves together enter nothing */
        if (any(b != safe))
            b = guarded(safe, b, T, mcell, mlist, mi, org, inv, dims);

        if (any(b != b0)) {
            const float3 moved = xform(P + 6, b) - xform(P + 6, b0);
            pos[at.x + v] = (float4)(x4.xyz + moved, x4.w);
            vel[at.x + v] = (float4)(vel[at.x + v].xyz + moved * inv_dt, 0.0f);
        }
    }
}
