"""Plain data shared by every layer: materials, features, colliders and per-cloth settings.

Nothing here touches numpy buffers on a device or the network; the solver, the tick loop and
the wire protocol all build on these dataclasses.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Literal

import numpy as np

LINK_STRUCTURAL = 0
LINK_SHEAR = 1
LINK_BENDING = 2
LINK_TYPE_NAMES = ("structural", "shear", "bending")

SOLVERS = ("workgroup", "coloured", "jacobi", "reference")
SolverName = Literal["workgroup", "coloured", "jacobi", "reference"]


@dataclass(frozen=True)
class LinkOptions:
    """Which link types a fabric is cooked with."""

    structural: bool = True
    shear: bool = True
    bending: bool = False

    def types(self) -> tuple[int, ...]:
        return tuple(t for t, on in enumerate((self.structural, self.shear, self.bending)) if on)


@dataclass(frozen=True)
class Features:
    """What a cloth asks the solver to simulate. Each one off costs nothing (kernels are
    specialised with -D build options per feature set)."""

    xpbd: bool = False  # compliance-based links (XPBD) instead of the talk's PBD stiffness
    tethers: bool = False  # long-range attachments to the nearest pinned vertex
    colliders: bool = False  # spheres, capsules, planes with friction
    wind: bool = False  # drag and lift from per-vertex normals and areas (Bullet's model)
    normals: bool = False  # per-vertex normals in the published state

    def key(self) -> tuple[bool, ...]:
        return tuple(getattr(self, f.name) for f in fields(self))

    def build_options(self) -> list[str]:
        return [f"-DFEATURE_{f.name.upper()}={int(getattr(self, f.name))}" for f in fields(self)]

    @property
    def needs_normals(self) -> bool:
        return self.wind or self.normals

    @classmethod
    def from_names(cls, names: list[str] | tuple[str, ...]) -> "Features":
        valid = {f.name for f in fields(cls)}
        bad = [n for n in names if n not in valid]
        if bad:
            raise ValueError(f"unknown feature(s) {bad}; known: {sorted(valid)}")
        return cls(**{n: True for n in names})

    def names(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name)]


@dataclass(frozen=True)
class Material:
    """Per-cloth material. Stiffness and compliance are per link type
    (structural, shear, bending)."""

    mass: float = 1.0  # total kg, spread over vertices by their share of the area
    stiffness: tuple[float, float, float] = (1.0, 1.0, 1.0)  # PBD kLST in [0, 1]
    compliance: tuple[float, float, float] = (0.0, 0.0, 0.0)  # XPBD, metres per newton
    damping: float = 0.0  # kDP: fraction of velocity removed per step, [0, 1]
    friction: float = 0.0  # Coulomb-like coefficient against colliders
    drag: float = 0.0  # kDG
    lift: float = 0.0  # kLF
    air_density: float = 1.2  # rho, kg/m^3
    tether_limit: float = 1.0  # a vertex may be this many times its rest distance from its anchor


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class Capsule:
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    radius: float


@dataclass(frozen=True)
class Plane:
    """The half space n.x >= offset is outside; n is normalised on packing."""

    normal: tuple[float, float, float]
    offset: float


Collider = Sphere | Capsule | Plane
COLLIDER_SPHERE, COLLIDER_CAPSULE, COLLIDER_PLANE = 0, 1, 2
MAX_COLLIDERS_PER_CLOTH = 32


def pack_colliders(colliders: list[Collider] | tuple[Collider, ...]) -> np.ndarray:
    """Colliders as (n, 2, 4) float32: row 0 = (x0, y0, z0, radius), row 1 = (x1, y1, z1, type).
    A sphere repeats its centre; a plane stores its unit normal in row 0 xyz, offset in w."""
    out = np.zeros((len(colliders), 2, 4), np.float32)
    for i, c in enumerate(colliders):
        if isinstance(c, Sphere):
            out[i, 0] = (*c.center, c.radius)
            out[i, 1] = (*c.center, COLLIDER_SPHERE)
        elif isinstance(c, Capsule):
            out[i, 0] = (*c.p0, c.radius)
            out[i, 1] = (*c.p1, COLLIDER_CAPSULE)
        elif isinstance(c, Plane):
            n = np.asarray(c.normal, np.float64)
            norm = float(np.linalg.norm(n))
            if not norm > 0.0:
                raise ValueError("plane normal must be non-zero")
            out[i, 0] = (*(n / norm), c.offset)
            out[i, 1] = (0.0, 0.0, 0.0, COLLIDER_PLANE)
        else:
            raise TypeError(f"not a collider: {c!r}")
    if not np.all(np.isfinite(out)):
        raise ValueError("collider values must be finite")
    return out


@dataclass(frozen=True)
class ClothParams:
    """Everything about one cloth instance except its topology (the fabric)."""

    material: Material = field(default_factory=Material)
    features: Features = field(default_factory=Features)
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    iterations: int = 10
    substeps: int = 1
    # Jacobi only: Chebyshev semi-iterative acceleration (Wang 2015) with this estimate of the
    # spectral radius; 0 turns it off. Typical 0.9 .. 0.99.
    chebyshev_rho: float = 0.0

    def with_(self, **changes) -> "ClothParams":
        return replace(self, **changes)

    def validate(self) -> None:
        m = self.material
        _finite("gravity", self.gravity)
        _finite("wind", self.wind)
        _finite("stiffness", m.stiffness)
        _finite("compliance", m.compliance)
        if not (0 <= self.iterations <= 1000):  # 0: no link solve (the talk's "no solver" row)
            raise ValueError("iterations must be in 0..1000")
        if not (0.0 <= self.chebyshev_rho < 1.0):
            raise ValueError("chebyshev_rho must be in [0, 1)")
        if not (1 <= self.substeps <= 100):
            raise ValueError("substeps must be in 1..100")
        if not (math.isfinite(m.mass) and m.mass > 0):
            raise ValueError("mass must be finite and > 0")
        if any(not (0.0 <= s <= 1.0) for s in m.stiffness):
            raise ValueError("stiffness must be in [0, 1]")
        if any(c < 0 for c in m.compliance):
            raise ValueError("compliance must be >= 0")
        for name in ("damping",):
            v = getattr(m, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1]")
        for name in ("friction", "drag", "lift", "air_density"):
            v = getattr(m, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0")
        if not (math.isfinite(m.tether_limit) and m.tether_limit >= 1.0):
            raise ValueError("tether_limit must be finite and >= 1")


def _finite(name: str, values) -> None:
    vals = tuple(values)
    if len(vals) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
        raise ValueError(f"{name} must be three finite numbers")
