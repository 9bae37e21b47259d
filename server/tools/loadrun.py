"""The measurement core of ``drape loadtest``: one load over one or several servers, measured over
a window of server ticks so that start-up never counts (see :mod:`.loadtest` for the command).

K client processes (:mod:`.loadclient`) share a load of N cloths. With one server every client
talks to it. With several (``Target`` per server, all on the clients' Zenoh network) the clients
start together but place their cloths one after another: each puts its cloths on the server the
SDK's placement ranks first by the servers' published load (PROTOCOL.md 11.3), once the stats it
sees count the cloths of the clients before it.

The **measured window** opens, once every client receives states for all its admitted cloths, at
the next stats publication of each server and closes at the first one ``spec.seconds`` later.
Each client counts its states in the ticks of its own server's window; the server's RSS is
sampled at the window's start (after admission and warm-up) as well as before the load, and the
host's load average at both ends of the window. The report (a
:class:`~.loadreport.Report`) adds every client up; with several servers, each server's cloths,
vertices, achieved rate and missed ticks are in ``Report.servers`` and the spread of cloths over
them (max / mean - 1) in ``Report.spread``; the achieved rate is the slowest server's.
"""

from __future__ import annotations

import logging
import math
import multiprocessing as mp
import os
import platform
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drape.client.placement import spread

from .loadclient import OVERLOADED_RETRIES, ClientResult, ClientSpec, Workload, client_main
from .loadlink import LinkSpec, links_report
from .loadreport import (
    Report,
    achieved_rate,
    counter_delta,
    decode_summary,
    latency_summary,
    phase_means,
    rate_counts,
    server_window,
    timeline,
)
from .procs import ServerProcess, format_cpus, progress

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class LoadSpec(Workload):
    """A load: ``cloths`` over ``clients`` processes, measured over ``seconds``, with the
    cloth settings of Workload."""

    clients: int = 4
    cloths: int = 64  # total cloths wanted (each client offers its share x ``offered``)
    seconds: float = 5.0  # the measured window, at least
    offered: float = 1.0  # offer this many times ``cloths``
    link: LinkSpec = LinkSpec()  # issue 21: some clients behind a home link (loadlink.py)

    def client_specs(self) -> list[ClientSpec]:
        """Each client's share of the offered cloths (the first ones take the remainder)."""
        total = int(math.ceil(self.cloths * self.offered))
        base, extra = divmod(total, self.clients)
        retries = OVERLOADED_RETRIES if self.offered <= 1.0 else 0
        return [
            ClientSpec(
                index=i,
                offered=base + (i < extra),
                retries=retries,
                client_rate=self.link.client_rate if shaped else "1",
                **{**self.workload(), "decode_sample": self.decode_one_in(self.cloths)},
            )
            for i, shaped in zip(range(self.clients), self.link.shaped(self.clients), strict=True)
        ]


class StatsWatch:
    """The server's stats publications, kept in arrival order with their local arrival time."""

    def __init__(self, endpoint: str, server_id: str | None) -> None:
        from drape.client import DrapeClient

        self.client = DrapeClient(endpoint, server_id=server_id, timeout=60.0)
        self.samples: list[tuple[float, dict[str, Any]]] = []
        self._cond = threading.Condition()
        self._cancel = self.client.on_stats(self._on)

    def _on(self, stats: dict[str, Any]) -> None:
        with self._cond:
            self.samples.append((time.monotonic(), stats))
            self._cond.notify_all()

    def next_after(
        self, index: int, timeout: float, check: Callable[[], None] | None = None
    ) -> tuple[int, dict[str, Any]]:
        """The first publication with position >= ``index`` (waiting up to ``timeout`` s);
        ``check()`` is called every 0.2 s while it waits (to raise when the server is gone)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self.samples) <= index:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise RuntimeError(f"no stats publication from the server in {timeout:.0f} s")
                self._cond.wait(min(left, 0.2))
                if check is not None and len(self.samples) <= index:
                    check()
            return index, self.samples[index][1]

    def count(self) -> int:
        with self._cond:
            return len(self.samples)

    def close(self) -> None:
        self._cancel()
        self.client.close()


def _load_average() -> float | None:
    """The host's 1-minute load average (None where the OS has none): the machine's load is
    part of every figure on a shared host."""
    try:
        return round(os.getloadavg()[0], 2)
    except OSError:
        return None


def _wait(cond: Any, what: str, deadline: float, procs: list[Any], targets: Sequence[Target] = ()) -> None:
    """Until ``cond()``; raises when the deadline passes, when a started server exited
    (:class:`~.procs.ServerExited`, first: a client dies of its server) or when a client did."""
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        _check_servers(targets, what)
        dead = [p.name for p in procs if not p.is_alive()]
        if dead:
            raise RuntimeError(f"{', '.join(dead)} exited while waiting for {what}")
        time.sleep(0.05)


@dataclass
class Target:
    """One server of a load: its id (None: the one the clients see), its stats and its process
    (None when the load test did not start it)."""

    server_id: str | None
    stats: StatsWatch
    proc: ServerProcess | None = None


def _check_servers(targets: Sequence[Target], before: str) -> None:
    """Raise :class:`~.procs.ServerExited` when a server the load test started has exited."""
    for t in targets:
        if t.proc is not None:
            t.proc.check(before)


def _result(results: Any, targets: Sequence[Target], deadline: float) -> Any:
    """The next client result from the ``results`` queue, checking the servers while it waits."""
    while True:
        try:
            return results.get(timeout=0.2)
        except queue.Empty:
            if time.monotonic() > deadline:
                raise RuntimeError("timed out waiting for the clients' results") from None
            _check_servers(targets, "the clients reported their results")


def run_load(
    spec: LoadSpec,
    endpoint: str | list[str],
    server_id: str | None,
    server: ServerProcess | None,
    stats: StatsWatch,
    quiet: bool = False,
) -> tuple[Report, list[ClientResult], list[tuple[float, dict]]]:
    """Run one load on one server (see the module docstring)."""
    return run_fleet_load(spec, endpoint, [Target(server_id, stats, server)], quiet)


def run_fleet_load(
    spec: LoadSpec,
    endpoint: str | list[str],
    targets: list[Target],
    quiet: bool = False,
    client_cpus: frozenset[int] | None = None,
) -> tuple[Report, list[ClientResult], list[tuple[float, dict]]]:
    """Run one load over ``targets`` (one or several servers); ``endpoint``: what the clients
    connect to (the servers' endpoints, or a router); ``client_cpus``: the CPUs the client
    processes run on (None: any)."""
    ctx = mp.get_context("spawn")
    several = len(targets) > 1
    spec = replace(spec, servers=len(targets))
    cspecs = spec.client_specs()
    shared = [
        {
            "connected": ctx.Event(),
            "turn": ctx.Event(),
            "expect": ctx.Value("q", 0, lock=False),
            "ready": ctx.Event(),
            "go": ctx.Event(),
            "stop": ctx.Event(),
            "admitted": ctx.Value("l", -1, lock=False),
            "receiving": ctx.Value("l", 0, lock=False),
            "progress": ctx.Value("l", 0, lock=False),
            "lo": ctx.Value("q", -1, lock=False),
            "hi": ctx.Value("q", -1, lock=False),
            "server": ctx.Array("c", 128, lock=False),
        }
        for _ in cspecs
    ]
    results = ctx.Queue()
    sid = None if several else targets[0].server_id
    shapers = spec.link.shapers(endpoint, spec.link.shaped(len(cspecs)))  # a home link each (issue 21)
    cspecs = [c if sh is None else replace(c, link_endpoint=sh.endpoint) for c, sh in zip(cspecs, shapers, strict=True)]
    procs = [
        ctx.Process(
            target=client_main,
            name=f"loadtest-client-{c.index}",
            args=(c, endpoint, sid, shared[c.index], results, client_cpus),
        )
        for c in cspecs
    ]
    figures = [t.proc.figures for t in targets if t.proc is not None]
    for f in figures:
        f.rss_mb.clear()
        f.sample_rss()
    t_start = time.monotonic()
    out: list[ClientResult] = []
    finished = False
    by_id = {t.server_id: k for k, t in enumerate(targets)}
    try:
        offered = sum(c.offered for c in cspecs)
        deadline = time.monotonic() + 120 + 0.05 * offered
        for p in procs:  # all start at once (imports, a Zenoh session, the servers seen) ...
            p.start()
        # ... and submit only once every one is up: a client starting beside the first submits
        # competes for the CPU with the server's first ticks, which admission measures
        _wait(
            lambda: all(s["connected"].is_set() for s in shared),
            "the clients connected",
            deadline,
            procs,
            targets,
        )
        placed = 0
        for p, s in zip(procs, shared, strict=True):
            s["expect"].value = placed * spec.size * spec.size
            s["turn"].set()
            if several:  # ... and place one after another: each by the load of those before it
                t_turn = time.monotonic()
                _wait(s["ready"].is_set, f"{p.name}'s submits were answered", deadline, procs, targets)
                placed += int(s["admitted"].value)
                log.debug("%s placed %d cloths in %.2f s", p.name, int(s["admitted"].value), time.monotonic() - t_turn)
        _wait(
            lambda: all(s["ready"].is_set() for s in shared),
            "the clients' submits were answered",
            deadline,
            procs,
            targets,
        )
        admitted = sum(int(s["admitted"].value) for s in shared)
        home = [by_id.get(s["server"].value.decode(), 0) if several else 0 for s in shared]
        log.info(
            "%d of %d cloths admitted in %.1f s; waiting for their states",
            admitted,
            offered,
            time.monotonic() - t_start,
        )
        for s in shared:
            s["go"].set()
        _wait(
            lambda: all(s["receiving"].value for s in shared),
            "every admitted cloth received a state",
            time.monotonic() + 60 + 0.02 * admitted,
            procs,
            targets,
        )
        # the window opens at each server's next stats publication, closes at the first one --seconds later
        first = [
            t.stats.next_after(t.stats.count(), 30, lambda: _check_servers(targets, "the measured window opened"))
            for t in targets
        ]
        for s, k in zip(shared, home, strict=True):
            s["lo"].value = int(first[k][1]["tick"])
        cpu0 = [f.cpu_seconds() for f in figures]
        rss0 = [f.sample_rss() for f in figures]  # the window's own start (admission and warm-up before it)
        load0 = _load_average()
        t0 = time.monotonic()
        bar = progress(total=round(spec.seconds, 1), desc=f"{admitted} cloths", unit="s", quiet=quiet)
        with bar:
            while time.monotonic() - t0 < spec.seconds:
                time.sleep(0.25)
                for f in figures:
                    f.sample_rss()
                bar.n = round(min(time.monotonic() - t0, spec.seconds), 1)
                bar.set_postfix(states=sum(int(s["progress"].value) for s in shared), refresh=False)
                bar.refresh()
                _check_servers(targets, "the measured window closed")
                if not all(p.is_alive() for p in procs):
                    raise RuntimeError("a client process exited during the measured window")
        last = [
            t.stats.next_after(t.stats.count(), 30, lambda: _check_servers(targets, "the measured window closed"))
            for t in targets
        ]
        cpu1 = [f.cpu_seconds() for f in figures]
        load1 = _load_average()
        elapsed = time.monotonic() - t0
        for s, k in zip(shared, home, strict=True):
            s["hi"].value = int(last[k][1]["tick"])
        time.sleep(max(1.0, 5.0 / spec.tick_rate))  # the window's last states are still on their way
        for s in shared:
            s["stop"].set()
        for _ in procs:
            kind, *rest = _result(results, targets, time.monotonic() + 120)
            if kind == "error":
                raise RuntimeError(f"client {rest[0]} failed: {rest[1]}")
            out.append(rest[0])
        for p in procs:
            p.join(30)
        for f in figures:
            f.sample_rss()
        finished = True
    finally:
        for s in shared:
            s["go"].set()
            s["stop"].set()
        # all together (a client stuck in a submit is not waited on for each); failed: no waiting
        t_end = time.monotonic() + (5.0 if finished else 0.5)
        for p in procs:
            if p.is_alive():
                p.join(max(0.0, t_end - time.monotonic()))
        for p in procs:
            if p.is_alive():
                p.terminate()
                p.join(5)
        for sh in shapers:
            if sh is not None:
                sh.stop()
    windows = [t.stats.samples[i0 + 1 : i1 + 1] for t, (i0, _), (i1, _) in zip(targets, first, last, strict=True)]
    per_server = [
        server_window(str(t.server_id), s0, s1, [st for _, st in w])
        for t, (_, s0), (_, s1), w in zip(targets, first, last, windows, strict=True)
    ]
    s0, s1 = first[0][1], last[0][1]
    seconds = float(np.mean([p["seconds"] for p in per_server]))
    # with home links (loadlink.py) the server's figures are the unshaped clients' (the shaped ones
    # are reported apart, in Report.links: their link, not the server, decides their states)
    main = [r for r in out if not r.extra.get("shaped")] or out
    lat = np.concatenate([r.latencies_ms for r in main]) if main else np.zeros(0)
    refused: Counter[str] = Counter()
    for r in out:
        refused.update(r.refused)
    server_info: dict[str, Any] = {"phases_ms": phase_means([st for w in windows for _, st in w])}
    if figures:
        server_info["cpu_percent"] = round(100.0 * (sum(cpu1) - sum(cpu0)) / elapsed, 1)
        rss = [f.rss_summary() for f in figures]
        server_info.update({k: round(sum(r[k] for r in rss), 1) for k in rss[0]})  # all processes together
        server_info["rss_window_start_mb"] = round(sum(rss0), 1)
    states = sum(r.received for r in main)
    report = Report(
        cloths=sum(r.admitted for r in out),
        offered=sum(r.offered for r in out),
        refused=dict(refused),
        clients=spec.clients,
        vertices_per_cloth=spec.size * spec.size,
        iterations=spec.iterations,
        features=list(spec.features),
        encoding=spec.encoding,
        bundle=spec.bundle,
        window_ticks=(int(s0["tick"]), int(s1["tick"])),
        seconds=round(seconds, 3),
        tick_hz_target=spec.tick_rate,
        tick_hz_achieved=round(min(p["hz"] for p in per_server), 2) if several else round(achieved_rate(s0, s1), 2),
        ticks=min(p["ticks"] for p in per_server) if several else counter_delta(s0, s1, "ticks"),
        missed_ticks=sum(p["missed_ticks"] for p in per_server),
        skipped_frames=sum(p["skipped_frames"] for p in per_server),
        latency_ms=latency_summary(lat),
        states=states,
        expected_states=sum(r.expected for r in main),
        lost=sum(r.lost for r in main),
        duplicated=sum(r.duplicated for r in main),
        out_of_order=sum(r.out_of_order for r in main),
        messages_per_s=round(states / seconds, 1),
        bytes_per_s=round(bytes_put(per_server, out) / seconds, 1),
        send_errors=sum(r.send_errors for r in out),
        decode_us={**decode_summary(out, seconds), "one_in": spec.decode_one_in(spec.cloths)},
        server=server_info,
        clients_cpu_percent=round(100.0 * sum(r.cpu_s for r in out) / elapsed, 1),
        host=f"{platform.node()} {os.cpu_count()} cores",
        affinity={
            k: format_cpus(v)
            for k, v in [("clients", client_cpus), *[(str(t.server_id), t.proc and t.proc.cpus) for t in targets]]
            if v
        },
        servers=per_server if several else [],
        spread=round(spread(p["cloths"] for p in per_server), 4) if several else 0.0,
        load_average=[x for x in (load0, load1) if x is not None],
        timeline=timeline(s0, [st for _, st in windows[0]]),
        links=links_report(out, seconds, spec.link),
        rates=rate_counts(per_server),
    )
    return report, out, windows[0]


def bytes_put(per_server: list[dict[str, Any]], out: list[ClientResult]) -> int:
    """The window's payload bytes: what the servers' publishers put (their stats' published_bytes:
    a predictive state's real size, a bundle's header and entries), or where a server does not
    report it the states the clients received times their encoding's size (exact for the
    fixed-size encodings, a predictive state's largest size)."""
    put = [p.get("published_bytes") for p in per_server]
    if put and all(b is not None for b in put):
        return int(sum(put))  # type: ignore[arg-type]
    return sum(r.bytes for r in out)


__all__ = ["LoadSpec", "StatsWatch", "Target", "run_load", "run_fleet_load"]
