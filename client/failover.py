"""Failover of the Python SDK (PROTOCOL.md section 11.1): a DrapeClient (``failover=True``, the
default since issue 26) keeps every cloth it submitted alive across the loss of its server.

Detection, on Zenoh threads: the server's liveliness token disappears (the client's server watch
calls :meth:`Failover.server_lost`), or a cloth's states stall and a probe (an empty control)
is answered ``not_found`` (the server reclaimed it while this client was paused or cut off), or
a control of the game is answered ``not_found``.

Recovery, on this module's one worker thread: for each lost cloth, if its own server is live
again (a restart under the same id, or this client's own link came back) the cloth is probed
there first and kept when it still exists; otherwise it is resubmitted, with ``resume`` (its last
received positions and the velocities of its last two states), to the live server the client's
:class:`~drape.client.placement.Placement` ranks first by load (the servers' stats publications
and what this client placed since; not round robin; a refusal tries the next), under the same
:class:`~drape.client.handle.ClothHandle`: its ``id``, ``token``, ``key`` and
``server_id`` change, its queue, callbacks and ``states()`` iterator carry on. The last pin
targets and colliders the game sent are sent again right after. ``on_failover`` callbacks get a
:class:`FailoverEvent` per cloth.

Scenes (1.7, PROTOCOL.md 5.3) stay together and keep their owner: the lost cloths of one scene go
to ONE server, the one holding this client's other cloths of the scene if any is still up, else
the placement's choice. A client that owns the scene (client/scenes.py) resubmits its first cloth
there, which founds the scene, then sends the scene's last state again (members, colliders, mesh
collider, as its ``scene`` requests last set them), then its other cloths. A member waits for the
owner: it resubmits to the live server that holds the scene (found by probing), retrying while
the scene is not there yet or its submission is ``forbidden`` (the owner has not admitted it
again yet); only after ``scene_wait`` seconds without the scene does it found it itself (the owner
is gone too), which makes it the new owner there.

Per state, the handle only keeps references to the last two decoded states (no copies, no
per-vertex Python).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from . import protocol as P
from .connection import Session
from .handle import ClothHandle
from .placement import PLACE_ELSEWHERE, Placement
from .protocol import DrapeError
from .registry import Cloths
from .scenes import SceneBook

log = logging.getLogger(__name__)

DEFAULT_TICK_RATE = 60.0  # Hz, when the lost server's stats never said
SCENE_WAIT = 10.0  # s a member's cloths wait for their scene's owner to found it again


@dataclass(frozen=True)
class FailoverEvent:
    """One cloth's failover: ``reason`` is ``server_lost`` or ``reclaimed``; on success
    ``new_cloth`` / ``new_server`` name where it lives now (``kept``: it was still there) and
    ``resumed_tick`` the tick of the state it continued from (None: started from its rest pose,
    no state had been received); on failure ``error`` says why and the handle is closed.
    ``detected_ns`` / ``done_ns``: time.monotonic_ns() of the detection and of the new reply."""

    handle: ClothHandle
    reason: str
    old_cloth: str
    old_server: str
    new_cloth: str | None = None
    new_server: str | None = None
    resumed_tick: int | None = None
    kept: bool = False
    error: DrapeError | None = None
    detected_ns: int = 0
    done_ns: int = 0

    @property
    def ok(self) -> bool:
        return self.error is None


FailoverCallback = Callable[[FailoverEvent], None]
#: (the lost handle, its resubmission, the server to submit it to) -> the handle, continued
Place = Callable[[ClothHandle, P.SubmitRequest, str], ClothHandle]


def resume_from(states: tuple[Any, Any], from_server: str, cloth: str, tick_rate: float) -> P.ResumeState | None:
    """The ``resume`` of a resubmission from a handle's last two states (older, newer): positions
    of the newer; velocities (x_k - x_{k-1}) / (dt (t_k - t_{k-1})) when both exist and are finite.
    None when no finite state was received (the cloth then starts from its rest pose)."""
    prev, last = states
    if last is None or not np.isfinite(last.positions).all():
        return None
    pos = np.ascontiguousarray(last.positions, np.float32)
    vel = None
    if prev is not None and prev.tick < last.tick and np.isfinite(prev.positions).all():
        dt = (last.tick - prev.tick) / tick_rate
        bound = P.DEFAULT_LIMITS.max_acceleration
        vel = np.clip((last.positions.astype(np.float64) - prev.positions) / dt, -bound, bound).astype(np.float32)
    return P.ResumeState(pos, vel, int(last.tick), from_server, cloth)


class Failover:
    """The failover worker of one DrapeClient (see the module docstring): over its ``session``,
    its open ``cloths``, its ``placement``, and ``place``, its submitter's resubmission."""

    def __init__(
        self,
        session: Session,
        cloths: Cloths,
        placement: Placement,
        place: Place,
        *,
        stall_timeout: float = 0.5,
        give_up_after: float = 60.0,
        scenes: SceneBook | None = None,
        scene_wait: float = SCENE_WAIT,
    ) -> None:
        self.session = session
        self.scenes = scenes if scenes is not None else SceneBook(session)
        self.scene_wait = scene_wait  # a member waits this long for the owner to found the scene again
        self.cloths = cloths
        self.place = place
        self.stall_timeout = stall_timeout  # no state for this long: probe the cloth
        self.give_up_after = give_up_after  # no live server for this long: close the handle
        self.events: list[FailoverEvent] = []
        self._callbacks: list[FailoverCallback] = []
        self._cond = threading.Condition()
        self._lost: dict[int, tuple[ClothHandle, str, str, int]] = {}  # id(handle) -> (handle, server, reason, t)
        self._closed = False
        self._paused = False
        self.placement = placement  # the servers' loads (client/placement.py)
        self.placement.attach(session.zenoh, session.keys)
        self._thread = threading.Thread(target=self._run, name="drape-failover", daemon=True)
        self._thread.start()

    # --- inputs (Zenoh threads) -------------------------------------------------------------
    def server_lost(self, server: str) -> None:
        """The liveliness token of ``server`` vanished: every cloth on it is lost."""
        for h in self.cloths.on(server):
            self.cloth_lost(h, "server_lost")

    def cloth_lost(self, h: ClothHandle, reason: str) -> None:
        with self._cond:
            if h.closed or id(h) in self._lost:
                return
            h.lost = True
            self._lost[id(h)] = (h, h.server_id, reason, time.monotonic_ns())
            self._cond.notify_all()
        log.info("cloth %s on server %s lost (%s): failing over", h.id, h.server_id, reason)

    def pause(self) -> None:
        """Stop acting (detections are still recorded) until :meth:`resume`: what a suspended
        process does; tests use it to stand for a SIGSTOP."""
        with self._cond:
            self._paused = True

    def resume(self) -> None:
        with self._cond:
            self._paused = False
            self._cond.notify_all()

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def on_failover(self, callback: FailoverCallback) -> Callable[[], None]:
        with self._cond:
            self._callbacks.append(callback)

        def cancel() -> None:
            with self._cond:
                if callback in self._callbacks:
                    self._callbacks.remove(callback)

        return cancel

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=5.0)

    # --- the worker ----------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                self._cond.wait(0.1)
                if self._closed:
                    return
                if self._paused:
                    continue
                todo = list(self._lost.values())
            try:
                if todo:
                    self._recover(todo)
                self._watch()
            except Exception:
                log.exception("failover worker")

    def _recover(self, todo: list[tuple[ClothHandle, str, str, int]]) -> None:
        scenes: dict[str, list[tuple[ClothHandle, str, str, int]]] = {}
        for h, old_server, reason, t0 in todo:
            if h.closed:
                self._done(h)
                continue
            live = set(self.session.live_servers())
            if old_server in live and self._still_there(h):  # back, and the cloth with it
                h.lost = False
                self._done(h)
                self._emit(
                    FailoverEvent(
                        h,
                        reason,
                        h.id,
                        old_server,
                        h.id,
                        old_server,
                        None,
                        True,
                        detected_ns=t0,
                        done_ns=time.monotonic_ns(),
                    )
                )
                continue
            scene = h.request.scene if h.request is not None else None
            if scene is None:
                self._resubmit(h, old_server, reason, t0)
            else:
                scenes.setdefault(scene, []).append((h, old_server, reason, t0))
        for scene, items in scenes.items():
            self._recover_scene(scene, items)

    def _recover_scene(self, scene: str, items: list[tuple[ClothHandle, str, str, int]]) -> None:
        """The lost cloths of ``scene`` to one server: the owner's founding the scene again and its
        last state sent before the next; a member's waiting for the scene (module docstring)."""
        owner = self.scenes.owns(scene)
        for h, old_server, reason, t0 in items:
            target = self.cloths.scene_server(scene)  # this client's cloths of it that still live
            founds = target is None
            if target is None and not owner:
                target = self.scenes.locate(scene, self.placement.ranked(wait=False))
                if target is None:
                    if time.monotonic_ns() - t0 < self.scene_wait * 1e9:
                        return  # the owner has not founded it again yet: the next pass
                    log.warning("scene %s: no live server holds it after %.0f s, founding it", scene, self.scene_wait)
                founds = target is None
            if not self._resubmit(h, old_server, reason, t0, target, retry_forbidden=not owner):
                return  # stays lost (the next pass), or given up: the scene's next cloths wait too
            if founds and owner:
                self._replay_scene(scene, h.server_id)

    def _replay_scene(self, scene: str, server: str) -> None:
        """The scene's last state (its owner's scene requests) sent to ``server``, where this
        client's cloth just founded it again."""
        req = self.scenes.get(scene).replay(self.session.client_id, scene, self.session.next_rid())
        if req is None:
            return
        try:
            rep = P.scene_reply_from_map(self.session.request("scene", P.encode_scene(req), None, server))
        except DrapeError as e:
            log.warning("scene %s founded again on server %s, but its state was refused: %s", scene, server, e)
            return
        self.scenes.sent(req, rep)
        log.info("scene %s founded again on server %s with its members and colliders", scene, server)

    def _resubmit(
        self,
        h: ClothHandle,
        old_server: str,
        reason: str,
        t0: int,
        target: str | None = None,
        retry_forbidden: bool = False,
    ) -> bool:
        """Resubmit ``h`` to ``target`` alone, or (None) to the live servers by load; True when it
        was placed. ``retry_forbidden``: a ``forbidden`` (a member's cloth, its scene's owner not
        back yet) leaves it lost for the next pass instead of closing it."""
        tried: set[str] = set()
        last_err: DrapeError | None = None
        if h.request is None:  # a handle made outside DrapeClient.submit: nothing to resubmit
            self._done(h)
            err = DrapeError(P.ERR_NOT_FOUND, f"cloth {h.id} lost and its submission is unknown")
            h.mark_closed(str(err))
            self._emit(
                FailoverEvent(h, reason, h.id, old_server, error=err, detected_ns=t0, done_ns=time.monotonic_ns())
            )
            return False
        fatal = False
        given = target
        while True:
            # the given server, else the least loaded live one (placement counts what this round placed)
            if given is not None:
                target = given if given not in tried and given in self.session.live_servers() else None
            else:
                target = self.placement.choose(tried, wait=False)
            if target is None:
                break
            tried.add(target)
            st = self.placement.stats(old_server) or {}
            resume = resume_from(h.last_states(), old_server, h.id, float(st.get("tick_rate") or DEFAULT_TICK_RATE))
            old_id = h.id
            req = dataclasses.replace(h.request, rid=self.session.next_rid(), resume=resume)
            try:
                self.place(h, req, target)
            except DrapeError as e:
                last_err = e
                log.warning("resubmitting cloth %s to server %s failed: %s", old_id, target, e)
                if e.code in PLACE_ELSEWHERE:  # overloaded, busy, limit_exceeded, no reply: the next server
                    continue
                if retry_forbidden and e.code == P.ERR_FORBIDDEN:  # not admitted again yet: the next pass
                    break
                fatal = True  # the request itself is refused (PROTOCOL.md 11.3): reported at once
                break
            h.failovers += 1
            self._done(h)
            h.lost = False
            h.resend_controls()
            self._emit(
                FailoverEvent(
                    h,
                    reason,
                    old_id,
                    old_server,
                    h.id,
                    target,
                    None if resume is None else resume.tick,
                    False,
                    detected_ns=t0,
                    done_ns=time.monotonic_ns(),
                )
            )
            return True
        if fatal or time.monotonic_ns() - t0 > self.give_up_after * 1e9:
            err = last_err or P.Unavailable(
                P.ERR_UNAVAILABLE, f"no live server to fail cloth {h.id} over to within {self.give_up_after} s"
            )
            self._done(h)
            h.mark_closed(f"failover failed: {err}")
            self._emit(
                FailoverEvent(h, reason, h.id, old_server, error=err, detected_ns=t0, done_ns=time.monotonic_ns())
            )
        # else: stays lost; tried again on the next pass (a server may appear)
        return False

    def _still_there(self, h: ClothHandle) -> bool:
        """Probe with an empty control: True when the server still holds the cloth."""
        try:
            probe = P.ControlRequest(h.id, h.token, rid=self.session.next_rid())
            self.session.request(
                "control", P.encode_control(probe), timeout=min(self.session.timeout, 2.0), server=h.server_id
            )
            return True
        except P.NotFound:
            return False
        except DrapeError:
            return False

    def _watch(self) -> None:
        """Cloths whose states stalled: probed (without waiting); ``not_found`` means reclaimed."""
        now = time.monotonic()
        for h in self.cloths.all():
            if h.lost or now - h.last_receipt < self.stall_timeout or now - h.last_probe < self.stall_timeout:
                continue
            h.last_probe = now
            self._probe_async(h)

    def _probe_async(self, h: ClothHandle) -> None:
        c = self.session
        cloth = h.id
        payload = P.encode_control(P.ControlRequest(cloth, h.token, rid=c.next_rid()))

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.err is None:
                return
            try:
                P.decode_reply(reply.err.payload.to_bytes())
            except P.NotFound:
                if h.id == cloth:
                    self.cloth_lost(h, "reclaimed")
            except Exception:
                pass

        try:
            c.zenoh.get(
                c.key("control", h.server_id),  # the client-scoped key on a 1.4 server
                zenoh.handlers.Callback(on_reply, lambda: None),
                payload=payload,
                timeout=min(c.timeout, 2.0),
            )
        except Exception as e:
            log.debug("probe of cloth %s failed: %s", cloth, e)

    def _done(self, h: ClothHandle) -> None:
        with self._cond:
            self._lost.pop(id(h), None)

    def _emit(self, ev: FailoverEvent) -> None:
        with self._cond:
            self.events.append(ev)
            callbacks = list(self._callbacks)
        if ev.ok:
            log.info(
                "cloth %s of server %s %s as %s on server %s",
                ev.old_cloth,
                ev.old_server,
                "kept" if ev.kept else "resubmitted",
                ev.new_cloth,
                ev.new_server,
            )
        else:
            log.warning("cloth %s of server %s lost: %s", ev.old_cloth, ev.old_server, ev.error)
        for cb in callbacks:
            try:
                cb(ev)
            except Exception:
                log.exception("on_failover callback failed")


__all__ = ["DEFAULT_TICK_RATE", "SCENE_WAIT", "Failover", "FailoverCallback", "FailoverEvent", "Place", "resume_from"]
