"""What the tools share about processes: a free loopback port, ``drape serve`` as a child process,
process CPU time and memory (psutil), progress bars (tqdm) and a clear error when an extra is
missing.

Imported only by the tools (``drape.server.tools``); it needs the ``tools`` extra (psutil, tqdm),
checked by :func:`require_extra` with a message naming the extra to install.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

from .. import pip_hint

log = logging.getLogger(__name__)

#: The Python modules each extra of pyproject.toml provides (import names, not package names).
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "server": ("pyopencl",),
    "tools": ("matplotlib", "PIL", "tqdm", "psutil"),
}


def require_extra(extra: str, command: str, modules: Sequence[str] | None = None) -> None:
    """Exit with a clear message when a module of ``extra`` is not installed."""
    missing = [m for m in (EXTRA_MODULES[extra] if modules is None else modules) if importlib.util.find_spec(m) is None]
    if missing:
        raise SystemExit(
            f"drape {command} needs the '{extra}' extra ({', '.join(missing)} not installed): {pip_hint(extra)}"
        )


def free_port(span: int = 1) -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now; ``span`` > 1: the next
    ``span - 1`` ports are free too (``drape serve --workers N`` listens on port + k)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port + span - 1 <= 65535 and all(_bindable(port + k) for k in range(1, span)):
            return port
    raise RuntimeError(f"no {span} adjacent free ports on 127.0.0.1")


def _bindable(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def progress(
    iterable: Iterable[Any] | None = None,
    *,
    total: float | None = None,
    desc: str = "",
    unit: str = "it",
    quiet: bool = False,
    **kw: Any,
) -> Any:
    """A tqdm progress bar on stderr, disabled when stderr is not a terminal or ``quiet``."""
    from tqdm import tqdm

    disable = quiet or not sys.stderr.isatty()
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=disable, leave=False, dynamic_ncols=True, **kw)


@dataclass
class ProcessFigures:
    """CPU time and resident memory of one process, sampled over a run."""

    pid: int
    rss_mb: list[float] = field(default_factory=list)

    def cpu_seconds(self) -> float:
        """User + system CPU seconds of the process so far (NaN when it is gone)."""
        import psutil

        try:
            t = psutil.Process(self.pid).cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            return float("nan")
        return float(t.user + t.system)

    def sample_rss(self) -> float:
        """Resident set size now, in MB; kept in ``rss_mb`` (NaN when the process is gone)."""
        import psutil

        try:
            mb = psutil.Process(self.pid).memory_info().rss / 2**20
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            return float("nan")
        self.rss_mb.append(mb)
        return float(mb)

    def rss_summary(self) -> dict[str, float]:
        """Start, end and maximum of the sampled RSS, in MB."""
        if not self.rss_mb:
            return {"rss_start_mb": float("nan"), "rss_end_mb": float("nan"), "rss_max_mb": float("nan")}
        return {
            "rss_start_mb": round(self.rss_mb[0], 1),
            "rss_end_mb": round(self.rss_mb[-1], 1),
            "rss_max_mb": round(max(self.rss_mb), 1),
        }


def csv_list(text: str | None) -> list[str]:
    """A command line's comma list ("a, b,,c") as its non-empty items, stripped ([] for None)."""
    return [t.strip() for t in (text or "").split(",") if t.strip()]


def parse_cpus(text: str) -> frozenset[int]:
    """A CPU list as taskset and /sys write it ("0-3,16-19") as a set of CPU numbers; ValueError
    when it is empty or malformed."""
    cpus: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        lo, sep, hi = part.partition("-")
        try:
            a, b = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"CPU list {text!r}: {part!r} is not N or N-M") from None
        if a < 0 or b < a:
            raise ValueError(f"CPU list {text!r}: {part!r} is not an increasing range of CPU numbers")
        cpus.update(range(a, b + 1))
    return frozenset(cpus)


def format_cpus(cpus: Iterable[int]) -> str:
    """A CPU set as a compact list ("0-3,16-19"), the inverse of :func:`parse_cpus`."""
    out: list[str] = []
    for c in sorted(cpus):
        if out and out[-1].split("-")[-1] == str(c - 1):
            out[-1] = f"{out[-1].split('-')[0]}-{c}"
        else:
            out.append(str(c))
    return ",".join(out)


def serve_command(endpoint: str, server_id: str, *args: str) -> list[str]:
    """The command line of a ``drape serve`` child listening on ``endpoint`` as ``server_id``
    (``args``: more ``drape serve`` arguments), run by this interpreter."""
    return [sys.executable, "-m", "drape.server.cli", "serve", "--listen", endpoint, "--server-id", server_id, *args]


def demo_server(args: Any, tick_hz: float = 60.0) -> ServerProcess:
    """The ``drape serve`` a ``drape demo`` stage runs against (demostages.py): ``tick_hz``,
    admission off (a few small cloths: admission, which refuses cloths while a busy machine
    stretches the ticks, would only make a demo fail on a loaded machine), the stage's
    ``--solver``, ``--device`` and ``--port`` options."""
    serve_args = ["--tick-rate", str(tick_hz), "--no-admission"]
    if args.solver:
        serve_args += ["--solver", args.solver]
    if args.device:
        serve_args += ["--device", args.device]
    return ServerProcess(serve_args, server_id="demo", port=args.port)


class ServerExited(RuntimeError):
    """The ``drape serve`` child a tool started exited while the tool waited on it; the message
    says with which exit status, before what, and ends with the server's last log lines."""


class ServerProcess:
    """``drape serve`` as a child process in its own session, on a free loopback port.

    ``args`` are extra ``drape serve`` arguments; ``output``: a file its stdout and stderr go to
    (default: a pipe that a thread copies to our stderr, line by line, keeping the last
    ``TAIL_LINES``); ``cpus``: the CPUs it (every thread of it) may run on (None: any). Stop it
    with :meth:`stop` (SIGTERM to its process group, SIGKILL after ``grace`` seconds); usable as
    a context manager. A tool that waits on the server calls :meth:`check` while it waits: a dead
    server raises :class:`ServerExited` with its exit status and last log lines, at once, rather
    than the tool timing out and blaming its clients."""

    TAIL_LINES = 200

    def __init__(
        self,
        args: Sequence[str] = (),
        *,
        server_id: str | None = None,
        port: int = 0,
        output: IO[Any] | None = None,
        cpus: frozenset[int] | None = None,
    ) -> None:
        self.endpoint = f"tcp/127.0.0.1:{port or free_port()}"
        self.server_id = server_id or f"tools-{os.getpid()}"
        self.cpus = cpus
        self.cmd = serve_command(self.endpoint, self.server_id, *args)
        self._output = output
        self._tail: deque[str] = deque(maxlen=self.TAIL_LINES)
        log.info("starting server%s: %s", f" on CPUs {format_cpus(cpus)}" if cpus else "", " ".join(self.cmd))
        self.proc = subprocess.Popen(
            self.cmd,
            start_new_session=True,
            stdout=subprocess.PIPE if output is None else output,
            stderr=subprocess.STDOUT,
            # set before exec, so that every thread the server starts inherits it
            preexec_fn=(lambda: os.sched_setaffinity(0, cpus)) if cpus else None,
        )
        self._pump: threading.Thread | None = None
        if output is None:
            self._pump = threading.Thread(target=self._copy_output, daemon=True, name=f"log-{self.server_id}")
            self._pump.start()
        self.figures = ProcessFigures(self.proc.pid)

    def _copy_output(self) -> None:
        """Copy the server's output to our stderr, keeping its last lines (until its pipe closes)."""
        assert self.proc.stdout is not None
        with self.proc.stdout as pipe:
            for raw in pipe:
                line = raw.decode("utf-8", "replace")
                self._tail.append(line.rstrip("\n"))
                try:
                    sys.stderr.write(line)
                    sys.stderr.flush()
                except (OSError, ValueError):  # our stderr closed: keep draining the pipe
                    pass

    def last_lines(self, n: int = 20) -> list[str]:
        """The server's last ``n`` lines of output (stdout and stderr together)."""
        if self._pump is not None:
            if self.proc.poll() is not None:
                self._pump.join(2.0)  # the pipe's last lines, once the process is gone
            return list(self._tail)[-n:]
        name = getattr(self._output, "name", None)
        if not isinstance(name, str):
            return []
        try:
            if self._output is not None:
                self._output.flush()
            with open(name, "rb") as fh:
                fh.seek(max(0, os.fstat(fh.fileno()).st_size - 64 * 1024))
                return fh.read().decode("utf-8", "replace").splitlines()[-n:]
        except (OSError, ValueError):
            return []

    def exit_message(self, before: str, n: int = 20) -> str:
        """ "server S exited with code N before ``before``", then its last ``n`` log lines."""
        rc = self.proc.poll()
        code = str(rc)
        if rc is not None and rc < 0:
            try:
                code += f" ({signal.Signals(-rc).name})"
            except ValueError:
                pass
        text = f"server {self.server_id} exited with code {code} before {before}"
        lines = self.last_lines(n)
        if lines:
            text += f"; its last {len(lines)} log lines:\n" + "\n".join(f"  | {line}" for line in lines)
        else:
            text += " (it wrote no output)"
        return text

    def check(self, before: str) -> None:
        """Raise :class:`ServerExited` (see :meth:`exit_message`) when the server has exited."""
        if self.proc.poll() is not None:
            raise ServerExited(self.exit_message(before))

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, grace: float = 20.0) -> int | None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(grace)
            except subprocess.TimeoutExpired:
                log.warning("server %s did not stop in %.0f s: killing it", self.server_id, grace)
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        if self._pump is not None:
            self._pump.join(5.0)
        return self.proc.returncode

    def __enter__(self) -> ServerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
