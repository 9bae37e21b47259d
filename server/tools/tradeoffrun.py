"""The runs of ``drape tradeoff`` (see its module docstring for scenes, knobs and metrics): the
scenes, one configuration, the wire encodings' round trip, the metrics of one run against a
ground truth, and the cost of one configuration."""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..sim.fabric import Fabric, cook_grid, cook_mesh, grid_mesh, vertex_masses
from ..sim.params import LINK_STRUCTURAL, Capsule, ClothParams, Features, LinkOptions, Material, Sphere, pack_colliders

log = logging.getLogger(__name__)

SCENES = ("hanging", "flag", "cape", "curtain")
ENCODINGS = P.STATELESS_ENCODINGS  # each state alone (predictive: docs/codec.md, codecbench)
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
    if name == "curtain":
        # a 1 m x 1 m mesh (not a grid: its tethers and long-range links are a mesh's), pleated
        # along x (depth 4.5 cm, 6 columns a pleat), hung from its top row; a ball swings through
        v, t = grid_mesh(n, n, 1.0, 1.0, "vertical", (0.0, 1.5, 0.0))
        col = np.arange(len(v)) % n
        v[:, 2] = CURTAIN_PLEAT * np.sin(2 * math.pi * col / 6)
        fab = cook_mesh(v, t, LinkOptions(bending=True), pinned=np.arange(n))
        params = ClothParams(material=Material(mass=1.0, friction=0.3), features=Features(colliders=True))
        return Scene(name, n, fab, params, pins=np.arange(n), motion=_CurtainBall(fab.rest_positions[:n].copy()))
    raise ValueError(f"unknown scene {name!r}; choose from {SCENES}")


CURTAIN_PLEAT = 0.045
CURTAIN_BALL = ((0.5, 2.3, -0.5), 1.6, 0.2, math.radians(40.0))  # pivot, rope, radius, swing


class _CurtainBall:
    """The curtain's pins stay on their rod; a ball on a rope swings across its front (in z)."""

    def __init__(self, pins: np.ndarray) -> None:
        self.pins = pins

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        (px, py, pz), rope, r, swing = CURTAIN_BALL
        a = swing * math.cos(2.0 * math.pi * t / 2.0)  # from the front, through the curtain and back
        c = (px, py - rope * math.cos(a), pz + rope * math.sin(a))
        return self.pins, pack_colliders([Sphere(c, r)])


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
    def from_preset(
        cls, name: str, solver: str = "workgroup", tick_hz: int = 60, base: ClothParams | None = None
    ) -> Config:
        """The preset's settings; for a cloth like ``base`` where given (a moving cloth's
        substeps: quality.MOVING_FEATURES), else for a still one."""
        from ..sim.quality import PRESETS

        p = PRESETS[name]  # presets keep the material: compliance 0 and tether limit 1 here
        cloth = base if base is not None else ClothParams()
        ss = p.substeps_for(cloth, tick_hz)
        return cls(solver, p.iterations_for(cloth), ss, p.xpbd, p.tethers, tick_hz=tick_hz, tag=f"preset:{name}")

    def for_scene(self, base: ClothParams) -> Config:
        """This configuration on a cloth like ``base``: a preset's takes the substeps the preset
        gives that cloth (its features), every other one is itself."""
        if not self.tag.startswith("preset:"):
            return self
        return self.from_preset(self.tag[len("preset:") :], self.solver, self.tick_hz, base)


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
    from ..sim import make_world

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
