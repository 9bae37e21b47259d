"""The SDK's bottom layer (:class:`Session`): one client's Zenoh session and what it knows of the
servers, with no notion of a cloth.

It opens the Zenoh session, declares the client's liveliness token, watches the servers' tokens
(the servers seen; the default server), keeps ONE per-server cache of what each server's ``info``
said (:class:`ServerInfo`: protocol version, batch size, largest cloth), and sends requests:
``request`` (waited) and ``send`` (not waited, failures counted). Requests to a server speaking
1.4 go to this client's own keys (``{ns}/server/{server}/client/{client}/{kind}``, PROTOCOL.md
11.2), to an older one to the server-wide keys: the version is asked once per server with
``info`` (server-wide in every version) before its first other request.
"""

from __future__ import annotations

import itertools
import logging
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from . import protocol as P
from .protocol import DrapeError, Unavailable
from .session import deployment_client_id, open_session, zenoh_config

log = logging.getLogger("drape.client.sdk")

ErrorCallback = Callable[[DrapeError], None]
ServerCallback = Callable[[str, bool], None]  # (server id, alive)


@dataclass(frozen=True)
class ServerInfo:
    """What one server's ``info`` reply says that the SDK acts on."""

    version: tuple[int, int]
    max_batch_items: int  # 0: not said
    max_vertices: int | None  # its max_vertices_per_cloth (None: not said)

    @classmethod
    def of(cls, info: dict[str, Any]) -> ServerInfo:
        major, _, minor = str(info.get("version", "1.0")).partition(".")
        limits = info.get("limits") or {}
        vmax = limits.get("max_vertices_per_cloth")
        return cls(
            (int(major), int(minor or 0)),
            int(limits.get("max_batch_items", 0) or 0),
            vmax if isinstance(vmax, int) and vmax > 0 else None,
        )

    @property
    def batch_limit(self) -> int:
        """Items per batch request the server takes; 0 when it speaks 1.0 (no batch control)."""
        return 0 if self.version < (1, 1) else max(1, self.max_batch_items)

    @property
    def client_scoped(self) -> bool:
        """Whether it declares this client's own request keys (1.4)."""
        return self.version >= (1, 4)


class Session:
    """One client's Zenoh session to the Drape servers of a namespace (module docstring).

    ``server_id``: the server to talk to; None: the default server is ``choose()`` among the live
    ones (the placement's first choice), kept while it is live."""

    def __init__(
        self,
        connect: Sequence[str],
        *,
        listen: Sequence[str] = (),
        mode: str = "peer",
        namespace: str = P.DEFAULT_NAMESPACE,
        server_id: str | None = None,
        client_id: str | None = None,
        timeout: float = 5.0,
        multicast_scouting: bool = False,
        zenoh_config_file: str | None = None,
        choose: Callable[[], str | None] | None = None,
    ) -> None:
        self.keys = P.Keys(namespace)
        self.client_id = client_id or deployment_client_id(zenoh_config_file) or f"c{secrets.token_hex(8)}"
        if not P.valid_id(self.client_id):
            raise ValueError(f"invalid client id {self.client_id!r}")
        if server_id is not None and not P.valid_id(server_id):
            raise ValueError(f"invalid server id {server_id!r}")
        self.timeout = timeout
        self.server_given = server_id is not None  # else: the default server is chosen by load
        self._server_id = server_id
        self._choose = choose
        self._rid = itertools.count(1)
        self._lock = threading.Lock()
        self._servers: set[str] = set()
        self._servers_cond = threading.Condition(self._lock)
        self._infos: dict[str, ServerInfo] = {}  # per server: its info, asked once
        self.closed = False
        self.send_errors = 0  # replies to send() that were errors (or refused batch items), or that never came
        self._watch: Any = None
        # the endpoints are checked before Zenoh sees them; Zenoh's refusal without its Rust paths
        self.zenoh: zenoh.Session = open_session(
            zenoh_config(mode, listen, list(connect), multicast_scouting, zenoh_config_file),
            f"{mode}, connect {list(connect)}" + (f", listen {list(listen)}" if listen else ""),
        )
        self.token: Any = self.zenoh.liveliness().declare_token(self.keys.alive_client(self.client_id))

    def watch(self, on_server: ServerCallback) -> None:
        """Watch the servers' liveliness tokens (once): ``on_server(id, alive)`` after each change
        of the servers seen (on a Zenoh thread)."""

        def on_sample(sample: zenoh.Sample) -> None:
            sid = self.keys.last_chunk(str(sample.key_expr))
            alive = sample.kind == zenoh.SampleKind.PUT
            with self._servers_cond:
                if alive:
                    self._servers.add(sid)
                    self._servers_cond.notify_all()
                else:
                    self._servers.discard(sid)
            on_server(sid, alive)

        if self._watch is None:
            lv = self.zenoh.liveliness()
            self._watch = lv.declare_subscriber(self.keys.all_servers_alive, on_sample, history=True)

    def close(self) -> None:
        """Withdraw the token and the watch and close the Zenoh session. Idempotent."""
        if self.closed:
            return
        self.closed = True
        for obj in (self.token, self._watch):
            if obj is None:
                continue
            try:
                obj.undeclare()
            except Exception:
                pass
        self.zenoh.close()

    # --- servers --------------------------------------------------------------------------------
    def next_rid(self) -> int:
        return next(self._rid)

    def live_servers(self) -> list[str]:
        """Ids of the servers whose liveliness tokens this client currently sees (its watch)."""
        with self._lock:
            return sorted(self._servers)

    @property
    def server_id(self) -> str:
        """The server given, or else the default server for requests that name none: ``choose()``
        among the live ones, kept while it is live (waiting up to ``timeout`` for one)."""
        if self.server_given:
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
            first = min(self._servers)
        chosen = self._choose() if self._choose is not None else first
        if chosen is None:  # gone again meanwhile
            return self.server_id
        self._server_id = chosen
        return chosen

    def servers(self, timeout: float = 1.0) -> list[str]:
        """Ids of the servers whose liveliness tokens are visible now (asked, not watched)."""
        replies = self.zenoh.liveliness().get(self.keys.all_servers_alive, timeout=timeout)
        return sorted({self.keys.last_chunk(str(r.ok.key_expr)) for r in replies if r.ok is not None})

    def info(self, server: str | None = None, timeout: float | None = None) -> dict[str, Any]:
        """``server``'s info reply (asked now; default: the default server)."""
        return self.request("info", P.encode_info(P.InfoRequest(self.next_rid())), timeout, server=server)

    def info_of(self, server: str | None = None, timeout: float | None = None) -> ServerInfo:
        """What ``server`` (default: the default server) said in its info: asked once per server,
        then remembered. Raises the DrapeError of an info left unanswered (not remembered)."""
        srv = server or self.server_id
        got = self._infos.get(srv)
        if got is None:
            got = self._infos[srv] = ServerInfo.of(self.info(srv, timeout))
        return got

    def known_info(self, server: str) -> ServerInfo | None:
        """``server``'s info if it was asked already (never asks)."""
        return self._infos.get(server)

    def set_info(self, server: str, info: ServerInfo | None) -> None:
        """Replace (None: forget) what ``server``'s info said: asked again on next use."""
        if info is None:
            self._infos.pop(server, None)
        else:
            self._infos[server] = info

    # --- requests -----------------------------------------------------------------------------
    def key(self, kind: str, server: str, timeout: float | None = None) -> str:
        """The key of a ``kind`` request to ``server``: this client's own key (1.4) when the server
        has them, else the server-wide key of 1.0-1.3 (always for info). A 1.3 server has no such
        queryable, so trying one first would cost a timeout each time: the info is asked first; an
        unanswered info means the server-wide keys (and is asked again next time)."""
        if kind in P.CLIENT_REQUESTS:
            try:
                scoped = self.info_of(server, timeout).client_scoped
            except DrapeError as e:
                log.debug("info of %s: %s; using the server-wide keys", server, e)
                scoped = False
            if scoped:
                return self.keys.client_request(kind, server, self.client_id)
        return str(getattr(self.keys, kind)(server))

    def request(
        self, kind: str, payload: bytes | bytearray, timeout: float | None = None, server: str | None = None
    ) -> dict[str, Any]:
        """Send a raw request payload to the ``kind`` queryable (submit, control, remove, info)
        of ``server`` (default: the default server) and return the success reply's map;
        raises the DrapeError subclass of an error reply, or Unavailable when no server answers
        in time."""
        if self.closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        srv = server or self.server_id
        timeout = self.timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        key = self.key(kind, srv, timeout)
        while True:
            remaining = deadline - time.monotonic()
            started = time.monotonic()
            replies = list(self.zenoh.get(key, payload=bytes(payload), timeout=max(remaining, 0.01)))
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
                if kind in P.CLIENT_REQUESTS and srv not in self._infos:  # its info went unanswered
                    key = self.key(kind, srv, max(deadline - time.monotonic(), 0.01))
                continue
            raise Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key} within {timeout} s")

    def send(
        self,
        kind: str,
        payload: bytes | bytearray,
        on_error: ErrorCallback | None = None,
        timeout: float | None = None,
        on_ok: Callable[[dict[str, Any]], None] | None = None,
        server: str | None = None,
        excused: Callable[[DrapeError], bool] | None = None,
    ) -> None:
        """Send a request without waiting for its reply: the reply is read on a Zenoh thread; an
        error reply or no reply at all is counted in ``send_errors`` and handed to ``on_error``
        (default: logged). ``on_ok``, if given, gets a success reply's map (on the Zenoh thread).
        ``excused(err)``: True for an error that is no failure (see :meth:`failed`)."""
        if self.closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        key = self.key(kind, server or self.server_id, timeout)
        answered = []

        def on_reply(reply: zenoh.Reply) -> None:
            answered.append(True)
            if reply.ok is not None:
                if on_ok is not None:
                    try:
                        on_ok(P.decode_reply(reply.ok.payload.to_bytes()))
                    except DrapeError as e:
                        self.failed(e, on_error, excused)
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
            self.failed(err, on_error, excused)

        def on_done() -> None:
            if not answered:
                self.failed(Unavailable(P.ERR_UNAVAILABLE, f"no reply from {key}"), on_error, excused)

        self.zenoh.get(
            key,
            zenoh.handlers.Callback(on_reply, on_done),
            payload=bytes(payload),
            timeout=self.timeout if timeout is None else timeout,
        )

    def failed(
        self,
        err: DrapeError,
        on_error: ErrorCallback | None,
        excused: Callable[[DrapeError], bool] | None = None,
    ) -> None:
        """An unwaited request failed: counted and handed to ``on_error`` (default: a warning),
        unless ``excused(err)`` (e.g. a ``not_found`` of a cloth this client is removing: a control
        sent just before the removal and applied after it; logged at debug level, not counted)."""
        if excused is not None and excused(err):
            log.debug("excused: %s", err)
            return
        with self._lock:
            self.send_errors += 1
        if on_error is not None:
            on_error(err)
        else:
            log.warning("request failed: %s", err)


__all__ = ["ErrorCallback", "ServerCallback", "ServerInfo", "Session"]
