"""A procedural humanoid body as one triangle mesh (issue 22's mesh collider: the penetration
scenario, the benchmark, the demo and the tests): tessellated ellipsoids (torso, pelvis, head,
arms and legs) whose triangles buried inside another part are dropped, counter-clockwise seen
from outside. About 1.8 m tall, standing at the origin on y = 0, facing +z.
"""

from __future__ import annotations

import numpy as np

from .meshes import CollisionMesh, collision_mesh

#: The body's parts: centre (x, y, z) and radii (x, y, z), metres.
BODY_PARTS: tuple[tuple[tuple[float, float, float], tuple[float, float, float]], ...] = (
    ((0.0, 1.30, 0.0), (0.19, 0.28, 0.12)),  # torso
    ((0.0, 0.98, 0.0), (0.17, 0.14, 0.11)),  # pelvis
    ((0.0, 1.67, 0.01), (0.10, 0.12, 0.11)),  # head
    ((-0.24, 1.22, 0.0), (0.055, 0.30, 0.055)),  # arms
    ((0.24, 1.22, 0.0), (0.055, 0.30, 0.055)),
    ((-0.09, 0.46, 0.0), (0.075, 0.46, 0.075)),  # legs
    ((0.09, 0.46, 0.0), (0.075, 0.46, 0.075)),
)


def ellipsoid(centre, radii, segments: int = 32, rings: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """A UV ellipsoid: ``segments`` around its y axis, ``rings`` from pole to pole, outward."""
    c, r = np.asarray(centre, np.float64), np.asarray(radii, np.float64)
    theta = np.pi * np.arange(1, rings) / rings  # from the top pole down
    phi = 2.0 * np.pi * np.arange(segments) / segments
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    ring = np.stack([st * np.cos(phi), np.broadcast_to(ct, st.shape * np.array([1, segments])), st * np.sin(phi)], -1)
    v = np.concatenate([[[0.0, 1.0, 0.0]], ring.reshape(-1, 3), [[0.0, -1.0, 0.0]]]) * r + c
    top, bottom = 0, len(v) - 1
    tris: list[tuple[int, int, int]] = []
    at = lambda i, j: 1 + i * segments + j % segments  # noqa: E731
    for j in range(segments):
        tris.append((top, at(0, j + 1), at(0, j)))
        tris.append((bottom, at(rings - 2, j), at(rings - 2, j + 1)))
        for i in range(rings - 2):
            tris.append((at(i, j), at(i, j + 1), at(i + 1, j)))
            tris.append((at(i, j + 1), at(i + 1, j + 1), at(i + 1, j)))
    t = np.asarray(tris, np.int32)
    tri = v[t]
    vol = float((tri[:, 0] * np.cross(tri[:, 1], tri[:, 2])).sum())
    if vol < 0:  # outward, whatever the parametrisation's handedness
        t = t[:, ::-1].copy()
    return v, t


def body_mesh(segments: int = 32, rings: int = 20) -> CollisionMesh:
    """The humanoid: every part's ellipsoid, without the triangles whose three corners are inside
    another part (5,900 triangles at the defaults)."""
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    base = 0
    for k, (c, r) in enumerate(BODY_PARTS):
        v, t = ellipsoid(c, r, segments, rings)
        buried = np.zeros(len(v), bool)
        for m, (c2, r2) in enumerate(BODY_PARTS):
            if m != k:
                buried |= (((v - np.asarray(c2)) / np.asarray(r2)) ** 2).sum(axis=1) < 1.0
        t = t[~buried[t].all(axis=1)]
        verts.append(v)
        tris.append(t + base)
        base += len(v)
    return collision_mesh(np.concatenate(verts), np.concatenate(tris))
