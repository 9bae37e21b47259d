"""The layout of a device-encoded frame: :class:`FramePlan` (where every publication and state
lies in the packed buffer, and the frame's static bytes), its inputs (:class:`ClothEntry`,
:class:`Publication`), the kernel's row layout (kernels/encode.cl's ``ENC_*``) and the dynamic
header fields' offsets (:data:`HEADER_OFFSETS`, found with drape.client.protocol's own writers).
encode.py's DeviceEncoder runs a plan on the device; see its docstring.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from drape.client import protocol as P

from .platforms import kernel_dir

SOURCE = "encode.cl"


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


@dataclass(frozen=True)
class ClothEntry:
    """One cloth of a plan: its id, vertex range ``[vbase, vbase + n)`` in the world's float4
    position (and normal) buffers, protocol encoding id, whether normals follow and (predictive,
    1.5) its grid step in metres and its first vertex in the encoder's history (1.8: a decimated
    streams' encoder keeps its own, for its cloths only; -1: ``vbase``)."""

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

    cloths: list[ClothEntry]
    publications: list[Publication]
    pub_offset: np.ndarray  # (P,) int64, multiples of 8
    pub_size: np.ndarray  # (P,) int64
    state_offset: np.ndarray  # (k,) int64 per plan cloth, -1 when it is in no publication
    rows: np.ndarray  # (R, ENC_ROW_WORDS) uint32: the kernel's table, one row per encoded cloth
    template: np.ndarray  # (size,) uint8: the static bytes of the whole frame
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

    @property
    def size(self) -> int:
        return int(self.template.size)

    @classmethod
    def build(cls, cloths: Sequence[ClothEntry], publications: Sequence[Publication]) -> FramePlan:
        """Lay out a frame. Raises ValueError on a bad entry (unknown encoding, negative range,
        a bundle with an invalid cloth id or no cloth, a single with other than one cloth, a
        cloth in two publications, an index out of range)."""
        cloths, publications = list(cloths), list(publications)
        k = len(cloths)
        for i, c in enumerate(cloths):
            if c.encoding not in P.ENCODING_NAMES:
                raise ValueError(f"cloth {i} ({c.cloth!r}): unknown encoding {c.encoding}")
            if c.encoding == P.ENC_PREDICTIVE and not P.STEP_RANGE[0] <= c.step <= P.STEP_RANGE[1]:
                raise ValueError(f"cloth {i} ({c.cloth!r}): step {c.step} out of {P.STEP_RANGE}")
            if c.vbase < 0 or c.n < 0 or c.vbase + c.n >= 2**32:
                raise ValueError(f"cloth {i} ({c.cloth!r}): bad vertex range {c.vbase}+{c.n}")
        owner = np.full(k, -1, np.int64)
        state_offset = np.full(k, -1, np.int64)
        pub_offset = np.zeros(len(publications), np.int64)
        pub_size = np.zeros(len(publications), np.int64)
        W = encode_layout()
        none = W["ENC_NONE"]
        rows: list[list[int]] = []
        parts: list[tuple[int, Publication]] = []
        at = 0
        for p, pub in enumerate(publications):
            idx = list(pub.cloths)
            if not idx:
                raise ValueError(f"publication {p} ({pub.key!r}) has no cloth")
            if not pub.bundle and len(idx) != 1:
                raise ValueError(f"single publication {p} ({pub.key!r}) has {len(idx)} cloths")
            for i in idx:
                if not 0 <= i < k:
                    raise ValueError(f"publication {p} ({pub.key!r}) names cloth {i} of {k}")
                if owner[i] >= 0:
                    raise ValueError(f"cloth {i} ({cloths[i].cloth!r}) is in publications {owner[i]} and {p}")
                owner[i] = p
                if pub.bundle and not P.valid_id(cloths[i].cloth):
                    raise ValueError(f"bundle {pub.key!r}: invalid cloth id {cloths[i].cloth!r}")
            sizes = [state_size(cloths[i].n, cloths[i].encoding, cloths[i].normals) for i in idx]
            if pub.bundle:
                size = P.bundle_size((cloths[i].cloth, s) for i, s in zip(idx, sizes, strict=True))
                s_at = at + P.BUNDLE_HEADER_SIZE
                for j, (i, s) in enumerate(zip(idx, sizes, strict=True)):
                    eh = P.bundle_entry_header_size(cloths[i].cloth)
                    s_at += eh
                    state_offset[i] = s_at
                    rows.append(
                        cls._row(cloths[i], s_at, at if j == 0 else none, i, s_at - eh + HEADER_OFFSETS["BE_SIZE"])
                    )
                    s_at += P.align8(s)
            else:
                size = sizes[0]
                state_offset[idx[0]] = at
                rows.append(cls._row(cloths[idx[0]], at, none, idx[0], none))
            pub_offset[p], pub_size[p] = at, size
            parts.append((at, pub))
            at = P.align8(at + size)
        if at >= 2**32:
            raise ValueError(f"a frame of {at} bytes does not fit 32-bit offsets")
        template = np.zeros(at, np.uint8)
        buf = memoryview(template).cast("B")  # type: ignore[arg-type]
        for off, pub in parts:
            if pub.bundle:
                P.pack_bundle_header(buf[off:], 0, 0, len(pub.cloths))
                for i in pub.cloths:
                    c = cloths[i]
                    so = int(state_offset[i])
                    e = so - P.bundle_entry_header_size(c.cloth)
                    P.pack_bundle_entry(buf, e, c.cloth, state_size(c.n, c.encoding, c.normals))
            for i in pub.cloths:
                c = cloths[i]
                so = int(state_offset[i])
                if c.encoding == P.ENC_PREDICTIVE:  # its static fields: the step, a stride of 1
                    hs = P.PREDICTIVE_HEADER_SIZE
                    P.pack_state_header(buf, so, c.encoding, 0, c.n, 0, 0, (0.0,) * 3, (0.0,) * 3, hs)
                    P.PREDICTIVE_HEADER.pack_into(
                        buf, so + P.STATE_HEADER_SIZE, float(np.float32(c.step)), 0, 1, 0, 0, 0
                    )
                else:
                    P.pack_state_header(buf, so, c.encoding, 0, c.n, 0, 0, (0.0,) * 3, (0.0,) * 3)
        table = np.array(rows, np.uint32).reshape(-1, W["ENC_ROW_WORDS"])
        enc_idx = table[:, W["ENC_ROW_CLOTH"]].astype(np.int64)
        plan = cls(cloths, publications, pub_offset, pub_size, state_offset, table, template)
        plan.max_n = int(table[:, W["ENC_ROW_N"]].max(initial=0))
        ends = table[:, W["ENC_ROW_VBASE"]].astype(np.int64) + table[:, W["ENC_ROW_N"]]
        plan.vertex_end = int(ends.max(initial=0))
        plan.normals = bool(table[:, W["ENC_ROW_NORMALS"]].any())
        plan._bounds_at = state_offset[enc_idx] if len(enc_idx) else np.zeros(0, np.int64)
        plan.predictive = np.array([c.encoding == P.ENC_PREDICTIVE for c in cloths], bool)
        plan.owner = owner
        plan.is_bundle = np.array([p.bundle for p in publications], bool)
        plan._sizes = np.array([state_size(c.n, c.encoding, c.normals) for c in cloths], np.int64)
        plan._pred_extra = np.array([P.PREDICTIVE_HEADER_SIZE + 6 * c.n * c.normals for c in cloths], np.int64)
        return plan

    @staticmethod
    def _row(c: ClothEntry, state_at: int, bundle_at: int, index: int, entry_at: int) -> list[int]:
        W = encode_layout()
        row = [0] * W["ENC_ROW_WORDS"]
        row[W["ENC_ROW_VBASE"]] = c.vbase
        row[W["ENC_ROW_N"]] = c.n
        row[W["ENC_ROW_ENC"]] = c.encoding
        row[W["ENC_ROW_NORMALS"]] = int(c.normals)
        row[W["ENC_ROW_STATE"]] = state_at
        row[W["ENC_ROW_BUNDLE"]] = bundle_at
        row[W["ENC_ROW_CLOTH"]] = index
        if c.encoding == P.ENC_PREDICTIVE:
            row[W["ENC_ROW_ENTRY"]] = entry_at
            row[W["ENC_ROW_INVSTEP"]] = int(np.array(P.inverse_step(c.step), np.float32).view(np.uint32))
            row[W["ENC_ROW_HIST"]] = c.hbase if c.hbase >= 0 else c.vbase
        else:
            row[W["ENC_ROW_ENTRY"]] = W["ENC_NONE"]
        return row

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
