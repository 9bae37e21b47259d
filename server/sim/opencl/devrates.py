"""Decimated predictive streams on the device encoder (protocol 1.8, PROTOCOL.md 9.3): every k-th
tick's state of a watched cloth or bundle on its own key ``{key}/every/{k}``, coded against that
key's own previous states, with no host fallback (bit-exact with the host path, wire.HostWire).

Per rate k with a subscriber, :class:`DeviceRates` keeps a small :class:`~.frameplan.FramePlan`
of the watched publications holding a predictive cloth (their decimated keys; rebuilt on the
rate's ticks when the roster or the watched set changed), a :class:`~.encode.DeviceEncoder` of its
own (its own launch, compaction and copy, enqueued right behind the full-rate frame on the same
queue, only on the ticks ``T mod k = 0``: no work on the others) and a
:class:`~.devstreams.DeviceStreams` (decided on those ticks only, keyframes every ``k x
keyframe_interval`` ticks). Its encoder keeps its own history of grid values (the 4 slots of
encode.py's :data:`~.encode.HISTORY`, of the rate's own ticks: T, T - k, T - 2k and T - 3k for a
frame dropped on its tick), for the watched cloths' vertices only (``ClothEntry.hbase``: 48 bytes
a watched vertex per rate; a cloth keeps its history range while it stays watched, so its stream
goes on across plans). A grid value is the same whichever stream quantises it (the same
position on the same step's grid), so the decimated rows quantise the positions again rather than
read the full-rate history, which would have to hold 2 x 3 + 2 ticks for every vertex.

The watched set is the publisher's (``RatePublishers.watching``, kept by Zenoh's matching
listeners), read when a frame is encoded: a publication first watched after its tick's frame was
encoded is served from its next tick of k (counted ``rate_unserved`` by the publisher). A
publication whose key lost its last subscriber leaves the plan, so its streams restart; one that
lost it and was watched again between two of the rate's ticks (the watched set the same) restarts
its streams too, from the count of such losses the watched set carries (as the host path forgets
them: its next subscriber starts on a keyframe).
A float32 / float16 / quant16 publication's decimated state is the full-rate bytes (no plan).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from drape.client import protocol as P

from ..roster import Roster
from ..statecodec import PredictiveStreams
from .device import Device
from .devstreams import DeviceStreams
from .encode import DeviceEncoder, FramePlan
from .hostframes import EncodedFrame

log = logging.getLogger(__name__)

# rate -> idents of the publications watched -> times each one's key lost its last subscriber
Watching = Callable[[], Mapping[int, Mapping[str, int]]]
_NOBODY: Mapping[str, int] = {}


@dataclass(frozen=True, eq=False)
class _Layout:
    """Where a rate plan's cloths and publications lie in the full-rate frame's roster."""

    base: np.ndarray  # plan cloth -> frame cloth
    pub_of: np.ndarray  # frame publication -> plan publication, -1 for none
    roster_pub: np.ndarray  # plan publication -> frame publication

    def cloths(self, frame_cloths: np.ndarray) -> np.ndarray:
        """The plan's cloths of frame cloths ``frame_cloths``."""
        return np.flatnonzero(np.isin(self.base, np.asarray(frame_cloths, np.int64)))


_NONE = _Layout(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))


@dataclass(eq=False)
class _Rate:
    """One decimated rate's plan, encoder and streams."""

    every: int
    encoder: DeviceEncoder
    streams: DeviceStreams
    version: tuple[object, Mapping[str, int]] | None = None
    layout: _Layout = _NONE  # of the plan now (a frame keeps its own: the publisher may lag)


@dataclass(eq=False)
class RateFrame:
    """A decimated rate's frame of one tick, held until released."""

    rate: _Rate
    frame: EncodedFrame
    keyframes: np.ndarray  # (plan cloths,) bool
    layout: _Layout  # its plan's
    put: bool = False  # its payloads were taken (else, at release, its states were lost)
    dropped: bool = False  # dropped whole and its streams taken back: nothing lost


_NO_HISTORY = (np.zeros(0, "<U1"), np.zeros(0, np.int64), np.zeros(0, np.int64))

Due = list[tuple[_Rate, np.ndarray]]  # the rates encoded this tick and their keyframes


class DeviceRates:
    """The decimated streams of one device encoder (a part DeviceFrames owns; the tick thread
    calls everything but :meth:`watch`)."""

    def __init__(self, dev: Device, encoder: DeviceEncoder) -> None:
        self.dev, self.main = dev, encoder
        self.rates: dict[int, _Rate] = {}
        # rate -> (its cloths' ids, sorted; their history bases; their vertex counts)
        self._hist: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._watching: Watching | None = None
        self.plans = 0  # decimated plans built (the tests count them)
        self.frames = 0  # decimated frames encoded

    def watch(self, watching: Watching) -> None:
        """Any thread: where the watched set is read from (the publisher's RatePublishers)."""
        self._watching = watching

    def follow(self, roster: Roster, plan: FramePlan, keyframe_interval: int, tick: int) -> None:
        """The decimated plans of ``roster`` (whose full-rate plan is ``plan``) and the watched
        set now, for the rates whose tick this is (as the host path sees the watched set only on
        those); a plan rebuilt only when either changed."""
        want = dict(self._watching()) if self._watching is not None else {}
        for k in sorted(set(want) | set(self.rates)):
            if tick % k:
                continue
            idents = want.get(k, _NOBODY)
            r = self.rates.get(k)
            version = (roster.version, idents)
            if r is not None and r.version == version:
                continue
            pubs = roster.publications()  # the plan's publications, in its order (FramePlan.for_roster)
            has_pred = np.zeros(len(pubs) + 1, bool)  # [-1]: in no publication
            has_pred[plan.owner[plan.predictive]] = True
            sel = [j for j, (p, h) in enumerate(zip(pubs, has_pred[:-1].tolist(), strict=True)) if h and p[0] in idents]
            if not sel:
                if r is not None:
                    r.encoder.close()
                    del self.rates[k]
                    self._hist.pop(k, None)
                continue
            members, ids = plan.members(sel), plan.ids
            hb = self._history_bases(k, [ids[i] for i in members.tolist()], plan.counts[members])
            sub, base = plan.subset(sel, [P.every_key(pubs[j][1], k) for j in sel], hb)
            before: Mapping[str, int] = _NOBODY
            if r is None:
                enc = DeviceEncoder(self.dev, stride=self.main.stride)
                r = self.rates[k] = _Rate(k, enc, DeviceStreams(k * keyframe_interval))
            elif r.version is not None:
                before = r.version[1]
            r.encoder.set_plan(sub)
            r.streams.follow(sub)
            # watched again since the last plan (its key lost its last subscriber meanwhile): restarted
            back = {i for i, _ in idents.items() - before.items() if i in before}
            if back:
                again = [i for jj, j in enumerate(sel) if pubs[j][0] in back for i in sub.publications[jj].cloths]
                r.streams.lost(sub, np.array(again, np.int64))
            pub_of = np.full(len(pubs), -1, np.int64)
            pub_of[np.array(sel, np.int64)] = np.arange(len(sel))
            r.version, r.layout = version, _Layout(base, pub_of, np.array(sel, np.int64))
            self.plans += 1
            log.debug("rate %d: %d publications, %d cloths", k, len(sel), len(base))

    def _history_bases(self, k: int, ids: list[str], n: np.ndarray) -> np.ndarray:
        """The first vertex in rate ``k``'s history of each cloth ``ids`` (of ``n`` vertices),
        whole arrays: a cloth still watched keeps its range (its stream goes on), a new one takes
        the next free, in order; packed afresh (those streams restart on keyframes) once the
        ranges span more than twice the vertices watched."""
        old_ids, old_base, old_n = self._hist.get(k, _NO_HISTORY)
        want = np.array(ids, str)
        kept = np.zeros(len(ids), bool)
        base = np.zeros(len(ids), np.int64)
        if len(old_ids):
            at = np.searchsorted(old_ids, want).clip(0, len(old_ids) - 1)
            kept = (old_ids[at] == want) & (old_n[at] == n)
            base[kept] = old_base[at[kept]]
        end = int((base + n)[kept].max(initial=0))
        if end > 2 * int(n.sum()) + 4096:
            kept[:], end = False, 0
        new = np.where(kept, 0, n)
        base = np.where(kept, base, end + np.cumsum(new) - new)
        order = np.argsort(want, kind="stable")
        self._hist[k] = (want[order], base[order], n[order])
        return base

    def encode(
        self,
        queue: cl.CommandQueue,
        positions: cl.Buffer,
        normals: cl.Buffer,
        tick: int,
        time_ns: int,
        flags: np.ndarray | None,
    ) -> Due:
        """Enqueue the frames of the rates whose tick this is (behind the full-rate frame of the
        same tick, on the same queue); returns (rate, keyframes) of each, to :meth:`hold` once
        back."""
        due: Due = []
        for k, r in self.rates.items():
            if tick % k:
                continue
            f = np.asarray(flags)[r.layout.base] if flags is not None else None
            pred, kf = r.streams.decide(tick, f)
            r.encoder.encode(queue, positions, normals, tick, time_ns, f, predictive=pred)
            self.frames += 1
            due.append((r, kf))
        return due

    @staticmethod
    def hold(due: Due) -> dict[int, RateFrame]:
        """The frames :meth:`encode` enqueued (waits for them), each kept with its plan's layout."""
        return {r.every: RateFrame(r, r.encoder.hold(), kf, r.layout) for r, kf in due}

    def reencode(
        self,
        frames: dict[int, RateFrame],
        positions: cl.Buffer,
        normals: cl.Buffer,
        tick: int,
        time_ns: int,
        flags: np.ndarray,
    ) -> None:
        """Each of these frames encoded again (after the full-rate frame was: resets, flags
        carried from a dropped frame), its decision taken again with ``flags`` (frame cloths)."""
        for rf in frames.values():
            r = rf.rate
            rf.frame.release()
            f = np.asarray(flags)[rf.layout.base]
            pred, rf.keyframes = r.streams.redo(tick, f)
            r.encoder.encode(self.dev.queue, positions, normals, tick, time_ns, f, predictive=pred).wait()
            rf.frame = r.encoder.hold()

    def payloads(
        self, rf: RateFrame, watched: list[int], streams: PredictiveStreams, tick: int
    ) -> Iterator[tuple[int, bytes]]:
        """(frame publication, bytes) of the ``watched`` publications this rate frame holds; what
        the publisher knows (requests, states put or not) reaches the rate's streams."""
        r = rf.rate
        ds = r.streams
        ds.keyframe_interval = streams.keyframe_interval
        ds.request(streams.take_requests())
        plan = rf.frame.plan
        lay = rf.layout
        at = lay.pub_of[np.asarray(watched, np.int64)] if len(watched) else np.zeros(0, np.int64)
        sel = at[at >= 0]
        shown = np.zeros(len(plan.publications) + 1, bool)
        shown[sel] = True
        seen = shown[plan.owner]
        ds.lost(plan, np.flatnonzero(plan.predictive & ~seen))
        ds.put(plan, np.flatnonzero(plan.predictive & seen), tick)
        streams.keyframes += int((rf.keyframes & seen).sum())
        rf.put = True
        for jj, payload in rf.frame.payloads(sel.tolist()):
            yield int(lay.roster_pub[jj]), payload

    def release(self, rf: RateFrame) -> None:
        if not rf.put and not rf.dropped:  # its states never went out
            plan = rf.frame.plan
            rf.rate.streams.lost(plan, np.flatnonzero(plan.predictive))
        rf.put = True
        rf.frame.release()

    def dropped(self, rf: RateFrame, tick: int) -> None:
        """The frame of ``tick`` holding ``rf`` was dropped whole: its rate's streams go back."""
        rf.dropped = True
        if rf.rate.streams.undo(tick):
            rf.rate.encoder.forget(tick)
        else:
            rf.rate.streams.lost(rf.frame.plan, np.flatnonzero(rf.frame.plan.predictive))

    def close(self) -> None:
        for r in self.rates.values():
            r.encoder.close()
        self.rates = {}
