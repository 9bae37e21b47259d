"""The Drape wire protocol, version 1.1 (see PROTOCOL.md at the repository root).

Requests and replies are msgpack maps; the per-tick cloth state is a fixed little-endian binary
layout that any language reads with a struct. This module is the single source of truth for
both: key expressions, dataclasses for every message, ``encode_*``/``decode_*`` pairs, and the
validation that turns anything malformed or hostile into a :class:`ProtocolError` carrying a
stable error ``code``.

1.1 adds, backward compatibly: state bundles (``state.bundle`` at submission; one binary
``DRPB`` publication per client per tick on :meth:`Keys.bundle`, see :func:`encode_bundle`) and
batch control (many cloths' controls in one request on :meth:`Keys.control_batch`, one result
per item, see :func:`decode_control_batch`).

It imports only numpy, msgpack and the standard library, so a game client or a tool can use it
without Zenoh or OpenCL installed.
"""
from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass, field, fields
from typing import Any, Iterable, Mapping, Sequence

import msgpack
import numpy as np

# ---------------------------------------------------------------------------------------------
# Versions, keys, names

PROTOCOL_MAJOR = 1
PROTOCOL_MINOR = 1
PROTOCOL_VERSION: tuple[int, int] = (PROTOCOL_MAJOR, PROTOCOL_MINOR)
VERSION_STRING = f"{PROTOCOL_MAJOR}.{PROTOCOL_MINOR}"

DEFAULT_NAMESPACE = "drape"
DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

#: Ids (server, client, cloth) are single key-expression chunks made of these characters.
ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
NAMESPACE_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,64}(/[A-Za-z0-9_.\-]{1,64}){0,7}$")
TOKEN_RE = re.compile(r"^[0-9a-f]{32}$")


def valid_id(s: object) -> bool:
    return isinstance(s, str) and bool(ID_RE.match(s))


@dataclass(frozen=True)
class Keys:
    """Every key expression of one Drape namespace."""

    namespace: str = DEFAULT_NAMESPACE

    def __post_init__(self) -> None:
        if not NAMESPACE_RE.match(self.namespace):
            raise ValueError(f"invalid namespace {self.namespace!r}: chunks of [A-Za-z0-9_.-] separated by '/'")

    def submit(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/submit"

    def control(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/control"

    def control_batch(self, server: str) -> str:  # queryable (1.1)
        return f"{self.namespace}/server/{server}/control_batch"

    def remove(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/remove"

    def info(self, server: str) -> str:  # queryable
        return f"{self.namespace}/server/{server}/info"

    def stats(self, server: str) -> str:  # publication, every stats period
        return f"{self.namespace}/server/{server}/stats"

    def state(self, cloth: str) -> str:  # publication, every tick, binary
        return f"{self.namespace}/cloth/{cloth}/state"

    def bundle(self, client: str) -> str:  # publication, every tick, binary bundle (1.1)
        return f"{self.namespace}/client/{client}/states"

    def alive_server(self, server: str) -> str:  # liveliness token
        return f"{self.namespace}/alive/server/{server}"

    def alive_client(self, client: str) -> str:  # liveliness token
        return f"{self.namespace}/alive/client/{client}"

    @property
    def all_servers_alive(self) -> str:
        return f"{self.namespace}/alive/server/*"

    @property
    def all_clients_alive(self) -> str:
        return f"{self.namespace}/alive/client/*"

    def last_chunk(self, key: str) -> str:
        return str(key).rsplit("/", 1)[-1]


# ---------------------------------------------------------------------------------------------
# Errors

ERR_MALFORMED = "malformed"  # not a msgpack map (truncated, garbage, trailing bytes)
ERR_UNSUPPORTED_VERSION = "unsupported_version"  # unknown major version
ERR_MISSING_FIELD = "missing_field"
ERR_INVALID_TYPE = "invalid_type"
ERR_INVALID_VALUE = "invalid_value"  # non-finite, out of range, unknown name, bad combination
ERR_INDEX_OUT_OF_RANGE = "index_out_of_range"
ERR_TOO_LARGE = "too_large"  # message bytes or an array beyond the protocol caps
ERR_LIMIT_EXCEEDED = "limit_exceeded"  # server quota: cloths, cloths per client, total vertices
ERR_NOT_FOUND = "not_found"  # no such cloth on this server
ERR_FORBIDDEN = "forbidden"  # the token does not own the cloth
ERR_BUSY = "busy"  # request queue full, or the server is shutting down
ERR_INTERNAL = "internal"
ERR_UNAVAILABLE = "unavailable"  # client side only: no server answered in time

ERROR_CODES = (
    ERR_MALFORMED,
    ERR_UNSUPPORTED_VERSION,
    ERR_MISSING_FIELD,
    ERR_INVALID_TYPE,
    ERR_INVALID_VALUE,
    ERR_INDEX_OUT_OF_RANGE,
    ERR_TOO_LARGE,
    ERR_LIMIT_EXCEEDED,
    ERR_NOT_FOUND,
    ERR_FORBIDDEN,
    ERR_BUSY,
    ERR_INTERNAL,
    ERR_UNAVAILABLE,
)


class DrapeError(Exception):
    """Any error reported by a Drape server (or by the SDK on its behalf): a stable ``code``
    from ERROR_CODES and a human-readable ``message``."""

    default_code = ERR_INTERNAL

    def __init__(self, code: str | None = None, message: str = "", rid: int | None = None) -> None:
        self.code = code or self.default_code
        self.message = message
        self.rid = rid
        super().__init__(f"[{self.code}] {message}")


class ProtocolError(DrapeError):
    """A message breaks the protocol: malformed, wrong version, wrong type or value, too large."""

    default_code = ERR_INVALID_VALUE


class LimitExceeded(DrapeError):
    default_code = ERR_LIMIT_EXCEEDED


class NotFound(DrapeError):
    default_code = ERR_NOT_FOUND


class Forbidden(DrapeError):
    default_code = ERR_FORBIDDEN


class Busy(DrapeError):
    default_code = ERR_BUSY


class Unavailable(DrapeError):
    default_code = ERR_UNAVAILABLE


class InternalError(DrapeError):
    default_code = ERR_INTERNAL


_ERROR_CLASSES: dict[str, type[DrapeError]] = {
    ERR_LIMIT_EXCEEDED: LimitExceeded,
    ERR_NOT_FOUND: NotFound,
    ERR_FORBIDDEN: Forbidden,
    ERR_BUSY: Busy,
    ERR_UNAVAILABLE: Unavailable,
    ERR_INTERNAL: InternalError,
}


def error_for(code: str, message: str, rid: int | None = None) -> DrapeError:
    """The DrapeError subclass for a code (ProtocolError for every validation code)."""
    cls = _ERROR_CLASSES.get(code, ProtocolError if code in ERROR_CODES else DrapeError)
    return cls(code, message, rid)


# ---------------------------------------------------------------------------------------------
# Limits


@dataclass(frozen=True)
class Limits:
    """Caps every decoder enforces (the server passes its configured values)."""

    max_message_bytes: int = 8 << 20
    max_vertices: int = 65536  # per cloth
    max_triangles: int = 262144  # per mesh
    max_pin_updates: int = 4096  # pin targets in one control message (in one batch item)
    max_batch_items: int = 64  # items in one batch control (1.1)
    max_colliders: int = 32  # = params.MAX_COLLIDERS_PER_CLOTH
    max_iterations: int = 100
    max_substeps: int = 100
    max_features: int = 16
    max_coordinate: float = 1.0e5  # |x|, |y|, |z| of any position in metres
    max_acceleration: float = 1.0e4  # |component| of gravity and wind, m/s^2 resp. m/s
    max_material_value: float = 1.0e6


DEFAULT_LIMITS = Limits()

# ---------------------------------------------------------------------------------------------
# Cloth description vocabulary (mirrors drape.server.sim.params; tests keep them in step)

FEATURE_NAMES = ("xpbd", "tethers", "colliders", "wind", "normals")
# Quality presets (1.1), cheapest first: named solver settings the server defines (iterations,
# substeps, XPBD, tethers); the server may step a cloth down this list under load and back up.
QUALITY_PRESETS = ("fast", "balanced", "accurate", "exact")
ORIENTATIONS = ("horizontal", "vertical")

#: name -> (number of components, lower bound, lower bound inclusive, upper bound)
MATERIAL_FIELDS: dict[str, tuple[int, float, bool, float | None]] = {
    "mass": (1, 0.0, False, None),
    "stiffness": (3, 0.0, True, 1.0),
    "compliance": (3, 0.0, True, None),
    "damping": (1, 0.0, True, 1.0),
    "friction": (1, 0.0, True, None),
    "drag": (1, 0.0, True, None),
    "lift": (1, 0.0, True, None),
    "air_density": (1, 0.0, True, None),
    "tether_limit": (1, 1.0, True, None),
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


@dataclass(frozen=True)
class LinkSpec:
    structural: bool = True
    shear: bool = True  # grids only: cell diagonals
    bending: bool = False


ENCODINGS = ("float32", "float16", "quant16")
ENC_FLOAT32, ENC_FLOAT16, ENC_QUANT16 = 0, 1, 2
ENCODING_IDS = {"float32": ENC_FLOAT32, "float16": ENC_FLOAT16, "quant16": ENC_QUANT16}
ENCODING_NAMES = {v: k for k, v in ENCODING_IDS.items()}


@dataclass(frozen=True)
class StateOptions:
    """How a cloth's state is published. None = unchanged (control) or the default (submit:
    no normals, float32, own key). ``bundle`` (1.1, submission only): publish the state inside
    the client's bundle on Keys.bundle(client) instead of on the cloth's own key."""

    normals: bool | None = None
    encoding: str | None = None
    bundle: bool | None = None


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


def _empty_u32() -> np.ndarray:
    return np.zeros(0, np.uint32)


# ---------------------------------------------------------------------------------------------
# Messages


@dataclass(eq=False)
class SubmitRequest:
    """Add a cloth. Exactly one of ``grid`` and ``mesh``. ``None`` means "server default"."""

    client: str
    grid: GridSpec | None = None
    mesh: MeshSpec | None = None
    pinned: np.ndarray = field(default_factory=_empty_u32)
    links: LinkSpec | None = None
    material: dict[str, Any] = field(default_factory=dict)  # only the fields given
    features: tuple[str, ...] = ()
    gravity: Vec3 | None = None
    wind: Vec3 | None = None
    iterations: int | None = None
    substeps: int | None = None
    chebyshev_rho: float | None = None
    colliders: tuple[Collider, ...] | None = None
    state: StateOptions | None = None
    quality: str | None = None  # 1.1: a QUALITY_PRESETS name; sets iterations, substeps, xpbd, tethers
    rid: int = 0

    @property
    def n_vertices(self) -> int:
        if self.grid is not None:
            return self.grid.cols * self.grid.rows
        assert self.mesh is not None
        return len(self.mesh.vertices)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SubmitRequest) and submit_to_map(self) == submit_to_map(other)


@dataclass(eq=False)
class ControlRequest:
    """Change a cloth from the next tick on. Every field but cloth and token is optional."""

    cloth: str
    token: str
    pins: PinUpdate | None = None
    colliders: tuple[Collider, ...] | None = None  # replaces the set; () clears it
    gravity: Vec3 | None = None
    wind: Vec3 | None = None
    material: dict[str, Any] = field(default_factory=dict)  # merged over the current material
    features: tuple[str, ...] | None = None  # replaces the feature set
    iterations: int | None = None
    substeps: int | None = None
    chebyshev_rho: float | None = None
    state: StateOptions | None = None
    reset: bool = False  # back to the rest pose with zero velocity
    quality: str | None = None  # 1.1: the preset the client wants from now on
    rid: int = 0

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControlRequest) and control_to_map(self) == control_to_map(other)


@dataclass
class RemoveRequest:
    cloth: str
    token: str
    rid: int = 0


@dataclass
class InfoRequest:
    rid: int = 0


@dataclass
class SubmitReply:
    cloth: str
    token: str
    key: str  # the cloth's own state key (where its state is published unless bundled)
    vertices: int
    tick: int  # the first tick whose state includes the cloth
    rid: int = 0
    bundle_key: str | None = None  # 1.1: set when the state goes in the client's bundle on this key instead


@dataclass
class ControlReply:
    tick: int  # the first tick whose state reflects the change
    rid: int = 0


@dataclass
class RemoveReply:
    tick: int  # the last tick published for the cloth; nothing later is ever published
    rid: int = 0


@dataclass
class ErrorReply:
    code: str
    message: str
    rid: int = 0

    def exception(self) -> DrapeError:
        return error_for(self.code, self.message, self.rid)


@dataclass(eq=False)
class ControlBatchRequest:
    """1.1: controls of many cloths of one client in one request. Each item is a control
    (cloth, token and any control field); the items' own ``rid`` is not sent."""

    client: str
    items: list[ControlRequest] = field(default_factory=list)
    rid: int = 0

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControlBatchRequest) and control_batch_to_map(self) == control_batch_to_map(other)


@dataclass(eq=False)
class DecodedControlBatch:
    """A batch control as a server reads it: the envelope was valid; each item is either its
    validated ControlRequest or the ProtocolError that rejects that item alone."""

    client: str
    items: list[ControlRequest | ProtocolError]
    rid: int = 0


@dataclass
class BatchItemResult:
    """The outcome of one batch item: ``tick`` when applied, else an error ``code`` and ``message``."""

    tick: int | None = None
    code: str = ""
    message: str = ""

    @property
    def ok(self) -> bool:
        return not self.code

    def exception(self, rid: int = 0) -> DrapeError | None:
        return None if self.ok else error_for(self.code, self.message, rid)


@dataclass
class ControlBatchReply:
    """``tick``: the first tick whose states reflect the applied items; one result per item, in order."""

    tick: int
    results: list[BatchItemResult] = field(default_factory=list)
    rid: int = 0

    @property
    def failed(self) -> int:
        return sum(1 for r in self.results if not r.ok)


# ---------------------------------------------------------------------------------------------
# msgpack framing


def pack(obj: Mapping[str, Any]) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack_message(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """Parse one msgpack map, enforce the size cap and the major version.

    Raises ProtocolError: too_large, malformed, missing_field/invalid_type (v), unsupported_version.
    """
    if not isinstance(data, (bytes, bytearray)):
        raise ProtocolError(ERR_MALFORMED, f"payload must be bytes, got {type(data).__name__}")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError(ERR_TOO_LARGE, f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}")
    if not data:
        raise ProtocolError(ERR_MALFORMED, "empty payload: expected a msgpack map")
    try:
        obj = msgpack.unpackb(
            bytes(data), raw=False, strict_map_key=True, use_list=True
        )
    except Exception as e:  # truncated, trailing bytes, bad utf-8, too deep, ...
        raise ProtocolError(ERR_MALFORMED, f"payload is not valid msgpack ({type(e).__name__}: {e})") from None
    if not isinstance(obj, dict):
        raise ProtocolError(ERR_MALFORMED, f"payload must be a msgpack map, got {type(obj).__name__}")
    rid = _peek_rid(obj)
    if "v" not in obj:
        raise ProtocolError(ERR_MISSING_FIELD, f"field 'v' (protocol version [major, minor]) is required; "
                            f"this side speaks {VERSION_STRING}", rid)
    v = obj["v"]
    if not (isinstance(v, list) and len(v) == 2 and all(_is_int(x) and 0 <= x <= 255 for x in v)):
        raise ProtocolError(ERR_INVALID_TYPE, f"'v' must be [major, minor] (two integers 0..255), got {v!r:.60}", rid)
    if v[0] != PROTOCOL_MAJOR:
        raise ProtocolError(
            ERR_UNSUPPORTED_VERSION,
            f"protocol version {v[0]}.{v[1]} is not supported; this side speaks {VERSION_STRING} (major {PROTOCOL_MAJOR})",
            rid,
        )
    return obj


def _peek_rid(obj: dict[str, Any]) -> int:
    rid = obj.get("rid", 0)
    return rid if _is_int(rid) and 0 <= rid < 1 << 64 else 0


def _header(rid: int) -> dict[str, Any]:
    return {"v": [PROTOCOL_MAJOR, PROTOCOL_MINOR], "rid": int(rid)}


# ---------------------------------------------------------------------------------------------
# Field validation


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


class _Reader:
    """Typed, bounded access to one map; every failure is a ProtocolError naming the field."""

    def __init__(self, m: Mapping[str, Any], path: str, rid: int, limits: Limits) -> None:
        self.m, self.path, self.rid, self.limits = m, path, rid, limits

    def name(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def fail(self, code: str, msg: str) -> ProtocolError:
        return ProtocolError(code, msg, self.rid)

    def has(self, key: str) -> bool:
        return key in self.m and self.m[key] is not None

    def raw(self, key: str, required: bool) -> Any:
        if not self.has(key):
            if required:
                raise self.fail(ERR_MISSING_FIELD, f"field '{self.name(key)}' is required")
            return None
        return self.m[key]

    def sub(self, key: str, required: bool = False) -> "_Reader | None":
        v = self.raw(key, required)
        if v is None:
            return None
        if not isinstance(v, dict):
            raise self.fail(ERR_INVALID_TYPE, f"'{self.name(key)}' must be a map, got {_tname(v)}")
        return _Reader(v, self.name(key), self.rid, self.limits)

    def int_(self, key: str, lo: int, hi: int, required: bool = False, over: str = ERR_INVALID_VALUE) -> int | None:
        v = self.raw(key, required)
        if v is None:
            return None
        if not _is_int(v):
            raise self.fail(ERR_INVALID_TYPE, f"'{self.name(key)}' must be an integer, got {_tname(v)}")
        if not lo <= v <= hi:
            raise self.fail(over if v > hi else ERR_INVALID_VALUE, f"'{self.name(key)}' must be in {lo}..{hi}, got {v}")
        return int(v)

    def bool_(self, key: str, required: bool = False) -> bool | None:
        v = self.raw(key, required)
        if v is None:
            return None
        if not isinstance(v, bool):
            raise self.fail(ERR_INVALID_TYPE, f"'{self.name(key)}' must be a boolean, got {_tname(v)}")
        return v

    def str_(self, key: str, required: bool = False, choices: Sequence[str] | None = None,
             pattern: re.Pattern[str] | None = None, what: str = "") -> str | None:
        v = self.raw(key, required)
        if v is None:
            return None
        if not isinstance(v, str):
            raise self.fail(ERR_INVALID_TYPE, f"'{self.name(key)}' must be a string, got {_tname(v)}")
        if choices is not None and v not in choices:
            raise self.fail(ERR_INVALID_VALUE, f"'{self.name(key)}' must be one of {list(choices)}, got {v[:40]!r}")
        if pattern is not None and not pattern.match(v):
            raise self.fail(ERR_INVALID_VALUE, f"'{self.name(key)}' must be {what or pattern.pattern}, got {v[:70]!r}")
        return v

    def num(self, key: str, lo: float | None = None, hi: float | None = None, required: bool = False,
            lo_inclusive: bool = True) -> float | None:
        v = self.raw(key, required)
        if v is None:
            return None
        return _check_num(self, self.name(key), v, lo, hi, lo_inclusive)

    def vec3(self, key: str, bound: float, required: bool = False) -> Vec3 | None:
        v = self.raw(key, required)
        if v is None:
            return None
        return _check_vec3(self, self.name(key), v, bound)

    def blob(self, key: str, dtype: str, width: int, max_count: int, required: bool = False) -> np.ndarray | None:
        """A bin field of little-endian ``dtype`` values, ``width`` per item: (count, width) array."""
        v = self.raw(key, required)
        if v is None:
            return None
        if not isinstance(v, (bytes, bytearray)):
            raise self.fail(ERR_INVALID_TYPE, f"'{self.name(key)}' must be binary (msgpack bin) of "
                            f"little-endian {dtype}, got {_tname(v)}")
        dt = np.dtype(dtype).newbyteorder("<")
        item = dt.itemsize * width
        if len(v) % item:
            raise self.fail(ERR_INVALID_VALUE, f"'{self.name(key)}' has {len(v)} bytes, not a multiple of {item} "
                            f"({width} x {dtype})")
        count = len(v) // item
        if count > max_count:
            raise self.fail(ERR_TOO_LARGE, f"'{self.name(key)}' has {count} items, more than the limit of {max_count}")
        arr = np.frombuffer(bytes(v), dt)
        return arr.reshape(count, width) if width > 1 else arr


def _tname(v: object) -> str:
    if isinstance(v, (bytes, bytearray)):
        return "binary"
    if isinstance(v, dict):
        return "map"
    if isinstance(v, list):
        return "array"
    if v is None:
        return "nil"
    return type(v).__name__


def _check_num(r: _Reader, name: str, v: object, lo: float | None, hi: float | None, lo_inclusive: bool = True) -> float:
    if not _is_num(v):
        raise r.fail(ERR_INVALID_TYPE, f"'{name}' must be a number, got {_tname(v)}")
    f = float(v)  # type: ignore[arg-type]
    if not math.isfinite(f):
        raise r.fail(ERR_INVALID_VALUE, f"'{name}' must be finite, got {f}")
    if lo is not None and (f < lo or (f == lo and not lo_inclusive)):
        raise r.fail(ERR_INVALID_VALUE, f"'{name}' must be {'>=' if lo_inclusive else '>'} {lo}, got {f}")
    if hi is not None and f > hi:
        raise r.fail(ERR_INVALID_VALUE, f"'{name}' must be <= {hi}, got {f}")
    return f


def _check_vec3(r: _Reader, name: str, v: object, bound: float) -> Vec3:
    if not (isinstance(v, list) and len(v) == 3):
        raise r.fail(ERR_INVALID_TYPE, f"'{name}' must be an array of 3 numbers, got {_tname(v)}"
                     + (f" of length {len(v)}" if isinstance(v, list) else ""))
    out = tuple(_check_num(r, f"{name}[{i}]", x, -bound, bound) for i, x in enumerate(v))
    return out  # type: ignore[return-value]


def _check_finite_array(r: _Reader, name: str, arr: np.ndarray, bound: float) -> None:
    if arr.size == 0:
        return
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr.reshape(-1)))[0])
        raise r.fail(ERR_INVALID_VALUE, f"'{name}' must be finite (value {bad} is {arr.reshape(-1)[bad]})")
    m = float(np.abs(arr).max())
    if m > bound:
        raise r.fail(ERR_INVALID_VALUE, f"'{name}' values must be within +-{bound:g}, got {m:g}")


def _read_material(r: _Reader, key: str = "material") -> dict[str, Any]:
    sub = r.sub(key)
    if sub is None:
        return {}
    out: dict[str, Any] = {}
    cap = r.limits.max_material_value
    for name, (width, lo, lo_inc, hi) in MATERIAL_FIELDS.items():
        if not sub.has(name):
            continue
        hi_eff = cap if hi is None else hi
        if width == 1:
            out[name] = sub.num(name, lo, hi_eff, lo_inclusive=lo_inc)
        else:
            v = sub.raw(name, True)
            if not (isinstance(v, list) and len(v) == width):
                raise r.fail(ERR_INVALID_TYPE, f"'{sub.name(name)}' must be an array of {width} numbers "
                             "(structural, shear, bending)")
            out[name] = tuple(_check_num(r, f"{sub.name(name)}[{i}]", x, lo, hi_eff, lo_inc) for i, x in enumerate(v))
    return out


def _read_features(r: _Reader, key: str = "features") -> tuple[str, ...] | None:
    v = r.raw(key, False)
    if v is None:
        return None
    if not isinstance(v, list):
        raise r.fail(ERR_INVALID_TYPE, f"'{r.name(key)}' must be an array of strings, got {_tname(v)}")
    if len(v) > r.limits.max_features:
        raise r.fail(ERR_TOO_LARGE, f"'{r.name(key)}' has {len(v)} entries, more than {r.limits.max_features}")
    out: list[str] = []
    for i, x in enumerate(v):
        if not isinstance(x, str):
            raise r.fail(ERR_INVALID_TYPE, f"'{r.name(key)}[{i}]' must be a string, got {_tname(x)}")
        if x not in FEATURE_NAMES:
            raise r.fail(ERR_INVALID_VALUE, f"unknown feature {x[:40]!r} in '{r.name(key)}'; known: {list(FEATURE_NAMES)}")
        if x not in out:
            out.append(x)
    return tuple(out)


def _read_colliders(r: _Reader, key: str = "colliders") -> tuple[Collider, ...] | None:
    v = r.raw(key, False)
    if v is None:
        return None
    if not isinstance(v, list):
        raise r.fail(ERR_INVALID_TYPE, f"'{r.name(key)}' must be an array of collider maps, got {_tname(v)}")
    if len(v) > r.limits.max_colliders:
        raise r.fail(ERR_TOO_LARGE, f"'{r.name(key)}' has {len(v)} colliders, more than the limit of {r.limits.max_colliders}")
    out: list[Collider] = []
    bound = r.limits.max_coordinate
    for i, c in enumerate(v):
        name = f"{r.name(key)}[{i}]"
        if not isinstance(c, dict):
            raise r.fail(ERR_INVALID_TYPE, f"'{name}' must be a map, got {_tname(c)}")
        cr = _Reader(c, name, r.rid, r.limits)
        kind = cr.str_("type", True, ("sphere", "capsule", "plane"))
        if kind == "sphere":
            out.append(Sphere(cr.vec3("center", bound, True), cr.num("radius", 0.0, bound, True)))  # type: ignore[arg-type]
        elif kind == "capsule":
            out.append(Capsule(cr.vec3("p0", bound, True), cr.vec3("p1", bound, True),  # type: ignore[arg-type]
                               cr.num("radius", 0.0, bound, True)))  # type: ignore[arg-type]
        else:
            n = cr.vec3("normal", bound, True)
            assert n is not None
            if not any(n):
                raise r.fail(ERR_INVALID_VALUE, f"'{name}.normal' must be non-zero")
            out.append(Plane(n, cr.num("offset", -bound, bound, True)))  # type: ignore[arg-type]
    return tuple(out)


def _read_state_options(r: _Reader, key: str = "state", submit: bool = True) -> StateOptions | None:
    sub = r.sub(key)
    if sub is None:
        return None
    bundle = sub.bool_("bundle")
    if bundle is not None and not submit:
        raise r.fail(ERR_INVALID_VALUE, f"'{sub.name('bundle')}' can only be chosen at submission, not changed by a control")
    return StateOptions(sub.bool_("normals"), sub.str_("encoding", choices=ENCODINGS), bundle)


def _read_rho(r: _Reader) -> float | None:
    rho = r.num("chebyshev_rho", 0.0, 1.0)
    if rho is not None and rho >= 1.0:
        raise r.fail(ERR_INVALID_VALUE, f"'{r.name('chebyshev_rho')}' must be in [0, 1), got {rho}")
    return rho


def _rid(r: _Reader) -> int:
    v = r.int_("rid", 0, (1 << 64) - 1)
    return 0 if v is None else v


# --- encoding helpers ------------------------------------------------------------------------


def _f(x: float) -> float:
    return float(x)


def _v3(v: Iterable[float]) -> list[float]:
    out = [float(x) for x in v]
    if len(out) != 3:
        raise ValueError(f"expected 3 numbers, got {len(out)}")
    return out


def _blob(arr: np.ndarray | Sequence, dtype: str) -> bytes:
    return np.ascontiguousarray(np.asarray(arr), np.dtype(dtype).newbyteorder("<")).tobytes()


def collider_to_map(c: Any) -> dict[str, Any]:
    """A collider (this module's or drape.server.sim.params', or a dict) as its wire map."""
    if isinstance(c, Mapping):
        return dict(c)
    if hasattr(c, "center"):
        return {"type": "sphere", "center": _v3(c.center), "radius": _f(c.radius)}
    if hasattr(c, "p0"):
        return {"type": "capsule", "p0": _v3(c.p0), "p1": _v3(c.p1), "radius": _f(c.radius)}
    if hasattr(c, "normal"):
        return {"type": "plane", "normal": _v3(c.normal), "offset": _f(c.offset)}
    raise TypeError(f"not a collider: {c!r}")


def material_to_map(material: Any) -> dict[str, Any]:
    """Material fields as a wire map: from a dict (only the keys given) or a dataclass such as
    drape.server.sim.params.Material (all of its fields)."""
    if material is None:
        return {}
    items = material.items() if isinstance(material, Mapping) else ((f.name, getattr(material, f.name)) for f in fields(material))
    out: dict[str, Any] = {}
    for k, v in items:
        if k not in MATERIAL_FIELDS:
            raise ValueError(f"unknown material field {k!r}; known: {list(MATERIAL_FIELDS)}")
        out[k] = _v3(v) if MATERIAL_FIELDS[k][0] == 3 else _f(v)
    return out


def _state_map(s: StateOptions) -> dict[str, Any]:
    m: dict[str, Any] = {}
    if s.normals is not None:
        m["normals"] = bool(s.normals)
    if s.encoding is not None:
        m["encoding"] = s.encoding
    if s.bundle is not None:
        m["bundle"] = bool(s.bundle)
    return m


# ---------------------------------------------------------------------------------------------
# Submit


def submit_to_map(req: SubmitRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["client"] = req.client
    if req.grid is not None:
        g = req.grid
        m["grid"] = {"cols": int(g.cols), "rows": int(g.rows), "width": _f(g.width), "height": _f(g.height),
                     "orientation": g.orientation, "origin": _v3(g.origin)}
    if req.mesh is not None:
        m["mesh"] = {"vertices": _blob(req.mesh.vertices, "f4"), "triangles": _blob(req.mesh.triangles, "u4")}
    if len(req.pinned):
        m["pinned"] = _blob(req.pinned, "u4")
    if req.links is not None:
        m["links"] = {"structural": bool(req.links.structural), "shear": bool(req.links.shear),
                      "bending": bool(req.links.bending)}
    if req.material:
        m["material"] = material_to_map(req.material)
    if req.features:
        m["features"] = list(req.features)
    if req.gravity is not None:
        m["gravity"] = _v3(req.gravity)
    if req.wind is not None:
        m["wind"] = _v3(req.wind)
    if req.iterations is not None:
        m["iterations"] = int(req.iterations)
    if req.substeps is not None:
        m["substeps"] = int(req.substeps)
    if req.chebyshev_rho is not None:
        m["chebyshev_rho"] = _f(req.chebyshev_rho)
    if req.colliders is not None:
        m["colliders"] = [collider_to_map(c) for c in req.colliders]
    if req.state is not None:
        m["state"] = _state_map(req.state)
    if req.quality is not None:
        m["quality"] = str(req.quality)
    return m


def encode_submit(req: SubmitRequest) -> bytes:
    return pack(submit_to_map(req))


def decode_submit(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> SubmitRequest:
    return submit_from_map(unpack_message(data, limits), limits)


def submit_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> SubmitRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    client = r.str_("client", True, pattern=ID_RE, what="1-64 characters of [A-Za-z0-9_.-]")
    bound = limits.max_coordinate
    gr, mr = r.sub("grid"), r.sub("mesh")
    if (gr is None) == (mr is None):
        if gr is None:
            raise r.fail(ERR_MISSING_FIELD, "one of 'grid' or 'mesh' is required")
        raise r.fail(ERR_INVALID_VALUE, "give exactly one of 'grid' or 'mesh', not both")
    grid = mesh = None
    if gr is not None:
        cols = gr.int_("cols", 1, limits.max_vertices, True, over=ERR_TOO_LARGE)
        rows = gr.int_("rows", 1, limits.max_vertices, True, over=ERR_TOO_LARGE)
        assert cols is not None and rows is not None
        if cols * rows > limits.max_vertices:
            raise r.fail(ERR_TOO_LARGE, f"grid of {cols}x{rows} = {cols * rows} vertices exceeds the limit of "
                         f"{limits.max_vertices} vertices per cloth")
        width = gr.num("width", 0.0, bound, lo_inclusive=False)
        height = gr.num("height", 0.0, bound, lo_inclusive=False)
        grid = GridSpec(
            cols, rows,
            1.0 if width is None else width,
            1.0 if height is None else height,
            gr.str_("orientation", choices=ORIENTATIONS) or "horizontal",
            gr.vec3("origin", bound) or (0.0, 0.0, 0.0),
        )
        n = cols * rows
    else:
        assert mr is not None
        verts = mr.blob("vertices", "f4", 3, limits.max_vertices, True)
        tris = mr.blob("triangles", "u4", 3, limits.max_triangles, True)
        assert verts is not None and tris is not None
        n = len(verts)
        if n == 0:
            raise r.fail(ERR_INVALID_VALUE, "'mesh.vertices' must hold at least one vertex")
        _check_finite_array(r, "mesh.vertices", verts, bound)
        if tris.size:
            mx = int(tris.max())
            if mx >= n:
                raise r.fail(ERR_INDEX_OUT_OF_RANGE, f"'mesh.triangles' refers to vertex {mx} but the mesh has {n} vertices")
            if np.any((tris[:, 0] == tris[:, 1]) | (tris[:, 1] == tris[:, 2]) | (tris[:, 0] == tris[:, 2])):
                raise r.fail(ERR_INVALID_VALUE, "'mesh.triangles' has a triangle with a repeated vertex")
        mesh = MeshSpec(verts, tris)
    pinned = r.blob("pinned", "u4", 1, limits.max_vertices)
    if pinned is None:
        pinned = _empty_u32()
    if pinned.size and int(pinned.max()) >= n:
        raise r.fail(ERR_INDEX_OUT_OF_RANGE, f"'pinned' refers to vertex {int(pinned.max())} but the cloth has {n} vertices")
    lr = r.sub("links")
    links = None
    if lr is not None:
        d = LinkSpec()
        s, sh, b = lr.bool_("structural"), lr.bool_("shear"), lr.bool_("bending")
        links = LinkSpec(d.structural if s is None else s, d.shear if sh is None else sh, d.bending if b is None else b)
    acc = limits.max_acceleration
    return SubmitRequest(
        client=client,  # type: ignore[arg-type]
        grid=grid,
        mesh=mesh,
        pinned=pinned,
        links=links,
        material=_read_material(r),
        features=_read_features(r) or (),
        gravity=r.vec3("gravity", acc),
        wind=r.vec3("wind", acc),
        iterations=r.int_("iterations", 0, limits.max_iterations),
        substeps=r.int_("substeps", 1, limits.max_substeps),
        chebyshev_rho=_read_rho(r),
        colliders=_read_colliders(r),
        state=_read_state_options(r),
        quality=r.str_("quality", choices=QUALITY_PRESETS),
        rid=rid,
    )


# ---------------------------------------------------------------------------------------------
# Control, remove, info


def control_to_map(req: ControlRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m.update(control_item_to_map(req))
    return m


def control_item_to_map(req: ControlRequest) -> dict[str, Any]:
    """A control's fields without ``v`` and ``rid``: one item of a batch control."""
    m: dict[str, Any] = {}
    m["cloth"] = req.cloth
    m["token"] = req.token
    if req.pins is not None:
        m["pins"] = {"indices": _blob(req.pins.indices, "u4"), "targets": _blob(req.pins.targets, "f4")}
    if req.colliders is not None:
        m["colliders"] = [collider_to_map(c) for c in req.colliders]
    if req.gravity is not None:
        m["gravity"] = _v3(req.gravity)
    if req.wind is not None:
        m["wind"] = _v3(req.wind)
    if req.material:
        m["material"] = material_to_map(req.material)
    if req.features is not None:
        m["features"] = list(req.features)
    if req.iterations is not None:
        m["iterations"] = int(req.iterations)
    if req.substeps is not None:
        m["substeps"] = int(req.substeps)
    if req.chebyshev_rho is not None:
        m["chebyshev_rho"] = _f(req.chebyshev_rho)
    if req.state is not None:
        m["state"] = _state_map(req.state)
    if req.quality is not None:
        m["quality"] = str(req.quality)
    if req.reset:
        m["reset"] = True
    return m


def encode_control(req: ControlRequest) -> bytes:
    return pack(control_to_map(req))


def decode_control(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS, n_vertices: int | None = None) -> ControlRequest:
    """Validate a control message; with ``n_vertices`` pin indices are range-checked too."""
    return control_from_map(unpack_message(data, limits), limits, n_vertices)


def _owner_fields(r: _Reader) -> tuple[str, str]:
    cloth = r.str_("cloth", True, pattern=ID_RE, what="a cloth id (1-64 characters of [A-Za-z0-9_.-])")
    token = r.str_("token", True, pattern=TOKEN_RE, what="32 lowercase hex digits")
    return cloth, token  # type: ignore[return-value]


def control_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS, n_vertices: int | None = None) -> ControlRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    return _read_control(r, _rid(r), n_vertices)


def _read_control(r: _Reader, rid: int, n_vertices: int | None = None) -> ControlRequest:
    """The fields of a control (a whole message, or one batch item whose reader path names it).
    Only the fields present are read (a per-tick control carries two or three of them)."""
    limits = r.limits
    m = r.m
    cloth, token = _owner_fields(r)
    pins = None
    pr = r.sub("pins") if "pins" in m else None
    if pr is not None:
        idx = pr.blob("indices", "u4", 1, limits.max_pin_updates, True)
        tgt = pr.blob("targets", "f4", 3, limits.max_pin_updates, True)
        assert idx is not None and tgt is not None
        if len(idx) != len(tgt):
            raise r.fail(ERR_INVALID_VALUE, f"'{r.name('pins')}' has {len(idx)} indices but {len(tgt)} targets")
        if n_vertices is not None and idx.size and int(idx.max()) >= n_vertices:
            raise r.fail(ERR_INDEX_OUT_OF_RANGE, f"'{pr.name('indices')}' refers to vertex {int(idx.max())} but the "
                         f"cloth has {n_vertices} vertices")
        _check_finite_array(r, pr.name("targets"), tgt, limits.max_coordinate)
        pins = PinUpdate(idx, tgt)
    acc = limits.max_acceleration
    reset = r.bool_("reset") if "reset" in m else None
    return ControlRequest(
        cloth=cloth,
        token=token,
        pins=pins,
        colliders=_read_colliders(r) if "colliders" in m else None,
        gravity=r.vec3("gravity", acc) if "gravity" in m else None,
        wind=r.vec3("wind", acc) if "wind" in m else None,
        material=_read_material(r) if "material" in m else {},
        features=_read_features(r) if "features" in m else None,
        iterations=r.int_("iterations", 0, limits.max_iterations) if "iterations" in m else None,
        substeps=r.int_("substeps", 1, limits.max_substeps) if "substeps" in m else None,
        chebyshev_rho=_read_rho(r) if "chebyshev_rho" in m else None,
        state=_read_state_options(r, submit=False) if "state" in m else None,
        reset=bool(reset),
        quality=r.str_("quality", choices=QUALITY_PRESETS) if "quality" in m else None,
        rid=rid,
    )


def remove_to_map(req: RemoveRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["cloth"] = req.cloth
    m["token"] = req.token
    return m


def encode_remove(req: RemoveRequest) -> bytes:
    return pack(remove_to_map(req))


def decode_remove(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> RemoveRequest:
    return remove_from_map(unpack_message(data, limits), limits)


def remove_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> RemoveRequest:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    cloth, token = _owner_fields(r)
    return RemoveRequest(cloth, token, rid)


def encode_info(req: InfoRequest) -> bytes:
    return pack(_header(req.rid))


def decode_info(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> InfoRequest:
    """An info query may carry no payload at all (then rid is 0)."""
    if not data:
        return InfoRequest()
    m = unpack_message(data, limits)
    return InfoRequest(_rid(_Reader(m, "", _peek_rid(m), limits)))


# ---------------------------------------------------------------------------------------------
# Batch control (1.1)


def control_batch_to_map(req: ControlBatchRequest) -> dict[str, Any]:
    m = _header(req.rid)
    m["client"] = req.client
    m["items"] = [control_item_to_map(it) for it in req.items]
    return m


def encode_control_batch(req: ControlBatchRequest) -> bytes:
    return pack(control_batch_to_map(req))


def decode_control_batch(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> DecodedControlBatch:
    """Validate a batch control. The envelope (size, msgpack, version, ``client``, ``items``
    being an array of 1..max_batch_items) raises ProtocolError for the whole request; every item
    is then validated on its own: an invalid item becomes its ProtocolError in ``items`` and
    does not affect the others."""
    return control_batch_from_map(unpack_message(data, limits), limits)


def control_batch_from_map(m: Mapping[str, Any], limits: Limits = DEFAULT_LIMITS) -> DecodedControlBatch:
    r = _Reader(m, "", _peek_rid(dict(m)), limits)
    rid = _rid(r)
    client = r.str_("client", True, pattern=ID_RE, what="1-64 characters of [A-Za-z0-9_.-]")
    raw_items = r.raw("items", True)
    if not isinstance(raw_items, list):
        raise r.fail(ERR_INVALID_TYPE, f"'items' must be an array of control maps, got {_tname(raw_items)}")
    if not raw_items:
        raise r.fail(ERR_INVALID_VALUE, "'items' must hold at least one control")
    if len(raw_items) > limits.max_batch_items:
        raise r.fail(ERR_TOO_LARGE, f"'items' has {len(raw_items)} controls, more than the limit of "
                     f"{limits.max_batch_items}")
    items: list[ControlRequest | ProtocolError] = []
    for i, it in enumerate(raw_items):
        name = f"items[{i}]"
        if not isinstance(it, dict):
            items.append(ProtocolError(ERR_INVALID_TYPE, f"'{name}' must be a map, got {_tname(it)}", rid))
            continue
        try:
            items.append(_read_control(_Reader(it, name, rid, limits), rid))
        except ProtocolError as e:
            items.append(e)
    return DecodedControlBatch(client, items, rid)  # type: ignore[arg-type]


def encode_control_batch_reply(rep: ControlBatchReply) -> bytes:
    m = _header(rep.rid)
    results: list[dict[str, Any]] = []
    for res in rep.results:
        if res.ok:
            results.append({"ok": True, "tick": int(rep.tick if res.tick is None else res.tick)})
        else:
            if res.code not in ERROR_CODES:
                raise ValueError(f"unknown error code {res.code!r}")
            results.append({"ok": False, "error": {"code": res.code, "message": str(res.message)}})
    m.update(ok=True, tick=int(rep.tick), failed=sum(1 for x in rep.results if not x.ok), results=results)
    return pack(m)


def control_batch_reply_from_map(m: Mapping[str, Any]) -> ControlBatchReply:
    """A batch reply's map (as decode_reply returns it) as a ControlBatchReply."""
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    tick = r.int_("tick", 0, (1 << 64) - 1, True)
    raw_results = r.raw("results", True)
    if not isinstance(raw_results, list):
        raise r.fail(ERR_INVALID_TYPE, f"'results' must be an array, got {_tname(raw_results)}")
    results: list[BatchItemResult] = []
    for i, x in enumerate(raw_results):
        if not isinstance(x, dict):
            raise r.fail(ERR_INVALID_TYPE, f"'results[{i}]' must be a map, got {_tname(x)}")
        xr = _Reader(x, f"results[{i}]", r.rid, DEFAULT_LIMITS)
        if xr.bool_("ok", True):
            results.append(BatchItemResult(tick=xr.int_("tick", 0, (1 << 64) - 1, True)))
        else:
            er = xr.sub("error", True)
            assert er is not None
            results.append(BatchItemResult(None, er.str_("code", True) or "", er.str_("message") or ""))
    return ControlBatchReply(tick, results, _rid(r))  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# Replies


def encode_submit_reply(rep: SubmitReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, cloth=rep.cloth, token=rep.token, key=rep.key, vertices=int(rep.vertices), tick=int(rep.tick))
    if rep.bundle_key is not None:
        m["bundle_key"] = rep.bundle_key
    return pack(m)


def encode_control_reply(rep: ControlReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, tick=int(rep.tick))
    return pack(m)


def encode_remove_reply(rep: RemoveReply) -> bytes:
    m = _header(rep.rid)
    m.update(ok=True, tick=int(rep.tick))
    return pack(m)


def encode_ok(rid: int = 0, **body: Any) -> bytes:
    """A success reply with arbitrary body fields (info)."""
    m = _header(rid)
    m["ok"] = True
    m.update(body)
    return pack(m)


def encode_error(code: str, message: str, rid: int = 0) -> bytes:
    if code not in ERROR_CODES:
        raise ValueError(f"unknown error code {code!r}")
    m = _header(rid)
    m.update(ok=False, error={"code": code, "message": str(message)})
    return pack(m)


def decode_reply(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """A reply's map if ``ok`` is true; raises the matching DrapeError when it is an error reply,
    ProtocolError when the reply itself is malformed."""
    m = unpack_message(data, limits)
    ok = m.get("ok")
    if ok is True:
        return m
    if ok is False:
        err = decode_error_map(m)
        raise err.exception()
    raise ProtocolError(ERR_MALFORMED, f"reply must have boolean 'ok', got {_tname(ok)}", _peek_rid(m))


def decode_error_map(m: Mapping[str, Any]) -> ErrorReply:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    er = r.sub("error", True)
    assert er is not None
    code = er.str_("code", True)
    msg = er.str_("message") or ""
    return ErrorReply(code, msg, _rid(r))  # type: ignore[arg-type]


def decode_error(data: bytes | bytearray) -> ErrorReply:
    return decode_error_map(unpack_message(data))


def submit_reply_from_map(m: Mapping[str, Any]) -> SubmitReply:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    return SubmitReply(
        cloth=r.str_("cloth", True, pattern=ID_RE),  # type: ignore[arg-type]
        token=r.str_("token", True, pattern=TOKEN_RE),  # type: ignore[arg-type]
        key=r.str_("key", True),  # type: ignore[arg-type]
        vertices=r.int_("vertices", 1, 1 << 32, True),  # type: ignore[arg-type]
        tick=r.int_("tick", 0, (1 << 64) - 1, True),  # type: ignore[arg-type]
        rid=_rid(r),
        bundle_key=r.str_("bundle_key"),
    )


def tick_reply_from_map(m: Mapping[str, Any]) -> int:
    r = _Reader(m, "", _peek_rid(dict(m)), DEFAULT_LIMITS)
    return r.int_("tick", 0, (1 << 64) - 1, True)  # type: ignore[return-value]


def encode_stats(stats: Mapping[str, Any]) -> bytes:
    m = _header(0)
    m.update(stats)
    return pack(m)


def decode_stats(data: bytes | bytearray) -> dict[str, Any]:
    return unpack_message(data)


# ---------------------------------------------------------------------------------------------
# Binary cloth state

STATE_MAGIC = b"DRPS"
STATE_HEADER = struct.Struct("<4sBBHBBHIQQ3f3f8x")
STATE_HEADER_SIZE = STATE_HEADER.size  # 64
assert STATE_HEADER_SIZE == 64

FLAG_NORMALS = 1 << 0  # normals follow the positions
FLAG_RESET = 1 << 1  # this state is a reset (rest pose after a non-finite step, or a reset control)
KNOWN_FLAGS = FLAG_NORMALS | FLAG_RESET

FLOAT16_MAX = 65504.0
QUANT_MAX = 65535
SNORM_MAX = 32767


@dataclass(eq=False)
class ClothState:
    """One cloth's state at one tick. ``positions`` (n, 3) float32 and ``normals`` (n, 3) float32
    or None; arrays decoded from float32 payloads are read-only views of the payload."""

    tick: int
    server_time_ns: int
    positions: np.ndarray
    normals: np.ndarray | None = None
    receive_time_ns: int = 0
    encoding: str = "float32"
    flags: int = 0
    bounds: tuple[Vec3, Vec3] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    cloth: str = ""

    @property
    def n_vertices(self) -> int:
        return len(self.positions)

    @property
    def reset(self) -> bool:
        return bool(self.flags & FLAG_RESET)

    @property
    def latency_ns(self) -> int:
        """Receive time minus server time (meaningful when both clocks are one host's)."""
        return self.receive_time_ns - self.server_time_ns


def _elem_size(encoding: int) -> int:
    return 4 if encoding == ENC_FLOAT32 else 2


def state_size(n_vertices: int, encoding: str = "float32", normals: bool = False) -> int:
    """Bytes of an encoded state."""
    e = _elem_size(ENCODING_IDS[encoding])
    return STATE_HEADER_SIZE + n_vertices * 3 * e * (2 if normals else 1)


def encode_state(
    tick: int,
    server_time_ns: int,
    positions: np.ndarray,
    normals: np.ndarray | None = None,
    encoding: str = "float32",
    flags: int = 0,
) -> bytearray:
    """The binary state payload. ``positions`` (n, 3) finite; normals (n, 3) when given.

    float32: values as is. float16: IEEE half (round to nearest even, clamped to +-65504).
    quant16: per axis q = rint((x - min) * 65535 / (max - min)) as uint16 against the float32
    bounds in the header (q = 0 where max == min); normals as snorm16 rint(n * 32767)."""
    enc = ENCODING_IDS.get(encoding)
    if enc is None:
        raise ValueError(f"unknown encoding {encoding!r}; choose from {ENCODINGS}")
    pos = np.asarray(positions, np.float32).reshape(-1, 3)
    n = len(pos)
    if normals is not None:
        flags |= FLAG_NORMALS
        nrm = np.asarray(normals, np.float32).reshape(n, 3)
    else:
        flags &= ~FLAG_NORMALS
    if n:
        lo = pos.min(axis=0)
        hi = pos.max(axis=0)
    else:
        lo = hi = np.zeros(3, np.float32)
    es = _elem_size(enc)
    block = n * 3 * es
    out = bytearray(STATE_HEADER_SIZE + block * (2 if normals is not None else 1))
    STATE_HEADER.pack_into(out, 0, STATE_MAGIC, PROTOCOL_MAJOR, PROTOCOL_MINOR, STATE_HEADER_SIZE, enc, 0, flags,
                           n, tick, server_time_ns, *lo.tolist(), *hi.tolist())
    if enc == ENC_FLOAT32:
        np.frombuffer(out, "<f4", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = pos
        if normals is not None:
            np.frombuffer(out, "<f4", n * 3, STATE_HEADER_SIZE + block).reshape(n, 3)[:] = nrm
    elif enc == ENC_FLOAT16:
        np.frombuffer(out, "<f2", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = np.clip(pos, -FLOAT16_MAX, FLOAT16_MAX)
        if normals is not None:
            np.frombuffer(out, "<f2", n * 3, STATE_HEADER_SIZE + block).reshape(n, 3)[:] = nrm
    else:
        lo64, hi64 = lo.astype(np.float64), hi.astype(np.float64)
        ext = hi64 - lo64
        scale = np.divide(QUANT_MAX, ext, out=np.zeros(3), where=ext > 0)
        q = np.rint(np.clip((pos.astype(np.float64) - lo64) * scale, 0, QUANT_MAX))
        np.frombuffer(out, "<u2", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = q
        if normals is not None:
            qn = np.rint(np.clip(nrm.astype(np.float64), -1.0, 1.0) * SNORM_MAX)
            np.frombuffer(out, "<i2", n * 3, STATE_HEADER_SIZE + block).reshape(n, 3)[:] = qn
    return out


def decode_state(data: bytes | bytearray | memoryview, cloth: str = "", receive_time_ns: int = 0) -> ClothState:
    """Parse a state payload. Raises ProtocolError on a bad magic, an unknown major version or
    encoding, or a payload shorter than its header says. Unknown flag bits, a longer header
    (a later minor version) and trailing bytes are ignored."""
    buf = memoryview(data).cast("B") if not isinstance(data, (bytes, bytearray)) else data
    if len(buf) < STATE_HEADER_SIZE:
        raise ProtocolError(ERR_MALFORMED, f"state payload of {len(buf)} bytes is shorter than the {STATE_HEADER_SIZE}-byte header")
    (magic, major, minor, hsize, enc, _res, flags, n, tick, t_ns,
     x0, y0, z0, x1, y1, z1) = STATE_HEADER.unpack_from(buf, 0)
    if magic != STATE_MAGIC:
        raise ProtocolError(ERR_MALFORMED, f"state payload magic {bytes(magic)!r} is not {STATE_MAGIC!r}")
    if major != PROTOCOL_MAJOR:
        raise ProtocolError(ERR_UNSUPPORTED_VERSION, f"state version {major}.{minor} is not supported; this side "
                            f"speaks {VERSION_STRING}")
    if hsize < STATE_HEADER_SIZE:
        raise ProtocolError(ERR_MALFORMED, f"state header_size {hsize} is below {STATE_HEADER_SIZE}")
    if enc not in ENCODING_NAMES:
        raise ProtocolError(ERR_INVALID_VALUE, f"unknown state encoding {enc}")
    es = _elem_size(enc)
    block = n * 3 * es
    has_n = bool(flags & FLAG_NORMALS)
    need = hsize + block * (2 if has_n else 1)
    if len(buf) < need:
        raise ProtocolError(ERR_MALFORMED, f"state payload of {len(buf)} bytes is shorter than the {need} bytes its "
                            f"header announces ({n} vertices, {ENCODING_NAMES[enc]}{', normals' if has_n else ''})")
    lo = np.array((x0, y0, z0), np.float32)
    hi = np.array((x1, y1, z1), np.float32)
    nrm = None
    if enc == ENC_FLOAT32:
        pos = np.frombuffer(buf, "<f4", n * 3, hsize).reshape(n, 3)
        if has_n:
            nrm = np.frombuffer(buf, "<f4", n * 3, hsize + block).reshape(n, 3)
    elif enc == ENC_FLOAT16:
        pos = np.frombuffer(buf, "<f2", n * 3, hsize).reshape(n, 3).astype(np.float32)
        if has_n:
            nrm = np.frombuffer(buf, "<f2", n * 3, hsize + block).reshape(n, 3).astype(np.float32)
    else:
        q = np.frombuffer(buf, "<u2", n * 3, hsize).reshape(n, 3).astype(np.float64)
        lo64, hi64 = lo.astype(np.float64), hi.astype(np.float64)
        pos = (lo64 + q * ((hi64 - lo64) / QUANT_MAX)).astype(np.float32)
        if has_n:
            nrm = (np.frombuffer(buf, "<i2", n * 3, hsize + block).reshape(n, 3) / SNORM_MAX).astype(np.float32)
    bounds = (tuple(float(v) for v in lo), tuple(float(v) for v in hi))
    return ClothState(tick, t_ns, pos, nrm, receive_time_ns, ENCODING_NAMES[enc], flags, bounds, cloth)  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# State bundles (1.1): the states of one client's bundled cloths at one tick, in one payload

BUNDLE_MAGIC = b"DRPB"
#: magic, major, minor, header_size, count, flags, tick, server time
BUNDLE_HEADER = struct.Struct("<4sBBHIIQQ")
BUNDLE_HEADER_SIZE = BUNDLE_HEADER.size  # 32
assert BUNDLE_HEADER_SIZE == 32
#: per entry: entry header size (offset of the state from the entry start), id length, reserved, state size
BUNDLE_ENTRY = struct.Struct("<HBxI")
BUNDLE_ENTRY_SIZE = BUNDLE_ENTRY.size  # 8, then the cloth id, then zeros up to the entry header size
BUNDLE_ALIGN = 8  # entries and states start at multiples of 8 from the start of the bundle


def align8(n: int) -> int:
    return (n + 7) & ~7


def bundle_entry_header_size(cloth: str) -> int:
    """Bytes from an entry's start to its state payload: 8 + id length, rounded up to 8."""
    return align8(BUNDLE_ENTRY_SIZE + len(cloth))


def bundle_size(entries: Iterable[tuple[str, int]]) -> int:
    """Bytes of a bundle of (cloth id, state size) entries."""
    return BUNDLE_HEADER_SIZE + sum(bundle_entry_header_size(c) + align8(n) for c, n in entries)


def pack_bundle_header(out: bytearray | memoryview, tick: int, server_time_ns: int, count: int, flags: int = 0) -> None:
    BUNDLE_HEADER.pack_into(out, 0, BUNDLE_MAGIC, PROTOCOL_MAJOR, PROTOCOL_MINOR, BUNDLE_HEADER_SIZE, count, flags,
                            tick, server_time_ns)


def pack_bundle_entry(out: bytearray | memoryview, at: int, cloth: str, state_size: int) -> int:
    """Write an entry header (with the id and its padding) at ``at``; returns the state's offset."""
    cid = cloth.encode("ascii")
    h = align8(BUNDLE_ENTRY_SIZE + len(cid))
    BUNDLE_ENTRY.pack_into(out, at, h, len(cid), state_size)
    end = at + BUNDLE_ENTRY_SIZE + len(cid)
    out[at + BUNDLE_ENTRY_SIZE:end] = cid
    out[end:at + h] = bytes(at + h - end)
    return at + h


def encode_bundle(tick: int, server_time_ns: int, states: Sequence[tuple[str, bytes | bytearray | memoryview]],
                  flags: int = 0) -> bytearray:
    """The bundle payload of (cloth id, state payload) pairs, in order. Every state should carry
    the bundle's tick and server time (encode_state(tick, server_time_ns, ...))."""
    out = bytearray(bundle_size((c, len(st)) for c, st in states))
    pack_bundle_header(out, tick, server_time_ns, len(states), flags)
    at = BUNDLE_HEADER_SIZE
    for cloth, st in states:
        if not valid_id(cloth):
            raise ValueError(f"invalid cloth id {cloth!r}")
        off = pack_bundle_entry(out, at, cloth, len(st))
        out[off:off + len(st)] = st
        at = off + align8(len(st))  # the padding is already zero
    return out


@dataclass(frozen=True)
class BundleEntry:
    cloth: str
    offset: int  # of the state payload, from the start of the bundle
    size: int  # of the state payload


@dataclass(eq=False)
class Bundle:
    """A parsed bundle: header fields and where each cloth's state payload lies in ``data``."""

    tick: int
    server_time_ns: int
    flags: int
    entries: list[BundleEntry]
    data: bytes | bytearray | memoryview
    minor: int = PROTOCOL_MINOR

    def payload(self, i: int) -> memoryview:
        e = self.entries[i]
        return memoryview(self.data)[e.offset:e.offset + e.size]

    def state(self, i: int, receive_time_ns: int = 0) -> ClothState:
        """Entry ``i`` decoded with decode_state (float32 arrays are views of the bundle)."""
        return decode_state(self.payload(i), self.entries[i].cloth, receive_time_ns)

    def states(self, receive_time_ns: int = 0) -> list[ClothState]:
        return [self.state(i, receive_time_ns) for i in range(len(self.entries))]


def parse_bundle(data: bytes | bytearray | memoryview) -> Bundle:
    """Parse a bundle's header and entry table (the states are decoded on demand). Raises
    ProtocolError on a bad magic, an unknown major version, a header_size below 32, an entry
    that does not fit, an entry header size below 8 + id length, or an id that is not a valid
    cloth id. Unknown flag bits, a longer header and trailing bytes after the last entry are
    ignored (later minor versions may add them)."""
    buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
    size = len(buf)
    if size < BUNDLE_HEADER_SIZE:
        raise ProtocolError(ERR_MALFORMED, f"bundle of {size} bytes is shorter than the {BUNDLE_HEADER_SIZE}-byte header")
    magic, major, minor, hsize, count, flags, tick, t_ns = BUNDLE_HEADER.unpack_from(buf, 0)
    if magic != BUNDLE_MAGIC:
        raise ProtocolError(ERR_MALFORMED, f"bundle magic {bytes(magic)!r} is not {BUNDLE_MAGIC!r}")
    if major != PROTOCOL_MAJOR:
        raise ProtocolError(ERR_UNSUPPORTED_VERSION, f"bundle version {major}.{minor} is not supported; this side "
                            f"speaks {VERSION_STRING}")
    if hsize < BUNDLE_HEADER_SIZE:
        raise ProtocolError(ERR_MALFORMED, f"bundle header_size {hsize} is below {BUNDLE_HEADER_SIZE}")
    at = hsize
    entries: list[BundleEntry] = []
    for i in range(count):
        if at + BUNDLE_ENTRY_SIZE > size:
            raise ProtocolError(ERR_MALFORMED, f"bundle entry {i} of {count} starts at byte {at}, past the end ({size})")
        h, id_len, st_size = BUNDLE_ENTRY.unpack_from(buf, at)
        if h < BUNDLE_ENTRY_SIZE + id_len:
            raise ProtocolError(ERR_MALFORMED, f"bundle entry {i}: entry header size {h} is below 8 + id length {id_len}")
        if at + h + st_size > size:
            raise ProtocolError(ERR_MALFORMED, f"bundle entry {i}: state of {st_size} bytes at byte {at + h} runs past "
                                f"the end ({size})")
        try:
            cloth = bytes(buf[at + BUNDLE_ENTRY_SIZE:at + BUNDLE_ENTRY_SIZE + id_len]).decode("ascii")
        except UnicodeDecodeError:
            cloth = ""
        if not valid_id(cloth):
            raise ProtocolError(ERR_MALFORMED, f"bundle entry {i}: invalid cloth id")
        entries.append(BundleEntry(cloth, at + h, st_size))
        at = align8(at + h + st_size)
    return Bundle(tick, t_ns, flags, entries, buf, minor)


def decode_bundle(data: bytes | bytearray | memoryview, receive_time_ns: int = 0) -> list[ClothState]:
    """Every state of a bundle, decoded (each ClothState's ``cloth`` is its entry's id)."""
    return parse_bundle(data).states(receive_time_ns)


# ---------------------------------------------------------------------------------------------
# Geometry a client needs without the server package


def grid_geometry(
    cols: int,
    rows: int,
    width: float = 1.0,
    height: float = 1.0,
    orientation: str = "horizontal",
    origin: Iterable[float] = (0.0, 0.0, 0.0),
) -> tuple[np.ndarray, np.ndarray]:
    """Rest positions (rows*cols, 3) float32 and triangles (m, 3) uint32 of a grid cloth, exactly
    as the server builds them (drape.server.sim.fabric.grid_mesh).

    Vertex (r, c) = r * cols + c. x = origin.x + c * width / (cols - 1) (0 when cols == 1).
    horizontal: y = origin.y, z = origin.z + r * height / (rows - 1);
    vertical: y = origin.y - r * height / (rows - 1), z = origin.z.
    Triangles: for every cell (r, c) in row-major order, a = r*cols + c, b = a + 1, d = a + cols,
    e = d + 1: first all (a, d, b), then all (b, d, e)."""
    if cols < 1 or rows < 1:
        raise ValueError("a grid needs at least one column and one row")
    ox, oy, oz = (float(v) for v in origin)
    u = np.linspace(0.0, width, cols) if cols > 1 else np.zeros(1)
    w = np.linspace(0.0, height, rows) if rows > 1 else np.zeros(1)
    cc, rr = np.meshgrid(u, w)
    verts = np.zeros((rows * cols, 3))
    verts[:, 0] = ox + cc.ravel()
    if orientation == "horizontal":
        verts[:, 1] = oy
        verts[:, 2] = oz + rr.ravel()
    elif orientation == "vertical":
        verts[:, 1] = oy - rr.ravel()
        verts[:, 2] = oz
    else:
        raise ValueError("orientation must be 'horizontal' or 'vertical'")
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (r * cols + c).ravel()
    b, d, e = a + 1, a + cols, a + cols + 1
    tris = np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, e], 1)]).astype(np.uint32)
    return verts.astype(np.float32), tris


def parse_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float32 and triangles (m, 3) uint32 of Wavefront OBJ text: faces
    fan-triangulated, v/vt/vn and negative indices accepted, everything else ignored (the same
    rules as drape.server.sim.fabric.parse_obj)."""
    verts: list[tuple[float, float, float]] = []
    tris: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if parts[0] == "v":
            if len(parts) < 4:
                raise ValueError(f"OBJ line {lineno}: vertex needs x y z")
            verts.append((float(parts[1]), float(parts[2]), float(parts[3])))
        elif parts[0] == "f":
            idx = []
            for p in parts[1:]:
                i = int(p.split("/")[0])
                idx.append(i - 1 if i > 0 else len(verts) + i)
            if len(idx) < 3:
                raise ValueError(f"OBJ line {lineno}: face needs three vertices")
            if min(idx) < 0:
                raise ValueError(f"OBJ line {lineno}: vertex index out of range")
            for k in range(1, len(idx) - 1):
                tris.append((idx[0], idx[k], idx[k + 1]))
    return np.asarray(verts, np.float32).reshape(-1, 3), np.asarray(tris, np.uint32).reshape(-1, 3)
