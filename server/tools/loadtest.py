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
(arrival to delivery, per state and per bundle; with ``--decode-sample N`` the clients decode one
cloth in N and count the others' states from their headers, the default for predictive loads over
2048 cloths). The server's CPU and RSS (before the load, at
the window's start, at its end, max) come from psutil; the report also holds the host's load
average at the window's ends and, per stats period, its ticks, missed ticks and coalesced frames
(when the misses happen).

``--loads 128,256,4096:quant16`` runs several loads (total cloths, optionally with an encoding)
on one server; ``--find-knee`` doubles the load until it is not held (a load that fails is run
once more before it counts: a one-off hiccup does not end the search), then halves the gap
between the last load held and the first not held ``--bisect`` times; ``--offered 2`` offers
twice each load and reports admitted against refused submits (past the knee, a server answers
``overloaded``) with the admitted cloths' figures. Outputs: a summary per load, ``--json``,
``--markdown`` (one table row per load) and plots in ``--out``.

``--servers N`` starts N ``drape serve`` processes (each its own server id and port; peers
connected to each other, or behind one Zenoh router process with ``--router``; on a GPU machine
they share the device) and spreads the clients over them by the servers' published load (the
SDK's placement, PROTOCOL.md 11.3): per server its cloths, vertices, achieved rate and missed
ticks, and the spread of cloths (max / mean - 1). ``--scale-out`` finds the knee of one server,
then of N, and prints the ratio. ``--endpoint E --server-id A,B`` measures servers already
running the same way (say ``drape serve --workers 2``'s ``<id>-0,<id>-1``). The measurement
itself is :mod:`.loadrun`'s. ``--link-rate R --link-delay D [--link-share S --link-client-rate auto]``
puts some or all clients behind a home link each (:mod:`.loadlink`), reported apart.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from .loadclient import AUTO_SAMPLE_ABOVE, SAMPLED_DECODE
from .loadlink import add_arguments as add_link_arguments
from .loadlink import link_spec, print_links
from .loadreport import Report, markdown_table, print_report, write_plots, write_summary_plot
from .loadrun import LoadSpec, StatsWatch, Target, run_fleet_load, run_load  # noqa: F401  (lt.run_load as before)
from .procs import ServerProcess, csv_list, free_port, parse_cpus, require_extra

log = logging.getLogger(__name__)


# ------------------------------------------------------------------------------------------------
# Command


def parse_loads(text: str, default_encoding: str) -> list[tuple[int, str]]:
    """``"128,256,4096:quant16"`` -> [(128, default), (256, default), (4096, "quant16")]."""
    loads = []
    for item in csv_list(text):
        n, _, enc = item.partition(":")
        if not n.isdigit() or int(n) < 1:
            raise argparse.ArgumentTypeError(f"a load is a positive number of cloths, got {item!r}")
        loads.append((int(n), enc or default_encoding))
    return loads


EXIT_CODES = """\
exit status:
  0  every load was held (with --offered > 1: the admitted cloths of every load were served;
     with --find-knee / --scale-out: some load was held, the loads past the knee are expected not to be)
  1  a load was not held (its summary says "held: NO (why)"); with --find-knee / --scale-out: no load held
  2  bad arguments (or the tools extra is not installed)
  3  the run failed: a server it started exited (its exit status and last log lines are printed), a
     client process failed, or a wait timed out"""


def configure(parser: argparse.ArgumentParser) -> None:
    try:
        require_extra("tools", "loadtest")
    except SystemExit as e:
        print(e, file=sys.stderr)
        raise SystemExit(2) from None
    parser.epilog = EXIT_CODES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
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
    parser.add_argument(
        "--decode-sample",
        type=int,
        default=0,
        metavar="N",
        help="with bundles, each client decodes fully one cloth in N and counts the others' states from "
        "their headers (tick, cloth: received, lost and latency counted alike), so that the clients measure "
        f"the server, not the SDK's decode; 1: decode all. Default (0): auto, one in {SAMPLED_DECODE} for "
        f"predictive loads over {AUTO_SAMPLE_ABOVE} cloths, all otherwise",
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
    parser.add_argument(
        "--server-id",
        default=None,
        help="with --endpoint: which server (default: the one seen); a comma list: these running servers "
        "(e.g. drape serve --workers N's <id>-0,<id>-1), the clients placing by load as with --servers",
    )
    parser.add_argument(
        "--admission",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="the started server refuses submits it cannot serve ('overloaded'); --no-admission: "
        "it takes every cloth (the raw capacity)",
    )
    parser.add_argument("--solver", default=None, help="solver of the started server")
    parser.add_argument(
        "--device",
        default=None,
        help="OpenCL device of the started server(s); a comma list gives the k-th server the k-th entry "
        "(in turn), e.g. gpu:0,gpu:1 for one server per GPU",
    )
    parser.add_argument("--server-arg", action="append", default=[], help="extra argument for drape serve")
    parser.add_argument(
        "--server-cpus",
        default=None,
        help="CPUs the started server(s) run on, as taskset writes them (0-3,16-19); a ';' list gives the "
        "k-th server the k-th entry (in turn)",
    )
    parser.add_argument(
        "--client-cpus",
        default=None,
        help="CPUs the client processes run on (0-15): the load clients stand for game clients on other "
        "machines, so they can be kept off the servers' cores",
    )
    parser.add_argument(
        "--find-knee",
        action="store_true",
        help="from the first load, double it until it is not held (a failed load is run twice), then --bisect halvings",
    )
    parser.add_argument("--max-cloths", type=int, default=8192, help="--find-knee stops here (total cloths)")
    parser.add_argument(
        "--max-total-seconds",
        type=float,
        default=None,
        help="skip the loads that would start after this many seconds (said in the output)",
    )
    parser.add_argument(
        "--servers",
        type=int,
        default=1,
        help="start this many drape serve processes (each its own server id and port, peers connected to "
        "each other); each client places its cloths on one of them by their published load",
    )
    parser.add_argument("--router", action="store_true", help="with --servers: behind one Zenoh router process")
    parser.add_argument(
        "--scale-out",
        action="store_true",
        help="find the knee of one server, then of --servers servers (doubling, then --bisect steps) "
        "and print the ratio",
    )
    parser.add_argument(
        "--bisect",
        type=int,
        default=2,
        help="--find-knee / --scale-out: halvings between the last held load and the first not held (default 2)",
    )
    parser.add_argument("--json", type=Path, default=None, help="write the reports here (a list, one per load)")
    parser.add_argument("--markdown", type=Path, default=None, help="write a markdown table here (a row per load)")
    parser.add_argument("--out", type=Path, default=Path("out/loadtest"), help="PNG plots go here")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_link_arguments(parser)  # issue 21: clients behind a home link (loadlink.py)


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
    return cmd + list(args.server_arg)


class Fleet:
    """The servers a load test starts: ``n`` ``drape serve`` processes, each with its own server id
    and loopback port, either peers connected to each other or, with ``router``, all connected to
    one Zenoh router process; ``endpoint`` is what the clients connect to. ``devices``: the k-th
    server's OpenCL device is ``devices[k % len(devices)]`` (none: the default device, which the
    servers then share, each process its own OpenCL context)."""

    def __init__(
        self,
        n: int,
        serve_args: list[str],
        router: bool = False,
        devices: Sequence[str] = (),
        cpus: Sequence[frozenset[int]] = (),
    ) -> None:
        self.router: Any = None
        self._router_stop: Any = None
        self.servers: list[ServerProcess] = []
        self.targets: list[Target] = []
        try:
            if router:
                ctx = mp.get_context("spawn")
                self.router_endpoint = f"tcp/127.0.0.1:{free_port()}"
                self._router_stop = ctx.Event()
                self.router = ctx.Process(
                    target=_router_main, args=(self.router_endpoint, self._router_stop), name="zenoh-router"
                )
                self.router.start()
            for k in range(n):
                connect = [self.router_endpoint] if router else [s.endpoint for s in self.servers]
                extra = [a for c in connect for a in ("--connect", c)]
                if devices:
                    extra += ["--device", devices[k % len(devices)]]
                sid = f"loadtest-{os.getpid()}" + (f"-{k}" if n > 1 else "")
                pin = cpus[k % len(cpus)] if cpus else None
                self.servers.append(ServerProcess([*serve_args, *extra], server_id=sid, cpus=pin))
            for srv in self.servers:
                self.targets.append(Target(srv.server_id, StatsWatch(srv.endpoint, srv.server_id), srv))
        except BaseException:
            self.stop()
            raise
        self.endpoint: str | list[str] = (
            self.router_endpoint
            if router
            else [s.endpoint for s in self.servers]
            if n > 1
            else self.servers[0].endpoint
        )

    def stop(self) -> None:
        for t in self.targets:
            t.stats.close()
        for srv in self.servers:
            srv.stop()
        if self.router is not None:
            self._router_stop.set()
            self.router.join(10)
            if self.router.is_alive():
                self.router.terminate()


def _router_main(endpoint: str, stop: Any) -> None:
    """A Zenoh router listening on ``endpoint`` until ``stop`` is set (a process of its own)."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(c)
    stop.wait()
    session.close()


def knee_search(
    base: LoadSpec, run_one: Any, max_cloths: int, bisect: int, budget_s: float | None, t_begin: float
) -> tuple[list[Report], int]:
    """From ``base.cloths`` double the load until it is not held (a load that fails runs once more
    before it counts), or, when the first load is not held, halve it until one is; then halve the
    gap between the last held and the first not held load ``bisect`` times.
    ``run_one(spec) -> Report``. Returns every report and the largest load held (0: none, down to
    one cloth a client)."""
    reports: list[Report] = []
    held, failed = 0, 0
    n = base.cloths
    last_cost = 0.0
    steps = bisect
    while n and n <= max_cloths:
        if budget_s and reports and time.monotonic() - t_begin + last_cost > budget_s:
            print(f"knee search stopped at {n} cloths to stay within --max-total-seconds {budget_s:g}")
            break
        t = time.monotonic()
        r = run_one(replace(base, cloths=n))
        if not r.held:  # kept in the reports, then run once more: a one-off hiccup does not end the search
            print(f"not held ({r.why_not_held()}): running this load once more")
            reports.append(r)
            r = run_one(replace(base, cloths=n))
        last_cost = time.monotonic() - t
        reports.append(r)
        if r.held:
            held = max(held, n)
        else:
            failed = n if not failed else min(failed, n)
        if not failed:
            n *= 2
        elif not held:  # nothing held yet: search downward, one cloth a client at least
            n = n // 2 if n // 2 >= base.clients else 0
        elif steps > 0 and failed - held > 1:
            steps -= 1
            n = (held + failed) // 2
        else:
            break
    return reports, held


def exit_status(reports: Sequence[Report], offered: float, search: bool) -> int:
    """0 when every load passed, else 1 (see EXIT_CODES): a load passes when it was held, or,
    offered more than it (``offered`` > 1, refusals expected), when its admitted cloths were served;
    a knee search (``search``) passes when some load did (the loads past the knee fail by design)."""
    passed = [r.served if offered > 1 else r.held for r in reports]
    if search:
        return 0 if any(passed) else 1
    return 0 if reports and all(passed) else 1


def run(args: argparse.Namespace) -> int:
    try:
        return _run(args)
    except (SystemExit, argparse.ArgumentTypeError) as e:
        if isinstance(e, SystemExit) and not isinstance(e.code, str):
            raise
        print(f"drape loadtest: {e}", file=sys.stderr)
        return 2
    except RuntimeError as e:  # ServerExited among them: the server's exit status and last log lines
        print(f"drape loadtest: {e}", file=sys.stderr)
        return 3


def _run(args: argparse.Namespace) -> int:
    if not 1 <= args.clients <= 256:
        raise SystemExit("--clients must be 1..256")
    if args.decode_sample < 0:
        raise SystemExit("--decode-sample must be 0 (auto) or more")
    if not 1 <= args.servers <= 16:
        raise SystemExit("--servers must be 1..16")
    if args.endpoint and (args.servers > 1 or args.scale_out):
        raise SystemExit("--servers / --scale-out start their own servers: not with --endpoint")
    try:
        server_cpus = [parse_cpus(c) for c in args.server_cpus.split(";")] if args.server_cpus else []
        client_cpus = parse_cpus(args.client_cpus) if args.client_cpus else None
    except ValueError as e:
        raise SystemExit(f"--server-cpus / --client-cpus: {e}") from None
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
        link=link_spec(args),
        decode_sample=args.decode_sample,
    )
    loads = parse_loads(args.loads, args.encoding) if args.loads else [(base.cloths, base.encoding)]
    base = replace(base, cloths=loads[0][0], encoding=loads[0][1])
    t_begin = time.monotonic()
    reports: list[Report] = []
    skipped: list[str] = []
    knees: dict[int, int] = {}

    def on(fleet: Fleet) -> Any:
        def run_one(spec: LoadSpec) -> Report:
            report, results, window = run_fleet_load(spec, fleet.endpoint, fleet.targets, args.quiet, client_cpus)
            print_report(report)
            if report.decode_us.get("one_in", 1) > 1:
                print(
                    f"  clients decoded one cloth in {report.decode_us['one_in']:.0f} fully "
                    "(the others' states counted from their headers: --decode-sample)"
                )
            print_links(report.links)
            tag = f"{report.cloths}-{report.encoding}" + (
                f"-{len(fleet.targets)}servers" if len(fleet.targets) > 1 else ""
            )
            for p in write_plots(args.out, report, results, window, tag):
                print(f"wrote {p}")
            time.sleep(1.0)  # the previous clients' cloths go
            return report

        return run_one

    if args.endpoint:
        ids: list[str | None] = [*csv_list(args.server_id)] or [None]
        targets = [Target(sid, StatsWatch(args.endpoint, sid)) for sid in ids]

        def stop_watching() -> None:
            for t in targets:
                t.stats.close()

    counts = [1, args.servers] if args.scale_out else [args.servers]
    for n_servers in counts:
        if args.endpoint:
            fleet: Any = argparse.Namespace(endpoint=args.endpoint, targets=targets, stop=stop_watching)
        else:
            devices = csv_list(args.device)
            fleet = Fleet(n_servers, _serve_args(args), args.router, devices, server_cpus)
        try:
            run_one = on(fleet)
            if args.find_knee or args.scale_out:
                start = replace(base, cloths=max(knees.values(), default=0) or base.cloths)
                got, knees[n_servers] = knee_search(
                    start, run_one, args.max_cloths, args.bisect, args.max_total_seconds, t_begin
                )
                reports += got
            else:
                queue = [replace(base, cloths=n, encoding=enc) for n, enc in loads]
                last_cost = 0.0
                while queue:
                    spec = queue.pop(0)
                    spent = time.monotonic() - t_begin
                    if args.max_total_seconds and reports and spent + last_cost > args.max_total_seconds:
                        skipped = [f"{s.cloths}:{s.encoding}" for s in [spec, *queue]]
                        print(
                            f"skipped (would pass --max-total-seconds {args.max_total_seconds:g}): {', '.join(skipped)}"
                        )
                        break
                    t = time.monotonic()
                    reports.append(run_one(spec))
                    last_cost = time.monotonic() - t
        finally:
            fleet.stop()
    for n_servers, knee in knees.items():
        bad = [r for r in reports if not r.held and max(1, len(r.servers)) == n_servers]
        print(
            f"knee: {knee} cloths held at {base.tick_rate:g} Hz on {n_servers} server(s)"
            + (f"; {bad[-1].cloths} cloths: {bad[-1].why_not_held()}" if bad else "")
        )
    if args.scale_out:
        one, many = knees.get(1, 0), knees.get(args.servers, 0)
        spreads = [r.spread for r in reports if r.held and r.servers]
        print(
            f"scale-out: {many} cloths held on {args.servers} servers against {one} on one: "
            + (f"{many / one:.2f}x" if one else "- (one server held none)")
            + (
                f"; spread of cloths over the servers at the held loads: max {100 * max(spreads):.1f} %"
                if spreads
                else ""
            )
        )
    if len(reports) > 1:
        print(f"wrote {write_summary_plot(args.out / 'loadtest-summary.png', reports)}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        doc: Any = [r.to_dict() for r in reports]
        if args.scale_out:
            doc = {"knees": {str(k): v for k, v in knees.items()}, "reports": doc}
        args.json.write_text(json.dumps(doc, indent=1))
        print(f"wrote {args.json}")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        note = f"\nSkipped to stay within --max-total-seconds: {', '.join(skipped)}\n" if skipped else ""
        args.markdown.write_text(markdown_table(reports) + note)
        print(f"wrote {args.markdown}")
    status = exit_status(reports, args.offered, args.find_knee or args.scale_out)
    if status:
        failed = [f"{r.cloths} cloths ({r.why_not_held()})" for r in reports if not r.held]
        print(f"exit status 1: not held: {'; '.join(failed) or 'no load ran'}")
    return status
