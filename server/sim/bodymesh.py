"""A procedural humanoid body as one closed triangle mesh (issue 22's mesh collider: the penetration
scenario, the benchmark, the demo and the tests): the smooth union of ellipsoids (torso, pelvis,
head, neck, arms and legs) tessellated by marching tetrahedra, so that the surface is one closed
skin with no triangle inside the body (overlapping closed parts would leave buried triangles at
their creases, which push a vertex near a crease into the other part). Counter-clockwise seen
from outside; about 1.8 m tall, standing at the origin on y = 0, facing +z.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .meshes import MESH_MIN_AREA, CollisionMesh, collision_mesh

#: The body's parts: centre (x, y, z) and radii (x, y, z), metres.
BODY_PARTS: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((0.0, 1.30, 0.0), (0.19, 0.26, 0.12)),  # torso
    ((0.0, 0.98, 0.0), (0.17, 0.14, 0.11)),  # pelvis
    ((0.0, 1.56, 0.0), (0.05, 0.08, 0.05)),  # neck
    ((0.0, 1.69, 0.01), (0.10, 0.12, 0.11)),  # head
    ((-0.25, 1.22, 0.0), (0.055, 0.30, 0.055)),  # arms
    ((0.25, 1.22, 0.0), (0.055, 0.30, 0.055)),
    ((-0.09, 0.47, 0.0), (0.075, 0.47, 0.075)),  # legs
    ((0.09, 0.47, 0.0), (0.075, 0.47, 0.075)),
)
#: The smooth union's blend (m): creases rounded over about this much.
BLEND = 0.02
#: The six tetrahedra of a cube around its diagonal 0-7 (corner c = (c & 1, c >> 1 & 1, c >> 2 & 1)):
#: neighbouring cubes cut their shared faces alike, so the surface is closed.
_TETRAS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])


def body_distance(p: np.ndarray) -> np.ndarray:
    """About the signed distance (m, < 0 inside) of points (..., 3) to the body: the parts'
    scaled ellipsoid distances, smoothly united (polynomial smooth minimum over BLEND)."""
    d = None
    for c, r in BODY_PARTS:
        q = (p - np.asarray(c)) / np.asarray(r)
        di = (np.sqrt((q * q).sum(-1)) - 1.0) * min(r)
        if d is None:
            d = di
        else:
            h = np.clip(0.5 + 0.5 * (di - d) / BLEND, 0.0, 1.0)
            d = di * (1 - h) + d * h - BLEND * h * (1 - h)
    assert d is not None
    return d


def body_mesh(cell: float = 0.035) -> CollisionMesh:
    """The humanoid, tessellated on a grid of ``cell`` metres (12,220 triangles at the default, 5,972 at 0.05)."""
    return tessellate(body_distance, (-0.36, -0.02, -0.16), (0.36, 1.84, 0.17), cell)


def tessellate(distance: Callable[[np.ndarray], np.ndarray], lo, hi, cell: float) -> CollisionMesh:
    """The closed surface ``distance(p) = 0`` of a solid (``distance`` < 0 inside, of points
    (..., 3)) in the box [lo, hi], by marching tetrahedra on a grid of ``cell`` metres: one skin,
    counter-clockwise seen from outside, every edge once in each direction."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    n = np.ceil((hi - lo) / cell).astype(int) + 1
    axes = [lo[i] + cell * np.arange(n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)  # (nx, ny, nz, 3)
    f = distance(grid)
    f = np.where(np.abs(f) < 1e-4, np.where(f < 0, -1e-4, 1e-4), f)  # no surface at a grid point: no sliver
    idx = np.arange(f.size).reshape(f.shape)
    corners = np.stack(
        [
            idx[
                c & 1 : n[0] - 1 + (c & 1), c >> 1 & 1 : n[1] - 1 + (c >> 1 & 1), c >> 2 & 1 : n[2] - 1 + (c >> 2 & 1)
            ].reshape(-1)
            for c in range(8)
        ],
        -1,
    )  # (cubes, 8) point indices
    tet = corners[:, _TETRAS].reshape(-1, 4)  # (tetras, 4)
    fv, pts = f.reshape(-1), grid.reshape(-1, 3)
    inside = fv[tet] < 0
    code = (inside * (1 << np.arange(4))).sum(-1)
    tet, code, inside = tet[(code > 0) & (code < 15)], code[(code > 0) & (code < 15)], inside[(code > 0) & (code < 15)]
    edges: list[np.ndarray] = []  # (k, 3, 2): each triangle's three edges as point index pairs
    outer: list[np.ndarray] = []  # (k,): an outside corner of each triangle's tetrahedron
    for c in range(1, 15):
        rows = tet[code == c]
        if not len(rows):
            continue
        ins = [i for i in range(4) if c >> i & 1]
        out = [i for i in range(4) if not c >> i & 1]
        if len(ins) in (1, 3):
            a, others = (ins[0], out) if len(ins) == 1 else (out[0], ins)
            tris = [[(a, others[0]), (a, others[1]), (a, others[2])]]
        else:
            (i0, i1), (o0, o1) = ins, out
            tris = [[(i0, o0), (i0, o1), (i1, o1)], [(i0, o0), (i1, o1), (i1, o0)]]
        for t in tris:
            edges.append(np.stack([np.stack([rows[:, a], rows[:, b]], -1) for a, b in t], 1))
            outer.append(rows[:, out[0]])
    e = np.concatenate(edges)  # (m, 3, 2)
    far = pts[np.concatenate(outer)]
    e.sort(axis=-1)
    keys, tri = np.unique(e[..., 0] * f.size + e[..., 1], return_inverse=True)
    tri = tri.reshape(-1, 3)
    ea, eb = keys // f.size, keys % f.size
    s = fv[ea] / (fv[ea] - fv[eb])
    verts = pts[ea] + s[:, None] * (pts[eb] - pts[ea])
    # outward: each triangle faces its tetrahedron's outside corners (it separates them from the
    # inside ones: the piecewise-linear field's level set, so neighbours agree and every edge is
    # once in each direction; the distance's gradient at a coarse triangle's centre turned 45 of
    # 5,972 triangles inward at the armpits, where the field's creases are finer than the cells)
    v = verts[tri]
    nrm = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    flip = (nrm * (far - v[:, 0])).sum(-1) < 0
    tri[flip] = tri[flip][:, ::-1]
    return collision_mesh(verts, tri[area >= MESH_MIN_AREA])
