"""What every ``drape chaos`` scenario stands on: a ``drape serve`` child process with its log in a
file (tracebacks and warnings counted there, RSS sampled with psutil, killed when it passes an RSS
cap), the server's stats publications, good game clients in their own processes recording every
state they receive, and the measurement of a window: tick rate, missed ticks, states lost, worst
gap between states, errors by code, RSS before and after.

Everything talks only to 127.0.0.1; every wait is bounded.
"""

from __future__ import annotations

import itertools
import json
import logging
import multiprocessing as mp
import os
import queue
import signal
import subprocess
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import psutil
import zenoh

from drape.client import protocol as P
from drape.server.tools.procs import ProcessFigures, free_port, serve_command

log = logging.getLogger(__name__)

_RUNS = itertools.count()
GAP_LIMIT_MS = 50.0  # issue 26: no gap over this between a good client's states
WAIT = 180.0  # the longest any start-up or reply is waited for (a loaded 2-core machine; a cold
# kernel cache: drape serve first builds every feature set in a child, build_in_child = "always")


def zenoh_session(endpoint: str) -> zenoh.Session:
    """A plain client-side Zenoh session connected to one loopback endpoint (no scouting), with
    Zenoh's shared memory off: the abusers stand for clients on other hosts, which cannot use it
    (a sender on the same host puts large messages into its 16 MB shared-memory pool, and the
    server maps that pool once per such session: +17 MB of the server's RSS, docs/reliability.md)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", "[]")
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(c)


def reply_outcome(reply: zenoh.Reply) -> str:
    """``ok``, an error code, or ``unparseable`` for an error reply that is not a Drape error map."""
    if reply.ok is not None:
        return "ok"
    if reply.err is None:
        return "unparseable"
    try:
        m = msgpack.unpackb(reply.err.payload.to_bytes(), raw=False)
        return str(m["error"]["code"])
    except Exception:
        return "unparseable"


class ChaosServer:
    """``drape serve`` on a free loopback port, its stderr in ``log_path``."""

    def __init__(
        self,
        out: Path,
        name: str,
        args: Sequence[str] = (),
        connect: Sequence[str] = (),
        rss_limit_mb: float = 4096.0,
        endpoint: str | None = None,
        server_id: str | None = None,
        env: dict[str, str | None] | None = None,
        router: Any = None,
    ) -> None:
        """``env``: environment variables for the server on top of ours (None: removed);
        ``router``: a :class:`~.chaos_router.AuthRouter` the server runs behind (client mode,
        ``--identity keys``; ``endpoint`` is then the router's)."""
        self.server_id = server_id or self.id_of(name)
        self.endpoint = router.endpoint if router is not None else endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.log_path = out / f"{name}-{os.getpid()}-{next(_RUNS)}.log"
        self.rss_limit_mb = rss_limit_mb
        self.killed_for_rss = False
        if router is None:
            self.cmd = serve_command(self.endpoint, self.server_id, "--stats-period", "0.5", "--device", "cpu", *args)
        else:  # listens on nothing: a client of the router
            self.cmd = serve_command(self.endpoint, self.server_id, "--stats-period", "0.5", "--device", "cpu", *args)
            at = self.cmd.index("--listen")
            del self.cmd[at : at + 2]
            self.cmd += router.serve_args(self.server_id)
        for c in connect:
            self.cmd += ["--connect", c]
        log.info("starting %s", " ".join(self.cmd))
        self._log_fh = open(self.log_path, "w")
        environ = dict(os.environ)
        for k, v in (env or {}).items():
            if v is None:
                environ.pop(k, None)
            else:
                environ[k] = v
        self.proc = subprocess.Popen(
            self.cmd, stdout=self._log_fh, stderr=subprocess.STDOUT, start_new_session=True, env=environ
        )
        self.figures = ProcessFigures(self.proc.pid)
        self.stats = StatsWatch(
            self.endpoint, self.server_id, session=None if router is None else router.session(router.watcher)
        )
        self._watch_stop = threading.Event()
        self._watch = threading.Thread(target=self._rss_watch, daemon=True, name=f"rss-{self.server_id}")
        self._watch.start()

    @staticmethod
    def id_of(name: str) -> str:
        """The server id of scenario ``name``'s server (unless one is given)."""
        return f"chaos-{name}-{os.getpid()}"

    def _rss_watch(self) -> None:
        """Sample RSS every 0.2 s; SIGKILL the server when it passes the cap (it would take the machine)."""
        while not self._watch_stop.wait(0.2) and self.alive():
            if self.figures.sample_rss() > self.rss_limit_mb:
                log.error("server %s passed the RSS cap of %.0f MB: killing it", self.server_id, self.rss_limit_mb)
                self.killed_for_rss = True
                self.kill(signal.SIGKILL)

    def wait_ready(self, timeout: float = WAIT) -> None:
        """Until the server published stats twice (it ticks and its session is up)."""
        t_end = time.monotonic() + timeout
        while not self.stats.wait_count(2, 0.5):
            if not self.alive() or time.monotonic() > t_end:
                break
        if not self.stats.wait_count(2, 0):
            raise RuntimeError(
                f"server {self.server_id} did not come up in {timeout:.0f} s "
                f"(exit {self.proc.poll()}); log: {self.log_path}"
            )

    def alive(self) -> bool:
        return self.proc.poll() is None

    def rss_mb(self) -> float:
        return self.figures.sample_rss() if self.alive() else float("nan")

    def log_counts(self) -> dict[str, int]:
        """Lines of the server's log containing 'Traceback', ' WARNING ' and ' ERROR '."""
        counts = {"tracebacks": 0, "warnings": 0, "errors": 0}
        try:
            with open(self.log_path, errors="replace") as fh:
                for line in fh:
                    counts["tracebacks"] += "Traceback" in line
                    counts["warnings"] += "WARNING" in line
                    counts["errors"] += "ERROR" in line
        except OSError:
            pass
        return counts

    def kill(self, sig: int) -> None:
        if self.alive():
            os.killpg(self.proc.pid, sig)

    def stop(self, grace: float = 15.0) -> None:
        self._watch_stop.set()
        self.stats.close()
        if self.alive():
            self.kill(signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                log.warning("server %s did not stop in %.0f s: killing it", self.server_id, grace)
                self.kill(signal.SIGKILL)
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            pass
        self._log_fh.close()


class StatsWatch:
    """A server's stats publications (msgpack maps) with the monotonic time they arrived."""

    def __init__(
        self, endpoint: str, server_id: str, namespace: str = P.DEFAULT_NAMESPACE, session: zenoh.Session | None = None
    ) -> None:
        self.session = session if session is not None else zenoh_session(endpoint)
        self.samples: list[tuple[float, dict[str, Any]]] = []
        self._cond = threading.Condition()
        self._sub = self.session.declare_subscriber(P.Keys(namespace).stats(server_id), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            stats = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
        except Exception:
            return
        with self._cond:
            self.samples.append((time.monotonic(), stats))
            self._cond.notify_all()

    def wait_count(self, n: int, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.samples) >= n, timeout)

    def next(self, timeout: float = 5.0) -> dict[str, Any] | None:
        """The next publication after now (None when none came: the server is stalled or gone)."""
        with self._cond:
            n = len(self.samples)
            if self._cond.wait_for(lambda: len(self.samples) > n, timeout):
                return self.samples[-1][1]
        return None

    def latest(self) -> dict[str, Any]:
        with self._cond:
            return self.samples[-1][1] if self.samples else {}

    def close(self) -> None:
        try:
            self._sub.undeclare()
            self.session.close()
        except Exception:
            pass


# ---------------------------------------------------------------------------------------------
# Good clients: one process each, the SDK, recording (tick, receive time) of every state.


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


# ---------------------------------------------------------------------------------------------
# The machine's other work

MACHINE_BUSY = 0.5  # cores of CPU work that is not this run's: a stats period with that much is the machine's


class HostLoad:
    """The machine's CPU work that is not this chaos run's, sampled every ``period`` s: the busy
    time of every CPU (``/proc/stat``: user, nice, system, irq, softirq, steal) less that of this
    process and all its descendants (servers, their build children, good clients, routers; the
    reaped ones through their parents' children times), in cores. What a shared machine's other
    users take; the server's own work, however heavy, is not in it (its device threads included).
    One per process (:meth:`shared`), started on first use."""

    _shared: HostLoad | None = None

    def __init__(self, period: float = 0.1) -> None:
        self.period = period
        self.samples: list[tuple[float, float]] = []  # (monotonic end of the interval, foreign cores over it)
        self._lock = threading.Lock()
        self._me = psutil.Process()
        self._tick = os.sysconf("SC_CLK_TCK")
        threading.Thread(target=self._run, daemon=True, name="host-load").start()

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


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


# ---------------------------------------------------------------------------------------------
# A measured window


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
