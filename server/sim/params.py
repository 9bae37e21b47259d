"""Plain data of the simulation: materials, features, colliders and per-cloth settings.

The vocabulary (feature, link type and collider names, material fields with their ranges and
defaults, default gravity, wind, iterations, substeps) is the wire protocol's
(drape.client.protocol.vocabulary): these dataclasses are built from it, and add the server's
side (kernel build options, collider packing for the device, validation of a whole cloth).
Nothing here touches a device or the network.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Literal, cast

import numpy as np

from drape.client.protocol.vocabulary import (
    COLLIDER_IDS,
    DEFAULT_CHEBYSHEV_RHO,
    DEFAULT_GRAVITY,
    DEFAULT_ITERATIONS,
    DEFAULT_SUBSTEPS,
    DEFAULT_WIND,
    FEATURE_NAMES,
    LINK_TYPE_NAMES,
    MATERIAL_DEFAULTS,
    MATERIAL_FIELDS,
    MAX_COLLIDERS_PER_CLOTH,  # noqa: F401 (re-exported: the server's collider capacity)
    Capsule,
    Plane,
    Sphere,
    collider_shape,
)

LINK_STRUCTURAL, LINK_SHEAR, LINK_BENDING = (LINK_TYPE_NAMES.index(n) for n in ("structural", "shear", "bending"))

# MATERIAL_DEFAULTS maps every field to a float or a 3-tuple: these views type each kind's fields
_FLOAT_DEFAULTS = cast("dict[str, float]", MATERIAL_DEFAULTS)  # one-component fields
_VEC3_DEFAULTS = cast("dict[str, tuple[float, float, float]]", MATERIAL_DEFAULTS)  # stiffness, compliance

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


#: Self-collision's passes per substep (the kernels' -DSELF_COLLISION_PASSES, the reference's).
SELF_COLLISION_PASSES = 2

#: Continuous collision against spheres and capsules (kernels/colliders.cl, reference.collide): at
#: most this many conservative-advancement steps along a vertex's motion in a substep (the
#: kernels' -DCCD_STEPS), stopping within CCD_SLOP metres of the surface (-DCCD_SLOP).
CCD_STEPS = 12
CCD_SLOP = 1e-5

#: The features whose build option is spelled out even when off (those of protocol 1.5's kernels).
ALWAYS_SPELLED = ("xpbd", "tethers", "colliders", "wind", "normals")


@dataclass(frozen=True)
class Features:
    """What a cloth asks the solver to simulate. Each one off costs nothing (kernels are
    specialised with -D build options per feature set)."""

    xpbd: bool = False  # compliance-based links (XPBD) instead of the talk's PBD stiffness
    tethers: bool = False  # long-range attachments to the nearest pinned vertex
    colliders: bool = False  # spheres, capsules, planes with friction
    wind: bool = False  # drag and lift from per-vertex normals and areas (Bullet's model)
    normals: bool = False  # per-vertex normals in the published state
    # 1.6: vertices keep the material's thickness from the cloth's other vertices that are further
    # apart than it at rest (kernels/selfcollide.cl, collision.py)
    self_collision: bool = False

    def key(self) -> tuple[bool, ...]:
        return tuple(getattr(self, f.name) for f in fields(self))

    def build_options(self) -> list[str]:
        """-DFEATURE_X=0/1 for the features of 1.5's kernels, and for a later one only when it is
        on (cloth.cl defaults it to 0): a cloth without the new features builds today's kernel
        with today's options (the same program, the same cache entry)."""
        opts = [
            f"-DFEATURE_{f.name.upper()}={int(getattr(self, f.name))}"
            for f in fields(self)
            if f.name in ALWAYS_SPELLED or getattr(self, f.name)
        ]
        if self.colliders:
            opts += [f"-DCCD_STEPS={CCD_STEPS}", f"-DCCD_SLOP={CCD_SLOP!r}f"]
        if self.self_collision:
            opts.append(f"-DSELF_COLLISION_PASSES={SELF_COLLISION_PASSES}")
        return opts

    @property
    def needs_normals(self) -> bool:
        return self.wind or self.normals

    @classmethod
    def from_names(cls, names: list[str] | tuple[str, ...]) -> Features:
        valid = {f.name for f in fields(cls)}
        bad = [n for n in names if n not in valid]
        if bad:
            raise ValueError(f"unknown feature(s) {bad}; known: {sorted(valid)}")
        return cls(**{n: True for n in names})

    def names(self) -> list[str]:
        return [f.name for f in fields(self) if getattr(self, f.name)]


# The flags are spelled out above for the solver's readers; they are the protocol's names, in order.
assert tuple(f.name for f in fields(Features)) == FEATURE_NAMES, "params.Features must list protocol.FEATURE_NAMES"


@dataclass(frozen=True)
class Material:
    """Per-cloth material: the protocol's fields (protocol.MATERIAL_FIELDS) with its defaults.
    Stiffness and compliance are per link type (structural, shear, bending)."""

    mass: float = _FLOAT_DEFAULTS["mass"]  # total kg, spread over vertices by their share of the area
    stiffness: tuple[float, float, float] = _VEC3_DEFAULTS["stiffness"]  # PBD kLST in [0, 1]
    compliance: tuple[float, float, float] = _VEC3_DEFAULTS["compliance"]  # XPBD, metres per newton
    damping: float = _FLOAT_DEFAULTS["damping"]  # kDP: fraction of velocity removed per step, [0, 1]
    friction: float = _FLOAT_DEFAULTS["friction"]  # Coulomb-like coefficient against colliders
    drag: float = _FLOAT_DEFAULTS["drag"]  # kDG
    lift: float = _FLOAT_DEFAULTS["lift"]  # kLF
    air_density: float = _FLOAT_DEFAULTS["air_density"]  # rho, kg/m^3
    # a vertex may be this many times its rest distance from its anchor
    tether_limit: float = _FLOAT_DEFAULTS["tether_limit"]
    # self_collision (1.6): the distance kept between vertices further apart than it at rest, in
    # metres, and the share of a contact's depth each pass corrects, in [0, 1]
    thickness: float = _FLOAT_DEFAULTS["thickness"]
    contact_stiffness: float = _FLOAT_DEFAULTS["contact_stiffness"]


assert tuple(f.name for f in fields(Material)) == tuple(MATERIAL_FIELDS), (
    "params.Material must list protocol.MATERIAL_FIELDS"
)

# Colliders are the protocol's dataclasses (Sphere, Capsule, Plane: the half space n.x >= offset is
# outside, n normalised on packing); their type ids on the device are protocol.COLLIDER_IDS.
Collider = Sphere | Capsule | Plane
COLLIDER_SPHERE, COLLIDER_CAPSULE, COLLIDER_PLANE = (COLLIDER_IDS[n] for n in ("sphere", "capsule", "plane"))


def pack_colliders(colliders: list[Collider] | tuple[Collider, ...]) -> np.ndarray:
    """Colliders as (n, 2, 4) float32 device slots (kernels/layout.h): each shape's two rows
    (protocol.COLLIDER_SHAPES: row 0 = (x0, y0, z0, w), row 1 = (x1, y1, z1)) with its type id
    in row 1's w. ValueError for one that cannot be packed, TypeError for a non-collider."""
    out = np.zeros((len(colliders), 2, 4), np.float32)
    for i, c in enumerate(colliders):
        shape = collider_shape(c)
        row0, row1 = shape.rows(c)
        out[i, 0] = row0
        out[i, 1] = (*row1, COLLIDER_IDS[shape.name])
    if not np.all(np.isfinite(out)):
        raise ValueError("collider values must be finite")
    return out


@dataclass(frozen=True)
class ClothParams:
    """Everything about one cloth instance except its topology (the fabric)."""

    material: Material = field(default_factory=Material)
    features: Features = field(default_factory=Features)
    gravity: tuple[float, float, float] = DEFAULT_GRAVITY
    wind: tuple[float, float, float] = DEFAULT_WIND
    iterations: int = DEFAULT_ITERATIONS
    substeps: int = DEFAULT_SUBSTEPS
    # Jacobi only: Chebyshev semi-iterative acceleration (Wang 2015) with this estimate of the
    # spectral radius; 0 turns it off. Typical 0.9 .. 0.99.
    chebyshev_rho: float = DEFAULT_CHEBYSHEV_RHO

    def with_(self, **changes) -> ClothParams:
        return replace(self, **changes)

    def validate(self) -> None:
        """ValueError unless every field is finite and in range: the material by the protocol's
        ranges (protocol.MATERIAL_FIELDS; the wire's general cap of 10^6 is the decoder's, not a
        solver limit), iterations and substeps by the solvers' own (wider than the wire's: tools
        use them)."""
        m = self.material
        _finite("gravity", self.gravity)
        _finite("wind", self.wind)
        if not (0 <= self.iterations <= 1000):  # 0: no link solve (the talk's "no solver" row)
            raise ValueError("iterations must be in 0..1000")
        if not (0.0 <= self.chebyshev_rho < 1.0):
            raise ValueError("chebyshev_rho must be in [0, 1)")
        if not (1 <= self.substeps <= 100):
            raise ValueError("substeps must be in 1..100")
        for name, (width, lo, lo_inclusive, hi) in MATERIAL_FIELDS.items():
            value = getattr(m, name)
            values = tuple(value) if width > 1 else (value,)
            hi_eff = math.inf if hi is None else hi
            for v in values:
                if not (isinstance(v, (int, float)) and math.isfinite(v)):
                    raise ValueError(f"{name} must be finite, got {value!r}")
                if v < lo or (v == lo and not lo_inclusive) or v > hi_eff:
                    bracket = "[" if lo_inclusive else "("
                    raise ValueError(f"{name} must be in {bracket}{lo:g}, {hi_eff:g}], got {value!r}")


def _finite(name: str, values) -> None:
    vals = tuple(values)
    if len(vals) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
        raise ValueError(f"{name} must be three finite numbers")
