"""The predictive streams of a device-encoded frame (protocol 1.5): per tick, each predictive
cloth's order and reference ticks, decided on the host as whole-frame arrays and uploaded with the
frame (encode.py's ``DeviceEncoder.encode(predictive=...)``); the grid values themselves stay on
the device, in the encoder's history buffers.

The rules are statecodec's (:func:`~drape.server.sim.statecodec.keyframe_rule`,
:func:`~drape.server.sim.statecodec.stream_phase`: one copy for both paths): a keyframe when a
stream starts, every ``keyframe_interval`` ticks (at a phase of its own), after a reset, on a new
step, when a subscriber asked (at most one every ``MIN_REQUESTED_GAP`` ticks) and after a tick
its state was not put because nobody watched it (whoever subscribes next lacks that state). The
device encodes every published cloth every tick, right behind the step, before the publisher
knows who watches; so what the publisher learns (requests, states not put) reaches
:class:`DeviceStreams` through :meth:`lost` and :meth:`request` (any thread) and applies from the
next frame encoded. A state whose reference the decoders lack is dropped by them (its ref ticks
say so; PROTOCOL.md 9.2), never shown; so a stream that begins (a new cloth, a new subscriber
after states nobody watched) sends keyframes until the publisher has told that one of its
states went out (:meth:`put`): its first subscriber's first states are never undecodable (the
frame after one the publisher found unwatched is decided before the publisher tells).

A frame the publisher drops whole (it had not taken it when the next one was back) is not a
loss: the tick thread learns it with the next frame, before stepping again (:meth:`dropped`),
the streams go back to where they were before the dropped tick (its requests and news kept),
and the next frame's decision is taken again (:meth:`redo`) and coded again against the last
states sent: a predicted state, as on the host path, where a dropped frame is never coded.

A decimated stream (1.8, every k-th tick's state on its own key) is a DeviceStreams of its own,
decided on its ticks only (devrates.py); a frame dropped on its tick is taken back with
:meth:`undo`.

A stream lives with its cloth id in the plan; it is carried across plans while the cloth keeps
its vertex range and history base (its history is indexed by them).
"""

from __future__ import annotations

import itertools
import threading
import zlib
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from drape.client import protocol as P

from ..statecodec import keyframe_rule
from .frameplan import FramePlan

_FAR = -(1 << 62)  # a new stream's key tick: its first state is a keyframe


@dataclass
class _State:
    """Every plan cloth's stream, as arrays (k,)."""

    valid: np.ndarray  # bool: a stream whose decoders hold its last state
    key_tick: np.ndarray  # int64
    step: np.ndarray  # float64
    since: np.ndarray  # int64, states since the keyframe, up to 2 (the order they allow)
    tick1: np.ndarray  # int64, ticks of the last two states
    tick2: np.ndarray
    start: np.ndarray  # int64, the tick its chain began (its first keyframe after a start or a loss)

    @classmethod
    def empty(cls, k: int) -> _State:
        z = np.zeros(k, np.int64)
        far = np.full(k, _FAR, np.int64)
        return cls(np.zeros(k, bool), far, np.zeros(k), z, z.copy(), z.copy(), far.copy())

    def take(self, rows: np.ndarray, into: _State, at: np.ndarray) -> None:
        for name in ("valid", "key_tick", "step", "since", "tick1", "tick2", "start"):
            getattr(into, name)[at] = getattr(self, name)[rows]


class DeviceStreams:
    """The predictive streams of one device encoder's plans (the World's tick thread calls
    :meth:`follow`, :meth:`decide`, :meth:`redo` and :meth:`dropped`; the publisher
    :meth:`lost`, :meth:`put` and :meth:`request`)."""

    def __init__(self, keyframe_interval: int = 60) -> None:
        self.keyframe_interval = keyframe_interval
        self._plan: FramePlan | None = None
        self._ids: dict[str, int] = {}
        self._state = _State.empty(0)
        self._pred = np.zeros(0, bool)
        self._steps = np.zeros(0)
        self._phase = np.zeros(0, np.int64)
        self._lock = threading.Lock()
        self._requested: set[str] = set()
        self._lost: list[tuple[FramePlan, np.ndarray]] = []
        self._put: list[tuple[FramePlan, np.ndarray, int]] = []
        self._seen = np.zeros(0, np.int64)  # per plan cloth: the last tick its state was put
        # the last decision, for redo: (tick, the state before it, requested and lost masks)
        self._last: tuple[int, _State, np.ndarray, np.ndarray] | None = None
        self._prev: tuple[int, _State, np.ndarray, np.ndarray] | None = None  # the one before it
        self._kept: set[str] = set()

    # -- any thread -------------------------------------------------------------------------

    def request(self, cloths: Iterable[str]) -> None:
        """The next state of each of these cloths' streams is a keyframe (a subscriber asked)."""
        with self._lock:
            self._requested.update(cloths)

    def lost(self, plan: FramePlan, cloths: np.ndarray) -> None:
        """These plan cloths' states (of a frame of ``plan``) were not put: their decoders lack
        them, so their next states are keyframes."""
        if len(cloths):
            with self._lock:
                self._lost.append((plan, np.asarray(cloths, np.int64)))

    def put(self, plan: FramePlan, cloths: np.ndarray, tick: int) -> None:
        """These plan cloths' states of ``tick`` (a frame of ``plan``) were put: a stream begun
        on a keyframe is predicted only once one of its states is known to have gone out (the
        publisher tells a frame later than the next one is decided, and a state predicted from
        one nobody got is undecodable: a new subscriber's first states)."""
        if len(cloths):
            with self._lock:
                self._put.append((plan, np.asarray(cloths, np.int64), tick))

    # -- the tick thread ----------------------------------------------------------------------

    def follow(self, plan: FramePlan) -> None:
        """Streams for a new plan: those of cloths still there, at the same vertices with the
        same count, go on; the others start afresh (per cloth only here, when the plan changes)."""
        if plan is self._plan:
            return
        k = len(plan.cloths)
        new = _State.empty(k)
        old_ids, old = self._ids, self._state
        ids = plan.ids
        j = np.fromiter(map(old_ids.get, ids, itertools.repeat(-1)), np.int64, k)  # whole arrays, not per cloth
        if self._plan is not None and len(j) and len(self._plan.cloths):
            jj = np.maximum(j, 0)
            prev_vb, prev_n, prev_hb = self._plan.vbases, self._plan.counts, self._plan.hbases
            same = (j >= 0) & (prev_vb[jj] == plan.vbases) & (prev_n[jj] == plan.counts) & (prev_hb[jj] == plan.hbases)
        else:
            same = np.zeros(k, bool)
        a = np.flatnonzero(same)
        r = j[a]
        old.take(r, new, a)
        seen = np.full(k, _FAR, np.int64)
        seen[a] = self._seen[r]
        self._seen = seen
        self._ids = dict(zip(ids, range(k), strict=True))
        self._pred = plan.predictive & (plan.state_offset >= 0)
        new.valid &= self._pred
        self._state = new
        self._steps = plan.steps.astype(np.float64)
        self._phase = np.fromiter(map(zlib.crc32, map(str.encode, ids)), np.int64, k)
        self._plan = plan
        last = self._last  # the state before the last decision goes on too (if its frame is dropped)
        if last is not None:
            before = _State.empty(k)
            last[1].take(r, before, a)
            before.valid &= self._pred
            masks = [np.zeros(k, bool), np.zeros(k, bool)]
            for m, o in zip(masks, last[2:], strict=True):
                m[a] = o[r]
            self._last = (last[0], before, masks[0], masks[1])
        self._prev = None

    def decide(self, tick: int, flags: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """This tick's (order, ref tick, ref2 tick) per plan cloth ((k, 3) uint64) and which
        are keyframes ((k,) bool); the streams move on to ``tick``."""
        k = len(self._pred)
        with self._lock:
            asked = self._requested | self._kept
            self._requested = set()
            lost_in = self._lost
            self._lost = []
            put_in = self._put
            self._put = []
        requested = np.zeros(k, bool)
        for c in asked:
            i = self._ids.get(c)
            if i is not None:
                requested[i] = True
        lost = np.zeros(k, bool)
        for plan, idx in lost_in:
            lost[self._rows(plan, idx)] = True
        for plan, idx, t in put_in:
            at = self._rows(plan, idx)
            self._seen[at] = np.maximum(self._seen[at], t)
        self._prev, self._last = self._last, (tick, self._state, requested, lost)
        return self._decide(tick, flags)

    def _rows(self, plan: FramePlan, idx: np.ndarray) -> np.ndarray:
        """This plan's rows of ``plan``'s cloths ``idx`` (an earlier plan's: by id)."""
        if plan is self._plan:
            return idx
        ids = plan.ids
        got = [self._ids.get(ids[i]) for i in idx.tolist()]
        return np.array([j for j in got if j is not None], np.int64)

    def dropped(self, tick: int) -> bool:
        """The frame of ``tick``, decided before the last one, was dropped whole (none of its
        states went out): the streams go back to before it, the requests and news it took kept
        for the last tick's decision, which the caller takes again (:meth:`redo`). False when
        that cannot be (a plan changed in between): the last tick's states are then keyframes."""
        last, prev = self._last, self._prev
        if last is None:
            return False
        t, s, requested, lost = last
        if prev is None or prev[0] != tick or len(prev[2]) != len(requested):
            self._last = (t, s, requested, np.ones(len(requested), bool))
            return False
        _, ps, preq, plost = prev
        self._last = (t, ps, preq | requested, plost | lost)
        self._prev = None
        return True

    def undo(self, tick: int) -> bool:
        """The frame of ``tick``, the last decided, was dropped whole (a decimated stream's: the
        next decision is on a later tick of its own): the streams go back to before it, its
        requests and news kept for the next decision. False when it was not the last decided."""
        last = self._last
        if last is None or last[0] != tick:
            return False
        _, s, requested, lost = last
        if len(requested) != len(self._pred):
            return False
        self._state = s
        plan = self._plan
        if plan is not None:
            with self._lock:
                self._requested.update(plan.ids[i] for i in np.flatnonzero(requested).tolist())
                if lost.any():
                    self._lost.append((plan, np.flatnonzero(lost)))
        self._kept = set()
        self._last, self._prev = self._prev, None
        return True

    def redo(self, tick: int, flags: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The decision of the tick just decided again, with new flags (cloths reset after the
        frame was encoded: keyframes)."""
        if self._last is None or self._last[0] != tick:
            raise RuntimeError(f"tick {tick} was not the last decided")
        return self._decide(tick, flags)

    def _decide(self, tick: int, flags: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        assert self._last is not None
        _, s, requested, lost = self._last
        pred = self._pred
        k = len(pred)
        new = ~s.valid | lost
        # a chain none of whose states is known to have gone out: keyframes until one is
        unsure = pred & ~new & (self._seen < s.start)
        key_tick = np.where(new, _FAR, s.key_tick)
        old_step = np.where(new, 0.0, s.step)
        since = np.where(new, 0, s.since)
        reset = (np.asarray(flags) & P.FLAG_RESET) != 0 if flags is not None else np.zeros(k, bool)
        keyframe, kept = keyframe_rule(tick, key_tick, self._steps, old_step, reset, requested, self.keyframe_interval)
        keyframe &= pred
        kept &= pred
        intra = keyframe | unsure
        order = np.where(intra, 0, np.minimum(since, 2))
        out = np.zeros((k, 3), np.uint64)
        out[:, 0] = order
        out[:, 1] = np.where(order >= 1, s.tick1, 0)
        out[:, 2] = np.where(order >= 2, s.tick2, 0)
        key_tick = np.where(keyframe, tick, key_tick)
        key_tick = np.where(new, tick - self._phase % self.keyframe_interval, key_tick)
        self._state = _State(
            pred.copy(),
            key_tick,
            self._steps.copy(),
            np.where(intra, 1, np.minimum(since + 1, 2)),
            np.full(k, tick, np.int64),
            np.where(intra, 0, s.tick1),
            np.where(new, tick, s.start),
        )
        plan = self._plan
        self._kept = {plan.ids[i] for i in np.flatnonzero(kept).tolist()} if plan is not None else set()
        return out, intra
