"""``drape loadtest``: how many cloths one server holds.

K client processes, each with M cloths, behave like game clients for T seconds: every tick
they move each cloth's pins and receive every state over Zenoh. Two ways (protocol 1.1):

- ``--bundle`` (the default): cloths submitted with ``bundle=True``: one publication per client
  per tick carries all its cloths' states, and one batch control per client per tick moves all
  its cloths' pins;
- ``--no-bundle``: one state publication and one control message per cloth per tick (what a
  1.0 client does).

Both are not waited for. The load test starts its own ``drape serve`` process (or targets a running
one with ``--endpoint``) and measures

- achieved tick rate and missed ticks, frames the publisher had to coalesce (server stats);
- end-to-end latency of every state (server timestamp at the tick -> client receipt; one host,
  one clock): p50 / p99 / max;
- messages and bytes per second; states lost, duplicated or out of order per cloth;
- server time per tick phase (apply, solve, readback, encode, publish), server CPU and memory.

It prints progress, a summary and writes ``--json`` plus PNG plots (latency histogram, tick
time over the run) into ``--out``. ``--find-knee`` doubles the cloths per client until a tick
is missed, a state is lost or p99 exceeds one tick, and reports the largest load held.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import multiprocessing as mp
import os
import platform
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class LoadSpec:
    clients: int = 4
    cloths: int = 16  # per client
    size: int = 32  # n x n vertices per cloth
    seconds: float = 5.0
    features: tuple[str, ...] = ()
    iterations: int = 10
    substeps: int = 1
    bending: bool = True
    encoding: str = "float32"
    tick_rate: float = 60.0
    bundle: bool = True  # bundled states and one batch control per client per tick

    @property
    def total_cloths(self) -> int:
        return self.clients * self.cloths


@dataclass
class ClientResult:
    index: int
    cloths: int
    received: int
    lost: int
    duplicated: int
    out_of_order: int
    latencies_ms: np.ndarray
    bytes: int
    send_errors: int
    first_tick: int
    last_tick: int
    cpu_s: float = float("nan")  # the client process's CPU time during the measured window


@dataclass
class Report:
    cloths: int
    clients: int
    cloths_per_client: int
    vertices_per_cloth: int
    iterations: int
    features: list[str]
    encoding: str
    seconds: float
    tick_hz_target: float
    tick_hz_achieved: float
    ticks: int
    missed_ticks: int
    skipped_frames: int
    latency_ms: dict[str, float]
    states: int
    lost: int
    duplicated: int
    out_of_order: int
    messages_per_s: float
    bytes_per_s: float
    send_errors: int
    server: dict = field(default_factory=dict)
    host: str = ""
    bundle: bool = False  # clients used bundles and batch control (protocol 1.1)
    clients_cpu_percent: float = float("nan")  # CPU of all client processes together, % of one core

    @property
    def held(self) -> bool:
        """The load is held: no missed tick, nothing lost or coalesced, p99 within one tick."""
        return (self.missed_ticks == 0 and self.lost == 0 and self.skipped_frames == 0
                and self.latency_ms["p99"] <= 1000.0 / self.tick_hz_target)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------------
# Client processes


def _client_main(index: int, endpoint: str, server_id: str | None, spec: LoadSpec, ready, go, stop, progress,
                 results) -> None:
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient
    from drape.client.protocol import state_size

    n = spec.size
    pins = [0, n - 1]
    ticks: list[list[int]] = []
    lat: list[list[int]] = []
    handles = []
    recording = threading.Event()
    try:
        with DrapeClient(endpoint, server_id=server_id, timeout=30.0, queue_size=4) as client:
            for j in range(spec.cloths):
                h = client.submit_grid(
                    n, n, 1.0, 1.0, origin=(1.5 * j, 1.0, 2.0 * index), pinned=pins,
                    links={"structural": True, "shear": True, "bending": spec.bending},
                    features=list(spec.features), iterations=spec.iterations, substeps=spec.substeps,
                    encoding=spec.encoding, bundle=spec.bundle,
                )
                tl: list[int] = []
                ll: list[int] = []
                ticks.append(tl)
                lat.append(ll)

                def record(st, tl=tl, ll=ll):
                    if recording.is_set():
                        tl.append(st.tick)
                        ll.append(st.receive_time_ns - st.server_time_ns)

                h.on_state(record)
                handles.append(h)
            rest = [np.asarray(h.rest_positions[pins], np.float64) for h in handles]
            if spec.bundle:
                assert all(h.bundled for h in handles), "the server does not bundle states (protocol 1.0?)"
                client.server_version  # noqa: B018 - asks once now rather than in the first tick
            ready.set()
            go.wait()
            recording.set()
            cpu0 = time.process_time()
            period = 1.0 / spec.tick_rate
            t0 = next_t = time.monotonic()
            while not stop.is_set() and time.monotonic() - t0 < spec.seconds:
                t = time.monotonic() - t0
                # like a game: every cloth's pins follow its character, once per tick
                if spec.bundle:
                    with client.batch() as b:
                        for j, h in enumerate(handles):
                            offset = np.array([0.1 * math.sin(2.0 * t + j), 0.05 * math.sin(3.0 * t), 0.0])
                            b.move_pins(h, pins, rest[j] + offset)
                else:
                    for j, h in enumerate(handles):
                        offset = np.array([0.1 * math.sin(2.0 * t + j), 0.05 * math.sin(3.0 * t), 0.0])
                        h.move_pins(pins, rest[j] + offset, wait=False)
                progress.value = sum(len(tl) for tl in ticks)
                next_t += period
                delay = next_t - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    next_t = time.monotonic()
            recording.clear()
            cpu_s = time.process_time() - cpu0
            send_errors = client.send_errors
            per_state = state_size(n * n, spec.encoding)
    except BaseException as e:  # report, don't hang the parent
        results.put(("error", index, repr(e)))
        raise
    received = lost = dup = ooo = 0
    first = last = -1
    for tl in ticks:
        if not tl:
            continue
        arr = np.asarray(tl, np.int64)
        received += len(arr)
        ooo += int(np.count_nonzero(np.diff(arr) < 0))
        uniq = np.unique(arr)
        dup += len(arr) - len(uniq)
        lost += int(uniq[-1] - uniq[0] + 1 - len(uniq))
        first = int(uniq[0]) if first < 0 else min(first, int(uniq[0]))
        last = max(last, int(uniq[-1]))
    lat_ms = (np.concatenate([np.asarray(x, np.float64) for x in lat]) / 1e6) if received else np.zeros(0)
    results.put(("ok", ClientResult(index, spec.cloths, received, lost, dup, ooo, lat_ms.astype(np.float32),
                                    received * per_state, send_errors, first, last, cpu_s)))


# ------------------------------------------------------------------------------------------------
# Server side


class ServerProcess:
    """``drape serve`` as a child process on a free loopback port."""

    def __init__(self, tick_rate: float, solver: str | None, device: str | None, extra: list[str]) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.server_id = f"loadtest-{os.getpid()}"
        cmd = [sys.executable, "-m", "drape.server.cli", "serve", "--listen", self.endpoint, "--server-id",
               self.server_id, "--tick-rate", str(tick_rate), "--max-cloths", "100000",
               "--max-cloths-per-client", "100000", "--max-total-vertices", str(1 << 26), "--stats-period", "0.5",
               "--max-pending-requests", "1000000", "--max-batch-items", "100000"]
        if solver:
            cmd += ["--solver", solver]
        if device:
            cmd += ["--device", device]
        cmd += extra
        log.info("starting server: %s", " ".join(cmd))
        self.proc = subprocess.Popen(cmd, start_new_session=True)

    def cpu_seconds(self) -> float:
        try:
            parts = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            return float("nan")

    def memory_mb(self) -> dict[str, float]:
        out = {}
        try:
            for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
                if line.startswith(("VmRSS:", "VmHWM:")):
                    out[line.split(":")[0]] = int(line.split()[1]) / 1024
        except OSError:
            pass
        return {"rss_mb": out.get("VmRSS", float("nan")), "peak_rss_mb": out.get("VmHWM", float("nan"))}

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)


class StatsWatch:
    """The server's periodic stats publications, kept with their arrival time."""

    def __init__(self, endpoint: str, server_id: str | None) -> None:
        from drape.client import DrapeClient

        self.client = DrapeClient(endpoint, server_id=server_id, timeout=60.0)
        self.samples: list[tuple[float, dict]] = []
        self._lock = threading.Lock()
        self._cancel = self.client.on_stats(self._on)

    def _on(self, stats: dict) -> None:
        with self._lock:
            self.samples.append((time.monotonic(), stats))

    def latest(self) -> dict:
        with self._lock:
            return self.samples[-1][1] if self.samples else {}

    def close(self) -> None:
        self._cancel()
        self.client.close()


# ------------------------------------------------------------------------------------------------
# One run


def run_load(spec: LoadSpec, endpoint: str, server_id: str | None, server: ServerProcess | None,
             stats: StatsWatch) -> tuple[Report, list[ClientResult], list[tuple[float, dict]]]:
    ctx = mp.get_context("spawn")
    ready = [ctx.Event() for _ in range(spec.clients)]
    go, stop = ctx.Event(), ctx.Event()
    progress = [ctx.Value("l", 0, lock=False) for _ in range(spec.clients)]
    results = ctx.Queue()
    procs = [ctx.Process(target=_client_main, name=f"loadtest-client-{i}",
                         args=(i, endpoint, server_id, spec, ready[i], go, stop, progress[i], results))
             for i in range(spec.clients)]
    for p in procs:
        p.start()
    try:
        deadline = time.monotonic() + 120 + 0.5 * spec.total_cloths
        for i, ev in enumerate(ready):
            while not ev.wait(0.5):
                if not procs[i].is_alive() or time.monotonic() > deadline:
                    raise RuntimeError(f"client {i} did not get its {spec.cloths} cloths accepted")
        time.sleep(max(0.5, 2.0 / spec.tick_rate))  # the last submissions' first ticks
        s0, t0 = stats.latest(), time.monotonic()
        cpu0 = server.cpu_seconds() if server else float("nan")
        samples_from = len(stats.samples)
        go.set()
        log.info("load: %d clients x %d cloths of %dx%d for %.1f s", spec.clients, spec.cloths, spec.size,
                 spec.size, spec.seconds)
        next_log = t0 + 1.0
        while any(p.is_alive() for p in procs) and time.monotonic() - t0 < spec.seconds:
            time.sleep(0.1)
            if time.monotonic() >= next_log:
                st = stats.latest()
                ph = st.get("phases", {}).get("tick", {})
                log.info("  %4.1f s: tick %s, missed %s, skipped %s, states received %d, tick mean %.2f ms max %.2f ms",
                         time.monotonic() - t0, st.get("tick"), st.get("missed_ticks", 0) - s0.get("missed_ticks", 0),
                         st.get("skipped_frames", 0) - s0.get("skipped_frames", 0), sum(v.value for v in progress),
                         ph.get("mean_ms", 0.0), ph.get("max_ms", 0.0))
                next_log += 1.0
        elapsed = time.monotonic() - t0
        cpu1 = server.cpu_seconds() if server else float("nan")
        s1 = stats.latest()
        stop.set()
        out: list[ClientResult] = []
        for _ in procs:
            kind, *rest = results.get(timeout=120)
            if kind == "error":
                raise RuntimeError(f"client {rest[0]} failed: {rest[1]}")
            out.append(rest[0])
        for p in procs:
            p.join(30)
    finally:
        stop.set()
        for p in procs:
            if p.is_alive():
                p.terminate()
    lat = np.concatenate([r.latencies_ms for r in out]) if out else np.zeros(0)
    pct = (lambda q: float(np.percentile(lat, q))) if len(lat) else (lambda q: float("nan"))
    d = lambda k: int(s1.get(k, 0)) - int(s0.get(k, 0))  # noqa: E731
    ticks = d("ticks")
    window = stats.samples[samples_from:]
    phases = _phase_means(window)
    server_info = {"phases_ms": phases}
    if server:
        server_info["cpu_percent"] = round(100.0 * (cpu1 - cpu0) / elapsed, 1)
        server_info.update(server.memory_mb())
    report = Report(
        cloths=spec.total_cloths,
        clients=spec.clients,
        cloths_per_client=spec.cloths,
        vertices_per_cloth=spec.size * spec.size,
        iterations=spec.iterations,
        features=list(spec.features),
        encoding=spec.encoding,
        seconds=round(elapsed, 3),
        tick_hz_target=spec.tick_rate,
        tick_hz_achieved=_tick_rate(s0, s1, ticks, elapsed),
        ticks=ticks,
        missed_ticks=d("missed_ticks"),
        skipped_frames=d("skipped_frames"),
        latency_ms={"p50": round(pct(50), 3), "p99": round(pct(99), 3), "max": round(float(lat.max()), 3) if len(lat) else float("nan"),
                    "mean": round(float(lat.mean()), 3) if len(lat) else float("nan")},
        states=int(sum(r.received for r in out)),
        lost=int(sum(r.lost for r in out)),
        duplicated=int(sum(r.duplicated for r in out)),
        out_of_order=int(sum(r.out_of_order for r in out)),
        messages_per_s=round(sum(r.received for r in out) / elapsed, 1),
        bytes_per_s=round(sum(r.bytes for r in out) / elapsed, 1),
        send_errors=int(sum(r.send_errors for r in out)),
        server=server_info,
        host=f"{platform.node()} {os.cpu_count()} cores",
        bundle=spec.bundle,
        clients_cpu_percent=round(100.0 * sum(r.cpu_s for r in out) / elapsed, 1) if elapsed > 0 else float("nan"),
    )
    return report, out, window


def _tick_rate(s0: dict, s1: dict, ticks: int, elapsed: float) -> float:
    """Ticks per second between two stats publications, over the server's own timestamps of
    those publications (the load's window is measured on the client side and does not line up
    with the 0.5 s stats windows)."""
    span = (int(s1.get("time_ns", 0)) - int(s0.get("time_ns", 0))) / 1e9
    if span > 0 and ticks > 0:
        return round(ticks / span, 2)
    return round(ticks / elapsed, 2) if elapsed > 0 else 0.0


def _phase_means(window: list[tuple[float, dict]]) -> dict[str, dict[str, float]]:
    """Mean and max milliseconds per phase over the stats windows of the run."""
    acc: dict[str, list[tuple[float, float, float]]] = {}
    for _, st in window:
        for name, ph in st.get("phases", {}).items():
            acc.setdefault(name, []).append((ph.get("count", 0), ph.get("mean_ms", 0.0), ph.get("max_ms", 0.0)))
    out = {}
    for name, rows in acc.items():
        n = sum(c for c, _, _ in rows)
        if n:
            out[name] = {"mean": round(sum(c * m for c, m, _ in rows) / n, 3),
                         "max": round(max(mx for _, _, mx in rows), 3)}
    return out


# ------------------------------------------------------------------------------------------------
# Output


def print_report(r: Report) -> None:
    lat = r.latency_ms
    print(f"load: {r.clients} clients x {r.cloths_per_client} cloths = {r.cloths} cloths of {r.vertices_per_cloth} "
          f"vertices, {r.iterations} iterations, features {r.features or 'none'}, {r.encoding}, "
          f"{'bundles + batch control' if r.bundle else 'per-cloth states and controls'}")
    print(f"  ticks: {r.tick_hz_achieved:.2f} Hz achieved of {r.tick_hz_target:g} Hz; missed {r.missed_ticks}, "
          f"coalesced {r.skipped_frames}")
    print(f"  latency ms: p50 {lat['p50']:.2f}  p99 {lat['p99']:.2f}  max {lat['max']:.2f}")
    print(f"  states: {r.states} received, {r.lost} lost, {r.duplicated} duplicated, {r.out_of_order} out of order; "
          f"{r.messages_per_s:.0f} msg/s, {r.bytes_per_s / 1e6:.2f} MB/s; control errors {r.send_errors}")
    ph = r.server.get("phases_ms", {})
    if ph:
        print("  server ms per tick (mean/max): " + ", ".join(f"{k} {v['mean']:.2f}/{v['max']:.2f}" for k, v in ph.items()))
    if "cpu_percent" in r.server:
        print(f"  server CPU {r.server['cpu_percent']:.0f}%, RSS {r.server.get('rss_mb', float('nan')):.0f} MB "
              f"(peak {r.server.get('peak_rss_mb', float('nan')):.0f} MB); clients CPU {r.clients_cpu_percent:.0f}%")
    print(f"  held: {'yes' if r.held else 'NO'}")


def write_plots(out: Path, report: Report, results: list[ClientResult], window: list[tuple[float, dict]],
                tag: str) -> list[Path]:
    from .imaging import histogram, line_plot

    out.mkdir(parents=True, exist_ok=True)
    lat = np.concatenate([r.latencies_ms for r in results]) if results else np.zeros(0)
    paths = []
    p = out / f"loadtest-{tag}-latency.png"
    histogram(p, lat, bins=60, title=f"State latency, {report.cloths} cloths x {report.vertices_per_cloth} vertices",
              xlabel="server tick -> client receipt (ms)",
              markers={"p50": report.latency_ms["p50"], "p99": report.latency_ms["p99"]})
    paths.append(p)
    if window:
        t0 = window[0][0]
        xs = [t - t0 for t, _ in window]
        series = {}
        for name in ("tick", "solve", "readback", "encode", "publish"):
            ys = [st.get("phases", {}).get(name, {}).get("mean_ms", float("nan")) for _, st in window]
            series[f"{name} mean"] = (xs, ys)
        series["tick max"] = (xs, [st.get("phases", {}).get("tick", {}).get("max_ms", float("nan"))
                                   for _, st in window])
        series["budget (1 tick)"] = (xs, [1000.0 / report.tick_hz_target] * len(xs))
        p = out / f"loadtest-{tag}-ticks.png"
        line_plot(p, series, title=f"Server time per tick phase, {report.cloths} cloths", xlabel="time (s)",
                  ylabel="ms per tick")
        paths.append(p)
    return paths


# ------------------------------------------------------------------------------------------------
# Command


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--clients", type=int, default=4, help="client processes")
    parser.add_argument("--cloths", type=int, default=16, help="cloths per client")
    parser.add_argument("--size", type=int, default=32, help="each cloth is SIZE x SIZE vertices")
    parser.add_argument("--seconds", type=float, default=5.0, help="measured seconds per load")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--substeps", type=int, default=1)
    parser.add_argument("--features", default="", help="comma-separated scene features")
    parser.add_argument("--no-bending", action="store_true", help="structural and shear links only")
    parser.add_argument("--encoding", default="float32", choices=["float32", "float16", "quant16"])
    parser.add_argument("--tick-rate", type=float, default=60.0)
    parser.add_argument("--bundle", action=argparse.BooleanOptionalAction, default=True,
                        help="bundled states and one batch control per client per tick (protocol 1.1); "
                             "--no-bundle: one state and one control per cloth per tick")
    parser.add_argument("--endpoint", default=None, help="target a running server instead of starting one")
    parser.add_argument("--server-id", default=None, help="with --endpoint: which server (default: the one seen)")
    parser.add_argument("--solver", default=None, help="solver of the started server")
    parser.add_argument("--device", default=None, help="OpenCL device of the started server")
    parser.add_argument("--server-arg", action="append", default=[], help="extra argument for drape serve")
    parser.add_argument("--find-knee", action="store_true", help="double the cloths per client until the load is not held")
    parser.add_argument("--max-cloths", type=int, default=8192, help="--find-knee stops here (total cloths)")
    parser.add_argument("--json", type=Path, default=None, help="write the report(s) here")
    parser.add_argument("--out", type=Path, default=Path("out/loadtest"), help="PNG plots go here")


def run(args: argparse.Namespace) -> int:
    spec = LoadSpec(clients=args.clients, cloths=args.cloths, size=args.size, seconds=args.seconds,
                    features=tuple(f for f in args.features.split(",") if f), iterations=args.iterations,
                    substeps=args.substeps, bending=not args.no_bending, encoding=args.encoding,
                    tick_rate=args.tick_rate, bundle=args.bundle)
    server = None
    if args.endpoint:
        endpoint, server_id = args.endpoint, args.server_id
    else:
        server = ServerProcess(args.tick_rate, args.solver, args.device, args.server_arg)
        endpoint, server_id = server.endpoint, server.server_id
    reports: list[Report] = []
    try:
        stats = StatsWatch(endpoint, server_id)
        try:
            while True:
                report, results, window = run_load(spec, endpoint, server_id, server, stats)
                print_report(report)
                tag = f"{report.cloths}"
                for p in write_plots(args.out, report, results, window, tag):
                    print(f"wrote {p}")
                reports.append(report)
                if not args.find_knee or not report.held or spec.total_cloths * 2 > args.max_cloths:
                    break
                spec = LoadSpec(**{**asdict(spec), "cloths": spec.cloths * 2})
                time.sleep(1.0)  # let the previous clients' cloths go
        finally:
            stats.close()
    finally:
        if server:
            server.stop()
    if args.find_knee:
        held = [r for r in reports if r.held]
        knee = held[-1].cloths if held else 0
        first_bad = next((r for r in reports if not r.held), None)
        why = _why_not_held(first_bad) if first_bad else "not reached within --max-cloths"
        print(f"knee: {knee} cloths held at {spec.tick_rate:g} Hz; next load ({first_bad.cloths if first_bad else '-'}"
              f" cloths): {why}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        data = [asdict(r) | {"held": r.held} for r in reports]
        args.json.write_text(json.dumps(data if args.find_knee else data[0], indent=1))
        print(f"wrote {args.json}")
    return 0


def _why_not_held(r: Report) -> str:
    why = []
    if r.missed_ticks:
        why.append(f"{r.missed_ticks} missed ticks")
    if r.skipped_frames:
        why.append(f"{r.skipped_frames} frames coalesced")
    if r.lost:
        why.append(f"{r.lost} states lost")
    if r.latency_ms["p99"] > 1000.0 / r.tick_hz_target:
        why.append(f"p99 {r.latency_ms['p99']:.1f} ms > one tick")
    return ", ".join(why) or "held"
