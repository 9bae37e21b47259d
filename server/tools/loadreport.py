"""What ``drape loadtest`` reports about one load: the figures of the measured window, computed
from two of the server's stats publications (tick counters and timestamps) and the clients'
results, and their outputs: printed summary, markdown table, JSON-ready dicts and plots.

The measured window runs from one stats publication to a later one, both taken after every
client is up and receiving, so start-up (submits, cooking, first publications) never counts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drape.client.protocol.stats import stat_field

from .loadclient import ClientResult

#: The decimated keys' counters of the stats (protocol 1.8, PROTOCOL.md 10) a report carries over
#: its window: states put on ``{key}/every/{k}`` keys, and those of watched decimated keys not put
#: (a publication first watched after its tick's frame was encoded).
RATE_COUNTERS: tuple[str, ...] = tuple(  # stat_field: each a field of the stats table, or KeyError
    stat_field(name).name for name in ("rate_published", "rate_unserved")
)


def achieved_rate(s0: Mapping[str, Any], s1: Mapping[str, Any]) -> float:
    """Ticks per second between two stats publications of one server: the difference of their
    tick counters over the difference of their server timestamps."""
    for name, s in (("first", s0), ("second", s1)):
        missing = [k for k in ("ticks", "time_ns") if k not in s]
        if missing:
            raise ValueError(f"{name} stats publication lacks {', '.join(missing)}")
    span_s = (int(s1["time_ns"]) - int(s0["time_ns"])) / 1e9
    ticks = int(s1["ticks"]) - int(s0["ticks"])
    if span_s <= 0:
        raise ValueError(f"the second stats publication is not later than the first ({span_s:.3f} s)")
    if ticks < 0:
        raise ValueError("tick counter went backwards: not the same server run")
    return ticks / span_s


def server_window(
    server: str, s0: Mapping[str, Any], s1: Mapping[str, Any], window: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """One server's figures over a window (two of its stats publications, those in between):
    cloths and vertices at its end, achieved rate, ticks, missed ticks, coalesced frames, the
    bytes it put (None when its stats do not report them), the decimated keys' counters
    (:data:`RATE_COUNTERS`, those its stats report), the mean tick and the window's length on
    its clock."""
    ph = phase_means(window)
    return {
        "server": server,
        "cloths": int(s1.get("cloths", 0)),
        "vertices": int(s1.get("vertices", 0)),
        "hz": round(achieved_rate(s0, s1), 2),
        "ticks": counter_delta(s0, s1, "ticks"),
        "missed_ticks": counter_delta(s0, s1, "missed_ticks"),
        "skipped_frames": counter_delta(s0, s1, "skipped_frames"),
        "published_bytes": counter_delta(s0, s1, "published_bytes") if "published_bytes" in s1 else None,
        "rates": {name: counter_delta(s0, s1, name) for name in RATE_COUNTERS if name in s1},
        "tick_ms": ph.get("tick", {}).get("mean", float("nan")),
        "seconds": (int(s1["time_ns"]) - int(s0["time_ns"])) / 1e9,
    }


def counter_delta(s0: Mapping[str, Any], s1: Mapping[str, Any], key: str) -> int:
    return int(s1.get(key, 0)) - int(s0.get(key, 0))


def rate_counts(per_server: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """``Report.rates``: the servers' windows' decimated-key counters summed (a counter no server
    reports is left out)."""
    out: dict[str, int] = {}
    for p in per_server:
        for name, n in p.get("rates", {}).items():
            out[name] = out.get(name, 0) + int(n)
    return out


def timeline(s0: Mapping[str, Any], window: Sequence[Mapping[str, Any]]) -> list[list[float]]:
    """Per stats period of a window (``s0``, then the publications after it): seconds from the
    window's start to the period's end on the server's clock, and the period's ticks, missed
    ticks and coalesced frames. Tells when misses happen (all at once: a stall; spread out: a
    load the server does not hold)."""
    out, prev = [], s0
    for st in window:
        out.append(
            [
                round((int(st["time_ns"]) - int(s0["time_ns"])) / 1e9, 3),
                counter_delta(prev, st, "ticks"),
                counter_delta(prev, st, "missed_ticks"),
                counter_delta(prev, st, "skipped_frames"),
            ]
        )
        prev = st
    return out


def missed_summary(periods: Sequence[Sequence[float]]) -> str:
    """``timeline``'s missed ticks in words: how many stats periods had any, the worst one."""
    bad = [p for p in periods if p[2]]
    if not bad:
        return "no period with a missed tick"
    worst = max(bad, key=lambda p: p[2])
    return (
        f"missed ticks in {len(bad)} of {len(periods)} stats periods "
        f"(at most {int(worst[2])} in one, ending {worst[0]:.1f} s into the window)"
    )


def phase_means(window: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Mean and max milliseconds per server phase over stats publications (each carries its
    own window's count, mean and max), weighted by count."""
    acc: dict[str, list[tuple[float, float, float]]] = {}
    for st in window:
        for name, ph in st.get("phases", {}).items():
            acc.setdefault(name, []).append((ph.get("count", 0), ph.get("mean_ms", 0.0), ph.get("max_ms", 0.0)))
    out = {}
    for name, rows in acc.items():
        n = sum(c for c, _, _ in rows)
        if n:
            out[name] = {
                "mean": round(sum(c * m for c, m, _ in rows) / n, 3),
                "max": round(max(x for _, _, x in rows), 3),
            }
    return out


def admission_capacity(reports: Sequence[Mapping[str, Any]], loads: Sequence[int], budget_s: float) -> int:
    """The largest load (cloths) the server's admission model admits once it has measured the
    ``loads`` (cloths) of these reports (load test JSON dicts, float32 32x32 or not: vertices are
    taken from each report): each report's phase means become ten steady ticks (tick thread =
    tick - readback, device = solve, publisher = encode + publish). Tells what the model makes of
    a load test's figures, e.g. those of a quiet machine (docs/loadtest.md, session 12)."""
    from drape.server.service.requests.admission_model import MeasuredCost, TickCost

    model = MeasuredCost()
    vpc = 0
    for r in reports:
        if r["cloths"] not in loads:
            continue
        ph = {k: v["mean"] / 1e3 for k, v in r["server"]["phases_ms"].items()}
        vpc = int(r["vertices_per_cloth"])
        cost = TickCost(r["cloths"] * vpc, ph["tick"] - ph["readback"], ph["solve"], ph["encode"] + ph["publish"])
        for _ in range(10):
            model.observe(cost)
    if not vpc:
        raise ValueError(f"no report of {list(loads)} cloths")
    n = 0
    while True:  # the first cloth more that the model refuses (None: admitted on trust)
        got = model.predict((n + 1) * vpc, budget_s)
        if got is not None and max(got.values()) > budget_s:
            return n
        n += 1


@dataclass
class Report:
    cloths: int  # admitted
    offered: int
    refused: dict[str, int]  # refused submits by error code
    clients: int
    vertices_per_cloth: int
    iterations: int
    features: list[str]
    encoding: str
    bundle: bool
    window_ticks: tuple[int, int]  # server ticks lo+1 .. hi
    seconds: float  # the window on the server's clock
    tick_hz_target: float
    tick_hz_achieved: float
    ticks: int
    missed_ticks: int
    skipped_frames: int
    latency_ms: dict[str, float]
    states: int
    expected_states: int
    lost: int
    duplicated: int
    out_of_order: int
    messages_per_s: float
    bytes_per_s: float  # the payload bytes the servers put (a predictive state's real size), else the clients' count
    send_errors: int
    decode_us: dict[str, float]  # per state, per payload (bundle or state), clients' share of one core
    server: dict[str, Any] = field(default_factory=dict)  # phases_ms, cpu_percent, rss_*_mb
    clients_cpu_percent: float = float("nan")
    host: str = ""
    servers: list[dict[str, Any]] = field(default_factory=list)  # several servers: each one's figures
    spread: float = 0.0  # several servers: max / mean - 1 of their cloths (0: even)
    load_average: list[float] = field(default_factory=list)  # the host's 1-minute load at the window's start, end
    affinity: dict[str, str] = field(default_factory=dict)  # CPUs the clients / each server were kept on, if any
    links: dict[str, Any] = field(default_factory=dict)  # issue 21: home links' clients apart (loadlink.py)
    rates: dict[str, int] = field(default_factory=dict)  # 1.8: RATE_COUNTERS over the window, all servers
    timeline: list[list[float]] = field(default_factory=list)  # per stats period: s, ticks, missed, coalesced

    @property
    def served(self) -> bool:
        """The admitted cloths were served: no missed tick, nothing lost or coalesced, p99 within
        one tick."""
        p99 = self.latency_ms.get("p99", float("nan"))
        return (
            self.ticks > 0
            and self.missed_ticks == 0
            and self.lost == 0
            and self.skipped_frames == 0
            and math.isfinite(p99)
            and p99 <= 1000.0 / self.tick_hz_target
        )

    @property
    def held(self) -> bool:
        """The whole load was held: every submit admitted and the admitted cloths served."""
        return self.served and self.cloths == self.offered

    def why_not_held(self) -> str:
        why = []
        if self.refused:
            why.append(", ".join(f"{n} submits refused ({code})" for code, n in sorted(self.refused.items())))
        if self.ticks <= 0:
            why.append("no ticks in the window")
        if self.missed_ticks:
            why.append(f"{self.missed_ticks} missed ticks")
        if self.skipped_frames:
            why.append(f"{self.skipped_frames} frames coalesced")
        if self.lost:
            why.append(f"{self.lost} states lost")
        p99 = self.latency_ms.get("p99", float("nan"))
        if not (math.isfinite(p99) and p99 <= 1000.0 / self.tick_hz_target):
            why.append(f"p99 {p99:.1f} ms > one tick")
        return ", ".join(why) or "held"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self) | {"served": self.served, "held": self.held}


def latency_summary(lat_ms: np.ndarray) -> dict[str, float]:
    if not len(lat_ms):
        return {"p50": float("nan"), "p99": float("nan"), "max": float("nan"), "mean": float("nan")}
    p50, p99 = np.percentile(lat_ms, [50, 99])
    return {
        "p50": round(float(p50), 3),
        "p99": round(float(p99), 3),
        "max": round(float(lat_ms.max()), 3),
        "mean": round(float(lat_ms.mean()), 3),
    }


def decode_summary(results: Sequence[ClientResult], seconds: float) -> dict[str, float]:
    states = sum(r.received for r in results)
    payloads = sum(r.payloads for r in results)
    total = sum(r.decode_s for r in results)
    return {
        "per_state": round(1e6 * total / states, 2) if states else float("nan"),
        "per_payload": round(1e6 * total / payloads, 2) if payloads else float("nan"),
        "cpu_percent": round(100.0 * total / seconds, 1) if seconds > 0 else float("nan"),
    }


# ------------------------------------------------------------------------------------------------
# Output


def print_report(r: Report) -> None:
    lat, ph = r.latency_ms, r.server.get("phases_ms", {})
    refused = ", ".join(f"{n} {code}" for code, n in sorted(r.refused.items())) or "none"
    print(
        f"load: {r.cloths} cloths admitted of {r.offered} offered (refused: {refused}) over {r.clients} clients, "
        f"{r.vertices_per_cloth} vertices, {r.iterations} iterations, features {r.features or 'none'}, {r.encoding}, "
        f"{'bundles + batch control' if r.bundle else 'per-cloth states and controls'}"
    )
    if r.servers:
        print(f"  {len(r.servers)} servers, cloths spread {100 * r.spread:.1f} % (max / mean - 1):")
        for s in r.servers:
            print(
                f"    {s['server']}: {s['cloths']} cloths, {s['vertices']} vertices, {s['hz']:.2f} Hz "
                f"({s['ticks']} ticks), missed {s['missed_ticks']}, coalesced {s['skipped_frames']}, "
                f"tick {s['tick_ms']:.2f} ms"
            )
    else:
        print(f"  window: server ticks {r.window_ticks[0] + 1}..{r.window_ticks[1]} ({r.seconds:.2f} s on the server)")
    print(
        f"  ticks: {r.tick_hz_achieved:.2f} Hz achieved of {r.tick_hz_target:g} Hz ({r.ticks} ticks); "
        f"missed {r.missed_ticks}, coalesced {r.skipped_frames}"
    )
    if r.timeline:
        print(f"  {missed_summary(r.timeline)}")
    print(f"  latency ms: p50 {lat['p50']:.2f}  p99 {lat['p99']:.2f}  max {lat['max']:.2f}")
    print(
        f"  states: {r.states} of {r.expected_states} received, {r.lost} lost, {r.duplicated} duplicated, "
        f"{r.out_of_order} out of order; {r.messages_per_s:.0f} msg/s, {r.bytes_per_s / 1e6:.2f} MB/s; "
        f"control errors {r.send_errors}"
    )
    if r.rates:
        print(f"  {rates_summary(r.rates, r.seconds)}")
    print(
        f"  client decode: {r.decode_us['per_state']:.1f} us per state, {r.decode_us['per_payload']:.1f} us per "
        f"{'bundle' if r.bundle else 'state message'}, {r.decode_us['cpu_percent']:.0f}% of one core in all"
    )
    if ph:
        print(
            "  server ms per tick (mean/max): "
            + ", ".join(f"{k} {v['mean']:.2f}/{v['max']:.2f}" for k, v in ph.items())
        )
    s = r.server
    if "cpu_percent" in s:
        print(
            f"  server CPU {s['cpu_percent']:.0f}%, RSS {s['rss_start_mb']:.0f} -> {s['rss_end_mb']:.0f} MB "
            f"(max {s['rss_max_mb']:.0f} MB); clients CPU {r.clients_cpu_percent:.0f}%"
        )
    if "rss_window_start_mb" in s:
        print(f"  server RSS over the window: {s['rss_window_start_mb']:.0f} -> {s['rss_end_mb']:.0f} MB")
    if r.load_average:
        print(
            f"  host load average (1 min) at the window's start / end: {' / '.join(f'{x:.2f}' for x in r.load_average)}"
        )
    if r.affinity:
        print(f"  kept on CPUs: {'; '.join(f'{k} {v}' for k, v in r.affinity.items())}")
    if r.cloths != r.offered:
        print(f"  admitted cloths served: {'yes' if r.served else 'NO'}")
    print(f"  held: {'yes' if r.held else 'NO (' + r.why_not_held() + ')'}")


def rates_summary(rates: Mapping[str, int], seconds: float) -> str:
    """``Report.rates`` in words: states put on decimated keys (and per second), those unserved."""
    put, unserved = rates.get("rate_published"), rates.get("rate_unserved")
    words = []
    if put is not None:
        per_s = f" ({put / seconds:.0f}/s)" if seconds > 0 else ""
        words.append(f"{put} states put on decimated keys{per_s}")
    if unserved is not None:
        words.append(f"{unserved} of watched decimated keys not served")
    return "decimated rates (1.8): " + ", ".join(words)


COLUMNS = (
    "cloths",
    "offered",
    "refused",
    "encoding",
    "Hz",
    "missed",
    "coalesced",
    "p50 ms",
    "p99 ms",
    "lost",
    "MB/s",
    "solve ms",
    "readback ms",
    "encode ms",
    "publish ms",
    "tick ms",
    "decode us/state",
    "decode us/bundle",
    "server CPU %",
    "RSS MB (start/end/max)",
    "served",
    "held",
)


def markdown_table(reports: Sequence[Report]) -> str:
    """One row per load."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in reports:
        ph = r.server.get("phases_ms", {})
        s = r.server

        def phase(name: str, ph: dict = ph) -> str:
            return f"{ph[name]['mean']:.2f}" if name in ph else "-"

        rss = f"{s['rss_start_mb']:.0f}/{s['rss_end_mb']:.0f}/{s['rss_max_mb']:.0f}" if "rss_max_mb" in s else "-"
        row = [
            r.cloths,
            r.offered,
            sum(r.refused.values()),
            r.encoding,
            f"{r.tick_hz_achieved:.2f}",
            r.missed_ticks,
            r.skipped_frames,
            f"{r.latency_ms['p50']:.2f}",
            f"{r.latency_ms['p99']:.2f}",
            r.lost,
            f"{r.bytes_per_s / 1e6:.1f}",
            phase("solve"),
            phase("readback"),
            phase("encode"),
            phase("publish"),
            phase("tick"),
            f"{r.decode_us['per_state']:.1f}",
            f"{r.decode_us['per_payload']:.1f}",
            f"{s.get('cpu_percent', float('nan')):.0f}",
            rss,
            "yes" if r.served else "**no**",
            "yes" if r.held else "**no**",
        ]
        lines.append("| " + " | ".join(str(v) for v in row) + " |")
    return "\n".join(lines) + "\n"


def write_plots(
    out: Path, report: Report, results: Sequence[ClientResult], window: Sequence[tuple[float, dict]], tag: str
) -> list[Path]:
    """The latency histogram and the server's time per tick phase over the run."""
    from .plots import histogram, line_plot

    lat = np.concatenate([r.latencies_ms for r in results]) if results else np.zeros(0)
    paths = [
        histogram(
            out / f"loadtest-{tag}-latency.png",
            lat,
            title=f"State latency, {report.cloths} cloths x {report.vertices_per_cloth} vertices ({report.encoding})",
            xlabel="server tick -> client receipt (ms)",
            markers={"p50": report.latency_ms["p50"], "p99": report.latency_ms["p99"]},
        )
    ]
    if window:
        t0 = window[0][0]
        xs = [t - t0 for t, _ in window]
        series: dict[str, tuple[list[float], list[float]]] = {}
        for name in ("tick", "solve", "readback", "encode", "publish"):
            series[f"{name} mean"] = (
                xs,
                [st.get("phases", {}).get(name, {}).get("mean_ms", math.nan) for _, st in window],
            )
        series["tick max"] = (xs, [st.get("phases", {}).get("tick", {}).get("max_ms", math.nan) for _, st in window])
        series["budget (1 tick)"] = (xs, [1000.0 / report.tick_hz_target] * len(xs))
        paths.append(
            line_plot(
                out / f"loadtest-{tag}-ticks.png",
                series,
                dashed=("budget (1 tick)",),
                title=f"Server time per tick phase, {report.cloths} cloths ({report.encoding})",
                xlabel="time in the measured window (s)",
                ylabel="ms per tick",
            )
        )
    return paths


def write_summary_plot(path: Path, reports: Sequence[Report]) -> Path:
    """Achieved tick rate and p99 latency against the load (cloths admitted), one line per
    encoding; a load measured twice (--find-knee's second try) counts with its last run."""
    from .plots import stacked_line_plots

    last = {(r.cloths, r.encoding): r for r in reports}
    hz: dict[str, tuple[list[float], list[float]]] = {}
    p99: dict[str, tuple[list[float], list[float]]] = {}
    for (cloths, enc), r in sorted(last.items()):
        for series, y in ((hz, r.tick_hz_achieved), (p99, r.latency_ms["p99"])):
            xs, ys = series.setdefault(enc, ([], []))
            xs.append(cloths)
            ys.append(y)
    xs = sorted({c for c, _ in last})
    target = reports[0].tick_hz_target if reports else 60.0
    hz["target"] = (xs, [target] * len(xs))
    p99["one tick"] = (xs, [1000.0 / target] * len(xs))
    return stacked_line_plots(
        path,
        [("ticks per second achieved", hz), ("p99 latency (ms)", p99)],
        dashed=("target", "one tick"),
        logx=True,
        xlabel="cloths admitted",
        title="Load test: achieved tick rate and p99 latency against the load",
    )
