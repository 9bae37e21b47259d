"""Triangle-mesh colliders (issue 22): a mesh's data and checks, its rigid poses, the uniform grid
over its triangles that the device walks, and mesh collision in float64 numpy (the reference of
kernels/meshcollide.cl, drape.server.sim.opencl.meshes) with the metric of what it leaves.

A mesh collider is a triangle mesh (vertices in its own frame, triangles counter-clockwise seen
from outside) placed by a rigid pose per tick (a 3 x 4 matrix ``[R | t]``: mesh frame to world).
It is **one-sided**: the side its triangles' normals point to, ``(v1 - v0) x (v2 - v0)``, is
outside (a closed body's outside), as game engines' mesh colliders are. Moving it rigidly
changes only its pose (the cloth's vertices are carried into the mesh's frame, the grid is not
rebuilt); re-posing it (new vertices, same triangles) rebuilds the grid on the host.

Once per step (tick), after every cloth's own solve and the scenes' inter-cloth collision, for
each free vertex of a cloth with a mesh (its own, then its scene's), in the mesh's frame
(``a``: the vertex's position at the step's start carried by the inverse of the pose at the
start, ``b``: its position now by the inverse of the pose now, so a rigid motion of the mesh is
exact at both ends and linear between):

1. **continuous**: the first triangle that the segment ``a -> b`` crosses from its front
   (``a`` on or in front of its plane, ``b`` behind it, the crossing point inside the triangle
   within MESH_EDGE_TOLERANCE of its barycentric range) puts ``b`` back onto that plane's front at
   the thickness, and the rest of the motion slides on from the contact (the contact, at the
   thickness, is the next segment's start): MESH_SLIDES times; a motion that still crosses
   then stops at its last contact (a plane's extension far from its triangle can lie inside
   another part of a non-convex body). No vertex tunnels through the surface, however fast;
2. **thickness**: MESH_PASSES passes, each finds the triangle closest to ``b`` among those
   within ``thickness`` of it; if ``b`` is in front of its plane, ``b`` is moved away from the
   closest point to the thickness (an edge or a corner pushes radially); behind it, onto the
   front at the thickness (one-sided).
3. **friction** (the material's ``friction``, as against the other colliders), after the first
   thickness pass (the passes after it keep the thickness): where 1 or 2 pushed the vertex, the
   tangential part of its motion relative to the mesh (``b - a``, along the last push's normal)
   is reduced by ``friction`` times the pushes' total length, unless that move crosses the
   surface (tested as in 1: at a crease it could cross the next face).
4. **the guard**: every move the steps make on their own (1's step from a contact out to the
   thickness, 2 and 3 together from where 1 left the vertex) is tested as in 1 and stops
   MESH_GUARD_BACKOFF of the way to the first surface it would enter: in a crease narrower than
   twice the thickness a push away from one face goes through the other (then the vertex stays
   between the faces, nearer than the thickness). A vertex outside at the step's start is
   outside at its end: the metric's 0 does not hang on the pushes' geometry.

5. **deep** (in a mesh's first step, set or re-posed onto a cloth that overlaps it): a vertex
   with no triangle within the thickness that is behind the plane of every triangle nearest to it
   (within MESH_DEEP_TIE of the nearest's distance: a corner or an edge is shared; outside a
   corner a point is in front of at least one of its faces) is inside, and the first thickness
   pass puts it onto the nearest's front at the thickness, as a vertex behind within the
   thickness.

The thickness is the cloth's material ``thickness`` (the self-collision field, as scenes use it),
at least MESH_MIN_THICKNESS (1 mm: float32 keeps a vertex on the surface only to its rounding).
A vertex moved by ``dx`` gains ``dx / dt`` of velocity (as inter-cloth collision does). The
candidates are the triangles of the grid cells that the query's box (the segment's, grown by the
thickness) covers; a box over MESH_MAX_QUERY_CELLS cells tests every triangle of the mesh instead,
so the grid never misses a triangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A mesh collider's size limits and its least triangle area: the protocol's (one copy).
from drape.client.protocol.vocabulary import (  # noqa: F401 (the limits re-exported)
    MESH_MAX_TRIANGLES,
    MESH_MAX_VERTICES,
    MESH_MIN_AREA,
    mesh_problem,
)

#: The thickness passes per step.
MESH_PASSES = 2
#: The continuous test's slides along the surface after a contact, per step.
MESH_SLIDES = 2
#: A guarded move (a contact's push, the thickness passes' pushes) that would enter the surface
#: stops this share of the way to where it would (a crease narrower than twice the thickness).
MESH_GUARD_BACKOFF = 0.5
#: The crossing point's barycentric slack: a segment through a shared edge is caught by both.
MESH_EDGE_TOLERANCE = 1e-5
#: A query box over more cells than this tests the whole mesh.
MESH_MAX_QUERY_CELLS = 512
#: A deep vertex's nearest triangles: those within this share of the nearest's distance (step 5).
MESH_DEEP_TIE = 1e-4
#: Grid cells per triangle at most (the cell edge is grown until the grid fits).
MESH_CELLS_PER_TRIANGLE = 8
#: The least thickness kept from a mesh (a cloth whose material says less, 0 included).
MESH_MIN_THICKNESS = 1e-3


def mesh_thickness(thickness: float) -> float:
    """The distance a cloth of material ``thickness`` keeps from a mesh's surface."""
    return max(float(thickness), MESH_MIN_THICKNESS)


@dataclass(frozen=True, eq=False)
class CollisionMesh:
    """A mesh collider's geometry in its own frame: (n, 3) float64 vertices, (m, 3) int32
    triangles. Build it with :func:`collision_mesh` (which checks it)."""

    vertices: np.ndarray
    triangles: np.ndarray

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def reposed(self, vertices: np.ndarray) -> CollisionMesh:
        """The same triangles on new vertices (a re-pose): checked as a new mesh."""
        return collision_mesh(vertices, self.triangles)


def collision_mesh(vertices: np.ndarray, triangles: np.ndarray) -> CollisionMesh:
    """A checked mesh collider: ValueError (a message that says what is wrong) for no triangles,
    too many vertices or triangles, a non-finite vertex, an index out of range or a degenerate
    triangle (area under MESH_MIN_AREA m^2, repeated indices included): the protocol's checks
    (``vocabulary.mesh_problem``, one copy for the wire and the World)."""
    problem = mesh_problem(vertices, triangles)
    if problem is not None:
        raise ValueError(problem[1])
    return CollisionMesh(np.asarray(vertices, np.float64), np.asarray(triangles).astype(np.int32))


# --- poses ---------------------------------------------------------------------------------------
def pose_matrix(position=(0.0, 0.0, 0.0), rotation=(1.0, 0.0, 0.0, 0.0)) -> np.ndarray:
    """The rigid pose ``[R | t]`` (3 x 4, float64) of a position and a rotation quaternion
    ``(w, x, y, z)`` (normalised here; ValueError for a zero one)."""
    q = np.asarray(rotation, np.float64)
    n = float(np.linalg.norm(q))
    if q.shape != (4,) or not n > 0.0 or not np.isfinite(n):
        raise ValueError(f"rotation must be a non-zero quaternion (w, x, y, z), got {rotation!r}")
    w, x, y, z = q / n
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    p = np.asarray(position, np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"position must be 3 finite numbers, got {position!r}")
    return np.concatenate([r, p[:, None]], axis=1)


def invert_pose(p: np.ndarray) -> np.ndarray:
    r, t = p[:, :3], p[:, 3]
    return np.concatenate([r.T, (-r.T @ t)[:, None]], axis=1)


def apply_pose(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.asarray(x, np.float64) @ p[:, :3].T + p[:, 3]


# --- the grid ------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class MeshGrid:
    """A uniform grid over a mesh's triangles in its frame: cell (i, j, k) (i fastest) holds the
    triangles whose box meets it, ``tris[start[c]:start[c + 1]]``."""

    origin: np.ndarray  # (3,) float64: the grid's lowest corner
    cell: float  # the cells' edge (m)
    dims: np.ndarray  # (3,) int: cells per axis
    start: np.ndarray  # (cells + 1,) int32
    tris: np.ndarray  # int32 triangle indices


def build_grid(mesh: CollisionMesh) -> MeshGrid:
    """The grid of ``mesh``: cells of the mean triangle edge (a thickness's query then meets a
    few cells of a few triangles each, and far from the surface only empty cells), grown until
    there are at most MESH_CELLS_PER_TRIANGLE cells per triangle."""
    v, t = mesh.vertices, mesh.triangles
    tri = v[t]  # (m, 3, 3)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    origin = lo.min(axis=0)
    extent = np.maximum(hi.max(axis=0) - origin, 1e-6)
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    cell = max(float(edges.mean()), float(extent.max()) / 256.0)
    while True:
        dims = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
        if int(np.prod(dims)) <= MESH_CELLS_PER_TRIANGLE * len(t) + 8:
            break
        cell *= 1.25
    c0 = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, dims - 1)
    c1 = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, dims - 1)
    cells: list[np.ndarray] = []
    owners: list[np.ndarray] = []
    span = c1 - c0 + 1
    for sx in range(int(span[:, 0].max())):
        for sy in range(int(span[:, 1].max())):
            for sz in range(int(span[:, 2].max())):
                ok = (sx < span[:, 0]) & (sy < span[:, 1]) & (sz < span[:, 2])
                idx = np.nonzero(ok)[0]
                c = c0[idx] + np.array([sx, sy, sz])
                cells.append(c[:, 0] + dims[0] * (c[:, 1] + dims[1] * c[:, 2]))
                owners.append(idx)
    cid, own = np.concatenate(cells), np.concatenate(owners)
    order = np.lexsort((own, cid))
    cid, own = cid[order], own[order]
    n = int(np.prod(dims))
    start = np.zeros(n + 1, np.int64)
    np.add.at(start, cid + 1, 1)
    return MeshGrid(origin, cell, dims, np.cumsum(start).astype(np.int32), own.astype(np.int32))


# --- collision, float64 --------------------------------------------------------------------------
def _triangle_frames(mesh: CollisionMesh) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    tri = mesh.vertices[mesh.triangles]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    return v0, e1, e2, n / np.linalg.norm(n, axis=1)[:, None]


def closest_points(p: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> np.ndarray:
    """The closest point of each triangle (v0, v0 + e1, v0 + e2) to each point: ``p`` (..., 3)
    broadcast against the triangles (Ericson's regions, as kernels/meshcollide.cl)."""
    a, b, c = v0, v0 + e1, v0 + e2
    ap = p - a
    d1, d2 = (e1 * ap).sum(-1), (e2 * ap).sum(-1)
    bp = p - b
    d3, d4 = (e1 * bp).sum(-1), (e2 * bp).sum(-1)
    cp = p - c
    d5, d6 = (e1 * cp).sum(-1), (e2 * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v_in, w_in = vb * denom, vc * denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    out = a + v_in[..., None] * e1 + w_in[..., None] * e2
    # the regions, last assignment wins: from the face inwards to the corners (Ericson's order reversed)
    bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    out = np.where(bc[..., None], b + t_bc[..., None] * (c - b), out)
    ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(ac[..., None], a + t_ac[..., None] * e2, out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[..., None], c, out)
    ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(ab[..., None], a + t_ab[..., None] * e1, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[..., None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[..., None], a, out)
    return np.broadcast_to(out, np.broadcast_shapes(p.shape, v0.shape)).copy()


_CHUNK = 1 << 20  # point-triangle pairs evaluated at once


def collide_mesh(
    x: np.ndarray,
    v: np.ndarray,
    x_start: np.ndarray,
    invm: np.ndarray,
    mesh: CollisionMesh,
    pose_start: np.ndarray,
    pose_end: np.ndarray,
    thickness: float,
    dt: float,
    friction: float = 0.0,
    fresh: bool = False,
) -> None:
    """One cloth's vertices kept out of one mesh collider (the module's steps), ``x`` and ``v``
    in place; ``x_start``: the positions at the step's start; ``fresh``: the mesh's first step
    (set or re-posed), its deep vertices put out (step 5)."""
    free = np.nonzero(np.asarray(invm) > 0)[0]
    if not len(free):
        return
    h = mesh_thickness(thickness)
    a = apply_pose(invert_pose(pose_start), x_start[free])
    b = apply_pose(invert_pose(pose_end), x[free])
    b0 = b.copy()
    v0, e1, e2, n = _triangle_frames(mesh)
    tri = mesh.vertices[mesh.triangles]
    tlo, thi = tri.min(axis=1), tri.max(axis=1)
    # an exact cull: the cloth's box, grown by what a query reaches (a push ends within 2h of b)
    lo, hi = np.minimum(a, b).min(axis=0) - 3 * h, np.maximum(a, b).max(axis=0) + 3 * h
    near = np.nonzero(np.all((thi >= lo) & (tlo <= hi), axis=1) | fresh)[0]  # fresh: every triangle
    v0, e1, e2, n = v0[near], e1[near], e2[near], n[near]
    step = max(1, _CHUNK // max(len(near), 1))
    for s in range(0, len(b), step):
        sl = slice(s, s + step)
        b[sl] = _collide_points(a[sl], b[sl], v0, e1, e2, n, h, friction, fresh)
    moved = apply_pose(pose_end, b) - apply_pose(pose_end, b0)
    x[free] += moved
    v[free] += moved / dt


def _collide_points(a, b, v0, e1, e2, n, h, mu, fresh=False):
    if not len(v0):
        return b
    ncon = np.zeros_like(b)  # the last contact's normal and the pushes' total length, per point
    pen = np.zeros(len(b))
    # 1. continuous: the first front-to-back crossing, then the slides from the contact
    p = a.copy()
    live = np.arange(len(b))
    for _ in range(MESH_SLIDES):
        rows, nf, df, t = _first_crossing(p[live], b[live], v0, e1, e2, n)
        r = live[rows]
        c = p[r] + t[:, None] * (b[r] - p[r]) + nf * h
        b[r] -= nf * (df - h)[:, None]
        ncon[r] = nf
        pen[r] += h - df
        p[r] = _guarded(p[r], c, v0, e1, e2, n)  # the contact at the thickness, reached safely
        live = r
    rows = _first_crossing(p[live], b[live], v0, e1, e2, n)[0]
    b[live[rows]] = p[live[rows]]  # still crossing: stopped at the last contact
    safe = b.copy()  # outside: reached from the step's start by moves that entered nothing
    # 2. the thickness, MESH_PASSES passes
    for k_pass in range(MESH_PASSES):
        if k_pass == 1:
            _friction(a, b, ncon, pen, mu, h, v0, e1, e2, n)
        q = closest_points(b[:, None], v0, e1, e2)  # (p, m, 3)
        d = b[:, None] - q
        dist = np.linalg.norm(d, axis=-1)
        k = np.argmin(dist, axis=1)
        r = np.arange(len(b))
        dk = dist[r, k]
        within = dk < h
        if k_pass == 0 and fresh:
            # 5. deep (a fresh mesh: ``near`` is every triangle): no triangle within h, and behind
            # the plane of every nearest one: inside, put onto its front at the thickness below
            tied = dist <= (dk * (1.0 + MESH_DEEP_TIE) + 1e-6)[:, None]
            behind_all = np.all(~tied | ((d * n[None]).sum(-1) < 0.0), axis=1)
            within |= behind_all
        rows = np.nonzero(within)[0]
        if not len(rows):
            if k_pass == 0:
                continue  # the friction of a continuous contact still comes
            break
        kk = k[rows]
        qk, nk, dv, dd = q[rows, kk], n[kk], d[rows, kk], dk[rows]
        front = ((dv * nk).sum(-1) > 0.0) & (dd > 1e-9)
        dirn = np.where(front[:, None], dv / np.where(front, dd, 1.0)[:, None], nk)
        nb = qk + dirn * h
        pen[rows] += np.linalg.norm(nb - b[rows], axis=1)
        ncon[rows] = dirn
        b[rows] = nb
    # 4. the guard: the passes' and friction's moves together enter nothing
    rows = np.nonzero(np.any(b != safe, axis=1))[0]
    b[rows] = _guarded(safe[rows], b[rows], v0, e1, e2, n)
    return b


def _guarded(s, x, v0, e1, e2, n):
    """The moves ``s -> x`` of points ``s`` outside the mesh, each stopped MESH_GUARD_BACKOFF of
    the way to the first surface it would enter (``x`` elsewhere as given): a push away from one
    face of a crease narrower than twice the thickness would go through the other."""
    rows, _, _, t = _first_crossing(s, x, v0, e1, e2, n)
    x = x.copy()
    x[rows] = s[rows] + (MESH_GUARD_BACKOFF * t)[:, None] * (x[rows] - s[rows])
    return x


def _first_crossing(a, b, v0, e1, e2, n):
    """The points whose segment a -> b crosses a triangle's plane from its front to its back inside
    the triangle (kernels/meshcollide.cl's first_crossing): their rows, the first such triangle's
    normal, b's signed distance to its plane and the crossing's parameter along a -> b."""
    da = ((a[:, None] - v0) * n).sum(-1)  # (p, m)
    db = ((b[:, None] - v0) * n).sum(-1)
    cross = (da >= 0.0) & (db < 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cross, da / (da - db), 2.0)
    hit = a[:, None] + t[..., None] * (b - a)[:, None] - v0
    d00, d01, d11 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    d20, d21 = (hit * e1).sum(-1), (hit * e2).sum(-1)
    det = d00 * d11 - d01 * d01
    bv, bw = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
    tol = MESH_EDGE_TOLERANCE
    inside = cross & (bv >= -tol) & (bw >= -tol) & (bv + bw <= 1.0 + tol)
    t = np.where(inside, t, 2.0)
    first = np.argmin(t, axis=1)
    rows = np.nonzero(t[np.arange(len(b)), first] <= 1.0)[0]
    f = first[rows]
    return rows, n[f], db[rows, f], t[rows, f]


def _friction(a, b, ncon, pen, mu, h, v0, e1, e2, n):
    """3. friction against the (still, in its frame) mesh, after the first pass: the tangential
    motion reduced by mu x pen unless that move crosses the surface (a crease), ``b`` in place
    (the passes after it keep the thickness)."""
    rows = np.nonzero(pen > 0.0)[0] if mu > 0.0 else np.zeros(0, np.int64)
    if not len(rows):
        return
    rel = b[rows] - a[rows]
    nc = ncon[rows]
    tang = rel - nc * (rel * nc).sum(-1)[:, None]
    tl = np.linalg.norm(tang, axis=1)
    ok = tl > 1e-12
    cut = np.where(ok, np.minimum(mu * pen[rows], tl) / np.where(ok, tl, 1.0), 0.0)
    bf = b[rows] - tang * cut[:, None]
    hit = _first_crossing(b[rows], bf, v0, e1, e2, n)[0]
    bf[hit] = b[rows[hit]]  # a move that crosses the surface (a crease) is not made
    b[rows] = bf


# --- the metric ----------------------------------------------------------------------------------
def depth_inside(x: np.ndarray, mesh: CollisionMesh, pose: np.ndarray) -> np.ndarray:
    """How far each point is inside the mesh placed at ``pose`` (> 0 inside, else 0): inside by
    the generalised winding number (over 1/2: the solid angle the mesh's triangles subtend), its
    depth the distance to the surface. Written apart from the solver on purpose: the metric checks
    it, and a mesh that is not closed counts as deep as its winding says."""
    p_all = apply_pose(invert_pose(pose), np.asarray(x, np.float64).reshape(-1, 3))
    out_all = np.zeros(len(p_all))
    box = np.nonzero(np.all((p_all >= mesh.vertices.min(axis=0)) & (p_all <= mesh.vertices.max(axis=0)), axis=1))[0]
    p = p_all[box]  # a point outside the mesh's box is outside the mesh
    tri = mesh.vertices[mesh.triangles]
    m = len(tri)
    step = max(1, _CHUNK // (9 * max(m, 1)))
    out = np.zeros(len(p))
    v0, e1, e2, _ = _triangle_frames(mesh)
    tri32 = tri.astype(np.float32)
    for s in range(0, len(p), step):
        r = tri32[None] - p[s : s + step, None, None, :].astype(np.float32)  # (p, m, 3, 3)
        ln = np.sqrt(np.einsum("pmkc,pmkc->pmk", r, r))
        a, b, c = r[..., 0, :], r[..., 1, :], r[..., 2, :]
        num = np.einsum("pmc,pmc->pm", a, np.cross(b, c))
        den = ln[..., 0] * ln[..., 1] * ln[..., 2] + np.einsum("pmc,pmc->pm", a, b) * ln[..., 2]
        den += np.einsum("pmc,pmc->pm", a, c) * ln[..., 1] + np.einsum("pmc,pmc->pm", b, c) * ln[..., 0]
        wind = (2.0 * np.arctan2(num, den)).sum(-1, dtype=np.float64) / (4.0 * np.pi)
        ins = np.nonzero(wind > 0.5)[0]
        if len(ins):
            pts = p[s + ins]
            dist = np.linalg.norm(closest_points(pts[:, None], v0, e1, e2) - pts[:, None], axis=-1).min(axis=1)
            out[s + ins] = dist
    out_all[box] = out
    return out_all
