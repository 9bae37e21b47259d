"""The penetration scenarios of issue 22 (no tunnelling): each run on a World, the penetration
metric (drape.server.sim.collision.penetration) reported at the end of every tick.

    python -m drape.server.tools.penetration [--solver workgroup] [--scenario NAME ...] [--size full|small]
                                             [--substeps 1,2,4,8] [--self-collision on,off] [--json FILE]

Scenarios (every cloth 5 mm thick with self-collision on, 60 Hz, 10 iterations, 2 substeps):

- ``capsule_hit``: a cloth hanging by its top corners hit at mid-height by a capsule (radius
  4 cm, wider than the cloth) crossing it at 10 m/s (8 cm per substep: the capsule's own
  diameter, so a test at the end of each substep alone pushes the cloth out of its far side);
- ``plane_drop``: a flat cloth dropped onto a plane, reaching it at 20 m/s (it falls 20.4 m);
- ``stack``: 8 cloths (each its own: cloths do not collide with each other without a scene)
  dropped from a stack 2 cm apart onto a plane, then lying on it;
- ``cape_run``: a cape pinned across a running character's shoulders (a torso, two legs and two
  arms of capsules moved every tick: swinging limbs at 2.5 strides a second, running up to
  5 m/s, turning, stopping).
- ``cape_body`` (1.8 mesh colliders): the same cape and run on a body mesh (the 7,565-triangle
  procedural humanoid of drape.server.sim.bodymesh) moved rigidly by its pose every tick.
- ``scene_drag`` (1.7 scenes): two capes of one scene (two players'), pinned at their shoulders
  0.3 m apart, dragged 0.3 m through each other over 30 ticks, then held;
- ``scene_stack`` (1.7 scenes): the ``stack`` in one scene, so that its cloths collide with each
  other as they land on each other (at 4 cm a tick at the small size: their contact distance).
  The scene scenarios' cloths are 0.6 times their vertex spacing thick (contacts are
  vertex-vertex: a vertex slips between the vertices of a cloth spaced over twice the contact
  distance).

Each tick's record: ``pairs`` (vertex pairs of one cloth closer than the thickness, summed over
the cloths), ``scene_pairs`` (vertex pairs of two cloths of one scene closer than their contact
distance: drape.server.sim.scenes.scene_penetration), ``behind`` (free vertices behind a
collider's surface), their depths, and
``crossed`` (free vertices whose motion over the tick went through a sphere or capsule: a test
at the end of each substep alone lets a fast capsule pass through the cloth and leaves no
vertex inside it at the end of the tick, which ``behind`` cannot see). The scenarios are
shared with the tests (tests/sim/test_ccd.py, small sizes) and the stability suite.
``--substeps`` and ``--self-collision`` give the trade of collision's accuracy against its cost
(each row's ``ms_per_tick``: the median tick of the World's step alone).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from drape.server.sim import make_world
from drape.server.sim.bodymesh import body_mesh
from drape.server.sim.collision import penetration
from drape.server.sim.fabric import Fabric, cook_grid
from drape.server.sim.params import (
    COLLIDER_CAPSULE,
    COLLIDER_PLANE,
    Capsule,
    ClothParams,
    Features,
    LinkOptions,
    Material,
    Plane,
    pack_colliders,
)
from drape.server.sim.scenes import scene_penetration
from drape.server.sim.world import World

HZ = 60
DT = 1.0 / HZ
THICKNESS = 0.005
CAPSULE_SPEED = 10.0
DROP_SPEED = 20.0
CROSSED_CORE = 0.25  # crossed(): the share of a collider's radius a vertex's chord must come within
SIZES = {"full": 32, "small": 9}  # vertices along a cloth's side


#: The scenarios' cloth: self-collision at 5 mm, tethers, 10 iterations, 2 substeps (each
#: scenario sets its friction; ``--substeps`` and ``--self-collision off`` change this).
BASE = ClothParams(
    features=Features(colliders=True, self_collision=True, tethers=True),
    material=Material(thickness=THICKNESS),
    iterations=10,
    substeps=2,
)


def params(base: ClothParams, friction: float = 0.0) -> ClothParams:
    return base.with_(material=replace(base.material, friction=friction))


@dataclass
class Cloth:
    """One cloth of a scenario and what the metric needs of it."""

    handle: int
    fabric: Fabric
    params: ClothParams
    colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4), np.float32))  # at the tick's end
    meshes: list = field(default_factory=list)  # (mesh, pose) at the tick's end (1.8)
    scene: str | None = None  # 1.7: the cloths of one scene collide with each other


@dataclass
class Tick:
    """The state after one tick: each cloth's positions (and the previous tick's, for ``crossed``)."""

    index: int
    seconds: float  # the World's step and positions (not the metric)
    cloths: list[Cloth]
    x: list[np.ndarray]
    x_before: list[np.ndarray]
    colliders_before: list[np.ndarray]


@dataclass
class Record:
    """The penetration metric of one tick, over every cloth of a scenario."""

    tick: int
    seconds: float = 0.0
    pairs: int = 0
    deepest_pair: float = 0.0
    scene_pairs: int = 0
    deepest_scene_pair: float = 0.0
    behind: int = 0
    deepest_behind: float = 0.0
    crossed: int = 0

    @property
    def total(self) -> int:
        return self.pairs + self.scene_pairs + self.behind + self.crossed


def _stepper(world: World, cloths: list[Cloth], ticks: int, move: Callable[[int], None]) -> Iterator[Tick]:
    x = [world.positions(c.handle).copy() for c in cloths]
    for k in range(ticks):
        before = [c.colliders.copy() for c in cloths]
        move(k)
        for c in cloths:
            if c.params.features.colliders:
                world.set_colliders(c.handle, c.colliders)
        t0 = time.perf_counter()
        world.step(DT)
        now = [world.positions(c.handle).copy() for c in cloths]
        yield Tick(k, time.perf_counter() - t0, cloths, now, x, before)
        x = now


def capsule_hit(world: World, n: int, ticks: int = 12, base: ClothParams = BASE) -> Iterator[Tick]:
    """A 0.5 m cloth hanging by its top corners, a 4 cm capsule crossing it at 10 m/s."""
    fab = cook_grid(n, n, 0.5, 0.5, LinkOptions(bending=True), [0, n - 1], "vertical", (-0.25, 1.0, 0.0))
    p = params(base, 0.5)
    cloth = Cloth(world.add(fab, p), fab, p)
    y = float(fab.rest_positions[:, 1].mean())

    def move(k: int) -> None:
        z = -0.25 + CAPSULE_SPEED * DT * (k + 1)
        cloth.colliders = pack_colliders([Capsule((-0.5, y, z), (0.5, y, z), 0.04)])

    cloth.colliders = pack_colliders([Capsule((-0.5, y, -0.25), (0.5, y, -0.25), 0.04)])
    return _stepper(world, [cloth], ticks, move)


def plane_drop(world: World, n: int, ticks: int = 150, base: ClothParams = BASE) -> Iterator[Tick]:
    """A flat 0.5 m cloth falling 20.4 m onto a plane (20 m/s at contact), then lying on it."""
    height = DROP_SPEED**2 / (2 * 9.81)
    fab = cook_grid(n, n, 0.5, 0.5, LinkOptions(bending=True), [], "horizontal", (-0.25, height + 0.01, -0.25))
    p = params(base)
    cloth = Cloth(world.add(fab, p), fab, p)
    cloth.colliders = pack_colliders([Plane((0.0, 1.0, 0.0), 0.0)])
    return _stepper(world, [cloth], ticks, lambda k: None)


def stack(world: World, n: int, ticks: int = 90, count: int = 8, base: ClothParams = BASE) -> Iterator[Tick]:
    """``count`` cloths stacked 2 cm apart, 0.3 m above a plane, dropped (each its own)."""
    cloths = []
    for i in range(count):
        fab = cook_grid(n, n, 0.5, 0.5, LinkOptions(bending=True), [], "horizontal", (-0.25, 0.3 + 0.02 * i, -0.25))
        p = params(base, 0.3)
        c = Cloth(world.add(fab, p), fab, p)
        c.colliders = pack_colliders([Plane((0.0, 1.0, 0.0), 0.0)])
        cloths.append(c)
    return _stepper(world, cloths, ticks, lambda k: None)


@dataclass
class Runner:
    """The cape's character: runs up to 5 m/s for 1.5 s, turns left for 1.5 s, stops."""

    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    heading: float = 0.0
    speed: float = 0.0

    def advance(self, t: float) -> None:
        if t < 1.5:
            self.speed = min(5.0, self.speed + 6.0 * DT)
        elif t < 3.0:
            self.heading += 1.6 * DT
        else:
            self.speed = max(0.0, self.speed - 8.0 * DT)
        h = self.heading
        self.pos = self.pos + self.speed * DT * np.array([math.sin(h), 0.0, math.cos(h)])


def character(t: float, pos: np.ndarray, heading: float, speed: float) -> tuple[tuple[Capsule, ...], np.ndarray]:
    """A running character at ``pos`` facing ``heading`` (radians about y, 0: +z): its capsules
    (torso, legs and arms swinging with the stride) and the world transform of its frame."""
    c, s = math.cos(heading), math.sin(heading)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    swing = 0.6 * math.sin(2 * math.pi * 2.5 * t) * min(1.0, speed / 5.0)

    def limb(top, length, angle, r):
        top = np.asarray(top, np.float64)
        end = top + length * np.array([0.0, -math.cos(angle), math.sin(angle)])
        return top, end, r

    parts = [
        (np.array([0.0, 0.95, 0.0]), np.array([0.0, 1.35, 0.0]), 0.16),  # torso
        limb((-0.1, 0.9, 0.0), 0.85, swing, 0.07),  # legs
        limb((0.1, 0.9, 0.0), 0.85, -swing, 0.07),
        limb((-0.24, 1.38, 0.0), 0.6, -swing, 0.05),  # arms
        limb((0.24, 1.38, 0.0), 0.6, swing, 0.05),
    ]
    return tuple(Capsule(tuple(rot @ a + pos), tuple(rot @ b + pos), r) for a, b, r in parts), rot


def cape_run(world: World, n: int, ticks: int = 300, base: ClothParams = BASE) -> Iterator[Tick]:
    """A 0.6 x 1.0 m cape pinned across the shoulders of a character that runs up to 5 m/s,
    turns left and stops (codecbench's cape_run motion, with a body to hit)."""
    shoulders = np.array([0.0, 1.42, -0.2])
    top = np.arange(n)  # row 0, at the origin's height (the grid's rows go down)
    fab = cook_grid(n, n, 0.6, 1.0, LinkOptions(bending=True), top, "vertical", tuple(shoulders - [0.3, 0, 0]))
    p = params(base, 0.3)
    cloth = Cloth(world.add(fab, p), fab, p)
    rest_top = fab.rest_positions[top] - shoulders
    run = Runner()

    def move(k: int) -> None:
        t = k * DT
        run.advance(t)
        caps, rot = character(t, run.pos, run.heading, run.speed)
        cloth.colliders = pack_colliders(caps)
        world.set_pin_targets(cloth.handle, top, (rest_top + shoulders) @ rot.T + run.pos)

    caps, _ = character(0.0, np.zeros(3), 0.0, 0.0)
    cloth.colliders = pack_colliders(caps)
    return _stepper(world, [cloth], ticks, move)


def cape_body(world: World, n: int, ticks: int = 300, base: ClothParams = BASE) -> Iterator[Tick]:
    """A 0.5 x 0.9 m cape pinned 2 cm behind the shoulders of a body mesh that runs as in
    ``cape_run`` (moved rigidly: the mesh's pose each tick)."""
    body = body_mesh()
    shoulders = np.array([0.0, 1.45, -0.12])
    top = np.arange(n)
    fab = cook_grid(n, n, 0.5, 0.9, LinkOptions(bending=True), top, "vertical", tuple(shoulders - [0.25, 0, 0]))
    p = params(base, 0.3)
    cloth = Cloth(world.add(fab, p), fab, p)
    rest_top = fab.rest_positions[top]
    run = Runner()
    pose = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    world.set_mesh(cloth.handle, body, pose)
    cloth.meshes = [(body, pose)]

    def move(k: int) -> None:
        run.advance(k * DT)
        c, s = math.cos(run.heading), math.sin(run.heading)
        rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        pose = np.concatenate([rot, run.pos[:, None]], axis=1)
        world.move_mesh(cloth.handle, pose)
        cloth.meshes = [(body, pose)]
        world.set_pin_targets(cloth.handle, top, rest_top @ rot.T + run.pos)

    return _stepper(world, [cloth], ticks, move)


def _scene_params(base: ClothParams, n: int, friction: float = 0.0) -> ClothParams:
    """A scene scenario's cloth: 0.6 times its vertex spacing (0.5 m / (n - 1)) thick, at least THICKNESS."""
    p = params(base, friction)
    return p.with_(material=replace(p.material, thickness=max(THICKNESS, 0.6 * 0.5 / (n - 1))))


def scene_drag(world: World, n: int, ticks: int = 45, base: ClothParams = BASE) -> Iterator[Tick]:
    """Two capes of one scene, the second higher and to the side, pinned by their shoulders 0.3 m
    apart in z, dragged 0.3 m towards each other over 30 ticks: their lower halves pass through
    each other (the issue's "two capes of two clients dragged through each other in one scene")."""
    pins = np.array([0, n - 1])
    p = _scene_params(base, n)
    cloths = []
    for origin in ((-0.25, 1.0, -0.15), (-0.1, 1.25, 0.15)):
        fab = cook_grid(n, n, 0.5, 0.5, LinkOptions(bending=True), pins, "vertical", origin)
        cloths.append(Cloth(world.add(fab, p, scene="drag"), fab, p, scene="drag"))

    def move(k: int) -> None:
        s = min(1.0, (k + 1) / 30)
        for c, sign in zip(cloths, (1.0, -1.0), strict=True):
            world.set_pin_targets(c.handle, pins, c.fabric.rest_positions[pins] + [0.0, 0.0, sign * 0.3 * s])

    return _stepper(world, cloths, ticks, move)


def scene_stack(world: World, n: int, ticks: int = 90, count: int = 8, base: ClothParams = BASE) -> Iterator[Tick]:
    """``count`` cloths of one scene stacked 2 cm apart (1.5 thicknesses if more), 0.3 m above a
    plane, dropped onto it and onto each other."""
    p = _scene_params(base, n, 0.3)
    gap = max(0.02, 1.5 * p.material.thickness)
    cloths = []
    for i in range(count):
        fab = cook_grid(n, n, 0.5, 0.5, LinkOptions(bending=True), [], "horizontal", (-0.25, 0.3 + gap * i, -0.25))
        c = Cloth(world.add(fab, p, scene="pile"), fab, p, scene="pile")
        c.colliders = pack_colliders([Plane((0.0, 1.0, 0.0), 0.0)])
        cloths.append(c)
    return _stepper(world, cloths, ticks, lambda k: None)


SCENARIOS: dict[str, Callable[..., Iterator[Tick]]] = {
    "capsule_hit": capsule_hit,
    "plane_drop": plane_drop,
    "stack": stack,
    "cape_run": cape_run,
    "cape_body": cape_body,
    "scene_drag": scene_drag,
    "scene_stack": scene_stack,
}
#: Scenarios that still leave penetration (docs/collision.md, "What scenes do not do yet"): named
#: by ``--scenario``, never run by the tests that iterate SCENARIOS (none now).
OPEN: dict[str, Callable[..., Iterator[Tick]]] = {}


def _axis_point(x: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's nearest point on a packed sphere's centre or capsule's axis, and its parameter."""
    if int(round(float(c[1, 3]))) != COLLIDER_CAPSULE:
        return np.broadcast_to(c[0, :3], x.shape), np.zeros(len(x))
    axis = c[1, :3] - c[0, :3]
    t = np.clip((x - c[0, :3]) @ axis / max(float(axis @ axis), 1e-20), 0.0, 1.0)
    return c[0, :3] + t[:, None] * axis, t


def crossed(x: np.ndarray, x_before: np.ndarray, c_before: np.ndarray, c_now: np.ndarray, free: np.ndarray) -> int:
    """Free vertices whose straight motion over the tick, relative to a sphere or capsule, went
    through its core (within CROSSED_CORE of its radius of its centre or axis): what a collider
    passing through the cloth leaves, which the end of the tick alone (``behind``) cannot see.
    The start is carried with the collider (at its axis parameter) to the tick's end pose, and
    the straight path between sampled at 32 points. Only the tick's ends are known, so a vertex
    that went around the surface (a long way in one tick: slipping off the top of a capsule
    that had pinned it, say) is counted when its chord cuts the core; hence the small core, and
    the count is a lower bound of the vertices that went through (about a quarter of them)."""
    out = np.zeros(len(x), bool)
    for a, b in zip(c_before.reshape(-1, 2, 4), c_now.reshape(-1, 2, 4), strict=True):
        if int(round(float(b[1, 3]))) == COLLIDER_PLANE or not b[0, 3] > 0:
            continue
        pa, t = _axis_point(x_before, a)
        carried = x_before - pa + (b[0, :3] + t[:, None] * (b[1, :3] - b[0, :3]))
        for s in np.linspace(0.0, 1.0, 32):
            y = carried + s * (x - carried)
            out |= np.linalg.norm(y - _axis_point(y, b)[0], axis=1) < CROSSED_CORE * b[0, 3]
    return int((out & free).sum())


def measure(tick: Tick) -> Record:
    """The penetration metric of one tick over its cloths."""
    rec = Record(tick.index, tick.seconds)
    for c, x, xb, cb in zip(tick.cloths, tick.x, tick.x_before, tick.colliders_before, strict=True):
        free = ~c.fabric.pinned
        th = c.params.material.thickness
        p = penetration(x, c.fabric.rest_positions, th, c.colliders, free.astype(np.float64), meshes=c.meshes)
        rec.pairs += p.pairs
        rec.behind += p.behind
        rec.deepest_pair = max(rec.deepest_pair, p.deepest_pair)
        rec.deepest_behind = max(rec.deepest_behind, p.deepest_behind)
        rec.crossed += crossed(x, xb, cb, c.colliders, free)
    for name in {c.scene for c in tick.cloths} - {None}:
        members = [i for i, c in enumerate(tick.cloths) if c.scene == name]
        thicknesses = [tick.cloths[i].params.material.thickness for i in members]
        sp = scene_penetration([tick.x[i] for i in members], thicknesses)
        rec.scene_pairs += sp.pairs
        rec.deepest_scene_pair = max(rec.deepest_scene_pair, sp.deepest)
    return rec


def run(name: str, world: World, n: int, ticks: int | None = None, base: ClothParams = BASE) -> list[Record]:
    """One scenario's records, one per tick."""
    kw = {} if ticks is None else {"ticks": ticks}
    return [measure(t) for t in {**SCENARIOS, **OPEN}[name](world, n, base=base, **kw)]


def summary(records: list[Record]) -> dict:
    return {
        "ticks": len(records),
        "ms_per_tick": 1e3 * float(np.median([r.seconds for r in records])),
        "ticks_over_0": sum(r.total > 0 for r in records),
        "max_pairs": max(r.pairs for r in records),
        "max_scene_pairs": max(r.scene_pairs for r in records),
        "max_behind": max(r.behind for r in records),
        "max_crossed": max(r.crossed for r in records),
        "deepest_pair_mm": 1e3 * max(r.deepest_pair for r in records),
        "deepest_behind_mm": 1e3 * max(r.deepest_behind for r in records),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--solver", default="workgroup", help="workgroup, coloured, jacobi or reference")
    ap.add_argument("--scenario", nargs="*", default=list(SCENARIOS), choices=[*SCENARIOS, *OPEN])
    ap.add_argument("--size", default="full", choices=list(SIZES))
    ap.add_argument("--substeps", default="2", help="a comma list: the trade of substeps against penetration")
    ap.add_argument("--self-collision", default="on", help="on, off or on,off")
    ap.add_argument("--json", help="write every tick's records here")
    args = ap.parse_args(argv)
    out = {}
    for name in args.scenario:
        for sub in (int(v) for v in args.substeps.split(",")):
            for sc in args.self_collision.split(","):
                base = BASE.with_(substeps=sub, features=replace(BASE.features, self_collision=sc == "on"))
                world = make_world(args.solver)
                records = run(name, world, SIZES[args.size], base=base)
                world.close()
                s = summary(records)
                key = f"{name} substeps={sub} self_collision={sc}"
                out[key] = {"summary": s, "ticks": [asdict(r) for r in records]}
                print(
                    f"{key:44s} "
                    + "  ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in s.items())
                )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
