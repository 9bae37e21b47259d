"""The Drape server: composition and lifecycle of the service's parts around one World.

``Server(config).start()`` ... ``.stop()``, or ``with Server(config) as s: ...``. ``__init__``
builds every part once, each after the parts it takes (the World itself is made at ``start``).
Parts, each owning one job (and one thread's state); the folders are the threads:

- shared, at the top: registry (registry.py: cloths, clients, ownership, quotas, counters;
  lock-protected), commands (commands.py: the bounded, per-cloth coalescing intake of the tick
  thread), replies (replies.py: answering queries, error replies counted), worldparams
  (worldparams.py: requests into what the World takes), config (config.py);
- the request thread (requests/): the handlers, fed by the bounded request queue that Zenoh's
  queryable callbacks put their queries on (requestq.py, with the gate that keeps requests off
  the tick), moves blocks checked on arrival, admission (the cost model submits are refused by);
- the cook thread (cook/): fabrics (the one fabric cache) and kernel builds, the warm-up of a
  World, kernel builds in a child process;
- the tick thread (tick/: the ticker with its one frame path, the queued commands and moves
  blocks applied to the World at the start of a tick, adaptive quality), the only one touching
  the World;
- the publisher thread (publish/: the publisher puts the World's wire-ready bytes, with the
  replies before and after; keyframe queries);
- the process (process/): ``drape serve``, its workers, metrics, health, logs, memory, timers.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, TypeVar

import zenoh

from drape.client import protocol as P
from drape.client.protocol.stats import STAT_COUNTERS
from drape.client.session import listening, open_session, zenoh_config

from ..sim import make_world
from ..sim.world import World
from .commands import Call, Intake
from .config import ServerConfig
from .cook.fabrics import FabricStore
from .cook.warmup import warm_up
from .cook.worker import CookWorker
from .process.telemetry import PHASES, PhaseTimer
from .publish.keyframes import KeyframeQueries
from .publish.publisher import Publisher
from .registry import Registry
from .replies import Replies, undeclare
from .requests.admission import Admission
from .requests.handlers import Handlers
from .requests.requestq import TickGate
from .tick.adaptive import AdaptiveQuality
from .tick.ticker import Ticker

log = logging.getLogger(__name__)

T = TypeVar("T")


class Server:
    """``config`` defaults to ServerConfig(); keyword overrides replace its fields
    (``Server(tick_rate=30, listen=["tcp/127.0.0.1:7500"])``)."""

    def __init__(self, config: ServerConfig | None = None, *, warmup: bool = True, **overrides: Any) -> None:
        base = config or ServerConfig()
        self.config: ServerConfig = (replace(base, **overrides) if overrides else base).validate()
        self.keys = P.Keys(self.config.namespace)
        self.limits = self.config.limits()
        self.warmup = warmup
        self.device_name = "?"
        self._timers = {p: PhaseTimer() for p in PHASES}
        self._stopping = threading.Event()
        self._stopped = threading.Event()
        self._started_at = 0.0
        # the parts, each built once after those it takes (the World comes at start())
        cfg = self.config
        self.registry = Registry(cfg)
        self.replies = Replies(self.registry)
        self.intake = Intake(cfg.max_pending_requests)
        self.admission = Admission(cfg)
        self.quality = AdaptiveQuality(cfg)
        self.fabrics = FabricStore()
        self.gate = TickGate(cfg.dt) if cfg.request_yield else None  # requests while the tick thread sleeps
        self.publisher = Publisher(cfg, self.keys, self.registry, self._timers)
        self.keyframes = KeyframeQueries(self.keys, self.registry, self.publisher)  # 1.5
        self.cook = CookWorker(
            cfg,
            self.registry,
            self.replies,
            self.intake,
            self.fabrics,
            lambda: self.ticker.world,
            self._stopping.is_set,
        )
        self.handlers = Handlers(
            cfg,
            self.keys,
            self.registry,
            self.replies,
            self.intake,
            self.cook.queue,
            self.admission,
            self.gate,
            lambda: self.ticker.tick,
            self.info,
            self._stopping.is_set,
        )
        self.ticker = Ticker(
            cfg,
            self.registry,
            self.replies,
            self.intake,
            self.publisher.mailbox,
            self.fabrics,
            self.admission,
            self.quality,
            self._timers,
            self._stats_bytes,
            lambda: self.publisher.last_cost_s,
            self.cook.request_prepare,
            self.gate.tick_sleeps if self.gate is not None else None,
        )
        self._session: zenoh.Session | None = None
        self.listening: list[str] = []  # the endpoints the session listens on (client mode: none)
        self._declared: list[Any] = []
        self._token: Any = None
        self._threads: list[threading.Thread] = []

    # --- lifecycle ---------------------------------------------------------------------------
    def start(self) -> Server:
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
        kw = {} if cfg.solver == "reference" else {"device": cfg.device, "device_encode": cfg.device_encode}
        world = make_world(cfg.solver, **kw)
        self.ticker.attach(world)
        self.device_name = getattr(world, "device_name", cfg.solver)
        dev = getattr(world, "dev", None)
        self.quality.use_device(bool(dev is not None and dev.info.is_gpu))
        self.admission.use_device(bool(dev is not None and dev.info.is_gpu))
        if self.warmup:  # before serving: the first cloths build nothing (cook/warmup.py)
            warm_up(world, cfg)
        # a --zenoh-config file's listen endpoints are honoured: --listen's default only where it sets none
        listen = [] if cfg.zenoh_config and cfg.listen == [P.DEFAULT_ENDPOINT] else cfg.listen
        zc = zenoh_config(cfg.mode, listen, cfg.connect, cfg.multicast_scouting, cfg.zenoh_config, [P.DEFAULT_ENDPOINT])
        self.listening = listening(zc, cfg.mode)
        if cfg.zenoh_config is None and not cfg.send_buffer:
            # States go out in bursts under DROP congestion control; Zenoh's default data queue (2
            # batches, drop after 1 ms) lost states of a briefly descheduled server on a busy 2-core
            # box. Sixteen batches (Zenoh's maximum) ride that out.
            zc.insert_json5("transport/link/tx/queue/size/data", "16")
        if cfg.send_buffer:  # fresh or nothing on slow links (docs/rates.md): Zenoh's 2 batches, a small socket
            zc.insert_json5("transport/link/tcp/so_sndbuf", str(int(cfg.send_buffer)))
        self._session = s = open_session(zc, f"{cfg.mode}, listen {self.listening}, connect {cfg.connect}")
        self.publisher.attach(s)
        sid = cfg.server_id
        self._started_at = time.monotonic()
        self._threads = [
            threading.Thread(target=self.publisher.run, name=f"drape-publish-{sid}", daemon=True),
            threading.Thread(target=self.cook.run, name=f"drape-cook-{sid}", daemon=True),
            threading.Thread(target=self.ticker.run, name=f"drape-tick-{sid}", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self.handlers.request_queue.start()
        lv = s.liveliness()
        self._declared.append(
            lv.declare_subscriber(self.keys.all_clients_alive, self.handlers.on_client_liveliness, history=True)
        )
        for key, cb in self.handlers.endpoints() + self.keyframes.endpoints():
            self._declared.append(s.declare_queryable(key, cb))
        self._token = lv.declare_token(self.keys.alive_server(sid))
        log.info(
            "drape server %s up: %s solver on %s, %.0f Hz, %s mode, %s, connect %s, namespace %r, identity %s",
            sid,
            cfg.solver,
            self.device_name,
            cfg.tick_rate,
            cfg.mode,
            f"listening on {self.listening}" if self.listening else "listening on nothing (client mode)",
            cfg.connect,
            cfg.namespace,
            cfg.identity,
        )

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
                undeclare(d)
            self._declared.clear()
            self.handlers.request_queue.close()  # what still waits is answered busy
            self.cook.queue.put(None)
            self.ticker.stop_event.set()
            deadline = time.monotonic() + timeout
            others = [t for t in self._threads if not t.name.startswith("drape-publish")]
            for t in others:
                t.join(max(0.0, deadline - time.monotonic()))
            self.ticker.applier.shutdown_commands()  # anything the cook thread queued after the tick thread ended
            self.publisher.mailbox.close()
            for t in self._threads:
                if t.name.startswith("drape-publish"):
                    t.join(max(0.0, deadline - time.monotonic()))
            self.publisher.close()
            if self.ticker.world is not None:
                self.ticker.world.close()
            if self._session is not None:
                self._session.close()
                self._session = None
        finally:
            self._stopped.set()
            log.info("drape server %s stopped after %d ticks", self.config.server_id, self.ticker.tick)

    def __enter__(self) -> Server:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # --- state -------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self._session is not None and not self._stopping.is_set()

    @property
    def tick(self) -> int:
        return self.ticker.tick

    @property
    def failure(self) -> BaseException | None:
        return self.ticker.failure

    @failure.setter
    def failure(self, e: BaseException | None) -> None:
        self.ticker.failure = e

    @property
    def server_id(self) -> str:
        return self.config.server_id

    @property
    def phase_timers(self) -> Mapping[str, PhaseTimer]:
        return self._timers

    def wait_stopped(self, timeout: float | None = None) -> bool:
        return self._stopped.wait(timeout)

    def call(self, fn: Callable[[World], T], timeout: float = 10.0) -> T:
        """Run ``fn(world)`` on the tick thread between two ticks and return its result (for
        tools and tests; the World must only ever be touched there)."""
        cmd = Call(fn)
        self.intake.put_call(cmd, timeout)
        if not cmd.done.wait(timeout):
            raise TimeoutError("the tick thread did not run the call in time")
        if cmd.error is not None:
            raise cmd.error
        return cmd.result  # type: ignore[return-value]

    def world_handle(self, cloth_id: str) -> int | None:
        """The World handle of a cloth (for ``call``)."""
        rec = self.registry.get(cloth_id)
        return None if rec is None else rec.handle

    # --- stats -------------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Cumulative counters and the phase timings of the current stats window."""
        return self._stats(reset_window=False)

    def _stats_bytes(self) -> bytes:
        return P.encode_stats(self._stats(reset_window=True))

    def _stats(self, reset_window: bool) -> dict[str, Any]:
        reg = self.registry
        with reg.lock:
            c = dict(reg.counters)
            out: dict[str, Any] = {
                "server": self.config.server_id,
                "tick": self.ticker.tick,
                "time_ns": time.time_ns(),
                "uptime_s": time.monotonic() - self._started_at if self._started_at else 0.0,
                "tick_rate": self.config.tick_rate,
                "cloths": len(reg.cloths),
                "clients": len(reg.by_client),
                "alive_clients": len(reg.alive),
                "vertices": reg.vertices,
                "requests": dict(reg.requests),
                "errors": dict(reg.errors),
            }
            recs = list(reg.cloths.values())
        for k in STAT_COUNTERS:
            out[k] = c.get(k, 0)
        out["phases"] = {p: t.snapshot(reset_window) for p, t in self._timers.items()}
        out["quality"] = self.quality.stats(recs)
        return out

    def info(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "server": cfg.server_id,
            "version": P.VERSION_STRING,
            "solver": cfg.solver,
            "device": self.device_name,
            "tick_rate": cfg.tick_rate,
            "tick": self.ticker.tick,
            **self.registry.counts(),
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
