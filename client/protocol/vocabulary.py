"""The cloth description vocabulary and limits: features, quality presets, encodings, colliders,
material fields with their ranges and defaults, link options, grid/mesh/state/pin specs and the
decoder caps (PROTOCOL.md sections 4, 5, 13). The server (drape.server.sim.params) takes its names,
defaults and ranges from here."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

MAX_COLLIDERS_PER_CLOTH = 32  # the server's per-cloth collider capacity (device buffers)
MAX_SCENE_COLLIDERS = 16  # 1.7: a scene's colliders (each cloth of it: its own + these <= MAX_COLLIDERS_PER_CLOTH)
MAX_SCENE_MEMBERS = 64  # 1.7: client ids a scene request's members may list
#: 1.8: a mesh collider's size limits (the device's buffers and the wire's; a 5,000-triangle body is
#: far below them) and the least area of one of its triangles (m^2; a smaller one is degenerate).
MESH_MAX_VERTICES = 65536
MESH_MAX_TRIANGLES = 65536
MESH_MIN_AREA = 1e-10

#: Decoding caps against hostile input (1.2, PROTOCOL.md section 13), independent of the server's
#: configured limits: no legitimate message comes near them. Nesting counts maps and arrays (a
#: batch item's collider centre is at depth 6); elements counts every value of the message.
MAX_NESTING = 16
MAX_MAP_KEYS = 128  # keys of any one map, known and unknown together
MAX_ARRAY_LENGTH = 1024  # elements of any one msgpack array (bulk data travels as bin)
MAX_STRING_BYTES = 1 << 16  # bytes of any one string
MAX_ELEMENTS = 1 << 16  # values in one message, containers and scalars together


@dataclass(frozen=True)
class Limits:
    """Caps every decoder enforces (the server passes its configured values)."""

    max_message_bytes: int = 8 << 20
    max_vertices: int = 65536  # per cloth
    max_triangles: int = 262144  # per mesh
    max_pin_updates: int = 4096  # pin targets in one control message (in one batch item)
    max_batch_items: int = 64  # items in one batch control (1.1)
    max_batch_moves: int = MAX_ARRAY_LENGTH  # cloths in one batch control's moves block (1.4; fixed)
    max_colliders: int = MAX_COLLIDERS_PER_CLOTH
    max_iterations: int = 100
    max_substeps: int = 100
    max_features: int = 16
    max_coordinate: float = 1.0e5  # |x|, |y|, |z| of any position in metres
    max_acceleration: float = 1.0e4  # |component| of gravity and wind, m/s^2 resp. m/s
    max_material_value: float = 1.0e6


DEFAULT_LIMITS = Limits()

# ---------------------------------------------------------------------------------------------
# Cloth description vocabulary (drape.server.sim.params builds its dataclasses from these)

#: Feature names, in the order of the server's feature flags (params.Features fields).
FEATURE_NAMES = ("xpbd", "tethers", "colliders", "wind", "normals", "self_collision")
#: What a quality preset switches (1.1): iterations, substeps and these features.
PRESET_FEATURES = ("xpbd", "tethers")
# Quality presets (1.1), cheapest first: named solver settings the server defines (iterations,
# substeps, XPBD, tethers); the server may step a cloth down this list under load and back up.
QUALITY_PRESETS = ("fast", "balanced", "accurate", "exact")
ORIENTATIONS = ("horizontal", "vertical")
#: Link types, in the order of their ids on the server (0 structural, 1 shear, 2 bending).
LINK_TYPE_NAMES = ("structural", "shear", "bending")
#: 1.2: the least total mass (kg). Smaller masses make per-vertex masses or inverse masses that
#: float32 cannot hold (subnormal, or infinite), which turns the cloth non-finite every tick.
MIN_MASS = 1.0e-9

#: name -> (number of components, lower bound, lower bound inclusive, upper bound)
MATERIAL_FIELDS: dict[str, tuple[int, float, bool, float | None]] = {
    "mass": (1, MIN_MASS, True, None),
    "stiffness": (3, 0.0, True, 1.0),
    "compliance": (3, 0.0, True, None),
    "damping": (1, 0.0, True, 1.0),
    "friction": (1, 0.0, True, None),
    "drag": (1, 0.0, True, None),
    "lift": (1, 0.0, True, None),
    "air_density": (1, 0.0, True, None),
    "tether_limit": (1, 1.0, True, None),
    "thickness": (1, 0.0, True, 1.0),  # 1.6, self_collision: metres kept between non-neighbours
    "contact_stiffness": (1, 0.0, True, 1.0),  # 1.6, self_collision: share of a contact corrected
}
#: The server's defaults (params.Material, ClothParams) for fields a submission leaves out.
MATERIAL_DEFAULTS: dict[str, float | tuple[float, float, float]] = {
    "mass": 1.0,
    "stiffness": (1.0, 1.0, 1.0),
    "compliance": (0.0, 0.0, 0.0),
    "damping": 0.0,
    "friction": 0.0,
    "drag": 0.0,
    "lift": 0.0,
    "air_density": 1.2,
    "tether_limit": 1.0,
    "thickness": 0.01,
    "contact_stiffness": 1.0,
}
DEFAULT_GRAVITY = (0.0, -9.81, 0.0)
DEFAULT_WIND = (0.0, 0.0, 0.0)
DEFAULT_ITERATIONS = 10  # 0 = no link solve
DEFAULT_SUBSTEPS = 1
DEFAULT_CHEBYSHEV_RHO = 0.0  # Jacobi solver only; 0 = off

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Sphere:
    center: Vec3
    radius: float


@dataclass(frozen=True)
class Capsule:
    p0: Vec3
    p1: Vec3
    radius: float


@dataclass(frozen=True)
class Plane:
    """The half space normal . x >= offset is outside (normal need not be unit length)."""

    normal: Vec3
    offset: float


Collider = Sphere | Capsule | Plane

#: A device collider slot's two float4 rows without the type: row 0 (x0, y0, z0, w0), row 1 xyz
#: (the packer writes the shape's id in row 1's w). The layout is kernels/layout.h's.
ColliderRows = tuple[tuple[float, float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class ShapeField:
    """One wire field of a collider shape: a vec3 (each component within +-max_coordinate) or a
    number (within 0..max_coordinate, or +-max_coordinate when ``signed``); ``nonzero``: a vec3
    that must not be all zeros."""

    name: str
    vec3: bool = False
    signed: bool = False
    nonzero: bool = False


@dataclass(frozen=True)
class ColliderShape:
    """A collider shape: its wire ``type`` name, dataclass, wire fields (in wire order, the
    dataclass's fields) and its packing into a device collider slot (``rows``; ValueError when
    the collider cannot be packed). Its type id on the device is its position in COLLIDER_SHAPES."""

    name: str
    cls: type
    fields: tuple[ShapeField, ...]
    rows: Callable[[Any], ColliderRows]


def _plane_rows(c: Plane) -> ColliderRows:
    """Row 0 = the unit normal and the offset (the normal normalised in float64)."""
    n = np.asarray(c.normal, np.float64)
    norm = float(np.linalg.norm(n))
    if not norm > 0.0:
        raise ValueError("plane normal must be non-zero")
    x, y, z = (float(v) for v in n / norm)
    return (x, y, z, c.offset), (0.0, 0.0, 0.0)


#: Every collider shape, each declared once (PROTOCOL.md section 4, "Colliders"): the codec,
#: validation, JSON Schema and the server's packing (drape.server.sim.params.pack_colliders)
#: iterate over it. Row 0 of a slot holds (point, radius) and row 1 (point, type id): a sphere
#: repeats its centre; a plane keeps its unit normal and offset in row 0.
COLLIDER_SHAPES: tuple[ColliderShape, ...] = (
    ColliderShape(
        "sphere",
        Sphere,
        (ShapeField("center", vec3=True), ShapeField("radius")),
        lambda c: ((*c.center, c.radius), c.center),
    ),
    ColliderShape(
        "capsule",
        Capsule,
        (ShapeField("p0", vec3=True), ShapeField("p1", vec3=True), ShapeField("radius")),
        lambda c: ((*c.p0, c.radius), c.p1),
    ),
    ColliderShape(
        "plane",
        Plane,
        (ShapeField("normal", vec3=True, nonzero=True), ShapeField("offset", signed=True)),
        _plane_rows,
    ),
)
#: Collider type names, in the order of their ids on the device (0 sphere, 1 capsule, 2 plane).
COLLIDER_TYPES = tuple(s.name for s in COLLIDER_SHAPES)
COLLIDER_IDS = {s.name: i for i, s in enumerate(COLLIDER_SHAPES)}
_SHAPE_OF_CLASS = {s.cls: s for s in COLLIDER_SHAPES}
for _s in COLLIDER_SHAPES:
    assert tuple(f.name for f in _s.fields) == tuple(f.name for f in fields(_s.cls)), _s.name


def collider_shape(c: object) -> ColliderShape:
    """The shape of collider ``c``: by its class, else (an object of another library) the first
    shape whose every field it has. TypeError for anything else."""
    shape = _SHAPE_OF_CLASS.get(type(c))
    if shape is not None:
        return shape
    for shape in COLLIDER_SHAPES:
        if isinstance(c, shape.cls) or all(hasattr(c, f.name) for f in shape.fields):
            return shape
    raise TypeError(f"not a collider: {c!r}")


def as_collider(c: Any) -> Collider:
    """``c`` as a protocol collider: one already, a wire map (``{"type": "sphere", ...}``) or an
    object with a shape's fields (TypeError or ValueError for anything else)."""
    if type(c) in _SHAPE_OF_CLASS:
        return c  # type: ignore[no-any-return]
    if isinstance(c, Mapping):
        kind = c.get("type")
        if kind not in COLLIDER_IDS:
            raise TypeError(f"not a collider: {c!r}")
        shape = COLLIDER_SHAPES[COLLIDER_IDS[kind]]
        get = c.__getitem__
    else:
        shape = collider_shape(c)
        get = functools.partial(getattr, c)
    values = []
    for f in shape.fields:
        v = get(f.name)
        if f.vec3:
            v = tuple(float(x) for x in v)
            if len(v) != 3:
                raise ValueError(f"collider {shape.name}.{f.name}: expected 3 numbers, got {len(v)}")
        values.append(v if f.vec3 else float(v))
    return shape.cls(*values)  # type: ignore[no-any-return]


def collider_shape_named(name: str) -> ColliderShape:
    """The shape whose wire ``type`` is ``name`` (KeyError if none)."""
    return COLLIDER_SHAPES[COLLIDER_IDS[name]]


@dataclass(frozen=True)
class GridSpec:
    """A regular grid; vertex (row r, column c) has index r * cols + c (see grid_geometry)."""

    cols: int
    rows: int
    width: float = 1.0
    height: float = 1.0
    orientation: str = "horizontal"
    origin: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True, eq=False)
class MeshSpec:
    vertices: np.ndarray  # (n, 3) float32
    triangles: np.ndarray  # (m, 3) uint32

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, MeshSpec)
            and np.array_equal(self.vertices, other.vertices)
            and np.array_equal(self.triangles, other.triangles)
        )


@dataclass(frozen=True, eq=False)
class MeshCollider:
    """1.8: a cloth's or a scene's triangle-mesh collider (PROTOCOL.md 5.4), one of four changes:

    - a new mesh: ``vertices`` (n, 3) float32 in its own frame and ``triangles`` (m, 3) uint32,
      counter-clockwise seen from outside, placed at the pose;
    - a re-pose: ``vertices`` alone, new positions of the current mesh's vertices (same triangles);
    - a rigid move: neither (:meth:`pose`), the current mesh to ``position`` and ``rotation``;
    - a removal: ``remove`` (:meth:`removal`), nothing else.

    The pose is a position (m) and a rotation quaternion ``(w, x, y, z)`` (normalised by the
    server), mesh frame to world."""

    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None
    position: Vec3 = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    remove: bool = False

    @classmethod
    def pose(cls, position: Iterable[float], rotation: Iterable[float] = (1.0, 0.0, 0.0, 0.0)) -> MeshCollider:
        """A rigid move of the current mesh (the per-tick change)."""
        return cls(None, None, tuple(map(float, position)), tuple(map(float, rotation)))  # type: ignore[arg-type]

    @classmethod
    def removal(cls) -> MeshCollider:
        return cls(remove=True)

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, MeshCollider)
            and _same(self.vertices, other.vertices)
            and _same(self.triangles, other.triangles)
            and tuple(self.position) == tuple(other.position)
            and tuple(self.rotation) == tuple(other.rotation)
            and self.remove == other.remove
        )


def _same(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


def mesh_problem(vertices: np.ndarray, triangles: np.ndarray | None) -> tuple[str, str] | None:
    """What is wrong with a mesh collider, as (``too_large`` or ``invalid_value``, message), or
    None: no vertices or triangles, more than MESH_MAX_VERTICES or MESH_MAX_TRIANGLES, a non-finite
    vertex, non-integer indices, an index out of range, a degenerate triangle (area under
    MESH_MIN_AREA m^2, repeated indices included). ``triangles`` None checks the vertices alone.
    The one copy of these checks: the decoder and the server's ``meshes.collision_mesh`` call it."""
    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        return "invalid_value", f"mesh vertices must be (n, 3) with n >= 1, got shape {v.shape}"
    if len(v) > MESH_MAX_VERTICES:
        return "too_large", f"mesh has {len(v)} vertices: at most {MESH_MAX_VERTICES}"
    if not np.all(np.isfinite(v)):
        return "invalid_value", "mesh vertices must be finite"
    if triangles is None:
        return None
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        return "invalid_value", f"mesh triangles must be (m, 3) with m >= 1, got shape {t.shape}"
    if len(t) > MESH_MAX_TRIANGLES:
        return "too_large", f"mesh has {len(t)} triangles: at most {MESH_MAX_TRIANGLES}"
    if not np.issubdtype(t.dtype, np.integer):
        return "invalid_value", "mesh triangle indices must be integers"
    bad = np.nonzero((t < 0) | (t >= len(v)))[0]
    if len(bad):
        return "invalid_value", f"mesh triangle {int(bad[0])} has an index out of range (vertices: {len(v)})"
    t = t.astype(np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    bad = np.nonzero(~(area >= MESH_MIN_AREA))[0]
    if len(bad):
        return (
            "invalid_value",
            f"mesh triangle {int(bad[0])} is degenerate (area {area[bad[0]]:.3g} m^2 < {MESH_MIN_AREA:g});"
            f" {len(bad)} such",
        )
    return None


@dataclass(frozen=True)
class LinkSpec:
    structural: bool = True
    shear: bool = True  # grids only: cell diagonals
    bending: bool = False


ENCODINGS = ("float32", "float16", "quant16", "predictive")
ENC_FLOAT32, ENC_FLOAT16, ENC_QUANT16, ENC_PREDICTIVE = 0, 1, 2, 3
ENCODING_IDS = {"float32": ENC_FLOAT32, "float16": ENC_FLOAT16, "quant16": ENC_QUANT16, "predictive": ENC_PREDICTIVE}
#: Encodings whose every state stands alone (a predictive state needs the stream's last two: 1.5).
STATELESS_ENCODINGS = ("float32", "float16", "quant16")
#: predictive (1.5): the grid step in metres a client may choose (``state.step``), and the default.
STEP_MIN, STEP_MAX, STEP_DEFAULT = 1e-5, 0.1, 0.001
ENCODING_NAMES = {v: k for k, v in ENCODING_IDS.items()}


@dataclass(frozen=True)
class StateOptions:
    """How a cloth's state is published. None = unchanged (control) or the default (submit:
    no normals, float32, own key). ``bundle`` (1.1, submission only): publish the state inside
    the client's bundle on Keys.bundle(client) instead of on the cloth's own key. ``step`` (1.5):
    the predictive encoding's grid step in metres (default STEP_DEFAULT; the largest error of a
    decoded position is half of it)."""

    normals: bool | None = None
    encoding: str | None = None
    bundle: bool | None = None
    step: float | None = None  # 1.5, predictive: grid step in metres (STEP_MIN..STEP_MAX)


@dataclass(frozen=True, eq=False)
class PinUpdate:
    indices: np.ndarray  # (k,) uint32, pinned vertices only
    targets: np.ndarray  # (k, 3) float32, metres

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, PinUpdate)
            and np.array_equal(self.indices, other.indices)
            and np.array_equal(self.targets, other.targets)
        )


@dataclass(frozen=True, eq=False)
class PinMoves:
    """1.4, batch control only: the pin moves of many cloths as one columnar block (PROTOCOL.md
    5.1.1). ``cloths[j]`` (owned by ``tokens[j]``) has its pinned vertices ``indices`` (k,) uint32,
    the same for every cloth, at ``targets[j]`` ((n, k, 3) float32, metres)."""

    cloths: list[str]
    tokens: list[str]
    indices: np.ndarray  # (k,) uint32, distinct, pinned vertices of every cloth
    targets: np.ndarray  # (n, k, 3) float32

    def __len__(self) -> int:
        return len(self.cloths)

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, PinMoves)
            and list(self.cloths) == list(other.cloths)
            and list(self.tokens) == list(other.tokens)
            and np.array_equal(self.indices, other.indices)
            and np.array_equal(np.asarray(self.targets).reshape(-1), np.asarray(other.targets).reshape(-1))
        )


@dataclass(frozen=True, eq=False)
class ResumeState:
    """1.3, submit only: continue a cloth from its last known state instead of its rest pose (a
    failover to another server, or a resubmission after the cloth was reclaimed). ``positions``
    (n, 3) float32 metres; ``velocities`` (n, 3) float32 m/s, None = zero; pinned vertices start
    at ``positions`` (their pin targets there) with zero velocity. ``tick``, ``from_server`` and
    ``cloth``: where the state came from, informational (logged by the server, never trusted)."""

    positions: np.ndarray
    velocities: np.ndarray | None = None
    tick: int | None = None
    from_server: str | None = None
    cloth: str | None = None

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, ResumeState)
            and np.array_equal(self.positions, other.positions)
            and (self.velocities is None) == (other.velocities is None)
            and (
                self.velocities is None or other.velocities is None or np.array_equal(self.velocities, other.velocities)
            )
            and (self.tick, self.from_server, self.cloth) == (other.tick, other.from_server, other.cloth)
        )


def _empty_u32() -> np.ndarray:
    return np.zeros(0, np.uint32)
