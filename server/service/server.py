"""The Drape server: composition and lifecycle of the service's parts around one World.

``Server(config).start()`` ... ``.stop()``, or ``with Server(config) as s: ...``. Parts, each
owning one job (and one thread's state):

- registry (registry.py): cloths, clients, ownership, quotas, counters; lock-protected;
- handlers (handlers.py): the request handlers, on the request thread, fed by the bounded
  request queue (requestq.py) that Zenoh's queryable callbacks put their queries on;
- commands (commands.py): the bounded, per-cloth coalescing intake of the tick thread;
- cook (cook.py): the cook thread, fabrics (the one fabric cache) and kernel builds;
- ticker (tick/ticker.py): the tick thread, the only one touching the World, and its applier
  (applier.py): the queued commands applied to the World at the start of a tick;
- publisher (publish/publisher.py): the publisher thread, the replies and the World's bytes put;
- admission (admission.py) and adaptive quality (tick/adaptive.py): the tick-cost policies;
- replies (replies.py): answering queries, error replies counted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, TypeVar

import numpy as np
import zenoh

from drape.client import protocol as P
from drape.client.protocol.stats import STAT_COUNTERS
from drape.client.session import open_session, zenoh_config

from ..sim import make_world
from ..sim.fabric import Fabric, cook_grid
from ..sim.params import ClothParams, Features, Sphere, pack_colliders
from ..sim.roster import Roster
from ..sim.world import World
from .admission import Admission
from .commands import Call, Intake
from .config import ServerConfig
from .cook import CookWorker
from .handlers import Handlers
from .publish.keyframes import KeyframeQueries
from .publish.publisher import Publisher
from .registry import Registry
from .replies import Replies, undeclare
from .telemetry import PHASES, PhaseTimer
from .tick.adaptive import AdaptiveQuality
from .tick.ticker import Ticker

log = logging.getLogger(__name__)

T = TypeVar("T")


class Server:
    """``config`` defaults to ServerConfig(); keyword overrides replace its fields
    (``Server(tick_rate=30, listen=["tcp/127.0.0.1:7500"])``)."""

    def __init__(self, config: ServerConfig | None = None, *, warmup: bool = True, **overrides: Any) -> None:
        cfg = config or ServerConfig()
        self.config: ServerConfig = (replace(cfg, **overrides) if overrides else cfg).validate()
        self.keys = P.Keys(self.config.namespace)
        self.limits = self.config.limits()
        self.warmup = warmup
        self.device_name = "?"
        self._timers = {p: PhaseTimer() for p in PHASES}
        self._stopping = threading.Event()
        self._stopped = threading.Event()
        self._started_at = 0.0
        self.registry = Registry(self.config)
        self.replies = Replies(self.registry)
        self.intake = Intake(self.config.max_pending_requests)
        self.admission = Admission(self.config)
        self.quality = AdaptiveQuality(self.config)
        self.publisher = Publisher(self.config, self.keys, self.registry, self._timers)
        self.keyframes = KeyframeQueries(self.keys, self.registry, self.publisher)  # 1.5
        self.cook = CookWorker(
            self.config, self.registry, self.replies, self.intake, lambda: self.ticker.world, self._stopping.is_set
        )
        self.handlers = Handlers(
            self.config,
            self.keys,
            self.registry,
            self.replies,
            self.intake,
            self.cook.queue,
            self.admission,
            lambda: self.ticker.tick,
            self.info,
            self._stopping.is_set,
        )
        gate = self.handlers.gate  # requests start while the tick thread sleeps
        self.ticker = Ticker(
            self.config,
            self.registry,
            self.replies,
            self.intake,
            self.publisher.mailbox,
            self.cook.fabrics,
            self.admission,
            self.quality,
            self._timers,
            self._stats_bytes,
            lambda: self.publisher.last_cost_s,
            self.cook.request_prepare,
            gate.tick_sleeps if gate is not None else None,
        )
        self._session: zenoh.Session | None = None
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
        self.ticker.attach(make_world(cfg.solver, **kw))
        self.device_name = getattr(self.ticker.world, "device_name", cfg.solver)
        dev = getattr(self.ticker.world, "dev", None)
        self.quality.use_device(bool(dev is not None and dev.info.is_gpu))
        if self.warmup:
            self.warm_up()
        zc = zenoh_config(cfg.mode, cfg.listen, cfg.connect, cfg.multicast_scouting, cfg.zenoh_config)
        if cfg.zenoh_config is None:
            # States go out in bursts under DROP congestion control; Zenoh's default data queue (2
            # batches, drop after 1 ms) lost states of a briefly descheduled server on a busy 2-core
            # box. Sixteen batches (Zenoh's maximum) ride that out.
            zc.insert_json5("transport/link/tx/queue/size/data", "16")
        self._session = s = open_session(zc, f"{cfg.mode}, listen {cfg.listen}, connect {cfg.connect}")
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
            "drape server %s up: %s solver on %s, %.0f Hz, %s mode, listen %s connect %s, namespace %r, identity %s",
            sid,
            cfg.solver,
            self.device_name,
            cfg.tick_rate,
            cfg.mode,
            cfg.listen,
            cfg.connect,
            cfg.namespace,
            cfg.identity,
        )

    def warm_up(self) -> None:
        """Build and run, before the server serves, the kernels a cloth of the default feature
        set can need, so that the first such submission neither waits for a build nor stalls a
        tick (PoCL compiles a kernel again at its first launch):

        - the tick thread's warm-up: a small cloth's kernels, the frame encoder's programs;
        - with ``device_encode``, one frame encoded (the encoder's first launch cost 8-21 ticks
          on the tick thread with a cold PoCL cache);
        - the largest cloth this server admits (a strip of ``max_vertices_per_cloth`` vertices)
          when its kernels are others: too large for local memory, it takes the global-memory
          ones (a 256x256 cloth's first submit took 2.2 s on the CPU, 0.7 s once warmed)."""
        self.ticker.warm_up()
        w = self.ticker.world
        assert w is not None
        params = ClothParams()
        t = time.perf_counter()
        if self.config.device_encode:  # states encoded on the device: launch the encoder once
            h = w.add(cook_grid(2, 2, pinned=[0]), params)
            w.step(self.config.dt)
            lay = w.layout()
            f32 = [P.ENCODING_IDS["float32"]]
            roster = Roster((-1, -1), ["warm-up"], ["warm-up"], f32, lay.normals.copy(), np.array([0]), [])
            w.fetch_async(roster, 0).wait().release()
            w.remove(h)
            w.fetch()
        for names in self.config.warm_feature_sets():  # the feature sets a deployment declares
            t0 = time.perf_counter()
            self._step_once(w, cook_grid(32, 32, pinned=[0, 31]), ClothParams(features=Features.from_names(names)))
            log.debug("warm-up of features %s took %.3f s", "+".join(names), time.perf_counter() - t0)
        largest = cook_grid(1, self.config.max_vertices_per_cloth, pinned=[0])
        if w.ready(largest, params):
            return
        w.prepare(largest, params)
        self._step_once(w, largest, params)
        log.debug("warm-up of a %d-vertex cloth took %.3f s", largest.n_vertices, time.perf_counter() - t)

    def _step_once(self, w: World, fabric: Fabric, params: ClothParams) -> None:
        """Add a cloth, move its first pin, give it a collider when its features ask for them,
        step it once, read the frame back and remove it: every kernel it needs built and run."""
        h = w.add(fabric, params)
        w.set_pin_targets(h, np.array([0]), np.zeros((1, 3)))
        if params.features.colliders:
            w.set_colliders(h, pack_colliders([Sphere((0.5, -0.5, 0.5), 0.2)]))
        w.step(self.config.dt)
        w.fetch()
        w.remove(h)
        w.fetch()

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
