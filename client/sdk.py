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

A ``DrapeClient`` keeps every cloth across the loss of its server or a reclaim (failover, on by
default; ``failover=False`` turns it off; protocol 1.3, PROTOCOL.md 11.1): see
:mod:`drape.client.failover`.

This module is the facade: :class:`DrapeClient` composes the SDK's layers, each given the parts
below it (no mixins): :mod:`.connection` the Session (Zenoh session, servers seen, one per-server
info cache, requests), :mod:`.controls` pure control building, :mod:`.moves` the record of moves
blocks, :mod:`.sending` the one sending path of controls, :mod:`.handle` the ClothHandle,
:mod:`.registry` the open cloths, :mod:`.bundles` the bundle receiver, :mod:`.batching` the
ControlBatch, :mod:`.placement` and :mod:`.submitting` where and how cloths are submitted,
:mod:`.failover` the failover worker. Needs numpy, msgpack and eclipse-zenoh only: nothing here
imports drape.server or OpenCL.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, cast

import numpy as np
import zenoh

from . import protocol as P
from .batching import ControlBatch
from .bundles import MAX_ORPHAN_CLOTHS, BundleReceiver
from .connection import ErrorCallback, Session
from .controls import BatchError
from .controls import mesh_collider as as_mesh_collider
from .failover import Failover, FailoverCallback, FailoverEvent
from .handle import ClothHandle, StateCallback
from .keyframes import KeyframeQueries
from .moves import MoveBook
from .placement import PLACE_ELSEWHERE, Placement
from .protocol import ClothState, DrapeError, Unavailable
from .rates import rate_option
from .registry import Cloths
from .scenes import SceneBook
from .sending import ControlSender, Target
from .session import zenoh_config
from .submitting import Submitter, cloth_options, grid_spec, mesh_spec, submit_request

log = logging.getLogger(__name__)
REMOVES_IN_FLIGHT = 64  # removals a closing client has under way at once


class DrapeClient:
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
    version) before its first other request; every choice of a wire form follows the version of
    the server the request goes to.

    Its parts, built once here in dependency order: ``connection`` (the Session), ``placement``,
    ``cloths`` (the open cloths), ``bundles``, ``sender`` (the sending path of controls),
    ``submitter`` and, with ``failover`` (the default), the failover worker; ``failover=False``:
    none, a cloth lost with its server is closed (issue 26: a game using the first example lost
    every cloth with its server while failover was opt-in).

    ``rate`` (1.8): take every k-th state (1, 2, 3: 60, 30, 20 Hz at the default tick; 1.9: 6,
    12: 10, 5 Hz) of each cloth and bundle, on its own key, or ``"auto"``: full rate, stepped down
    by itself when states arrive late (and back up after a quiet period; client/rates.py), counted
    in each handle's ``step_downs`` / ``step_ups`` (a bundle's: ``client.bundles``). Cloths on a
    server older than 1.8 come at full rate, on a 1.8 server at every 3rd state at most."""

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
        failover: bool = True,
        stall_timeout: float = 0.5,
        failover_give_up: float = 60.0,
        rate: int | str = 1,
    ) -> None:
        if connect is None:
            connect = [P.DEFAULT_ENDPOINT]
        elif isinstance(connect, str):
            connect = [connect]
        self.queue_size = queue_size
        self._closed = False
        self._failover: Failover | None = None
        # the default server is the placement's first choice among the live ones
        self.connection = Session(
            connect,
            listen=listen,
            mode=mode,
            namespace=namespace,
            server_id=server_id,
            client_id=client_id,
            timeout=timeout,
            multicast_scouting=multicast_scouting,
            zenoh_config_file=zenoh_config_file,
            choose=lambda: self.placement.choose(),
        )
        self.keys = self.connection.keys
        self.client_id = self.connection.client_id
        self.timeout = timeout
        self.session: zenoh.Session = self.connection.zenoh
        # where new cloths go: the servers' loads from their stats (client/placement.py)
        self.placement = Placement(self.client_id, self.connection.live_servers, stats_wait=min(timeout, 1.5))
        if server_id is None or failover:
            self.placement.attach(self.session, self.keys)
        self.cloths = Cloths()
        # this client's bundle: decoded whole, its states delivered to the handles (client/bundles.py)
        start, governed = rate_option(rate)  # 1.8: every k-th state, or "auto" (client/rates.py)
        self.bundles = BundleReceiver(
            self.cloths.by_id, self.cloths.lock, queue_size, self.keys.bundle(self.client_id), start, governed
        )
        self.sender = ControlSender(self.connection, MoveBook(self), self._cloth_not_found)
        self.keyframes = KeyframeQueries()  # 1.5: one keyframe query per key in a while, for all its cloths
        self.scenes = SceneBook(self.connection)  # 1.7: the scenes' owners and last requests (client/scenes.py)
        self.submitter = Submitter(
            self, self.connection, self.placement, self.cloths, self.bundles, queue_size, (start, governed), self.scenes
        )
        # failover (the default): cloths survive the loss of their server (client/failover.py, PROTOCOL.md 11.1)
        if failover:
            self._failover = Failover(
                self.connection,
                self.cloths,
                self.placement,
                self.submitter.place,
                stall_timeout=stall_timeout,
                give_up_after=failover_give_up,
                scenes=self.scenes,
            )
        self.connection.watch(self._on_server)
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
            open_cloths = self.cloths.all()

            def remove_one(h: ClothHandle) -> None:
                try:
                    h.remove(timeout=min(self.timeout, 2.0))
                except DrapeError as e:
                    log.debug("removing %s on close: %s", h.id, e)

            # REMOVES_IN_FLIGHT at a time: the server removes every cloth that arrived in a tick
            # together, where one at a time (each answered after the next frame) took a tick each
            # and rebuilt the server's frame every tick (1,024 cloths: over a minute)
            if len(open_cloths) > 1:
                with ThreadPoolExecutor(min(REMOVES_IN_FLIGHT, len(open_cloths)), "drape-remove") as pool:
                    list(pool.map(remove_one, open_cloths))
            else:
                for h in open_cloths:
                    remove_one(h)
        self._closed = True
        if self._failover is not None:
            self._failover.close()
        self.placement.close()
        self.bundles.close()
        self.connection.close()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def moves(self) -> MoveBook:
        """The record of the moves blocks sent (1.4): what a failover re-sends of them."""
        return self.sender.book

    def _on_server(self, sid: str, alive: bool) -> None:
        gone: list[ClothHandle] = []
        if not alive:
            gone = self.cloths.on(sid)
            self.placement.server_gone(sid)
        if self._failover is not None:
            if gone:
                self._failover.server_lost(sid)
            else:
                self._failover.wake()
            return
        for h in gone:
            h.mark_closed(f"server {sid} went away")

    @property
    def server_id(self) -> str:
        """The server given, or else this client's default server for requests that name none
        (info, stats): the placement's first choice among the live ones, kept while it is live
        (waiting up to ``timeout`` for one to appear). Submissions are placed one by one."""
        return self.connection.server_id

    def live_servers(self) -> list[str]:
        """Ids of the servers whose liveliness tokens this client currently sees (its watch)."""
        return self.connection.live_servers()

    def servers(self, timeout: float = 1.0) -> list[str]:
        """Ids of the servers whose liveliness tokens are visible now."""
        return self.connection.servers(timeout)

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

    def _cloth_not_found(self, h: Target) -> None:
        """A control of ``h`` was answered not_found: reclaimed (or its server restarted), unless
        this client is removing it."""
        if self._failover is not None and isinstance(h, ClothHandle) and not h.closed and not h.removing:
            self._failover.cloth_lost(h, "reclaimed")

    def forget(self, handle: ClothHandle) -> None:
        """``handle`` closed: no longer one of this client's open cloths."""
        self.cloths.forget(handle)

    # --- bundles (protocol 1.1) -------------------------------------------------------------------
    @property
    def bundle_key(self) -> str:
        """Where the server publishes this client's bundle: {ns}/client/{client id}/states."""
        return self.keys.bundle(self.client_id)

    @property
    def bundle_invalid(self) -> int:
        """Bundle payloads that could not be parsed."""
        return self.bundles.invalid

    # --- requests -----------------------------------------------------------------------------
    @property
    def send_errors(self) -> int:
        """Replies to send() that were errors (or refused batch items), or that never came."""
        return self.connection.send_errors

    def request(
        self, kind: str, payload: bytes | bytearray, timeout: float | None = None, server: str | None = None
    ) -> dict[str, Any]:
        """Send a raw request payload to the ``kind`` queryable (submit, control, remove, info)
        of ``server`` (default: this client's server) and return the success reply's map;
        raises the DrapeError subclass of an error reply, or Unavailable when no server answers
        in time."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        return self.connection.request(kind, payload, timeout, server)

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
        request is about; its ``not_found`` once this client is removing it is no failure."""
        if self._closed:
            raise DrapeError(P.ERR_UNAVAILABLE, "client is closed")
        excused = handle.removal_outcome if handle is not None else None
        self.connection.send(kind, payload, on_error, timeout, on_ok, server, excused)

    @property
    def server_version(self) -> tuple[int, int]:
        """The protocol version this client's default server speaks (asked once with info, then
        remembered, as for every server)."""
        return self.connection.info_of().version

    def info(self, timeout: float | None = None) -> dict[str, Any]:
        """The server's description: version, solver, device, tick rate, limits, counts."""
        return self.connection.info(None, timeout)

    def on_stats(self, callback: Callable[[dict[str, Any]], None]) -> Callable[[], None]:
        """Call ``callback(stats)`` for every stats publication. Returns an unsubscribe function."""

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                callback(P.decode_stats(sample.payload.to_bytes()))
            except Exception:
                log.exception("stats callback failed")

        sub = self.session.declare_subscriber(self.keys.stats(self.server_id), on_sample)
        return sub.undeclare

    # --- controls of many cloths ------------------------------------------------------------------
    def batch(
        self, *, wait: bool = False, on_error: ErrorCallback | None = None, timeout: float | None = None
    ) -> ControlBatch:
        """Collect controls of many of this client's cloths and send them as one batch control
        request when the ``with`` block ends (or on ``send()``): the per-tick call of a game
        loop with many cloths. ``wait=False``: the reply is not waited for; refused items are
        counted in ``send_errors`` and handed to ``on_error``. ``wait=True``: ``results`` holds
        each item's first tick, and BatchError is raised if any item was refused."""
        return ControlBatch(self.sender, self, wait=wait, on_error=on_error, timeout=timeout)

    def move_pins_many(
        self,
        handles: Sequence[ClothHandle],
        indices: Sequence[int] | np.ndarray | Sequence[Sequence[int]],
        targets: Sequence[Any] | np.ndarray,
        *,
        colliders: Sequence[Sequence[Any] | None] | None = None,
        wait: bool = False,
        on_error: ErrorCallback | None = None,
    ) -> list[int | DrapeError] | None:
        """Move the pins of many cloths in one message: ``indices`` the same for every cloth
        (a sequence of ints) or one sequence per cloth; ``targets[j]`` the (k, 3) targets of
        ``handles[j]`` (one (n, k, 3) array is best); ``colliders[j]`` (optional) the colliders of
        ``handles[j]`` (None: unchanged). Shared indices and no colliders, to a 1.4 server: one
        ``moves`` block (PROTOCOL.md 5.1.1), with no Python loop over the cloths (client/sending.py).
        ``wait=True``: each cloth's first tick; BatchError (with every outcome) if any was refused."""
        if len(targets) != len(handles):
            raise ValueError(f"{len(handles)} cloths but {len(targets)} target arrays")
        try:
            shared = np.asarray(indices).ndim == 1  # one index list for every cloth
        except ValueError:  # ragged: one list per cloth
            shared = False
        if shared and colliders is None:
            return self.sender.moves(handles, np.asarray(indices), np.asarray(targets), wait, on_error)
        b = self.batch(wait=wait, on_error=on_error)
        for j, h in enumerate(handles):
            idx = cast("Sequence[int] | np.ndarray", indices if shared else indices[j])
            b.move_pins(h, idx, targets[j], colliders=None if colliders is None else colliders[j])
        return b.send()

    # --- submissions ------------------------------------------------------------------------------
    def submit(
        self,
        req: P.SubmitRequest,
        rest_positions: np.ndarray | None = None,
        triangles: np.ndarray | None = None,
        timeout: float | None = None,
        queue_size: int | None = None,
        server: str | None = None,
    ) -> ClothHandle:
        """Send a SubmitRequest as is and subscribe to the new cloth's state (with
        ``req.state.bundle``: to this client's bundle, once for all its bundled cloths; a 1.0
        server ignores the option and the handle subscribes to the cloth's own key). A grid's
        ``rest_positions`` and ``triangles`` default to its geometry, built once it is accepted.

        To ``server``, else the client's ``server_id`` when one was given, else the live server
        the placement ranks first (PROTOCOL.md 11.3); a refusal another server may not give
        (``overloaded``, ``busy``, ``limit_exceeded``, no reply) tries the next one, and the last
        refusal is raised when every live server refused."""
        return self.submitter.submit(req, rest_positions, triangles, timeout, queue_size, server)

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
        ``cloth_options``. Its geometry (the handle's ``rest_positions`` and ``triangles``) is
        built once the server accepted it: a grid too large is refused before anything is built."""
        return self._submit(grid=grid_spec(cols, rows, width, height, orientation, origin), **options)

    def submit_mesh(
        self, vertices: np.ndarray | Sequence, triangles: np.ndarray | Sequence, **options: Any
    ) -> ClothHandle:
        """A triangle mesh cloth: vertices (n, 3) metres, triangles (m, 3) vertex indices."""
        mesh = mesh_spec(vertices, triangles)
        return self._submit(mesh=mesh, rest=mesh.vertices, tris=mesh.triangles, **options)

    def submit_obj(self, path: str | Path, **options: Any) -> ClothHandle:
        """A cloth from a Wavefront OBJ file (faces fan-triangulated)."""
        v, t = P.parse_obj(Path(path).read_text())
        return self.submit_mesh(v, t, **options)

    def set_scene(
        self,
        scene: str,
        colliders: Sequence[Any] | None = None,
        members: Sequence[str] | None = None,
        timeout: float | None = None,
        server: str | None = None,
        *,
        mesh_collider: Any = None,
        mesh_position: Sequence[float] | None = None,
        mesh_rotation: Sequence[float] | None = None,
    ) -> P.SceneReply:
        """Protocol 1.7: move the colliders of ``scene`` (they act on every cloth of the scene
        beside its own; ``[]`` clears them) and/or set who else may submit cloths into it
        (client ids, ``"*"``: anyone), as the scene's owner: the client whose cloth founded it
        on ``server`` (PROTOCOL.md 5.3). None leaves a field as it is. Raises Forbidden for
        another client's scene, NotFound for a scene without cloths.

        1.8 (PROTOCOL.md 5.4): ``mesh_collider``, the scene's mesh for every cloth of it (a
        ``(vertices, triangles)`` pair or an object with them, ``False`` to remove it, or a
        ``P.MeshCollider``), at ``mesh_position`` / ``mesh_rotation`` (w, x, y, z); the pose alone
        (``mesh_collider`` None) moves the scene's mesh rigidly: the per-tick call.

        ``server`` None: the server of this client's cloths of the scene (else the default server).
        What a request that succeeded set is remembered (``client.scenes``): a failover founds the
        scene again with it (client/failover.py)."""
        if mesh_collider is None and (mesh_position is not None or mesh_rotation is not None):
            mesh_collider = P.MeshCollider.pose(mesh_position or (0.0, 0.0, 0.0))
        mc = as_mesh_collider(mesh_collider, mesh_position, mesh_rotation)
        req = P.SceneRequest(
            self.client_id,
            scene,
            tuple(P.as_collider(c) for c in colliders) if colliders is not None else None,
            tuple(members) if members is not None else None,
            self.connection.next_rid(),
            mc,
        )
        server = server or self.cloths.scene_server(scene)
        rep = P.scene_reply_from_map(self.connection.request("scene", P.encode_scene(req), timeout, server))
        self.scenes.sent(req, rep)
        return rep

    def _submit(
        self,
        *,
        rest: np.ndarray | None = None,
        tris: np.ndarray | None = None,
        timeout: float | None = None,
        queue_size: int | None = None,
        server: str | None = None,
        **options: Any,
    ) -> ClothHandle:
        req = submit_request(self.client_id, self.connection.next_rid(), **options)
        return self.submit(req, rest, tris, timeout, queue_size, server)


__all__ = [
    "MAX_ORPHAN_CLOTHS",
    "PLACE_ELSEWHERE",
    "BatchError",
    "ClothHandle",
    "ClothState",
    "ControlBatch",
    "DrapeClient",
    "DrapeError",
    "ErrorCallback",
    "Failover",
    "FailoverCallback",
    "FailoverEvent",
    "Placement",
    "StateCallback",
    "Unavailable",
    "cloth_options",
    "zenoh_config",
]
