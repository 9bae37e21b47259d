"""A device-encoded frame compacted on the device (kernels/compact.cl), for plans with predictive
states (protocol 1.5), whose size varies per tick: encode.py's ``encode_frame`` writes each
state into a slot of its largest size, then two launches on the same queue (``compact_scan``:
the states' real sizes and a one-work-group prefix sum of the pieces' lengths; ``compact_copy``:
every piece to its offset) write every publication's wire bytes back to back into a second
device buffer. The host copies that buffer's first bytes (a guess from the recent frames' sizes,
the rest copied once the index is read if the guess was short) and a small index
(:class:`FrameIndex`): where each publication and each state lies in it. No per-state work on
the host: a publication is a slice.

:class:`Pieces` is a plan's table (one piece per encoded cloth, in the plan's row order, which
is the publications' order: the bytes in front of its state, a bundle's header and its entry's
header, then the state padded to 8 bytes); :class:`Compactor` runs it on a device.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyopencl as cl

from drape.client import protocol as P

from . import reuse
from .buffers import map_pinned
from .device import Device
from .frameplan import HEADER_OFFSETS, FramePlan, encode_layout
from .platforms import kernel_dir

log = logging.getLogger(__name__)

MF = cl.mem_flags
SOURCE = "compact.cl"


@lru_cache(maxsize=1)
def compact_layout() -> dict[str, int]:
    """The ``#define CMP_ROW_* int`` constants of kernels/compact.cl (the one copy of its table)."""
    text = (kernel_dir() / SOURCE).read_text()
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^#define\s+(CMP_ROW_\w+)\s+(\d+)\b", text, re.M)}


@dataclass(eq=False)
class Pieces:
    """A plan's pieces: the kernel's table and what the host needs to read a compacted frame."""

    table: np.ndarray  # (R, CMP_ROW_WORDS) uint32
    prefix: np.ndarray  # (R,) int64: bytes in front of each state
    cloth: np.ndarray  # (R,) int64: each row's plan cloth
    first: np.ndarray  # (P,) int64: each publication's first row
    last: np.ndarray  # (P,) int64: and its last
    bundle: np.ndarray  # (P,) bool
    k: int  # plan cloths

    @classmethod
    def build(cls, plan: FramePlan) -> Pieces:
        W, C = encode_layout(), compact_layout()
        rows = plan.rows
        n_rows = len(rows)
        cloth = rows[:, W["ENC_ROW_CLOTH"]].astype(np.int64)
        state = rows[:, W["ENC_ROW_STATE"]].astype(np.int64)
        # each publication's rows are consecutive, in the publications' order (FramePlan.build)
        counts = np.array([len(p.cloths) for p in plan.publications], np.int64)
        last = np.cumsum(counts) - 1
        first = last - counts + 1
        opens = np.zeros(n_rows, bool)
        opens[first] = True
        pub_of_row = np.repeat(np.arange(len(counts)), counts)
        bundle = plan.is_bundle
        entry = plan.entry_header_sizes
        prefix = np.where(bundle[pub_of_row], entry[cloth], 0) if n_rows else np.zeros(0, np.int64)
        prefix = prefix + np.where(opens & bundle[pub_of_row], P.BUNDLE_HEADER_SIZE, 0)
        pred = plan.predictive[cloth]
        sizes = plan._sizes[cloth]
        table = np.zeros((n_rows, C["CMP_ROW_WORDS"]), np.uint32)
        table[:, C["CMP_ROW_SRC"]] = state - prefix
        table[:, C["CMP_ROW_PREFIX"]] = prefix
        table[:, C["CMP_ROW_SIZE"]] = np.where(pred, plan._pred_extra[cloth], sizes)
        table[:, C["CMP_ROW_PRED"]] = pred
        if ((state - prefix) % 8).any() or (prefix % 8).any():
            raise ValueError("a piece of the frame is not 8-byte aligned")
        return cls(table, prefix.astype(np.int64), cloth, first, last, bundle, len(plan.cloths))

    def frame_index(self, index: np.ndarray) -> FrameIndex:
        """Where things lie in a compacted frame whose kernel index (``2 R + 1`` uint32) is given."""
        r = len(self.cloth)
        at = index[: r + 1].astype(np.int64)
        size = index[r + 1 :].astype(np.int64)
        state_at = np.full(self.k, -1, np.int64)
        state_at[self.cloth] = at[:r] + self.prefix
        pub_at = at[self.first]
        pub_len = np.where(self.bundle, at[self.last + 1] - pub_at, size[self.first])
        return FrameIndex(int(at[r]), state_at, pub_at, pub_len)


@dataclass(eq=False)
class FrameIndex:
    """A compacted frame's index: its size, each plan cloth's state offset (-1: in no
    publication), each publication's offset and length."""

    size: int
    state_at: np.ndarray  # (k,) int64
    pub_at: np.ndarray  # (P,) int64
    pub_len: np.ndarray  # (P,) int64

    def views(self, data: np.ndarray) -> list[memoryview]:
        """Each publication's bytes in the compacted frame ``data``, views in plan order."""
        mv = memoryview(data).cast("B")  # type: ignore[arg-type]
        return [mv[a : a + n] for a, n in zip(self.pub_at.tolist(), self.pub_len.tolist(), strict=True)]


class Compactor:
    """compact.cl on ``dev`` for one plan at a time (a part the DeviceEncoder owns)."""

    def __init__(self, dev: Device, local_size: int | None = None) -> None:
        self.dev = dev
        want = local_size or (256 if dev.info.is_gpu else 8)
        wg = 1
        while wg * 2 <= min(want, dev.info.max_work_group):
            wg *= 2
        self.wg = wg
        self.copy_wg = min(64 if dev.info.is_gpu else 1, dev.info.max_work_group)
        self.pieces: Pieces | None = None
        self._table: cl.Buffer | None = None
        self._index: cl.Buffer | None = None
        self.packed: cl.Buffer | None = None
        self._packed = reuse.ReusedBuffer(dev.ctx, MF.READ_WRITE)  # kept across plans while it fits
        self._recent: list[float] = []  # the last frames' compacted bytes per piece (the copy's guess)
        self.copied = 0  # bytes the last frame finished took from the device (its guess and the rest)
        self.frames = 0  # frames compacted
        self.short = 0  # of which the guess was short (a second copy)
        self._scan: cl.Kernel | None = None
        self._copy: cl.Kernel | None = None
        self.scan_event: cl.Event | None = None
        self.copy_event: cl.Event | None = None
        self.index_event: cl.Event | None = None

    def _options(self) -> list[str]:
        return [f"-DCMP_WG={self.wg}", f"-DPH_SIZE={HEADER_OFFSETS['PH_SIZE']}"]

    def build(self) -> None:
        """Build the program now (the tick thread never compiles)."""
        self.dev.program(self._options(), source=SOURCE)

    def set_plan(self, plan: FramePlan, frame: cl.Buffer) -> Pieces:
        """Upload ``plan``'s pieces, size the buffers and bind the kernels to ``frame`` (the
        encoder's output buffer); returns the pieces. Everything is made before anything is
        replaced."""
        pieces = Pieces.build(plan)
        prg = self.dev.program(self._options(), source=SOURCE)
        ctx = self.dev.ctx
        table_host = pieces.table if pieces.table.size else np.zeros((1, compact_layout()["CMP_ROW_WORDS"]), np.uint32)
        table = cl.Buffer(ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(table_host))
        index = cl.Buffer(ctx, MF.READ_WRITE, 4 * (2 * len(pieces.cloth) + 1))
        packed = self._packed.get(max(plan.size, 8))  # its last frame's bytes are read by then
        rows = np.uint32(len(pieces.cloth))
        scan, copy = cl.Kernel(prg, "compact_scan"), cl.Kernel(prg, "compact_copy")
        scan.set_args(rows, table, frame, index)
        copy.set_args(rows, table, frame, index, packed)
        self._table, self._index, self.packed, self._scan, self._copy = table, index, packed, scan, copy
        self.pieces = pieces
        return pieces

    @property
    def buffers_made(self) -> int:
        """Compacted-frame buffers allocated so far (kept across plans while they fit)."""
        return self._packed.made

    def host_index(self, n: int | None = None) -> np.ndarray:
        """A host array for one frame's index (or of ``n`` entries, one kept for larger plans),
        in pinned memory (ALLOC_HOST_PTR, mapped for good; its mapping keeps the buffer): a
        driver may copy into pageable memory synchronously, which would make the enqueue wait
        for the frame."""
        assert self.pieces is not None
        n = 2 * len(self.pieces.cloth) + 1 if n is None else n
        try:
            _, arr = map_pinned(self.dev, n, np.uint32)  # the mapping keeps the buffer
            return arr
        except cl.Error as e:  # a driver without mappable host memory: plain numpy
            log.debug("no mapped host buffer for the index (%s): plain host memory", e)
            return np.zeros(n, np.uint32)

    def guess(self, size: int) -> int:
        """Bytes to copy before the index is known: the largest of the last frames' bytes per
        piece times this plan's pieces, and a quarter more (kept across plans: cloths coming and
        going do not make the next frame copy its slots whole); all of ``size`` at first."""
        if not self._recent or self.pieces is None:
            return size
        return min(size, P.align8(int(max(self._recent) * len(self.pieces.cloth) * 1.25) + 4096))

    def enqueue(
        self,
        queue: cl.CommandQueue,
        host_data: np.ndarray,
        host_index: np.ndarray,
        size: int,
        wait_for: Sequence[cl.Event] | None,
    ) -> tuple[cl.Event, int]:
        """Compact the encoder's frame (``size`` bytes of slots) and start copying the index and
        the compacted frame's first bytes into ``host_index`` and ``host_data``. Returns the last
        copy's event and how many bytes it copies."""
        pieces = self.pieces
        assert pieces is not None and self._scan is not None and self._copy is not None
        assert self._index is not None and self.packed is not None
        rows = len(pieces.cloth)
        wait = list(wait_for or []) or None
        ev = cl.enqueue_nd_range_kernel(queue, self._scan, (self.wg,), (self.wg,), wait_for=wait)
        self.scan_event = ev
        if rows:
            ev = cl.enqueue_nd_range_kernel(queue, self._copy, (rows * self.copy_wg,), (self.copy_wg,), wait_for=[ev])
        self.copy_event = ev
        # kept: pyopencl's event of a copy into host memory waits for it when it is dropped
        self.index_event = cl.enqueue_copy(queue, host_index, self._index, is_blocking=False, wait_for=[ev])
        n = self.guess(size)
        ev = cl.enqueue_copy(queue, host_data[:n], self.packed, is_blocking=False, wait_for=[ev])
        self.frames += 1
        return ev, n

    def finish(self, host_data: np.ndarray, host_index: np.ndarray, copied: int) -> FrameIndex:
        """The index of a frame whose copies are done; the rest of its bytes copied now when the
        guess was short (blocking; ``packed`` must still hold this frame)."""
        assert self.pieces is not None and self.packed is not None
        fi = self.pieces.frame_index(host_index)
        self._recent = [*self._recent[-3:], fi.size / max(len(self.pieces.cloth), 1)]
        self.copied = max(copied, fi.size)
        if fi.size > copied:
            self.short += 1
            cl.enqueue_copy(
                self.dev.queue, host_data[copied : fi.size], self.packed, src_offset=copied, is_blocking=True
            )
        return fi
