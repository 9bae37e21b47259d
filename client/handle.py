"""One submitted cloth of the Python SDK (:class:`ClothHandle`): its state stream (queue,
callbacks, iterators), its controls, and what a failover needs of it (its submission, its last
two states, the last pin targets and colliders sent; ``rebind`` moves it to its new incarnation).
1.8: the rate its states come at (every k-th state on its own key, :meth:`ClothHandle.set_rate`;
with ``rate="auto"`` a rates.RateGovernor steps it down when its states arrive late).

A handle works over the parts its owner (the DrapeClient, :class:`HandleOwner`) gives it: the
Zenoh session its states come on, and the sending path its controls take."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, Unpack

import numpy as np
import zenoh

from . import protocol as P
from .controls import SetOptions, collider, pin_changes, set_changes
from .keyframes import KeyframeQueries
from .protocol import ClothState, DrapeError, Unavailable
from .rates import RateGovernor, fit_rate
from .sending import ControlSender
from .smoothing import ServerClock, sample

log = logging.getLogger("drape.client.sdk")

StateCallback = Callable[[ClothState], None]


class HandleOwner(Protocol):
    """What a handle needs of the client that owns it (a DrapeClient)."""

    @property
    def session(self) -> zenoh.Session: ...  # its states and keyframe queries
    @property
    def sender(self) -> ControlSender: ...  # its controls, its requests, its moves record
    @property
    def keyframes(self) -> KeyframeQueries: ...  # its keyframe queries, one per key in a while
    def forget(self, handle: ClothHandle) -> None: ...  # it closed


class ClothHandle:
    """One submitted cloth: its state stream and its controls. A context manager that removes
    the cloth on exit.

    States arrive on a Zenoh thread. ``on_state`` callbacks run there (keep them short); the
    ``states()`` iterator and ``next_state()`` read a bounded queue (oldest states are dropped,
    and counted in ``dropped``, when the consumer is slower than the tick rate)."""

    def __init__(
        self,
        client: HandleOwner,
        reply: P.SubmitReply,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        queue_size: int = 64,
        server_id: str = "",
        request: P.SubmitRequest | None = None,
        rate: int = 1,
        governed: bool = False,
        served: tuple[int, ...] = P.RATES,
    ) -> None:
        self.client = client
        self.server_id = server_id  # the server holding the cloth now (failover may change it)
        self.request = request  # the submission as sent (what a failover resubmits)
        self.lost = False  # a failover is under way
        self.failovers = 0
        self.last_receipt = time.monotonic()  # of the last state (or of the submit reply)
        self.last_probe = 0.0
        self._prev: ClothState | None = None  # the state before ``_latest`` (velocities for a failover)
        self._fresh = False  # rebound by a failover: the next state starts a new tick sequence
        self._last_pins: dict[int, np.ndarray] = {}  # pinned vertex -> the last target sent
        self._last_colliders: tuple[P.Collider, ...] | None = None
        self._last_mesh: P.MeshCollider | None = request.mesh_collider if request is not None else None  # 1.8, whole
        self.id = reply.cloth
        self.token = reply.token
        self.key = reply.key
        self.bundle_key = reply.bundle_key  # 1.1: the state arrives in the client's bundle, not on ``key``
        self.n_vertices = reply.vertices
        self.first_tick = reply.tick
        self.features: tuple[str, ...] | None = None  # 1.2: as the last waited control's reply reported it
        self.rest_positions = rest_positions
        self.triangles = triangles
        self.received = 0
        self.dropped = 0
        self.invalid = 0
        # 1.5, predictive states: decoded against this stream's last two (protocol.StateStream);
        # a state predicted from one this client lacks is shown extrapolated and counted here
        self.stream = P.StateStream(self.id)
        self.clock = ServerClock()  # render times (client clock) as server times (smoothing.sample)
        self.gaps = 0
        self.keyframe_queries = 0
        self.closed = False
        self.close_reason = ""
        self.removing = False  # this client asked the server to remove it (controls sent before may find it gone)
        self._lock = threading.RLock()  # the state stream's fields
        self._cond = threading.Condition(self._lock)  # a state arrived, or the cloth closed
        self._waiting = 0  # threads waiting on _cond (a state wakes them only when there are any)
        self.deliver_lock = threading.RLock()  # states are delivered one at a time, in order
        self._queue: deque[ClothState] = deque(maxlen=max(1, queue_size))
        self._latest: ClothState | None = None
        self._callbacks: tuple[StateCallback, ...] = ()  # replaced, never changed: deliver reads it as is
        self._sub: Any = None
        # 1.8: every ``rate``-th state, on its own key (a bundled cloth's: its bundle receiver's)
        self.rate = rate
        # the rates its server serves (protocol.served_rates: 1.8's 2 and 3, 1.9's 6 and 12 too; a
        # failover may move it to a server that serves fewer)
        self.served = served
        self.governor = RateGovernor(rate=rate, rates=served) if governed and self.bundle_key is None else None
        if self.bundle_key is None:
            self._sub = self._subscribe(rate)

    @property
    def step_downs(self) -> int:
        """1.8: times ``rate="auto"`` stepped this cloth's states down (a bundled cloth: its bundle's)."""
        return self.governor.step_downs if self.governor is not None else 0

    @property
    def step_ups(self) -> int:
        return self.governor.step_ups if self.governor is not None else 0

    def set_rate(self, rate: int) -> None:
        """1.8: take every ``rate``-th state (protocol.RATES) from now on, on its own key: the
        stream starts afresh with a keyframe asked for; on a server that does not serve ``rate``
        (6 or 12 from a 1.8 server) the served rate below it. A bundled cloth's rate is its
        bundle's (BundleReceiver.set_rate)."""
        if rate not in P.RATES:
            raise ValueError(f"rate {rate!r}: one of {P.RATES}")
        if self.bundle_key is not None:
            raise ValueError("a bundled cloth takes its bundle's rate (DrapeClient.bundles.set_rate)")
        with self._cond:
            rate = fit_rate(rate, self.served)
            if rate == self.rate or self.closed:
                return
            self.rate = rate  # from now on the old key's states are ignored
            self.stream = P.StateStream(self.id)  # the new key's stream: its own states
        new = self._subscribe(rate)  # before the old one goes: no more of a gap than the new key's first state
        with self._cond:
            old, self._sub = self._sub, new
        if old is not None:
            try:
                old.undeclare()
            except Exception:
                pass
        self.ask_keyframe(0.0)

    def _subscribe(self, rate: int) -> Any:
        """A subscriber of this cloth's key at ``rate`` whose states count only while it is the
        handle's rate."""

        def on_sample(sample: zenoh.Sample) -> None:
            if rate == self.rate:
                self._on_sample(sample)

        return self.client.session.declare_subscriber(P.every_key(self.key, rate), on_sample)

    @property
    def bundled(self) -> bool:
        """Whether the state arrives inside the client's bundle (submitted with bundle=True to
        a 1.1 server)."""
        return self.bundle_key is not None

    def __repr__(self) -> str:
        return f"ClothHandle({self.id!r}, {self.n_vertices} vertices{', closed' if self.closed else ''})"

    # --- states ------------------------------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        try:
            st = self._decode(sample.payload.to_bytes(), now)
        except DrapeError as e:
            self.invalid += 1
            log.warning("cloth %s: invalid state payload: %s", self.id, e)
            return
        if st is not None:
            self.deliver(st)
            gov = self.governor
            if gov is not None and len(self.served) > 1 and not st.extrapolated:
                new = gov.observe(st.tick, st.server_time_ns, now)
                if new is not None:  # switched off this thread: its subscriber is undeclared
                    log.info("cloth %s: states every %d ticks from now", self.id, new)
                    threading.Thread(target=self.set_rate, args=(new,), name="drape-rate", daemon=True).start()

    def _decode(self, data: bytes | memoryview, receive_time_ns: int) -> ClothState | None:
        """The state of a payload, through the cloth's stream (1.5: a predictive state needs the
        last two). One predicted from a state this client lacks (lost, or before it subscribed)
        gives the last state extrapolated instead, counts a gap and asks for a keyframe (None
        before any state)."""
        st = self.stream.decode(data, receive_time_ns)
        if st is not None:
            return st
        return self.missing(data, receive_time_ns)

    def missing(self, data: bytes | memoryview, receive_time_ns: int) -> ClothState | None:
        """A state this stream could not decode: counted, a keyframe asked for, the last state
        extrapolated to its tick instead (None before any)."""
        self.gaps += 1
        self.ask_keyframe()
        tick = P.read_state_header(data, len(data))[4]
        return self.stream.extrapolate(tick, receive_time_ns=receive_time_ns)

    def ask_keyframe(self, min_interval_s: float = 0.1) -> bool:
        """1.5: ask the server for a keyframe of this cloth's stream (a query on the key its
        states come on, not waited for); at most one every ``min_interval_s``. Whether asked."""
        key = P.every_key(self.bundle_key or self.key, self.rate)
        if not self.client.keyframes.ask(self.client.session, key, min_interval_s):
            return False  # asked lately, by this cloth or another of its bundle
        self.keyframe_queries += 1
        return True

    def deliver(self, st: ClothState, now: float | None = None) -> None:
        """Queue a state and run the callbacks (on the thread that received it). ``now``: the
        monotonic time of its arrival (one clock read for a whole bundle)."""
        # acquire/release rather than ``with``: half the cost on this path, once per state per tick
        self.deliver_lock.acquire()
        try:
            self._lock.acquire()
            try:
                if self.closed:
                    return
                if self._fresh:
                    self._prev, self._fresh = None, False
                else:
                    self._prev = self._latest
                self._latest = st
                self.clock.observe(st)
                self.last_receipt = time.monotonic() if now is None else now
                queue = self._queue
                if len(queue) == queue.maxlen:
                    self.dropped += 1
                queue.append(st)
                self.received += 1
                if self._waiting:
                    self._cond.notify_all()
                callbacks = self._callbacks
            finally:
                self._lock.release()
            for cb in callbacks:
                try:
                    cb(st)
                except Exception:
                    log.exception("cloth %s: on_state callback failed", self.id)
        finally:
            self.deliver_lock.release()

    def sample(
        self, now_ns: int | None = None, delay: float | None = None, extrapolate: bool = False
    ) -> np.ndarray | None:
        """The positions to draw at render time ``now_ns`` (``time.time_ns()`` by default): the
        last two states interpolated ``delay`` seconds (default: one tick) behind the newest, so
        that a renderer faster than the server moves the cloth every frame, at the cost of that
        delay; ``extrapolate``: carried past the newest state instead (no delay, overshoots where
        the motion turns). None before the first state (client/smoothing.py)."""
        prev, last = self.last_states()
        if last is None:
            return None
        server_ns = self.clock.to_server(time.time_ns() if now_ns is None else now_ns)
        if server_ns is None:
            return last.positions
        delay_ns = None if delay is None else int(delay * 1e9)
        return sample(prev, last, server_ns, delay_ns, extrapolate)

    def last_states(self) -> tuple[ClothState | None, ClothState | None]:
        """The last two states received from the cloth's current server (older, newer; the older
        None when there is only one): what a failover resumes from."""
        with self._cond:
            return (None if self._fresh else self._prev), self._latest

    def rebind(self, reply: P.SubmitReply, server: str, served: tuple[int, ...] = P.RATES) -> None:
        """Failover: the cloth lives on as ``reply.cloth`` on ``server``; states keep flowing to
        this handle (its queue, callbacks and iterators). ``served``: the rates ``server`` serves
        (protocol.served_rates); a rate it does not serve becomes the served one below it (a
        decimated key would carry nothing): the full-rate key on a server older than 1.8, where
        ``rate="auto"`` stays off until a failover onto a 1.8 server, and at most every 3rd state
        on a 1.8 one."""
        old_sub = None
        with self._cond:
            self.served = served
            rate = fit_rate(self.rate, served)
            if rate != self.rate:
                log.info("cloth %s: server %s does not serve every %d: every %d", self.id, server, self.rate, rate)
                self.rate = rate
            if self.governor is not None:
                self.governor.limit(served)
            old_sub, self._sub = self._sub, None
            self.id, self.token, self.key = reply.cloth, reply.token, reply.key
            self.bundle_key = reply.bundle_key
            self.first_tick = reply.tick
            self.server_id = server
            self.last_receipt = time.monotonic()
            self._fresh = True
            self.stream = P.StateStream(reply.cloth)  # the new server's stream starts with a keyframe
        self.client.sender.book.changed()  # cached ids and tokens of moves blocks (1.4) are stale
        if old_sub is not None:
            try:
                old_sub.undeclare()
            except Exception:
                pass
        if self.bundle_key is None:
            self._sub = self._subscribe(self.rate)

    def record_pins(self, indices: list[int], targets: np.ndarray) -> None:
        """Pins ``indices`` were last sent to ``targets`` ((k, 3)): what a failover sends again."""
        self._last_pins.update(zip(indices, targets, strict=True))

    def note_controls(self, changes: dict[str, Any]) -> None:
        """Remember the last pin targets, colliders and mesh collider sent (a failover sends them again)."""
        self.client.sender.book.fold(self)  # moves blocks sent since (1.4) come before this control
        pins = changes.get("pins")
        if pins is not None:
            for i, t in zip(pins.indices.tolist(), np.asarray(pins.targets, np.float32).reshape(-1, 3), strict=True):
                self._last_pins[i] = t
        if changes.get("colliders") is not None:
            self._last_colliders = changes["colliders"]
        mc = changes.get("mesh_collider")
        if mc is not None:  # 1.8: a move or a re-pose of the mesh last set is that mesh at its new pose
            last = self._last_mesh
            if not mc.remove and mc.triangles is None and last is not None and last.triangles is not None:
                verts = last.vertices if mc.vertices is None else mc.vertices
                mc = P.MeshCollider(verts, last.triangles, mc.position, mc.rotation)
            self._last_mesh = mc
        if changes.get("reset"):
            self._last_pins.clear()

    def resend_controls(self) -> None:
        """After a failover: the last pin targets, colliders and mesh collider, again (not waited for)."""
        self.client.sender.book.fold(self)
        changes: dict[str, Any] = {}
        if self._last_pins:
            idx = np.fromiter(self._last_pins, np.uint32, len(self._last_pins))
            changes["pins"] = P.PinUpdate(idx, np.stack(list(self._last_pins.values())).astype(np.float32))
        if self._last_colliders is not None:
            changes["colliders"] = self._last_colliders
        if self._last_mesh is not None and (self._last_mesh.remove or self._last_mesh.triangles is not None):
            changes["mesh_collider"] = self._last_mesh
        if changes:
            link = self.client.sender.session
            req = P.ControlRequest(self.id, self.token, rid=link.next_rid(), **changes)
            link.send("control", P.encode_control(req), server=self.server_id)

    def on_state(self, callback: StateCallback) -> Callable[[], None]:
        """Call ``callback(state)`` for every state (on a Zenoh thread). Returns an unsubscribe function."""
        with self._cond:
            self._callbacks = (*self._callbacks, callback)

        def cancel() -> None:
            with self._cond:
                if callback in self._callbacks:
                    i = self._callbacks.index(callback)
                    self._callbacks = self._callbacks[:i] + self._callbacks[i + 1 :]

        return cancel

    def latest(self) -> ClothState | None:
        """The most recent state received (None before the first)."""
        return self._latest

    def next_state(self, timeout: float | None = None) -> ClothState:
        """The oldest queued state, waiting up to ``timeout`` seconds. Raises TimeoutError, or
        DrapeError when the cloth was removed or the server went away."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._queue:
                if self.closed:
                    raise DrapeError(P.ERR_NOT_FOUND, f"cloth {self.id} is closed: {self.close_reason}")
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise TimeoutError(f"no state for cloth {self.id} within {timeout} s")
                self._waiting += 1
                try:
                    self._cond.wait(remaining)
                finally:
                    self._waiting -= 1
            return self._queue.popleft()

    def states(self, timeout: float | None = None) -> Iterator[ClothState]:
        """Iterate over states as they arrive. Ends when none arrives within ``timeout`` seconds
        (None: wait forever), or when the cloth is removed or its server goes away."""
        while True:
            try:
                yield self.next_state(timeout)
            except (TimeoutError, DrapeError):
                return

    def wait_for_tick(self, tick: int, timeout: float | None = None) -> ClothState:
        """Consume queued states until one with ``state.tick >= tick``."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            st = self.next_state(remaining)
            if st.tick >= tick:
                return st

    def clear(self) -> None:
        """Forget queued states."""
        with self._cond:
            self._queue.clear()

    # --- controls (each returns the first tick whose state reflects it) -------------------------
    def move_pins(
        self,
        indices: Sequence[int] | np.ndarray,
        targets: Sequence[Sequence[float]] | np.ndarray,
        *,
        wait: bool = True,
        colliders: Sequence[Any] | None = None,
    ) -> int | None:
        """Move pinned vertices ``indices`` to ``targets`` ((k, 3) metres) by the end of the next
        tick (and, if given, the colliders with them, in the same message). ``wait=False`` does
        not wait for the reply (see DrapeClient.send): the per-tick call of a game loop."""
        return self._control(wait, **pin_changes(indices, targets, colliders))

    def set_colliders(self, colliders: Sequence[Any], *, wait: bool = True) -> int | None:
        """Replace the cloth's colliders (Sphere, Capsule, Plane of this package or of
        drape.server.sim.params); [] removes them. Colliders move to their new pose over the next tick."""
        return self._control(wait, colliders=tuple(collider(c) for c in colliders))

    def set(self, *, wait: bool = True, **options: Unpack[SetOptions]) -> int | None:
        """Change any of the cloth's settings from the next tick on; fields left None stay as
        they are (``material`` may name only the fields to change; ``quality``: a preset of
        protocol.QUALITY_PRESETS, which sets iterations, substeps, XPBD and tethers).

        ``features`` replaces the whole feature set (dropping, say, ``normals`` the submission
        turned on); ``features_add`` / ``features_remove`` (protocol 1.2) switch only the names
        given. A 1.2 server reports the resulting set, kept in :attr:`features` after a waited
        control. ``encoding="predictive"`` and ``step`` (metres; protocol 1.5) switch to the
        predictive encoding or change its grid: the next state is a keyframe.

        The options (:class:`~drape.client.controls.SetOptions`, one per control field of
        ``protocol.CONTROL_FIELDS`` but pins and colliders): ``gravity``, ``wind`` (3 numbers),
        ``material``, ``features``, ``iterations``, ``substeps``, ``chebyshev_rho``, ``quality``,
        ``features_add``, ``features_remove``, ``reset``, ``mesh_collider`` (1.8: the cloth's own
        mesh collider: a ``(vertices, triangles)`` pair or an object with them, ``False`` to remove
        it, ``P.MeshCollider.pose(position, rotation)`` to move it rigidly, the per-tick change;
        :func:`~drape.client.controls.mesh_collider`), and the state's ``normals``,
        ``encoding`` and ``step``; an unknown name is a TypeError."""
        return self._control(wait, **set_changes(**options))

    def reset(self) -> int:
        """Back to the rest pose with zero velocity."""
        tick = self._control(True, reset=True)
        assert tick is not None  # a waited control answers with a tick
        return tick

    def _control(self, wait: bool, **changes: Any) -> int | None:
        self.check_open()
        sender = self.client.sender
        req = P.ControlRequest(self.id, self.token, rid=sender.session.next_rid(), **changes)
        sender.server_info(self.server_id or None, (req,))  # refused before it is recorded
        self.note_controls(changes)
        rep = sender.control(self, req, wait, checked=True)
        if rep is None:
            return None
        if rep.features is not None:  # 1.2 servers report the feature set after the change
            self.features = rep.features
        return rep.tick

    def remove(self, timeout: float | None = None) -> int | None:
        """Remove the cloth; returns the last tick published for it (None if it was already
        gone). Idempotent."""
        if self.closed:
            return None
        # Set before the request: a control sent without waiting just before it may be applied
        # in the same tick as the removal and answered ``not_found`` before the removal's reply
        # comes (the server removes before it applies the tick's controls); that answer is the
        # expected outcome of this removal, not a failure (see Session.failed).
        self.removing = True
        try:
            link = self.client.sender.session
            rep = link.request(
                "remove",
                P.encode_remove(P.RemoveRequest(self.id, self.token, link.next_rid())),
                timeout=timeout,
                server=self.server_id,
            )
            last: int | None = P.tick_reply_from_map(rep)
        except (P.NotFound, Unavailable):
            last = None
        except BaseException:
            self.removing = False  # refused (forbidden, busy...): the cloth lives on
            raise
        self.mark_closed("removed")
        return last

    def removal_outcome(self, err: DrapeError) -> bool:
        """Whether ``err``, the answer to a request about this cloth, is only the outcome of this
        client's own removal of it (``not_found`` once the removal was asked for)."""
        return self.removing and isinstance(err, P.NotFound)

    def check_open(self) -> None:
        """Raises DrapeError (not_found) once the handle is closed."""
        if self.closed:
            raise DrapeError(P.ERR_NOT_FOUND, f"cloth {self.id} is closed: {self.close_reason}")

    def mark_closed(self, reason: str) -> None:
        """Closed for ``reason`` (removed, its server gone, a failover failed): iterators end."""
        with self._cond:
            if self.closed:
                return
            self.closed = True
            self.close_reason = reason
            self._cond.notify_all()
        self.client.sender.book.changed()
        if self._sub is not None:
            try:
                self._sub.undeclare()
            except Exception:
                pass
        self.client.forget(self)

    def __enter__(self) -> ClothHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.remove()
        except DrapeError as e:
            log.warning("removing cloth %s failed: %s", self.id, e)


__all__ = ["ClothHandle", "HandleOwner", "StateCallback"]
