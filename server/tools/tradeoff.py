"""``drape tradeoff``: how much accuracy each millisecond of device time buys.

Scenes (all 1 m x 1 m, 1 kg, n x n vertices with structural and shear links, gravity -9.81,
simulated for 2 s from rest):

- ``hanging``: flat (horizontal) at a height of 1 m, the two corners of one edge pinned;
- ``flag``: vertical, pinned along one vertical edge, in a steady wind (wind feature, drag and
  lift on);
- ``cape``: vertical, its top row pinned to the shoulders of a character that accelerates to a
  run along a circle (pins follow the path, turning with the heading, bobbing), a capsule
  collider as the body (colliders feature, friction 0.3).

Knobs: solver (jacobi, coloured, workgroup, reference), iterations, substeps, PBD or XPBD
(compliance, 0 by default: an inextensible cloth like PBD's stiffness 1), tethers, the state
encoding on the wire (float32, float16, 16-bit quantised against the cloth's axis-aligned
bounds) and the tick rate.

Ground truth: the float64 numpy reference (``ReferenceWorld``, colour-ordered Gauss-Seidel)
with XPBD, compliance 0, ``REF_SUBSTEPS`` x ``REF_ITERATIONS`` at 60 Hz (see docs/accuracy.md
for the convergence study behind the choice). It is cached under ``OUT/refcache``.

Metrics of one run (every one over the 2 s, on what a client would decode):

- ``max_strain`` / ``mean_strain``: relative strain ``|l - l0| / l0`` over the structural links
  only; ``max_strain`` is the largest over every link and every frame, ``mean_strain`` the mean
  over links, averaged over frames. ``end_max_strain`` / ``end_mean_strain``: the same at t = 2 s;
  ``late_max_strain``: the largest over the frames from t = 1 s on (after the first fall).
- ``rms_dev`` / ``max_dev``: position deviation from the ground truth in metres, over every
  vertex at t = 0.1, 0.2, ..., 2.0 s; ``rms_dev_early``: the same up to t = 0.5 s, before the
  falling cloth folds (the folding is chaotic: two converged references part by centimetres
  after 1 s, so late deviation is partly noise; see the docs).
- ``energy_drift``: (E(2 s) - E(0)) / (M g 1 m), E = kinetic (from frame-to-frame velocities)
  + gravitational potential of the free vertices; negative is numerical (or real) damping.
  ``energy_gain``: the largest (E(t) - E(0)) / (M g 1 m), > 0 means energy was created.
- ``enc_err_max`` / ``enc_err_rms``: the encoding's own position error in metres.
- ``ms_per_frame``: median wall time of ``world.step(dt)`` plus a blocking ``world.fetch()``
  over the frames after ``WARMUP_FRAMES`` (kernel builds happen in the first), the lowest of
  ``TIMING_ROUNDS`` such medians: the measured run's and short re-runs spread over the sweep,
  so that a burst of other load on the machine does not land on one configuration; ``load``: the
  fraction of real time the device spends (ms_per_frame x tick rate / 1000);
  ``ms_per_60hz``: cost of 1/60 s of simulated time, to compare tick rates.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import os
import statistics
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..sim.fabric import Fabric, cook_grid, vertex_masses
from ..sim.params import LINK_STRUCTURAL, SOLVERS, Capsule, ClothParams, Features, Material, pack_colliders
from .procs import progress, require_extra

log = logging.getLogger(__name__)

SCENES = ("hanging", "flag", "cape")
ENCODINGS = P.ENCODINGS
DURATION = 2.0  # simulated seconds per run
COMPARE_HZ = 10  # deviation instants: t = 0.1, 0.2, ... (divides every tick rate used)
EARLY_S = 0.5  # rms_dev_early covers t <= EARLY_S
LATE_S = 1.0  # late_max_strain covers t >= LATE_S (after the first fall and jerk)
WARMUP_FRAMES = 5
TIMING_ROUNDS = 3  # the measured run plus 2 short timing-only re-runs
TIMING_FRAMES = 30  # frames timed in each re-run (after WARMUP_FRAMES)
REF_TICK_HZ = 60
REF_SUBSTEPS = 100  # ground truth: XPBD, compliance 0, float64, 100 substeps x 10 iterations
REF_ITERATIONS = 10
QUICK_REF_SUBSTEPS = 25  # --quick: a cheaper ground truth (its figures are indicative only)
SCENE_VERSION = 1  # bump when a scene changes: invalidates cached ground truths
GRAVITY = 9.81

FLAG_WIND = (6.0, 0.0, 2.0)  # m/s
CAPE_RADIUS = 2.0  # the character runs along a circle of this radius (m)
CAPE_TOP_SPEED = 2.5  # m/s, reached after CAPE_RAMP s
CAPE_RAMP = 0.5
CAPE_BODY = ((0.0, 0.15, 0.22), (0.0, 1.3, 0.22), 0.2)  # capsule in the character frame


# ---------------------------------------------------------------------------------------------
# Scenes


@dataclass
class Scene:
    name: str
    size: int
    fabric: Fabric
    params: ClothParams  # material, features, gravity, wind; iterations etc. come from a Config
    positions: np.ndarray | None = None  # initial pose (None: the fabric's rest pose)
    pins: np.ndarray | None = None  # pinned vertices that follow ``motion``
    motion: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = None  # t -> (targets, colliders)

    @property
    def label(self) -> str:
        return f"{self.name}{self.size}"

    @property
    def total_mass(self) -> float:
        return self.params.material.mass


def make_scene(name: str, n: int) -> Scene:
    if n < 2:
        raise ValueError("scenes need at least 2 x 2 vertices")
    if name == "hanging":
        fab = cook_grid(n, n, 1.0, 1.0, pinned=[0, n - 1], orientation="horizontal", origin=(0.0, 1.0, 0.0))
        return Scene(name, n, fab, ClothParams(material=Material(mass=1.0)))
    if name == "flag":
        fab = cook_grid(n, n, 1.0, 1.0, pinned=np.arange(n) * n, orientation="vertical", origin=(0.0, 2.0, 0.0))
        params = ClothParams(
            material=Material(mass=1.0, drag=1.0, lift=0.5), features=Features(wind=True), wind=FLAG_WIND
        )
        return Scene(name, n, fab, params)
    if name == "cape":
        fab = cook_grid(n, n, 1.0, 1.0, pinned=np.arange(n), orientation="vertical", origin=(-0.5, 1.5, 0.0))
        params = ClothParams(material=Material(mass=1.0, friction=0.3), features=Features(colliders=True))
        pins = np.arange(n)
        local = fab.rest_positions[pins].copy()
        motion = _CapeMotion(local)
        pos0 = _CapeMotion.transform(fab.rest_positions, 0.0)
        return Scene(name, n, fab, params, positions=pos0, pins=pins, motion=motion)
    raise ValueError(f"unknown scene {name!r}; choose from {SCENES}")


class _CapeMotion:
    """The character's path: speed ramps to CAPE_TOP_SPEED, along a circle turning left,
    with a running bob; the cape's pins and the body capsule ride in its frame."""

    def __init__(self, local_pins: np.ndarray) -> None:
        self.local_pins = local_pins
        (a, b, r) = CAPE_BODY
        self.body = np.array([a, b], np.float64)
        self.radius = r

    @staticmethod
    def pose(t: float) -> tuple[np.ndarray, float]:
        acc = CAPE_TOP_SPEED / CAPE_RAMP
        if t < CAPE_RAMP:
            s = 0.5 * acc * t * t
        else:
            s = 0.5 * acc * CAPE_RAMP**2 + CAPE_TOP_SPEED * (t - CAPE_RAMP)
        th = s / CAPE_RADIUS
        bob = 0.02 * math.sin(2.0 * math.pi * 2.0 * t)  # peak acceleration 3.2 m/s^2
        return np.array([CAPE_RADIUS * (1.0 - math.cos(th)), bob, CAPE_RADIUS * math.sin(th)]), th

    @classmethod
    def transform(cls, local: np.ndarray, t: float) -> np.ndarray:
        c, th = cls.pose(t)
        cs, sn = math.cos(th), math.sin(th)
        out = np.empty_like(local, dtype=np.float64)
        out[:, 0] = local[:, 0] * cs + local[:, 2] * sn + c[0]
        out[:, 1] = local[:, 1] + c[1]
        out[:, 2] = -local[:, 0] * sn + local[:, 2] * cs + c[2]
        return out

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        targets = self.transform(self.local_pins, t)
        p = self.transform(self.body, t)
        return targets, pack_colliders([Capsule(tuple(p[0]), tuple(p[1]), self.radius)])


# ---------------------------------------------------------------------------------------------
# Configurations


@dataclass(frozen=True)
class Config:
    solver: str = "workgroup"
    iterations: int = 10
    substeps: int = 1
    xpbd: bool = False
    tethers: bool = False
    compliance: float = 0.0  # XPBD compliance of structural and shear links (m/N)
    tether_limit: float = 1.0
    tick_hz: int = 60
    tag: str = ""  # the sweep this run belongs to (or "preset:<name>")
    chebyshev_rho: float = 0.0  # Jacobi only: Chebyshev acceleration (0: off)

    def apply(self, base: ClothParams) -> ClothParams:
        m = base.material
        mat = replace(m, compliance=(self.compliance, self.compliance, m.compliance[2]), tether_limit=self.tether_limit)
        feats = replace(base.features, xpbd=self.xpbd, tethers=self.tethers)
        extra = {"chebyshev_rho": self.chebyshev_rho} if self.chebyshev_rho else {}
        return base.with_(material=mat, features=feats, iterations=self.iterations, substeps=self.substeps, **extra)

    @property
    def mode(self) -> str:
        return ("xpbd" if self.xpbd else "pbd") + (f"+cheb{self.chebyshev_rho:g}" if self.chebyshev_rho else "")

    def describe(self) -> str:
        s = f"{self.solver} {self.mode} {self.iterations}it x {self.substeps}ss"
        if self.tethers:
            s += " +tethers"
        if self.xpbd and self.compliance:
            s += f" a={self.compliance:g}"
        return s + f" {self.tick_hz}Hz"

    @classmethod
    def from_preset(cls, name: str, solver: str = "workgroup", tick_hz: int = 60) -> Config:
        from ..sim.quality import PRESETS

        p = PRESETS[name]  # presets keep the material: compliance 0 and tether limit 1 here
        return cls(solver, p.iterations, p.substeps, p.xpbd, p.tethers, tick_hz=tick_hz, tag=f"preset:{name}")


def reference_config(substeps: int = REF_SUBSTEPS, iterations: int = REF_ITERATIONS) -> Config:
    return Config("reference", iterations, substeps, xpbd=True, tick_hz=REF_TICK_HZ, tag="ground-truth")


# ---------------------------------------------------------------------------------------------
# Encodings


def wire_bytes(n_vertices: int, encoding: str) -> int:
    """Bytes of one state of ``n_vertices`` on the wire (the protocol's own size)."""
    return int(P.state_size(n_vertices, encoding))


def encode_roundtrip(x: np.ndarray, encoding: str) -> np.ndarray:
    """Positions as a client decodes them after ``encoding`` (float32 input), through the wire
    protocol's own encoder and decoder."""
    x = np.asarray(x, np.float32)
    if encoding == "float32":
        return x
    if encoding not in ENCODINGS:
        raise ValueError(f"unknown encoding {encoding!r}; choose from {ENCODINGS}")
    return np.array(P.decode_state(P.encode_state(0, 0, x, encoding=encoding)).positions, np.float32)


# ---------------------------------------------------------------------------------------------
# Metrics


class _Meter:
    """Per-encoding accumulators of strain, deviation and encoding error over one run."""

    def __init__(self, fabric: Fabric) -> None:
        st = fabric.link_type == LINK_STRUCTURAL
        self.a = fabric.links[st, 0]
        self.b = fabric.links[st, 1]
        l0 = fabric.rest_length[st]
        ok = l0 > 0
        self.a, self.b, self.l0 = self.a[ok], self.b[ok], l0[ok]
        self.max_strain = 0.0
        self.sum_mean_strain = 0.0
        self.frames = 0
        self.end_max = self.end_mean = 0.0
        self.late_max = 0.0
        self.dev_sq = 0.0
        self.dev_n = 0
        self.dev_max = 0.0
        self.early_sq = 0.0
        self.early_n = 0
        self.enc_sq = 0.0
        self.enc_n = 0
        self.enc_max = 0.0

    def frame(self, x: np.ndarray, late: bool = False) -> None:
        if len(self.l0):
            d = x[self.a].astype(np.float64) - x[self.b]
            s = np.abs(np.sqrt(np.einsum("ij,ij->i", d, d)) - self.l0) / self.l0
            self.end_max = float(s.max())
            self.end_mean = float(s.mean())
        self.max_strain = max(self.max_strain, self.end_max)
        if late:
            self.late_max = max(self.late_max, self.end_max)
        self.sum_mean_strain += self.end_mean
        self.frames += 1

    def encoding_error(self, x: np.ndarray, raw: np.ndarray) -> None:
        e = np.linalg.norm(x.astype(np.float64) - raw, axis=1)
        self.enc_sq += float(np.dot(e, e))
        self.enc_n += len(e)
        self.enc_max = max(self.enc_max, float(e.max(initial=0.0)))

    def compare(self, x: np.ndarray, ref: np.ndarray, early: bool) -> None:
        e = np.linalg.norm(x.astype(np.float64) - ref, axis=1)
        sq = float(np.dot(e, e))
        self.dev_sq += sq
        self.dev_n += len(e)
        self.dev_max = max(self.dev_max, float(e.max(initial=0.0)))
        if early:
            self.early_sq += sq
            self.early_n += len(e)

    def result(self) -> dict[str, float]:
        nan = float("nan")
        return {
            "max_strain": self.max_strain,
            "mean_strain": self.sum_mean_strain / max(self.frames, 1),
            "end_max_strain": self.end_max,
            "late_max_strain": self.late_max,
            "end_mean_strain": self.end_mean,
            "rms_dev": math.sqrt(self.dev_sq / self.dev_n) if self.dev_n else nan,
            "max_dev": self.dev_max if self.dev_n else nan,
            "rms_dev_early": math.sqrt(self.early_sq / self.early_n) if self.early_n else nan,
            "enc_err_max": self.enc_max,
            "enc_err_rms": math.sqrt(self.enc_sq / self.enc_n) if self.enc_n else 0.0,
        }


def _energy(x: np.ndarray, x_prev: np.ndarray | None, dt: float, mass: np.ndarray, free: np.ndarray) -> float:
    pe = GRAVITY * float(np.dot(mass[free], x[free, 1]))
    if x_prev is None:
        return pe
    v = (x[free].astype(np.float64) - x_prev[free]) / dt
    return pe + 0.5 * float(np.dot(mass[free], np.einsum("ij,ij->i", v, v)))


# ---------------------------------------------------------------------------------------------
# Running


@dataclass
class RunResult:
    config: Config
    scene: str
    size: int
    device: str
    ms_per_frame: float
    ms_p90: float
    finite: bool
    energy_drift: float
    energy_gain: float
    metrics: dict[str, dict[str, float]]  # per encoding
    n_vertices: int = 0
    snapshots: list[np.ndarray] | None = None  # float64 positions at the compare instants

    def records(self) -> list[dict[str, Any]]:
        c = self.config
        out = []
        for enc, m in self.metrics.items():
            rec = {
                "scene": self.scene,
                "size": self.size,
                "solver": c.solver,
                "iterations": c.iterations,
                "substeps": c.substeps,
                "xpbd": c.xpbd,
                "tethers": c.tethers,
                "compliance": c.compliance,
                "chebyshev_rho": c.chebyshev_rho,
                "tick_hz": c.tick_hz,
                "encoding": enc,
                "wire_bytes": wire_bytes(self.n_vertices, enc),
                "tag": c.tag,
                "device": self.device,
                "ms_per_frame": self.ms_per_frame,
                "ms_p90": self.ms_p90,
                "ms_per_60hz": self.ms_per_frame * c.tick_hz / 60.0,
                "load": self.ms_per_frame * c.tick_hz / 1000.0,
                "finite": self.finite,
                "energy_drift": self.energy_drift,
                "energy_gain": self.energy_gain,
                **m,
            }
            out.append(rec)
        return out


def make_world_for(solver: str, device=None):
    from ..sim.world import make_world

    if solver == "reference":
        return make_world("reference")
    return make_world(solver, device=device)


def simulate(
    scene: Scene,
    cfg: Config,
    device=None,
    truth: np.ndarray | None = None,
    encodings: Iterable[str] = ENCODINGS,
    duration: float = DURATION,
    keep_snapshots: bool = False,
) -> RunResult:
    """Run ``scene`` under ``cfg`` for ``duration`` seconds; measure cost and error.

    ``truth``: ground-truth positions (K, n, 3) at t = k / COMPARE_HZ, k = 1..K."""
    if cfg.tick_hz % COMPARE_HZ:
        raise ValueError(f"tick rate must be a multiple of {COMPARE_HZ} Hz")
    world = make_world_for(cfg.solver, device)
    try:
        params = cfg.apply(scene.params)
        h = world.add(scene.fabric, params, scene.positions)
        fab = scene.fabric
        dt = 1.0 / cfg.tick_hz
        frames = int(round(duration * cfg.tick_hz))
        every = cfg.tick_hz // COMPARE_HZ
        mass = vertex_masses(fab, scene.total_mass)
        free = ~fab.pinned
        scale = scene.total_mass * GRAVITY * 1.0
        meters = {e: _Meter(fab) for e in encodings}
        x0 = (scene.positions if scene.positions is not None else fab.rest_positions).astype(np.float64)
        e0 = _energy(x0, None, dt, mass, free)
        x_prev: np.ndarray | None = x0
        gain = 0.0
        drift = 0.0
        times: list[float] = []
        snaps: list[np.ndarray] = []
        finite = True
        for f in range(1, frames + 1):
            t = f * dt
            if scene.motion is not None:
                targets, colliders = scene.motion(t)
                world.set_pin_targets(h, scene.pins, targets)
                world.set_colliders(h, colliders)
            t0 = time.perf_counter()
            world.step(dt)
            frame = world.fetch()
            times.append(time.perf_counter() - t0)
            x = np.array(frame.positions[h], np.float32)
            if not np.all(np.isfinite(x)):
                finite = False
                log.warning("%s %s: non-finite positions at frame %d", scene.label, cfg.describe(), f)
                break
            e = _energy(x, x_prev, dt, mass, free)
            drift = (e - e0) / scale
            gain = max(gain, drift)
            x_prev = x
            compare = f % every == 0
            k = f // every - 1
            if compare and keep_snapshots:
                snaps.append(world.state(h).x.copy() if cfg.solver == "reference" else x.astype(np.float64))
            for enc, m in meters.items():
                xe = encode_roundtrip(x, enc)
                m.frame(xe, late=t >= LATE_S - 1e-9)
                if enc != "float32":
                    m.encoding_error(xe, x)
                if compare and truth is not None and k < len(truth):
                    m.compare(xe, truth[k], early=t <= EARLY_S + 1e-9)
        timed = times[WARMUP_FRAMES:] or times
        metrics: dict[str, dict[str, float]] = {enc: m.result() for enc, m in meters.items()}
        if not finite:
            inf = float("inf")
            for mt in metrics.values():
                for key in (
                    "max_strain",
                    "mean_strain",
                    "end_max_strain",
                    "end_mean_strain",
                    "late_max_strain",
                    "rms_dev",
                    "max_dev",
                    "rms_dev_early",
                ):
                    mt[key] = inf
            drift = gain = inf
        return RunResult(
            config=cfg,
            scene=scene.name,
            size=scene.size,
            device=getattr(world, "device_name", "?"),
            ms_per_frame=1e3 * statistics.median(timed),
            ms_p90=1e3 * float(np.percentile(timed, 90)),
            finite=finite,
            energy_drift=drift,
            energy_gain=gain,
            metrics=metrics,
            n_vertices=fab.n_vertices,
            snapshots=snaps if keep_snapshots else None,
        )
    finally:
        world.close()


def time_config(scene: Scene, cfg: Config, device=None, frames: int = TIMING_FRAMES) -> float:
    """Median ms of step + blocking fetch over ``frames`` frames after WARMUP_FRAMES, from t = 0."""
    world = make_world_for(cfg.solver, device)
    try:
        h = world.add(scene.fabric, cfg.apply(scene.params), scene.positions)
        dt = 1.0 / cfg.tick_hz
        times = []
        for f in range(1, WARMUP_FRAMES + frames + 1):
            if scene.motion is not None:
                targets, colliders = scene.motion(f * dt)
                world.set_pin_targets(h, scene.pins, targets)
                world.set_colliders(h, colliders)
            t0 = time.perf_counter()
            world.step(dt)
            world.fetch()
            times.append(time.perf_counter() - t0)
        return 1e3 * statistics.median(times[WARMUP_FRAMES:])
    finally:
        world.close()


# ---------------------------------------------------------------------------------------------
# Ground truth (cached)


def _source_digest() -> str:
    here = Path(__file__).resolve().parent
    h = hashlib.sha1()
    for name in ("reference.py", "fabric.py"):
        p = here / name
        if p.exists():
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


def truth_path(cache: Path, scene: str, size: int, duration: float, substeps: int, iterations: int) -> Path:
    key = f"{scene}-{size}-{duration:g}s-{substeps}x{iterations}-v{SCENE_VERSION}-{_source_digest()}"
    return cache / f"truth-{key}.npz"


def _compute_truth(args: tuple[str, int, float, int, int, str]) -> str:
    scene_name, size, duration, substeps, iterations, path = args
    scene = make_scene(scene_name, size)
    t0 = time.perf_counter()
    res = simulate(
        scene, reference_config(substeps, iterations), encodings=("float32",), duration=duration, keep_snapshots=True
    )
    stats = {
        **res.metrics["float32"],
        "energy_drift": res.energy_drift,
        "energy_gain": res.energy_gain,
        "seconds": time.perf_counter() - t0,
        "finite": res.finite,
    }
    tmp = path + ".tmp.npz"
    np.savez_compressed(tmp, snapshots=np.array(res.snapshots), stats=json.dumps(stats))
    os.replace(tmp, path)
    return path


def ensure_truths(
    wanted: list[tuple[str, int]], cache: Path, duration: float, substeps: int, iterations: int, jobs: int
) -> dict[tuple[str, int], tuple[np.ndarray, dict]]:
    """Ground truths of every (scene, size), computed in ``jobs`` processes where not cached."""
    cache.mkdir(parents=True, exist_ok=True)
    paths = {w: truth_path(cache, *w, duration, substeps, iterations) for w in wanted}
    missing = [w for w, p in paths.items() if not p.exists()]
    if missing:
        log.info(
            "computing %d ground truth(s) (float64 reference, XPBD %d substeps x %d iterations) in %d process(es): %s",
            len(missing),
            substeps,
            iterations,
            min(jobs, len(missing)),
            ", ".join(f"{s}{n}" for s, n in missing),
        )
        t0 = time.perf_counter()
        work: list[tuple[str, int, float, int, int, str]] = [
            (s, n, duration, substeps, iterations, str(paths[(s, n)])) for s, n in missing
        ]
        # largest first so the pool finishes together
        work.sort(key=lambda w: -w[1])
        if jobs > 1 and len(work) > 1:
            with ProcessPoolExecutor(max_workers=min(jobs, len(work))) as ex:
                for p in ex.map(_compute_truth, work):
                    log.info("  ground truth written: %s (%.0f s so far)", Path(p).name, time.perf_counter() - t0)
        else:
            for item in work:
                log.info(
                    "  ground truth written: %s (%.0f s so far)",
                    Path(_compute_truth(item)).name,
                    time.perf_counter() - t0,
                )
    out = {}
    for w, path in paths.items():
        z = np.load(path)
        out[w] = (z["snapshots"], json.loads(str(z["stats"])))
    return out


# ---------------------------------------------------------------------------------------------
# Sweeps

PBD_ITERS_DEFAULT = (1, 2, 5, 10, 20, 50, 100)
XPBD_SUBSTEPS_DEFAULT = (1, 2, 5, 10, 20)


def main_sweep(level: str, solvers: list[str]) -> list[Config]:
    """Every knob on the main scene. ``level``: quick, default or full."""
    cfgs: list[Config] = []
    gpu_solvers = [s for s in ("workgroup", "coloured", "jacobi") if s in solvers]
    iters: tuple[int, ...]
    subs: tuple[int, ...]
    grid: tuple[tuple[int, int], ...]
    teth_iters: tuple[int, ...]
    teth_subs: tuple[int, ...]
    ref_iters: tuple[int, ...]
    ticks: tuple[int, ...]
    compl: tuple[float, ...]
    cheb_iters: tuple[int, ...]
    rhos: tuple[float, ...]
    if level == "quick":
        iters = (1, 5, 10, 30)
        subs = (1, 5, 10)
        grid = ((5, 2),)
        teth_iters = (2, 10)
        teth_subs = (5,)
        ref_iters = (10,)
        ticks = (30, 120)
        compl = ()
        cheb_iters, rhos = (10,), (0.95,)
    elif level == "full":
        iters = (1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100)
        subs = (1, 2, 3, 4, 5, 7, 10, 15, 20)
        grid = ((2, 2), (2, 5), (3, 3), (4, 2), (5, 2), (5, 3), (5, 5), (10, 2), (10, 3), (10, 5), (20, 2), (20, 5))
        teth_iters = (1, 2, 3, 5, 10, 20)
        teth_subs = (1, 2, 3, 4, 5, 7, 10, 15, 20, 30, 40, 50, 60, 70, 100)
        ref_iters = (1, 10, 100)
        ticks = (30, 120)
        compl = (1e-7, 1e-5, 1e-3)
        cheb_iters, rhos = (5, 10, 20, 50, 100), (0.9, 0.95, 0.99)
    else:
        iters = PBD_ITERS_DEFAULT
        subs = XPBD_SUBSTEPS_DEFAULT
        grid = ((2, 2), (4, 2), (5, 2), (10, 2), (5, 5))
        teth_iters = (1, 2, 5, 10, 20)
        teth_subs = (1, 2, 3, 5, 10, 30, 50, 100)
        ref_iters = (10, 100)
        ticks = (30, 120)
        compl = (1e-6, 1e-3)
        cheb_iters, rhos = (5, 10, 20, 50), (0.95,)
    for s in gpu_solvers:
        cfgs += [Config(s, i, 1, tag="pbd-iterations") for i in iters]
        cfgs += [Config(s, 1, n, xpbd=True, tag="xpbd-substeps") for n in subs]
    if "jacobi" in solvers:
        cfgs += [Config("jacobi", i, 1, chebyshev_rho=rho, tag="jacobi-chebyshev") for i in cheb_iters for rho in rhos]
        cfgs += [Config("jacobi", 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in (5, 10, 20)]
    if "reference" in solvers:
        cfgs += [Config("reference", i, 1, tag="pbd-iterations") for i in ref_iters]
        cfgs += [Config("reference", 1, 5, xpbd=True, tag="xpbd-substeps")]
    main = gpu_solvers[0] if gpu_solvers else "reference"
    for n, i in grid:
        cfgs.append(Config(main, i, n, xpbd=True, tag="xpbd-substeps-x-iterations"))
    cfgs += [Config(main, i, 1, tethers=True, tag="pbd-tethers") for i in teth_iters]
    cfgs += [Config(main, 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in teth_subs]
    for s in gpu_solvers[1:]:
        cfgs.append(Config(s, 10, 1, tethers=True, tag="pbd-tethers"))
        cfgs.append(Config(s, 1, 5, xpbd=True, tethers=True, tag="xpbd-tethers"))
    cfgs += [Config(main, 1, 10, xpbd=True, compliance=a, tag="xpbd-compliance") for a in compl]
    for hz in ticks:
        cfgs.append(Config(main, 10, 1, tick_hz=hz, tag="tick-rate"))
        cfgs.append(Config(main, 1, max(1, 5 * 60 // hz), xpbd=True, tethers=True, tick_hz=hz, tag="tick-rate"))
    if level != "quick" and main != "reference":
        # the ground truth's own settings in float32 on the device: how far float32 alone drifts
        cfgs.append(Config(main, REF_ITERATIONS, REF_SUBSTEPS, xpbd=True, tag="noise-floor"))
    cfgs += preset_configs(main)
    return _dedupe(cfgs)


def side_sweep(level: str, solvers: list[str]) -> list[Config]:
    """A few points on the other scenes and sizes: the baseline, Small Steps, tethers, presets."""
    gpu_solvers = [s for s in ("workgroup", "coloured", "jacobi") if s in solvers]
    main = gpu_solvers[0] if gpu_solvers else "reference"
    cfgs = [Config(main, i, 1, tag="pbd-iterations") for i in (5, 10, 20)]
    cfgs += [Config(main, 1, n, xpbd=True, tag="xpbd-substeps") for n in (5, 10)]
    cfgs += [Config(main, 10, 1, tethers=True, tag="pbd-tethers")]
    for s in gpu_solvers[1:]:
        cfgs.append(Config(s, 10, 1, tag="pbd-iterations"))
    cfgs += preset_configs(main)
    if level == "full":
        cfgs += [Config(main, i, 1, tag="pbd-iterations") for i in (1, 2, 50, 100)]
        cfgs += [Config(main, 1, n, xpbd=True, tag="xpbd-substeps") for n in (1, 2, 20)]
        cfgs += [Config(main, 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in (2, 5, 10)]
    return _dedupe(cfgs)


def sweep_layout(level: str, scenes: list[str], sizes: list[str] | None) -> list[tuple[str, int, bool]]:
    """(scene, size, main sweep?) for every scene and size to run. Without --sizes: --quick runs
    the main sweep on hanging 32 x 32; the default runs it on hanging 64 x 64 plus a few points
    on every scene at 32 x 32; --full runs it on every scene at 64 x 64 plus a few points at 32
    and 150."""
    if sizes is not None:
        ns = [int(v) for v in sizes]
        return [
            (s, n, (i == 0 and j == 0) or (level == "full" and j == 0))
            for i, s in enumerate(scenes)
            for j, n in enumerate(ns)
        ]
    if level == "quick":
        return [(s, 32, i == 0) for i, s in enumerate(scenes)]
    if level == "full":
        return [(s, 64, True) for s in scenes] + [(s, n, False) for n in (32, 150) for s in scenes]
    return [(scenes[0], 64, True)] + [(s, 32, False) for s in scenes]


def preset_configs(solver: str) -> list[Config]:
    try:
        from ..sim.quality import PRESETS
    except ImportError:
        return []
    return [Config.from_preset(name, solver) for name in PRESETS]


def _dedupe(cfgs: list[Config]) -> list[Config]:
    seen: dict[str, Config] = {}
    for c in cfgs:
        k = replace(c, tag="").__repr__()
        if k not in seen or c.tag.startswith("preset:"):
            seen[k] = c
    return list(seen.values())


# ---------------------------------------------------------------------------------------------
# Pareto front, table, plot


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both cost (x) and error (y), by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        x, y = points[i]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if y < best:
            front.append(i)
            best = y
    return front


def _pct(v: float) -> str:
    return "   inf" if not math.isfinite(v) else f"{100 * v:6.2f}"


def _mm(v: float) -> str:
    return "    nan" if v is None or not math.isfinite(v) else f"{1e3 * v:7.1f}"


def format_table(records: list[dict], encoding: str = "float32") -> str:
    head = (
        f"{'scene':10} {'solver':9} {'mode':8} {'it':>3} {'ss':>3} {'teth':4} {'Hz':>3} {'ms/frame':>8} "
        f"{'load%':>6} {'max%':>6} {'mean%':>6} {'late%':>6} {'end%':>6} {'rms mm':>7} {'early mm':>8} {'max mm':>7} "
        f"{'energy':>7}  tag"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        if r["encoding"] != encoding:
            continue
        mode = "xpbd" if r["xpbd"] else "pbd"
        if r["xpbd"] and r["compliance"]:
            mode = f"x{r['compliance']:.0e}"
        if r.get("chebyshev_rho"):
            mode += f"+c{r['chebyshev_rho']:g}"
        energy = r["energy_drift"]
        lines.append(
            f"{r['scene'] + str(r['size']):10} {r['solver']:9} {mode:8} {r['iterations']:>3} {r['substeps']:>3} "
            f"{'on' if r['tethers'] else 'off':4} {r['tick_hz']:>3} {r['ms_per_frame']:8.2f} "
            f"{100 * r['load']:6.1f} {_pct(r['max_strain'])} {_pct(r['mean_strain'])} "
            f"{_pct(r['late_max_strain'])} {_pct(r['end_max_strain'])} {_mm(r['rms_dev'])} "
            f"{_mm(r['rms_dev_early']):>8} {_mm(r['max_dev'])} "
            f"{energy:7.3f}  {r['tag']}"
        )
    return "\n".join(lines)


def format_encoding_table(records: list[dict]) -> str:
    head = (
        f"{'scene':10} {'config':38} {'encoding':8} {'enc rms mm':>10} {'enc max mm':>10} {'max%':>6} "
        f"{'mean%':>6} {'rms mm':>7}"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        if not (
            r["tag"].startswith("preset:")
            or (
                r["iterations"] == 10
                and r["substeps"] == 1
                and not r["xpbd"]
                and not r["tethers"]
                and r["tick_hz"] == 60
            )
        ):
            continue
        cfg = (
            f"{r['solver']} {'xpbd' if r['xpbd'] else 'pbd'} {r['iterations']}x{r['substeps']}"
            + (" +teth" if r["tethers"] else "")
            + (f" ({r['tag']})" if r["tag"].startswith("preset") else "")
        )
        lines.append(
            f"{r['scene'] + str(r['size']):10} {cfg:38} {r['encoding']:8} {1e3 * r['enc_err_rms']:10.3f} "
            f"{1e3 * r['enc_err_max']:10.3f} {_pct(r['max_strain'])} {_pct(r['mean_strain'])} {_mm(r['rms_dev'])}"
        )
    return "\n".join(lines)


def plot(records: list[dict], path: Path, scene: str, size: int, error: str = "max_strain") -> Path | None:
    """Error against cost (ms per 1/60 s simulated), a series per solver, Pareto front marked."""
    from .plots import scatter_plot

    pts = [
        r
        for r in records
        if r["scene"] == scene
        and r["size"] == size
        and r["encoding"] == "float32"
        and r["finite"]
        and r.get(error) is not None
        and math.isfinite(r[error])
        and r[error] > 0
    ]
    if not pts:
        return None
    series: dict[str, tuple[list[float], list[float]]] = {}
    for r in pts:
        family = (
            f"{r['solver']} {'XPBD' if r['xpbd'] else 'PBD'}{' +tethers' if r['tethers'] else ''}"
            f"{' +Chebyshev' if r.get('chebyshev_rho') else ''}"
        )
        if r["tag"].startswith("preset:"):
            family = (
                "quality presets ("
                + "/".join(q["tag"][7:] for q in pts if q["tag"].startswith("preset:") and q["solver"] == r["solver"])
                + ")"
            )
        xs, ys = series.setdefault(family, ([], []))
        xs.append(r["ms_per_60hz"])
        ys.append(r[error] * (100.0 if "strain" in error else 1e3))
    allp = [(r["ms_per_60hz"], r[error]) for r in pts]
    front = pareto_front(allp)
    hx = [allp[i][0] for i in front]
    hy = [allp[i][1] * (100.0 if "strain" in error else 1e3) for i in front]
    unit = "%" if "strain" in error else "mm"
    label = {
        "max_strain": "max structural strain",
        "mean_strain": "mean structural strain",
        "rms_dev": "RMS deviation from reference",
        "rms_dev_early": "RMS deviation, first 0.5 s",
    }.get(error, error)
    scatter_plot(
        path,
        {k: series[k] for k in sorted(series)},
        title=f"{scene} {size}x{size}: {label} vs cost",
        xlabel=f"ms per 1/60 s simulated (step + blocking fetch), {_short_device(pts[0]['device'])}",
        ylabel=f"{label} ({unit})",
        logx=True,
        logy=True,
        highlight=(hx, hy),
        highlight_label="Pareto front",
        size=(1000, 640),
    )
    return path


def _short_device(name: str) -> str:
    return name.replace("Portable Computing Language", "PoCL").replace("pthread-", "")[:60]


def code_version() -> str:
    """The git commit of the running code, with "+dirty" when the tree has changes."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "unknown") + ("+dirty" if dirty else "")


# ---------------------------------------------------------------------------------------------
# CLI


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "tradeoff")
    require_extra("tools", "tradeoff")
    parser.add_argument(
        "--scenes", default=None, help=f"comma list of {','.join(SCENES)} (default: all; --quick: hanging)"
    )
    parser.add_argument(
        "--sizes",
        default=None,
        help="comma list of grid sizes n (n x n), for every scene; the main sweep runs on "
        "the first scene at the first size (default: the main sweep on hanging 64 and a "
        "few points on every scene at 32; --quick: hanging 32; --full: the main sweep "
        "on every scene at 64, points at 32 and 150)",
    )
    parser.add_argument("--solvers", default=",".join(SOLVERS), help="comma list of solvers to sweep")
    level = parser.add_mutually_exclusive_group()
    level.add_argument("--quick", action="store_true", help="a small sweep (about a minute on 2 CPU cores)")
    level.add_argument("--full", action="store_true", help="every knob densely, every scene and size (long)")
    parser.add_argument("--out", default="out/tradeoff", help="output folder (table, JSON, plots, ground-truth cache)")
    parser.add_argument("--json", default=None, help="write the records here (default OUT/tradeoff.json)")
    parser.add_argument("--duration", type=float, default=DURATION, help="simulated seconds per run")
    parser.add_argument(
        "--ref-substeps",
        type=int,
        default=None,
        help=f"ground-truth substeps (default {REF_SUBSTEPS}; --quick {QUICK_REF_SUBSTEPS})",
    )
    parser.add_argument("--ref-iterations", type=int, default=REF_ITERATIONS, help="ground-truth iterations")
    parser.add_argument(
        "--timing-rounds",
        type=int,
        default=TIMING_ROUNDS,
        help="the cost is the lowest of this many medians (1: the measured run's only)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes for the ground truths (computed before any timing)",
    )
    parser.add_argument("--device", default=None, help="OpenCL device: auto, gpu, cpu or a name substring")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ..sim.opencl.device import Device

    level = "quick" if args.quick else "full" if args.full else "default"
    scenes = _csv(args.scenes) if args.scenes else (["hanging"] if level == "quick" else list(SCENES))
    for s in scenes:
        if s not in SCENES:
            raise SystemExit(f"unknown scene {s!r}; choose from {SCENES}")
    solvers = _csv(args.solvers)
    for s in solvers:
        if s not in SOLVERS:
            raise SystemExit(f"unknown solver {s!r}; choose from {SOLVERS}")
    ref_substeps = args.ref_substeps or (QUICK_REF_SUBSTEPS if level == "quick" else REF_SUBSTEPS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    plan: list[tuple[str, int, Config]] = []
    for scene_name, size, main in sweep_layout(level, scenes, _csv(args.sizes) if args.sizes else None):
        cfgs = main_sweep(level, solvers) if main else side_sweep(level, solvers)
        plan += [(scene_name, size, c) for c in cfgs]
    wanted = list(dict.fromkeys((s, n) for s, n, _ in plan))
    log.info(
        "tradeoff (%s): %d runs over %s, %.1f s simulated each",
        level,
        len(plan),
        ", ".join(f"{s}{n}" for s, n in wanted),
        args.duration,
    )
    truths = ensure_truths(wanted, out / "refcache", args.duration, ref_substeps, args.ref_iterations, args.jobs)
    for (s, n), (_, st) in truths.items():
        log.info(
            "ground truth %s%d: its own max strain %.2f%%, mean %.3f%%, energy drift %.3f (computed in %.0f s)",
            s,
            n,
            100 * st["max_strain"],
            100 * st["mean_strain"],
            st["energy_drift"],
            st["seconds"],
        )

    device = Device(args.device) if any(c.solver != "reference" for _, _, c in plan) else None
    version = code_version()
    records: list[dict] = []
    scene_cache: dict[tuple[str, int], Scene] = {}
    per_run: list[list[dict]] = []
    bar = progress(total=len(plan) * args.timing_rounds, desc="tradeoff", unit="run", quiet=args.quiet)
    for i, (sname, n, cfg) in enumerate(plan, 1):
        scene = scene_cache.get((sname, n)) or scene_cache.setdefault((sname, n), make_scene(sname, n))
        res = simulate(scene, cfg, device, truth=truths[(sname, n)][0], duration=args.duration)
        recs = res.records()
        for r in recs:
            r["code"] = version
            r["ms_rounds"] = [res.ms_per_frame]
        records += recs
        per_run.append(recs)
        m = res.metrics["float32"]
        bar.set_description(f"{sname}{n} {cfg.describe()}", refresh=False)
        bar.update()
        log.debug(
            "[%d/%d] %s %s: %.2f ms/frame, strain max %.2f%% mean %.3f%%, rms dev %.1f mm (early %.1f mm)",
            i,
            len(plan),
            scene.label,
            cfg.describe(),
            res.ms_per_frame,
            100 * m["max_strain"],
            100 * m["mean_strain"],
            1e3 * m["rms_dev"],
            1e3 * m["rms_dev_early"],
        )

    for rnd in range(1, args.timing_rounds):
        log.debug("timing round %d of %d (%d frames per configuration)", rnd + 1, args.timing_rounds, TIMING_FRAMES)
        order = list(range(len(plan)))
        if rnd % 2:
            order.reverse()  # so no configuration always sits next to the same neighbours in time
        for j in order:
            s, n, cfg = plan[j]
            frames = TIMING_FRAMES if cfg.solver != "reference" else 10
            ms = time_config(scene_cache[(s, n)], cfg, device, frames)
            bar.set_description(f"timing round {rnd + 1}: {s}{n} {cfg.describe()}", refresh=False)
            bar.update()
            for r in per_run[j]:
                r["ms_rounds"].append(ms)
    bar.close()
    for recs in per_run:
        for r in recs:
            r["ms_per_frame"] = min(r["ms_rounds"])
            r["ms_per_60hz"] = r["ms_per_frame"] * r["tick_hz"] / 60.0
            r["load"] = r["ms_per_frame"] * r["tick_hz"] / 1000.0

    for (s, n), (_, st) in truths.items():
        records.append(
            {
                "scene": s,
                "size": n,
                "solver": "reference",
                "iterations": args.ref_iterations,
                "substeps": ref_substeps,
                "xpbd": True,
                "tethers": False,
                "compliance": 0.0,
                "tick_hz": REF_TICK_HZ,
                "encoding": "float64",
                "tag": "ground-truth",
                "device": "numpy float64",
                "ms_per_frame": 1e3 * st["seconds"] / (args.duration * REF_TICK_HZ),
                "ms_p90": None,
                "ms_per_60hz": 1e3 * st["seconds"] / (args.duration * REF_TICK_HZ),
                "load": None,
                "finite": st["finite"],
                "energy_drift": st["energy_drift"],
                "energy_gain": st["energy_gain"],
                **{
                    k: st.get(k, float("nan"))
                    for k in ("max_strain", "mean_strain", "end_max_strain", "end_mean_strain", "late_max_strain")
                },
                "rms_dev": 0.0,
                "max_dev": 0.0,
                "rms_dev_early": 0.0,
                "enc_err_max": 0.0,
                "enc_err_rms": 0.0,
                "code": version,
            }
        )

    print(
        f"\nDrape tradeoff ({level}, code {version}) on {records[0]['device'] if records else '?'}; "
        f"{args.duration:g} s simulated "
        f"per run; ground truth: float64 reference, XPBD {ref_substeps} substeps x {args.ref_iterations} "
        f"iterations at {REF_TICK_HZ} Hz\n"
    )
    print(format_table(records))
    for r in records:
        if r["tag"] == "ground-truth":
            print(
                f"ground truth {r['scene']}{r['size']}: float64 reference, XPBD {r['substeps']} substeps x "
                f"{r['iterations']} iterations: its own strain max {_pct(r['max_strain']).strip()}% mean "
                f"{_pct(r['mean_strain']).strip()}%, at 2 s max {_pct(r['end_max_strain']).strip()}%; energy drift "
                f"{r['energy_drift']:.3f}; {r['ms_per_frame']:.0f} ms per frame"
            )
    print("\nEncodings (strain and deviation measured on what the client decodes):\n")
    print(format_encoding_table(records))
    summary = preset_summary(records)
    if summary:
        print("\n" + summary)

    json_path = Path(args.json) if args.json else out / "tradeoff.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(_jsonable(records), indent=1))
    print(f"\nrecords: {json_path}")
    for s, n in wanted:
        for err in ("max_strain", "rms_dev"):
            p = plot(records, out / f"tradeoff-{s}{n}-{err.replace('_', '-')}.png", s, n, err)
            if p:
                print(f"plot: {p}")
    log.info("tradeoff done in %.0f s", time.perf_counter() - t_start)
    return 0


def preset_summary(records: list[dict]) -> str:
    """Each preset's error and its cost relative to the plain 10-iteration PBD solve of the same
    scene, size, solver and tick rate, measured in this process."""
    lines = []
    base = {
        (r["scene"], r["size"], r["solver"], r["tick_hz"]): r
        for r in records
        if r["encoding"] == "float32"
        and not r["xpbd"]
        and not r["tethers"]
        and r["iterations"] == 10
        and r["substeps"] == 1
    }
    for r in records:
        if r["encoding"] != "float32" or not r["tag"].startswith("preset:"):
            continue
        b = base.get((r["scene"], r["size"], r["solver"], r["tick_hz"]))
        ratio = r["ms_per_frame"] / b["ms_per_frame"] if b else float("nan")
        lines.append(
            f"{r['scene'] + str(r['size']):10} {r['tag'][7:]:9} {r['solver']:9} "
            f"{r['ms_per_frame']:7.2f} ms ({ratio:4.2f}x the 10-iteration PBD solve)  strain max "
            f"{_pct(r['max_strain'])}% mean {_pct(r['mean_strain'])}%  rms dev {_mm(r['rms_dev'])} mm"
        )
    return ("Presets against the plain 10-iteration solve:\n" + "\n".join(lines)) if lines else ""


def _jsonable(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return _jsonable(obj.item())
    return obj
