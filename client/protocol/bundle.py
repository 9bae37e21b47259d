"""State bundles "DRPB" (1.1, PROTOCOL.md section 9.1): the states of one client's bundled cloths
at one tick in one payload. Writing (``encode_bundle`` and the helpers the server's encoders share)
and reading: ``parse_bundle`` reads the entry table (as columns: a bundle of equal entries in a
few numpy operations), ``Bundle.decode`` every state at once (decode_states)."""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import repeat
from typing import overload

import numpy as np

from .errors import ERR_MALFORMED, ProtocolError
from .keys import PROTOCOL_MAJOR, PROTOCOL_MINOR, valid_id
from .state import (
    FLAG_NORMALS,
    STATE_HEADER_DTYPE,
    STATE_HEADER_SIZE,
    STATE_MAGIC,
    ClothState,
    check_preamble,
    decode_state,
    element_size,
    float16_decode_many,
    header_dtype,
    quant16_decode_many,
    read_state_header,
    snorm16_decode_many,
)
from .vocabulary import ENC_FLOAT16, ENC_FLOAT32, ENC_PREDICTIVE, ENC_QUANT16, ENCODING_NAMES

BUNDLE_MAGIC = b"DRPB"
#: The bundle header, field by field: (name, struct code, meaning); BUNDLE_HEADER and the C header
#: client/protocol/drape_wire.h are this list.
BUNDLE_HEADER_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("magic", "4s", 'ASCII "DRPB"'),
    ("major", "B", "protocol major version (1)"),
    ("minor", "B", "protocol minor version of the writer; readers accept any"),
    ("header_size", "H", "byte offset of the first entry (32 up to 1.2)"),
    ("count", "I", "number of entries"),
    ("flags", "I", "none defined up to 1.2 (0)"),
    ("tick", "Q", "tick number"),
    ("server_time_ns", "Q", "Unix epoch nanoseconds, as in the states"),
)
BUNDLE_HEADER = struct.Struct("<" + "".join(code for _, code, _ in BUNDLE_HEADER_FIELDS))
assert BUNDLE_HEADER.format == "<4sBBHIIQQ"
BUNDLE_HEADER_SIZE = BUNDLE_HEADER.size  # 32
assert BUNDLE_HEADER_SIZE == 32
#: An entry's fixed part: (name, struct code, meaning); then the cloth id and zeros up to header_size.
BUNDLE_ENTRY_FIELDS: tuple[tuple[str, str, str], ...] = (
    ("header_size", "H", "h: offset of the state from the entry start, 8 + id_length rounded up to 8"),
    ("id_length", "B", "L: length of the cloth id (1..64)"),
    ("reserved", "x", "0"),
    ("state_size", "I", "s: size of the state payload in bytes"),
)
BUNDLE_ENTRY = struct.Struct("<" + "".join(code for _, code, _ in BUNDLE_ENTRY_FIELDS))
assert BUNDLE_ENTRY.format == "<HBxI"
BUNDLE_ENTRY_SIZE = BUNDLE_ENTRY.size  # 8, then the cloth id, then zeros up to the entry header size
BUNDLE_ENTRY_DTYPE = header_dtype(BUNDLE_ENTRY_FIELDS)  # many entries' fixed parts at once
assert BUNDLE_ENTRY_DTYPE.itemsize == BUNDLE_ENTRY_SIZE
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
    BUNDLE_HEADER.pack_into(
        out, 0, BUNDLE_MAGIC, PROTOCOL_MAJOR, PROTOCOL_MINOR, BUNDLE_HEADER_SIZE, count, flags, tick, server_time_ns
    )


def pack_bundle_entry(out: bytearray | memoryview, at: int, cloth: str, state_size: int) -> int:
    """Write an entry header (with the id and its padding) at ``at``; returns the state's offset."""
    cid = cloth.encode("ascii")
    h = align8(BUNDLE_ENTRY_SIZE + len(cid))
    BUNDLE_ENTRY.pack_into(out, at, h, len(cid), state_size)
    end = at + BUNDLE_ENTRY_SIZE + len(cid)
    out[at + BUNDLE_ENTRY_SIZE : end] = cid
    out[end : at + h] = bytes(at + h - end)
    return at + h


def encode_bundle(
    tick: int, server_time_ns: int, states: Sequence[tuple[str, bytes | bytearray | memoryview]], flags: int = 0
) -> bytearray:
    """The bundle payload of (cloth id, state payload) pairs, in order. Every state should carry
    the bundle's tick and server time (encode_state(tick, server_time_ns, ...))."""
    out = bytearray(bundle_size((c, len(st)) for c, st in states))
    pack_bundle_header(out, tick, server_time_ns, len(states), flags)
    at = BUNDLE_HEADER_SIZE
    for cloth, st in states:
        if not valid_id(cloth):
            raise ValueError(f"invalid cloth id {cloth!r}")
        off = pack_bundle_entry(out, at, cloth, len(st))
        out[off : off + len(st)] = st
        at = off + align8(len(st))  # the padding is already zero
    return out


@dataclass(frozen=True)
class BundleEntry:
    cloth: str
    offset: int  # of the state payload, from the start of the bundle
    size: int  # of the state payload


class BundleEntries(Sequence[BundleEntry]):
    """A bundle's entry table as columns: ``cloths`` (ids), ``offsets`` and ``sizes`` (int64 arrays)
    of each state payload. A sequence of BundleEntry (made when read: a bundle's reader needs
    the columns, not thousands of small objects)."""

    __slots__ = ("cloths", "offsets", "sizes")

    def __init__(self, cloths: list[str], offsets: np.ndarray, sizes: np.ndarray) -> None:
        self.cloths = cloths
        self.offsets = offsets
        self.sizes = sizes

    @classmethod
    def of(cls, entries: Sequence[BundleEntry]) -> BundleEntries:
        if isinstance(entries, BundleEntries):
            return entries
        return cls(
            [e.cloth for e in entries],
            np.array([e.offset for e in entries], np.int64),
            np.array([e.size for e in entries], np.int64),
        )

    def __len__(self) -> int:
        return len(self.cloths)

    @overload
    def __getitem__(self, i: int) -> BundleEntry: ...

    @overload
    def __getitem__(self, i: slice) -> list[BundleEntry]: ...

    def __getitem__(self, i: int | slice) -> BundleEntry | list[BundleEntry]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        return BundleEntry(self.cloths[i], int(self.offsets[i]), int(self.sizes[i]))

    def __iter__(self) -> Iterator[BundleEntry]:
        for c, o, s in zip(self.cloths, self.offsets.tolist(), self.sizes.tolist(), strict=True):
            yield BundleEntry(c, o, s)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    def __repr__(self) -> str:
        return f"BundleEntries({list(self)!r})"


@dataclass(eq=False)
class Bundle:
    """A parsed bundle: header fields and where each cloth's state payload lies in ``data``."""

    tick: int
    server_time_ns: int
    flags: int
    entries: Sequence[BundleEntry]  # a BundleEntries from parse_bundle
    data: bytes | bytearray | memoryview
    minor: int = PROTOCOL_MINOR

    def payload(self, i: int) -> memoryview:
        e = self.entries[i]
        return memoryview(self.data)[e.offset : e.offset + e.size]

    def state(self, i: int, receive_time_ns: int = 0) -> ClothState:
        """Entry ``i`` decoded with decode_state (float32 arrays are views of the bundle)."""
        return decode_state(self.payload(i), self.entries[i].cloth, receive_time_ns)

    def decode(self, receive_time_ns: int = 0) -> list[ClothState | ProtocolError]:
        """Every entry at once: entry ``i`` is what ``state(i)`` returns, equal bit for bit, or the
        ProtocolError it would raise (an invalid state spoils only its own entry). One pass of
        decode_states over the whole bundle instead of decode_state per entry."""
        cols = BundleEntries.of(self.entries)
        return decode_states(self.data, cols.offsets, cols.sizes, cols.cloths, receive_time_ns)

    def states(self, receive_time_ns: int = 0) -> list[ClothState]:
        """Every entry's state (``decode``), raising the first invalid entry's ProtocolError."""
        out = self.decode(receive_time_ns)
        for st in out:
            if isinstance(st, ProtocolError):
                raise st
        return out  # type: ignore[return-value]


_known_ids: set[str] = set()  # ids valid_id accepted (a client's bundle repeats its ids every tick)
_MAX_KNOWN_IDS = 1 << 16


def _all_valid(ids: list[str]) -> bool:
    """valid_id of every id, remembering the valid ones."""
    if _known_ids.issuperset(ids):
        return True
    fresh = [c for c in ids if c not in _known_ids]
    if not all(valid_id(c) for c in fresh):
        return False
    if len(_known_ids) + len(fresh) > _MAX_KNOWN_IDS:
        _known_ids.clear()
    _known_ids.update(fresh)
    return True


def _equal_entries(buf: bytes | bytearray | memoryview, at: int, count: int) -> BundleEntries | None:
    """The entry table when every entry has the first one's header size and state size (a bundle
    of equal cloths), checked and read with a few numpy operations; None when they differ or
    anything is wrong (the entry-by-entry walk then reads the table or names the error)."""
    size = len(buf)
    if count == 0 or at + BUNDLE_ENTRY_SIZE > size:
        return None
    h0, len0, s0 = BUNDLE_ENTRY.unpack_from(buf, at)
    if len0 == 0 or h0 < BUNDLE_ENTRY_SIZE + len0:
        return None
    stride = align8(h0 + s0)  # >= 16: count is bounded by the size checked next
    if at + (count - 1) * stride + h0 + s0 > size:
        return None
    e = np.ndarray((count,), BUNDLE_ENTRY_DTYPE, buf, at, (stride,))  # every entry's fixed part, no copy
    lengths = e["id_length"]
    if (e["header_size"] != h0).any() or (e["state_size"] != s0).any() or (lengths == 0).any():
        return None
    if BUNDLE_ENTRY_SIZE + int(lengths.max()) > h0:
        return None
    width = int(lengths.max())
    raw = np.array(np.ndarray((count, width), np.uint8, buf, at + BUNDLE_ENTRY_SIZE, (stride, 1)))
    inside = np.arange(width) < lengths[:, None]
    if (raw[inside] == 0).any():  # a NUL in an id (invalid): the walk says so
        return None
    raw[~inside] = 0
    try:
        ids = b"\0".join(raw.view(f"S{width}").reshape(count).tolist()).decode("ascii").split("\0")
    except UnicodeDecodeError:
        return None
    if not _all_valid(ids):
        return None
    return BundleEntries(ids, at + h0 + stride * np.arange(count, dtype=np.int64), np.full(count, s0, np.int64))


def _walk_entries(buf: bytes | bytearray | memoryview, at: int, count: int) -> BundleEntries:
    """The entry table, entry by entry (entries of different sizes), raising on the first bad one."""
    size = len(buf)
    cloths: list[str] = []
    offsets: list[int] = []
    sizes: list[int] = []
    for i in range(count):
        if at + BUNDLE_ENTRY_SIZE > size:
            raise ProtocolError(
                ERR_MALFORMED, f"bundle entry {i} of {count} starts at byte {at}, past the end ({size})"
            )
        h, id_len, st_size = BUNDLE_ENTRY.unpack_from(buf, at)
        if h < BUNDLE_ENTRY_SIZE + id_len:
            raise ProtocolError(
                ERR_MALFORMED, f"bundle entry {i}: entry header size {h} is below 8 + id length {id_len}"
            )
        if at + h + st_size > size:
            raise ProtocolError(
                ERR_MALFORMED, f"bundle entry {i}: state of {st_size} bytes at byte {at + h} runs past the end ({size})"
            )
        try:
            cloth = bytes(buf[at + BUNDLE_ENTRY_SIZE : at + BUNDLE_ENTRY_SIZE + id_len]).decode("ascii")
        except UnicodeDecodeError:
            cloth = ""
        if cloth not in _known_ids and not _all_valid([cloth]):
            raise ProtocolError(ERR_MALFORMED, f"bundle entry {i}: invalid cloth id")
        cloths.append(cloth)
        offsets.append(at + h)
        sizes.append(st_size)
        at = align8(at + h + st_size)
    return BundleEntries(cloths, np.array(offsets, np.int64), np.array(sizes, np.int64))


def parse_bundle(data: bytes | bytearray | memoryview) -> Bundle:
    """Parse a bundle's header and entry table (the states are decoded on demand: ``state(i)``, or
    all at once: ``decode()``). Raises ProtocolError on a bad magic, an unknown major version, a
    header_size below 32, an entry that does not fit, an entry header size below 8 + id length,
    or an id that is not a valid cloth id. Unknown flag bits, a longer header and trailing bytes
    after the last entry are ignored (later minor versions may add them)."""
    buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
    size = len(buf)
    if size < BUNDLE_HEADER_SIZE:
        raise ProtocolError(
            ERR_MALFORMED, f"bundle of {size} bytes is shorter than the {BUNDLE_HEADER_SIZE}-byte header"
        )
    magic, major, minor, hsize, count, flags, tick, t_ns = BUNDLE_HEADER.unpack_from(buf, 0)
    check_preamble("bundle", magic, BUNDLE_MAGIC, major, minor, hsize, BUNDLE_HEADER_SIZE)
    entries = _equal_entries(buf, hsize, count)
    if entries is None:
        entries = _walk_entries(buf, hsize, count)
    return Bundle(tick, t_ns, flags, entries, buf, minor)


def decode_bundle(data: bytes | bytearray | memoryview, receive_time_ns: int = 0) -> list[ClothState]:
    """Every state of a bundle, decoded (each ClothState's ``cloth`` is its entry's id), raising
    the first invalid state's ProtocolError (``parse_bundle(data).decode()`` keeps the others)."""
    return parse_bundle(data).states(receive_time_ns)


# --- every state of a bundle at once --------------------------------------------------------------


def _block(buf: bytes | bytearray | memoryview, at: np.ndarray, dtype: str, n: int) -> np.ndarray:
    """(m, n, 3) ``dtype`` values starting at byte offsets ``at`` of ``buf``: a view when the offsets
    are evenly spaced and ascending (the usual bundle), else one copy per entry into one array."""
    m = len(at)
    es = np.dtype(dtype).itemsize
    stride = int(at[1] - at[0]) if m > 1 else n * 3 * es
    if m == 1 or (stride > 0 and (m == 2 or bool((np.diff(at) == stride).all()))):
        return np.ndarray((m, n, 3), dtype, buf, int(at[0]), (stride, 3 * es, es))
    out = np.empty((m, n, 3), dtype)
    for j, a in enumerate(at.tolist()):
        out[j] = np.frombuffer(buf, dtype, n * 3, a).reshape(n, 3)
    out.flags.writeable = not memoryview(buf).readonly  # as the views decode_state gives
    return out


_ELEMENT_SIZES = np.array([element_size(e) for e in range(256)], np.int64)
_KNOWN_ENCODINGS = np.zeros(256, bool)  # decoded here by groups (a predictive state needs its stream)
_KNOWN_ENCODINGS[[e for e in ENCODING_NAMES if e != ENC_PREDICTIVE]] = True
_VALUES = {ENC_FLOAT32: ("<f4", "<f4"), ENC_FLOAT16: ("<f2", "<f2"), ENC_QUANT16: ("<u2", "<i2")}


def decode_states(
    data: bytes | bytearray | memoryview,
    offsets: Sequence[int] | np.ndarray,
    sizes: Sequence[int] | np.ndarray,
    cloths: Sequence[str],
    receive_time_ns: int = 0,
) -> list[ClothState | ProtocolError]:
    """The state payloads ``data[offsets[i] : offsets[i] + sizes[i]]`` (inside ``data``), each
    decoded as ``decode_state(payload, cloths[i], receive_time_ns)`` would, or the ProtocolError it
    would raise: the whole-frame reader of a bundle. Equal in every field and bit for bit in every
    array; the work is a handful of numpy operations per group of states of the same encoding,
    vertex count and normals, not per state (float32 arrays are views of ``data`` as
    decode_state's are when the group's states are evenly spaced; the others are rows of one
    array per group, which a state keeps alive)."""
    buf = data if isinstance(data, (bytes, bytearray)) else memoryview(data).cast("B")
    off = np.asarray(offsets, np.int64).reshape(-1)
    size = np.asarray(sizes, np.int64).reshape(-1)
    k = len(off)
    if len(size) != k or len(cloths) != k:
        raise ValueError(f"{k} offsets, {len(size)} sizes and {len(cloths)} cloth ids")
    if k and (int(off.min()) < 0 or int(size.min()) < 0 or int((off + size).max()) > len(buf)):
        raise ValueError("state payloads must lie inside the data")
    u8 = np.frombuffer(buf, np.uint8)
    if k and int(size.min()) >= STATE_HEADER_SIZE:  # a bundle of like states: one group, checked once
        stride = int(off[1] - off[0]) if k > 1 else STATE_HEADER_SIZE
        if stride >= STATE_HEADER_SIZE and (k < 3 or bool((np.diff(off) == stride).all())):
            raw = np.ndarray((k, STATE_HEADER_SIZE), np.uint8, buf, int(off[0]), (stride, 1))  # no copy
        else:
            raw = u8[off[:, None] + np.arange(STATE_HEADER_SIZE)]
        kind = raw[:, :16].view("<u8") & _KIND_MASK
        if bool((kind == kind[0]).all()):
            try:
                hsize0, e, _, n0 = read_state_header(buf, int(size.min()), int(off[0]))[:4]
            except ProtocolError:
                e = ENC_PREDICTIVE  # the entry by entry path says for which
            if e != ENC_PREDICTIVE:  # predictive states: each its stream's, entry by entry below
                with np.errstate(all="ignore"):  # hostile bounds and values (NaN, inf) decode quietly
                    h = raw.view(STATE_HEADER_DTYPE).reshape(k)
                    has_n = bool(h["flags"][0] & FLAG_NORMALS)
                    return _decode_group(  # type: ignore[return-value]
                        buf, off + hsize0, h, e, n0, has_n, cloths, receive_time_ns
                    )
    out = np.empty(k, object)
    whole = np.flatnonzero(size >= STATE_HEADER_SIZE)
    h = u8[off[whole, None] + np.arange(STATE_HEADER_SIZE)].view(STATE_HEADER_DTYPE).reshape(-1)
    ok, enc, n, hsize, normals, _ = _check(h, size[whole])
    bad = np.ones(k, bool)
    bad[whole[ok]] = False
    for i in np.flatnonzero(bad).tolist():  # each as decode_state reports it
        a = int(off[i])
        try:
            out[i] = decode_state(buf[a : a + int(size[i])], cloths[i], receive_time_ns)
        except ProtocolError as err:
            out[i] = err
    idx, h, enc, n, hsize, normals = whole[ok], h[ok], enc[ok], n[ok], hsize[ok], normals[ok]
    # groups of one encoding, vertex count and normals flag, each in entry order
    key = n * 8 + enc * 2 + normals
    order = np.argsort(key, kind="stable")
    cuts = np.flatnonzero(np.diff(key[order])) + 1
    for g in np.split(order, cuts) if len(order) else ():
        ids = [cloths[i] for i in idx[g].tolist()]
        e, nv, has_n = int(enc[g[0]]), int(n[g[0]]), bool(normals[g[0]])
        with np.errstate(all="ignore"):
            out[idx[g]] = _decode_group(buf, off[idx[g]] + hsize[g], h[g], e, nv, has_n, ids, receive_time_ns)
    return out.tolist()  # type: ignore[no-any-return]


def _kind_mask() -> np.ndarray:
    """The bits of a state header's first 16 bytes that make its kind (what decode_state checks
    and the layout of its values: magic, major, header_size, encoding, the normals flag, vertex
    count), as two little-endian u64 masks: states whose masked words are equal decode alike."""
    fields = STATE_HEADER_DTYPE.fields
    assert fields is not None
    mask = np.zeros(16, np.uint8)
    for name in ("magic", "major", "header_size", "encoding", "vertex_count"):
        dt, at = fields[name][:2]
        assert at + dt.itemsize <= 16
        mask[at : at + dt.itemsize] = 0xFF
    at = fields["flags"][1]
    mask[at : at + 2] = np.frombuffer(struct.pack("<H", FLAG_NORMALS), np.uint8)
    return mask.view("<u8")


_KIND_MASK = _kind_mask()


def _check(h: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, ...]:
    """decode_state's checks on many headers: (ok, encoding, vertex count, header size, normals,
    bytes needed) per header."""
    enc = h["encoding"].astype(np.int64)
    n = h["vertex_count"].astype(np.int64)
    hsize = h["header_size"].astype(np.int64)
    normals = (h["flags"] & FLAG_NORMALS).astype(bool)
    need = hsize + n * 3 * _ELEMENT_SIZES[enc] * (1 + normals)
    ok = (
        (h["magic"] == STATE_MAGIC)
        & (h["major"] == PROTOCOL_MAJOR)
        & (hsize >= STATE_HEADER_SIZE)
        & _KNOWN_ENCODINGS[enc]
        & (need <= size)
    )
    return ok, enc, n, hsize, normals, need


def _decode_group(
    buf: bytes | bytearray | memoryview,
    at: np.ndarray,
    h: np.ndarray,
    e: int,
    n: int,
    has_n: bool,
    cloths: Sequence[str],
    receive_time_ns: int,
) -> list[ClothState]:
    """The states of one group (encoding ``e``, ``n`` vertices, normals or not) whose values start
    at byte offsets ``at``; ``h`` their headers."""
    m = len(at)
    pos_t, nrm_t = _VALUES[e]
    raw = _block(buf, at, pos_t, n)
    nraw = _block(buf, at + n * 3 * element_size(e), nrm_t, n) if has_n else None
    if e == ENC_FLOAT32:
        pos, nrm = raw, nraw
    elif e == ENC_FLOAT16:
        pos = float16_decode_many(raw)
        nrm = None if nraw is None else float16_decode_many(nraw)
    else:
        pos = quant16_decode_many(raw, h["bounds_min"], h["bounds_max"])
        nrm = None if nraw is None else snorm16_decode_many(nraw)
    lo = h["bounds_min"].astype(np.float64).T.tolist()  # per axis, each as float(np.float32) gives it
    hi = h["bounds_max"].astype(np.float64).T.tolist()
    return list(
        map(
            ClothState,
            h["tick"].tolist(),
            h["server_time_ns"].tolist(),
            list(pos),
            [None] * m if nrm is None else list(nrm),
            repeat(receive_time_ns, m),
            repeat(ENCODING_NAMES[e], m),
            h["flags"].tolist(),
            zip(zip(*lo, strict=True), zip(*hi, strict=True), strict=True),
            cloths,
        )
    )
