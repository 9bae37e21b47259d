"""The Drape server: a fixed-rate tick loop over one World, served over Zenoh.

Threads and who owns what:

- **Zenoh callbacks** (submit, control, control_batch, remove, info queryables; client
  liveliness) decode and validate every request with drape.client.protocol, check ownership and
  quotas against the registry (a lock-protected dict of ClothRecord), then queue a command. A
  bad request gets its error reply right there; nothing else notices it. A batch control is
  validated item by item: a bad item gets its own error in the reply, the others go ahead.
- **cook thread**: cooks the fabric of each accepted submission (pure numpy, possibly slow for
  a large mesh), so neither a Zenoh thread nor the tick thread waits for it.
- **tick thread**: the only thread that touches the World. Each tick: apply queued commands,
  reclaim cloths of vanished clients, step, read back, copy every cloth's positions out of the
  World's double-buffered host memory into one contiguous array (resetting any cloth that went
  non-finite), and hand the frame to the publisher. Ticks follow a monotonic deadline schedule: an overrun skips whole
  deadlines and counts them as missed, it never drifts.
- **publisher thread**: sends the acknowledgements of the commands applied this tick, encodes
  the frame (drape.server.service.statecodec: bounds and encodings for all cloths at once, reused
  buffers) and publishes each cloth's state on its own key, or, for cloths submitted with
  ``state.bundle``, one bundle per client on that client's bundle key, while the device already
  works on the next tick; states (or bundles) whose key has no subscriber are not encoded at
  all (Zenoh matching status, counted as ``unwatched``). Then it sends remove acknowledgements
  and the periodic stats. If it is still busy when the
  next frame is ready, that frame replaces the pending one (coalesced, counted as skipped): the
  tick thread never waits for the network.
"""
from __future__ import annotations

import hashlib
import hmac
import logging
import queue
import secrets
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any, Callable, TypeVar

import numpy as np
import zenoh

from drape.client import protocol as P
from drape.client.sdk import zenoh_config

from ..sim import quality
from .config import ServerConfig
from ..sim.fabric import Fabric, FabricCache, cook_grid, cook_mesh
from ..sim.params import Capsule, ClothParams, Features, LinkOptions, Material, Plane, Sphere, pack_colliders
from ..sim.reference import vertex_normals
from .statecodec import FrameEncoder
from .telemetry import PHASES, PhaseTimer
from ..sim.world import World, make_world

log = logging.getLogger(__name__)

T = TypeVar("T")

MAX_COMMANDS_PER_TICK = 256
FABRIC_MEMO_SIZE = 64


# ---------------------------------------------------------------------------------------------
# Records, commands, jobs


@dataclass(eq=False)
class ClothRecord:
    """One cloth as the service knows it. Created (reserved) when a submission is accepted;
    ``handle`` is set by the tick thread once the cloth is in the World."""

    id: str
    client: str
    token: str
    key: str
    n_vertices: int
    encoding: str = "float32"
    fabric: Fabric | None = None
    params: ClothParams | None = None
    handle: int | None = None
    removed: bool = False
    reset_flag: bool = False  # the next published state carries FLAG_RESET
    bundle_key: str | None = None  # published inside this client's bundle on this key (1.1), not on ``key``
    quality_wanted: str | None = None  # the preset the client asked for (1.1)
    quality: str | None = None  # the preset in force: lower than wanted while the server is overloaded


@dataclass(eq=False)
class _Add:
    record: ClothRecord
    colliders: np.ndarray | None
    query: zenoh.Query
    rid: int


@dataclass(eq=False)
class _Control:
    record: ClothRecord
    req: P.ControlRequest
    colliders: np.ndarray | None
    query: zenoh.Query


@dataclass(eq=False)
class _BatchItem:
    index: int  # in the request's items
    record: ClothRecord
    req: P.ControlRequest
    colliders: np.ndarray | None


@dataclass(eq=False)
class _BatchControl:
    query: zenoh.Query
    rid: int
    results: list[P.BatchItemResult | None]  # filled in for items refused on arrival
    items: list[_BatchItem]  # the items to apply


@dataclass(eq=False)
class _Remove:
    record: ClothRecord
    query: zenoh.Query
    rid: int


@dataclass(eq=False)
class _Call:
    fn: Callable[[World], Any]
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


@dataclass(eq=False)
class _Reply:
    query: zenoh.Query
    payload: bytes
    error: bool = False


@dataclass(eq=False)
class _StateItem:
    """One cloth of a frame; its positions are rows ``offsets[i]:offsets[i + 1]`` of the job's
    ``positions`` where ``i`` is its index in ``states``."""

    cloth: str
    key: str
    bundle: str | None  # the client's bundle key, or None: published on ``key``
    normals: np.ndarray | None  # (n, 3) float32, owned
    encoding: int  # protocol encoding id
    flags: int


@dataclass(eq=False)
class _Job:
    """Everything the publisher sends for one tick, in order: ``before`` replies, states,
    publisher undeclarations for ``removed`` cloths, ``after`` replies, stats."""

    tick: int = 0
    time_ns: int = 0
    states: list[_StateItem] = field(default_factory=list)
    positions: np.ndarray | None = None  # (N, 3) float32: every state's positions back to back, owned
    offsets: np.ndarray | None = None  # (len(states) + 1,) int64
    before: list[_Reply] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    after: list[_Reply] = field(default_factory=list)
    stats: bytes | None = None

    def absorb(self, older: "_Job") -> None:
        """Coalesce: keep this job's states, keep every reply and removal of the older one first."""
        self.before = older.before + self.before
        self.removed = older.removed + self.removed
        self.after = older.after + self.after
        if self.stats is None:
            self.stats = older.stats


class _Mailbox:
    """A one-slot hand-off from the tick thread to the publisher that never blocks the producer."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._job: _Job | None = None
        self._closed = False

    def put(self, job: _Job) -> bool:
        """Hand over a job; True when it replaced one the publisher had not taken yet."""
        with self._cond:
            coalesced = self._job is not None
            if coalesced:
                job.absorb(self._job)  # type: ignore[arg-type]
            self._job = job
            self._cond.notify()
            return coalesced

    def take(self) -> _Job | None:
        """The next job; None once closed and empty."""
        with self._cond:
            while self._job is None and not self._closed:
                self._cond.wait()
            job, self._job = self._job, None
            return job

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


QUALITY_PATIENCE = 3  # ticks over budget in a row before presets step down (x4 under, to step up)
QUALITY_HEADROOM = 0.6  # step back up only when ticks take less than this share of the budget


# ---------------------------------------------------------------------------------------------
# The server


class Server:
    """``Server(config).start()`` ... ``.stop()``, or ``with Server(config) as s: ...``.

    ``config`` defaults to ServerConfig(); keyword overrides replace its fields
    (``Server(tick_rate=30, listen=["tcp/127.0.0.1:7500"])``)."""

    def __init__(self, config: ServerConfig | None = None, *, warmup: bool = True, **overrides: Any) -> None:
        cfg = config or ServerConfig()
        self.config: ServerConfig = (replace(cfg, **overrides) if overrides else cfg).validate()
        self.keys = P.Keys(self.config.namespace)
        self.limits = self.config.limits()
        self.warmup = warmup
        self._lock = threading.Lock()  # guards the registry and counters below
        self._cloths: dict[str, ClothRecord] = {}
        self._by_client: dict[str, set[str]] = {}
        self._vertices = 0
        self._alive: set[str] = set()
        self._gone_since: dict[str, float] = {}
        self._requests: Counter[str] = Counter()
        self._errors: Counter[str] = Counter()
        self._counters: Counter[str] = Counter()
        self._timers = {p: PhaseTimer() for p in PHASES}
        self._quality_state: dict[str, Any] = {"over": 0, "under": 0, "events": 0, "last": None,
                                               "degraded_since": None, "degraded_s": 0.0,
                                               "last_check": time.monotonic()}
        self._live: dict[str, ClothRecord] = {}  # tick thread only: cloths in the World
        self._commands: queue.Queue = queue.Queue(self.config.max_pending_requests)
        self._cook_q: queue.Queue = queue.Queue(self.config.max_pending_requests)
        self._mailbox = _Mailbox()
        self._fabrics = FabricCache()
        self._memo: OrderedDict[str, Fabric] = OrderedDict()
        self._world: World | None = None
        self._session: zenoh.Session | None = None
        self._declared: list[Any] = []
        self._pubs: dict[str, tuple[zenoh.Publisher, bool]] = {}  # publisher thread only: per cloth
        self._bundle_pubs: dict[str, tuple[zenoh.Publisher, bool]] = {}  # publisher thread only: per bundle key
        self._encoder = FrameEncoder()  # publisher thread only
        self._buffers: dict[str, bytearray] = {}  # publisher thread only: payload buffers reused per key
        self._stats_pub: zenoh.Publisher | None = None
        self._token: Any = None
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._stop_ticks = threading.Event()
        self._stopped = threading.Event()
        self._tick = 0
        self._started_at = 0.0
        self._last_stats: dict[str, Any] = {}
        self.failure: BaseException | None = None
        self.device_name = "?"

    # --- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "Server":
        """Create the World, open the Zenoh session, start the threads, declare the endpoints
        and finally the server's liveliness token. On failure everything is torn down again."""
        try:
            self._start()
        except BaseException:
            self.stop()
            raise
        return self

    def _start(self) -> None:
        cfg = self.config
        kw = {} if cfg.solver == "reference" else {"device": cfg.device}
        self._world = make_world(cfg.solver, **kw)
        self.device_name = getattr(self._world, "device_name", cfg.solver)
        if self.warmup:
            self._warm_up()
        zc = zenoh_config(cfg.mode, cfg.listen, cfg.connect, cfg.multicast_scouting, cfg.zenoh_config)
        if cfg.zenoh_config is None:
            # States go out in bursts (every cloth each tick) under DROP congestion control. Zenoh's
            # default data queue holds 2 batches and drops after waiting 1 ms, so a server whose
            # Zenoh threads were descheduled for a few ms lost states on a busy 2-core box. Sixteen
            # batches (Zenoh's maximum) ride that out; a dead subscriber still cannot stall the
            # publisher for longer than the unchanged 1 ms wait.
            zc.insert_json5("transport/link/tx/queue/size/data", "16")
        self._session = s = zenoh.open(zc)
        sid = cfg.server_id
        self._started_at = time.monotonic()
        self._threads = [
            threading.Thread(target=self._run_publisher, name=f"drape-publish-{sid}", daemon=True),
            threading.Thread(target=self._run_cook, name=f"drape-cook-{sid}", daemon=True),
            threading.Thread(target=self._run_ticks, name=f"drape-tick-{sid}", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self._stats_pub = s.declare_publisher(self.keys.stats(sid), congestion_control=zenoh.CongestionControl.DROP)
        lv = s.liveliness()
        self._declared.append(lv.declare_subscriber(self.keys.all_clients_alive, self._on_client_liveliness, history=True))
        for name, cb in (("submit", self._on_submit), ("control", self._on_control),
                         ("control_batch", self._on_control_batch), ("remove", self._on_remove),
                         ("info", self._on_info)):
            key = getattr(self.keys, name)(sid)
            self._declared.append(s.declare_queryable(key, self._guard(name, cb)))
        self._token = lv.declare_token(self.keys.alive_server(sid))
        log.info("drape server %s up: %s solver on %s, %.0f Hz, %s mode, listen %s connect %s, namespace %r",
                 sid, cfg.solver, self.device_name, cfg.tick_rate, cfg.mode, cfg.listen, cfg.connect, cfg.namespace)

    def stop(self, timeout: float = 10.0) -> None:
        """Stop serving: no new requests, last tick finishes, publishing stops, everything is
        undeclared and the session closed. Idempotent."""
        if self._stopping.is_set():
            self._stopped.wait(timeout)
            return
        self._stopping.set()
        log.info("drape server %s stopping", self.config.server_id)
        try:
            if self._token is not None:
                self._token.undeclare()
                self._token = None
            for d in self._declared:
                _undeclare(d)
            self._declared.clear()
            self._cook_q.put(None)
            self._stop_ticks.set()
            deadline = time.monotonic() + timeout
            for t in self._threads:
                if t.name.startswith("drape-publish"):
                    continue
                t.join(max(0.0, deadline - time.monotonic()))
            self._shutdown_commands()  # anything the cook thread queued after the tick thread ended
            self._mailbox.close()
            for t in self._threads:
                if t.name.startswith("drape-publish"):
                    t.join(max(0.0, deadline - time.monotonic()))
            for pub, _ in list(self._pubs.values()) + list(self._bundle_pubs.values()):
                _undeclare(pub)
            self._pubs.clear()
            self._bundle_pubs.clear()
            if self._stats_pub is not None:
                _undeclare(self._stats_pub)
                self._stats_pub = None
            if self._world is not None:
                self._world.close()
            if self._session is not None:
                self._session.close()
                self._session = None
        finally:
            self._stopped.set()
            log.info("drape server %s stopped after %d ticks", self.config.server_id, self._tick)

    def __enter__(self) -> "Server":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._session is not None and not self._stopping.is_set()

    @property
    def tick(self) -> int:
        return self._tick

    @property
    def server_id(self) -> str:
        return self.config.server_id

    def wait_stopped(self, timeout: float | None = None) -> bool:
        return self._stopped.wait(timeout)

    def call(self, fn: Callable[[World], T], timeout: float = 10.0) -> T:
        """Run ``fn(world)`` on the tick thread between two ticks and return its result (for
        tools and tests; the World must only ever be touched there)."""
        cmd = _Call(fn)
        self._commands.put(cmd, timeout=timeout)
        if not cmd.done.wait(timeout):
            raise TimeoutError("the tick thread did not run the call in time")
        if cmd.error is not None:
            raise cmd.error
        return cmd.result  # type: ignore[return-value]

    def world_handle(self, cloth_id: str) -> int | None:
        """The World handle of a cloth (for ``call``)."""
        with self._lock:
            rec = self._cloths.get(cloth_id)
            return None if rec is None else rec.handle

    # --- stats -------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Cumulative counters and the phase timings of the current stats window."""
        return self._stats(reset_window=False)

    def _stats(self, reset_window: bool) -> dict[str, Any]:
        with self._lock:
            c = dict(self._counters)
            out: dict[str, Any] = {
                "server": self.config.server_id,
                "tick": self._tick,
                "time_ns": time.time_ns(),
                "uptime_s": time.monotonic() - self._started_at if self._started_at else 0.0,
                "tick_rate": self.config.tick_rate,
                "cloths": len(self._cloths),
                "clients": len(self._by_client),
                "alive_clients": len(self._alive),
                "vertices": self._vertices,
                "requests": dict(self._requests),
                "errors": dict(self._errors),
            }
        for k in ("ticks", "missed_ticks", "skipped_frames", "nan_resets", "reclaimed", "published",
                  "unwatched", "publish_errors", "bundles", "batch_items"):
            out[k] = c.get(k, 0)
        out["phases"] = {p: t.snapshot(reset_window) for p, t in self._timers.items()}
        out["quality"] = self._quality_stats()
        return out

    def info(self) -> dict[str, Any]:
        cfg = self.config
        with self._lock:
            counts = {"cloths": len(self._cloths), "clients": len(self._by_client), "vertices": self._vertices}
        return {
            "server": cfg.server_id,
            "version": P.VERSION_STRING,
            "solver": cfg.solver,
            "device": self.device_name,
            "tick_rate": cfg.tick_rate,
            "tick": self._tick,
            **counts,
            "limits": {
                "max_cloths": cfg.max_cloths,
                "max_cloths_per_client": cfg.max_cloths_per_client,
                "max_vertices_per_cloth": cfg.max_vertices_per_cloth,
                "max_total_vertices": cfg.max_total_vertices,
                "max_message_bytes": cfg.max_message_bytes,
                "max_pin_updates": cfg.max_pin_updates,
                "max_batch_items": cfg.max_batch_items,
                "max_colliders": self.limits.max_colliders,
                "max_iterations": cfg.max_iterations,
                "max_substeps": cfg.max_substeps,
            },
            "encodings": list(P.ENCODINGS),
            "features": list(P.FEATURE_NAMES),
            "grace_period_s": cfg.grace_period,
            "stats_period_s": cfg.stats_period,
        }

    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counters[name] += n

    # --- replies -----------------------------------------------------------------------------
    def _reply_error(self, query: zenoh.Query, code: str, message: str, rid: int | None = 0) -> None:
        with self._lock:
            self._errors[code] += 1
        log.debug("request %s rejected: [%s] %s", query.key_expr, code, message)  # counted in stats
        _send(_Reply(query, P.encode_error(code, message, rid or 0), True))

    def _error_reply(self, query: zenoh.Query, code: str, message: str, rid: int | None) -> _Reply:
        with self._lock:
            self._errors[code] += 1
        log.debug("request %s failed: [%s] %s", query.key_expr, code, message)
        return _Reply(query, P.encode_error(code, message, rid or 0), True)

    def _guard(self, name: str, cb: Callable[[zenoh.Query, bytes], None]) -> Callable[[zenoh.Query], None]:
        def handler(query: zenoh.Query) -> None:
            with self._lock:
                self._requests[name] += 1
            rid: int | None = 0
            try:
                if self._stopping.is_set():
                    raise P.Busy(P.ERR_BUSY, "server is shutting down")
                payload = query.payload.to_bytes() if query.payload is not None else b""
                cb(query, payload)
            except P.DrapeError as e:
                rid = e.rid
                self._reply_error(query, e.code, e.message, rid)
            except Exception as e:  # never let a request kill a Zenoh thread
                log.exception("internal error handling %s", name)
                self._reply_error(query, P.ERR_INTERNAL, f"internal error: {type(e).__name__}", rid)

        return handler

    def _enqueue(self, q: queue.Queue, item: Any, rid: int) -> None:
        try:
            q.put_nowait(item)
        except queue.Full:
            raise P.Busy(P.ERR_BUSY, "server request queue is full, retry later", rid) from None

    # --- request handlers (Zenoh threads) ------------------------------------------------------
    def _on_submit(self, query: zenoh.Query, payload: bytes) -> None:
        req = P.decode_submit(payload, self.limits)
        n = req.n_vertices
        cfg = self.config
        rec = ClothRecord(
            id=secrets.token_hex(8),
            client=req.client,
            token=secrets.token_hex(16),
            key="",
            n_vertices=n,
            encoding=(req.state.encoding if req.state and req.state.encoding else "float32"),
        )
        rec.key = self.keys.state(rec.id)
        if req.state is not None and req.state.bundle:
            rec.bundle_key = self.keys.bundle(req.client)
        with self._lock:
            mine = self._by_client.get(req.client, set())
            if len(self._cloths) >= cfg.max_cloths:
                raise P.LimitExceeded(P.ERR_LIMIT_EXCEEDED, f"server is full: {cfg.max_cloths} cloths", req.rid)
            if len(mine) >= cfg.max_cloths_per_client:
                raise P.LimitExceeded(P.ERR_LIMIT_EXCEEDED, f"client {req.client!r} already has "
                                      f"{len(mine)} cloths (limit {cfg.max_cloths_per_client})", req.rid)
            if self._vertices + n > cfg.max_total_vertices:
                raise P.LimitExceeded(P.ERR_LIMIT_EXCEEDED, f"server vertex budget exhausted: {self._vertices} + {n} "
                                      f"> {cfg.max_total_vertices}", req.rid)
            self._cloths[rec.id] = rec
            self._by_client.setdefault(req.client, set()).add(rec.id)
            self._vertices += n
            if req.client not in self._alive:
                self._gone_since.setdefault(req.client, time.monotonic())
        try:
            self._enqueue(self._cook_q, (rec, req, query), req.rid)
        except P.DrapeError:
            self._unreserve(rec)
            raise

    def _owned(self, cloth: str, token: str, rid: int) -> ClothRecord:
        with self._lock:
            rec = self._cloths.get(cloth)
        if rec is None or rec.removed or rec.fabric is None:
            raise P.NotFound(P.ERR_NOT_FOUND, f"no cloth {cloth!r} on server {self.config.server_id!r}", rid)
        if not hmac.compare_digest(rec.token, token):
            raise P.Forbidden(P.ERR_FORBIDDEN, f"the token does not own cloth {cloth!r}", rid)
        return rec

    def _on_control(self, query: zenoh.Query, payload: bytes) -> None:
        req = P.decode_control(payload, self.limits)
        rec, packed = self._check_control(req)
        self._enqueue(self._commands, _Control(rec, req, packed, query), req.rid)

    def _on_control_batch(self, query: zenoh.Query, payload: bytes) -> None:
        batch = P.decode_control_batch(payload, self.limits)  # the envelope: all or nothing
        results: list[P.BatchItemResult | None] = [None] * len(batch.items)
        todo: list[_BatchItem] = []
        failed: Counter[str] = Counter()
        for i, item in enumerate(batch.items):
            try:
                if isinstance(item, P.ProtocolError):
                    raise item
                rec, packed = self._check_control(item, batch.client)
            except P.DrapeError as e:
                results[i] = P.BatchItemResult(None, e.code, e.message)
                failed[e.code] += 1
                continue
            todo.append(_BatchItem(i, rec, item, packed))
        with self._lock:
            self._errors.update(failed)
            self._counters["batch_items"] += len(batch.items)
        if failed:
            log.debug("batch control of client %s: %d of %d items refused: %s", batch.client, sum(failed.values()),
                      len(batch.items), dict(failed))
        if not todo:  # nothing to apply: answer now
            rep = P.ControlBatchReply(self._tick + 1, results, batch.rid)  # type: ignore[arg-type]
            _send(_Reply(query, P.encode_control_batch_reply(rep)))
            return
        self._enqueue(self._commands, _BatchControl(query, batch.rid, results, todo), batch.rid)

    def _check_control(self, req: P.ControlRequest, client: str | None = None) -> tuple[ClothRecord, np.ndarray | None]:
        """Ownership (and, in a batch, that the cloth is the batch client's), pin indices and
        colliders of one control; raises the DrapeError that refuses it."""
        rec = self._owned(req.cloth, req.token, req.rid)
        assert rec.fabric is not None
        if client is not None and rec.client != client:
            raise P.Forbidden(P.ERR_FORBIDDEN, f"cloth {rec.id!r} is not a cloth of client {client!r}", req.rid)
        if req.pins is not None and len(req.pins.indices):
            idx = req.pins.indices
            top = int(idx.max())
            if top >= rec.n_vertices:
                raise P.ProtocolError(P.ERR_INDEX_OUT_OF_RANGE, f"'pins.indices' refers to vertex {top} but cloth "
                                      f"{rec.id!r} has {rec.n_vertices} vertices", req.rid)
            free = idx[~rec.fabric.pinned[idx]]
            if len(free):
                raise P.ProtocolError(P.ERR_INVALID_VALUE, f"vertex {int(free[0])} of cloth {rec.id!r} is not pinned; "
                                      "only pinned vertices take targets", req.rid)
        packed = None
        if req.colliders is not None:
            packed = _pack(req.colliders, req.rid)
        return rec, packed

    def _on_remove(self, query: zenoh.Query, payload: bytes) -> None:
        req = P.decode_remove(payload, self.limits)
        rec = self._owned(req.cloth, req.token, req.rid)
        self._enqueue(self._commands, _Remove(rec, query, req.rid), req.rid)

    def _on_info(self, query: zenoh.Query, payload: bytes) -> None:
        req = P.decode_info(payload, self.limits)
        _send(_Reply(query, P.encode_ok(req.rid, **self.info())))

    def _on_client_liveliness(self, sample: zenoh.Sample) -> None:
        client = self.keys.last_chunk(str(sample.key_expr))
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(client)
                self._gone_since.pop(client, None)
            else:
                self._alive.discard(client)
                if client in self._by_client:
                    self._gone_since[client] = time.monotonic()
        log.debug("client %s %s", client, "alive" if sample.kind == zenoh.SampleKind.PUT else "gone")

    def _unreserve(self, rec: ClothRecord) -> None:
        with self._lock:
            if self._cloths.pop(rec.id, None) is not None:
                self._vertices -= rec.n_vertices
                mine = self._by_client.get(rec.client)
                if mine is not None:
                    mine.discard(rec.id)
                    if not mine:
                        del self._by_client[rec.client]
            rec.removed = True

    # --- cook thread ---------------------------------------------------------------------------
    def _run_cook(self) -> None:
        while True:
            item = self._cook_q.get()
            if item is None:
                break
            rec, req, query = item
            if self._stopping.is_set():
                self._unreserve(rec)
                _send(self._error_reply(query, P.ERR_BUSY, "server is shutting down", req.rid))
                continue
            try:
                fabric = self._cook(req)
            except ValueError as e:
                self._unreserve(rec)
                _send(self._error_reply(query, P.ERR_INVALID_VALUE, f"cannot build the cloth: {e}", req.rid))
                continue
            except Exception as e:
                log.exception("cooking failed")
                self._unreserve(rec)
                _send(self._error_reply(query, P.ERR_INTERNAL, f"cooking failed: {type(e).__name__}", req.rid))
                continue
            try:
                rec.params = _params_from_submit(req)
                if req.quality is not None:
                    rec.params = self._with_preset(rec.params, req.quality, req.rid)
                    rec.quality_wanted = rec.quality = req.quality
                packed = _pack(req.colliders, req.rid) if req.colliders else None
            except P.DrapeError as e:
                self._fabrics.release(fabric)
                self._unreserve(rec)
                _send(self._error_reply(query, e.code, e.message, req.rid))
                continue
            rec.fabric = fabric
            try:
                self._commands.put_nowait(_Add(rec, packed, query, req.rid))
            except queue.Full:
                self._fabrics.release(fabric)
                self._unreserve(rec)
                _send(self._error_reply(query, P.ERR_BUSY, "server request queue is full, retry later", req.rid))
        # drain what is left
        while True:
            try:
                item = self._cook_q.get_nowait()
            except queue.Empty:
                break
            if item is not None:
                rec, req, query = item
                self._unreserve(rec)
                _send(self._error_reply(query, P.ERR_BUSY, "server is shutting down", req.rid))

    def _cook(self, req: P.SubmitRequest) -> Fabric:
        links = LinkOptions(**vars(req.links)) if req.links is not None else LinkOptions()
        pinned = np.unique(req.pinned.astype(np.int64))
        h = hashlib.sha1()
        h.update(repr((req.grid, links)).encode())
        h.update(pinned.tobytes())
        if req.mesh is not None:
            h.update(req.mesh.vertices.tobytes())
            h.update(req.mesh.triangles.tobytes())
        key = h.hexdigest()
        fab = self._memo.get(key)
        if fab is None:
            if req.grid is not None:
                g = req.grid
                fab = cook_grid(g.cols, g.rows, g.width, g.height, links, pinned.tolist(), g.orientation, g.origin)
            else:
                assert req.mesh is not None
                fab = cook_mesh(req.mesh.vertices.astype(np.float64), req.mesh.triangles.astype(np.int64), links,
                                pinned.tolist())
            self._memo[key] = fab
            while len(self._memo) > FABRIC_MEMO_SIZE:
                self._memo.popitem(last=False)
        else:
            self._memo.move_to_end(key)
        return self._fabrics.intern(fab)

    # --- tick thread -----------------------------------------------------------------------------
    def _warm_up(self) -> None:
        """Build the default kernels before serving so the first submission does not stall a tick."""
        w = self._world
        assert w is not None
        t = time.perf_counter()
        h = w.add(cook_grid(2, 2, pinned=[0]), ClothParams())
        w.set_pin_targets(h, np.array([0]), np.zeros((1, 3)))  # builds the pin-target scatter too
        w.step(self.config.dt)
        w.fetch()
        w.remove(h)
        w.fetch()
        log.debug("warm-up took %.3f s", time.perf_counter() - t)

    def _run_ticks(self) -> None:
        cfg = self.config
        period = cfg.dt
        next_t = time.monotonic()
        next_stats = next_t + cfg.stats_period
        try:
            while not self._stop_ticks.is_set():
                t0 = time.monotonic()
                job = _Job()
                self._apply_commands(job)
                self._reclaim(job, t0)
                t1 = time.monotonic()
                tick = self._tick + 1
                states = self._step_and_read(job, tick)
                t3 = time.monotonic()
                job.tick, job.time_ns, job.states = tick, time.time_ns(), states
                self._tick = tick
                self._timers["apply"].add(t1 - t0)
                self._timers["tick"].add(t3 - t0)
                self._adapt_quality(t3 - t0, tick)
                self._count("ticks")
                if t3 >= next_stats:
                    job.stats = P.encode_stats(self._stats(reset_window=True))
                    next_stats += cfg.stats_period
                    if next_stats <= t3:  # fell behind (a long stall): restart the schedule
                        next_stats = t3 + cfg.stats_period
                if self._mailbox.put(job):
                    self._count("skipped_frames")
                next_t += period
                now = time.monotonic()
                if now > next_t:
                    missed = int((now - next_t) / period)
                    if missed:
                        self._count("missed_ticks", missed)
                        next_t += missed * period
                else:
                    self._stop_ticks.wait(next_t - now)
        except BaseException as e:  # a device failure: stop serving loudly
            log.exception("tick loop failed")
            self.failure = e
        finally:
            self._shutdown_commands()

    def _step_and_read(self, job: _Job, tick: int) -> list[_StateItem]:
        w = self._world
        assert w is not None
        if not self._live:
            return []
        t = time.monotonic()
        w.step(self.config.dt)
        w.sync()  # so "solve" is the device's time and "readback" the copy
        t2 = time.monotonic()
        frame = w.fetch()
        recs = list(self._live.values())
        # The frame's arrays are views of double-buffered host memory: copy them out now, every
        # cloth's positions back to back in one array (what the publisher encodes from).
        pos = np.concatenate([frame.positions[r.handle] for r in recs], axis=0, dtype=np.float32)
        offsets = np.zeros(len(recs) + 1, np.int64)
        np.cumsum([r.n_vertices for r in recs], out=offsets[1:])
        bad: set[int] = set()
        if not np.isfinite(pos).all():
            ok = np.isfinite(pos).all(axis=1)
            bad = set(np.flatnonzero(~np.logical_and.reduceat(ok, offsets[:-1])).tolist())
        states: list[_StateItem] = []
        for i, rec in enumerate(recs):
            h = rec.handle
            nrm = frame.normals.get(h)
            nrm = None if nrm is None else np.array(nrm, np.float32)
            flags = 0
            if rec.reset_flag:
                flags |= P.FLAG_RESET
                rec.reset_flag = False
            if i in bad or (nrm is not None and not np.isfinite(nrm).all()):
                assert rec.fabric is not None
                log.warning("cloth %s of client %s went non-finite at tick %d: reset to its rest pose",
                            rec.id, rec.client, tick)
                w.reset(h)
                self._count("nan_resets")
                pos[offsets[i]:offsets[i + 1]] = rec.fabric.rest_positions
                if nrm is not None:
                    nrm = vertex_normals(rec.fabric.rest_positions, rec.fabric)[0].astype(np.float32)
                flags |= P.FLAG_RESET
            states.append(_StateItem(rec.id, rec.key, rec.bundle_key, nrm, P.ENCODING_IDS[rec.encoding], flags))
        job.positions, job.offsets = pos, offsets
        t3 = time.monotonic()
        self._timers["solve"].add(t2 - t)
        self._timers["readback"].add(t3 - t2)
        return states

    def _apply_commands(self, job: _Job) -> None:
        for _ in range(MAX_COMMANDS_PER_TICK):
            try:
                cmd = self._commands.get_nowait()
            except queue.Empty:
                return
            try:
                self._apply(cmd, job)
            except Exception as e:
                log.exception("applying %s failed", type(cmd).__name__)
                q = getattr(cmd, "query", None)
                if q is not None:
                    job.before.append(self._error_reply(q, P.ERR_INTERNAL, f"internal error: {type(e).__name__}: {e}",
                                                        getattr(cmd, "rid", 0)))

    def _apply(self, cmd: Any, job: _Job) -> None:
        w = self._world
        assert w is not None
        if isinstance(cmd, _Call):
            try:
                cmd.result = cmd.fn(w)
            except BaseException as e:
                cmd.error = e
            cmd.done.set()
        elif isinstance(cmd, _Add):
            rec = cmd.record
            if rec.removed:  # its client vanished while it was being cooked
                if rec.fabric is not None:
                    self._fabrics.release(rec.fabric)
                job.before.append(self._error_reply(cmd.query, P.ERR_NOT_FOUND, "cloth was reclaimed before it "
                                                    "was added (client liveliness token gone)", cmd.rid))
                return
            assert rec.fabric is not None and rec.params is not None
            h = None
            try:
                h = w.add(rec.fabric, rec.params)
                if cmd.colliders is not None:
                    w.set_colliders(h, cmd.colliders)
            except Exception as e:
                if h is not None:
                    w.remove(h)
                self._fabrics.release(rec.fabric)
                self._unreserve(rec)
                if isinstance(e, ValueError):
                    job.before.append(self._error_reply(cmd.query, P.ERR_INVALID_VALUE, str(e), cmd.rid))
                else:
                    log.exception("adding cloth %s failed", rec.id)
                    job.before.append(self._error_reply(cmd.query, P.ERR_INTERNAL, f"adding the cloth failed: "
                                                        f"{type(e).__name__}", cmd.rid))
                return
            rec.handle = h
            self._live[rec.id] = rec
            rep = P.SubmitReply(rec.id, rec.token, rec.key, rec.n_vertices, self._tick + 1, cmd.rid, rec.bundle_key)
            job.before.append(_Reply(cmd.query, P.encode_submit_reply(rep)))
            log.info("cloth %s added for client %s: %d vertices, %d links", rec.id, rec.client, rec.n_vertices,
                     rec.fabric.n_links)
        elif isinstance(cmd, _Control):
            job.before.append(self._apply_control(cmd))
        elif isinstance(cmd, _BatchControl):
            job.before.append(self._apply_batch(cmd))
        elif isinstance(cmd, _Remove):
            rec = cmd.record
            if rec.removed or rec.handle is None:
                job.before.append(self._error_reply(cmd.query, P.ERR_NOT_FOUND, f"no cloth {rec.id!r}", cmd.rid))
                return
            last = self._tick
            self._drop(rec, job)
            job.after.append(_Reply(cmd.query, P.encode_remove_reply(P.RemoveReply(last, cmd.rid))))
            log.info("cloth %s removed by client %s", rec.id, rec.client)

    def _apply_control(self, cmd: _Control) -> _Reply:
        err = self._apply_control_item(cmd.record, cmd.req, cmd.colliders)
        if err is not None:
            return self._error_reply(cmd.query, err[0], err[1], cmd.req.rid)
        return _Reply(cmd.query, P.encode_control_reply(P.ControlReply(self._tick + 1, cmd.req.rid)))

    def _apply_batch(self, cmd: _BatchControl) -> _Reply:
        tick = self._tick + 1
        failed: Counter[str] = Counter()
        for it in cmd.items:
            try:
                err = self._apply_control_item(it.record, it.req, it.colliders)
            except Exception as e:  # one item's failure must not leave the others unanswered
                log.exception("applying batch item %d (cloth %s) failed", it.index, it.record.id)
                err = (P.ERR_INTERNAL, f"internal error: {type(e).__name__}: {e}")
            if err is None:
                cmd.results[it.index] = P.BatchItemResult(tick)
            else:
                cmd.results[it.index] = P.BatchItemResult(None, err[0], err[1])
                failed[err[0]] += 1
        if failed:
            with self._lock:
                self._errors.update(failed)
        rep = P.ControlBatchReply(tick, cmd.results, cmd.rid)  # type: ignore[arg-type]
        return _Reply(cmd.query, P.encode_control_batch_reply(rep))

    def _apply_control_item(self, rec: ClothRecord, req: P.ControlRequest,
                            colliders: np.ndarray | None) -> tuple[str, str] | None:
        """Apply one validated control on the tick thread: None, or (code, message) when it is
        refused now (the cloth went away, or its new parameters are invalid); nothing of a
        refused control is applied."""
        w = self._world
        assert w is not None
        if rec.removed or rec.handle is None or rec.params is None:
            return P.ERR_NOT_FOUND, f"no cloth {rec.id!r}"
        p = rec.params
        if _changes_params(req, p):
            feats = set(req.features) if req.features is not None else set(p.features.names())
            if req.colliders:
                feats.add("colliders")
            if req.state is not None and req.state.normals is not None:
                (feats.add if req.state.normals else feats.discard)("normals")
            try:
                material = replace(p.material, **req.material) if req.material else p.material
                new = _params_with(p, req, material, feats)
                new.validate()
            except ValueError as e:
                return P.ERR_INVALID_VALUE, str(e)
            if req.quality is not None:
                try:
                    new = self._with_preset(new, req.quality, req.rid)
                except P.DrapeError as e:
                    return e.code, e.message
                rec.quality_wanted = rec.quality = req.quality
            if new != p:
                w.set_params(rec.handle, new)
                rec.params = new
        h = rec.handle
        if colliders is not None:
            w.set_colliders(h, colliders)
        if req.pins is not None and len(req.pins.indices):
            w.set_pin_targets(h, req.pins.indices.astype(np.int64), req.pins.targets)
        if req.reset:
            w.reset(h)
            rec.reset_flag = True
        if req.state is not None and req.state.encoding is not None:
            rec.encoding = req.state.encoding
        return None

    def _with_preset(self, params: ClothParams, name: str, rid: int) -> ClothParams:
        """``params`` with quality preset ``name`` at this server's tick rate, within its limits."""
        out = quality.apply_preset(params, name, self.config.tick_rate)
        if out.substeps > self.config.max_substeps or out.iterations > self.config.max_iterations:
            raise P.LimitExceeded(P.ERR_LIMIT_EXCEEDED, f"quality {name!r} needs {out.substeps} substeps x "
                                  f"{out.iterations} iterations; this server allows {self.config.max_substeps} x "
                                  f"{self.config.max_iterations}", rid)
        return out

    def _adapt_quality(self, tick_s: float, tick: int) -> None:
        """Adaptive quality (tick thread): when the tick's own work (apply, solve, readback) stays
        over ``quality_budget`` of a tick for ``QUALITY_PATIENCE`` ticks, every cloth that chose a
        preset steps one preset down; once ticks stay under ``QUALITY_HEADROOM`` of the budget for
        four times as long and the step back up is predicted to fit (the presets' measured
        relative costs), they step back up toward what their clients asked for."""
        q = self._quality_state
        now = time.monotonic()
        if q["degraded_since"] is not None:
            q["degraded_s"] += now - q["last_check"]
        q["last_check"] = now
        if not self.config.adaptive_quality:
            return
        budget = self.config.quality_budget * self.config.dt
        if tick_s > budget:
            q["over"] += 1
            q["under"] = 0
            if q["over"] < QUALITY_PATIENCE:
                return
            q["over"] = 0
            moved = [r for r in self._live.values() if r.quality is not None and quality.can_degrade(r.quality)]
            if moved:
                self._set_quality(moved, tick, "down")
            return
        q["over"] = 0
        low = [r for r in self._live.values() if r.quality is not None and r.quality != r.quality_wanted]
        if not low or tick_s >= QUALITY_HEADROOM * budget:
            q["under"] = 0
            return
        ratio = max(quality.PRESETS[quality.restore(r.quality, r.quality_wanted)].cost / quality.PRESETS[r.quality].cost
                    for r in low)
        if tick_s * ratio >= budget:
            q["under"] = 0
            return
        q["under"] += 1
        if q["under"] >= 4 * QUALITY_PATIENCE:
            q["under"] = 0
            self._set_quality(low, tick, "up")

    def _set_quality(self, recs: list[ClothRecord], tick: int, direction: str) -> None:
        w = self._world
        assert w is not None
        changed = 0
        for r in recs:
            name = quality.degrade(r.quality) if direction == "down" else quality.restore(r.quality, r.quality_wanted)
            if name == r.quality or r.handle is None or r.params is None:
                continue
            r.params = quality.apply_preset(r.params, name, self.config.tick_rate)
            r.quality = name
            w.set_params(r.handle, r.params)
            changed += 1
        q = self._quality_state
        degraded = sum(1 for r in self._live.values() if r.quality is not None and r.quality != r.quality_wanted)
        if degraded and q["degraded_since"] is None:
            q["degraded_since"] = time.time_ns()
        elif not degraded:
            q["degraded_since"] = None
        q["events"] += 1
        q["last"] = {"tick": tick, "time_ns": time.time_ns(), "direction": direction, "cloths": changed}
        log.info("adaptive quality: %d cloths one preset %s at tick %d (%d below what they asked for)", changed,
                 direction, tick, degraded)

    def _quality_stats(self) -> dict[str, Any]:
        q = self._quality_state
        live = list(self._live.values())
        by: dict[str, int] = {}
        for r in live:
            if r.quality is not None:
                by[r.quality] = by.get(r.quality, 0) + 1
        return {
            "adaptive": self.config.adaptive_quality,
            "presets": by,
            "degraded": sum(1 for r in live if r.quality is not None and r.quality != r.quality_wanted),
            "degraded_since_ns": q["degraded_since"],
            "degraded_s": round(q["degraded_s"], 3),
            "changes": q["events"],
            "last_change": q["last"],
        }

    def _drop(self, rec: ClothRecord, job: _Job) -> None:
        """Take a cloth out of the World and the registry (tick thread)."""
        w = self._world
        assert w is not None
        if rec.handle is not None and rec.id in self._live:
            w.remove(rec.handle)
            del self._live[rec.id]
            if rec.fabric is not None:
                self._fabrics.release(rec.fabric)
        self._unreserve(rec)
        job.removed.append(rec.id)

    def _reclaim(self, job: _Job, now: float) -> None:
        if not self._gone_since:
            return
        grace = self.config.grace_period
        with self._lock:
            expired = [c for c, t in self._gone_since.items() if now - t >= grace]
            victims: list[ClothRecord] = []
            for c in expired:
                del self._gone_since[c]
                victims.extend(self._cloths[i] for i in self._by_client.get(c, ()))
        for rec in victims:
            self._drop(rec, job)
        if victims:
            self._count("reclaimed", len(victims))
            log.info("reclaimed %d cloth(s) of vanished client(s) %s", len(victims), expired)

    def _shutdown_commands(self) -> None:
        """Answer everything still queued once the tick thread stops."""
        while True:
            try:
                cmd = self._commands.get_nowait()
            except queue.Empty:
                return
            if isinstance(cmd, _Call):
                cmd.error = RuntimeError("server stopped")
                cmd.done.set()
            elif getattr(cmd, "query", None) is not None:
                if isinstance(cmd, _Add) and cmd.record.fabric is not None:
                    self._fabrics.release(cmd.record.fabric)
                    self._unreserve(cmd.record)
                _send(self._error_reply(cmd.query, P.ERR_BUSY, "server is shutting down", getattr(cmd, "rid", 0)))

    # --- publisher thread --------------------------------------------------------------------------
    def _run_publisher(self) -> None:
        while True:
            job = self._mailbox.take()
            if job is None:
                break
            try:
                self._publish(job)
            except Exception:
                log.exception("publishing tick %d failed", job.tick)
                self._count("publish_errors")

    def _publisher(self, store: dict[str, tuple[zenoh.Publisher, bool]], ident: str, key: str,
                   size: int) -> zenoh.Publisher:
        """The publisher of ``key`` (kept in ``store`` under ``ident``), re-declared when the
        congestion control its payload size calls for changes (``auto``)."""
        mode = self.config.state_congestion
        block = mode == "block" or (mode == "auto" and size > self.config.drop_max_bytes)
        have = store.get(ident)
        if have is not None and have[1] == block:
            return have[0]
        if have is not None:
            _undeclare(have[0])
        assert self._session is not None
        cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self._session.declare_publisher(key, congestion_control=cc)
        store[ident] = (pub, block)
        return pub

    def _buffer(self, key: str, size: int) -> bytearray:
        """The payload buffer of ``key``, reused from tick to tick (Zenoh copies a bytearray
        when it is put, so it may be rewritten as soon as put returns)."""
        buf = self._buffers.get(key)
        if buf is None or len(buf) != size:
            buf = self._buffers[key] = bytearray(size)
        return buf

    def _publish(self, job: _Job) -> None:
        for r in job.before:
            _send(r)
        bundle_keys: set[str] = set()
        if job.states:
            bundle_keys = self._publish_states(job)
        for cid in job.removed:
            have = self._pubs.pop(cid, None)
            if have is not None:
                _undeclare(have[0])
                self._buffers.pop(self.keys.state(cid), None)
        for bkey in [k for k in self._bundle_pubs if k not in bundle_keys]:  # the client has no bundled cloth left
            _undeclare(self._bundle_pubs.pop(bkey)[0])
            self._buffers.pop(bkey, None)
        for r in job.after:
            _send(r)
        if job.stats is not None and self._stats_pub is not None:
            self._stats_pub.put(job.stats)

    def _publish_states(self, job: _Job) -> set[str]:
        """Encode and put the states of one frame: each cloth on its own key, bundled cloths in
        one payload per bundle key. Returns the bundle keys of the frame."""
        t0 = time.perf_counter()
        enc = self._encoder
        assert job.positions is not None and job.offsets is not None
        enc.begin(job.tick, job.time_ns, job.positions, job.offsets)
        singles: list[tuple[int, zenoh.Publisher, int]] = []
        bundles: dict[str, list[int]] = {}
        unwatched = errors = 0
        for i, st in enumerate(job.states):
            if st.bundle is not None:
                bundles.setdefault(st.bundle, []).append(i)
                continue
            try:
                size = enc.state_size(i, st.encoding, st.normals is not None)
                pub = self._publisher(self._pubs, st.cloth, st.key, size)
                if pub.matching_status.matching:
                    singles.append((i, pub, size))
                else:  # nobody subscribed: skip the work
                    unwatched += 1
            except Exception as e:
                errors += 1
                log.warning("publishing cloth %s at tick %d failed: %s", st.cloth, job.tick, e)
        watched_bundles: list[tuple[str, list[int], zenoh.Publisher, int]] = []
        for bkey, idx in bundles.items():
            try:
                size = enc.bundle_size([(job.states[i].cloth, i, job.states[i].encoding,
                                         job.states[i].normals is not None) for i in idx])
                pub = self._publisher(self._bundle_pubs, bkey, bkey, size)
                if pub.matching_status.matching:
                    watched_bundles.append((bkey, idx, pub, size))
                else:
                    unwatched += len(idx)
            except Exception as e:
                errors += len(idx)
                log.warning("publishing bundle %s at tick %d failed: %s", bkey, job.tick, e)
        selected = [i for i, _, _ in singles] + [i for _, idx, _, _ in watched_bundles for i in idx]
        enc.prepare(selected, [st.encoding for st in job.states])
        enc_t = time.perf_counter() - t0
        pub_t = 0.0
        published = n_bundles = 0
        for i, pub, size in singles:
            st = job.states[i]
            try:
                a = time.perf_counter()
                buf = self._buffer(st.key, size)
                enc.write_state(buf, 0, i, st.encoding, st.flags, st.normals)
                b = time.perf_counter()
                pub.put(buf)
                enc_t += b - a
                pub_t += time.perf_counter() - b
                published += 1
            except Exception as e:
                errors += 1
                log.warning("publishing cloth %s at tick %d failed: %s", st.cloth, job.tick, e)
        for bkey, idx, pub, size in watched_bundles:
            try:
                a = time.perf_counter()
                buf = self._buffer(bkey, size)
                enc.write_bundle(buf, [(job.states[i].cloth, i, job.states[i].encoding, job.states[i].flags,
                                        job.states[i].normals) for i in idx])
                b = time.perf_counter()
                pub.put(buf)
                enc_t += b - a
                pub_t += time.perf_counter() - b
                published += len(idx)
                n_bundles += 1
            except Exception as e:
                errors += len(idx)
                log.warning("publishing bundle %s at tick %d failed: %s", bkey, job.tick, e)
        self._timers["encode"].add(enc_t)
        self._timers["publish"].add(pub_t)
        with self._lock:
            self._counters["published"] += published
            self._counters["unwatched"] += unwatched
            self._counters["publish_errors"] += errors
            self._counters["bundles"] += n_bundles
        return set(bundles)


# ---------------------------------------------------------------------------------------------
# Helpers


def _send(reply: _Reply) -> None:
    try:
        if reply.error:
            reply.query.reply_err(reply.payload)
        else:
            reply.query.reply(reply.query.key_expr, reply.payload)
    except Exception as e:  # the querier may be gone
        log.debug("reply failed: %s", e)
    finally:
        try:
            reply.query.drop()
        except Exception:
            pass


def _undeclare(obj: Any) -> None:
    try:
        obj.undeclare()
    except Exception as e:
        log.debug("undeclare failed: %s", e)


def _pack(colliders: tuple[P.Collider, ...] | None, rid: int) -> np.ndarray:
    out = []
    for c in colliders or ():
        if isinstance(c, P.Sphere):
            out.append(Sphere(c.center, c.radius))
        elif isinstance(c, P.Capsule):
            out.append(Capsule(c.p0, c.p1, c.radius))
        else:
            out.append(Plane(c.normal, c.offset))
    try:
        return pack_colliders(out)
    except ValueError as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"colliders: {e}", rid) from None


def _changes_params(req: P.ControlRequest, p: ClothParams) -> bool:
    """Whether a control changes the cloth's parameters (the common per-tick control, pins and
    colliders of a cloth whose colliders feature is on, changes none)."""
    return bool(
        req.material or req.features is not None or req.gravity is not None or req.wind is not None
        or req.iterations is not None or req.substeps is not None or req.chebyshev_rho is not None
        or req.quality is not None
        or (req.colliders and not p.features.colliders)
        or (req.state is not None and req.state.normals is not None and req.state.normals != p.features.normals)
    )


def _params_with(base: ClothParams, req: P.SubmitRequest | P.ControlRequest, material: Material,
                 features: set[str]) -> ClothParams:
    """``base`` with the solver fields a submit or control request gives (absent ones kept)."""
    return base.with_(
        material=material,
        features=Features.from_names(sorted(features)),
        gravity=req.gravity if req.gravity is not None else base.gravity,
        wind=req.wind if req.wind is not None else base.wind,
        iterations=req.iterations if req.iterations is not None else base.iterations,
        substeps=req.substeps if req.substeps is not None else base.substeps,
        chebyshev_rho=req.chebyshev_rho if req.chebyshev_rho is not None else base.chebyshev_rho,
    )


def _params_from_submit(req: P.SubmitRequest) -> ClothParams:
    feats = set(req.features)
    if req.colliders:
        feats.add("colliders")
    if req.state is not None and req.state.normals:
        feats.add("normals")
    try:
        params = _params_with(ClothParams(), req, Material(**req.material), feats)
        params.validate()
    except (TypeError, ValueError) as e:
        raise P.ProtocolError(P.ERR_INVALID_VALUE, f"cloth parameters: {e}", req.rid) from None
    return params
