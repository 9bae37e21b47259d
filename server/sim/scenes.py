"""Scenes (protocol 1.7): cloths of one scene collide with each other, cloths of different scenes
never interact. What every World keeps of them (which cloths are in which scene, the scene's
colliders), and inter-cloth collision in float64 numpy: the reference of kernels/intercollide.cl
(drape.server.sim.opencl.scenes) and the metric of what it leaves.

Inter-cloth collision runs once per step (tick), after every cloth's own solve (its substeps,
links, self-collision, colliders): a World-level phase, as NvCloth puts inter-collision on its
Solver. It is INTER_COLLISION_ROUNDS rounds, each of which finds the contacts at the round's
start positions, then iterates them:

1. every cloth's bounds (its positions' box grown by half its thickness x margin x
   INTER_COLLISION_REACH): the broad phase, a cloth whose box meets no other box of its scene
   takes no part;
2. the candidates: every pair of vertices of two different cloths of one scene closer than
   INTER_COLLISION_REACH times the pair's contact distance ``d' = (thickness_a + thickness_b) / 2
   x INTER_COLLISION_MARGIN`` (the materials' ``thickness``), the distance the solve sets them at;
3. INTER_COLLISION_PASSES / INTER_COLLISION_ROUNDS passes, each of which moves each free end of
   every candidate pair now closer than ``d'`` by ``k (d' - |x_a - x_b|) w_a / (w_a + w_b)``
   along the pair's direction (``k`` the mean of the two materials' ``contact_stiffness``, ``w``
   inverse masses; two coincident vertices part along +y for the cloth added first, -y for the
   other): Jacobi, every contact from the same positions, so the order of the work does not
   matter. Where the pair's direction is within INTER_COLLISION_SHOCK (a cosine) of +y, the lower
   end's ``w`` is scaled down linearly to 0 straight below (``shock``, where the upper end is
   free): shock propagation, so a pile's weight is carried down to what its bottom rests on. After each
   pass, every vertex the pass moved is put back out of its cloth's colliders (spheres,
   capsules, planes at their end-of-step pose, without friction: the cloth step's own
   projection, drape.server.sim.reference.collide), so a pile's corrections never push its bottom
   cloth through what it rests on.

A pair that comes within ``d'`` during a round's passes from further than the reach at the
round's start is seen by the next round (a pile landing at its contact distance per tick: the
second cloth, pushed back out of the first, lands in the third's way), or else left to the next
step. A vertex moved by ``dx`` in a round's passes also gains ``dx / dt`` of velocity (the step's
velocity is its displacement over the step, as PBD has it), so contacts carry cloths along, but
no more along ``dx`` than it had (``inelastic``): a contact stops an approach and never throws a
vertex off (coincident cloths of a landing pile parted by a contact distance in one tick would
otherwise leave at that distance per tick).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from drape.client.protocol.vocabulary import MAX_SCENE_COLLIDERS  # noqa: F401 (the scenes' collider capacity)

from .reference import collide

#: Inter-cloth collision's passes per step (the kernels' -DINTER_COLLISION_PASSES, the reference's).
INTER_COLLISION_PASSES = 8
#: The solve keeps each pair this much further than its contact distance (1.05: 1.5 mm at 3 cm),
#: so that what the Jacobi passes leave of many contacts at once (a cloth resting on another)
#: stays outside the contact distance; the device multiplies each cloth's thickness by it.
INTER_COLLISION_MARGIN = 1.05
#: Candidate pairs: closer than this many contact distances at the step's start (-DIC_REACH).
INTER_COLLISION_REACH = 1.3
#: The candidates are found again this many times a step, each followed by its share of the passes
#: (-DIC_ROUNDS): a pair the passes bring together from further than the reach is seen in the next
#: round (a pile landing: its second cloth pushed back out of the bottom one into the third's way).
INTER_COLLISION_ROUNDS = 4
#: The device's later rounds (kernels/intercollide.cl): only the vertices that moved further than
#: this many of the World's largest contact distances since their candidates were found walk the
#: hash again; the others keep their unmoved candidates and gain the moved ones that find them. A
#: pair missed so was further than the reach when last found, its ends moving less than 3 x this
#: since (the reach's margin, 0.3): not in contact at the round's start. This reference keeps the
#: full find each round.
INTER_COLLISION_SKIN = 0.1
#: Shock propagation (-DIC_SHOCK): where a contact's direction is within this cosine of +y, the
#: lower end yields less, and not at all straight below (its inverse mass scaled by ``shock``),
#: so a pile's weight is carried down to what its bottom rests on instead of sinking through it.
INTER_COLLISION_SHOCK = 0.7
#: Cloths of one scene at most (a scene is a shared space; the spatial hash is keyed by scene).
MAX_SCENE_CLOTHS = 1024

_NONE = np.zeros((0, 2, 4))

_CHUNK = 512  # rows of the pairwise distances computed at once


@dataclass
class Scene:
    """One scene of a World: its cloths (handles, in the order they joined) and its colliders
    (packed as params.pack_colliders), which act on each of its cloths beside the cloth's own."""

    name: str
    handles: list[int] = field(default_factory=list)
    colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4), np.float32))


@dataclass
class SceneCloth:
    """What inter-cloth collision reads and writes of one cloth: views of its state."""

    x: np.ndarray  # (n, 3) positions, moved in place
    v: np.ndarray  # (n, 3) velocities, moved in place
    invm: np.ndarray  # (n,) inverse masses (0: pinned)
    thickness: float
    stiffness: float
    colliders: np.ndarray = field(default_factory=lambda: _NONE)  # (m, 2, 4) packed, at the step's end pose


def bounds(x: np.ndarray, grow: float) -> np.ndarray:
    """(2, 3): the box of positions ``x`` grown by ``grow`` on every side."""
    return np.stack([x.min(axis=0) - grow, x.max(axis=0) + grow])


def overlapping(boxes: list[np.ndarray]) -> list[tuple[int, int]]:
    """The broad phase: every pair (a, b), a < b, of boxes that meet."""
    out = []
    for a in range(len(boxes)):
        for b in range(a + 1, len(boxes)):
            if np.all(boxes[a][0] <= boxes[b][1]) and np.all(boxes[b][0] <= boxes[a][1]):
                out.append((a, b))
    return out


def _pairs(xa: np.ndarray, xb: np.ndarray, d: float) -> tuple[np.ndarray, np.ndarray]:
    """Every (i, j) with |xa[i] - xb[j]| < d."""
    d2 = d * d
    out_i, out_j = [], []
    for lo in range(0, len(xa), _CHUNK):
        hi = min(lo + _CHUNK, len(xa))
        diff = xa[lo:hi, None, :] - xb[None, :, :]
        i, j = np.nonzero(np.einsum("ijk,ijk->ij", diff, diff) < d2)
        out_i.append(lo + i)
        out_j.append(j)
    if not out_i:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(out_i), np.concatenate(out_j)


def inter_collide(cloths: list[SceneCloth], dt: float, passes: int = INTER_COLLISION_PASSES) -> None:
    """Inter-cloth collision of one scene's cloths (in the order they joined it), in place:
    INTER_COLLISION_ROUNDS rounds, each finding the candidates at its start positions and running
    its share of the ``passes``."""
    if len(cloths) < 2:
        return
    for _ in range(INTER_COLLISION_ROUNDS):
        start = [c.x.copy() for c in cloths]
        cands = _candidates(cloths)
        for _ in range(passes // INTER_COLLISION_ROUNDS):
            _pass(cloths, cands)
        for c, x0 in zip(cloths, start, strict=True):
            c.v[:] = inelastic(c.v, c.x - x0, dt)


def inelastic(v: np.ndarray, dx: np.ndarray, dt: float) -> np.ndarray:
    """Velocities ``v`` after a round's displacement ``dx``: ``v + dx / dt``, but no faster along
    ``dx`` than ``v`` was (or 0): a contact stops an approach, never throws a vertex off (a pile's
    cloths landing on each other at their contact distance a tick are not launched)."""
    out = v + dx / dt
    dl = np.linalg.norm(dx, axis=1)
    n = dx / np.where(dl > 0, dl, 1.0)[:, None]
    over = np.einsum("ij,ij->i", out, n) - np.maximum(np.einsum("ij,ij->i", v, n), 0.0)
    return np.where(((dl > 0) & (over > 0))[:, None], out - n * over[:, None], out)


Candidates = list[tuple[int, int, np.ndarray, np.ndarray, float, float]]


def _candidates(cloths: list[SceneCloth]) -> Candidates:
    """(a, b, i, j, d, k): the candidate pairs of cloths a and b (a < b) at their positions now."""
    boxes = [bounds(c.x, 0.5 * c.thickness * INTER_COLLISION_MARGIN * INTER_COLLISION_REACH) for c in cloths]
    cands = []
    for a, b in overlapping(boxes):
        ca, cb = cloths[a], cloths[b]
        d = 0.5 * (ca.thickness + cb.thickness) * INTER_COLLISION_MARGIN
        k = 0.5 * (ca.stiffness + cb.stiffness)
        if not (d > 0.0 and k > 0.0):
            continue
        i, j = _pairs(ca.x, cb.x, d * INTER_COLLISION_REACH)
        keep = (ca.invm[i] + cb.invm[j]) > 0
        if np.any(keep):
            cands.append((a, b, i[keep], j[keep], d, k))
    return cands


def _pass(cloths: list[SceneCloth], cands: Candidates) -> None:
    """One Jacobi pass over the candidates, then each moved vertex out of its cloth's colliders."""
    corr = [np.zeros_like(c.x) for c in cloths]
    for a, b, i0, j0, d, k in cands:
        ca, cb = cloths[a], cloths[b]
        diff = ca.x[i0] - cb.x[j0]
        dist = np.linalg.norm(diff, axis=1)
        near = dist < d
        if not np.any(near):
            continue
        i, j, diff, dist = i0[near], j0[near], diff[near], dist[near]
        wa, wb = ca.invm[i], cb.invm[j]
        apart = dist > 1e-12
        n = np.where(apart[:, None], diff / np.where(apart, dist, 1.0)[:, None], np.array([0.0, 1.0, 0.0]))
        m = shock(n[:, 1])  # the lower end of a stacked pair yields less, none where it is straight below
        wa = np.where((n[:, 1] < 0.0) & (wb > 0), wa * m, wa)
        wb = np.where((n[:, 1] > 0.0) & (wa > 0), wb * m, wb)
        push = n * (k * (d - dist) / (wa + wb))[:, None]
        np.add.at(corr[a], i, push * wa[:, None])
        np.add.at(corr[b], j, -push * wb[:, None])
    for c, dx in zip(cloths, corr, strict=True):
        c.x += dx
        if len(c.colliders):
            _keep_out(c, np.flatnonzero(np.any(dx != 0.0, axis=1)))


def shock(ny: np.ndarray) -> np.ndarray:
    """Shock propagation: the factor of the lower end's inverse mass in a contact whose direction
    has ``ny`` of +y: 1 up to INTER_COLLISION_SHOCK, falling linearly to 0 straight up or down
    (continuous, so that rounding never flips a contact's shares)."""
    return np.clip((1.0 - np.abs(ny)) / (1.0 - INTER_COLLISION_SHOCK), 0.0, 1.0)


def _keep_out(c: SceneCloth, rows: np.ndarray) -> None:
    """Rows ``rows`` of ``c`` back out of its colliders at their end pose, without friction (the
    cloth step's projection; kernels/intercollide.cl calls colliders.cl's collide_vertex so)."""
    if len(rows):
        x = c.x[rows]
        collide(x, x.copy(), c.invm[rows], c.colliders, c.colliders, 0.0)
        c.x[rows] = x


@dataclass(frozen=True)
class ScenePenetration:
    """What a scene's cloths leave inside each other's contact distance."""

    pairs: int  # vertex pairs of two different cloths closer than their contact distance - tolerance
    deepest: float  # metres: the contact distance minus the closest such pair's distance (0: none)


def scene_penetration(xs: list[np.ndarray], thicknesses: list[float], tolerance: float = 1e-3) -> ScenePenetration:
    """The penetration metric between the cloths of one scene (positions ``xs``): pairs of
    vertices of two different cloths closer than ``(t_a + t_b) / 2 - tolerance``."""
    pairs, deepest = 0, 0.0
    xs = [np.asarray(x, np.float64) for x in xs]
    for a in range(len(xs)):
        for b in range(a + 1, len(xs)):
            d = 0.5 * (thicknesses[a] + thicknesses[b])
            if d <= tolerance:
                continue
            i, j = _pairs(xs[a], xs[b], d - tolerance)
            pairs += len(i)
            if len(i):
                deepest = max(deepest, float(d - np.linalg.norm(xs[a][i] - xs[b][j], axis=1).min()))
    return ScenePenetration(pairs, deepest)
