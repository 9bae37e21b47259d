"""Commands applied to the World at the start of a tick: what the tick thread does with the intake.

Structural commands first (adds, removes, calls on the World), then each cloth's coalesced
control (a refused one changes nothing; the pin targets of all of them go in one upload), then
the 1.4 moves blocks; replies go into the tick's Job (sent by the publisher around the frame).
Also the removal of cloths (by their client, by the non-finite guard, of vanished clients) and
the answers to whatever is still queued when the tick thread stops. The Applier owns the map of
live cloths by World handle and what the tick loop (ticker.py) reads back from it: the reset
flags of the next frame, the publication changes and the removes answered after the next frame.
Only the tick thread calls it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from drape.client import protocol as P
from drape.client.protocol.requestfields import pins_only

from ...sim import quality
from ...sim.world import World
from ..commands import Add, BatchControl, Call, ControlSlot, Intake, MoveBlock, Remove, SceneColliders
from ..config import ServerConfig
from ..cook.fabrics import FabricStore
from ..publish.publisher import Job
from ..registry import ClothRecord, Registry
from ..replies import Replies, Reply, send
from ..worldparams import changes_params, params_after_control, prepare_mesh, with_preset
from .adaptive import AdaptiveQuality
from .moves import apply_blocks

log = logging.getLogger(__name__)

MAX_DEFER_TICKS = 600  # a control waits at most this many ticks for its kernels, then builds them itself
_DEFER = ("defer", "")  # _apply_control: not applied this tick, kernels being built


class Applier:
    def __init__(
        self,
        config: ServerConfig,
        registry: Registry,
        replies: Replies,
        intake: Intake,
        fabrics: FabricStore,
        adaptive: AdaptiveQuality,
        request_prepare: Callable[[Any, Any], bool] = lambda fabric, params: False,
        on_drop: Callable[[ClothRecord], None] = lambda rec: None,
    ) -> None:
        self.config, self.registry, self.replies, self.intake = config, registry, replies, intake
        self.fabrics, self.adaptive = fabrics, adaptive
        self.world: World | None = None
        self.live: dict[int, ClothRecord] = {}  # by World handle
        self.applied_controls = 0  # coalesced controls applied (one per cloth per tick at most)
        self.reset_flags: set[int] = set()  # handles whose next frame carries the reset flag
        self.pub_changes = 0  # counts changes of a cloth's publication (its roster is rebuilt)
        self.after_next: list[Reply] = []  # remove replies, sent after the next frame
        self.request_prepare = request_prepare  # the cook thread builds a cloth's kernels
        self.on_drop = on_drop  # a cloth left the World

    # --- commands ----------------------------------------------------------------------------------
    def apply(self, job: Job, tick: int) -> None:
        """Everything queued since the last tick; ``tick`` is the last one stepped."""
        for cmd in self.intake.take_structural():
            try:
                self._apply_structural(cmd, job, tick)
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
            self._apply_controls(slots, job, tick + 1)
        blocks = self.intake.take_moves()  # 1.4: after the controls; cloths reset by them keep no move
        if blocks:
            assert self.world is not None
            apply_blocks(self.world, blocks, tick + 1, self.reset_flags, self.registry, job.before)

    def _apply_structural(self, cmd: Any, job: Job, tick: int) -> None:
        w = self.world
        assert w is not None
        if isinstance(cmd, Call):
            try:
                cmd.result = cmd.fn(w)
            except BaseException as e:
                cmd.error = e
            cmd.done.set()
        elif isinstance(cmd, Add):
            self._add(cmd, job, tick)
        elif isinstance(cmd, SceneColliders):  # 1.7: every cloth of the scene, from the next tick
            try:
                mesh = prepare_mesh(w, cmd.mesh, scene=cmd.scene) if cmd.mesh is not None else None  # 1.8
                if cmd.colliders is not None:
                    w.set_scene_colliders(cmd.scene, cmd.colliders)
                if mesh is not None:
                    mesh()
            except ValueError as e:
                job.before.append(self.replies.error(cmd.query, P.ERR_INVALID_VALUE, str(e), cmd.reply.rid))
                return
            cmd.reply.tick = tick + 1
            job.before.append(Reply(cmd.query, P.encode_scene_reply(cmd.reply)))
        elif isinstance(cmd, Remove):
            rec = cmd.record
            if rec.removed or rec.handle is None:
                job.before.append(self.replies.error(cmd.query, P.ERR_NOT_FOUND, f"no cloth {rec.id!r}", cmd.rid))
                return
            last = tick
            self.drop(rec, job)
            # answered after the first frame without the cloth, not right behind its last state:
            # a reply and a publication sent back to back may overtake each other on the wire
            self.after_next.append(Reply(cmd.query, P.encode_remove_reply(P.RemoveReply(last, cmd.rid))))
            log.info("cloth %s removed by client %s", rec.id, rec.client)

    def _add(self, cmd: Add, job: Job, tick: int) -> None:
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
            h = w.add(rec.fabric, params, cmd.positions, cmd.velocities, scene=rec.scene)
            if cmd.colliders is not None:
                w.set_colliders(h, cmd.colliders)
            if cmd.mesh is not None:  # 1.8
                prepare_mesh(w, cmd.mesh, h)()
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
        rep = P.SubmitReply(rec.id, rec.token, rec.key, rec.n_vertices, tick + 1, cmd.rid, rec.bundle_key)
        job.before.append(Reply(cmd.query, P.encode_submit_reply(rep)))
        log.info(
            "cloth %s added for client %s: %d vertices, %d links",
            rec.id,
            rec.client,
            rec.n_vertices,
            rec.fabric.n_links,
        )

    def _apply_controls(self, slots: list[ControlSlot], job: Job, tick: int) -> None:
        """Each cloth's merged control; the pin targets of all of them gathered into one call
        (one upload before the step); ``tick`` is the one they take effect in."""
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
        mesh = None
        if req.mesh_collider is not None:  # 1.8: checked before anything of the control is applied
            try:
                mesh = prepare_mesh(w, req.mesh_collider, h)
            except ValueError as e:
                return P.ERR_INVALID_VALUE, str(e)
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
        if mesh is not None:
            mesh()
        if req.pins is not None and len(req.pins.indices):
            if req.reset:  # the reset puts the pins back: targets before it
                w.set_pin_targets(h, req.pins.indices.astype(np.int64), req.pins.targets)
            else:
                pins[0].append(h)
                pins[1].append(req.pins.indices)
                pins[2].append(req.pins.targets)
        if req.reset:
            w.reset(h)
            self.reset_flags.add(h)
        if req.state is not None and req.state.encoding is not None and req.state.encoding != rec.encoding:
            rec.encoding = req.state.encoding
            self.pub_changes += 1
        if req.state is not None and req.state.step is not None and req.state.step != rec.step:
            rec.step = req.state.step  # a predictive stream's next state is a keyframe on the new grid
            self.pub_changes += 1
        return None

    def _features(self, rec: ClothRecord) -> tuple[str, ...] | None:
        """The cloth's feature set for a 1.2 reply (protocol order)."""
        w = self.world
        cloth = w.cloths.get(rec.handle) if w is not None and rec.handle is not None else None  # type: ignore[arg-type]
        return tuple(cloth.params.features.names()) if cloth is not None else None

    def set_preset(self, rec: ClothRecord, name: str) -> bool:
        w = self.world
        if rec.handle is None or w is None or name == rec.quality:
            return False
        w.set_params(rec.handle, quality.apply_preset(w.cloths[rec.handle].params, name, self.config.tick_rate))
        rec.quality = name
        return True

    # --- removal -----------------------------------------------------------------------------------
    def drop(self, rec: ClothRecord, job: Job) -> None:
        """Take a cloth out of the World and the registry."""
        w = self.world
        assert w is not None
        if rec.handle is not None and self.live.get(rec.handle) is rec:
            w.remove(rec.handle)
            del self.live[rec.handle]
            self.reset_flags.discard(rec.handle)
            if rec.fabric is not None:
                self.fabrics.release(rec.fabric)
        self.on_drop(rec)
        self.registry.unreserve(rec)
        job.removed.append(rec.id)

    def reclaim(self, job: Job, now: float) -> None:
        expired, victims = self.registry.expired(now)
        for rec in victims:
            self.drop(rec, job)
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
