"""The machine's other work during a ``drape chaos`` run (a shared machine's other users): CPU
cores taken by processes that are not this run's, sampled from /proc/stat, so that a missed tick
is judged the server's own only where the host was quiet enough."""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any

import psutil

log = logging.getLogger(__name__)


SAMPLE_S = 0.1  # seconds between samples of the machine's other work
MACHINE_BUSY = 0.5  # cores of CPU work that is not this run's: a stats period with that much is the machine's


class HostLoad:
    """The machine's CPU work that is not this chaos run's, sampled every ``period`` s: the busy
    time of every CPU (``/proc/stat``: user, nice, system, irq, softirq, steal) less that of this
    process and all its descendants (servers, their build children, good clients, routers; the
    reaped ones through their parents' children times), in cores. What a shared machine's other
    users take; the server's own work, however heavy, is not in it (its device threads included).
    One per process (:meth:`shared`), started on first use."""

    _shared: HostLoad | None = None

    def __init__(self, period: float = SAMPLE_S) -> None:
        self.period = period
        self.samples: list[tuple[float, float]] = []  # (monotonic end of the interval, foreign cores over it)
        self._lock = threading.Lock()
        self._me = psutil.Process()
        self._tick = os.sysconf("SC_CLK_TCK")
        threading.Thread(target=self._run, daemon=True, name="host-load").start()

    @classmethod
    def measured(cls) -> bool:
        """Whether this process has sampled the machine's other work (not where /proc is missing)."""
        return cls._shared is not None and bool(cls._shared.samples)

    @classmethod
    def shared(cls) -> HostLoad:
        if cls._shared is None:
            cls._shared = cls()
        return cls._shared

    def _busy_s(self) -> float:
        with open("/proc/stat") as fh:
            f = [int(x) for x in fh.readline().split()[1:9]]
        return (f[0] + f[1] + f[2] + f[5] + f[6] + f[7]) / self._tick

    def _ours_s(self) -> float:
        total = 0.0
        for p in [self._me, *self._me.children(recursive=True)]:
            try:
                t = p.cpu_times()
            except psutil.Error:
                continue
            total += t.user + t.system + t.children_user + t.children_system
        return total

    def _run(self) -> None:
        try:
            t0, b0, o0 = time.monotonic(), self._busy_s(), self._ours_s()
            while True:
                time.sleep(self.period)
                t1, b1, o1 = time.monotonic(), self._busy_s(), self._ours_s()
                foreign = max(0.0, ((b1 - b0) - (o1 - o0)) / max(t1 - t0, 1e-6))
                with self._lock:
                    self.samples.append((t1, foreign))
                    if len(self.samples) > 36_000:  # an hour
                        del self.samples[:6_000]
                t0, b0, o0 = t1, b1, o1
        except (OSError, ValueError, IndexError):  # no /proc: nothing attributed to the machine
            log.warning("host load not measured here: missed ticks are all counted as the server's")

    def cores(self, t0: float, t1: float, how: Any = max) -> float:
        """``how`` (max, or a mean) of the foreign cores of the intervals that overlap [t0, t1]."""
        with self._lock:
            xs = [f for t, f in self.samples if t0 < t <= t1 + self.period]
        return float(how(xs)) if xs else 0.0
