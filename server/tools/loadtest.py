"""``drape loadtest``: how many cloths one server holds, measured so that start-up never counts.

K client processes (``--clients``, 16-64 for big loads) share a load of N cloths; each behaves
like a game client (``loadclient``): every tick it moves each cloth's pins and receives every
state over Zenoh, bundled (one publication and one batch control per client per tick, protocol
1.1, the default) or per cloth (``--no-bundle``).

One load runs like this: clients submit their cloths (refused submits counted by error code),
start their game loops, and once every client receives states for all its admitted cloths the
**measured window** opens at the next stats publication of the server and closes at the first
stats publication ``--seconds`` later. Everything is computed over that window: the achieved
tick rate from the two publications' tick counters and server timestamps, missed ticks and
coalesced frames from their counters, per-phase server time from the publications in between,
and, from the clients, the states of exactly those ticks (lost, duplicated, out of order),
latency (server tick -> client receipt) p50/p99/max, message and byte rates and decode cost
(arrival to delivery, per state and per bundle). The server's CPU and RSS (start, end, max) come
from psutil.

``--loads 128,256,4096:quant16`` runs several loads (total cloths, optionally with an encoding)
on one server; ``--find-knee`` doubles the load until it is not held (a load that fails is run
once more before it counts: a one-off hiccup does not end the search); ``--offered 2`` offers
twice each load and reports admitted against refused submits (past the knee, a server answers
``overloaded``) with the admitted cloths' figures. Outputs: a summary per load, ``--json``,
``--markdown`` (one table row per load) and plots in ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import multiprocessing as mp
import os
import platform
import threading
import time
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from .loadclient import ClientResult, ClientSpec, client_main
from .loadreport import (
    Report,
    achieved_rate,
    counter_delta,
    decode_summary,
    latency_summary,
    markdown_table,
    phase_means,
    print_report,
    write_plots,
    write_summary_plot,
)
from .procs import ServerProcess, progress, require_extra

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoadSpec:
    clients: int = 4
    cloths: int = 64  # total cloths wanted (each client offers its share x ``offered``)
    size: int = 32  # n x n vertices per cloth
    seconds: float = 5.0  # the measured window, at least
    features: tuple[str, ...] = ()
    iterations: int = 10
    substeps: int = 1
    bending: bool = True
    encoding: str = "float32"
    tick_rate: float = 60.0
    bundle: bool = True
    offered: float = 1.0  # offer this many times ``cloths``

    def client_specs(self) -> list[ClientSpec]:
        """Each client's share of the offered cloths (the first ones take the remainder)."""
        total = int(math.ceil(self.cloths * self.offered))
        base, extra = divmod(total, self.clients)
        return [
            ClientSpec(
                index=i,
                offered=base + (i < extra),
                size=self.size,
                features=self.features,
                iterations=self.iterations,
                substeps=self.substeps,
                bending=self.bending,
                encoding=self.encoding,
                tick_rate=self.tick_rate,
                bundle=self.bundle,
            )
            for i in range(self.clients)
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

    def next_after(self, index: int, timeout: float) -> tuple[int, dict[str, Any]]:
        """The first publication with position >= ``index`` (waiting up to ``timeout`` s)."""
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.samples) > index, timeout):
                raise RuntimeError(f"no stats publication from the server in {timeout:.0f} s")
            return index, self.samples[index][1]

    def count(self) -> int:
        with self._cond:
            return len(self.samples)

    def close(self) -> None:
        self._cancel()
        self.client.close()


def _wait(cond: Any, what: str, deadline: float, procs: list[Any]) -> None:
    while not cond():
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        dead = [p.name for p in procs if not p.is_alive()]
        if dead:
            raise RuntimeError(f"{', '.join(dead)} exited while waiting for {what}")
        time.sleep(0.05)


def run_load(
    spec: LoadSpec,
    endpoint: str,
    server_id: str | None,
    server: ServerProcess | None,
    stats: StatsWatch,
    quiet: bool = False,
) -> tuple[Report, list[ClientResult], list[tuple[float, dict]]]:
    """Run one load and measure it over a window of server ticks (see the module docstring)."""
    ctx = mp.get_context("spawn")
    cspecs = spec.client_specs()
    shared = [
        {
            "ready": ctx.Event(),
            "go": ctx.Event(),
            "stop": ctx.Event(),
            "admitted": ctx.Value("l", -1, lock=False),
            "receiving": ctx.Value("l", 0, lock=False),
            "progress": ctx.Value("l", 0, lock=False),
            "lo": ctx.Value("q", -1, lock=False),
            "hi": ctx.Value("q", -1, lock=False),
        }
        for _ in cspecs
    ]
    results = ctx.Queue()
    procs = [
        ctx.Process(
            target=client_main,
            name=f"loadtest-client-{c.index}",
            args=(c, endpoint, server_id, shared[c.index], results),
        )
        for c in cspecs
    ]
    figures = server.figures if server else None
    if figures:
        figures.rss_mb.clear()
        figures.sample_rss()
    t_start = time.monotonic()
    for p in procs:
        p.start()
    out: list[ClientResult] = []
    try:
        offered = sum(c.offered for c in cspecs)
        deadline = time.monotonic() + 120 + 0.05 * offered
        _wait(lambda: all(s["ready"].is_set() for s in shared), "the clients' submits", deadline, procs)
        admitted = sum(int(s["admitted"].value) for s in shared)
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
            "states of every admitted cloth",
            time.monotonic() + 60 + 0.02 * admitted,
            procs,
        )
        # the window opens at the next stats publication, closes at the first one --seconds later
        i0, s0 = stats.next_after(stats.count(), timeout=30)
        for s in shared:
            s["lo"].value = int(s0["tick"])
        cpu0 = figures.cpu_seconds() if figures else math.nan
        t0 = time.monotonic()
        bar = progress(total=round(spec.seconds, 1), desc=f"{admitted} cloths", unit="s", quiet=quiet)
        with bar:
            while time.monotonic() - t0 < spec.seconds:
                time.sleep(0.25)
                if figures:
                    figures.sample_rss()
                bar.n = round(min(time.monotonic() - t0, spec.seconds), 1)
                bar.set_postfix(states=sum(int(s["progress"].value) for s in shared), refresh=False)
                bar.refresh()
                if not all(p.is_alive() for p in procs):
                    raise RuntimeError("a client process exited during the measured window")
        i1, s1 = stats.next_after(stats.count(), timeout=30)
        cpu1 = figures.cpu_seconds() if figures else math.nan
        elapsed = time.monotonic() - t0
        for s in shared:
            s["hi"].value = int(s1["tick"])
        time.sleep(max(1.0, 5.0 / spec.tick_rate))  # the window's last states are still on their way
        for s in shared:
            s["stop"].set()
        for _ in procs:
            kind, *rest = results.get(timeout=120)
            if kind == "error":
                raise RuntimeError(f"client {rest[0]} failed: {rest[1]}")
            out.append(rest[0])
        for p in procs:
            p.join(30)
        if figures:
            figures.sample_rss()
    finally:
        for s in shared:
            s["go"].set()
            s["stop"].set()
        for p in procs:
            p.join(5)
            if p.is_alive():
                p.terminate()
    window = stats.samples[i0 + 1 : i1 + 1]
    seconds = (int(s1["time_ns"]) - int(s0["time_ns"])) / 1e9
    lat = np.concatenate([r.latencies_ms for r in out]) if out else np.zeros(0)
    refused: Counter[str] = Counter()
    for r in out:
        refused.update(r.refused)
    server_info: dict[str, Any] = {"phases_ms": phase_means([st for _, st in window])}
    if figures:
        server_info["cpu_percent"] = round(100.0 * (cpu1 - cpu0) / elapsed, 1)
        server_info.update(figures.rss_summary())
    states = sum(r.received for r in out)
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
        tick_hz_achieved=round(achieved_rate(s0, s1), 2),
        ticks=counter_delta(s0, s1, "ticks"),
        missed_ticks=counter_delta(s0, s1, "missed_ticks"),
        skipped_frames=counter_delta(s0, s1, "skipped_frames"),
        latency_ms=latency_summary(lat),
        states=states,
        expected_states=sum(r.expected for r in out),
        lost=sum(r.lost for r in out),
        duplicated=sum(r.duplicated for r in out),
        out_of_order=sum(r.out_of_order for r in out),
        messages_per_s=round(states / seconds, 1),
        bytes_per_s=round(sum(r.bytes for r in out) / seconds, 1),
        send_errors=sum(r.send_errors for r in out),
        decode_us=decode_summary(out, seconds),
        server=server_info,
        clients_cpu_percent=round(100.0 * sum(r.cpu_s for r in out) / elapsed, 1),
        host=f"{platform.node()} {os.cpu_count()} cores",
    )
    return report, out, window


# ------------------------------------------------------------------------------------------------
# Command


def parse_loads(text: str, default_encoding: str) -> list[tuple[int, str]]:
    """``"128,256,4096:quant16"`` -> [(128, default), (256, default), (4096, "quant16")]."""
    loads = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        n, _, enc = item.partition(":")
        if not n.isdigit() or int(n) < 1:
            raise argparse.ArgumentTypeError(f"a load is a positive number of cloths, got {item!r}")
        loads.append((int(n), enc or default_encoding))
    return loads


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("tools", "loadtest")
    parser.add_argument("--clients", type=int, default=4, help="client processes (16-64 for thousands of cloths)")
    parser.add_argument("--cloths", type=int, default=16, help="cloths per client (without --loads)")
    parser.add_argument(
        "--loads",
        default=None,
        help="total cloths per load, comma-separated, each optionally :ENCODING "
        "(e.g. 128,256,4096:quant16); run one after another on one server",
    )
    parser.add_argument(
        "--offered",
        type=float,
        default=1.0,
        help="offer this many times each load (2: past the knee; refused submits are counted)",
    )
    parser.add_argument("--size", type=int, default=32, help="each cloth is SIZE x SIZE vertices")
    parser.add_argument("--seconds", type=float, default=5.0, help="measured window per load (server stats to stats)")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--substeps", type=int, default=1)
    parser.add_argument("--features", default="", help="comma-separated scene features")
    parser.add_argument("--no-bending", action="store_true", help="structural and shear links only")
    parser.add_argument("--encoding", default="float32", choices=["float32", "float16", "quant16"])
    parser.add_argument("--tick-rate", type=float, default=60.0)
    parser.add_argument(
        "--bundle",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="bundled states and one batch control per client per tick (protocol 1.1); "
        "--no-bundle: one state and one control per cloth per tick",
    )
    parser.add_argument("--endpoint", default=None, help="target a running server instead of starting one")
    parser.add_argument("--server-id", default=None, help="with --endpoint: which server (default: the one seen)")
    parser.add_argument(
        "--admission",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the started server refuses submits it cannot serve ('overloaded'); --no-admission: "
        "it takes every cloth (the raw capacity)",
    )
    parser.add_argument("--solver", default=None, help="solver of the started server")
    parser.add_argument("--device", default=None, help="OpenCL device of the started server")
    parser.add_argument("--server-arg", action="append", default=[], help="extra argument for drape serve")
    parser.add_argument(
        "--find-knee",
        action="store_true",
        help="from the first load, double it until it is not held (a failed load is run twice)",
    )
    parser.add_argument("--max-cloths", type=int, default=8192, help="--find-knee stops here (total cloths)")
    parser.add_argument(
        "--max-total-seconds",
        type=float,
        default=None,
        help="skip the loads that would start after this many seconds (said in the output)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the reports here (a list, one per load)")
    parser.add_argument("--markdown", type=Path, default=None, help="write a markdown table here (a row per load)")
    parser.add_argument("--out", type=Path, default=Path("out/loadtest"), help="PNG plots go here")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _serve_args(args: argparse.Namespace) -> list[str]:
    cmd = [
        "--tick-rate",
        str(args.tick_rate),
        "--max-cloths",
        "100000",
        "--max-cloths-per-client",
        "100000",
        "--max-total-vertices",
        str(1 << 26),
        "--stats-period",
        "0.5",
        "--max-pending-requests",
        "1000000",
        "--max-batch-items",
        "100000",
    ]
    if not args.admission:
        cmd += ["--no-admission"]
    if args.solver:
        cmd += ["--solver", args.solver]
    if args.device:
        cmd += ["--device", args.device]
    return cmd + list(args.server_arg)


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.clients <= 256:
        raise SystemExit("--clients must be 1..256")
    base = LoadSpec(
        clients=args.clients,
        cloths=args.clients * args.cloths,
        size=args.size,
        seconds=args.seconds,
        features=tuple(f for f in args.features.split(",") if f),
        iterations=args.iterations,
        substeps=args.substeps,
        bending=not args.no_bending,
        encoding=args.encoding,
        tick_rate=args.tick_rate,
        bundle=args.bundle,
        offered=args.offered,
    )
    loads = parse_loads(args.loads, args.encoding) if args.loads else [(base.cloths, base.encoding)]
    server = None
    if args.endpoint:
        endpoint, server_id = args.endpoint, args.server_id
    else:
        server = ServerProcess(_serve_args(args), server_id=f"loadtest-{os.getpid()}")
        endpoint, server_id = server.endpoint, server.server_id
    reports: list[Report] = []
    skipped: list[str] = []
    t_begin = time.monotonic()
    last_cost = 0.0
    try:
        stats = StatsWatch(endpoint, server_id)
        try:
            queue = [replace(base, cloths=n, encoding=enc) for n, enc in loads]
            if args.find_knee:  # from the first load up, doubling
                queue = queue[:1]
            retried = False
            while queue:
                spec = queue.pop(0)
                spent = time.monotonic() - t_begin
                if args.max_total_seconds and reports and spent + last_cost > args.max_total_seconds:
                    skipped = [f"{s.cloths}:{s.encoding}" for s in [spec, *queue]]
                    print(f"skipped (would pass --max-total-seconds {args.max_total_seconds:g}): {', '.join(skipped)}")
                    break
                t = time.monotonic()
                report, results, window = run_load(spec, endpoint, server_id, server, stats, args.quiet)
                last_cost = time.monotonic() - t
                print_report(report)
                tag = f"{report.cloths}-{report.encoding}"
                for p in write_plots(args.out, report, results, window, tag):
                    print(f"wrote {p}")
                reports.append(report)
                if args.find_knee:
                    if not report.held and not retried:
                        print(f"not held ({report.why_not_held()}): running this load once more")
                        retried = True
                        queue.insert(0, spec)
                    elif report.held and spec.cloths * 2 <= args.max_cloths:
                        retried = False
                        queue.append(replace(spec, cloths=spec.cloths * 2))
                time.sleep(1.0)  # the previous clients' cloths go
        finally:
            stats.close()
    finally:
        if server:
            server.stop()
    if args.find_knee and reports:
        held = [r for r in reports if r.held]
        knee = max((r.cloths for r in held), default=0)
        bad = reports[-1] if not reports[-1].held else None
        print(
            f"knee: {knee} cloths held at {base.tick_rate:g} Hz; next load "
            f"({bad.cloths if bad else '-'} cloths): {bad.why_not_held() if bad else 'not reached within --max-cloths'}"
        )
    if len(reports) > 1:
        print(f"wrote {write_summary_plot(args.out / 'loadtest-summary.png', reports)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps([r.to_dict() for r in reports], indent=1))
        print(f"wrote {args.json}")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        note = f"\nSkipped to stay within --max-total-seconds: {', '.join(skipped)}\n" if skipped else ""
        args.markdown.write_text(markdown_table(reports) + note)
        print(f"wrote {args.markdown}")
    return 0
