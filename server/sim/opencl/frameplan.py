"""The layout of a device-encoded frame: :class:`FramePlan` (where every publication and state
lies in the packed buffer, and the frame's static bytes), its inputs (:class:`ClothEntry`,
:class:`Publication`), the kernel's row layout (kernels/encode.cl's ``ENC_*``) and the dynamic
header fields' offsets (:data:`HEADER_OFFSETS`, found with drape.client.protocol's own writers).
encode.py's DeviceEncoder runs a plan on the device; see its docstring.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import NamedTuple, overload

import numpy as np

from drape.client import protocol as P

from ..roster import Roster
from .platforms import kernel_dir

SOURCE = "encode.cl"
STATIC_SOURCE = "static.cl"  # a plan's static words put into the encoder's output buffer


@lru_cache(maxsize=1)
def encode_layout() -> dict[str, int]:
    """The ``#define ENC_* int`` constants of kernels/encode.cl (the one copy of the row layout)."""
    text = (kernel_dir() / SOURCE).read_text()
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^#define\s+(ENC_\w+)\s+(\d+)\b", text, re.M)}


@lru_cache(maxsize=4096)
def state_size(n: int, encoding: int, normals: bool) -> int:
    """Bytes of one encoded state (PROTOCOL.md section 9); cached (a plan asks for each cloth's
    three times, and a predictive state's largest size takes numpy: 0.27 s a plan of 4096)."""
    return P.state_size(n, P.ENCODING_NAMES[encoding], normals)


class ClothEntry(NamedTuple):
    """One cloth of a plan: its id, vertex range ``[vbase, vbase + n)`` in the world's float4
    position (and normal) buffers, protocol encoding id, whether normals follow and (predictive,
    1.5) its grid step in metres and its first vertex in the encoder's history (1.8: a decimated
    streams' encoder keeps its own, for its cloths only; -1: ``vbase``). A named tuple, not a
    frozen dataclass: a plan of 8192 cloths makes 8192 of them on the tick thread, 4x faster so
    (docs/loadtest.md, tickbench)."""

    cloth: str
    vbase: int
    n: int
    encoding: int = P.ENC_FLOAT32
    normals: bool = False
    step: float = P.DEFAULT_STEP
    hbase: int = -1  # predictive: its first vertex in the encoder's history (-1: vbase)


@dataclass(frozen=True)
class Publication:
    """One payload per tick: a single state (``bundle=False``, exactly one cloth) or a bundle of
    the given cloths, in that order. ``cloths`` index the plan's cloth list; ``key`` is the
    caller's (the Zenoh key expression), carried along untouched."""

    key: str
    cloths: tuple[int, ...]
    bundle: bool = False


@dataclass(eq=False)
class FramePlan:
    """Where every publication and state lies in the packed frame, and its static bytes."""

    cloths: Sequence[ClothEntry]  # a list, or (for_roster) entries made when asked for
    publications: list[Publication]
    pub_offset: np.ndarray  # (P,) int64, multiples of 8
    pub_size: np.ndarray  # (P,) int64
    state_offset: np.ndarray  # (k,) int64 per plan cloth, -1 when it is in no publication
    rows: np.ndarray  # (R, ENC_ROW_WORDS) uint32: the kernel's table, one row per encoded cloth
    static_at: np.ndarray  # (m,) int64: the frame's 8-byte words holding static bytes (headers, ids)
    static_words: np.ndarray  # (m,) uint64: their values (every other byte of the frame is 0)
    nbytes: int  # the frame's size
    max_n: int = 0
    vertex_end: int = 0  # one past the last vertex any row reads
    normals: bool = False  # whether any row reads normals
    _bounds_at: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    _time_at: np.ndarray | None = None
    predictive: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (k,) coded predictively (1.5)
    owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (k,) publication, -1 for none
    is_bundle: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (P,) a bundle
    _sizes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (k,) each state's largest size
    _pred_extra: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # header and normals bytes

    _template: np.ndarray | None = None
    _cols: _Columns | None = None

    @property
    def size(self) -> int:
        return self.nbytes

    @property
    def ids(self) -> list[str]:
        """Each plan cloth's id (the columns of :attr:`cloths`, for whole-plan work)."""
        return self._columns().ids

    @property
    def vbases(self) -> np.ndarray:
        """(k,) int64: each plan cloth's first vertex."""
        return self._columns().vbase

    @property
    def hbases(self) -> np.ndarray:
        """(k,) int64: each plan cloth's first vertex in the encoder's history (-1: its vbase)."""
        return self._columns().hbase

    @property
    def counts(self) -> np.ndarray:
        """(k,) int64: each plan cloth's vertex count."""
        return self._columns().n

    @property
    def steps(self) -> np.ndarray:
        """(k,) float64: each plan cloth's grid step (predictive, 1.5)."""
        return self._columns().step

    def _columns(self) -> _Columns:
        if self._cols is None:
            self._cols = _Columns.of(list(self.cloths))
        return self._cols

    @property
    def template(self) -> np.ndarray:
        """(size,) uint8: the static bytes of the whole frame, made on first use (a frame of
        8192 predictive cloths is 100 MB, mostly zeros: :meth:`write_static` puts only the
        static words into a zeroed frame)."""
        if self._template is None:
            t = np.zeros(self.nbytes, np.uint8)
            self.write_static(t)
            self._template = t
        return self._template

    def write_static(self, frame: np.ndarray) -> None:
        """Put the static words into ``frame`` (uint8, at least :attr:`size` bytes, 8-byte
        aligned, zero elsewhere)."""
        if len(self.static_at):
            frame[: self.nbytes].view("<u8")[self.static_at] = self.static_words

    @classmethod
    def build(cls, cloths: Sequence[ClothEntry], publications: Sequence[Publication]) -> FramePlan:
        """Lay out a frame, whole-frame numpy over the cloths' and publications' columns: every
        state header, bundle header and bundle entry of the static bytes written as arrays (one
        header packed per kind of state), so a plan of 8192 cloths costs milliseconds, not a
        Python pass per cloth (docs/loadtest.md, tickbench). Raises ValueError on a bad entry
        (unknown encoding, negative range, an id two cloths share, a bundle with an invalid
        cloth id or no cloth, a single with other than one cloth, a cloth in two publications, an
        index out of range). Ids must be distinct: the host encoder keys its predictive streams
        by cloth id, the device's by plan row, and a decoder tells streams and bundle entries
        apart by id alone, so two cloths of one id would code different streams on the two paths
        (the server's cloths have distinct ids: its registry is keyed by them)."""
        cloths = list(cloths)
        return cls._build(_Columns.of(cloths), cloths, publications)

    @classmethod
    def _build(cls, cols: _Columns, cloths: Sequence[ClothEntry], publications: Sequence[Publication]) -> FramePlan:
        publications = list(publications)
        W = encode_layout()
        none = W["ENC_NONE"]
        n_pub = len(publications)
        counts = np.fromiter((len(p.cloths) for p in publications), np.int64, n_pub)
        is_bundle = np.fromiter((p.bundle for p in publications), bool, n_pub)
        members = np.fromiter(itertools.chain.from_iterable(p.cloths for p in publications), np.int64)
        pub_of = np.repeat(np.arange(n_pub), counts)  # each row's publication
        owner = _check(publications, cols, counts, is_bundle, members, pub_of)
        in_bundle = is_bundle[pub_of]
        size = cols.size[members]
        # each row's piece of its publication: a single's state, a bundle's entry header and state
        entry = np.where(in_bundle, _align8(P.BUNDLE_ENTRY_SIZE + cols.id_len[members]), 0)
        piece = np.where(in_bundle, entry + _align8(size), size)
        starts = np.cumsum(counts) - counts  # each publication's first row
        excl = np.cumsum(piece) - piece
        before = excl - excl[starts][pub_of]  # bytes of the rows before in the same publication
        pub_size = np.add.reduceat(piece, starts) if len(members) else np.zeros(n_pub, np.int64)
        pub_size = pub_size + np.where(is_bundle, P.BUNDLE_HEADER_SIZE, 0)
        pub_offset = np.cumsum(_align8(pub_size)) - _align8(pub_size)
        at = int(_align8(pub_size).sum())
        if at >= 2**32:
            raise ValueError(f"a frame of {at} bytes does not fit 32-bit offsets")
        state_at = pub_offset[pub_of] + np.where(in_bundle, P.BUNDLE_HEADER_SIZE + before + entry, 0)
        state_offset = np.full(cols.k, -1, np.int64)
        state_offset[members] = state_at
        # the kernel's table, one row per publication member, in publication order
        pred = cols.enc[members] == P.ENC_PREDICTIVE
        opens = np.zeros(len(members), bool)
        opens[starts] = True
        table = np.zeros((len(members), W["ENC_ROW_WORDS"]), np.uint32)
        table[:, W["ENC_ROW_VBASE"]] = cols.vbase[members]
        table[:, W["ENC_ROW_N"]] = cols.n[members]
        table[:, W["ENC_ROW_ENC"]] = cols.enc[members]
        table[:, W["ENC_ROW_NORMALS"]] = cols.normals[members]
        table[:, W["ENC_ROW_STATE"]] = state_at
        table[:, W["ENC_ROW_BUNDLE"]] = np.where(opens & in_bundle, pub_offset[pub_of], none)
        table[:, W["ENC_ROW_CLOTH"]] = members
        entry_at = state_at - entry + HEADER_OFFSETS["BE_SIZE"]
        table[:, W["ENC_ROW_ENTRY"]] = np.where(pred & in_bundle, entry_at, none)
        table[:, W["ENC_ROW_INVSTEP"]] = np.where(pred, cols.inv_step_bits[members], 0)
        hist = np.where(cols.hbase[members] >= 0, cols.hbase[members], cols.vbase[members])
        table[:, W["ENC_ROW_HIST"]] = np.where(pred, hist, 0)
        # the static bytes
        b = in_bundle
        static = [
            _bundle_headers(pub_offset[is_bundle], counts[is_bundle]),
            _bundle_entries(state_at[b] - entry[b], members[b], size[b], cols),
            _state_headers(state_at, members, cols),
        ]
        static_at = np.concatenate([s[0] for s in static])
        static_words = np.concatenate([s[1] for s in static])
        plan = cls(cloths, publications, pub_offset, pub_size, state_offset, table, static_at, static_words, at)
        plan._cols = cols
        plan.max_n = int(cols.n[members].max(initial=0))
        plan.vertex_end = int((cols.vbase[members] + cols.n[members]).max(initial=0))
        plan.normals = bool(cols.normals[members].any())
        plan._bounds_at = state_at
        plan.predictive = cols.enc == P.ENC_PREDICTIVE
        plan.owner = owner
        plan.is_bundle = is_bundle
        plan._sizes = cols.size
        plan._pred_extra = P.PREDICTIVE_HEADER_SIZE + 6 * cols.n * cols.normals
        return plan

    @classmethod
    def for_roster(cls, roster: Roster, vbase: Sequence[int], counts: Sequence[int]) -> FramePlan:
        """The plan of a tick's roster: its cloths at vertex bases ``vbase`` with ``counts``
        vertices each (frame order), its publications in the roster's order."""
        k = len(roster.ids)
        steps = roster.steps if len(roster.steps) == k else [P.DEFAULT_STEP] * k
        cols = _Columns.checked(
            roster.ids,
            np.fromiter(vbase, np.int64, k),
            np.fromiter(counts, np.int64, k),
            np.fromiter(roster.encodings, np.int64, k),
            np.asarray(roster.normals, bool),
            np.fromiter(steps, np.float64, k),
        )
        pubs = [Publication(key, tuple(idx), bundle) for _, key, idx, bundle in roster.publications()]
        return cls._build(cols, _Entries(cols), pubs)

    def members(self, publications: Sequence[int] | np.ndarray) -> np.ndarray:
        """(m,) int64: the cloths of publications ``publications`` (ascending), in row order."""
        sel = np.asarray(publications, np.int64)
        if (np.diff(sel) <= 0).any():
            raise ValueError("publications must be given in ascending order")
        counts = np.fromiter((len(p.cloths) for p in self.publications), np.int64, len(self.publications))
        return self.encoded[np.repeat(np.isin(np.arange(len(counts)), sel), counts)]  # rows: publication order

    def subset(
        self, publications: Sequence[int] | np.ndarray, keys: Sequence[str], hbase: np.ndarray | None = None
    ) -> tuple[FramePlan, np.ndarray]:
        """A plan of some of this plan's publications (indices ``publications``, ascending, under new
        ``keys``), their cloths in row order with history bases ``hbase`` (one per cloth; None:
        their own), from this plan's columns (no entry made per cloth: devrates.py's decimated
        plans). Returns it and its cloths' indices in this plan."""
        sel = np.asarray(publications, np.int64)
        members = self.members(sel)
        counts = np.fromiter((len(self.publications[j].cloths) for j in sel.tolist()), np.int64, len(sel))
        c = self._columns()
        ids = [c.ids[i] for i in members.tolist()]
        m = members
        cols = _Columns.checked(ids, c.vbase[m], c.n[m], c.enc[m], c.normals[m], c.step[m], hbase)
        at = np.cumsum(counts) - counts
        pubs = [
            Publication(key, tuple(range(a, a + n)), self.publications[j].bundle)
            for key, j, a, n in zip(keys, sel.tolist(), at.tolist(), counts.tolist(), strict=True)
        ]
        return FramePlan._build(cols, _Entries(cols), pubs), members

    @property
    def entry_header_sizes(self) -> np.ndarray:
        """(k,) int64: each plan cloth's bundle entry header size (P.bundle_entry_header_size)."""
        return _align8(P.BUNDLE_ENTRY_SIZE + self._columns().id_len)

    def time_offsets(self, state_at: np.ndarray | None = None, pub_at: np.ndarray | None = None) -> np.ndarray:
        """Byte offsets of every server-time field of the frame (each encoded state's, each
        bundle's): of the plan's layout (computed once), or of a compacted frame whose states
        and publications lie at ``state_at`` (k,) and ``pub_at`` (P,)."""
        if state_at is not None and pub_at is not None:
            states = state_at[self.encoded] + HEADER_OFFSETS["ST_TIME"]
            return np.concatenate([states, pub_at[self.is_bundle] + HEADER_OFFSETS["BH_TIME"]])
        if self._time_at is None:
            states = self._bounds_at + HEADER_OFFSETS["ST_TIME"]
            bundles = self.pub_offset[self.is_bundle] + HEADER_OFFSETS["BH_TIME"]
            self._time_at = np.concatenate([states, bundles]).astype(np.int64)
        return self._time_at

    @property
    def encoded(self) -> np.ndarray:
        """Plan cloth indices that are encoded (in some publication), in row order."""
        return self.rows[:, encode_layout()["ENC_ROW_CLOTH"]].astype(np.int64)


def _align8(n: np.ndarray) -> np.ndarray:
    """P.align8 of every element."""
    return (n + 7) & ~7


def _kinds(*columns: np.ndarray) -> tuple[list[tuple[int, ...]], np.ndarray]:
    """The distinct rows of some integer columns (each row's values as a tuple) and each row's
    index among them: a plan's cloths are of few kinds, so a plan packs one header per kind."""
    if not len(columns[0]):
        return [], np.zeros(0, np.int64)
    codes = np.zeros(len(columns[0]), np.int64)
    for col in columns:  # factorised one column at a time (no row-wise sort of wide keys)
        values, code = np.unique(col, return_inverse=True)
        codes = codes * len(values) + code.reshape(-1)
        codes = np.unique(codes, return_inverse=True)[1].reshape(-1)
    first = np.unique(codes, return_index=True)[1]
    return [tuple(int(col[i]) for col in columns) for i in first.tolist()], codes


_ID_CHARS = np.zeros(256, bool)  # the bytes a valid id is made of (P.valid_id has the last word)
_ID_CHARS[np.frombuffer(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789_.-", np.uint8)] = True


@dataclass(eq=False)
class _Columns:
    """A plan's cloths as arrays (one pass over the entries per field), checked."""

    k: int
    ids: list[str]
    vbase: np.ndarray  # (k,) int64
    n: np.ndarray  # (k,) int64
    enc: np.ndarray  # (k,) int64
    normals: np.ndarray  # (k,) bool
    step: np.ndarray  # (k,) float64
    id_len: np.ndarray  # (k,) int64: characters of each id
    id_bytes: np.ndarray  # every id's bytes back to back (non-ASCII characters as b"?")
    size: np.ndarray  # (k,) int64: each state's (largest) size
    inv_step_bits: np.ndarray  # (k,) uint32: float32 bits of 1 / step (predictive.inverse_step)
    hbase: np.ndarray  # (k,) int64: first vertex in the encoder's history, -1: vbase

    @classmethod
    def of(cls, cloths: list[ClothEntry]) -> _Columns:
        k = len(cloths)
        ids = [c.cloth for c in cloths]
        vbase = np.fromiter((c.vbase for c in cloths), np.int64, k)
        n = np.fromiter((c.n for c in cloths), np.int64, k)
        enc = np.fromiter((c.encoding for c in cloths), np.int64, k)
        normals = np.fromiter((c.normals for c in cloths), bool, k)
        step = np.fromiter((c.step for c in cloths), np.float64, k)
        hbase = np.fromiter((c.hbase for c in cloths), np.int64, k)
        return cls.checked(ids, vbase, n, enc, normals, step, hbase)

    @classmethod
    def checked(
        cls,
        ids: list[str],
        vbase: np.ndarray,
        n: np.ndarray,
        enc: np.ndarray,
        normals: np.ndarray,
        step: np.ndarray,
        hbase: np.ndarray | None = None,
    ) -> _Columns:
        """The columns of ``len(ids)`` cloths (``hbase`` None: every cloth's history at its
        ``vbase``); raises ValueError on the first bad one."""
        k = len(ids)
        if hbase is None:
            hbase = np.full(k, -1, np.int64)
        known = np.isin(enc, np.fromiter(P.ENCODING_NAMES, np.int64))
        pred = enc == P.ENC_PREDICTIVE
        bad_step = pred & ~((step >= P.STEP_RANGE[0]) & (step <= P.STEP_RANGE[1]))
        bad_range = (vbase < 0) | (n < 0) | (vbase + n >= 2**32)
        wrong = np.flatnonzero(~known | bad_step | bad_range)
        if len(wrong):
            i = int(wrong[0])
            if not known[i]:
                raise ValueError(f"cloth {i} ({ids[i]!r}): unknown encoding {int(enc[i])}")
            if bad_step[i]:
                raise ValueError(f"cloth {i} ({ids[i]!r}): step {float(step[i])} out of {P.STEP_RANGE}")
            raise ValueError(f"cloth {i} ({ids[i]!r}): bad vertex range {int(vbase[i])}+{int(n[i])}")
        if len(set(ids)) != k:  # a stream, a key and a bundle entry are a cloth id's (0.2 ms at 8192)
            first: dict[str, int] = {}
            for j, cid in enumerate(ids):
                if (i := first.setdefault(cid, j)) != j:
                    raise ValueError(f"cloth {j} ({cid!r}): the id of cloth {i} too")
        id_len = np.fromiter(map(len, ids), np.int64, k)
        id_bytes = np.frombuffer("".join(ids).encode("ascii", "replace"), np.uint8)
        # sizes and inverse steps: one call per distinct kind of cloth
        kinds, inverse = _kinds(n, enc, normals)
        size = np.array([state_size(a, e, bool(m)) for a, e, m in kinds], np.int64)[inverse]
        inv_step_bits = np.zeros(k, np.uint32)
        if pred.any():
            steps, inverse = np.unique(step[pred], return_inverse=True)
            inv = np.array([P.inverse_step(float(s)) for s in steps], np.float32).view(np.uint32)
            inv_step_bits[pred] = inv[inverse.reshape(-1)]
        return cls(k, ids, vbase, n, enc, normals, step, id_len, id_bytes, size, inv_step_bits, hbase)

    def entry(self, i: int) -> ClothEntry:
        return ClothEntry(
            self.ids[i],
            int(self.vbase[i]),
            int(self.n[i]),
            int(self.enc[i]),
            bool(self.normals[i]),
            float(self.step[i]),
            int(self.hbase[i]),
        )

    def invalid_ids(self, idx: np.ndarray) -> np.ndarray:
        """Those of cloths ``idx`` whose id is not a valid one (P.valid_id): whole arrays, and
        P.valid_id itself only for ids that look wrong."""
        start = np.cumsum(self.id_len) - self.id_len
        odd = ~_ID_CHARS[self.id_bytes]
        odd_ids = np.zeros(self.k, bool)
        if odd.any():
            odd_ids[np.searchsorted(start, np.flatnonzero(odd), side="right") - 1] = True
        ln = self.id_len[idx]
        maybe = idx[odd_ids[idx] | (ln < 1) | (ln > 64)]
        return np.array([i for i in maybe.tolist() if not P.valid_id(self.ids[i])], np.int64)


class _Entries(Sequence[ClothEntry]):
    """A plan's cloths as :class:`ClothEntry` items made when asked for (a plan of 8192 cloths
    made from a roster's columns makes none on the tick thread)."""

    def __init__(self, cols: _Columns) -> None:
        self._cols = cols

    def __len__(self) -> int:
        return self._cols.k

    @overload
    def __getitem__(self, i: int) -> ClothEntry: ...

    @overload
    def __getitem__(self, i: slice) -> list[ClothEntry]: ...

    def __getitem__(self, i: int | slice) -> ClothEntry | list[ClothEntry]:
        if isinstance(i, slice):
            return [self._cols.entry(j) for j in range(*i.indices(self._cols.k))]
        if not -self._cols.k <= i < self._cols.k:
            raise IndexError(i)
        return self._cols.entry(i % self._cols.k)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]


def _check(
    publications: list[Publication],
    cols: _Columns,
    counts: np.ndarray,
    is_bundle: np.ndarray,
    members: np.ndarray,
    pub_of: np.ndarray,
) -> np.ndarray:
    """Each cloth's publication ((k,) int64, -1 for none); raises ValueError on the first bad
    publication (in publication order)."""
    k = cols.k
    problems: list[tuple[int, str]] = []  # (publication, message): the first one is raised
    for p in np.flatnonzero(counts == 0)[:1].tolist():
        problems.append((p, f"publication {p} ({publications[p].key!r}) has no cloth"))
    for p in np.flatnonzero(~is_bundle & (counts != 1))[:1].tolist():
        problems.append((p, f"single publication {p} ({publications[p].key!r}) has {counts[p]} cloths"))
    out = np.flatnonzero((members < 0) | (members >= k))
    if len(out):
        p, i = int(pub_of[out[0]]), int(members[out[0]])
        problems.append((p, f"publication {p} ({publications[p].key!r}) names cloth {i} of {k}"))
    else:
        order = np.argsort(members, kind="stable")
        again = np.flatnonzero(members[order][1:] == members[order][:-1])
        if len(again):  # a cloth named twice: its first repeat, in row order, against its first naming
            rows = order[again + 1]
            j = int(np.argmin(rows))
            later, earlier = int(rows[j]), int(order[again[j]])
            i = int(members[later])
            a, b = int(pub_of[earlier]), int(pub_of[later])
            problems.append((b, f"cloth {i} ({cols.ids[i]!r}) is in publications {a} and {b}"))
        bad = cols.invalid_ids(members[is_bundle[pub_of]])
        if len(bad):
            row = int(np.flatnonzero(np.isin(members, bad) & is_bundle[pub_of])[0])
            p, i = int(pub_of[row]), int(members[row])
            problems.append((p, f"bundle {publications[p].key!r}: invalid cloth id {cols.ids[i]!r}"))
    if problems:
        raise ValueError(min(problems, key=lambda pm: pm[0])[1])
    owner = np.full(k, -1, np.int64)
    owner[members] = pub_of
    return owner


Words = tuple[np.ndarray, np.ndarray]  # (word index (m,) int64, value (m,) uint64) of a frame's static bytes


def _same(at: np.ndarray, header: bytes | bytearray) -> Words:
    """The same 8-byte aligned ``header`` at every byte offset ``at``."""
    words = np.frombuffer(bytes(header), "<u8")
    idx = (at >> 3)[:, None] + np.arange(len(words))
    return idx.reshape(-1), np.broadcast_to(words, idx.shape).reshape(-1)


def _concat(parts: list[Words]) -> Words:
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.uint64)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _bundle_headers(at: np.ndarray, counts: np.ndarray) -> Words:
    """Every bundle's header (tick and time 0): one packed per distinct count."""
    parts = []
    for count in np.unique(counts).tolist():
        head = bytearray(P.BUNDLE_HEADER_SIZE)
        P.pack_bundle_header(head, 0, 0, count)
        parts.append(_same(at[counts == count], head))
    return _concat(parts)


def _bundle_entries(at: np.ndarray, idx: np.ndarray, sizes: np.ndarray, cols: _Columns) -> Words:
    """The entry headers of bundle members ``idx`` at ``at``: their fixed part, then their id
    and its zeros up to the state."""
    if not len(idx):
        return _concat([])
    ln = cols.id_len[idx]
    fixed = np.zeros(len(idx), P.BUNDLE_ENTRY_DTYPE)
    fixed["header_size"] = _align8(P.BUNDLE_ENTRY_SIZE + ln)
    fixed["id_length"] = ln
    fixed["state_size"] = sizes
    padded = _align8(ln)  # each id's bytes with their zeros, back to back
    ids = np.zeros(int(padded.sum()), np.uint8)
    start = np.cumsum(cols.id_len) - cols.id_len
    within = np.arange(int(ln.sum())) - np.repeat(np.cumsum(ln) - ln, ln)
    ids[np.repeat(np.cumsum(padded) - padded, ln) + within] = cols.id_bytes[np.repeat(start[idx], ln) + within]
    nw = padded >> 3
    id_at = (
        np.repeat((at + P.BUNDLE_ENTRY_SIZE) >> 3, nw) + np.arange(int(nw.sum())) - np.repeat(np.cumsum(nw) - nw, nw)
    )
    return np.concatenate([at >> 3, id_at]), np.concatenate([fixed.view("<u8"), ids.view("<u8")])


def _state_headers(at: np.ndarray, idx: np.ndarray, cols: _Columns) -> Words:
    """The static state headers of cloths ``idx`` at ``at``: one packed per distinct (encoding,
    vertex count, step); a predictive state's with its step and a stride of 1."""
    if not len(idx):
        return _concat([])
    pred = cols.enc[idx] == P.ENC_PREDICTIVE
    step32 = np.where(pred, cols.step[idx], 0.0).astype(np.float32)
    kinds, inverse = _kinds(cols.enc[idx], cols.n[idx], step32.view(np.uint32))
    parts = []
    for j, (enc, n, bits) in enumerate(kinds):
        if enc == P.ENC_PREDICTIVE:
            head = bytearray(P.PREDICTIVE_HEADER_SIZE)
            P.pack_state_header(head, 0, enc, 0, n, 0, 0, (0.0,) * 3, (0.0,) * 3, P.PREDICTIVE_HEADER_SIZE)
            step = float(np.array(bits, np.uint32).view(np.float32))
            P.PREDICTIVE_HEADER.pack_into(head, P.STATE_HEADER_SIZE, step, 0, 1, 0, 0, 0)
        else:
            head = bytearray(P.STATE_HEADER_SIZE)
            P.pack_state_header(head, 0, enc, 0, n, 0, 0, (0.0,) * 3, (0.0,) * 3)
        parts.append(_same(at[inverse == j], head))
    return _concat(parts)


def take_bytes(data: np.ndarray, at: np.ndarray, n: int) -> np.ndarray:
    """(len(at), n) uint8: ``n`` bytes at each offset ``at`` of the frame ``data``; whole 8-byte
    words when the offsets and ``n`` are multiples of 8 (a header's fields in a frame of
    8-byte aligned states: 8x fewer indices than bytes)."""
    if n % 8 == 0 and len(data) % 8 == 0 and not (at % 8).any():
        words = data.view("<u8")[(at >> 3)[:, None] + np.arange(n >> 3)]
        return words.view(np.uint8).reshape(len(at), n)
    return data[at[:, None] + np.arange(n)]


def put_words(data: np.ndarray, at: np.ndarray, value: np.ndarray) -> None:
    """Write the 8 bytes ``value`` at each offset ``at`` of the frame ``data`` (one word each when
    the offsets are 8-byte aligned)."""
    if len(data) % 8 == 0 and not (at % 8).any():
        data.view("<u8")[at >> 3] = value.view("<u8")[0]
    else:
        data[(at[:, None] + np.arange(8)).ravel()] = np.tile(value, len(at))


def _find(packed: bytes, marker: bytes) -> int:
    at = packed.find(marker)
    assert at >= 0 and packed.find(marker, at + 1) < 0
    return at


def _header_offsets() -> dict[str, int]:
    """Byte offsets of the dynamic header fields, found by packing marker values with
    drape.client.protocol's own header writers (the one copy of the layout); passed to
    encode.cl as -D options."""
    st = bytearray(P.STATE_HEADER_SIZE)
    P.pack_state_header(st, 0, 0, 0xA5C3, 0, 0x1122334455667788, 0x99AABBCCDDEEFF10, (1.5, 2.5, 3.5), (4.5, 5.5, 6.5))
    bh = bytearray(P.BUNDLE_HEADER_SIZE)
    P.pack_bundle_header(bh, 0x1122334455667788, 0x99AABBCCDDEEFF10, 0)
    ph = bytearray(P.PREDICTIVE_HEADER.size)
    P.PREDICTIVE_HEADER.pack_into(ph, 0, 0.0, 0xA5, 0, 0x1122334455667788, 0x99AABBCCDDEEFF10, 0x5A6B7C8D)
    be = bytearray(P.BUNDLE_ENTRY_SIZE + 8)
    P.pack_bundle_entry(be, 0, "x", 0x5A6B7C8D)
    f32 = lambda x: np.float32(x).tobytes()  # noqa: E731
    return {
        "ST_FLAGS": _find(bytes(st), (0xA5C3).to_bytes(2, "little")),
        "ST_TICK": _find(bytes(st), (0x1122334455667788).to_bytes(8, "little")),
        "ST_TIME": _find(bytes(st), (0x99AABBCCDDEEFF10).to_bytes(8, "little")),
        "ST_MIN": _find(bytes(st), f32(1.5) + f32(2.5) + f32(3.5)),
        "ST_MAX": _find(bytes(st), f32(4.5) + f32(5.5) + f32(6.5)),
        "ST_DATA": P.STATE_HEADER_SIZE,
        "BH_TICK": _find(bytes(bh), (0x1122334455667788).to_bytes(8, "little")),
        "BH_TIME": _find(bytes(bh), (0x99AABBCCDDEEFF10).to_bytes(8, "little")),
        "PH_ORDER": P.STATE_HEADER_SIZE + _find(bytes(ph), bytes([0xA5])),
        "PH_REF1": P.STATE_HEADER_SIZE + _find(bytes(ph), (0x1122334455667788).to_bytes(8, "little")),
        "PH_REF2": P.STATE_HEADER_SIZE + _find(bytes(ph), (0x99AABBCCDDEEFF10).to_bytes(8, "little")),
        "PH_SIZE": P.STATE_HEADER_SIZE + _find(bytes(ph), (0x5A6B7C8D).to_bytes(4, "little")),
        "PH_DATA": P.PREDICTIVE_HEADER_SIZE,
        "BE_SIZE": _find(bytes(be), (0x5A6B7C8D).to_bytes(4, "little")),
        "ENC_PREDICTIVE": P.ENC_PREDICTIVE,
        "Q_CLAMP": 1 << 27,
        "Q_LIMIT": P.Q_LIMIT,
        "FLAG_NORMALS": P.FLAG_NORMALS,
        "FLOAT16_MAX": int(P.FLOAT16_MAX),
        "QUANT_MAX": P.QUANT_MAX,
        "SNORM_MAX": P.SNORM_MAX,
    }


HEADER_OFFSETS = _header_offsets()
