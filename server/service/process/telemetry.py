"""The server's timers: one PhaseTimer per tick phase, the single source of the phase figures in
the Zenoh stats and of the tick-phase histograms an operator scrapes.

A PhaseTimer keeps a cumulative count, sum and fixed-bucket histogram (never reset, as Prometheus
expects) and a window (mean and max since the last stats publication, reset by it). ``add`` is a
few additions under a lock: cheap enough for every phase of every tick.

The phases (ticks are pipelined, drape.server.service.tick.ticker): ``apply`` the tick thread's
commands and reclaims; ``solve`` the device's time from the start of a step to the end of its
readback (OpenCL profiling timestamps; the host's wait where the queue has none); ``readback``
the tick thread's wait for the previous step's readback plus its non-finite check (near zero
while the device keeps up); ``encode`` and ``publish`` the publisher thread's encoding and puts
of one frame; ``tick`` the tick thread's own work per tick.
"""

from __future__ import annotations

import bisect
import threading

PHASES = ("apply", "solve", "readback", "encode", "publish", "tick")

#: Upper bounds of the phase-duration histogram buckets, in seconds (+Inf is implied): fine
#: around one 60 Hz tick (16.7 ms), coarse beyond.
BUCKETS_S: tuple[float, ...] = (
    0.0001,
    0.00025,
    0.0005,
    0.001,
    0.002,
    0.004,
    0.008,
    0.012,
    0.0167,
    0.025,
    0.0333,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
)


class PhaseTimer:
    """Count, total, histogram and maximum of one phase's durations: cumulative and since the
    last window."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.count = 0
        self.total = 0.0
        self.buckets = [0] * (len(BUCKETS_S) + 1)  # per bucket (not cumulative); the last is +Inf
        self.w_count = 0
        self.w_total = 0.0
        self.w_max = 0.0

    def add(self, seconds: float) -> None:
        i = bisect.bisect_left(BUCKETS_S, seconds)
        with self._lock:
            self.count += 1
            self.total += seconds
            self.buckets[i] += 1
            self.w_count += 1
            self.w_total += seconds
            self.w_max = max(self.w_max, seconds)

    def histogram(self) -> tuple[list[tuple[float, int]], float, int]:
        """Cumulative ``[(upper bound, count <= bound), ..., (inf, count)]``, sum and count."""
        with self._lock:
            out, acc = [], 0
            for bound, n in zip((*BUCKETS_S, float("inf")), self.buckets, strict=True):
                acc += n
                out.append((bound, acc))
            return out, self.total, self.count

    def snapshot(self, reset_window: bool) -> dict[str, float]:
        with self._lock:
            out = {
                "mean_ms": 1e3 * self.w_total / self.w_count if self.w_count else 0.0,
                "max_ms": 1e3 * self.w_max,
                "count": self.w_count,
                "total_mean_ms": 1e3 * self.total / self.count if self.count else 0.0,
            }
            if reset_window:
                self.w_count, self.w_total, self.w_max = 0, 0.0, 0.0
            return out
