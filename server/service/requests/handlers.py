"""The request handlers: decode and validate every request with drape.client.protocol, check
ownership and quotas against the registry, admission (submissions and controls that change work)
against the cost model, then hand the work
on (submissions to the cook worker, everything else to the tick thread's intake). A bad request
gets its error reply right here; nothing else notices it. Zenoh's queryable callbacks only queue
the queries (requestq.py: bounded, a full queue answers ``busy`` without decoding); the handlers
run on the one request thread, in arrival order. A batch control is validated
item by item: a bad item gets its own error in the reply, the others go ahead; its moves block
(1.4) move by move, without a per-move loop unless one is refused (moves.py).

Identity (protocol 1.4, PROTOCOL.md 11.2): the submit, control, control_batch and remove
queryables are declared on client-scoped keys, ``{ns}/server/{S}/client/*/{kind}``; a request there
is the client's whose id the key names (a router binds that chunk to the authenticated user). The
handler takes the client id from the key: a payload ``client`` that differs, or a control or remove
of another client's cloth, is refused ``forbidden``, so quotas, bundles and liveliness hang on the
key's id. With ``identity = "open"`` (the default) the server-wide queryables of 1.0-1.3 are
declared as well and work as before; ``identity = "keys"`` declares only the client-scoped ones.
"""

from __future__ import annotations

import logging
import queue
import secrets
from collections import Counter
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import zenoh

from drape.client import protocol as P

from ..commands import BatchControl, Intake, Remove, SceneColliders
from ..config import ServerConfig
from ..registry import ClothRecord, Registry
from ..replies import Replies, Reply, send
from ..worldparams import pack
from .admission import ERR_OVERLOADED, Admission
from .moves import MoveChecker, refused_counts
from .requestq import RequestQueue, TickGate

log = logging.getLogger(__name__)


def reports_features(payload: bytes) -> bool:
    """Whether a request is stamped 1.2 or later (its replies then carry ``features``): reads
    the ``v`` entry only, without decoding the rest again."""
    try:
        up = msgpack.Unpacker(raw=False)
        up.feed(payload)
        for _ in range(up.read_map_header()):
            key = up.unpack()
            if key == "v":
                v = up.unpack()
                return tuple(v[:2]) >= (1, 2)
            up.skip()
    except Exception:
        pass
    return False


class Handlers:
    def __init__(
        self,
        config: ServerConfig,
        keys: P.Keys,
        registry: Registry,
        replies: Replies,
        intake: Intake,
        cook_q: queue.Queue,
        admission: Admission,
        gate: TickGate | None,
        tick: Callable[[], int],
        info: Callable[[], dict],
        stopping: Callable[[], bool],
    ) -> None:
        self.config, self.keys, self.registry, self.replies = config, keys, registry, replies
        self.intake, self.cook_q, self.admission = intake, cook_q, admission
        self.moves = MoveChecker(registry)  # 1.4 moves blocks
        self.limits = config.limits()
        self._tick, self._info, self._stopping = tick, info, stopping
        self.gate = gate  # requests start while the tick thread sleeps (None: whenever they come)
        self.request_queue = RequestQueue(
            config.max_pending_requests,
            config.max_pending_request_bytes,
            self.refuse,
            name=f"drape-requests-{config.server_id}",
            gate=self.gate,
        )

    def endpoints(self) -> list[tuple[str, Callable[[zenoh.Query], None]]]:
        """(key expression, callback) of every queryable this server declares: the client-scoped
        request keys (1.4), the server-wide ones unless ``identity = "keys"``, and info. Each
        callback queues its query for the request thread (``self.request_queue``, started by the server)."""
        sid = self.config.server_id
        callbacks: dict[str, Callable[..., None]] = {
            "submit": self.on_submit,
            "control": self.on_control,
            "control_batch": self.on_control_batch,
            "remove": self.on_remove,
            "scene": self.on_scene,  # 1.7
        }
        out = [(self.keys.client_request(n, sid, "*"), self._guard(n, cb, scoped=True)) for n, cb in callbacks.items()]
        if self.config.identity == "open":
            out += [(getattr(self.keys, n)(sid), self._guard(n, cb)) for n, cb in callbacks.items()]
        out.append((self.keys.info(sid), self._guard("info", self.on_info)))
        return [(key, self.request_queue.callback(name, handler)) for key, (name, handler) in out]

    def refuse(self, name: str, query: zenoh.Query, reason: str) -> None:
        """Answer a query the request queue turned away (full, or the server stopping): ``busy``,
        counted as a request of its kind; nothing of it is decoded."""
        with self.registry.lock:
            self.registry.requests[name] += 1
        self.replies.send_error(query, P.ERR_BUSY, reason, 0)

    def _guard(
        self, name: str, cb: Callable[..., None], scoped: bool = False
    ) -> tuple[str, Callable[[zenoh.Query], None]]:
        """(name, the handler around ``cb(query, payload, client)``): counts, turns every
        DrapeError into its error reply; ``scoped``: ``client`` is the id the query's key names."""
        reg = self.registry

        def handler(query: zenoh.Query) -> None:
            with reg.lock:
                reg.requests[name] += 1
            rid: int | None = 0
            try:
                if self._stopping():
                    raise P.Busy(P.ERR_BUSY, "server is shutting down")
                client = None
                if scoped:
                    client = self.keys.request_client(str(query.key_expr), name)
                    if client is None:
                        raise P.Forbidden(P.ERR_FORBIDDEN, f"{query.key_expr}: the key must name exactly one client id")
                payload = query.payload.to_bytes() if query.payload is not None else b""
                cb(query, payload, client)
            except P.DrapeError as e:
                rid = e.rid
                if e.code == ERR_OVERLOADED:
                    reg.count("overload_refusals")
                self.replies.send_error(query, e.code, e.message, rid)
            except Exception as e:  # never let a request kill the request thread
                log.exception("internal error handling %s", name)
                self.replies.send_error(query, P.ERR_INTERNAL, f"internal error: {type(e).__name__}", rid)

        return name, handler

    # --- submit ------------------------------------------------------------------------------------
    @staticmethod
    def same_client(named: str, key_client: str | None, rid: int) -> None:
        """A request on a client-scoped key must name the key's client wherever it names one."""
        if key_client is not None and named != key_client:
            raise P.Forbidden(
                P.ERR_FORBIDDEN, f"client {named!r} in a request on client {key_client!r}'s key (PROTOCOL.md 11.2)", rid
            )

    def on_submit(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        req = P.decode_submit(payload, self.limits)
        self.same_client(req.client, client, req.rid)
        rec = ClothRecord(
            id=secrets.token_hex(8),
            client=req.client,
            token=secrets.token_hex(16),
            key="",
            n_vertices=req.n_vertices,
            encoding=(req.state.encoding if req.state and req.state.encoding else "float32"),
            step=(req.state.step if req.state and req.state.step else P.STEP_DEFAULT),
        )
        # a cloth submitted on a client-scoped key (1.4) publishes on the client-scoped state key
        rec.key = self.keys.state(rec.id) if client is None else self.keys.client_state(client, rec.id)
        if req.state is not None and req.state.bundle:
            rec.bundle_key = self.keys.bundle(req.client)
        rec.scene = req.scene  # 1.7: reserve checks it admits the client (PROTOCOL.md 5.3)
        self.admission.admit_submit(self.registry, rec, req)  # priced by its work (rec.priced)
        self.registry.reserve(rec, req.rid)
        try:
            self.cook_q.put_nowait((rec, req, query))
        except queue.Full:
            self.registry.unreserve(rec)
            raise P.Busy(P.ERR_BUSY, "server request queue is full, retry later", req.rid) from None

    # --- controls ----------------------------------------------------------------------------------
    def check_control(self, req: P.ControlRequest, client: str | None = None) -> tuple[ClothRecord, np.ndarray | None]:
        """Ownership (and, in a batch, that the cloth is the batch client's), pin indices and
        colliders of one control; raises the DrapeError that refuses it."""
        rec = self.registry.owned(req.cloth, req.token, req.rid)
        assert rec.fabric is not None
        if client is not None and rec.client != client:
            raise P.Forbidden(P.ERR_FORBIDDEN, f"cloth {rec.id!r} is not a cloth of client {client!r}", req.rid)
        if req.pins is not None and len(req.pins.indices):
            idx = req.pins.indices
            top = int(idx.max())
            if top >= rec.n_vertices:
                raise P.ProtocolError(
                    P.ERR_INDEX_OUT_OF_RANGE,
                    f"'pins.indices' refers to vertex {top} but cloth {rec.id!r} has {rec.n_vertices} vertices",
                    req.rid,
                )
            free = idx[~rec.fabric.pinned[idx]]
            if len(free):
                raise P.ProtocolError(
                    P.ERR_INVALID_VALUE,
                    f"vertex {int(free[0])} of cloth {rec.id!r} is not pinned; only pinned vertices take targets",
                    req.rid,
                )
        packed = pack(req.colliders, req.rid) if req.colliders is not None else None
        self.admission.admit_control(self.registry, rec, req)  # a control that raises the cloth's work
        return rec, packed

    def on_control(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        req = P.decode_control(payload, self.limits)
        rec, packed = self.check_control(req, client)
        self.intake.put_controls([(rec, req, packed, query, (req.rid, reports_features(payload)))], req.rid)

    def on_control_batch(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        batch = P.decode_control_batch(payload, self.limits)  # the envelope: all or nothing
        self.same_client(batch.client, client, batch.rid)  # then every item is checked against batch.client
        results: list[P.BatchItemResult | None] = [None] * len(batch.items)
        waiter = BatchControl(query, batch.rid, results, features=reports_features(payload))
        todo: list[tuple[ClothRecord, P.ControlRequest, np.ndarray | None, Any, int]] = []
        failed: Counter[str] = Counter()
        for i, item in enumerate(batch.items):
            try:
                if isinstance(item, P.ProtocolError):
                    raise item
                rec, packed = self.check_control(item, batch.client)
            except P.DrapeError as e:
                results[i] = P.BatchItemResult(None, e.code, e.message)
                failed[e.code] += 1
                if e.code == ERR_OVERLOADED:
                    self.registry.count("overload_refusals")
                continue
            todo.append((rec, item, packed, waiter, i))
        block = None
        if batch.moves is not None:  # 1.4: ownership per move, pinned-ness per fabric (moves.py)
            block = self.moves.check(batch.moves, batch.client, waiter)
        reg = self.registry
        with reg.lock:
            reg.errors.update(failed)
            reg.errors.update(refused_counts(waiter.moves_failed or []))
            reg.counters["batch_items"] += len(batch.items)
            reg.counters["batch_moves"] += len(batch.moves or ())
        if failed:
            log.debug(
                "batch control of client %s: %d of %d items refused: %s",
                batch.client,
                sum(failed.values()),
                len(batch.items),
                dict(failed),
            )
        if not todo and block is None:  # nothing to apply: answer now
            send(waiter.reply(self._tick() + 1))
            return
        waiter.pending = len(todo) + (block is not None)
        self.intake.put_controls(todo, batch.rid, block)

    # --- remove, info, liveliness ----------------------------------------------------------------------
    def on_remove(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        req = P.decode_remove(payload, self.limits)
        rec = self.registry.owned(req.cloth, req.token, req.rid)
        if client is not None and rec.client != client:
            raise P.Forbidden(P.ERR_FORBIDDEN, f"cloth {rec.id!r} is not a cloth of client {client!r}", req.rid)
        self.intake.put(Remove(rec, query, req.rid), req.rid)

    def on_scene(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        """1.7: a scene's colliders and members, 1.8: its mesh collider, from its owner only
        (PROTOCOL.md 5.3, 5.4)."""
        req = P.decode_scene(payload, self.limits)
        self.same_client(req.client, client, req.rid)
        scene = self.registry.owned_scene(req.scene, req.client, req.rid)
        packed = pack(req.colliders, req.rid) if req.colliders is not None else None
        with self.registry.lock:
            if req.members is not None:
                scene.members = req.members
            reply = P.SceneReply(self._tick() + 1, scene.owner, len(scene.cloths), scene.members, req.rid)
        if packed is None and req.mesh_collider is None:
            send(Reply(query, P.encode_scene_reply(reply)))
            return
        self.intake.put(SceneColliders(req.scene, packed, query, reply, req.mesh_collider), req.rid)

    def on_info(self, query: zenoh.Query, payload: bytes, client: str | None = None) -> None:
        req = P.decode_info(payload, self.limits)
        send(Reply(query, P.encode_ok(req.rid, **self._info())))

    def on_client_liveliness(self, sample: zenoh.Sample) -> None:
        client = self.keys.last_chunk(str(sample.key_expr))
        alive = sample.kind == zenoh.SampleKind.PUT
        self.registry.client_alive(client, alive)
        log.debug("client %s %s", client, "alive" if alive else "gone")
