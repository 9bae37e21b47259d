"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state.

    from drape.client import DrapeClient

    with DrapeClient("tcp/127.0.0.1:7447") as client:
        with client.submit_grid(16, 16, pinned=[0, 15]) as cloth:
            for state in cloth.states(timeout=1.0):
                draw(state.positions)            # (256, 3) float32
                cloth.move_pins([0, 15], [[0, 0, 0], [1, 0, 0]])

Needs numpy, msgpack and eclipse-zenoh only: nothing here imports drape.server or OpenCL.
"""
from __future__ import annotations

import itertools
import json
import logging
import secrets
import threading
import time
from collections import deque
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import zenoh

from . import protocol as P
from .protocol import ClothState, DrapeError, Unavailable

log = logging.getLogger(__name__)

StateCallback = Callable[[ClothState], None]


def zenoh_config(
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    multicast_scouting: bool = False,
    base_file: str | None = None,
) -> zenoh.Config:
    """A Zenoh configuration: ``base_file`` (JSON5: TLS, auth, access control...) if given,
    then mode, listen and connect endpoints and multicast scouting set explicitly."""
    cfg = zenoh.Config.from_file(base_file) if base_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    if mode != "client":
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    return cfg


class ClothHandle:
    """One submitted cloth: its state stream and its controls. A context manager that removes
    the cloth on exit.

    States arrive on a Zenoh thread. ``on_state`` callbacks run there (keep them short); the
    ``states()`` iterator and ``next_state()`` read a bounded queue (oldest states are dropped,
    and counted in ``dropped``, when the consumer is slower than the tick rate)."""

    def __init__(
        self,
        client: "DrapeClient",
        reply: P.SubmitReply,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        queue_size: int = 64,
    ) -> None:
        self.client = client
        self.id = reply.cloth
        self.token = reply.token
        self.key = reply.key
        self.n_vertices = reply.vertices
        self.first_tick = reply.tick
        self.rest_positions = rest_positions
        self.triangles = triangles
        self.received = 0
        self.dropped = 0
        self.invalid = 0
        self.closed = False
        self.close_reason = ""
        self._cond = threading.Condition()
        self._queue: deque[ClothState] = deque(maxlen=max(1, queue_size))
        self._latest: ClothState | None = None
        self._callbacks: list[StateCallback] = []
        self._sub = client.session.declare_subscriber(self.key, self._on_sample)

    def __repr__(self) -> str:
        return f"ClothHandle({self.id!r}, {self.n_vertices} vertices{', closed' if self.closed else ''})"

    # --- states ------------------------------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        try:
            st = P.decode_state(sample.payload.to_bytes(), self.id, now)
        except DrapeError as e:
            self.invalid += 1
            log.warning("cloth %s: invalid state payload: %s", self.id, e)
            return
        with self._cond:
            if self.closed:
                return
            self._latest = st
            if len(self._queue) == self._queue.maxlen:
                self.dropped += 1
            self._queue.append(st)
            self.received += 1
            self._cond.notify_all()
            callbacks = list(self._callbacks)
        for cb in callbacks:
            try:
                cb(st)
            except Exception:
                log.exception("cloth %s: on_state callback failed", self.id)

    def on_state(self, callback: StateCallback) -> Callable[[], None]:
        """Call ``callback(state)`` for every state (on a Zenoh thread). Returns an unsubscribe function."""
        with self._cond:
            self._callbacks.append(callback)

        def cancel() -> None:
            with self._cond:
                if callback in self._callbacks:
                    self._callbacks.remove(callback)

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
                self._cond.wait(remaining)
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
    def move_pins(self, indices: Sequence[int] | np.ndarray, targets: Sequence[Sequence[float]] | np.ndarray,
                  *, wait: bool = True, colliders: Sequence[Any] | None = None) -> int | None:
        """Move pinned vertices ``indices`` to ``targets`` ((k, 3) metres) by the end of the next
        tick (and, if given, the colliders with them, in the same message). ``wait=False`` does
        not wait for the reply (see DrapeClient.send): the per-tick call of a game loop."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        tgt = np.asarray(targets, np.float32).reshape(-1, 3)
        if len(idx) != len(tgt):
            raise ValueError(f"{len(idx)} indices but {len(tgt)} targets")
        if idx.size and idx.min() < 0:
            raise ValueError("pin indices must be >= 0")
        extra = {"colliders": tuple(_collider(c) for c in colliders)} if colliders is not None else {}
        return self._control(wait, pins=P.PinUpdate(idx.astype(np.uint32), tgt), **extra)

    def set_colliders(self, colliders: Sequence[Any], *, wait: bool = True) -> int | None:
        """Replace the cloth's colliders (Sphere, Capsule, Plane of this package or of
        drape.server.params); [] removes them. Colliders move to their new pose over the next tick."""
        return self._control(wait, colliders=tuple(_collider(c) for c in colliders))

    def set(
        self,
        *,
        gravity: Sequence[float] | None = None,
        wind: Sequence[float] | None = None,
        material: Mapping[str, Any] | Any = None,
        features: Iterable[str] | None = None,
        iterations: int | None = None,
        substeps: int | None = None,
        chebyshev_rho: float | None = None,
        normals: bool | None = None,
        encoding: str | None = None,
        reset: bool = False,
        wait: bool = True,
    ) -> int | None:
        """Change any of the cloth's settings from the next tick on; fields left None stay as
        they are (``material`` may name only the fields to change)."""
        state = P.StateOptions(normals, encoding) if (normals is not None or encoding is not None) else None
        return self._control(
            wait,
            gravity=_vec3(gravity),
            wind=_vec3(wind),
            material=P.material_to_map(material) if material is not None else {},
            features=tuple(features) if features is not None else None,
            iterations=iterations,
            substeps=substeps,
            chebyshev_rho=chebyshev_rho,
            state=state,
            reset=reset,
        )

    def reset(self) -> int:
        """Back to the rest pose with zero velocity."""
        return self._control(True, reset=True)

    def _control(self, wait: bool, **changes: Any) -> int | None:
        self._check_open()
        req = P.ControlRequest(self.id, self.token, rid=self.client._next_rid(), **changes)
        if not wait:
            self.client.send("control", P.encode_control(req))
            return None
        rep = self.client.request("control", P.encode_control(req))
        return P.tick_reply_from_map(rep)

    def remove(self, timeout: float | None = None) -> int | None:
        """Remove the cloth; returns the last tick published for it (None if it was already
        gone). Idempotent."""
        if self.closed:
            return None
        try:
            rep = self.client.request("remove", P.encode_remove(P.RemoveRequest(self.id, self.token, self.client._next_rid())),
                                      timeout=timeout)
            last: int | None = P.tick_reply_from_map(rep)
        except (P.NotFound, Unavailable):
            last = None
        self._close("removed")
        return last

    def _check_open(self) -> None:
        if self.closed:
            raise DrapeError(P.ERR_NOT_FOUND, f"cloth {self.id} is closed: {self.close_reason}")

    def _close(self, reason: str) -> None:
        with self._cond:
            if self.closed:
                return
            self.closed = True
            self.close_reason = reason
            self._cond.notify_all()
        try:
            self._sub.undeclare()
        except Exception:
            pass
        self.client._forget(self)

    def __enter__(self) -> "ClothHandle":
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.remove()
        except DrapeError as e:
            log.warning("removing cloth %s failed: %s", self.id, e)


class DrapeClient:
    """A Zenoh session to a Drape server, with this client's liveliness token.

    ``connect``: endpoints of the server (or of a router); default tcp/127.0.0.1:7447.
    ``server_id``: the server to talk to; None picks the one whose liveliness token is seen
    (waiting up to ``timeout``). ``client_id``: this client's id (default: random); its
    liveliness token tells the server the client is alive: when it disappears for longer than
    the server's grace period, the server reclaims the client's cloths."""

    def __init__(
        self,
        connect: str | Sequence[str] | None = None,
        *,
        listen: Sequence[str] = (),
        mode: str = "peer",
        namespace: str = P.DEFAULT_NAMESPACE,
        server_id: str | None = None,
        client_id: str | None = None,
        timeout: float = 5.0,
        multicast_scouting: bool = False,
        zenoh_config_file: str | None = None,
        queue_size: int = 64,
    ) -> None:
        if connect is None:
            connect = [P.DEFAULT_ENDPOINT]
        elif isinstance(connect, str):
            connect = [connect]
        self.keys = P.Keys(namespace)
        self.client_id = client_id or f"c{secrets.token_hex(8)}"
        if not P.valid_id(self.client_id):
            raise ValueError(f"invalid client id {self.client_id!r}")
        if server_id is not None and not P.valid_id(server_id):
            raise ValueError(f"invalid server id {server_id!r}")
        self.timeout = timeout
        self.queue_size = queue_size
        self._server_id = server_id
        self._rid = itertools.count(1)
        self._lock = threading.Lock()
        self._handles: dict[str, ClothHandle] = {}
        self._servers: set[str] = set()
        self._servers_cond = threading.Condition(self._lock)
        self._closed = False
        self.send_errors = 0  # replies to send() that were errors, or that never came
        self.session: zenoh.Session = zenoh.open(
            zenoh_config(mode, listen, list(connect), multicast_scouting, zenoh_config_file)
        )
        lv = self.session.liveliness()
        self._server_watch = lv.declare_subscriber(self.keys.all_servers_alive, self._on_server, history=True)
        self._token = lv.declare_token(self.keys.alive_client(self.client_id))
        log.debug("drape client %s connected to %s", self.client_id, list(connect))

    # --- session ------------------------------------------------------------------------------
    def __enter__(self) -> "DrapeClient":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self, remove: bool = True) -> None:
        """Remove this client's open cloths (unless ``remove`` is False), withdraw the
        liveliness token and close the session. Idempotent."""
        if self._closed:
            return
        if remove:
            for h in list(self._handles.values()):
                try:
                    h.remove(timeout=min(self.timeout, 2.0))
                except DrapeError as e:
                    log.debug("removing %s on close: %s", h.id, e)
        self._closed = True
        for obj in (self._token, self._server_watch):
            try:
                obj.undeclare()
            except Exception:
                pass
        self.session.close()

    @property
    def closed(self) -> bool:
        return self._closed

    def _on_server(self, sample: zenoh.Sample) -> None:
        sid = self.keys.last_chunk(str(sample.key_expr))
        gone: list[ClothHandle] = []
        with self._servers_cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._servers.add(sid)
                self._servers_cond.notify_all()
            else:
                self._servers.discard(sid)
                if sid == self._server_id:
                    gone = list(self._handles.values())
        for h in gone:
            h._close(f"server {sid} went away")

    @property
    def server_id(self) -> str:
        """The server this client talks to (found through liveliness when not given)."""
        if self._server_id is None:
            with self._servers_cond:
                self._servers_cond.wait_for(lambda: bool(self._servers), self.timeout)
                if not self._servers:
                    raise Unavailable(P.ERR_UNAVAILABLE, f"no Drape server seen in namespace {self.keys.namespace!r} "
                                      f"within {self.timeout} s")
                found = sorted(self._servers)
                if len(found) > 1:
                    log.warning("several Drape servers %s: using %s (pass server_id to choose)", found, found[0])
                self._server_id = found[0]
        return self._server_id

    def servers(self, timeout: float = 1.0) -> list[str]:
        """Ids of the servers whose liveliness tokens are visible now."""
        replies = self.session.liveliness().get(self.keys.all_servers_alive, timeout=timeout)
        return sorted({self.keys.last_chunk(str(r.ok.key_expr)) for r in replies if r.ok is not None})

    def _next_rid(self) -> int:
        return next(self._rid)

    def _forget(self, handle: ClothHandle) -> None:
        with self._lock:
            self._handles.pop(handle.id, None)

    # --- requests -----------------------------------------------------------------------------
    def request(self, kind: str, payload: bytes | bytearray, timeout: float | None = None) -> dict[str, Any]:
        """Send a raw request payload to the server's ``kind`` queryable (submit, control,
        remove, info) and return the success reply's map; raises the DrapeError subclass of
        an error reply, or Unavailable when no server answers in time."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        key = getattr(self.keys, kind)(self.server_id)
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            started = time.monotonic()
            replies = list(self.session.get(key, payload=bytes(payload), timeout=max(remaining, 0.01)))
            for r in replies:
                if r.ok is not None:
                    return P.decode_reply(r.ok.payload.to_bytes())
                data = r.err.payload.to_bytes()
                try:
                    P.unpack_message(data)
                except P.ProtocolError:  # not ours: Zenoh's own error, e.g. "Timeout"
                    raise Unavailable(P.ERR_UNAVAILABLE, f"{key}: {data[:80].decode(errors='replace')}") from None
                P.decode_reply(data)  # raises the server's error
                raise Unavailable(P.ERR_UNAVAILABLE, f"{key}: error reply without an error")
            # No reply at all: no queryable matched yet (connecting) -> retry; a timeout -> give up.
            elapsed = time.monotonic() - started
            if time.monotonic() + 0.05 < deadline and elapsed < 0.5 * max(remaining, 0.0):
                time.sleep(0.05)
                continue
            raise Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key} within {timeout} s")

    def send(self, kind: str, payload: bytes | bytearray, on_error: Callable[[DrapeError], None] | None = None,
             timeout: float | None = None) -> None:
        """Send a request without waiting for its reply (what a game does with per-tick pin
        updates): the reply is read on a Zenoh thread; an error reply or no reply at all is
        counted in ``send_errors`` and handed to ``on_error`` (default: logged)."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        key = getattr(self.keys, kind)(self.server_id)
        answered = []

        def on_reply(reply: zenoh.Reply) -> None:
            answered.append(True)
            if reply.ok is not None:
                return
            data = reply.err.payload.to_bytes()
            try:
                P.decode_reply(data)
                err = Unavailable(P.ERR_UNAVAILABLE, f"{key}: error reply without an error")
            except DrapeError as e:
                err = e
            except P.ProtocolError:
                err = Unavailable(P.ERR_UNAVAILABLE, f"{key}: {data[:80].decode(errors='replace')}")
            self._send_failed(err, on_error)

        def on_done() -> None:
            if not answered:
                self._send_failed(Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key}"), on_error)

        self.session.get(key, zenoh.handlers.Callback(on_reply, on_done), payload=bytes(payload),
                         timeout=self.timeout if timeout is None else timeout)

    def _send_failed(self, err: DrapeError, on_error: Callable[[DrapeError], None] | None) -> None:
        with self._lock:
            self.send_errors += 1
        if on_error is not None:
            on_error(err)
        else:
            log.warning("request failed: %s", err)

    def info(self, timeout: float | None = None) -> dict[str, Any]:
        """The server's description: version, solver, device, tick rate, limits, counts."""
        return self.request("info", P.encode_info(P.InfoRequest(self._next_rid())), timeout)

    def on_stats(self, callback: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """Call ``callback(stats)`` for every stats publication. Returns an unsubscribe function."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(P.decode_stats(sample.payload.to_bytes()))
            except Exception:
                log.exception("stats callback failed")

        sub = self.session.declare_subscriber(self.keys.stats(self.server_id), on_sample)
        return sub.undeclare

    # --- submissions ------------------------------------------------------------------------------
    def submit(
        self,
        req: P.SubmitRequest,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        timeout: float | None = None,
        queue_size: int | None = None,
    ) -> ClothHandle:
        """Send a SubmitRequest as is and subscribe to the new cloth's state."""
        rep = P.submit_reply_from_map(self.request("submit", P.encode_submit(req), timeout))
        h = ClothHandle(self, rep, rest_positions, triangles, queue_size or self.queue_size)
        with self._lock:
            self._handles[h.id] = h
        return h

    def submit_grid(
        self,
        cols: int,
        rows: int,
        width: float = 1.0,
        height: float = 1.0,
        *,
        orientation: str = "horizontal",
        origin: Sequence[float] = (0.0, 0.0, 0.0),
        **options: Any,
    ) -> ClothHandle:
        """A regular grid cloth; vertex (row r, column c) is r * cols + c. ``options``: see
        ``cloth_options``."""
        grid = P.GridSpec(int(cols), int(rows), float(width), float(height), orientation,
                          tuple(float(v) for v in origin))  # type: ignore[arg-type]
        verts, tris = P.grid_geometry(cols, rows, width, height, orientation, origin)
        return self._submit(grid=grid, rest=verts, tris=tris, **options)

    def submit_mesh(self, vertices: np.ndarray | Sequence, triangles: np.ndarray | Sequence, **options: Any) -> ClothHandle:
        """A triangle mesh cloth: vertices (n, 3) metres, triangles (m, 3) vertex indices."""
        v = np.ascontiguousarray(np.asarray(vertices, np.float32).reshape(-1, 3))
        t = np.asarray(triangles, np.int64).reshape(-1, 3)
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError("triangle index out of range")
        mesh = P.MeshSpec(v, t.astype(np.uint32))
        return self._submit(mesh=mesh, rest=v, tris=mesh.triangles, **options)

    def submit_obj(self, path: str | Path, **options: Any) -> ClothHandle:
        """A cloth from a Wavefront OBJ file (faces fan-triangulated)."""
        v, t = P.parse_obj(Path(path).read_text())
        return self.submit_mesh(v, t, **options)

    def _submit(
        self,
        *,
        rest: np.ndarray,
        tris: np.ndarray,
        grid: P.GridSpec | None = None,
        mesh: P.MeshSpec | None = None,
        pinned: Iterable[int] = (),
        links: Any = None,
        material: Mapping[str, Any] | Any = None,
        features: Iterable[str] = (),
        gravity: Sequence[float] | None = None,
        wind: Sequence[float] | None = None,
        iterations: int | None = None,
        substeps: int | None = None,
        chebyshev_rho: float | None = None,
        colliders: Sequence[Any] | None = None,
        normals: bool = False,
        encoding: str = "float32",
        timeout: float | None = None,
        queue_size: int | None = None,
    ) -> ClothHandle:
        pins = np.asarray(list(pinned), np.int64).reshape(-1)
        if pins.size and (pins.min() < 0 or pins.max() >= len(rest)):
            raise ValueError("pinned index out of range")
        req = P.SubmitRequest(
            client=self.client_id,
            grid=grid,
            mesh=mesh,
            pinned=pins.astype(np.uint32),
            links=_links(links),
            material=P.material_to_map(material) if material is not None else {},
            features=tuple(features),
            gravity=_vec3(gravity),
            wind=_vec3(wind),
            iterations=iterations,
            substeps=substeps,
            chebyshev_rho=chebyshev_rho,
            colliders=tuple(_collider(c) for c in colliders) if colliders is not None else None,
            state=P.StateOptions(bool(normals), encoding) if (normals or encoding != "float32") else None,
            rid=self._next_rid(),
        )
        return self.submit(req, rest, tris, timeout, queue_size)


# Options every submit_* method takes, for documentation and for tools wrapping the SDK.
cloth_options = (
    "pinned", "links", "material", "features", "gravity", "wind", "iterations", "substeps",
    "chebyshev_rho", "colliders", "normals", "encoding", "timeout", "queue_size",
)


def _vec3(v: Sequence[float] | None) -> P.Vec3 | None:
    if v is None:
        return None
    t = tuple(float(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"expected 3 numbers, got {len(t)}")
    return t  # type: ignore[return-value]


def _links(links: Any) -> P.LinkSpec | None:
    if links is None or isinstance(links, P.LinkSpec):
        return links
    if isinstance(links, Mapping):
        return P.LinkSpec(**links)
    if is_dataclass(links):
        return P.LinkSpec(**{f.name: bool(getattr(links, f.name)) for f in fields(links)})
    raise TypeError(f"links must be a LinkSpec, a mapping or a dataclass, got {type(links).__name__}")


def _collider(c: Any) -> P.Collider:
    if isinstance(c, (P.Sphere, P.Capsule, P.Plane)):
        return c
    m = P.collider_to_map(c)
    kind = m.get("type")
    if kind == "sphere":
        return P.Sphere(_vec3(m["center"]), float(m["radius"]))  # type: ignore[arg-type]
    if kind == "capsule":
        return P.Capsule(_vec3(m["p0"]), _vec3(m["p1"]), float(m["radius"]))  # type: ignore[arg-type]
    if kind == "plane":
        return P.Plane(_vec3(m["normal"]), float(m["offset"]))  # type: ignore[arg-type]
    raise TypeError(f"not a collider: {c!r}")
