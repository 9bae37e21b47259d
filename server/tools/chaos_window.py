"""A measured ``drape chaos`` window of one server: the server's figures between two stats
publications (tick rate, missed ticks, errors by code), the good clients' states, lost states and
gaps, the missed ticks and gaps split into the server's own and the machine's
(:mod:`.chaos_hostload`), RSS before, at peak and after, tracebacks and warnings in its log."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .chaos_clients import GoodClient
from .chaos_harness import GAP_LIMIT_MS, WAIT, ChaosServer
from .chaos_hostload import MACHINE_BUSY, SAMPLE_S, HostLoad


def judging() -> dict[str, Any]:
    """The rule that judges a window's missed ticks, lost states and gaps as the server's own, as
    ``drape chaos --help`` says it and its JSON report records it (with whether the machine's
    other work could be measured here at all: where it could not, everything is the server's)."""
    return {
        "rule": (
            f"missed ticks, lost good states and gaps over {GAP_LIMIT_MS:g} ms between good states are judged "
            f"as the server's own only in stats periods (lost states and gaps: their spans) where the machine's "
            f"other processes took under {MACHINE_BUSY} cores at every {SAMPLE_S:g} s sample (/proc/stat less "
            "this run's processes); the rest are the machine's (missed_ticks_machine), reported, not judged"
        ),
        "machine_busy_cores": MACHINE_BUSY,
        "host_sample_s": SAMPLE_S,
        "host_load_measured": HostLoad.measured(),
    }


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def stats_delta(s0: dict[str, Any], s1: dict[str, Any]) -> dict[str, Any]:
    """Server figures between two stats publications: tick rate, missed ticks, errors by code."""
    out: dict[str, Any] = {}
    dt = (s1.get("time_ns", 0) - s0.get("time_ns", 0)) / 1e9
    ticks = s1.get("ticks", 0) - s0.get("ticks", 0)
    out["server_tick_hz"] = round(ticks / dt, 1) if dt > 0 else float("nan")
    for k in ("missed_ticks", "nan_resets", "reclaimed", "skipped_frames"):
        out[k] = s1.get(k, 0) - s0.get(k, 0)
    e0, e1 = s0.get("errors", {}) or {}, s1.get("errors", {}) or {}
    out["errors"] = {c: e1[c] - e0.get(c, 0) for c in sorted(e1) if e1[c] - e0.get(c, 0)}
    return out


def _tick_max_ms(stats: dict[str, Any]) -> float:
    """The longest tick-thread tick (its own work) of a stats period."""
    try:
        return float(stats["phases"]["tick"]["max_ms"])
    except (KeyError, TypeError, ValueError):
        return 0.0


@dataclass
class Window:
    """Start-of-window figures of one server; :meth:`close` measures the window."""

    server: ChaosServer
    t0: float
    stats0: dict[str, Any]
    rss0: float
    log0: dict[str, int]
    n0: int = 0  # stats publications received before the window

    @classmethod
    def open(cls, server: ChaosServer) -> Window:
        HostLoad.shared()
        stats0 = server.stats.next(WAIT) or server.stats.latest()
        return cls(server, time.monotonic(), stats0, server.rss_mb(), server.log_counts(), len(server.stats.samples))

    @staticmethod
    def busy(t0: float, t1: float) -> bool:
        """Whether other processes took ``MACHINE_BUSY`` cores or more at some point in [t0, t1]."""
        return HostLoad.shared().cores(t0, t1) >= MACHINE_BUSY

    def attribute(self, out: dict[str, Any], gaps: list[tuple[float, float]]) -> None:
        """Split the window's missed ticks by stats period, and the good clients' gaps over
        ``GAP_LIMIT_MS``, into the machine's (``MACHINE_BUSY`` cores or more of other work in the
        period or gap, :class:`HostLoad`) and the server's own."""
        host = HostLoad.shared()
        samples = self.server.stats.samples[max(self.n0 - 1, 0) :]
        own = machine = busy_periods = 0
        tick_own = 0.0
        for (ta, sa), (tb, sb) in zip(samples, samples[1:], strict=False):
            busy = self.busy(ta, tb)
            busy_periods += busy
            if not busy:
                tick_own = max(tick_own, _tick_max_ms(sb))
            missed = int(sb.get("missed_ticks", 0)) - int(sa.get("missed_ticks", 0))
            if missed <= 0:
                continue
            if busy:
                machine += missed
            else:
                own += missed
        out["missed_ticks_own"], out["missed_ticks_machine"] = own, machine
        out["tick_max_own_ms"] = round(tick_own, 1)  # the longest tick-thread tick of those periods
        own_gaps = [b - a for a, b in gaps if not self.busy(a, b)]
        out["good_gaps_over_limit"] = len(gaps)
        out["good_worst_gap_own_ms"] = round(1000 * max(own_gaps, default=0.0), 1)
        out["host_other_cores"] = round(host.cores(self.t0, time.monotonic(), _mean), 2)
        # the share of the window's stats periods judged as the machine's: near 1, the window judges little
        out["host_busy_share"] = round(busy_periods / max(len(samples) - 1, 1), 2)
        # the periods whose missed ticks were judged: none, and the window judged none of them
        out["quiet_periods"] = max(len(samples) - 1, 0) - busy_periods

    def close(self, clients: Sequence[GoodClient] = (), settle_s: float = 0.0) -> dict[str, Any]:
        """Measure up to now; then let the server settle ``settle_s`` seconds and sample its RSS."""
        t1 = time.monotonic()
        stats1 = self.server.stats.next(10.0)
        stalled = stats1 is None
        out: dict[str, Any] = {
            "seconds": round(t1 - self.t0, 1),
            "server_alive": self.server.alive(),
            "stats_stalled": stalled,
        }
        out.update(stats_delta(self.stats0, stats1 or self.server.stats.latest()))
        periods = [st for _, st in self.server.stats.samples[self.n0 :]]
        out["tick_max_ms"] = round(max((_tick_max_ms(st) for st in periods), default=0.0), 1)
        gaps: list[tuple[float, float]] = []
        if clients:
            per = [c.window(self.t0, t1) for c in clients]
            out["good_states"] = sum(p["states"] for p in per)
            out["good_lost"] = sum(p["lost"] for p in per)
            out["good_rate_hz"] = min(p["rate_hz"] for p in per)
            out["good_worst_gap_ms"] = max(p["worst_gap_ms"] for p in per)
            gaps = [g for p in per for g in p["gaps"]]
            out["good_lost_own"] = sum(n for p in per for a, b, n in p["lost_spans"] if not self.busy(a, b))
        self.attribute(out, gaps)
        if settle_s > 0:
            time.sleep(settle_s)
        log1 = self.server.log_counts()
        out["tracebacks"] = log1["tracebacks"] - self.log0["tracebacks"]
        out["log_warnings"] = log1["warnings"] - self.log0["warnings"]
        out["rss_before_mb"] = round(self.rss0, 1)
        out["rss_after_mb"] = round(self.server.rss_mb(), 1)
        out["rss_max_mb"] = round(max(self.server.figures.rss_mb or [float("nan")]), 1)
        out["killed_for_rss"] = self.server.killed_for_rss
        return out
