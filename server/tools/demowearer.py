"""The cape and its wearer, shared by ``drape demo``'s three-cloth stage (demo.py: one walker on
a circle) and its crossing stage (demoscene.py: two walkers passing): the cape's rest shape in
its wearer's frame, the walker's body (capsules to draw, the cape's colliders) at a pose, the
cape's texture and a grid's texture coordinates, and the cape's submission options."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

# the cape and its wearer: shoulder height, the cape's ring around the neck and its flare
CAPE_COLS, CAPE_ROWS, CAPE_LEN = 22, 26, 1.15
SHOULDER_Y, NECK_R, HEM_R, CAPE_ARC = 1.47, 0.19, 0.34, math.radians(100.0)
# the cape's submission options (features, links, material, solver), the same on every stage that
# drapes it (the crossing stage adds its thickness to the material)
CAPE_OPTIONS: dict[str, Any] = {
    "features": ["colliders", "tethers", "wind"],
    "links": {"bending": True},
    "material": {
        "mass": 0.6,
        "stiffness": (1.0, 0.8, 0.15),
        "friction": 0.3,
        "tether_limit": 1.05,
        "damping": 0.01,
        "drag": 1.0,
        "lift": 0.0,
    },
    "wind": (0.0, 0.0, 0.0),
    "iterations": 10,
    "substeps": 2,
}
MANNEQUIN = (92, 98, 112)
SKIN = (214, 176, 146)


def cape_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The cape's rest shape in its wearer's frame (x right, y up, z behind; the neck at the
    origin): a flared cone around the back, its top row a ring of radius NECK_R at shoulder
    height, widening to HEM_R at the hem. Triangles wound so that normals point outwards."""
    from drape.client import protocol as P

    _, t = P.grid_positions(CAPE_COLS, CAPE_ROWS, 1.0, 1.0, "vertical")
    r = np.repeat(np.linspace(0.0, 1.0, CAPE_ROWS), CAPE_COLS)
    a = np.tile(np.linspace(-CAPE_ARC, CAPE_ARC, CAPE_COLS), CAPE_ROWS)
    rad = NECK_R + (HEM_R - NECK_R) * r**1.3
    v = np.stack([rad * np.sin(a), -CAPE_LEN * r, rad * np.cos(a)], 1)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    if float((n * v[t[:, 0]] * [1, 0, 1]).sum()) < 0:  # inward: turn the triangles around
        t = t[:, ::-1].copy()
    return v, t


def body_parts(pos: np.ndarray, frame: np.ndarray, phase: float) -> tuple[list[list[Any]], list[dict[str, Any]]]:
    """A walker's body at its feet ``pos``, ``frame`` (right, up, behind) and stride ``phase``:
    capsules to draw and a cape's colliders (demo.walker_parts; demoscene's two walkers)."""

    def at(x: float, y: float, z: float) -> np.ndarray:
        return pos + frame @ np.array([x, y, z])

    swing = 0.45 * math.sin(phase)
    parts: list[list[Any]] = []
    colliders: list[dict[str, Any]] = []
    torso = (at(0, 1.3, 0.0), at(0, 0.98, 0.0), 0.165)
    parts.append([*torso, MANNEQUIN])
    colliders.append({"type": "capsule", "p0": tuple(torso[0]), "p1": tuple(torso[1]), "radius": 0.18})
    for side, s in ((-1, swing), (1, -swing)):
        hip = at(0.09 * side, 0.92, 0.0)
        foot = at(0.09 * side, 0.08, 0.0) + frame @ np.array([0.0, 0.0, -0.84 * math.sin(s)])
        foot[1] = pos[1] + 0.08 + 0.05 * max(0.0, math.sin(phase + (0 if side < 0 else math.pi)))
        parts.append([hip, foot, 0.075, MANNEQUIN])
        colliders.append({"type": "capsule", "p0": tuple(hip), "p1": tuple(foot), "radius": 0.09})
        shoulder = at(0.2 * side, 1.36, 0.0)
        hand = at(0.23 * side, 0.78, 0.0) + frame @ np.array([0.0, 0.0, 0.45 * math.sin(s)])
        parts.append([shoulder, hand, 0.055, MANNEQUIN])
    parts.append([at(0, 1.42, 0), at(0, 1.52, 0), 0.06, SKIN])  # neck
    head = at(0, 1.66, 0)
    parts.append([head, head, 0.115, SKIN])
    colliders.append({"type": "sphere", "center": tuple(head), "radius": 0.14})
    return [[np.asarray(p[0]).tolist(), np.asarray(p[1]).tolist(), p[2], p[3]] for p in parts], colliders


def grid_uv(rows: int, cols: int) -> np.ndarray:
    """Texture coordinates of a grid's vertices: u along a row (0..1), v down the columns."""
    u = np.tile(np.linspace(0.0, 1.0, cols), rows)
    v = np.repeat(np.linspace(0.0, 1.0, rows), cols)
    return np.stack([u, v], 1)


def cape_texture(uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A royal-blue cape with a gold border, lined in crimson."""
    from .rendermath import linear

    u, v = uv[:, 0], uv[:, 1]
    front = np.broadcast_to(linear((38, 52, 132)), (len(u), 3)).copy()
    border = (u < 0.035) | (u > 0.965) | (v > 0.955)
    front[border] = linear((214, 166, 60))
    back = np.broadcast_to(linear((150, 26, 40)), (len(u), 3)).copy()
    return front, back
