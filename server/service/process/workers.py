"""``drape serve --workers N``: N ``drape serve`` processes sharing one device, run as one daemon
(one GIL each: docs/loadtest.md, issue 10; README "Several server processes on one device").

The supervisor resolves the configuration once and starts each worker with it as flags (its
environment without DRAPE_CONFIG and DRAPE_<FIELD>, so restarted workers run the same settings);
what differs per worker (id, ports, connections, device) is drape.server.service.process.workerplan's.

Supervision: SIGINT/SIGTERM stop every worker with SIGTERM (exit 0 when all stopped with 0, else
1; SIGKILL after STOP_GRACE_S). A worker that exits on its own is restarted under the same id and
endpoints after a back-off (BACKOFF_S doubling to BACKOFF_MAX_S), logged with its status; more than
MAX_RESTARTS within RESTART_WINDOW_S, or a status 2 (bad configuration), and the supervisor stops
the others and exits 1. Workers die with the supervisor (Linux PR_SET_PDEATHSIG). Text log lines
of a worker are prefixed ``[<server id>]`` (JSON lines carry ``server_id``). systemd: the workers
notify the supervisor's own socket; it says READY=1 once all are ready, then WATCHDOG=1 while
every ready worker pings (drape.server.service.process.ops: only while its ticks advance).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import select
import selectors
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from types import FrameType
from typing import IO

from ..config import ServerConfig
from .ops import sd_notify, watchdog_interval
from .workerplan import WorkerSpec, plan, worker_command

log = logging.getLogger(__name__)

RESTART_WINDOW_S = 60.0  # restarts counted over this window; a worker up this long has its back-off reset
MAX_RESTARTS = 5  # restarts (all workers together) within the window before the supervisor gives up
BACKOFF_S = 0.5  # first restart delay, doubled for each consecutive failure of the same worker...
BACKOFF_MAX_S = 30.0  # ...up to this
STOP_GRACE_S = 30.0  # a worker not gone this long after SIGTERM gets SIGKILL
_PR_SET_PDEATHSIG = 1


def worker_env(env: Mapping[str, str], notify_socket: str, watchdog_usec: str | None) -> dict[str, str]:
    """The workers' environment: ``env`` without the configuration's variables (the flags carry
    it) and systemd's, with NOTIFY_SOCKET the supervisor's socket (and the watchdog period)."""
    drop = {"DRAPE_CONFIG", "NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"}
    drop |= {f"DRAPE_{f.name.upper()}" for f in fields(ServerConfig)}
    out = {k: v for k, v in env.items() if k not in drop}
    out["NOTIFY_SOCKET"] = notify_socket
    if watchdog_usec:
        out["WATCHDOG_USEC"] = watchdog_usec
    return out


def _pdeathsig() -> Callable[[], None] | None:
    """A function for the child before exec: SIGTERM when the supervisor dies (Linux prctl
    PR_SET_PDEATHSIG, resolved here in the parent); None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None

    def child() -> None:
        prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)

    return child


def describe_status(rc: int) -> str:
    """``status 1`` or ``signal SIGKILL``, from a Popen return code."""
    try:
        return f"signal {signal.Signals(-rc).name}" if rc < 0 else f"status {rc}"
    except ValueError:
        return f"signal {-rc}"


@dataclass
class Worker:
    """One worker slot: its spec and its current process (None while waiting for a restart)."""

    spec: WorkerSpec
    cmd: list[str]
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    starts: int = 0
    failures: int = 0  # consecutive short-lived runs (back-off exponent)
    restart_at: float | None = None
    ready: bool = False
    last_ping: float = 0.0


@dataclass
class Supervisor:
    """Runs the workers until :meth:`request_stop` (the signal handlers of :meth:`run`) or a give-up.

    One thread: a selector waits on the workers' notifications and (text logs) their stderr.
    ``commands`` (tests) replaces the worker command lines."""

    config: ServerConfig
    specs: list[WorkerSpec]
    commands: Sequence[list[str]] | None = None
    env: Mapping[str, str] = field(default_factory=lambda: dict(os.environ))
    max_restarts: int = MAX_RESTARTS
    restart_window_s: float = RESTART_WINDOW_S
    backoff_s: float = BACKOFF_S
    stop_grace_s: float = STOP_GRACE_S
    stream: IO[str] | None = None  # where prefixed text log lines go (default: sys.stderr)
    workers: list[Worker] = field(init=False)
    restarts: deque[float] = field(init=False, default_factory=deque)
    gave_up: str | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        cmds = self.commands or [worker_command(self.config, s) for s in self.specs]
        self.workers = [Worker(s, list(c)) for s, c in zip(self.specs, cmds, strict=True)]
        self._stop = False
        self._all_ready_said = False
        self._sel = selectors.DefaultSelector()
        self._partial: dict[int, bytes] = {}  # fd -> an unfinished log line
        self._preexec = _pdeathsig()

    def request_stop(self) -> None:
        self._stop = True

    # --- the loop -------------------------------------------------------------------------------
    def run(self) -> int:
        """Start the workers, supervise them, stop them; 0 when all stopped cleanly, else 1."""

        def on_signal(signum: int, frame: FrameType | None) -> None:
            log.info("received %s: stopping %d workers", signal.Signals(signum).name, len(self.workers))
            self._stop = True

        previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        watchdog = watchdog_interval(self.env)
        clean = False
        with tempfile.TemporaryDirectory(prefix="drape-workers-") as tmp:
            path = str(Path(tmp) / "notify")
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            try:
                sock.bind(path)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_PASSCRED, 1)
                sock.setblocking(False)
                self._sel.register(sock, selectors.EVENT_READ, None)
                usec = self.env.get("WATCHDOG_USEC") if watchdog is not None else None
                child_env = worker_env(self.env, path, usec)
                ids = ", ".join(w.spec.server_id for w in self.workers)
                log.info("supervising %d workers: %s", len(self.workers), ids)
                for w in self.workers:
                    self._start(w, child_env)
                next_ping = time.monotonic()
                while not self._stop and self.gave_up is None:
                    self._poll(sock, 0.1)
                    now = time.monotonic()
                    self._reap(now)
                    for w in self.workers:
                        if self.gave_up is None and w.proc is None and w.restart_at is not None and now >= w.restart_at:
                            self._start(w, child_env)
                    if watchdog is not None and now >= next_ping:
                        next_ping = now + watchdog
                        # after READY=1 (systemd's start timeout covers the start), while no ready worker is wedged
                        fresh = all(now - w.last_ping <= 2 * watchdog for w in self.workers if w.ready)
                        if self._all_ready_said and fresh:
                            sd_notify("WATCHDOG=1", self.env)
                sd_notify("STOPPING=1", self.env)
                clean = self._stop_all(sock)
            finally:
                for w in self.workers:  # only after an error of our own: never leave a worker behind
                    if w.proc is not None and w.proc.poll() is None:
                        w.proc.kill()
                        w.proc.wait()
                self._sel.close()
                sock.close()
                for s, h in previous.items():
                    signal.signal(s, h)
        if self.gave_up is not None:
            log.error("gave up: %s; the other workers were stopped", self.gave_up)
            return 1
        return 0 if clean else 1

    def _start(self, w: Worker, env: Mapping[str, str]) -> None:
        text = self.config.log_format == "text"
        w.proc = subprocess.Popen(
            w.cmd,
            env=dict(env),
            start_new_session=True,  # a terminal's Ctrl-C reaches the supervisor only; it stops them in order
            preexec_fn=self._preexec,  # noqa: PLW1509 (one thread: no lock can be held at fork)
            stderr=subprocess.PIPE if text else None,
        )
        w.started_at, w.restart_at, w.ready = time.monotonic(), None, False
        w.starts += 1
        if w.proc.stderr is not None:
            os.set_blocking(w.proc.stderr.fileno(), False)
            self._sel.register(w.proc.stderr, selectors.EVENT_READ, w)
        log.info(
            "worker %s started (pid %d): listen %s, device %s",
            w.spec.server_id,
            w.proc.pid,
            w.spec.listen,
            w.spec.device or "default",
        )
        log.debug("worker %s command: %s", w.spec.server_id, " ".join(w.cmd))

    def _poll(self, sock: socket.socket, timeout: float) -> None:
        """Wait up to ``timeout`` for notifications and log lines, and handle what came."""
        for key, _ in self._sel.select(timeout):
            if key.data is None:
                self._receive(sock)
            else:
                self._copy_lines(key.fileobj, key.data)  # type: ignore[arg-type]

    def _copy_lines(self, pipe: IO[bytes], w: Worker) -> None:
        """Our stderr gets a worker's complete stderr lines, each prefixed with its server id."""
        fd = pipe.fileno()
        try:
            chunk = os.read(fd, 1 << 16)
        except BlockingIOError:
            return
        data = self._partial.pop(fd, b"") + chunk
        if not chunk:  # the worker closed it (exited)
            self._sel.unregister(pipe)
            pipe.close()
        lines = data.split(b"\n")
        if chunk:
            self._partial[fd] = lines.pop()
        out = self.stream or sys.stderr
        try:
            out.write("".join(f"[{w.spec.server_id}] {x.decode(errors='replace')}\n" for x in lines if x))
            out.flush()
        except (OSError, ValueError):
            pass

    def _reap(self, now: float) -> None:
        for w in self.workers:
            if w.proc is None or (rc := w.proc.poll()) is None:
                continue
            self._drain(w)
            w.proc, w.ready = None, False
            if rc == 2:
                self.gave_up = f"worker {w.spec.server_id} exited with status 2 (bad configuration)"
                return
            ran = now - w.started_at
            w.failures = 0 if ran >= self.restart_window_s else w.failures + 1
            while self.restarts and now - self.restarts[0] > self.restart_window_s:
                self.restarts.popleft()
            if len(self.restarts) >= self.max_restarts:
                self.gave_up = (
                    f"worker {w.spec.server_id} exited with {describe_status(rc)} after {len(self.restarts)} "
                    f"restarts within {self.restart_window_s:g} s"
                )
                return
            self.restarts.append(now)
            delay = min(BACKOFF_MAX_S, self.backoff_s * 2 ** max(0, w.failures - 1))
            w.restart_at = now + delay
            log.warning(
                "worker %s exited with %s after %.1f s: restarting it in %.1f s (restart %d within %g s)",
                w.spec.server_id,
                describe_status(rc),
                ran,
                delay,
                len(self.restarts),
                self.restart_window_s,
            )

    def _drain(self, w: Worker, timeout: float = 2.0) -> None:
        """An exited worker's last log lines: its pipe until end of file (or ``timeout``)."""
        pipe = w.proc.stderr if w.proc is not None else None
        deadline = time.monotonic() + timeout
        while pipe is not None and not pipe.closed:
            if time.monotonic() >= deadline:
                self._sel.unregister(pipe)
                pipe.close()
                break
            if select.select([pipe], [], [], 0.05)[0]:
                self._copy_lines(pipe, w)

    def _receive(self, sock: socket.socket) -> None:
        """The workers' notifications waiting on the socket (READY=1, WATCHDOG=1...)."""
        creds = struct.calcsize("3i")
        while True:
            try:
                data, anc, _, _ = sock.recvmsg(4096, socket.CMSG_SPACE(creds))
            except (BlockingIOError, InterruptedError):
                return
            pid = next(
                (
                    struct.unpack("3i", d[:creds])[0]
                    for level, kind, d in anc
                    if level == socket.SOL_SOCKET and kind == socket.SCM_CREDENTIALS
                ),
                None,
            )
            w = next((w for w in self.workers if w.proc is not None and w.proc.pid == pid), None)
            if w is None:
                continue
            lines = data.decode(errors="replace").splitlines()
            now = time.monotonic()
            if "READY=1" in lines:
                w.ready, w.last_ping = True, now
                log.info("worker %s ready (start %d)", w.spec.server_id, w.starts)
                if not self._all_ready_said and all(x.ready for x in self.workers):
                    self._all_ready_said = True
                    log.info("all %d workers ready", len(self.workers))
                    sd_notify(f"READY=1\nSTATUS=serving {len(self.workers)} workers\nMAINPID={os.getpid()}", self.env)
            if "WATCHDOG=1" in lines:
                w.last_ping = now

    def _stop_all(self, sock: socket.socket) -> bool:
        """SIGTERM to every worker, SIGKILL to those not gone after the grace; True when all
        exited with status 0 (their log lines keep coming meanwhile)."""
        running = [w for w in self.workers if w.proc is not None]
        for w in running:
            assert w.proc is not None
            with contextlib.suppress(ProcessLookupError):
                w.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_grace_s
        while any(w.proc is not None and w.proc.poll() is None for w in running) and time.monotonic() < deadline:
            self._poll(sock, 0.1)
        clean = True
        for w in running:
            assert w.proc is not None
            rc = w.proc.poll()
            if rc is None:
                log.error("worker %s did not stop in %.0f s: killing it", w.spec.server_id, self.stop_grace_s)
                w.proc.kill()
                rc = w.proc.wait()
            self._drain(w)
            if rc != 0:
                clean = False
                log.error("worker %s stopped with %s", w.spec.server_id, describe_status(rc))
            else:
                log.info("worker %s stopped", w.spec.server_id)
            w.proc = None
        return clean


def supervise(config: ServerConfig) -> int:
    """``drape serve`` with ``workers > 1``: plan the workers, then supervise them until
    SIGINT/SIGTERM (main thread only); 2 for a configuration that cannot work."""
    try:
        specs = plan(config)
    except ValueError as e:
        log.error("bad configuration: %s", e)
        return 2
    return Supervisor(config, specs).run()
