"""The ``drape chaos`` scenarios: each starts its own ``drape serve`` (and good clients), measures a
baseline, applies one fault or abuse, measures again and returns the figures and its verdict
against the targets of issue 11 (see :mod:`drape.server.tools.chaos`).

Scenarios: ``fuzz`` (in :mod:`.chaos_fuzz`), ``flood-ids``, ``big-submit``, ``big-cook``,
``tiny-mass``, ``new-features`` (``kill`` and ``pause``: :mod:`.chaos_failover`, which builds on
this module's Context, Stage and judge; the command's table of all: :mod:`.chaos`). Every one is
bounded in messages and seconds and talks only to 127.0.0.1.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from drape.client import protocol as P

from ..service.config import ServerConfig
from . import chaos_fuzz
from .chaos_clients import GoodClient
from .chaos_harness import GAP_LIMIT_MS, ChaosServer, reply_outcome, zenoh_session
from .chaos_router import AuthRouter
from .chaos_window import Window

log = logging.getLogger(__name__)

TICK_HZ = 60.0
RATE_FLOOR = 0.95  # a good client's state rate must stay within 5 % of the tick rate
RSS_SLACK = 0.10  # RSS back within 10 % of where it was
FAILOVER_GAP_S = 1.0  # kill and pause: every cloth back within this
RETRY_LATER = ("busy", "overloaded")  # error codes that ask the client to try again later


@dataclass
class Context:
    """What every scenario gets from the command line."""

    out: Path
    seconds: float = 5.0  # measured window after the abuse, where a scenario has one
    baseline_s: float = 2.0
    fuzz_count: int = 2000
    flood_ids: int = 2000
    pause_s: float = 20.0
    max_message_bytes: int = 8 << 20
    rss_limit_mb: float = 4096.0
    seed: int = 1
    grace_period: float = 5.0
    program_idle_s: float = ServerConfig.program_idle_s  # the servers' (fuzz: RSS measured after it)
    serve_args: tuple[str, ...] = ()  # extra `drape serve` arguments for every server
    kill_servers: int = 2  # kill: servers (2-4) the failover clients' cloths are placed on
    kills: int = 1  # kill: servers killed one after the other, each restarted after kill_gap s
    kill_gap: float = 1.0
    auth: str = ""  # "tls" or "tcp": every Stage behind an authenticated ACL router (chaos_router); "": loopback peers


#: The abusing clients' ids of the scenarios that use a Stage (users of the router with ``--auth``).
AUTH_CLIENTS = ("heavy", "big", "filler", "newcomer", "features", "burst", "mesh", "cook", "tiny")


class Stage:
    """A server plus one measured good client: ``with Stage(ctx, "name") as st``. With
    ``ctx.auth`` both sit behind an authenticated ACL router (:class:`~.chaos_router.AuthRouter`),
    the server with ``--identity keys``, and the scenario's requests go on each client's own keys
    as that client's user."""

    def __init__(
        self,
        ctx: Context,
        name: str,
        server_args: tuple[str, ...] = (),
        good_cloths: int = 1,
        env: dict[str, str | None] | None = None,
        metrics: bool = False,
    ) -> None:
        self.ctx = ctx
        self.router: AuthRouter | None = None
        if ctx.auth:
            self.router = AuthRouter(
                ctx.out, [ChaosServer.id_of(name)], [GoodClient.id_of("good", name), *AUTH_CLIENTS], ctx.auth
            )
        self.server = ChaosServer(
            ctx.out,
            name,
            (
                "--grace-period",
                str(ctx.grace_period),
                "--max-message-bytes",
                str(ctx.max_message_bytes),
                "--program-idle-s",
                str(ctx.program_idle_s),
                *ctx.serve_args,
                *server_args,
            ),
            rss_limit_mb=ctx.rss_limit_mb,
            env=env,
            router=self.router,
            metrics=metrics,
        )
        self.good: GoodClient | None = None
        self.name = name
        self.good_cloths = good_cloths
        self.session: zenoh.Session | None = None
        self.sessions: dict[str, zenoh.Session] = {}  # with a router: one per client user
        self.owners: dict[str, str] = {}  # cloth id -> the client that submitted it
        self.tokens: list[Any] = []  # liveliness tokens held for clients (declare_alive)
        self.keys = P.Keys()

    def __enter__(self) -> Stage:
        try:
            self.server.wait_ready()
            sdk = None if self.router is None else self.router.sdk(GoodClient.id_of("good", self.name))
            self.good = GoodClient(self.server.endpoint, self.server.server_id, self.name, self.good_cloths, sdk=sdk)
            self.good.wait_ready()
            if self.router is None:
                self.session = zenoh_session(self.server.endpoint)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        if self.good is not None:
            self.good.close()
        for t in self.tokens:
            t.undeclare()
        for s in [self.session, *self.sessions.values()]:
            if s is not None:
                s.close()
        self.server.stop()
        if self.router is not None:
            self.router.close()

    def _route(self, queryable: str, client: str | None) -> tuple[zenoh.Session, str]:
        """The session and key of a request of ``client``: its own user's session and
        client-scoped key behind a router, the shared session and server-wide key otherwise."""
        if self.router is None or client is None or queryable == "info":
            assert self.session is not None or self.router is not None
            if self.session is None:
                self.session = self.router.session(self.router.watcher)  # type: ignore[union-attr]
            return self.session, getattr(self.keys, queryable)(self.server.server_id)
        if client not in self.sessions:
            self.sessions[client] = self.router.session(client)
        return self.sessions[client], self.keys.client_request(queryable, self.server.server_id, client)

    def baseline(self) -> dict[str, Any]:
        """The good client and the server, undisturbed, for ``baseline_s`` (the machine's own noise)."""
        w = Window.open(self.server)
        time.sleep(self.ctx.baseline_s)
        b = w.close([self.good] if self.good else [])
        return {
            k: b[k]
            for k in (
                "good_rate_hz",
                "missed_ticks",
                "missed_ticks_own",
                "host_other_cores",
                "good_lost",
                "good_lost_own",
                "good_worst_gap_ms",
                "good_worst_gap_own_ms",
                "server_tick_hz",
                "rss_after_mb",
            )
            if k in b
        }

    def declare_alive(self, client: str) -> None:
        """Hold ``client``'s liveliness token (as its SDK would), so that its cloths are not reclaimed
        after the grace period while it takes longer than that to be served."""
        session, _ = self._route("submit", client)
        self.tokens.append(session.liveliness().declare_token(self.keys.alive_client(client)))

    def request(
        self, queryable: str, payload: bytes, timeout: float = 60.0, client: str | None = None
    ) -> tuple[str, dict[str, Any]]:
        """One query of ``client``; (outcome, reply map) with outcome ``ok``, an error code, or ``no_reply``."""
        session, key = self._route(queryable, client)
        for reply in session.get(key, payload=payload, timeout=timeout):
            outcome = reply_outcome(reply)
            data = reply.ok.payload.to_bytes() if reply.ok is not None else b""
            return outcome, (msgpack.unpackb(data, raw=False) if data else {})
        return "no_reply", {}

    def submit(self, req: P.SubmitRequest, timeout: float = 60.0) -> tuple[str, dict[str, Any]]:
        outcome, reply = self.request("submit", P.encode_submit(req), timeout, req.client)
        if "cloth" in reply:
            self.owners[reply["cloth"]] = req.client
        return outcome, reply

    def submit_retrying(self, req: P.SubmitRequest, attempts: int = 10) -> str:
        """A submit, retried (1 s apart, at most ``attempts`` times) while the server answers with a
        code that means "later" (busy, overloaded); the last outcome."""
        outcome = "no_reply"
        for _ in range(attempts):
            outcome, _ = self.submit(req)
            if outcome not in RETRY_LATER:
                break
            time.sleep(1.0)
        return outcome

    def submit_async(self, req: P.SubmitRequest, timeout: float = 120.0) -> dict[str, Any]:
        """Send a submit without waiting; the returned dict gets ``outcome``/``reply`` when it comes."""
        session, key = self._route("submit", req.client)
        box: dict[str, Any] = {"done": threading.Event()}

        def on_reply(reply: zenoh.Reply) -> None:
            box["outcome"] = reply_outcome(reply)
            if reply.ok is not None:
                box["reply"] = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
                self.owners[box["reply"].get("cloth", "")] = req.client

        session.get(
            key,
            zenoh.handlers.Callback(on_reply, box["done"].set),
            payload=P.encode_submit(req),
            timeout=timeout,
        )
        return box

    def remove(self, reply: dict[str, Any]) -> str:
        if "cloth" not in reply:
            return "nothing to remove"
        payload = P.encode_remove(P.RemoveRequest(reply["cloth"], reply["token"]))
        return self.request("remove", payload, client=self.owners.get(reply["cloth"]))[0]


def grid_request(client: str, n: int = 16, **kw: Any) -> P.SubmitRequest:
    return P.SubmitRequest(client=client, grid=P.GridSpec(n, n), pinned=np.array([0, n - 1], np.uint32), **kw)


def judge(m: dict[str, Any], *, good: bool = True, rss: bool = True) -> list[str]:
    """Which targets a window missed: good clients at the tick rate, 0 missed ticks, 0 states lost
    and no gap over ``GAP_LIMIT_MS`` between good states (the three counted where the machine's other work stayed
    under ``MACHINE_BUSY`` cores: :meth:`.chaos_window.Window.attribute`; the raw counts are
    reported beside), 0 tracebacks, the server alive and publishing, RSS back within 10 %."""
    fails = []
    if not m.get("server_alive", True):
        fails.append("server died" + (" (killed at the RSS cap)" if m.get("killed_for_rss") else ""))
    if m.get("stats_stalled"):
        fails.append("server stopped publishing stats")
    if good:
        if m.get("good_rate_hz", 0.0) < RATE_FLOOR * TICK_HZ:
            fails.append(f"good client at {m.get('good_rate_hz')} Hz < {RATE_FLOOR * TICK_HZ:.0f}")
        own = m.get("missed_ticks_own", m.get("missed_ticks", 0))
        if own:
            fails.append(f"{own} missed ticks (of {m.get('missed_ticks')}) in stats periods without other load")
        lost = m.get("good_lost_own", m.get("good_lost", 0))
        if lost:
            fails.append(f"{lost} good states lost (of {m.get('good_lost')}) without other load")
        if m.get("good_worst_gap_own_ms", 0.0) > GAP_LIMIT_MS:
            fails.append(f"a gap of {m['good_worst_gap_own_ms']} ms between good states without other load")
    if m.get("tracebacks", 0):
        fails.append(f"{m['tracebacks']} tracebacks in the server log")
    if rss and m.get("rss_after_mb", 0) > (1 + RSS_SLACK) * m.get("rss_before_mb", float("inf")):
        fails.append(f"RSS {m['rss_before_mb']} -> {m['rss_after_mb']} MB (> +{RSS_SLACK:.0%})")
    return fails


# ---------------------------------------------------------------------------------------------
# Scenarios


def fuzz(ctx: Context, count: int | None = None) -> dict[str, Any]:
    """Malformed messages on every queryable, then a valid submit must still be served."""
    count = ctx.fuzz_count if count is None else count
    with Stage(ctx, "fuzz") as st:
        base = st.baseline()
        outcome, reply = st.submit(grid_request("fuzzer", 8))
        cloth, token = reply.get("cloth", "0123456789abcdef"), reply.get("token", "0" * 32)
        w = Window.open(st.server)
        msgs = chaos_fuzz.messages(count, ctx.seed, "fuzzer", cloth, token, ctx.max_message_bytes)
        assert st.session is not None
        c = chaos_fuzz.send_all(st.session, st.keys, st.server.server_id, msgs)
        # RSS after the fuzz is gone: its cloths reclaimed (grace period), then their programs
        # released (program_idle_s) and the heap trimmed (the server's cook thread, once a second)
        m = w.close([st.good] if st.good else [], settle_s=ctx.grace_period + ctx.program_idle_s + 3.0)
        after = st.submit_retrying(grid_request("after-fuzz", 8))
    m.update(
        baseline=base,
        sent=c.sent,
        outcomes=dict(c.outcomes),
        no_reply=c.no_reply,
        internal=c.outcomes.get("internal", 0),
        internal_kinds=dict(c.internal_kinds.most_common(10)),
        by_kind=dict(c.by_kind),
        valid_submit_after=after,
        first_submit=outcome,
    )
    fails = judge(m)
    if m["internal"]:
        fails.append(f"{m['internal']} 'internal' error replies")
    if c.outcomes.get("unparseable"):
        fails.append(f"{c.outcomes['unparseable']} error replies that are not Drape error maps")
    if c.no_reply:
        fails.append(f"{c.no_reply} messages got no reply")
    if after != "ok":
        fails.append(f"a valid submit afterwards got {after}")
    return {**m, "fails": fails}


def flood_ids(ctx: Context) -> dict[str, Any]:
    """Many self-declared client ids, one small cloth each (no liveliness token: reclaimed after grace)."""
    with Stage(ctx, "flood-ids") as st:
        base = st.baseline()
        w = Window.open(st.server)
        outcomes: dict[str, int] = {}
        slots = threading.BoundedSemaphore(16)
        lock = threading.Lock()
        assert st.session is not None
        for i in range(ctx.flood_ids):
            slots.acquire(timeout=120)

            def on_reply(reply: zenoh.Reply) -> None:
                with lock:
                    o = reply_outcome(reply)
                    outcomes[o] = outcomes.get(o, 0) + 1

            st.session.get(
                st.keys.submit(st.server.server_id),
                zenoh.handlers.Callback(on_reply, slots.release),
                payload=P.encode_submit(grid_request(f"flood-{i}", 8)),
                timeout=60,
            )
        for _ in range(16):
            slots.acquire(timeout=120)
        peak = st.server.stats.next(10) or {}
        newcomer = st.submit_retrying(grid_request("newcomer", 8))
        rss_peak = st.server.rss_mb()
        m = w.close([st.good] if st.good else [], settle_s=ctx.grace_period + 3.0)
    m.update(
        baseline=base,
        submitted=ctx.flood_ids,
        outcomes=outcomes,
        cloths_at_peak=peak.get("cloths"),
        rss_peak_mb=round(rss_peak, 1),
        newcomer_submit=newcomer,
    )
    fails = judge(m)
    if newcomer != "ok":
        fails.append(f"a new genuine client's submit got {newcomer} during the flood")
    return {**m, "fails": fails}


def _one_heavy(ctx: Context, name: str, req: P.SubmitRequest, wait_s: float) -> dict[str, Any]:
    """Submit one heavy cloth without waiting, measure ``wait_s`` seconds, remove it, settle."""
    with Stage(ctx, name) as st:
        base = st.baseline()
        w = Window.open(st.server)
        t0 = time.monotonic()
        box = st.submit_async(req)
        box["done"].wait(wait_s)
        replied_s = time.monotonic() - t0 if box["done"].is_set() else None
        time.sleep(max(0.0, wait_s - (time.monotonic() - t0)))
        m = w.close([st.good] if st.good else [])
        removed = st.remove(box.get("reply", {})) if st.server.alive() else "server gone"
        time.sleep(2.0)
        m["rss_after_mb"] = round(st.server.rss_mb(), 1)
    m.update(
        baseline=base,
        submit_outcome=box.get("outcome", "no reply yet"),
        submit_reply_s=None if replied_s is None else round(replied_s, 2),
        removed=removed,
    )
    return {**m, "fails": judge(m)}


def big_submit(ctx: Context) -> dict[str, Any]:
    """One valid 256x256 cloth at 100 iterations x 100 substeps."""
    req = grid_request("heavy", 256, iterations=100, substeps=100)
    return _one_heavy(ctx, "big-submit", req, max(ctx.seconds, 10.0))


def big_cook(ctx: Context) -> dict[str, Any]:
    """A 256x256 cloth with 32,768 pinned vertices (every other one): the cook's cost."""
    req = P.SubmitRequest(
        client="cook", grid=P.GridSpec(256, 256), pinned=np.arange(0, 65536, 2, dtype=np.uint32), features=("tethers",)
    )
    return _one_heavy(ctx, "big-cook", req, max(ctx.seconds, 20.0))


def tiny_mass(ctx: Context, cloths: int = 64) -> dict[str, Any]:
    """64 cloths of mass 5e-324 (valid in protocol 1.1: > 0), which went non-finite every tick."""
    with Stage(ctx, "tiny-mass") as st:
        base = st.baseline()
        replies = [st.submit(grid_request("tiny", 16, material={"mass": 5e-324})) for _ in range(cloths)]
        w = Window.open(st.server)
        time.sleep(ctx.seconds)
        m = w.close([st.good] if st.good else [])
        for _, r in replies:
            st.remove(r)
        time.sleep(1.0)
        m["rss_after_mb"] = round(st.server.rss_mb(), 1)
    m.update(
        baseline=base,
        accepted=sum(o == "ok" for o, _ in replies),
        submit_outcomes=dict(Counter(o for o, _ in replies)),
        nan_resets_per_s=round(m["nan_resets"] / max(m["seconds"], 1e-9), 1),
        log_warnings_per_s=round(m["log_warnings"] / max(m["seconds"], 1e-9), 1),
    )
    fails = judge(m)
    if m["log_warnings_per_s"] > 1.0:
        fails.append(f"{m['log_warnings_per_s']} warning lines per second in the server log")
    return {**m, "fails": fails}


def new_features(ctx: Context) -> dict[str, Any]:
    """The first cloth of each feature combination (all 32 subsets), one after the other."""
    combos = [c for n in range(len(P.FEATURE_NAMES) + 1) for c in itertools.combinations(P.FEATURE_NAMES, n)]
    with Stage(ctx, "new-features") as st:
        base = st.baseline()
        w = Window.open(st.server)
        outcomes = []
        for combo in combos:
            o, r = st.submit(grid_request("features", 16, features=combo))
            outcomes.append(o)
            st.remove(r)
        time.sleep(0.5)
        m = w.close([st.good] if st.good else [])
    m.update(
        baseline=base, combinations=len(combos), accepted=outcomes.count("ok"), submit_outcomes=dict(Counter(outcomes))
    )
    return {**m, "fails": judge(m, rss=False)}  # gaps: judge's GAP_LIMIT_MS (issue 26), not 2 ticks
