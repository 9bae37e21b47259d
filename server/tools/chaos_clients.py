"""``drape chaos``'s good game clients: one process each, the SDK, one small cloth, recording
(tick, receive time) of every state it receives; a window of them measured: states, lost, rate,
worst gap and the gaps over ``GAP_LIMIT_MS``."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .chaos_harness import GAP_LIMIT_MS, WAIT

log = logging.getLogger(__name__)


def _good_client_main(
    endpoint: str,
    server_id: str,
    client_id: str,
    cloths: int,
    size: int,
    records: Any,
    ready: Any,
    stop: Any,
    sdk: dict[str, Any] | None = None,
) -> None:
    logging.basicConfig(level=logging.WARNING)
    from drape.client import DrapeClient, DrapeError

    def submit(client: Any, j: int) -> Any:
        """Like a game: retry (bounded) while the server says "later" (overloaded, busy)."""
        t_end = time.monotonic() + WAIT
        while True:
            try:
                return client.submit_grid(size, size, origin=(1.5 * j, 1.0, 0.0), pinned=[0, size - 1])
            except DrapeError as e:
                if e.code not in ("overloaded", "busy") or time.monotonic() > t_end:
                    raise
                time.sleep(0.5)

    try:
        kw = {"client_id": client_id, **(sdk or {})}  # sdk: an authenticated deployment's (chaos_router)
        with DrapeClient(endpoint, server_id=server_id, timeout=WAIT, **kw) as client:
            handles = []
            for j in range(cloths):
                h = submit(client, j)
                h.on_state(lambda st, j=j: records.put((j, int(st.tick), time.monotonic())))
                handles.append(h)
            records.put(("ready", [h.id for h in handles], client.client_id, time.monotonic()))
            ready.set()
            stop.wait()
            # where each cloth is served at the end (a failover may move it to another server)
            records.put(
                (
                    "where",
                    [str(getattr(h, "server_id", None) or client.server_id) for h in handles],
                    client_id,
                    time.monotonic(),
                )
            )
            client.close(remove=False)
    except BaseException as e:  # report, never hang the parent
        records.put(("error", repr(e), client_id, time.monotonic()))


@dataclass
class StateLog:
    """States one good client received: per cloth index, (tick, receive time) pairs."""

    ticks: dict[int, list[tuple[int, float]]] = field(default_factory=dict)
    cloth_ids: list[str] = field(default_factory=list)
    where: list[str] = field(default_factory=list)  # the server of each cloth when the client stopped
    error: str | None = None


class GoodClient:
    """A game client process holding ``cloths`` small cloths on one server and receiving every state."""

    def __init__(
        self,
        endpoint: str,
        server_id: str,
        name: str,
        cloths: int = 1,
        size: int = 16,
        sdk: dict[str, Any] | None = None,
    ) -> None:
        """``sdk``: more ``DrapeClient`` arguments (an authenticated deployment's, whose
        ``client_id`` must then be :meth:`id_of` ``("good", name)``)."""
        self._start(_good_client_main, "good", endpoint, server_id, name, cloths, size, sdk)

    @staticmethod
    def id_of(kind: str, name: str) -> str:
        """The client id of a client process of ``kind`` for scenario ``name``."""
        return f"{kind}-{name}-{os.getpid()}"

    def _start(
        self,
        target: Any,
        kind: str,
        where: Any,
        server_id: str | None,
        name: str,
        cloths: int,
        size: int,
        sdk: dict[str, Any] | None = None,
    ) -> None:
        """Start the client process ``target(where, server_id, client_id, cloths, size, records,
        ready, stop[, sdk=])`` and the thread draining its records."""
        ctx = mp.get_context("spawn")
        self.client_id = self.id_of(kind, name)
        self.records = ctx.Queue()
        self.ready, self.stop_event = ctx.Event(), ctx.Event()
        self.log = StateLog()
        self._lock = threading.Lock()
        self.proc = ctx.Process(
            target=target,
            name=self.client_id,
            daemon=True,
            args=(where, server_id, self.client_id, cloths, size, self.records, self.ready, self.stop_event),
            kwargs={} if sdk is None else {"sdk": sdk},
        )
        self.proc.start()
        self._drain = threading.Thread(target=self._drain_loop, daemon=True)
        self._drain.start()

    def _record(self, rec: tuple[Any, ...]) -> bool:
        """A record kind of a subclass's process (called under the lock): True when taken."""
        return False

    def _drain_loop(self) -> None:
        while True:
            try:
                rec = self.records.get(timeout=0.5)
            except queue.Empty:
                if not self.proc.is_alive() and self.records.empty():
                    return
                continue
            except (EOFError, OSError, ValueError):
                return
            with self._lock:
                if self._record(rec):
                    continue
                if rec[0] == "ready":
                    self.log.cloth_ids = list(rec[1])
                elif rec[0] == "where":
                    self.log.where = list(rec[1])
                elif rec[0] == "error":
                    self.log.error = rec[1]
                else:
                    self.log.ticks.setdefault(rec[0], []).append((rec[1], rec[2]))

    def wait_ready(self, timeout: float = WAIT) -> None:
        t_end = time.monotonic() + timeout
        while not self.ready.wait(0.25):
            if self.log.error is not None or not self.proc.is_alive() or time.monotonic() > t_end:
                break
        if not self.ready.is_set():
            why = self.log.error or (
                f"its process exited with {self.proc.exitcode}"
                if not self.proc.is_alive()
                else f"not ready in {timeout:.0f} s"
            )
            raise RuntimeError(f"good client {self.client_id}: {why}")

    def window(self, t0: float, t1: float) -> dict[str, Any]:
        """States received in [t0, t1): count, ticks covered, lost (gaps), worst gap between receipts."""
        with self._lock:
            per = {j: [(k, t) for k, t in v if t0 <= t < t1] for j, v in self.log.ticks.items()}
        received = lost = 0
        worst_gap = 0.0
        rates = []
        gaps: list[tuple[float, float]] = []  # (from, to) of every gap over GAP_LIMIT_MS
        lost_spans: list[tuple[float, float, int]] = []  # (from, to, states) of every run of lost states
        for j in range(len(self.log.cloth_ids)):
            v = per.get(j, [])
            if not v:
                worst_gap = max(worst_gap, t1 - t0)
                gaps.append((t0, t1))
                rates.append(0.0)
                continue
            ticks = np.unique([k for k, _ in v])
            times = np.asarray([t0] + sorted(t for _, t in v) + [t1])
            received += len(ticks)
            lost += int(ticks[-1] - ticks[0] + 1 - len(ticks))
            first: dict[int, float] = {}  # each tick's first receipt: a lost run of ticks lies between two of them
            for k, t in sorted(v, key=lambda kt: kt[1]):
                first.setdefault(k, t)
            for a, b in zip(ticks[:-1], ticks[1:], strict=True):
                if b - a > 1:
                    lost_spans.append((first[int(a)], first[int(b)], int(b - a - 1)))
            d = np.diff(times)
            worst_gap = max(worst_gap, float(np.max(d)))
            gaps += [(float(times[i]), float(times[i + 1])) for i in np.flatnonzero(d > GAP_LIMIT_MS / 1000)]
            rates.append(len(ticks) / max(t1 - t0, 1e-9))
        return {
            "states": received,
            "lost": lost,
            "worst_gap_ms": round(1000 * worst_gap, 1),
            "rate_hz": round(float(min(rates)) if rates else 0.0, 1),
            "gaps": gaps,
            "lost_spans": lost_spans,
        }

    def last_receipt(self, cloth: int) -> float:
        with self._lock:
            v = self.log.ticks.get(cloth, [])
            return v[-1][1] if v else float("-inf")

    def outage(self, cloth: int, t: float, settle: float = 0.5) -> float | None:
        """Seconds without a state around a fault at ``t``: the longest interval between successive
        receipts from the last one before ``t`` to the first one later than ``t + settle`` (states
        in flight at the fault arrive within ``settle``). None when no state came after that."""
        with self._lock:
            times = sorted(tr for _, tr in self.log.ticks.get(cloth, []))
        before = [x for x in times if x <= t]
        after = [x for x in times if x > t + settle]
        if not after:
            return None
        span = ([before[-1]] if before else [t]) + [x for x in times if t < x <= after[0]]
        return float(np.max(np.diff(span))) if len(span) > 1 else 0.0

    def first_receipt_after(self, cloth: int, t: float) -> float | None:
        with self._lock:
            for _, tr in self.log.ticks.get(cloth, []):
                if tr >= t:
                    return tr
        return None

    def close(self) -> None:
        self.stop_event.set()
        self.proc.join(10)
        self._drain.join(2)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5)
