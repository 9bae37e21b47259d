"""An OpenCL World's device-encoded ticks (``CLWorld(device_encode=True)``; the service's config
``device_encode``).

Per tick, right after the step and on the same queue (no host round trip), one launch of
encode.py's ``encode_frame`` writes every publication's bytes (states and bundles exactly as
drape.client.protocol encodes them) into one packed device buffer, straight from the world's
float4 position and normal buffers, and one copy brings it into pinned host memory. The
:class:`~drape.server.sim.opencl.encode.FramePlan` is rebuilt only when the roster changes
(cloths come or go, change encoding, normals or bundling: ``Roster.version``). The World's
``fetch_async(roster, tick)`` gives a :class:`DeviceWire` whose payloads are slices of that
memory.

Non-finite cloths show as non-finite bounds in their headers (``DeviceEncoder.nonfinite``);
once the World has reset them, :meth:`DeviceWire.reset` writes their rest normals and encodes
the frame again with the reset flag: the same bytes the host path publishes.

Predictive cloths (protocol 1.5) are coded here too: devstreams.DeviceStreams decides each
stream's order and reference ticks per tick (the host path's rules, whole-frame arrays), the
kernel codes it against the history the encoder keeps on the device, and compact.py's launches
write the frame's wire bytes back to back before the copy (each payload is then a slice). A
cloth reset on the tick thread after its frame was encoded (:meth:`DeviceWire.add_flags`,
:meth:`DeviceWire.reset`) is coded again as a keyframe; the publisher's news (keyframe
requests, states nobody watched, frames it dropped) reach the streams through
:meth:`DeviceWire.payloads` and :meth:`DeviceWire.release` (O(news), not O(cloths), per tick).

Decimated predictive streams (1.8: ``{key}/every/{k}`` while watched) are devrates.py's
:class:`~.devrates.DeviceRates`: a small plan per rate, encoded right behind the full-rate frame on
its ticks against the full-rate history; :meth:`DeviceWire.rate_payloads` gives their bytes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

import numpy as np

from drape.client import protocol as P

from ..fabric import Fabric
from ..frame import Frame, Layout, PendingFrame
from ..roster import Roster
from ..shared import vertex_normals
from ..statecodec import PredictiveStreams
from ..wire import Payload, PendingWire, Wire
from .buffers import ClothSlot, DeviceMemory
from .device import Device
from .devrates import DeviceRates, Due, RateFrame, Watching
from .devstreams import DeviceStreams
from .encode import DeviceEncoder, FramePlan
from .frames import FrameReadback, device_span
from .hostframes import EncodedFrame

log = logging.getLogger(__name__)


class DeviceFrames:
    """One OpenCL world's frame encoder (a part the world owns): reads ``mem.pos`` and
    ``mem.nrm`` at each cloth's ``rec`` vertex base; a step's device time from ``readback``'s
    step marker."""

    def __init__(self, dev: Device, mem: DeviceMemory, rec: dict[int, ClothSlot], readback: FrameReadback) -> None:
        self.dev, self.mem, self.rec, self.readback = dev, mem, rec, readback
        self.encoder = DeviceEncoder(dev, stride=4)
        self.streams = DeviceStreams()
        self.rates = DeviceRates(dev, self.encoder)  # 1.8: the decimated streams watched
        self._plan_version: tuple[int, int] | None = None
        self.plans = 0  # plans built (the tests count them)
        self.frames = 0  # frames encoded
        self.predictive_frames = 0  # of which with predictive states (issue 21: no host fallback)

    def build_all(self) -> None:
        """Every program a plan may pick, built now (the tick thread never compiles)."""
        self.encoder.build_all()

    def _plan(self, roster: Roster, lay: Layout) -> None:
        if self._plan_version == roster.version and self.encoder.plan is not None:
            return
        vbase = [self.rec[h].vbase for h in lay.handles.tolist()]
        plan = FramePlan.for_roster(roster, vbase, np.diff(lay.offsets).tolist())
        self.encoder.set_plan(plan)
        self.streams.follow(plan)
        self._plan_version = roster.version
        self.plans += 1

    def encode(self, roster: Roster, tick: int, lay: Layout, step: int) -> PendingWire:
        """Enqueue tick ``tick``'s frame (step ``step`` of the world, in ``lay``) right behind
        the step (its server time is set once read back)."""
        self._plan(roster, lay)
        mem = self.mem
        assert self.encoder.plan is not None
        self.rates.follow(roster, self.encoder.plan, self.streams.keyframe_interval, tick)
        pred = keyframes = None
        if self.encoder.plan.predictive.any():
            pred, keyframes = self.streams.decide(tick, None)
            self.predictive_frames += 1
        ev = self.encoder.encode(self.dev.queue, mem.pos.buf, mem.nrm.buf, tick, 0, None, predictive=pred)
        self.frames += 1
        due: Due = []
        if keyframes is not None:  # 1.8: the decimated streams whose tick this is, behind it
            due = self.rates.encode(self.dev.queue, mem.pos.buf, mem.nrm.buf, tick, 0, None)
        frame = Frame(step, lay, np.zeros((0, 3), np.float32), None)
        pending = PendingFrame(frame, ev.wait, device_span(self.readback.step_marker, ev))
        return PendingWire(pending, lambda f: DeviceWire(f, roster, tick, self, keyframes, due))

    def reencode(
        self,
        old: EncodedFrame,
        tick: int,
        time_ns: int,
        flags: np.ndarray,
        reset: list[tuple[int, Fabric]],
        rates: dict[int, RateFrame] | None = None,
    ) -> tuple[EncodedFrame, np.ndarray | None]:
        """The frame encoded again after the World reset some cloths (``reset``: (handle,
        fabric) of those carrying normals, whose rest normals are written first); its
        predictive cloths' decisions taken again with ``flags`` (reset: keyframes), and its
        decimated ``rates`` frames (replaced in place). Returns the frame and its keyframes."""
        mem = self.mem
        for h, fabric in reset:
            n = fabric.n_vertices
            nrm = np.zeros((n, 4), np.float32)
            nrm[:, :3] = vertex_normals(fabric.rest_positions, fabric)[0]
            mem.nrm.write(self.rec[h].vbase, nrm)
        old.release()
        t = time.perf_counter()
        pred = keyframes = None
        assert self.encoder.plan is not None
        if self.encoder.plan.predictive.any():
            pred, keyframes = self.streams.redo(tick, flags)
        self.encoder.encode(self.dev.queue, mem.pos.buf, mem.nrm.buf, tick, time_ns, flags, predictive=pred).wait()
        if rates:
            self.rates.reencode(rates, mem.pos.buf, mem.nrm.buf, tick, time_ns, flags)
        log.debug("frame of tick %d encoded again after resets in %.3f ms", tick, 1e3 * (time.perf_counter() - t))
        return self.encoder.hold(), keyframes

    def close(self) -> None:
        self.rates.close()
        self.encoder.close()


class DeviceWire(Wire):
    """A tick's payloads as encoded on the device: slices of pinned host memory, held until released."""

    def __init__(
        self,
        frame: Frame,
        roster: Roster,
        tick: int,
        frames: DeviceFrames,
        keyframes: np.ndarray | None,
        due: Due | None = None,
    ) -> None:
        super().__init__(frame, roster, tick)
        self._frames = frames
        self.encoded = frames.encoder.hold()
        # 1.8: the decimated rates whose tick this is, each its own frame (devrates.py)
        self._rates = DeviceRates.hold(due or [])
        self._bad = frames.encoder.nonfinite()
        self._keyframes = keyframes  # (k,) bool, predictive plans only
        self._put = False  # payloads taken (else, at release, its predictive states were lost)
        self._dropped = False  # dropped whole and its streams taken back (after_dropped): nothing lost

    def set_time(self, time_ns: int) -> None:
        super().set_time(time_ns)
        self.encoded.set_time(self.time_ns)
        for rf in self._rates.values():
            rf.frame.set_time(self.time_ns)

    def _reencode(self, reset: list[tuple[int, Fabric]]) -> None:
        self.encoded, self._keyframes = self._frames.reencode(
            self.encoded, self.tick, self.time_ns, self.flags, reset, self._rates
        )

    def add_flags(self, cloths: np.ndarray, flag: int) -> None:
        """On the tick thread, before the next frame is encoded: a predictive cloth reset is
        coded again as a keyframe (the whole frame encoded again, as after a non-finite step)."""
        super().add_flags(cloths, flag)
        plan = self.encoded.plan
        if flag & P.FLAG_RESET and plan.predictive[np.asarray(cloths, np.int64)].any():
            self._reencode([])
        else:
            self.encoded.add_flags(np.asarray(cloths).tolist(), flag)
            for rf in self._rates.values():
                rf.frame.add_flags(rf.layout.cloths(cloths).tolist(), flag)

    def after_dropped(self, older: Wire) -> None:
        """On the tick thread, before the next step (the world's positions are still this
        frame's): the frame before, never taken by the publisher, is dropped whole; its streams
        go back to the last states sent and this frame is coded again against them (a predicted
        state, not a keyframe: what the host path sends), its reset flags carried."""
        if not isinstance(older, DeviceWire) or older._keyframes is None or self._keyframes is None:
            self.carry_flags(older)
            return
        older._dropped = True
        frames = self._frames
        if older.roster.version == self.roster.version:
            Wire.add_flags(self, np.flatnonzero(older.flags & P.FLAG_RESET), P.FLAG_RESET)
        for rf in older._rates.values():  # its decimated states: never coded on the host path either
            frames.rates.dropped(rf, older.tick)
        if frames.streams.dropped(older.tick):
            frames.encoder.forget(older.tick)
        self._reencode([])

    def carry_flags(self, older: Wire) -> None:
        """On the publisher's thread: the header flags only (the older frame's predictive
        states were lost with it, so these streams' next states are keyframes anyway)."""
        if older.roster.version == self.roster.version:
            bad = np.flatnonzero(older.flags & P.FLAG_RESET)
            if len(bad):
                Wire.add_flags(self, bad, P.FLAG_RESET)
                self.encoded.add_flags(bad.tolist(), P.FLAG_RESET)
                for rf in self._rates.values():
                    rf.frame.add_flags(rf.layout.cloths(bad).tolist(), P.FLAG_RESET)

    def nonfinite(self) -> np.ndarray:
        return self._bad

    def reset(self, cloths: list[tuple[int, Fabric]]) -> None:
        live, lay = self._frames.rec, self.frame.layout
        normals: list[tuple[int, Fabric]] = []
        for i, fabric in cloths:
            self.flags[i] |= P.FLAG_RESET
            h = int(lay.handles[i])
            if h in live and lay.normals[i]:
                normals.append((h, fabric))
        # the frame again, the reset cloths at rest with the reset flag (as the host path publishes)
        self._reencode(normals)
        self._bad = np.zeros(0, np.int64)

    def sizes(self) -> list[int]:
        return self.encoded.sizes()

    def payloads(self, watched: list[int], streams: PredictiveStreams) -> Iterator[tuple[int, Payload]]:
        """One ``bytes`` copy each: eclipse-zenoh 1.10's put takes ``bytes``, ``bytearray``,
        ``str`` or ``ZBytes`` (made from one of those), not a memoryview (checked: "expected
        bytes/str type, found 'memoryview'"), so each payload is one copy out of the pinned
        frame (a compacted frame's slice: no gather). Measured against it on the H100
        (docs/loadtest.md, session 12): copying into a ``bytearray`` kept per key doubled the
        copy and put phases (3.5 -> 6.1 and 9.8 -> 17.4 ms a tick at 2048 float32)."""
        self._put = True
        enc = self.encoded
        plan = enc.plan
        if self._keyframes is not None:  # 1.5: what the publisher knows reaches the streams
            ds = self._frames.streams
            ds.keyframe_interval = streams.keyframe_interval
            ds.request(streams.take_requests())
            shown = np.zeros(len(plan.publications) + 1, bool)  # [-1]: no publication
            shown[np.asarray(watched, np.int64)] = True
            seen = shown[plan.owner]
            ds.lost(plan, np.flatnonzero(plan.predictive & ~seen))
            ds.put(plan, np.flatnonzero(plan.predictive & seen), self.tick)
            streams.keyframes += int((self._keyframes & seen).sum())
        yield from enc.payloads(watched)

    def watch_rates(self, watching: Watching) -> None:
        self._frames.rates.watch(watching)

    def rate_payloads(
        self, every: int, watched: list[int], streams: PredictiveStreams
    ) -> Iterator[tuple[int, Payload]]:
        """1.8: the decimated payloads of the ``watched`` publications: a publication without a
        predictive cloth, the full-rate bytes; one with, its rate frame's (those first watched
        after this frame was encoded: none yet, the publisher counts them)."""
        plan = self.encoded.plan
        has_pred = np.zeros(len(plan.publications) + 1, bool)  # [-1]: in no publication
        has_pred[plan.owner[plan.predictive]] = True
        w = np.asarray(watched, np.int64)
        plain = w[~has_pred[w]].tolist()
        if plain:
            yield from self.encoded.payloads(plain)
        rf = self._rates.get(every)
        if rf is not None:
            yield from self._frames.rates.payloads(rf, watched, streams, self.tick)

    def release(self) -> None:
        if not self._put and not self._dropped and self._keyframes is not None:  # its states never went out
            plan = self.encoded.plan
            self._frames.streams.lost(plan, np.flatnonzero(plan.predictive))
        self._put = True
        self.encoded.release()
        for rf in self._rates.values():
            self._frames.rates.release(rf)
        self._rates = {}
        super().release()
