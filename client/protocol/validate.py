"""msgpack framing with hostile-input caps, and the typed field readers every decoder validates
with: anything malformed becomes a ProtocolError naming the field (PROTOCOL.md sections 3, 8)."""

from __future__ import annotations

import math
import re
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import fields
from typing import Any

import msgpack
import numpy as np

from .errors import (
    ERR_INVALID_TYPE,
    ERR_INVALID_VALUE,
    ERR_MALFORMED,
    ERR_MISSING_FIELD,
    ERR_TOO_LARGE,
    ERR_UNSUPPORTED_VERSION,
    ProtocolError,
)
from .keys import PROTOCOL_MAJOR, PROTOCOL_MINOR, VERSION_STRING
from .vocabulary import (
    COLLIDER_TYPES,
    DEFAULT_LIMITS,
    ENCODINGS,
    FEATURE_NAMES,
    MATERIAL_FIELDS,
    MAX_ARRAY_LENGTH,
    MAX_ELEMENTS,
    MAX_MAP_KEYS,
    MAX_NESTING,
    MAX_STRING_BYTES,
    STEP_MAX,
    STEP_MIN,
    Collider,
    Limits,
    StateOptions,
    Vec3,
    collider_shape,
    collider_shape_named,
)


def pack(obj: Mapping[str, Any]) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack_message(data: bytes | bytearray, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """Parse one msgpack map, enforce the size cap and the major version.

    Raises ProtocolError: too_large, malformed, missing_field/invalid_type (v), unsupported_version.
    """
    if not isinstance(data, (bytes, bytearray)):
        raise ProtocolError(ERR_MALFORMED, f"payload must be bytes, got {type(data).__name__}")
    if len(data) > limits.max_message_bytes:
        raise ProtocolError(
            ERR_TOO_LARGE, f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}"
        )
    if not data:
        raise ProtocolError(ERR_MALFORMED, "empty payload: expected a msgpack map")
    try:
        obj = msgpack.unpackb(bytes(data), **_unpack_caps(limits))
    except ValueError as e:  # truncated, trailing bytes, bad utf-8, a cap exceeded, nesting beyond msgpack's own stack
        raise ProtocolError(
            ERR_MALFORMED,
            f"payload is not valid msgpack within the protocol's caps ({type(e).__name__}: {str(e)[:120]})",
        ) from None
    except Exception as e:  # anything else msgpack raises on hostile bytes (ExtraData, FormatError, ...)
        raise ProtocolError(
            ERR_MALFORMED, f"payload is not valid msgpack ({type(e).__name__}: {str(e)[:120]})"
        ) from None
    _check_shape(obj)
    if not isinstance(obj, dict):
        raise ProtocolError(ERR_MALFORMED, f"payload must be a msgpack map, got {type(obj).__name__}")
    rid = _peek_rid(obj)
    if "v" not in obj:
        raise ProtocolError(
            ERR_MISSING_FIELD,
            f"field 'v' (protocol version [major, minor]) is required; this side speaks {VERSION_STRING}",
            rid,
        )
    v = obj["v"]
    if not (isinstance(v, list) and len(v) == 2 and all(_is_int(x) and 0 <= x <= 255 for x in v)):
        raise ProtocolError(ERR_INVALID_TYPE, f"'v' must be [major, minor] (two integers 0..255), got {v!r:.60}", rid)
    if v[0] != PROTOCOL_MAJOR:
        raise ProtocolError(
            ERR_UNSUPPORTED_VERSION,
            f"protocol version {v[0]}.{v[1]} is not supported; this side speaks {VERSION_STRING} "
            f"(major {PROTOCOL_MAJOR})",
            rid,
        )
    return obj


def _unpack_caps(limits: Limits) -> dict[str, Any]:
    """msgpack's own length caps for one message of at most ``limits.max_message_bytes``: a bin
    may fill the message; strings, arrays and maps are capped far below what fits in it, so a
    map of 200 000 keys is refused by the C parser before any field is looked at."""
    return dict(
        raw=False,
        strict_map_key=True,
        use_list=True,
        max_bin_len=limits.max_message_bytes,
        max_str_len=min(limits.max_message_bytes, MAX_STRING_BYTES),
        max_array_len=min(limits.max_message_bytes, MAX_ARRAY_LENGTH),
        max_map_len=min(limits.max_message_bytes, MAX_MAP_KEYS),
        max_ext_len=0,  # the protocol has no extension types
    )


def _check_shape(obj: Any) -> None:
    """Refuse nesting deeper than MAX_NESTING and more than MAX_ELEMENTS values, without recursion
    (the walk stops at the first excess, so it costs at most MAX_ELEMENTS steps). A container
    holding no container (a 1.4 moves block's ids and tokens) is counted at once, not walked."""
    stack: list[tuple[Any, int]] = [(obj, 1)]
    seen = 0
    while stack:
        o, depth = stack.pop()
        seen += 1
        if seen > MAX_ELEMENTS:
            raise ProtocolError(ERR_TOO_LARGE, f"message holds more than {MAX_ELEMENTS} values")
        if isinstance(o, dict):
            if not all(isinstance(k, str) for k in o):  # msgpack's strict_map_key still lets bin keys through
                raise ProtocolError(ERR_MALFORMED, "map keys must be strings")
            children: Collection[Any] = o.values()
            seen += len(o)  # the keys (strings)
        elif isinstance(o, list):
            children = o
        else:
            continue
        if depth > MAX_NESTING:
            raise ProtocolError(ERR_MALFORMED, f"maps and arrays nested deeper than {MAX_NESTING} levels")
        kinds = set(map(type, children))
        if dict in kinds or list in kinds:
            stack.extend((c, depth + 1) for c in children)
        elif seen + len(children) > MAX_ELEMENTS:
            raise ProtocolError(ERR_TOO_LARGE, f"message holds more than {MAX_ELEMENTS} values")
        else:
            seen += len(children)  # scalars only: nothing below them


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

    def sub(self, key: str, required: bool = False) -> _Reader | None:
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

    def str_(
        self,
        key: str,
        required: bool = False,
        choices: Sequence[str] | None = None,
        pattern: re.Pattern[str] | None = None,
        what: str = "",
    ) -> str | None:
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

    def num(
        self,
        key: str,
        lo: float | None = None,
        hi: float | None = None,
        required: bool = False,
        lo_inclusive: bool = True,
    ) -> float | None:
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
            raise self.fail(
                ERR_INVALID_TYPE,
                f"'{self.name(key)}' must be binary (msgpack bin) of little-endian {dtype}, got {_tname(v)}",
            )
        dt = np.dtype(dtype).newbyteorder("<")
        item = dt.itemsize * width
        if len(v) % item:
            raise self.fail(
                ERR_INVALID_VALUE,
                f"'{self.name(key)}' has {len(v)} bytes, not a multiple of {item} ({width} x {dtype})",
            )
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


def _check_num(
    r: _Reader, name: str, v: object, lo: float | None, hi: float | None, lo_inclusive: bool = True
) -> float:
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
        raise r.fail(
            ERR_INVALID_TYPE,
            f"'{name}' must be an array of 3 numbers, got {_tname(v)}"
            + (f" of length {len(v)}" if isinstance(v, list) else ""),
        )
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
                raise r.fail(
                    ERR_INVALID_TYPE,
                    f"'{sub.name(name)}' must be an array of {width} numbers (structural, shear, bending)",
                )
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
            raise r.fail(
                ERR_INVALID_VALUE, f"unknown feature {x[:40]!r} in '{r.name(key)}'; known: {list(FEATURE_NAMES)}"
            )
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
        raise r.fail(
            ERR_TOO_LARGE, f"'{r.name(key)}' has {len(v)} colliders, more than the limit of {r.limits.max_colliders}"
        )
    out: list[Collider] = []
    bound = r.limits.max_coordinate
    for i, c in enumerate(v):
        name = f"{r.name(key)}[{i}]"
        if not isinstance(c, dict):
            raise r.fail(ERR_INVALID_TYPE, f"'{name}' must be a map, got {_tname(c)}")
        cr = _Reader(c, name, r.rid, r.limits)
        shape = collider_shape_named(cr.str_("type", True, COLLIDER_TYPES))  # type: ignore[arg-type]
        values: list[Any] = []
        for f in shape.fields:
            if f.vec3:
                v = cr.vec3(f.name, bound, True)
                assert v is not None
                if f.nonzero and not any(v):
                    raise r.fail(ERR_INVALID_VALUE, f"'{cr.name(f.name)}' must be non-zero")
                values.append(v)
            else:
                values.append(cr.num(f.name, -bound if f.signed else 0.0, bound, True))
        out.append(shape.cls(*values))
    return tuple(out)


def _read_state_options(r: _Reader, key: str = "state", submit: bool = True) -> StateOptions | None:
    sub = r.sub(key)
    if sub is None:
        return None
    bundle = sub.bool_("bundle")
    if bundle is not None and not submit:
        raise r.fail(
            ERR_INVALID_VALUE, f"'{sub.name('bundle')}' can only be chosen at submission, not changed by a control"
        )
    step = sub.num("step", STEP_MIN, STEP_MAX)  # 1.5, the predictive encoding's grid (metres)
    return StateOptions(sub.bool_("normals"), sub.str_("encoding", choices=ENCODINGS), bundle, step)


def _read_rho(r: _Reader, key: str = "chebyshev_rho") -> float | None:
    """A number in [0, 1) (the ``fraction`` kind of requestfields)."""
    rho = r.num(key, 0.0, 1.0)
    if rho is not None and rho >= 1.0:
        raise r.fail(ERR_INVALID_VALUE, f"'{r.name(key)}' must be in [0, 1), got {rho}")
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
    """A collider (a COLLIDER_SHAPES dataclass, or a dict) as its wire map."""
    if isinstance(c, Mapping):
        return dict(c)
    shape = collider_shape(c)
    m: dict[str, Any] = {"type": shape.name}
    for f in shape.fields:
        v = getattr(c, f.name)
        m[f.name] = _v3(v) if f.vec3 else _f(v)
    return m


def material_to_map(material: Any) -> dict[str, Any]:
    """Material fields as a wire map: from a dict (only the keys given) or a dataclass such as
    drape.server.sim.params.Material (all of its fields)."""
    if material is None:
        return {}
    items = (
        material.items()
        if isinstance(material, Mapping)
        else ((f.name, getattr(material, f.name)) for f in fields(material))
    )
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
    if s.step is not None:
        m["step"] = _f(s.step)
    return m


# ---------------------------------------------------------------------------------------------
# Messages the SDK's own checks and the server's decoder share (one wording for both)


def cloth_shape(n_vertices: int, grid: tuple[int, int] | None = None) -> str:
    """``a 32x32 grid`` (``grid``: (cols, rows)) or ``a mesh of 500 vertices``."""
    return f"a {grid[0]}x{grid[1]} grid" if grid is not None else f"a mesh of {n_vertices} vertices"


def pinned_out_of_range(index: int, n_vertices: int, grid: tuple[int, int] | None = None) -> str:
    """Why a pinned vertex index is refused: ``pinned index 1030 out of range 0..1023 for a
    32x32 grid``."""
    return f"pinned index {index} out of range 0..{n_vertices - 1} for {cloth_shape(n_vertices, grid)}"


def too_many_vertices(n_vertices: int, limit: int, grid: tuple[int, int] | None = None) -> str:
    """Why a cloth is refused as too large: ``grid of 4000x4000 = 16000000 vertices exceeds the
    limit of 65536 vertices per cloth``."""
    what = f"grid of {grid[0]}x{grid[1]} = {n_vertices}" if grid is not None else f"mesh of {n_vertices}"
    return f"{what} vertices exceeds the limit of {limit} vertices per cloth"
