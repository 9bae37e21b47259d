"""Drape client SDK: submit cloths to a Drape server over Zenoh and receive their state.

    from drape.client import DrapeClient

    with DrapeClient("tcp/127.0.0.1:7447") as client:
        with client.submit_grid(16, 16, pinned=[0, 15]) as cloth:
            for state in cloth.states(timeout=1.0):
                draw(state.positions)            # (256, 3) float32
                cloth.move_pins([0, 15], [[0, 0, 0], [1, 0, 0]])

A game with many cloths (protocol 1.1) submits them with ``bundle=True`` (their states arrive in
one publication per tick for the whole client, dispatched to each ClothHandle exactly as
before) and moves them all with one message per tick::

    cloths = [client.submit_grid(16, 16, pinned=[0, 15], bundle=True) for _ in range(32)]
    while playing:
        with client.batch() as b:                # one batch control on exit, reply not awaited
            for c in cloths:
                b.move_pins(c, [0, 15], targets_of(c))

``DrapeClient(failover=True)`` keeps every cloth across the loss of its server or a reclaim
(protocol 1.3, PROTOCOL.md 11.1): see :mod:`drape.client.failover`.

This module holds the session (:class:`DrapeClient`: servers, requests); :mod:`.submitting` its
submissions and :mod:`.batching` its controls of many cloths (mixins), :mod:`.handle` the
ClothHandle, :mod:`.controls` the batch and argument conversions, :mod:`.failover` the failover
worker (all re-exported here). Needs numpy, msgpack and eclipse-zenoh only: nothing here imports
drape.server or OpenCL.
"""

from __future__ import annotations

import itertools
import logging
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from . import protocol as P
from .batching import BatchingMixin
from .bundles import MAX_ORPHAN_CLOTHS, BundleReceiver  # noqa: F401  (MAX_ORPHAN_CLOTHS: as before)
from .controls import (  # noqa: F401  (BatchError, ControlBatch and the helpers: drape.client.sdk.* as before)
    BatchError,
    ControlBatch,
    ErrorCallback,
    _collider,
    _feature_names,
    _item_outcomes,
    _links,
    _pin_changes,
    _set_changes,
    _vec3,
)
from .failover import Failover, FailoverCallback, FailoverEvent  # noqa: F401  (re-exported)
from .handle import ClothHandle, StateCallback  # noqa: F401  (drape.client.sdk.ClothHandle as before)
from .placement import PLACE_ELSEWHERE, Placement  # noqa: F401  (PLACE_ELSEWHERE: as before)
from .protocol import ClothState, DrapeError, Unavailable  # noqa: F401
from .sending import send_controls  # noqa: F401  (as before)
from .session import deployment_client_id, open_session, zenoh_config  # noqa: F401  (zenoh_config: the pre-1.2 path)
from .submitting import SubmittingMixin, cloth_options  # noqa: F401  (cloth_options: as before)

log = logging.getLogger(__name__)


class DrapeClient(SubmittingMixin, BatchingMixin):
    """A Zenoh session to a Drape server, with this client's liveliness token.

    ``connect``: endpoints of the server (or of a router); default tcp/127.0.0.1:7447.
    ``server_id``: the server to talk to; None: every submission is placed on the least loaded
    live server (:mod:`.placement`, waiting up to ``timeout`` for one), so one client's cloths
    may live on several servers (each handle's ``server_id``). ``client_id``: this client's id; None: the deployment's
    (``$DRAPE_CLIENT_ID``, else the sidecar file ``<zenoh_config_file>.client_id``), else a random
    one. Its liveliness token tells the server the client is alive: when it disappears for longer
    than the server's grace period, the server reclaims the client's cloths. Behind a router with
    ``drape acl``'s access control it must be the id the users file gives this client's user.

    Requests to a server speaking 1.4 go to this client's own keys
    (``{ns}/server/{server}/client/{client}/{kind}``, PROTOCOL.md 11.2), to an older one to the
    server-wide keys: the version is asked once per server with ``info`` (server-wide in every
    version) before its first other request."""

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
        failover: bool = False,
        stall_timeout: float = 0.5,
        failover_give_up: float = 60.0,
    ) -> None:
        if connect is None:
            connect = [P.DEFAULT_ENDPOINT]
        elif isinstance(connect, str):
            connect = [connect]
        self.keys = P.Keys(namespace)
        self.client_id = client_id or deployment_client_id(zenoh_config_file) or f"c{secrets.token_hex(8)}"
        if not P.valid_id(self.client_id):
            raise ValueError(f"invalid client id {self.client_id!r}")
        if server_id is not None and not P.valid_id(server_id):
            raise ValueError(f"invalid server id {server_id!r}")
        self.timeout = timeout
        self.queue_size = queue_size
        self._server_id = server_id
        self._server_given = server_id is not None  # else: submissions are placed by load
        self._rid = itertools.count(1)
        self._lock = threading.Lock()
        self._handles: dict[str, ClothHandle] = {}
        self._servers: set[str] = set()
        self._servers_cond = threading.Condition(self._lock)
        self._closed = False
        self.send_errors = 0  # replies to send() that were errors (or refused batch items), or that never came
        self._bundle_sub: Any = None
        # this client's bundle: decoded whole, its states delivered to the handles (client/bundles.py)
        self.bundles = BundleReceiver(self._handles, self._lock, queue_size, self.keys.bundle(self.client_id))
        self._server_version: tuple[int, int] | None = None
        self._scoped: dict[str, bool] = {}  # per server: whether it has client-scoped request keys (1.4)
        self._vertex_limits: dict[str, int] = {}  # per server: its max_vertices_per_cloth (from that info)
        self._max_batch_items = P.DEFAULT_LIMITS.max_batch_items
        self._failover: Failover | None = None
        # the endpoints are checked before Zenoh sees them; Zenoh's refusal without its Rust paths
        self.session: zenoh.Session = open_session(
            zenoh_config(mode, listen, list(connect), multicast_scouting, zenoh_config_file),
            f"{mode}, connect {list(connect)}" + (f", listen {list(listen)}" if listen else ""),
        )
        # where new cloths go: the servers' loads from their stats (client/placement.py)
        self.placement = Placement(self.client_id, self.live_servers, stats_wait=min(timeout, 1.5))
        if server_id is None or failover:
            self.placement.attach(self.session, self.keys)
        lv = self.session.liveliness()
        self._server_watch = lv.declare_subscriber(self.keys.all_servers_alive, self._on_server, history=True)
        self._token = lv.declare_token(self.keys.alive_client(self.client_id))
        # failover=True: cloths survive the loss of their server (client/failover.py, PROTOCOL.md 11.1)
        self._failover = (
            Failover(self, stall_timeout=stall_timeout, give_up_after=failover_give_up) if failover else None
        )
        log.debug("drape client %s connected to %s", self.client_id, list(connect))

    # --- session ------------------------------------------------------------------------------
    def __enter__(self) -> DrapeClient:
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
        if self._failover is not None:
            self._failover.close()
        self.placement.close()
        for obj in (self._bundle_sub, self._token, self._server_watch):
            if obj is None:
                continue
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
                gone = [h for h in self._handles.values() if h.server_id == sid]
        if sample.kind != zenoh.SampleKind.PUT:
            self.placement.server_gone(sid)
        if self._failover is not None:
            if gone:
                self._failover.server_lost(sid)
            else:
                self._failover.wake()
            return
        for h in gone:
            h._close(f"server {sid} went away")

    @property
    def server_id(self) -> str:
        """The server given, or else this client's default server for requests that name none
        (info, stats): the placement's first choice among the live ones, kept while it is live
        (waiting up to ``timeout`` for one to appear). Submissions are placed one by one."""
        if self._server_given:
            assert self._server_id is not None
            return self._server_id
        with self._servers_cond:
            if self._server_id in self._servers:
                return self._server_id
            self._servers_cond.wait_for(lambda: bool(self._servers), self.timeout)
            if not self._servers:
                raise Unavailable(
                    P.ERR_UNAVAILABLE,
                    f"no Drape server seen in namespace {self.keys.namespace!r} within {self.timeout} s",
                )
        chosen = self.placement.choose()
        if chosen is None:  # gone again meanwhile
            return self.server_id
        self._server_id = chosen
        return chosen

    def live_servers(self) -> list[str]:
        """Ids of the servers whose liveliness tokens this client currently sees (its watch)."""
        with self._lock:
            return sorted(self._servers)

    @property
    def failover(self) -> bool:
        """Whether this client fails its cloths over when their server is lost."""
        return self._failover is not None

    def on_failover(self, callback: FailoverCallback) -> Callable[[], None]:
        """Call ``callback(FailoverEvent)`` once per cloth failed over (or lost for good), on the
        failover thread. Needs ``failover=True``. Returns an unsubscribe function."""
        if self._failover is None:
            raise ValueError("this DrapeClient was created with failover=False")
        return self._failover.on_failover(callback)

    @property
    def failover_events(self) -> list[FailoverEvent]:
        """Every failover so far, in order (empty without failover)."""
        return list(self._failover.events) if self._failover is not None else []

    def _handles_on(self, server: str) -> list[ClothHandle]:
        with self._lock:
            return [h for h in self._handles.values() if h.server_id == server]

    def _open_handles(self) -> list[ClothHandle]:
        with self._lock:
            return list(self._handles.values())

    def _cloth_not_found(self, h: ClothHandle) -> None:
        """A control of ``h`` was answered not_found: reclaimed (or its server restarted), unless
        this client is removing it."""
        if self._failover is not None and not h.closed and not h.removing:
            self._failover.cloth_lost(h, "reclaimed")

    def _watch_not_found(self, h: ClothHandle, on_error: ErrorCallback | None) -> ErrorCallback | None:
        if self._failover is None:
            return on_error

        def cb(err: DrapeError) -> None:
            if isinstance(err, P.NotFound):
                self._cloth_not_found(h)
            if on_error is not None:
                on_error(err)
            else:
                log.warning("request failed: %s", err)

        return cb

    def servers(self, timeout: float = 1.0) -> list[str]:
        """Ids of the servers whose liveliness tokens are visible now."""
        replies = self.session.liveliness().get(self.keys.all_servers_alive, timeout=timeout)
        return sorted({self.keys.last_chunk(str(r.ok.key_expr)) for r in replies if r.ok is not None})

    def _next_rid(self) -> int:
        return next(self._rid)

    def _forget(self, handle: ClothHandle) -> None:
        with self._lock:
            if self._handles.get(handle.id) is handle:
                del self._handles[handle.id]

    # --- bundles (protocol 1.1) -------------------------------------------------------------------
    @property
    def bundle_key(self) -> str:
        """Where the server publishes this client's bundle: {ns}/client/{client id}/states."""
        return self.keys.bundle(self.client_id)

    def _ensure_bundle_subscriber(self) -> None:
        """Subscribe to this client's bundle once, before the first bundled submission, so the
        subscription is in place when the cloth's first state is published."""
        with self._lock:
            if self._bundle_sub is None:
                self._bundle_sub = self.session.declare_subscriber(self.bundle_key, self.bundles.on_sample)

    @property
    def bundle_invalid(self) -> int:
        """Bundle payloads that could not be parsed."""
        return self.bundles.invalid

    # --- requests -----------------------------------------------------------------------------
    def _key(self, kind: str, server: str, timeout: float | None = None) -> str:
        """The key of a ``kind`` request to ``server``: this client's own key (1.4) when the server
        has them, else the server-wide key of 1.0-1.3 (always for info)."""
        if kind in P.CLIENT_REQUESTS and self._client_scoped(server, timeout):
            return self.keys.client_request(kind, server, self.client_id)
        return str(getattr(self.keys, kind)(server))

    def _client_scoped(self, server: str, timeout: float | None = None) -> bool:
        """Whether ``server`` speaks 1.4 (client-scoped request keys): asked with info once (a 1.3
        server has no such queryable, so trying one first would cost a timeout each time). An
        unanswered info is not remembered: ``request`` asks again while it retries."""
        scoped = self._scoped.get(server)
        if scoped is None:
            try:
                info = self.request("info", P.encode_info(P.InfoRequest(self._next_rid())), timeout, server=server)
            except DrapeError as e:
                log.debug("info of %s: %s; using the server-wide keys", server, e)
                return False
            major, _, minor = str(info.get("version", "1.0")).partition(".")
            limit = (info.get("limits") or {}).get("max_vertices_per_cloth")
            if isinstance(limit, int) and limit > 0:
                self._vertex_limits[server] = limit
            scoped = self._scoped[server] = (int(major), int(minor or 0)) >= (1, 4)
        return scoped

    def _check_size(self, req: P.SubmitRequest, server: str, timeout: float | None = None) -> None:
        """Refuse a cloth larger than ``server`` takes (its ``max_vertices_per_cloth``, from the
        info asked once per server) before sending it: ``too_large``, the server's own words."""
        self._client_scoped(server, timeout)  # the info, asked once (and needed for the key anyway)
        limit = self._vertex_limits.get(server)
        n = req.n_vertices
        if limit is not None and n > limit:
            grid = (req.grid.cols, req.grid.rows) if req.grid is not None else None
            raise P.ProtocolError(P.ERR_TOO_LARGE, P.too_many_vertices(n, limit, grid), req.rid)

    def request(
        self, kind: str, payload: bytes | bytearray, timeout: float | None = None, server: str | None = None
    ) -> dict[str, Any]:
        """Send a raw request payload to the ``kind`` queryable (submit, control, remove, info)
        of ``server`` (default: this client's server) and return the success reply's map;
        raises the DrapeError subclass of an error reply, or Unavailable when no server answers
        in time."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        srv = server or self.server_id
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        key = self._key(kind, srv, timeout)
        while True:
            remaining = deadline - time.monotonic()
            started = time.monotonic()
            replies = list(self.session.get(key, payload=bytes(payload), timeout=max(remaining, 0.01)))
            for r in replies:
                if r.ok is not None:
                    return P.decode_reply(r.ok.payload.to_bytes())
                assert r.err is not None  # a reply is either ok or an error
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
                if kind in P.CLIENT_REQUESTS and srv not in self._scoped:  # its info went unanswered
                    key = self._key(kind, srv, max(deadline - time.monotonic(), 0.01))
                continue
            raise Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key} within {timeout} s")

    def send(
        self,
        kind: str,
        payload: bytes | bytearray,
        on_error: Callable[[DrapeError], None] | None = None,
        timeout: float | None = None,
        on_ok: Callable[[dict[str, Any]], None] | None = None,
        server: str | None = None,
        handle: ClothHandle | None = None,
    ) -> None:
        """Send a request without waiting for its reply (what a game does with per-tick pin
        updates): the reply is read on a Zenoh thread; an error reply or no reply at all is
        counted in ``send_errors`` and handed to ``on_error`` (default: logged). ``on_ok``, if
        given, gets a success reply's map (on the Zenoh thread). ``handle``: the cloth the
        request is about; its ``not_found`` once this client is removing it is no failure
        (``_send_failed``)."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        key = self._key(kind, server or self.server_id, timeout)
        answered = []

        def on_reply(reply: zenoh.Reply) -> None:
            answered.append(True)
            if reply.ok is not None:
                if on_ok is not None:
                    try:
                        on_ok(P.decode_reply(reply.ok.payload.to_bytes()))
                    except DrapeError as e:
                        self._send_failed(e, on_error, handle)
                    except Exception:
                        log.exception("%s: reply handler failed", key)
                return
            assert reply.err is not None  # a reply is either ok or an error
            data = reply.err.payload.to_bytes()
            err: DrapeError
            try:
                P.decode_reply(data)
                err = Unavailable(P.ERR_UNAVAILABLE, f"{key}: error reply without an error")
            except DrapeError as e:
                err = e
            except P.ProtocolError:
                err = Unavailable(P.ERR_UNAVAILABLE, f"{key}: {data[:80].decode(errors='replace')}")
            self._send_failed(err, on_error, handle)

        def on_done() -> None:
            if not answered:
                self._send_failed(Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key}"), on_error, handle)

        self.session.get(
            key,
            zenoh.handlers.Callback(on_reply, on_done),
            payload=bytes(payload),
            timeout=self.timeout if timeout is None else timeout,
        )

    def _send_failed(
        self, err: DrapeError, on_error: Callable[[DrapeError], None] | None, handle: ClothHandle | None = None
    ) -> None:
        """An unwaited request failed: counted and handed to ``on_error`` (default: a warning),
        except a ``not_found`` of a cloth (``handle``) this client is removing: a control sent
        just before the removal and applied after it (logged at debug level, not counted)."""
        if handle is not None and handle._removal_outcome(err):
            log.debug("cloth %s was being removed: %s", handle.id, err)
            return
        with self._lock:
            self.send_errors += 1
        if on_error is not None:
            on_error(err)
        else:
            log.warning("request failed: %s", err)

    @property
    def server_version(self) -> tuple[int, int]:
        """The protocol version the server speaks (asked once with info, then remembered)."""
        if self._server_version is None:
            info = self.info()
            major, _, minor = str(info.get("version", "1.0")).partition(".")
            self._max_batch_items = int(info.get("limits", {}).get("max_batch_items", 0) or 0)
            self._server_version = (int(major), int(minor or 0))
        return self._server_version

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
