"""Collision of a cloth with itself, in float64 numpy: the reference of kernels/selfcollide.cl, and
the penetration metric of issue 22 (what is left inside the thickness, behind a collider or inside
a mesh collider: meshes.py).

Self-collision (feature ``self_collision``, protocol 1.6): a vertex keeps the material's
``thickness`` from every vertex of its cloth that is further than ``thickness`` from it at rest
(closer ones are its own neighbourhood: NvCloth's rule, which needs no link graph and holds for
meshes as for grids). Each pass projects every contact at once (Jacobi): a pair closer than the
thickness moves each free end by ``contact_stiffness`` times its inverse-mass share of the depth,
along the pair's direction (the rest-pose direction where the two coincide); the device's spatial
hash finds the same pairs as the brute force here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .meshes import CollisionMesh, depth_inside
from .params import COLLIDER_CAPSULE, COLLIDER_PLANE, SELF_COLLISION_PASSES

_CHUNK = 256  # rows of the pairwise distances computed at once


def contact_pairs(
    x: np.ndarray, rest: np.ndarray, thickness: float, apart_at_rest: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair (i, j), i != j, closer than ``thickness`` in ``x`` and further than
    ``apart_at_rest`` (default: ``thickness``) in ``rest``: the contacts self-collision resolves
    and the metric counts."""
    th2 = thickness * thickness
    rest2 = th2 if apart_at_rest is None else apart_at_rest * apart_at_rest
    out_i, out_j = [], []
    for lo in range(0, len(x), _CHUNK):
        hi = min(lo + _CHUNK, len(x))
        d = x[lo:hi, None, :] - x[None, :, :]
        near = np.einsum("ijk,ijk->ij", d, d) < th2
        if not near.any():
            continue
        i, j = np.nonzero(near)
        rd = rest[lo + i] - rest[j]
        far = (np.einsum("ij,ij->i", rd, rd) > rest2) & (lo + i != j)
        out_i.append(lo + i[far])
        out_j.append(j[far])
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_i), np.concatenate(out_j)


def self_collide(
    x: np.ndarray,
    invm: np.ndarray,
    rest: np.ndarray,
    thickness: float,
    stiffness: float,
    passes: int = SELF_COLLISION_PASSES,
) -> None:
    """Self-collision's passes over one cloth's positions ``x`` in place (kernels/selfcollide.cl)."""
    if not (thickness > 0.0 and stiffness > 0.0):
        return
    for _ in range(passes):
        i, j = contact_pairs(x, rest, thickness)
        i, j = i[invm[i] > 0], j[invm[i] > 0]
        if len(i) == 0:
            continue
        d = x[i] - x[j]
        dist = np.linalg.norm(d, axis=1)
        rd = rest[i] - rest[j]
        apart = dist > 1e-12
        n = np.where(
            apart[:, None],
            d / np.where(apart, dist, 1.0)[:, None],
            rd / np.linalg.norm(rd, axis=1)[:, None],
        )
        share = invm[i] / (invm[i] + invm[j])
        corr = np.zeros_like(x)
        np.add.at(corr, i, n * (stiffness * (thickness - dist) * share)[:, None])
        x += corr


@dataclass(frozen=True)
class Penetration:
    """What one cloth leaves inside its thickness or behind its colliders."""

    pairs: int  # unordered vertex pairs closer than thickness - tolerance, further apart at rest
    deepest_pair: float  # metres: thickness minus the closest such pair's distance (0: none)
    behind: int  # free vertices more than tolerance behind a collider's surface
    deepest_behind: float  # metres: the deepest of those (0: none)

    @property
    def total(self) -> int:
        return self.pairs + self.behind


def penetration(
    x: np.ndarray,
    rest: np.ndarray,
    thickness: float,
    colliders: np.ndarray | None = None,
    invm: np.ndarray | None = None,
    tolerance: float = 1e-3,
    meshes: Sequence[tuple[CollisionMesh, np.ndarray]] = (),
) -> Penetration:
    """The penetration metric of one cloth's positions ``x``: non-neighbouring vertex pairs closer
    than ``thickness - tolerance`` (neighbours: within ``thickness`` at rest, as self-collision
    has them), and free vertices (``invm`` > 0; all without it) more than ``tolerance`` inside
    a packed collider (params.pack_colliders: spheres, capsules, behind planes) or inside a mesh
    collider (``meshes``: (mesh, pose) pairs, meshes.depth_inside). The tolerance absorbs float32
    rounding and what a finite number of passes leaves."""
    x = np.asarray(x, np.float64)
    rest = np.asarray(rest, np.float64)
    pairs, deepest_pair = 0, 0.0
    if thickness > tolerance:
        i, j = contact_pairs(x, rest, thickness - tolerance, thickness)
        keep = i < j
        pairs = int(keep.sum())
        if pairs:
            deepest_pair = float(thickness - np.linalg.norm(x[i[keep]] - x[j[keep]], axis=1).min())
    depth = np.zeros(len(x))
    for c in np.asarray(colliders if colliders is not None else np.zeros((0, 2, 4)), np.float64).reshape(-1, 2, 4):
        depth = np.maximum(depth, _depth_inside(x, c))
    for mesh, pose in meshes:
        depth = np.maximum(depth, depth_inside(x, mesh, pose))
    if invm is not None:
        depth[np.asarray(invm) <= 0] = 0.0
    inside = depth > tolerance
    return Penetration(pairs, deepest_pair, int(inside.sum()), float(depth.max()) if inside.any() else 0.0)


def _depth_inside(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """How far each point is inside one packed collider (<= 0 outside). Written apart from the
    solvers' push-out (reference.collide, colliders.cl) on purpose: the metric checks them."""
    kind = int(round(float(c[1, 3])))
    if kind == COLLIDER_PLANE:
        n = c[0, :3] / max(float(np.linalg.norm(c[0, :3])), 1e-30)
        return c[0, 3] - x @ n
    p0, p1, r = c[0, :3], c[1, :3], float(c[0, 3])
    if kind == COLLIDER_CAPSULE:
        axis = p1 - p0
        aa = float(axis @ axis)
        t = np.clip(((x - p0) @ axis) / aa, 0.0, 1.0) if aa > 0 else np.zeros(len(x))
        centre = p0 + t[:, None] * axis
    else:
        centre = np.broadcast_to(p0, x.shape)
    return r - np.linalg.norm(x - centre, axis=1)
