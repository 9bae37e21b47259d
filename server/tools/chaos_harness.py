"""What every ``drape chaos`` scenario stands on: a ``drape serve`` child process with its log in a
file (tracebacks and warnings counted there, RSS sampled with psutil, killed when it passes an RSS
cap), the server's stats publications, plain Zenoh sessions and reply outcomes. The good game
clients are :mod:`.chaos_clients`, the machine's other load :mod:`.chaos_hostload`, a measured
window :mod:`.chaos_window`.

Everything talks only to 127.0.0.1; every wait is bounded.
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import signal
import subprocess
import threading
import time
import urllib.request
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgpack
import zenoh
from prometheus_client.parser import text_string_to_metric_families

from drape.client import protocol as P
from drape.server.service.process.metrics import LABELLED
from drape.server.tools.procs import ProcessFigures, free_port, serve_command

log = logging.getLogger(__name__)

_RUNS = itertools.count()
# the /metrics families of ChaosServer.build_counts: family -> its key there (its label: metrics.LABELLED)
BUILD_FAMILIES = {"drape_kernel_builds": "kernel_builds", "drape_build_child_cloths": "build_child"}
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
        metrics: bool = False,
    ) -> None:
        """``env``: environment variables for the server on top of ours (None: removed);
        ``router``: a :class:`~.chaos_router.AuthRouter` the server runs behind (client mode,
        ``--identity keys``; ``endpoint`` is then the router's); ``metrics``: its operator
        listener on a free loopback port (:meth:`build_counts`)."""
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
        self.metrics_url: str | None = None
        if metrics:
            listen = f"127.0.0.1:{free_port()}"
            self.cmd += ["--metrics-listen", listen]
            self.metrics_url = f"http://{listen}/metrics"
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

    def build_counts(self) -> dict[str, dict[str, int]]:
        """The server's kernel builds by the thread that built them (``kernel_builds``: main, cook,
        tick...) and the cloths its build child took by outcome (``build_child``: ran, failed,
        memory_killed), from its ``/metrics`` (a server started with ``metrics=True``): counted
        events, whatever the machine's pace."""
        if self.metrics_url is None:
            raise RuntimeError("the server was started without metrics=True")
        with urllib.request.urlopen(self.metrics_url, timeout=30.0) as r:
            text = r.read().decode()
        out: dict[str, dict[str, int]] = {"kernel_builds": {}, "build_child": {}}
        for fam in text_string_to_metric_families(text):
            if fam.name in BUILD_FAMILIES:
                key, label = BUILD_FAMILIES[fam.name], LABELLED[fam.name][0]
                for sample in fam.samples:
                    if sample.name.endswith("_total"):
                        out[key][sample.labels[label]] = int(sample.value)
        return out

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
