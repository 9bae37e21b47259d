"""The tick thread: the only thread that touches the World.

Ticks follow a monotonic deadline schedule (an overrun skips whole deadlines and counts them as
missed; it never drifts) and are pipelined: tick N waits only for the readback of tick N - 1
(enqueued a tick ago, normally long finished), checks that frame for non-finite cloths (reset
and flagged, or removed when a cloth keeps doing it), applies this tick's commands (structural
ones first, then each cloth's coalesced control), reclaims vanished clients' cloths, enqueues
step N and its readback without waiting, and hands frame N - 1 to the publisher. So the device
steps tick N while the host publishes tick N - 1.

With ``device_encode`` on an OpenCL world, one launch right behind the step encodes every
publication's bytes into one packed buffer, read back once into pinned memory (devencode.py);
its bounds tell the non-finite cloths, reset and encoded again. The reference World keeps the
host path (the publisher's FrameEncoder).

Per tick the Python work is O(commands + changed cloths + non-finite cloths): the frame is one
contiguous array, its publication roster (drape.server.service.publisher.Roster) is rebuilt
only when the World's layout or a cloth's publication changes, and flags are one array.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..sim import quality
from ..sim.fabric import cook_grid
from ..sim.params import ClothParams
from ..sim.shared import vertex_normals
from ..sim.world import PendingFrame, World
from .adaptive import AdaptiveQuality
from .admission import Admission
from .commands import Add, BatchControl, Call, ControlSlot, Intake, MoveBlock, Remove
from .config import ServerConfig
from .cook import FabricStore
from .devencode import DeviceFrames, device_world
from .moves import apply_blocks
from .publisher import Job, Mailbox, Roster
from .registry import ClothRecord, Registry
from .replies import Replies, Reply, send
from .requests import changes_params, params_after_control, pins_only, with_preset
from .telemetry import PhaseTimer

log = logging.getLogger(__name__)

NAN_WARN_EVERY_S = 1.0  # at most one non-finite warning per second (the rest are counted)
MAX_DEFER_TICKS = 600  # a control waits at most this many ticks for its kernels, then builds them itself
_DEFER = ("defer", "")  # _apply_control: not applied this tick, kernels being built


class Ticker:
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
    ) -> None:
        self.config, self.registry, self.replies, self.intake, self.mailbox = config, registry, replies, intake, mailbox
        self.fabrics, self.admission, self.adaptive, self.timers = fabrics, admission, adaptive, timers
        self.make_stats = make_stats
        self.publish_cost: Callable[[], float] = lambda: 0.0
        self.world: World | None = None
        self.live: dict[int, ClothRecord] = {}  # by World handle
        self.tick = 0
        self.failure: BaseException | None = None
        self.stop_event = threading.Event()
        self.applied_controls = 0  # coalesced controls applied (one per cloth per tick at most)
        self._pending: tuple[PendingFrame, Job, float] | None = None  # the frame in flight, its job, host s
        self.device: DeviceFrames | None = None  # device-encoded frames (config device_encode, OpenCL worlds)
        self._roster: Roster | None = None
        self._pub_changes = 0
        self._reset_flags: set[int] = set()
        self._nan_times: dict[str, deque[float]] = {}
        self._nan_warned_at = 0.0
        self._nan_quiet = 0
        self._cost_layout = -1  # layout version of the last frame whose cost was measured
        self._after_next: list[Reply] = []  # remove replies, sent after the next frame
        self._carry: list[Reply] = []  # those of a tick that stepped nothing
        self.request_prepare: Callable[[Any, Any], bool] = lambda fabric, params: False

    # --- set-up ----------------------------------------------------------------------------------
    def warm_up(self) -> None:
        """Build the default kernels before serving so the first submission does not stall a tick."""
        w = self.world
        assert w is not None
        t = time.perf_counter()
        h = w.add(cook_grid(2, 2, pinned=[0]), ClothParams())
        w.set_pin_targets(h, np.array([0]), np.zeros((1, 3)))  # builds the pin-target scatter too
        w.step(self.config.dt)
        w.fetch()
        w.remove(h)
        w.fetch()
        dev = device_world(w, self.config.device_encode)
        if dev is not None:  # the frame encoder's kernels too: the tick thread never compiles
            self.device = DeviceFrames(dev)
            self.device.encoder.build_all()
        log.debug("warm-up took %.3f s", time.perf_counter() - t)

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
                self._apply(job)
                self._reclaim(job, ta)
                tb = time.monotonic()
                self._start_next(job)
                t1 = time.monotonic()
                self.timers["apply"].add(tb - ta)
                self.timers["tick"].add(t1 - t0)
                if self._pending is not None:
                    self._pending = (self._pending[0], self._pending[1], t1 - t0)
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
                    self.stop_event.wait(next_t - now)
        except BaseException as e:  # a device failure: stop serving loudly
            log.exception("tick loop failed")
            self.failure = e
        finally:
            for r in (self._pending[1].after if self._pending is not None else []) + self._carry:
                send(r)  # removes whose next frame will not be published
            self._pending = None  # its frame was never held
            self.shutdown_commands()

    def _finish_previous(self) -> Job:
        """The job of the tick stepped last time: its frame read back, checked, flagged."""
        if self._pending is None:  # nothing was stepped: carries what waited for a next frame
            job = Job(tick=self.tick, time_ns=time.time_ns(), after=self._carry)
            self._carry = []
            return job
        pending, job, host_s = self._pending
        self._pending = None
        t = time.monotonic()
        frame = pending.wait()
        job.frame = frame.hold()
        job.time_ns = time.time_ns()  # PROTOCOL.md: the server time is when the tick was read back
        if self.device is not None and job.roster is not None:  # encoded on the device at enqueue time
            job.encoded = self.device.hold()
            job.encoded.set_time(job.time_ns)
            bad = self.device.nonfinite()
        else:
            bad = frame.nonfinite()
        if len(bad):
            self._non_finite(job, bad)
        waited = time.monotonic() - t
        device_s = pending.device_s
        self.timers["readback"].add(waited)
        self.timers["solve"].add(device_s if device_s is not None else waited)
        # the whole tick's cost: the tick thread's host work, the device's step and readback, and
        # the publisher's encode and put of the frame before (Python in both threads shares the GIL)
        cost = host_s + (device_s if device_s is not None else waited) + self.publish_cost()
        if frame.layout.version == self._cost_layout:  # not a tick of cloths coming or going (rebuilds)
            self.admission.model.observe(cost, int(frame.offsets[-1]))
        self._cost_layout = frame.layout.version
        self.adaptive.observe(cost, job.tick, lambda: list(self.live.values()), self.world, self._set_preset)
        return job

    def _start_next(self, job: Job) -> None:
        """Enqueue the next step and its readback (no waiting); the tick counter moves on."""
        w = self.world
        assert w is not None
        self.tick += 1
        after, self._after_next = self._after_next, []
        if not self.live:
            self._carry = after  # no next frame: sent in the next tick's own publisher pass
            return
        w.step(self.config.dt)
        dev = device_world(w, self.config.device_encode)
        if dev is None:
            pending = w.fetch_async()
        elif self.device is None or self.device.world is not dev:
            self.device = DeviceFrames(dev)
        lay = w.layout()  # the frame's own layout (fetch_async just used it)
        roster = self._roster_for(lay)
        flags = np.zeros(len(lay.handles), np.int64)
        if self._reset_flags:
            idx = [lay.index[h] for h in self._reset_flags if h in lay.index]
            flags[idx] = P.FLAG_RESET
            self._reset_flags.clear()
        job = Job(tick=self.tick, roster=roster, flags=flags, after=after)
        if dev is not None:
            assert self.device is not None  # the server time is stamped after the readback (set_time)
            pending = self.device.encode(roster, lay, self.tick, 0, flags)
        self._pending = (pending, job, 0.0)

    def _roster_for(self, lay) -> Roster:
        version = (lay.version, self._pub_changes)
        if self._roster is not None and self._roster.version == version:
            return self._roster
        recs = [self.live[h] for h in lay.handles.tolist()]
        bundles: dict[str, list[int]] = {}
        singles: list[int] = []
        for i, r in enumerate(recs):
            (bundles.setdefault(r.bundle_key, []) if r.bundle_key else singles).append(i)
        self._roster = Roster(
            version,
            [r.id for r in recs],
            [r.key for r in recs],
            [P.ENCODING_IDS[r.encoding] for r in recs],
            lay.normals.copy(),
            np.array(singles, np.int64),
            [(k, np.array(v, np.int64)) for k, v in bundles.items()],
        )
        return self._roster

    # --- non-finite cloths -------------------------------------------------------------------------
    def _non_finite(self, job: Job, bad: np.ndarray) -> None:
        w = self.world
        assert w is not None and job.frame is not None and job.flags is not None
        frame, now = job.frame, time.monotonic()
        off = frame.offsets
        on_device = job.encoded is not None
        reset: list[tuple[int, Any]] = []  # on the device: (handle, fabric) of reset cloths with normals
        for i in bad.tolist():
            h = int(frame.handles[i])
            rec = self.live.get(h)
            if rec is None or rec.fabric is None:
                continue
            sl = slice(int(off[i]), int(off[i + 1]))
            if not on_device:
                frame.xyz[sl] = rec.fabric.rest_positions
                if frame.nxyz is not None and frame.layout.normals[i]:
                    frame.nxyz[sl] = vertex_normals(rec.fabric.rest_positions, rec.fabric)[0]
            job.flags[i] |= P.FLAG_RESET
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
                self._drop(rec, job)
                continue
            w.reset(h)
            if frame.layout.normals[i]:
                reset.append((h, rec.fabric))
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
        if on_device and self.device is not None and job.encoded is not None:
            # the frame again, the reset cloths at rest with the reset flag (as the host path publishes)
            job.encoded = self.device.reencode(job.encoded, job.tick, job.time_ns, job.flags, reset)

    # --- commands ----------------------------------------------------------------------------------
    def _apply(self, job: Job) -> None:
        for cmd in self.intake.take_structural():
            try:
                self._apply_structural(cmd, job)
            except Exception as e:
                log.exception("applying %s failed", type(cmd).__name__)
                q = getattr(cmd, "query", None)
                if q is not None:
                    job.before.append(
                        self.replies.error(
                            q, P.ERR_INTERNAL, f"internal error: {type(e).__name__}: {e}", getattr(cmd, "rid", 0)
                        )
                    )
        slots = self.intake.take_controls()
        if slots:
            self._apply_controls(slots, job)
        blocks = self.intake.take_moves()  # 1.4: after the controls; cloths reset by them keep no move
        if blocks:
            assert self.world is not None
            apply_blocks(self.world, blocks, self.tick + 1, self._reset_flags, self.registry, job.before)

    def _apply_structural(self, cmd: Any, job: Job) -> None:
        w = self.world
        assert w is not None
        if isinstance(cmd, Call):
            try:
                cmd.result = cmd.fn(w)
            except BaseException as e:
                cmd.error = e
            cmd.done.set()
        elif isinstance(cmd, Add):
            self._add(cmd, job)
        elif isinstance(cmd, Remove):
            rec = cmd.record
            if rec.removed or rec.handle is None:
                job.before.append(self.replies.error(cmd.query, P.ERR_NOT_FOUND, f"no cloth {rec.id!r}", cmd.rid))
                return
            last = self.tick
            self._drop(rec, job)
            # answered after the first frame without the cloth, not right behind its last state:
            # a reply and a publication sent back to back may overtake each other on the wire
            self._after_next.append(Reply(cmd.query, P.encode_remove_reply(P.RemoveReply(last, cmd.rid))))
            log.info("cloth %s removed by client %s", rec.id, rec.client)

    def _add(self, cmd: Add, job: Job) -> None:
        w = self.world
        assert w is not None
        rec = cmd.record
        if rec.removed:  # its client vanished while it was being cooked
            if rec.fabric is not None:
                self.fabrics.release(rec.fabric)
            job.before.append(
                self.replies.error(
                    cmd.query,
                    P.ERR_NOT_FOUND,
                    "cloth was reclaimed before it was added (client liveliness token gone)",
                    cmd.rid,
                )
            )
            return
        assert rec.fabric is not None
        params = cmd.params
        if rec.quality_wanted is not None:
            rec.quality = self.adaptive.preset_for(rec.quality_wanted)
            if rec.quality != rec.quality_wanted:
                params = quality.apply_preset(params, rec.quality, self.config.tick_rate)
        h = None
        try:
            h = w.add(rec.fabric, params, cmd.positions, cmd.velocities)
            if cmd.colliders is not None:
                w.set_colliders(h, cmd.colliders)
        except Exception as e:
            if h is not None:
                w.remove(h)
            self.fabrics.release(rec.fabric)
            self.registry.unreserve(rec)
            if isinstance(e, ValueError):
                job.before.append(self.replies.error(cmd.query, P.ERR_INVALID_VALUE, str(e), cmd.rid))
            else:
                log.exception("adding cloth %s failed", rec.id)
                job.before.append(
                    self.replies.error(
                        cmd.query, P.ERR_INTERNAL, f"adding the cloth failed: {type(e).__name__}", cmd.rid
                    )
                )
            return
        rec.handle = h
        self.live[h] = rec
        rep = P.SubmitReply(rec.id, rec.token, rec.key, rec.n_vertices, self.tick + 1, cmd.rid, rec.bundle_key)
        job.before.append(Reply(cmd.query, P.encode_submit_reply(rep)))
        log.info(
            "cloth %s added for client %s: %d vertices, %d links",
            rec.id,
            rec.client,
            rec.n_vertices,
            rec.fabric.n_links,
        )

    def _apply_controls(self, slots: list[ControlSlot], job: Job) -> None:
        """Each cloth's merged control; the pin targets of all of them gathered into one call
        (one upload before the step)."""
        tick = self.tick + 1
        pins: tuple[list[int], list[np.ndarray], list[np.ndarray]] = ([], [], [])
        deferred: list[ControlSlot] = []
        for slot in slots:
            try:
                err = self._apply_control(slot, pins)
            except Exception as e:  # one cloth's failure must not leave the others unanswered
                log.exception("applying a control of cloth %s failed", slot.record.id)
                err = (P.ERR_INTERNAL, f"internal error: {type(e).__name__}: {e}")
            if err is _DEFER:
                slot.deferred += 1
                deferred.append(slot)
                continue
            self.applied_controls += 1
            feats = self._features(slot.record) if err is None else None
            for waiter, tag in slot.waiters:
                if isinstance(waiter, BatchControl):
                    waiter.results[tag] = (
                        P.BatchItemResult(tick, features=feats if waiter.features else None)
                        if err is None
                        else P.BatchItemResult(None, *err)
                    )
                    if err is not None:
                        self.registry.error(err[0])
                    batch_rep = waiter.one_done(tick)
                    if batch_rep is not None:
                        job.before.append(batch_rep)
                elif err is None:
                    rid, with_features = tag
                    rep = P.ControlReply(tick, rid, feats if with_features else None)
                    job.before.append(Reply(waiter, partial(P.encode_control_reply, rep)))
                else:
                    job.before.append(self.replies.error(waiter, err[0], err[1], tag[0]))
        if pins[0]:
            assert self.world is not None
            self.world.set_pin_targets_many(*pins, validated=True)  # checked by the handlers and the decoder
        if deferred:
            self.intake.requeue(deferred)
            slots = [s for s in slots if s not in deferred]
        self.registry.count_many(controls_applied=len(slots), controls_coalesced=sum(s.merged - 1 for s in slots))

    def _apply_control(
        self, slot: ControlSlot, pins: tuple[list[int], list[np.ndarray], list[np.ndarray]]
    ) -> tuple[str, str] | None:
        """Apply one cloth's merged control: None, or (code, message) when it is refused now (the
        cloth went away, or its new parameters are invalid); nothing of a refused control is applied."""
        w = self.world
        assert w is not None
        rec, req = slot.record, slot.req
        if rec.removed or rec.handle is None or rec.handle not in self.live:
            return P.ERR_NOT_FOUND, f"no cloth {rec.id!r}"
        h = rec.handle
        if pins_only(req):  # the per-tick game-loop control: nothing but pin targets
            pins[0].append(h)
            pins[1].append(req.pins.indices)  # type: ignore[union-attr]
            pins[2].append(req.pins.targets)  # type: ignore[union-attr]
            return None
        p = w.cloths[h].params
        if changes_params(req, p):
            try:
                new = params_after_control(req, p)
            except ValueError as e:
                return P.ERR_INVALID_VALUE, str(e)
            if req.quality is not None:
                eff = self.adaptive.preset_for(req.quality)
                try:
                    with_preset(self.config, new, req.quality, req.rid)  # within this server's limits?
                    new = with_preset(self.config, new, eff, req.rid)
                except P.DrapeError as e:
                    return e.code, e.message
                rec.quality_wanted, rec.quality = req.quality, eff
            if (
                new.features != p.features
                and slot.deferred < MAX_DEFER_TICKS
                and rec.fabric is not None
                and not w.ready(rec.fabric, new)
            ):
                self.request_prepare(rec.fabric, new)  # the cook thread builds; applied once built
                return _DEFER
            if new != p:
                w.set_params(h, new)
        if slot.colliders is not None:
            w.set_colliders(h, slot.colliders)
        if req.pins is not None and len(req.pins.indices):
            if req.reset:  # the reset puts the pins back: targets before it
                w.set_pin_targets(h, req.pins.indices.astype(np.int64), req.pins.targets)
            else:
                pins[0].append(h)
                pins[1].append(req.pins.indices)
                pins[2].append(req.pins.targets)
        if req.reset:
            w.reset(h)
            self._reset_flags.add(h)
        if req.state is not None and req.state.encoding is not None and req.state.encoding != rec.encoding:
            rec.encoding = req.state.encoding
            self._pub_changes += 1
        return None

    def _features(self, rec: ClothRecord) -> tuple[str, ...] | None:
        """The cloth's feature set for a 1.2 reply (protocol order)."""
        w = self.world
        cloth = w.cloths.get(rec.handle) if w is not None and rec.handle is not None else None  # type: ignore[arg-type]
        return tuple(cloth.params.features.names()) if cloth is not None else None

    def _set_preset(self, rec: ClothRecord, name: str) -> bool:
        w = self.world
        if rec.handle is None or w is None or name == rec.quality:
            return False
        w.set_params(rec.handle, quality.apply_preset(w.cloths[rec.handle].params, name, self.config.tick_rate))
        rec.quality = name
        return True

    # --- removal -----------------------------------------------------------------------------------
    def _drop(self, rec: ClothRecord, job: Job) -> None:
        """Take a cloth out of the World and the registry."""
        w = self.world
        assert w is not None
        if rec.handle is not None and self.live.get(rec.handle) is rec:
            w.remove(rec.handle)
            del self.live[rec.handle]
            self._reset_flags.discard(rec.handle)
            if rec.fabric is not None:
                self.fabrics.release(rec.fabric)
        self._nan_times.pop(rec.id, None)
        self.registry.unreserve(rec)
        job.removed.append(rec.id)

    def _reclaim(self, job: Job, now: float) -> None:
        expired, victims = self.registry.expired(now)
        for rec in victims:
            self._drop(rec, job)
        if victims:
            self.registry.count("reclaimed", len(victims))
            log.info("reclaimed %d cloth(s) of vanished client(s) %s", len(victims), expired)

    def shutdown_commands(self) -> None:
        """Answer everything still queued once the tick thread stops."""
        structural, slots = self.intake.drain()
        answered: set[int] = set()
        for cmd in structural:
            if isinstance(cmd, MoveBlock):
                for w in (cmd.waiter, *cmd.superseded):
                    if id(w) not in answered:
                        answered.add(id(w))
                        send(self.replies.error(w.query, P.ERR_BUSY, "server is shutting down", w.rid))
            elif isinstance(cmd, Call):
                cmd.error = RuntimeError("server stopped")
                cmd.done.set()
            elif getattr(cmd, "query", None) is not None:
                if isinstance(cmd, Add) and cmd.record.fabric is not None:
                    self.fabrics.release(cmd.record.fabric)
                    self.registry.unreserve(cmd.record)
                send(self.replies.error(cmd.query, P.ERR_BUSY, "server is shutting down", getattr(cmd, "rid", 0)))
        for slot in slots:
            for waiter, tag in slot.waiters:
                if isinstance(waiter, BatchControl):
                    if id(waiter) not in answered:
                        answered.add(id(waiter))
                        send(self.replies.error(waiter.query, P.ERR_BUSY, "server is shutting down", waiter.rid))
                else:
                    send(self.replies.error(waiter, P.ERR_BUSY, "server is shutting down", tag[0]))
