"""The operator side of a running server: an HTTP listener with ``/metrics`` (Prometheus),
``/healthz`` and ``/readyz``, and systemd's notify protocol (READY=1, WATCHDOG=1, STOPPING=1).

``ops = start(server, config)`` once ``server.start()`` returned; ``ops.stop()`` before
``server.stop()``. It starts two small daemon threads and never touches the tick loop:

- the **listener** (``config.metrics_listen``, ``HOST:PORT``; none when it is None) answers
  ``/metrics`` from drape.server.service.process.metrics at scrape time, ``/healthz`` with 200 while the
  process serves HTTP at all, and ``/readyz`` with 200 only when the device is built, the Zenoh
  session is up and the tick counter advanced within ``2 tick periods + slack``, else 503 and
  the reason;
- the **watch** samples ``server.tick`` ten times a second (an attribute read) to know
  when it last advanced, and under systemd (``NOTIFY_SOCKET``) sends READY=1 once and WATCHDOG=1
  every half ``WatchdogSec`` only if the tick counter advanced since the previous ping, so a
  wedged tick loop stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from prometheus_client.exposition import choose_encoder

from ..config import ServerConfig, parse_listen
from .metrics import registry

log = logging.getLogger(__name__)

DEFAULT_SLACK_S = 0.5  # on top of 2 tick periods before /readyz says the ticks stalled
WATCH_INTERVAL_S = 0.1  # between two looks at the tick counter (well inside the slack)


# ---------------------------------------------------------------------------------------------
# systemd notify


def sd_notify(message: str, env: Mapping[str, str] | None = None) -> bool:
    """Send one sd_notify datagram (``READY=1``, ``WATCHDOG=1``...) to ``$NOTIFY_SOCKET``;
    False when there is no such socket (not under systemd) or it cannot be reached."""
    path = (os.environ if env is None else env).get("NOTIFY_SOCKET")
    if not path:
        return False
    if path.startswith("@"):  # Linux abstract namespace
        path = "\0" + path[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.connect(path)
            s.sendall(message.encode())
        return True
    except OSError as e:
        log.warning("sd_notify %r to %r failed: %s", message, path, e)
        return False


def watchdog_interval(env: Mapping[str, str] | None = None) -> float | None:
    """Half of systemd's ``WatchdogSec`` (``$WATCHDOG_USEC``) when the watchdog is on for this
    process, else None."""
    e: Mapping[str, str] = os.environ if env is None else env
    usec = e.get("WATCHDOG_USEC")
    pid = e.get("WATCHDOG_PID")
    if not usec or (pid and pid.isdigit() and int(pid) != os.getpid()):
        return None
    try:
        return max(0.001, int(usec) / 2e6)
    except ValueError:
        return None


# ---------------------------------------------------------------------------------------------
# Readiness


@dataclass(frozen=True)
class Readiness:
    ready: bool
    reason: str
    age_s: float = 0.0  # seconds since the tick counter last advanced


class TickWatch:
    """When the server's tick counter last advanced, from samples of ``server.tick``."""

    def __init__(self, server: Any, slack_s: float = DEFAULT_SLACK_S, clock: Callable[[], float] = time.monotonic):
        self.server = server
        self.clock = clock
        self.stall_s = 2.0 * server.config.dt + slack_s
        self._lock = threading.Lock()
        self._tick = server.tick
        self._advanced_at = clock()

    def sample(self) -> tuple[int, float]:
        """(tick, seconds since it last advanced)."""
        tick, now = self.server.tick, self.clock()
        with self._lock:
            if tick != self._tick:
                self._tick, self._advanced_at = tick, now
            return tick, now - self._advanced_at

    def readiness(self) -> Readiness:
        s = self.server
        tick, age = self.sample()
        if getattr(s, "failure", None) is not None:
            return Readiness(False, f"tick loop failed: {s.failure}", age)
        if getattr(s, "device_name", "?") == "?":  # set once the World has built its device
            return Readiness(False, "device not built", age)
        if not s.running:
            return Readiness(False, "zenoh session not up (starting or stopping)", age)
        if age > self.stall_s:
            return Readiness(False, f"tick {tick} has not advanced for {age:.2f} s (limit {self.stall_s:.2f} s)", age)
        return Readiness(True, f"ticking: tick {tick}", age)

    def probe(self) -> tuple[bool, float]:
        """(ready, seconds since the tick counter advanced): the readiness gauges' source."""
        r = self.readiness()
        return r.ready, r.age_s


# ---------------------------------------------------------------------------------------------
# HTTP


class _Handler(BaseHTTPRequestHandler):
    server: _HTTPServer
    protocol_version = "HTTP/1.1"

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        ops = self.server.ops
        path = self.path.split("?", 1)[0]
        try:
            if path == "/metrics":
                encoder, content_type = choose_encoder(self.headers.get("Accept", ""))
                self._send(200, encoder(ops.registry), content_type)
            elif path == "/healthz":
                self._send(200, b"ok\n")
            elif path == "/readyz":
                r = ops.watch.readiness()
                self._send(200 if r.ready else 503, (r.reason + "\n").encode())
            else:
                self._send(404, b"not found: try /metrics, /healthz or /readyz\n")
        except Exception as e:  # a failing scrape must say so, not kill the listener
            log.exception("answering %s failed", path)
            self._send(500, f"internal error: {type(e).__name__}: {e}\n".encode())

    def _send(self, status: int, body: bytes, content_type: str = "text/plain; charset=utf-8") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's name)
        log.debug("%s %s", self.address_string(), format % args)


class _HTTPServer(ThreadingHTTPServer):
    daemon_threads = True
    ops: Ops


class _HTTPServer6(_HTTPServer):
    address_family = socket.AF_INET6


def _http_server(listen: str) -> _HTTPServer:
    host, port = parse_listen(listen)
    return (_HTTPServer6 if ":" in host else _HTTPServer)((host, port), _Handler)


# ---------------------------------------------------------------------------------------------
# The whole


class Ops:
    """The listener and the watch of one server; see the module docstring."""

    def __init__(
        self,
        server: Any,
        config: ServerConfig | None = None,
        *,
        slack_s: float = DEFAULT_SLACK_S,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.server = server
        self.config = config or server.config
        self.env = dict(os.environ if env is None else env)
        self.watch = TickWatch(server, slack_s)
        self.registry = registry(server, namespace=self.config.namespace, readiness=self.watch.probe)
        self.watchdog_s = watchdog_interval(self.env)
        self.notify = bool(self.env.get("NOTIFY_SOCKET"))
        self.pings = 0  # WATCHDOG=1 sent
        self._http: _HTTPServer | None = None
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    @property
    def address(self) -> tuple[str, int] | None:
        """The listener's bound (host, port) (port 0 in the configuration picks a free one)."""
        return None if self._http is None else self._http.server_address[:2]  # type: ignore[return-value]

    @property
    def url(self) -> str | None:
        if self.address is None:
            return None
        host, port = self.address
        return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"

    def start(self) -> Ops:
        sid = self.config.server_id
        if self.watchdog_s is not None and 2 * self.watchdog_s < 2 * self.server.config.dt:
            log.warning(
                "WatchdogSec (%.1f s) is shorter than two tick periods (%.1f s): systemd will restart a "
                "healthy server; raise WatchdogSec",
                2 * self.watchdog_s,
                2 * self.server.config.dt,
            )
        if self.config.metrics_listen is not None:
            try:
                self._http = _http_server(self.config.metrics_listen)
            except OSError as e:
                raise OSError(
                    e.errno, f"cannot listen on metrics_listen {self.config.metrics_listen!r}: {e.strerror or e}"
                ) from None
            self._http.ops = self
            t = threading.Thread(
                target=self._http.serve_forever,
                kwargs={"poll_interval": 0.2},
                name=f"drape-ops-http-{sid}",
                daemon=True,
            )
            self._threads.append(t)
            t.start()
            log.info("operator endpoints on %s: /metrics /healthz /readyz", self.url)
        t = threading.Thread(target=self._run_watch, name=f"drape-ops-watch-{sid}", daemon=True)
        self._threads.append(t)
        t.start()
        if self.notify:
            self._notify(f"READY=1\nSTATUS=serving {sid}, {self.config.tick_rate:g} Hz\nMAINPID={os.getpid()}")
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Say STOPPING=1 to systemd, close the listener, end the threads. Idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._http is not None:
            self._http.shutdown()
            self._http.server_close()
        for t in self._threads:
            t.join(timeout)
        if self.notify:  # after the watch ended, so no WATCHDOG=1 follows it
            self._notify("STOPPING=1")

    def __enter__(self) -> Ops:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _notify(self, message: str) -> bool:
        return sd_notify(message, self.env)

    def _run_watch(self) -> None:
        interval = WATCH_INTERVAL_S if self.watchdog_s is None else min(WATCH_INTERVAL_S, self.watchdog_s / 2)
        last_ping_tick = self.server.tick
        next_ping = time.monotonic() + (self.watchdog_s or 0.0)
        stalled = False
        while not self._stop.wait(interval):
            tick, age = self.watch.sample()
            if self.server.running and (age > self.watch.stall_s) != stalled:
                stalled = not stalled
                if stalled:
                    where = _tick_stack()
                    log.warning("tick %d has not advanced for %.2f s; the tick thread is at:\n%s", tick, age, where)
                else:
                    log.info("ticking again at tick %d", tick)
            if self.watchdog_s is not None and time.monotonic() >= next_ping:
                next_ping = time.monotonic() + self.watchdog_s
                if tick != last_ping_tick and self.server.running:
                    last_ping_tick = tick
                    if self._notify("WATCHDOG=1"):
                        self.pings += 1


def _tick_stack() -> str:
    """Where the server's tick thread is now (the innermost frames), for a stalled tick's log line:
    what held it is the first thing an operator needs."""
    frames = sys._current_frames()
    for t in threading.enumerate():
        if t.name.startswith("drape-tick-") and t.ident in frames:
            return "".join(traceback.format_stack(frames[t.ident], limit=8))
    return "(no tick thread)"


def start(server: Any, config: ServerConfig | None = None, **kw: Any) -> Ops:
    """Start the operator endpoints and systemd notifications of a started server."""
    return Ops(server, config, **kw).start()
