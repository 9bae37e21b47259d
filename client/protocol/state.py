"""The binary cloth state "DRPS" (PROTOCOL.md section 9): header layout, encodings and the
float16/quant16/snorm16 arithmetic (the server's whole-frame encoder uses the same functions)."""

from __future__ import annotations

import re
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .errors import ERR_INVALID_VALUE, ERR_MALFORMED, ERR_UNSUPPORTED_VERSION, ProtocolError
from .keys import PROTOCOL_MAJOR, PROTOCOL_MINOR, VERSION_STRING
from .predictive import History, encode_step
from .vocabulary import ENC_FLOAT16, ENC_FLOAT32, ENC_PREDICTIVE, ENCODING_IDS, ENCODING_NAMES, ENCODINGS, Vec3

STATE_MAGIC = b"DRPS"
#: The state header, field by field: (name, struct code, meaning). STATE_HEADER, the C header
#: client/protocol/drape_wire.h and PROTOCOL.md's table are all this one list.
STATE_HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("magic", "4s", 'ASCII "DRPS"'),
    ("major", "B", "protocol major version (1)"),
    ("minor", "B", "protocol minor version of the writer; readers accept any"),
    ("header_size", "H", "byte offset of the vertex data (64 up to 1.2)"),
    ("encoding", "B", "0 float32, 1 float16, 2 quant16, 3 predictive (1.5)"),
    ("reserved0", "x", "0"),
    ("flags", "H", "bit 0: normals follow the positions; bit 1: reset state"),
    ("vertex_count", "I", "n, the number of vertices"),
    ("tick", "Q", "tick number"),
    ("server_time_ns", "Q", "Unix epoch nanoseconds (server wall clock) when the tick was read back"),
    ("bounds_min", "3f", "x, y, z minimum of the positions"),
    ("bounds_max", "3f", "x, y, z maximum of the positions"),
    ("reserved1", "8x", "0"),
)
STATE_HEADER = struct.Struct("<" + "".join(code for _, code, _ in STATE_HEADER_FIELDS))
assert STATE_HEADER.format == "<4sBBHBxHIQQ3f3f8x"
STATE_HEADER_SIZE = STATE_HEADER.size  # 64
assert STATE_HEADER_SIZE == 64

_NUMPY_CODES = {"s": "S", "B": "u1", "H": "<u2", "I": "<u4", "Q": "<u8", "f": "<f4"}


def header_dtype(fields: Sequence[tuple[str, str, str]]) -> np.dtype:
    """The numpy structured dtype of a little-endian header given as (name, struct code, meaning)
    fields (padding ``x`` fields are left out, their bytes kept): what reads many headers at once."""
    names: list[str] = []
    formats: list[object] = []
    offsets: list[int] = []
    at = 0
    for name, code, _ in fields:
        count_s, c = re.fullmatch(r"(\d*)([a-zA-Z])", code).groups()  # type: ignore[union-attr]
        count = int(count_s or 1)
        if c != "x":
            names.append(name)
            offsets.append(at)
            fmt = _NUMPY_CODES[c]
            formats.append(f"S{count}" if c == "s" else (fmt if count == 1 else (fmt, (count,))))
        at += struct.calcsize("<" + code)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": at})


STATE_HEADER_DTYPE = header_dtype(STATE_HEADER_FIELDS)
assert STATE_HEADER_DTYPE.itemsize == STATE_HEADER_SIZE

#: 1.5: what a predictive state's header adds after the first 64 bytes (PROTOCOL.md 9.2); its
#: header_size is 96 and the packed positions (client/protocol/predictive.py) follow.
PREDICTIVE_HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("step", "f", "grid step in metres: a decoded position is within step / 2 of the simulated one"),
    ("order", "B", "predictor order: 0 intra-coded (a keyframe), 1 the previous state, 2 the last two"),
    ("reserved2", "x", "0"),
    ("stride", "H", "ticks between this stream's states (1: every tick)"),
    ("ref_tick", "Q", "tick of the stream's previous state (order 1 and 2), else 0"),
    ("ref2_tick", "Q", "tick of the state before that (order 2), else 0"),
    ("data_size", "I", "bytes of the packed positions, a multiple of 4"),
    ("reserved3", "4x", "0"),
)
PREDICTIVE_HEADER = struct.Struct("<" + "".join(code for _, code, _ in PREDICTIVE_HEADER_FIELDS))
assert PREDICTIVE_HEADER.format == "<fBxHQQI4x"
PREDICTIVE_HEADER_SIZE = STATE_HEADER_SIZE + PREDICTIVE_HEADER.size  # 96
assert PREDICTIVE_HEADER_SIZE == 96

FLAG_NORMALS = 1 << 0  # normals follow the positions
FLAG_RESET = 1 << 1  # this state is a reset (rest pose after a non-finite step, or a reset control)
KNOWN_FLAGS = FLAG_NORMALS | FLAG_RESET

FLOAT16_MAX = 65504.0
QUANT_MAX = 65535
SNORM_MAX = 32767


@dataclass(eq=False)
class ClothState:
    """One cloth's state at one tick. ``positions`` (n, 3) float32 and ``normals`` (n, 3) float32
    or None; arrays decoded from float32 payloads are read-only views of the payload (read-only
    copies where Bundle.decode found a bundle's like states unevenly spaced); Bundle.decode's
    other arrays are rows of one array per group of like states."""

    tick: int
    server_time_ns: int
    positions: np.ndarray
    normals: np.ndarray | None = None
    receive_time_ns: int = 0
    encoding: str = "float32"
    flags: int = 0
    bounds: tuple[Vec3, Vec3] = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    cloth: str = ""
    #: 1.5: not received but extrapolated from the last two states decoded (a predictive state
    #: that could not be decoded: its reference was lost; see StateStream)
    extrapolated: bool = False

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


def element_size(encoding: int) -> int:
    """Bytes per coordinate of an encoding id: 4 for float32, 2 for float16 and quant16 (and for
    the normals of a predictive state, snorm16 as quant16's)."""
    return 4 if encoding == ENC_FLOAT32 else 2


_elem_size = element_size


def state_size(n_vertices: int, encoding: str | int = "float32", normals: bool = False) -> int:
    """Bytes of an encoded state (``encoding`` a name of ENCODINGS or its id); of a predictive
    state (whose size varies with its motion) the most it can take."""
    enc = ENCODING_IDS[encoding] if isinstance(encoding, str) else int(encoding)
    if enc == ENC_PREDICTIVE:
        from .predictive import packed_size

        nb = -(-n_vertices // 32)
        return PREDICTIVE_HEADER_SIZE + packed_size(n_vertices, [32] * 3 * nb) + n_vertices * 6 * normals
    return STATE_HEADER_SIZE + n_vertices * 3 * element_size(enc) * (2 if normals else 1)


def pack_state_header(
    out: bytearray | memoryview,
    at: int,
    encoding: int,
    flags: int,
    n: int,
    tick: int,
    server_time_ns: int,
    lo: Sequence[float],
    hi: Sequence[float],
    header_size: int = STATE_HEADER_SIZE,
) -> None:
    """Write a state header (this side's version; header_size 64, a predictive state's 96) at ``at``."""
    STATE_HEADER.pack_into(
        out,
        at,
        STATE_MAGIC,
        PROTOCOL_MAJOR,
        PROTOCOL_MINOR,
        header_size,
        encoding,
        flags,
        n,
        tick,
        server_time_ns,
        lo[0],
        lo[1],
        lo[2],
        hi[0],
        hi[1],
        hi[2],
    )


def float16_values(x: np.ndarray) -> np.ndarray:
    """float16 positions: IEEE half, round to nearest even, clamped to +-65504 first."""
    return np.clip(x, -FLOAT16_MAX, FLOAT16_MAX).astype("<f2")


def quant16_scale(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, scale) in float64 from float32 bounds (any shape ending in 3): per axis
    scale = 65535 / (max - min), 0 where max == min."""
    lo64 = np.asarray(lo, np.float32).astype(np.float64)
    ext = np.asarray(hi, np.float32).astype(np.float64) - lo64
    return lo64, np.divide(QUANT_MAX, ext, out=np.zeros_like(ext), where=ext > 0)


def quant16_round(q: np.ndarray) -> np.ndarray:
    """In place on float64 ``(x - min) * scale``: clamp to 0..65535 and round half to even."""
    np.clip(q, 0, QUANT_MAX, out=q)
    np.rint(q, out=q)
    return q


def quant16_values(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """quant16 of positions ``x`` (n, 3) against one cloth's float32 bounds: uint16
    rint(clamp((x - min) * 65535 / (max - min), 0, 65535)) evaluated in float64."""
    lo64, scale = quant16_scale(lo, hi)
    return quant16_round((np.asarray(x, np.float32).astype(np.float64) - lo64) * scale).astype("<u2")


def quant16_decode(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Positions from quant16 values: min + q * (max - min) / 65535 in float64, then float32. An
    axis whose bounds are not finite (a hostile or broken writer's) decodes to the canonical NaN:
    which of two NaNs an operation keeps is the hardware's and numpy's loop's choice."""
    lo64 = np.asarray(lo, np.float32).astype(np.float64)
    hi64 = np.asarray(hi, np.float32).astype(np.float64)
    out = (lo64 + np.asarray(q, np.float64) * ((hi64 - lo64) / QUANT_MAX)).astype(np.float32)
    bad = ~(np.isfinite(lo64) & np.isfinite(hi64))
    if bad.any():
        out[..., bad] = np.float32(np.nan)
    return out


def snorm16_values(normals: np.ndarray) -> np.ndarray:
    """quant16 normals: int16 rint(clamp(n, -1, 1) * 32767) evaluated in float64."""
    return np.rint(np.clip(np.asarray(normals, np.float32).astype(np.float64), -1.0, 1.0) * SNORM_MAX).astype("<i2")


def encode_normals_into(out: bytearray | memoryview, at: int, normals: np.ndarray, encoding: int) -> None:
    """Write a normals block of ``encoding`` at ``at``."""
    nrm = np.asarray(normals, np.float32).reshape(-1, 3)
    n = len(nrm)
    if encoding == ENC_FLOAT32:
        np.frombuffer(out, "<f4", n * 3, at).reshape(n, 3)[:] = nrm
    elif encoding == ENC_FLOAT16:
        np.frombuffer(out, "<f2", n * 3, at).reshape(n, 3)[:] = nrm
    else:
        np.frombuffer(out, "<i2", n * 3, at).reshape(n, 3)[:] = snorm16_values(nrm)


def bounds_of(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The header's bounds of (n, 3) float32 positions: per axis min and max (zeros for none)."""
    if not len(pos):
        return np.zeros(3, np.float32), np.zeros(3, np.float32)
    return pos.min(axis=0), pos.max(axis=0)


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
    if enc == ENC_PREDICTIVE:
        raise ValueError("a predictive state is coded against its stream's history: encode_predictive_state")
    pos = np.asarray(positions, np.float32).reshape(-1, 3)
    n = len(pos)
    if normals is not None:
        flags |= FLAG_NORMALS
        nrm = np.asarray(normals, np.float32).reshape(n, 3)
    else:
        flags &= ~FLAG_NORMALS
    lo, hi = bounds_of(pos)
    es = _elem_size(enc)
    block = n * 3 * es
    out = bytearray(STATE_HEADER_SIZE + block * (2 if normals is not None else 1))
    pack_state_header(out, 0, enc, flags, n, tick, server_time_ns, lo.tolist(), hi.tolist())
    if enc == ENC_FLOAT32:
        np.frombuffer(out, "<f4", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = pos
    elif enc == ENC_FLOAT16:
        np.frombuffer(out, "<f2", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = float16_values(pos)
    else:
        np.frombuffer(out, "<u2", n * 3, STATE_HEADER_SIZE).reshape(n, 3)[:] = quant16_values(pos, lo, hi)
    if normals is not None:
        encode_normals_into(out, STATE_HEADER_SIZE + block, nrm, enc)
    return out


def check_preamble(what: str, magic: bytes, want: bytes, major: int, minor: int, hsize: int, least: int) -> None:
    """PROTOCOL.md 9's reading rules every binary payload shares (``what``: "state", "bundle"):
    its magic, its major version, and a header_size of at least the header this side knows."""
    if magic != want:
        raise ProtocolError(ERR_MALFORMED, f"{what} magic {bytes(magic)!r} is not {want!r}")
    if major != PROTOCOL_MAJOR:
        raise ProtocolError(
            ERR_UNSUPPORTED_VERSION,
            f"{what} version {major}.{minor} is not supported; this side speaks {VERSION_STRING}",
        )
    if hsize < least:
        raise ProtocolError(ERR_MALFORMED, f"{what} header_size {hsize} is below {least}")


def read_state_header(buf: bytes | bytearray | memoryview, size: int, at: int = 0) -> tuple:
    """The header of the ``size``-byte state payload at ``at`` of ``buf``, checked by PROTOCOL.md 9's
    reading rules (ProtocolError if it breaks one): (header_size, encoding, flags, n, tick,
    server time, bounds min x y z, bounds max x y z)."""
    if size < STATE_HEADER_SIZE:
        raise ProtocolError(
            ERR_MALFORMED, f"state payload of {size} bytes is shorter than the {STATE_HEADER_SIZE}-byte header"
        )
    (magic, major, minor, hsize, enc, flags, n, *rest) = STATE_HEADER.unpack_from(buf, at)
    check_preamble("state", magic, STATE_MAGIC, major, minor, hsize, STATE_HEADER_SIZE)
    if enc not in ENCODING_NAMES:
        raise ProtocolError(ERR_INVALID_VALUE, f"unknown state encoding {enc}")
    has_n = bool(flags & FLAG_NORMALS)
    if enc == ENC_PREDICTIVE:
        if hsize < PREDICTIVE_HEADER_SIZE or size < PREDICTIVE_HEADER_SIZE:
            raise ProtocolError(
                ERR_MALFORMED, f"predictive state of {size} bytes, header_size {hsize}: below {PREDICTIVE_HEADER_SIZE}"
            )
        data_size = PREDICTIVE_HEADER.unpack_from(buf, at + STATE_HEADER_SIZE)[-1]
        need = hsize + data_size + n * 6 * has_n
    else:
        need = hsize + n * 3 * _elem_size(enc) * (2 if has_n else 1)
    if size < need:
        raise ProtocolError(
            ERR_MALFORMED,
            f"state payload of {size} bytes is shorter than the {need} bytes its "
            f"header announces ({n} vertices, {ENCODING_NAMES[enc]}{', normals' if has_n else ''})",
        )
    return (hsize, enc, flags, n, *rest)


def decode_state(data: bytes | bytearray | memoryview, cloth: str = "", receive_time_ns: int = 0) -> ClothState:
    """Parse a state payload. Raises ProtocolError on a bad magic, an unknown major version or
    encoding, or a payload shorter than its header says. Unknown flag bits, a longer header
    (a later minor version) and trailing bytes are ignored."""
    buf = memoryview(data).cast("B") if not isinstance(data, (bytes, bytearray)) else data
    (hsize, enc, flags, n, tick, t_ns, x0, y0, z0, x1, y1, z1) = read_state_header(buf, len(buf))
    if enc == ENC_PREDICTIVE:
        raise ProtocolError(
            ERR_INVALID_VALUE, "a predictive state decodes against its stream's last states: use a StateStream"
        )
    es = _elem_size(enc)
    block = n * 3 * es
    has_n = bool(flags & FLAG_NORMALS)
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
        pos = quant16_decode(np.frombuffer(buf, "<u2", n * 3, hsize).reshape(n, 3), lo, hi)
        if has_n:
            nrm = (np.frombuffer(buf, "<i2", n * 3, hsize + block).reshape(n, 3) / SNORM_MAX).astype(np.float32)
    bounds = (tuple(float(v) for v in lo), tuple(float(v) for v in hi))
    return ClothState(tick, t_ns, pos, nrm, receive_time_ns, ENCODING_NAMES[enc], flags, bounds, cloth)  # type: ignore[arg-type]


# --- many states at once ------------------------------------------------------------------------
# What a bundle's reader (bundle.decode_states) runs once per group of like states instead of
# decode_state per entry: the same arithmetic on (m, n, 3) arrays, bit for bit decode_state's.

_QUANT16_CHUNK = 1 << 16  # float64 values per step of quant16_decode_many (512 KiB of scratch: fastest here)
_TILE = 64  # vertices per contiguous inner run in quant16_decode_many
_FLOAT16_TABLE: np.ndarray | None = None


def float16_table() -> np.ndarray:
    """float32 of every float16 bit pattern, as ``astype(np.float32)`` converts it (a table read
    is several times faster than numpy's half conversion)."""
    global _FLOAT16_TABLE
    if _FLOAT16_TABLE is None:
        _FLOAT16_TABLE = np.arange(1 << 16, dtype=np.uint16).view(np.float16).astype(np.float32)
    return _FLOAT16_TABLE


def float16_decode_many(h: np.ndarray) -> np.ndarray:
    """float32 of (m, n, 3) float16 values (each (n, 3) contiguous): ``h.astype(np.float32)``, by
    table, a few cloths at a time (numpy makes a 64-bit copy of the indices of each call: small
    copies are reused memory, one big one is fresh pages every time)."""
    table, u = float16_table(), h.view(np.uint16)
    out = np.empty(h.shape, np.float32)
    chunk = max(1, _QUANT16_CHUNK // max(1, u[0].size)) if len(u) else 1
    for i in range(0, len(u), chunk):
        np.take(table, u[i : i + chunk], out=out[i : i + chunk], mode="wrap")  # every index is in range
    return out


def snorm16_decode_many(q: np.ndarray) -> np.ndarray:
    """Normals from snorm16 values of any shape: ``(q / 32767).astype(np.float32)`` in one pass."""
    out = np.empty(q.shape, np.float32)
    np.divide(q, SNORM_MAX, out=out, dtype=np.float64, casting="same_kind")
    return out


def _tile(a: np.ndarray, t: int) -> np.ndarray:
    """(m, 1, 3) repeated ``t`` times along its last axis (by doubling: np.tile is slower)."""
    out = a
    while out.shape[-1] < 3 * t:
        out = np.concatenate((out, out), axis=-1)
    return out[..., : 3 * t]


def quant16_decode_many(q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """quant16_decode of m cloths at once: ``q`` (m, n, 3) uint16 (each cloth's (n, 3) contiguous),
    ``lo`` / ``hi`` (m, 3) float32 bounds; (m, n, 3) float32, bit for bit quant16_decode of each.

    The same float64 operations per value (``lo + q * ((hi - lo) / 65535)``, then float32); the
    per-axis factors are tiled along each row so that numpy's loops run over long contiguous
    stretches instead of broadcasting a 3-vector (which is several times slower)."""
    m, n, _ = q.shape
    lo64 = np.asarray(lo, np.float32).astype(np.float64).reshape(m, 1, 3)
    hi64 = np.asarray(hi, np.float32).astype(np.float64).reshape(m, 1, 3)
    step = (hi64 - lo64) / QUANT_MAX
    out = np.empty((m, n, 3), np.float32)
    t = min(_TILE, n)
    n0 = n // t * t if t else 0
    if n0:
        runs = n0 // t
        step_t, lo_t = _tile(step, t), _tile(lo64, t)
        chunk = max(1, _QUANT16_CHUNK // (n0 * 3))
        scratch = np.empty((min(chunk, m), runs, 3 * t), np.float64)
        for i in range(0, m, chunk):
            j = min(m, i + chunk)
            tmp = scratch[: j - i]
            np.copyto(tmp, q[i:j, :n0].reshape(j - i, runs, 3 * t))
            np.multiply(tmp, step_t[i:j], out=tmp)
            np.add(lo_t[i:j], tmp, out=tmp)  # lo first, as quant16_decode: a NaN bound's bits win alike
            np.copyto(out[i:j, :n0].reshape(j - i, runs, 3 * t), tmp, casting="same_kind")
    if n0 < n:  # the last n % 64 vertices
        out[:, n0:] = (lo64 + np.asarray(q[:, n0:], np.float64) * step).astype(np.float32)
    bad = ~(np.isfinite(lo64) & np.isfinite(hi64)).reshape(m, 3)  # as quant16_decode: the canonical NaN
    if bad.any():
        out.transpose(0, 2, 1)[bad] = np.float32(np.nan)
    return out


# --- predictive states (1.5) ---------------------------------------------------------------------


def encode_predictive_state(
    tick: int,
    server_time_ns: int,
    positions: np.ndarray,
    step: float,
    history: History,
    keyframe: bool = False,
    normals: np.ndarray | None = None,
    flags: int = 0,
    stride: int = 1,
) -> bytearray:
    """A predictive state (PROTOCOL.md 9.2) of one stream, coded against ``history`` (the last
    two states its decoders rebuilt, advanced here); ``keyframe``: intra-coded."""
    pos = np.asarray(positions, np.float32).reshape(-1, 3)
    n = len(pos)
    data, order, ref1, ref2 = encode_step(pos, step, history, tick, keyframe)
    flags = flags | FLAG_NORMALS if normals is not None else flags & ~FLAG_NORMALS
    lo, hi = bounds_of(pos)
    out = bytearray(PREDICTIVE_HEADER_SIZE + len(data) + (n * 6 if normals is not None else 0))
    pack_state_header(out, 0, ENC_PREDICTIVE, flags, n, tick, server_time_ns, lo.tolist(), hi.tolist())
    STATE_HEADER.pack_into(
        out, 0, *STATE_HEADER.unpack_from(out)[:3], PREDICTIVE_HEADER_SIZE, *STATE_HEADER.unpack_from(out)[4:]
    )
    PREDICTIVE_HEADER.pack_into(out, STATE_HEADER_SIZE, float(np.float32(step)), order, stride, ref1, ref2, len(data))
    out[PREDICTIVE_HEADER_SIZE : PREDICTIVE_HEADER_SIZE + len(data)] = data
    if normals is not None:
        encode_normals_into(out, PREDICTIVE_HEADER_SIZE + len(data), normals, ENC_PREDICTIVE)
    return out


@dataclass
class PredictiveHeader:
    """The fields a predictive state adds (PREDICTIVE_HEADER_FIELDS)."""

    step: float
    order: int
    stride: int
    ref_tick: int
    ref2_tick: int
    data_size: int


def read_predictive_header(buf: bytes | bytearray | memoryview, at: int = 0) -> PredictiveHeader:
    step, order, stride, ref1, ref2, size = PREDICTIVE_HEADER.unpack_from(buf, at + STATE_HEADER_SIZE)
    if order > 2:
        raise ProtocolError(ERR_INVALID_VALUE, f"unknown predictor order {order}")
    if not (np.isfinite(step) and step > 0):
        raise ProtocolError(ERR_INVALID_VALUE, f"predictive step {step} is not a positive number")
    return PredictiveHeader(step, order, stride, ref1, ref2, size)
