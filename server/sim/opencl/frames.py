"""The OpenCL world's frame readback (a part the CLWorld owns).

One ``pack_rows`` launch gathers every cloth's positions (xyz, without the inverse mass) back to
back in the layout's order into one device buffer (normals likewise when a cloth carries them),
and one non-blocking copy brings it into a host buffer mapped from ``ALLOC_HOST_PTR`` memory
(pinned where the driver does that), reused from tick to tick (world.FramePool). The gather map
(frame row -> vertex) changes only with the layout, and then only where it changed: the rows of
cloths that stay are kept on the device (moved there in runs where cloths before them left),
the rows of new cloths computed and uploaded (O(changed cloths) on the host, not O(rows)).
``frame_async`` returns at once; its ``wait`` waits on that copy's event only; ``device_s`` is
the step-to-readback device time from the queue's profiling timestamps.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import pyopencl as cl

from ..frame import Frame, FramePool, Layout, PendingFrame
from .buffers import ClothSlot, DevArray, DeviceMemory, map_pinned
from .device import Device

log = logging.getLogger(__name__)

MAX_MOVED_RUNS = 256  # a new layout keeping its cloths' rows in more runs than this is rebuilt whole


def kept_runs(old: Layout | None, new: Layout) -> tuple[int, list[tuple[int, int, int]]] | None:
    """How ``new`` keeps ``old``'s rows: (k, runs) where ``new``'s first k cloths are the cloths
    of ``old`` still there, in ``old``'s order (cloths come at the end of a layout and leave
    anywhere), and each run (old first row, new first row, rows) is a stretch of them that was
    contiguous in ``old``; None when ``new`` is not so made (rebuilt whole)."""
    if old is None:
        return None
    keep = np.isin(old.handles, new.handles)
    idx = np.flatnonzero(keep)
    k = len(idx)
    if k > len(new.handles) or not np.array_equal(old.handles[idx], new.handles[:k]):
        return None
    if not k:
        return 0, []
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    if len(breaks) >= MAX_MOVED_RUNS:
        return None
    starts = [0, *breaks.tolist()]
    ends = [*breaks.tolist(), k]
    runs = []
    for s, e in zip(starts, ends, strict=True):
        a, b = int(idx[s]), int(idx[e - 1]) + 1
        runs.append((int(old.offsets[a]), int(new.offsets[s]), int(old.offsets[b] - old.offsets[a])))
    return k, runs


def device_span(start: cl.Event | None, end: cl.Event) -> Callable[[], float | None]:
    """The device's seconds from ``start`` (the step's first launch) to the end of ``end`` (the
    frame's last command), read from the queue's profiling once ``end`` is done; None without
    a start or without profiling."""

    def seconds() -> float | None:
        try:
            return 1e-9 * (end.profile.end - start.profile.start) if start is not None else None
        except Exception:  # no profiling on this queue or device
            return None

    return seconds


class FrameReadback:
    """Reads ``mem.pos`` (and ``mem.nrm``) back in the layout's order; marks each step's start."""

    def __init__(self, dev: Device, mem: DeviceMemory, rec: dict[int, ClothSlot], base_options: list[str]) -> None:
        self.dev, self.mem, self.rec, self.base_options = dev, mem, rec, base_options
        self._pool = FramePool(self._host_array)
        self._pinned: list[cl.Buffer] = []  # host buffers of the frames, alive as long as the world
        self._pack_src = DevArray(dev, np.int32, 1, 1024)  # frame row -> vertex of the buffers
        self._pack_spare = DevArray(dev, np.int32, 1, 1024)  # the next map, where rows move
        self._layout: Layout | None = None  # the layout of _pack_src
        self._packed = DevArray(dev, np.float32, 3, 1024)
        self._packed_nrm = DevArray(dev, np.float32, 3, 1024)
        self.step_marker: cl.Event | None = None  # the last step's start (its device time)

    def mark_step(self) -> None:
        """A step starts: its device time is measured from here (device_span)."""
        self.step_marker = cl.enqueue_marker(self.dev.queue)

    def _host_array(self, rows: int) -> np.ndarray:
        """A (rows, 3) float32 host array in ALLOC_HOST_PTR memory, mapped once for good."""
        try:
            buf, arr = map_pinned(self.dev, (rows, 3), np.float32)
            self._pinned.append(buf)
            return arr
        except cl.Error as e:  # a driver without mappable host memory: plain numpy
            log.debug("no mapped host buffer (%s): plain host memory", e)
            return np.zeros((rows, 3), np.float32)

    def layout_changed(self, layout: Layout) -> None:
        """The gather map of a new layout (frame row -> vertex): the kept cloths' rows kept or
        moved on the device (kept_runs), the new cloths' computed and written, behind the step
        without waiting for it."""
        n = layout.n_rows
        for arr in (self._pack_src, self._pack_spare, self._packed, self._packed_nrm):
            if arr.capacity < n:
                arr.resize(2 * n)
        kept = kept_runs(self._layout, layout)
        self._layout = layout
        k = 0
        if kept is not None:
            k, runs = kept
            if runs and runs != [(0, 0, runs[0][2])]:  # cloths left before some kept ones: moved
                cur, nxt = self._pack_src, self._pack_spare
                for old_row, new_row, count in runs:
                    cl.enqueue_copy(
                        self.dev.queue,
                        nxt.buf,
                        cur.buf,
                        byte_count=count * cur.itembytes,
                        src_offset=old_row * cur.itembytes,
                        dst_offset=new_row * cur.itembytes,
                    )
                self._pack_src, self._pack_spare = nxt, cur
        handles = layout.handles[k:]
        offsets = layout.offsets[k:]
        if not len(handles):
            return
        counts = np.diff(offsets)
        vbase = np.fromiter((self.rec[h].vbase for h in handles.tolist()), np.int64, len(counts))
        rows = np.arange(int(offsets[0]), n, dtype=np.int64)
        src = (np.repeat(vbase - offsets[:-1], counts) + rows).astype(np.int32)
        self._pack_src.write(int(offsets[0]), src, blocking=False)  # behind the step, not waiting for it

    def _pack(self, n: int, src: DevArray, out: DevArray) -> None:
        k = self.dev.kernel(self.base_options, "pack_rows")
        k(self.dev.queue, (-(-n // 64) * 64,), (64,), np.int32(n), self._pack_src.buf, src.buf, out.buf)

    def frame_async(self, lay: Layout, step: int) -> PendingFrame:
        """Start reading back step ``step``'s positions (and normals) in ``lay``'s order."""
        n = lay.n_rows
        want_nrm = bool(lay.normals.any())
        buf = self._pool.acquire(n, want_nrm)
        xyz, nxyz = buf.xyz[:n], (buf.nrm[:n] if want_nrm else None)
        frame = Frame(step, lay, xyz, nxyz, buf)
        if not n:
            return PendingFrame(frame)
        q = self.dev.queue
        self._pack(n, self.mem.pos, self._packed)
        if want_nrm:
            self._pack(n, self.mem.nrm, self._packed_nrm)
        ev = cl.enqueue_copy(q, xyz, self._packed.buf, is_blocking=False)
        if nxyz is not None:
            ev = cl.enqueue_copy(q, nxyz, self._packed_nrm.buf, is_blocking=False)
        return PendingFrame(frame, ev.wait, device_span(self.step_marker, ev))
