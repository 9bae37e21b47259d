"""The device encoder's frames in host memory: the pinned (ALLOC_HOST_PTR, mapped for good) copies
each frame is read back into, used in turn (:class:`HostFrames`), and a frame kept from reuse
while the publisher takes its payloads (:class:`EncodedFrame`: each publication's bytes, a view
of that memory or of a compacted frame's, and the header fields written once the frame is back).

encode.py's :class:`~.encode.DeviceEncoder` copies every frame (or, for plans with predictive
states, the compacted frame and its index: compact.py) into the next host frame no one holds;
host frames are bound to the plan in use and kept from plan to plan while their memory fits
(reuse.py), so cloths that come or go within the capacity allocate nothing.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from . import reuse
from .buffers import map_pinned
from .compact import Compactor, FrameIndex
from .device import Device
from .frameplan import HEADER_OFFSETS, FramePlan, put_words

log = logging.getLogger(__name__)


@dataclass(eq=False)
class HostFrame:
    """One pinned host copy of the frame, and each publication's view of it."""

    mapping: object  # pyopencl MemoryMap keeping the pinned buffer mapped
    buf: cl.Buffer
    data: np.ndarray  # (size,) uint8: the plan's first bytes of ``full``
    views: list[memoryview]
    event: cl.Event | None = None
    plan: FramePlan | None = None
    held: bool = False
    # a compacted frame (plans with predictive states): the kernel's index, the bytes the first
    # copy brought, and where things lie once it is back (views are then made on demand)
    index: np.ndarray | None = None
    copied: int = 0
    where: FrameIndex | None = None
    # the whole pinned arrays, kept from plan to plan while they fit (reuse.py)
    full: np.ndarray | None = None  # (capacity,) uint8
    index_full: np.ndarray | None = None  # (capacity,) uint32

    def state_at(self) -> np.ndarray:
        """(k,) each plan cloth's state offset in ``data`` (-1: in no publication)."""
        assert self.plan is not None
        return self.where.state_at if self.where is not None else self.plan.state_offset


class HostFrames:
    """``count`` pinned host frames used in turn (more while all are held: a consumer holding
    frames longer than ``count`` ticks), bound to the encoder's plan. The ``compactor`` the
    methods take is the encoder's when its plan's frames are compacted (predictive states),
    else None."""

    def __init__(self, dev: Device, count: int) -> None:
        if count < 1:
            raise ValueError("host_buffers must be at least 1")
        self.dev, self.count = dev, count
        self.frames: list[HostFrame] = []
        self._next = 0
        self.made = 0  # pinned host frames and indices allocated (kept across plans while they fit)

    def __len__(self) -> int:
        return len(self.frames)

    def bind(self, plan: FramePlan, compactor: Compactor | None) -> None:
        """``count`` host frames for ``plan``: the free ones bound to it (kept while they fit),
        new ones for the rest; held frames stay as they are (bound to the plan in use once
        released, :meth:`next_free`), extra free ones go."""
        free = [h for h in self.frames if not h.held]
        held = [h for h in self.frames if h.held]
        hosts = [self._frame(plan, compactor, free[i] if i < len(free) else None) for i in range(self.count)]
        self.frames, self._next = hosts + held, 0

    def next_free(self, plan: FramePlan, compactor: Compactor | None) -> HostFrame:
        """The next host frame in turn that is not held (bound to ``plan``); a new one when all are."""
        for _ in range(len(self.frames)):
            i = self._next
            host = self.frames[i]
            self._next = (self._next + 1) % len(self.frames)
            if not host.held:
                if host.plan is not plan:  # held across a plan change, released since
                    host = self.frames[i] = self._frame(plan, compactor, host)
                return host
        host = self._frame(plan, compactor)
        self.frames.append(host)
        if len(self.frames) == 8 * self.count + 1:
            log.warning("%d pinned frames held: is a consumer not releasing them?", len(self.frames))
        return host

    def clear(self) -> None:
        """Drop the pinned host frames. A view still held elsewhere keeps its memory (and its
        mapping) alive until it is dropped too, so it never dangles."""
        self.frames = []
        self._next = 0

    def _frame(self, plan: FramePlan, compactor: Compactor | None, old: HostFrame | None = None) -> HostFrame:
        """A pinned host copy of a frame of ``plan``: ``old`` (a frame no one holds) bound to it
        when its memory fits (reuse.py), else a new one. Every encode copies the whole frame (or
        the compacted one and its index) into it before it can be read."""
        size = max(plan.size, 8)
        if old is not None and old.full is not None and reuse.fits(old.full.size, size):
            host = old
            host.views, host.where, host.copied = [], None, 0
        else:
            cap = reuse.capacity(old.full.size if old is not None and old.full is not None else 0, size)
            hb, full = map_pinned(self.dev, cap, np.uint8)
            self.made += 1
            host = HostFrame(full.base, hb, full[:size], [], full=full)
            if old is not None and old.index_full is not None:
                host.index_full = old.index_full
        assert host.full is not None
        host.plan, host.data = plan, host.full[:size]
        if compactor is not None:  # compacted frames: views made per frame from its index
            assert compactor.pieces is not None
            n = 2 * len(compactor.pieces.cloth) + 1
            have = host.index_full.size if host.index_full is not None else 0
            if host.index_full is None or not reuse.fits(4 * have, 4 * n):
                host.index_full = compactor.host_index(reuse.capacity(4 * have, 4 * n) // 4)
                self.made += 1
            host.index = host.index_full[:n]
            return host
        host.index = None
        mv = memoryview(host.data).cast("B")  # type: ignore[arg-type]
        host.views = [mv[o : o + s] for o, s in zip(plan.pub_offset.tolist(), plan.pub_size.tolist(), strict=True)]
        return host


class EncodedFrame:
    """A frame kept from reuse (:meth:`DeviceEncoder.hold <.encode.DeviceEncoder.hold>`) until
    :meth:`release`: the publications' payload views (``slices``) of its pinned host memory, in
    plan order."""

    def __init__(self, host: HostFrame) -> None:
        assert host.plan is not None
        self._host: HostFrame | None = host
        self.plan = host.plan
        self._views = list(host.views) if host.where is None else None
        self._where = host.where
        self._data = host.data
        host.held = True

    @property
    def views(self) -> list[memoryview]:
        """Each publication's bytes, a view of the pinned host memory, in plan order."""
        if self._views is None:
            assert self._where is not None
            self._views = self._where.views(self._data)
        return self._views

    def add_flags(self, cloths: Sequence[int], flags: int) -> None:
        """OR ``flags`` into the state headers of plan cloths ``cloths`` (e.g. FLAG_RESET carried
        over from a frame that was dropped); cloths in no publication are ignored."""
        if self._host is None:
            raise RuntimeError("frame already released")
        at = self._host.state_at()[np.asarray(list(cloths), np.int64)]
        at = at[at >= 0] + HEADER_OFFSETS["ST_FLAGS"]
        if len(at):
            f = self._host.data[at] | np.uint8(flags & 0xFF)
            f2 = self._host.data[at + 1] | np.uint8((flags >> 8) & 0xFF)
            self._host.data[at], self._host.data[at + 1] = f, f2

    def set_time(self, time_ns: int) -> None:
        """Rewrite the server time of every state and bundle header (PROTOCOL.md: when the tick
        was read back, known only after the encode): one vectorised write per frame."""
        if self._host is None:
            raise RuntimeError("frame already released")
        w = self._where
        at = self.plan.time_offsets() if w is None else self.plan.time_offsets(w.state_at, w.pub_at)
        if len(at):
            put_words(self._host.data, at, np.frombuffer(int(time_ns).to_bytes(8, "little"), np.uint8))

    def payloads(self, watched: Sequence[int]) -> Iterator[tuple[int, bytes]]:
        """(publication index, its bytes) of the ``watched`` publications, in order: one
        ``bytes`` copy of each (of a compacted frame: a slice of it, no view made)."""
        if self._host is None:
            raise RuntimeError("frame already released")
        w = self._where
        if w is None:
            views = self.views
            for j in watched:
                yield j, bytes(views[j])
            return
        sel = np.asarray(watched, np.int64)
        mv = memoryview(self._data).cast("B")  # type: ignore[arg-type]
        for j, a, b in zip(watched, w.pub_at[sel].tolist(), (w.pub_at[sel] + w.pub_len[sel]).tolist(), strict=True):
            yield j, mv[a:b].tobytes()

    def sizes(self) -> list[int]:
        """Each publication's payload size, in plan order (no view made)."""
        return (self._where.pub_len if self._where is not None else self.plan.pub_size).tolist()

    def release(self) -> None:
        if self._host is not None:
            self._host.held = False
            self._host = None
