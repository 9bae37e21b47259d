"""The tick thread: the only thread that touches the World.

Ticks follow a monotonic deadline schedule (an overrun skips whole deadlines and counts them as
missed; it never drifts) and are pipelined: tick N waits only for the readback of tick N - 1
(enqueued a tick ago, normally long finished), checks that frame for non-finite cloths (reset
and flagged, or removed when a cloth keeps doing it), applies this tick's commands and reclaims
vanished clients' cloths (both applier.py), enqueues step N and its readback without waiting,
and hands frame N - 1 to the publisher. So the device steps tick N while the host publishes
tick N - 1.

One frame path: the World's ``fetch_async(roster, tick)`` gives the tick's wire-ready payloads
(drape.server.sim.wire; encoded on the device or on the host, the World's choice), the
non-finite cloths among them, and puts the cloths the World reset back at rest in them.

Per tick the Python work is O(commands + changed cloths + non-finite cloths): its publication
roster (drape.server.sim.roster.Roster) is rebuilt only when the World's layout or a cloth's
publication changes, and flags are one array.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from drape.client import protocol as P

from ...sim.roster import Roster
from ...sim.wire import PendingWire
from ...sim.world import World
from ..commands import Intake
from ..config import ServerConfig
from ..cook.fabrics import FabricStore
from ..process.telemetry import PhaseTimer
from ..publish.publisher import Job, Mailbox
from ..registry import ClothRecord, Registry
from ..replies import Replies, Reply, send
from ..requests.admission import Admission
from ..requests.admission_model import TickCost
from .adaptive import AdaptiveQuality
from .applier import Applier

log = logging.getLogger(__name__)

NAN_WARN_EVERY_S = 1.0  # at most one non-finite warning per second (the rest are counted)


class Ticker:
    """The tick thread's loop over the World given by :meth:`attach` (made when the server
    starts, after its parts). Its parts come in the constructor: ``publish_cost`` (the
    publisher's encode and put of its last frame), ``request_prepare`` (the cook thread's
    kernel builds, asked for by a submission whose kernels are not built) and ``on_sleep``
    (called with True before the sleep between ticks and False after it: the request gate)."""

    def __init__(
        self,
        config: ServerConfig,
        registry: Registry,
        replies: Replies,
        intake: Intake,
        mailbox: Mailbox,
        fabrics: FabricStore,
        admission: Admission,
        adaptive: AdaptiveQuality,
        timers: dict[str, PhaseTimer],
        make_stats: Callable[[], bytes],
        publish_cost: Callable[[], float],
        request_prepare: Callable[[Any, Any], bool],
        on_sleep: Callable[[bool], None] | None = None,
    ) -> None:
        self.config, self.registry, self.replies, self.intake, self.mailbox = config, registry, replies, intake, mailbox
        self.admission, self.adaptive, self.timers = admission, adaptive, timers
        self.make_stats, self.publish_cost = make_stats, publish_cost
        self.on_sleep: Callable[[bool], None] = on_sleep or (lambda sleeping: None)
        # the tick's commands
        self.applier = Applier(config, registry, replies, intake, fabrics, adaptive, request_prepare, self._forget)
        self.world: World | None = None
        self.tick = 0
        self.failure: BaseException | None = None
        self.stop_event = threading.Event()
        self._pending: tuple[PendingWire, Job, float] | None = None  # the frame in flight, its job, host s
        self._roster: Roster | None = None
        self._nan_times: dict[str, deque[float]] = {}
        self._nan_warned_at = 0.0
        self._nan_quiet = 0
        self._cost_layout = -1  # layout version of the last frame whose cost was measured
        self._work_at: tuple[tuple[int, int], int] = ((-1, -1), 0)  # (layout version, admission generation): work
        self._wait_s = 0.0  # the tick thread's wait for the device in the tick that enqueued the pending frame
        self._carry: list[Reply] = []  # remove replies of a tick that stepped nothing
        self._reset_next = np.zeros(0, np.int64)  # frame indices of the frame in flight carrying the reset flag

    def attach(self, world: World) -> None:
        """The World this ticker drives (and its applier applies commands to), once, before ``run``."""
        self.world = self.applier.world = world

    # --- set-up ----------------------------------------------------------------------------------
    # --- the loop --------------------------------------------------------------------------------
    def run(self) -> None:
        cfg = self.config
        period = cfg.dt
        next_t = time.monotonic()
        next_stats = next_t + cfg.stats_period
        try:
            while not self.stop_event.is_set():
                t0 = time.monotonic()
                job = self._finish_previous()
                ta = time.monotonic()
                self.applier.apply(job, self.tick)
                self.applier.reclaim(job, ta)
                tb = time.monotonic()
                self._start_next(job)
                t1 = time.monotonic()
                self.timers["apply"].add(tb - ta)
                if self._pending is not None:
                    self._pending = (self._pending[0], self._pending[1], t1 - t0)
                    if not cfg.pipeline:  # this tick's own frame, read back and published now
                        job = self._merged(job, self._finish_previous())
                        t1 = time.monotonic()
                self.timers["tick"].add(t1 - t0)
                self.registry.count("ticks")
                if t1 >= next_stats:
                    job.stats = self.make_stats()
                    next_stats += cfg.stats_period
                    if next_stats <= t1:  # fell behind (a long stall): restart the schedule
                        next_stats = t1 + cfg.stats_period
                if self.mailbox.put(job):
                    self.registry.count("skipped_frames")
                next_t += period
                now = time.monotonic()
                if now > next_t:
                    missed = int((now - next_t) / period)
                    if missed:
                        self.registry.count("missed_ticks", missed)
                        next_t += missed * period
                else:
                    self.on_sleep(True)  # the request thread may start requests (requestq.TickGate)
                    self.stop_event.wait(next_t - now)
                    self.on_sleep(False)
        except BaseException as e:  # a device failure: stop serving loudly
            log.exception("tick loop failed")
            self.failure = e
        finally:
            for r in (self._pending[1].after if self._pending is not None else []) + self._carry:
                send(r)  # removes whose next frame will not be published
            self._pending = None  # its frame was never held
            self.applier.shutdown_commands()

    @staticmethod
    def _merged(first: Job, frame: Job) -> Job:
        """``pipeline = false``: the replies of the commands just applied (``first``, a job with
        no frame) sent with the frame stepped after them, before its states."""
        frame.before = first.before + frame.before
        frame.removed = first.removed + frame.removed
        frame.after = first.after + frame.after
        return frame

    def _finish_previous(self) -> Job:
        """The job of the tick stepped last time: its frame read back, checked, flagged."""
        if self._pending is None:  # nothing was stepped: carries what waited for a next frame
            job = Job(tick=self.tick, after=self._carry)
            self._carry = []
            self._wait_s = 0.0
            return job
        pending, job, host_s = self._pending
        self._pending = None
        busy_s = host_s - self._wait_s  # the tick thread's own work in the tick that enqueued this frame
        t = time.monotonic()
        wire = pending.wait()
        self._wait_s = time.monotonic() - t
        job.wire = wire.hold()
        wire.set_time(time.time_ns())  # PROTOCOL.md: the server time is when the tick was read back
        older = self.mailbox.withdraw()  # the frame before, not taken by the publisher: dropped now
        if older is not None:
            job.drop_older(older)
            self.registry.count("skipped_frames")
        if len(self._reset_next):
            wire.add_flags(self._reset_next, P.FLAG_RESET)
            self._reset_next = np.zeros(0, np.int64)
        bad = wire.nonfinite()
        if len(bad):
            self._non_finite(job, bad)
        frame = wire.frame
        waited = time.monotonic() - t
        device_s = pending.device_s
        self.timers["readback"].add(waited)
        self.timers["solve"].add(device_s if device_s is not None else waited)
        # the whole tick's cost: the tick thread's host work, the device's step and readback, and
        # the publisher's encode and put of the frame before (Python in both threads shares the GIL)
        cost = host_s + (device_s if device_s is not None else waited) + self.publish_cost()
        if frame.layout.version == self._cost_layout:  # not a tick of cloths coming or going (rebuilds)
            # admission: each pipeline stage on its own (the period is bounded by the slowest)
            stage_device = device_s if device_s is not None else self._wait_s
            # without the pipeline the tick thread waits for the device within the tick: one stage
            stage_tick = busy_s if self.config.pipeline else busy_s + stage_device
            cost_now = TickCost(self._work(frame.layout.version), stage_tick, stage_device, self.publish_cost())
            self.admission.model.observe(cost_now)
        self._cost_layout = frame.layout.version
        self.adaptive.observe(
            cost, job.tick, lambda: list(self.applier.live.values()), self.world, self.applier.set_preset
        )
        return job

    def _work(self, version: int) -> int:
        """The work units of the cloths stepped (admission's prices and their scenes'
        inter-collision, requests/admission.py): summed once per layout and change of a price, not
        per tick."""
        key = (version, self.admission.generation)
        if self._work_at[0] != key:
            self._work_at = (key, round(self.admission.total_work(self.applier.live.values())))
        return self._work_at[1]

    def _start_next(self, job: Job) -> None:
        """Enqueue the next step and its readback (no waiting); the tick counter moves on."""
        w = self.world
        assert w is not None
        self.tick += 1
        after, self.applier.after_next = self.applier.after_next, []
        if not self.applier.live:
            self._carry = after  # no next frame: sent in the next tick's own publisher pass
            return
        w.step(self.config.dt)
        lay = w.layout()
        roster = self._roster_for(lay)
        reset_flags = self.applier.reset_flags
        if reset_flags:  # the cloths the applier reset: flagged in the frame once it is back
            self._reset_next = np.array([lay.index[h] for h in reset_flags if h in lay.index], np.int64)
            reset_flags.clear()
        job = Job(tick=self.tick, after=after)
        self._pending = (w.fetch_async(roster, self.tick), job, 0.0)

    def _roster_for(self, lay) -> Roster:
        version = (lay.version, self.applier.pub_changes)
        if self._roster is not None and self._roster.version == version:
            return self._roster
        live = self.applier.live
        self._roster = Roster.of(version, [live[h] for h in lay.handles.tolist()], lay.normals)
        return self._roster

    # --- non-finite cloths -------------------------------------------------------------------------
    def _forget(self, rec: ClothRecord) -> None:
        """A cloth left the World: its non-finite history goes with it."""
        self._nan_times.pop(rec.id, None)

    def _non_finite(self, job: Job, bad: np.ndarray) -> None:
        w, wire = self.world, job.wire
        assert w is not None and wire is not None
        frame, now = wire.frame, time.monotonic()
        at_rest: list[tuple[int, Any]] = []  # (frame index, fabric): at rest with the reset flag in the frame
        for i in bad.tolist():
            h = int(frame.handles[i])
            rec = self.applier.live.get(h)
            if rec is None or rec.fabric is None:
                continue
            at_rest.append((i, rec.fabric))
            times = self._nan_times.setdefault(rec.id, deque())
            times.append(now)
            while times and now - times[0] > self.config.nan_window:
                times.popleft()
            if len(times) > self.config.nan_max_resets:
                log.warning(
                    "cloth %s of client %s went non-finite %d times in %.0f s: removed",
                    rec.id,
                    rec.client,
                    len(times),
                    self.config.nan_window,
                )
                self.registry.count("nan_removals")
                self.registry.bury(
                    rec.id,
                    f"removed by the server: its state went non-finite {len(times)} times "
                    f"in {self.config.nan_window:.0f} s",
                )
                self.applier.drop(rec, job)
                continue
            w.reset(h)
            self.registry.count("nan_resets")
            if now - self._nan_warned_at >= NAN_WARN_EVERY_S:
                more = f" ({self._nan_quiet} more since the last warning)" if self._nan_quiet else ""
                log.warning(
                    "cloth %s of client %s went non-finite at tick %d: reset to its rest pose%s",
                    rec.id,
                    rec.client,
                    job.tick,
                    more,
                )
                self._nan_warned_at, self._nan_quiet = now, 0
            else:
                self._nan_quiet += 1
        wire.reset(at_rest)
