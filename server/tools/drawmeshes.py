"""What the drawing draws (server/tools/render.py): everything as triangles with per-vertex
normals and colours. Cloths (their normals averaged over the triangles around each vertex, so
shading is smooth across the grid; two-sided, with a colour for each side), and collider balls
and capsules (closed meshes, from cached unit templates)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from .rendermath import linear, unit


@dataclass
class Mesh:
    """Triangles to draw: positions, unit normals, linear colours of the front and back sides
    (n, 3) each, triangles (m, 3); ``two_sided``: a thin sheet (the side facing the viewer is lit,
    light passes through); ``specular`` / ``shininess``: Blinn-Phong highlight."""

    positions: np.ndarray
    normals: np.ndarray
    front: np.ndarray
    back: np.ndarray
    triangles: np.ndarray
    two_sided: bool = False
    specular: float = 0.0
    shininess: float = 20.0
    shadows: bool = True  # casts shadows
    sheen: float = 0.0  # brightening at grazing angles (velvet, satin)
    uv: np.ndarray | None = None  # (n, 2) texture coordinates, with ``texture``
    texture: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None  # uv (k, 2) -> front, back


def vertex_normals(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Per-vertex unit normals: the area-weighted sum of the normals of the triangles around each."""
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, t[:, k], face)
    return unit(n)


def cloth_mesh(pos: Any, tris: Any, colour: Any, back: Any = None) -> Mesh:
    """A two-sided cloth; ``colour`` / ``back``: one sRGB colour or one per vertex (n, 3).
    Triangles with a non-finite corner are dropped."""
    p = np.asarray(pos, np.float64).reshape(-1, 3)
    t = np.asarray(tris, np.int64).reshape(-1, 3)
    if len(t) and (t.min() < 0 or t.max() >= len(p)):
        raise ValueError(f"triangle indices out of range for {len(p)} positions")
    t = t[np.isfinite(p[t]).all(axis=(1, 2))] if len(t) else t
    p = np.where(np.isfinite(p), p, 0.0)
    front = np.broadcast_to(linear(colour), p.shape).copy()
    backc = front * 0.8 if back is None else np.broadcast_to(linear(back), p.shape).copy()
    return Mesh(p, vertex_normals(p, t) if len(t) else np.zeros_like(p), front, backc, t, True, 0.04, 10.0)


@lru_cache(maxsize=8)
def _unit_rings(lat: int, lon: int) -> tuple[np.ndarray, np.ndarray]:
    """Ring angles of a UV sphere: ``lat + 1`` latitudes from -90 to 90 degrees, ``lon`` longitudes."""
    return np.linspace(-math.pi / 2, math.pi / 2, lat + 1), np.linspace(0, 2 * math.pi, lon, endpoint=False)


def _ring_triangles(rings: int, lon: int) -> np.ndarray:
    """Triangles joining ``rings`` consecutive rings of ``lon`` vertices each."""
    i, j = np.meshgrid(np.arange(rings - 1), np.arange(lon), indexing="ij")
    a = i * lon + j
    b = i * lon + (j + 1) % lon
    c = a + lon
    d = b + lon
    return np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])


@lru_cache(maxsize=64)
def _capsule_template(segments: int, pieces: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A unit capsule in its own frame (e1, e2, axis): vertex directions (n, 3), each vertex's
    place along the axis (0 at p0, 1 at p1) and the triangles; ``pieces`` cylinder sections
    (0: a sphere)."""
    lats, lons = _unit_rings(max(4, segments // 2), segments)
    around = np.stack([np.cos(lons), np.sin(lons), np.zeros_like(lons)], 1)
    dirs, along = [], []
    for phi in lats:
        ring = math.cos(phi) * around + [0.0, 0.0, math.sin(phi)]
        dirs.append(ring)
        along.append(np.full(len(lons), 1.0 if phi > 0 else 0.0))
        if abs(phi) < 1e-9 and pieces:  # the cylinder between the ends, in short pieces
            for f in np.linspace(0.0, 1.0, pieces + 1)[1:]:
                dirs.append(ring)
                along.append(np.full(len(lons), f))
    return np.concatenate(dirs), np.concatenate(along), _ring_triangles(len(dirs), len(lons))


def capsule_mesh(
    p0: Any, p1: Any, radius: float, colour: Any, specular: float = 0.35, shininess: float = 40.0, segments: int = 24
) -> Mesh:
    """A capsule (a sphere when ``p0`` == ``p1``): smooth normals, ``segments`` around."""
    a, b = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = b - a
    ln = float(np.linalg.norm(axis))
    w = axis / ln if ln > 1e-9 else np.array([0.0, 1.0, 0.0])
    e1 = unit(np.cross(w, [1.0, 0, 0] if abs(w[0]) < 0.9 else [0, 0, 1.0]))
    e2 = np.cross(w, e1)
    pieces = int(np.clip(math.ceil(ln / (3 * radius)), 1, 48)) if ln > 1e-9 else 0
    local, along, t = _capsule_template(segments, pieces)
    n = local @ np.array([e1, e2, w])
    p = a + along[:, None] * axis + radius * n
    c = np.broadcast_to(linear(colour), p.shape).copy()
    return Mesh(p, n, c, c, t, False, specular, shininess)


def sphere_mesh(centre: Any, radius: float, colour: Any, specular: float = 0.35, shininess: float = 40.0) -> Mesh:
    return capsule_mesh(centre, centre, radius, colour, specular, shininess)
