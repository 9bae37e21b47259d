"""``drape top``: a live terminal view of the Drape servers on a Zenoh network, in the style of
htop, from the stats every server publishes (PROTOCOL.md section 10).

It subscribes to ``{ns}/server/*/stats`` (or one server's) and shows, per server: achieved and
configured tick rate, tick-phase times (mean over the last stats period; ``tick`` also its max),
cloths, clients, vertices, states and bytes published per second, missed ticks, quality presets
in force, overload refusals and error replies. Rates come from two consecutive publications of
the same server (the server's own clock), so they are exact over its stats period.

``drape top --once`` finds the servers by their liveliness tokens, waits (``--wait``) for two
publications of each, prints one frame as plain text and exits: for scripts and tests.
The live view ends on ``q`` (or ``Q``) when stdin is a terminal, and on Ctrl-C.
"""

from __future__ import annotations

import argparse
import logging
import os
import select
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, TextIO

import zenoh
from rich import box
from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from drape.client import protocol as P
from drape.client.session import zenoh_config

from ..service.process.metrics import overload_refusals
from ..service.process.telemetry import PHASES

log = logging.getLogger(__name__)

STALE_PERIODS = 3.0  # a server whose stats are this many periods late is shown stale
FORGET_S = 60.0  # and dropped from the view after this many seconds of silence


@dataclass
class ServerView:
    """The last two stats publications of one server."""

    server: str
    last: dict[str, Any]
    prev: dict[str, Any] | None = None
    received: float = 0.0  # monotonic time of ``last``
    count: int = 1

    def period_s(self) -> float | None:
        """Seconds between the two publications, by the server's clock."""
        if self.prev is None:
            return None
        dt = (int(self.last.get("time_ns", 0)) - int(self.prev.get("time_ns", 0))) / 1e9
        return dt if dt > 0 else None

    def rate(self, key: str, of: Any = None) -> float | None:
        """Per-second increase of a cumulative counter (``of(stats)`` when given) between the two."""
        dt = self.period_s()
        if dt is None:
            return None
        get = of or (lambda s: s.get(key))
        a, b = get(self.prev), get(self.last)
        if a is None or b is None:
            return None
        return max(0.0, (float(b) - float(a)) / dt)


class StatsBoard:
    """The latest stats of every server seen, fed by a Zenoh subscriber (thread-safe)."""

    def __init__(self, keys: P.Keys) -> None:
        self.keys = keys
        self._lock = threading.Lock()
        self._views: dict[str, ServerView] = {}
        self.invalid = 0
        self.changed = threading.Condition(self._lock)

    def on_sample(self, sample: zenoh.Sample) -> None:
        try:
            stats = P.decode_stats(sample.payload.to_bytes())
        except Exception as e:
            with self._lock:
                self.invalid += 1
            log.debug("undecodable stats on %s: %s", sample.key_expr, e)
            return
        self.add(str(stats.get("server") or self.keys.last_chunk(str(sample.key_expr).rsplit("/", 1)[0])), stats)

    def add(self, server: str, stats: dict[str, Any], now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            v = self._views.get(server)
            if v is None:
                self._views[server] = ServerView(server, stats, None, now)
            else:
                v.prev, v.last, v.received, v.count = v.last, stats, now, v.count + 1
            self.changed.notify_all()

    def views(self, now: float | None = None) -> list[ServerView]:
        now = time.monotonic() if now is None else now
        with self._lock:
            for sid in [s for s, v in self._views.items() if now - v.received > FORGET_S]:
                del self._views[sid]
            return sorted(self._views.values(), key=lambda v: v.server)

    def wait(self, pred: Any, timeout: float) -> bool:
        """Wait until ``pred(views)`` holds (re-checked on every publication)."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while not pred(dict(self._views)):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.changed.wait(left)
            return True


# ---------------------------------------------------------------------------------------------
# Rendering


def _f(v: float | None, fmt: str = "{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def _bytes(v: float | None) -> str:
    if v is None:
        return "-"
    for unit in ("B", "kB", "MB", "GB"):
        if v < 1000 or unit == "GB":
            return f"{v:.0f} {unit}" if unit == "B" else f"{v:.1f} {unit}"
        v /= 1000
    return "-"


def _quality(q: dict[str, Any]) -> str:
    presets = q.get("presets") or {}
    text = " ".join(f"{n}:{presets[n]}" for n in P.QUALITY_PRESETS if presets.get(n)) or "-"
    if q.get("degraded"):
        text += f" ({q['degraded']} down)"
    return text


def _phase(stats: dict[str, Any], name: str, key: str = "mean_ms") -> float | None:
    p = (stats.get("phases") or {}).get(name)
    return None if p is None else float(p.get(key, 0.0))


COLUMNS = (
    "SERVER",
    "TICK/s",
    "TICK ms",
    "MAX ms",
    "SOLVE",
    "READBK",
    "ENCODE",
    "PUBLSH",
    "CLOTHS",
    "CLIENTS",
    "VERTICES",
    "STATES/s",
    "BYTES/s",
    "MISSED/s",
    "QUALITY",
    "OVERLOAD",
    "ERRORS",
    "UPTIME",
)
#: The phase behind each phase column (mean milliseconds over the last stats period).
PHASE_COLUMNS = {"SOLVE": "solve", "READBK": "readback", "ENCODE": "encode", "PUBLSH": "publish"}
#: What a narrow terminal keeps, most important first (columns keep their order on screen).
PRIORITY = (
    "SERVER",
    "TICK/s",
    "TICK ms",
    "CLOTHS",
    "CLIENTS",
    "MISSED/s",
    "OVERLOAD",
    "STATES/s",
    "MAX ms",
    "ERRORS",
    "QUALITY",
    "SOLVE",
    "VERTICES",
    "BYTES/s",
    "PUBLSH",
    "ENCODE",
    "READBK",
    "UPTIME",
)
assert sorted(PRIORITY) == sorted(COLUMNS) and set(PHASE_COLUMNS.values()) <= set(PHASES)


def row_cells(v: ServerView, now: float) -> dict[str, str]:
    """Every column's text for one server."""
    s = v.last
    period = v.period_s() or 1.0
    stale = now - v.received > STALE_PERIODS * max(period, 0.1)
    tick_rate = v.rate("ticks")
    if tick_rate is None and s.get("uptime_s"):
        tick_rate = float(s.get("ticks", 0)) / float(s["uptime_s"])
    cells = {
        "SERVER": v.server + (" (stale)" if stale else ""),
        "TICK/s": f"{_f(tick_rate)}/{float(s.get('tick_rate', 0)):g}",
        "TICK ms": _f(_phase(s, "tick"), "{:.2f}"),
        "MAX ms": _f(_phase(s, "tick", "max_ms"), "{:.2f}"),
        "CLOTHS": str(s.get("cloths", 0)),
        "CLIENTS": str(s.get("clients", 0)),
        "VERTICES": str(s.get("vertices", 0)),
        "STATES/s": _f(v.rate("published"), "{:.0f}"),
        "BYTES/s": _bytes(v.rate("published_bytes")) if "published_bytes" in s else "-",
        "MISSED/s": _f(v.rate("missed_ticks"), "{:.1f}"),
        "QUALITY": _quality(s.get("quality") or {}),
        "OVERLOAD": str(overload_refusals(s)),
        "ERRORS": str(sum(int(n) for n in (s.get("errors") or {}).values())),
        "UPTIME": _uptime(float(s.get("uptime_s", 0.0))),
    }
    cells.update({c: _f(_phase(s, p), "{:.2f}") for c, p in PHASE_COLUMNS.items()})
    return cells


def fit_columns(rows: list[dict[str, str]], width: int | None) -> list[str]:
    """The columns that fit ``width`` characters, by PRIORITY, in COLUMNS order (all when None)."""
    if width is None:
        return list(COLUMNS)
    chosen: set[str] = set()
    used = 0
    for c in PRIORITY:
        w = max([len(c)] + [len(r[c]) for r in rows]) + 3  # padding either side and a separator
        if used + w > width and chosen:
            continue
        chosen.add(c)
        used += w
    return [c for c in COLUMNS if c in chosen]


def render(views: list[ServerView], source: str, now: float | None = None, width: int | None = None) -> Group:
    """One frame: a summary line and a row per server, in the columns that fit ``width``."""
    now = time.monotonic() if now is None else now
    rows = [row_cells(v, now) for v in views]
    columns = fit_columns(rows, width)
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, expand=False, header_style="bold")
    for c in columns:
        table.add_column(c, justify="left" if c in ("SERVER", "QUALITY") else "right", no_wrap=True)
    for r in rows:
        table.add_row(*(r[c] for c in columns), style="dim" if r["SERVER"].endswith("(stale)") else None)
    totals = {k: sum(int(v.last.get(k, 0)) for v in views) for k in ("cloths", "clients", "vertices")}
    head = Text(
        f"drape top - {len(views)} server(s), {totals['cloths']} cloths, {totals['clients']} clients, "
        f"{totals['vertices']} vertices - {source}"
    )
    return Group(head, table)


def _uptime(s: float) -> str:
    h, rem = divmod(int(s), 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}"


def print_frame(views: list[ServerView], source: str, out: TextIO) -> None:
    """A frame as plain text (no colours, no terminal control codes)."""
    console = Console(file=out, force_terminal=False, color_system=None, width=250, highlight=False)
    console.print(render(views, source))


# ---------------------------------------------------------------------------------------------
# The command


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--endpoint",
        action="append",
        default=None,
        help=f"Zenoh endpoint to connect to (a server or router; repeatable; default {P.DEFAULT_ENDPOINT})",
    )
    parser.add_argument("--namespace", default=P.DEFAULT_NAMESPACE, help="key namespace of the servers")
    parser.add_argument("--server", default=None, help="show this server only (default: every server seen)")
    parser.add_argument("--mode", default="peer", choices=("peer", "client"), help="Zenoh mode of this session")
    parser.add_argument("--zenoh-config", default=None, help="Zenoh JSON5 file (TLS, authentication)")
    parser.add_argument("--once", action="store_true", help="print one frame as plain text and exit")
    parser.add_argument(
        "--wait", type=float, default=5.0, help="--once: seconds to wait for two stats publications of every server"
    )
    parser.add_argument("--refresh", type=float, default=0.5, help="seconds between redraws")


def run(args: argparse.Namespace) -> int:
    keys = P.Keys(args.namespace)
    if args.server is not None and not P.valid_id(args.server):
        print(f"drape top: invalid server id {args.server!r}", file=sys.stderr)
        return 2
    endpoints = args.endpoint or [P.DEFAULT_ENDPOINT]
    source = ",".join(endpoints) + f" {args.namespace}/"
    board = StatsBoard(keys)
    session = zenoh.open(zenoh_config(args.mode, (), endpoints, False, args.zenoh_config))
    try:
        sub = session.declare_subscriber(keys.stats(args.server or "*"), board.on_sample)
        try:
            if args.once:
                return _once(session, keys, board, args, source)
            return _live(board, source, args.refresh)
        finally:
            sub.undeclare()
    finally:
        session.close()


def _once(session: zenoh.Session, keys: P.Keys, board: StatsBoard, args: argparse.Namespace, source: str) -> int:
    deadline = time.monotonic() + args.wait
    replies = session.liveliness().get(keys.alive_server(args.server or "*"), timeout=min(args.wait, 2.0))
    servers = {keys.last_chunk(str(r.ok.key_expr)) for r in replies if r.ok is not None}
    if servers:
        board.wait(lambda vs: all(s in vs and vs[s].count >= 2 for s in servers), max(0.0, deadline - time.monotonic()))
    else:  # no token seen (an old server, or a router that does not forward them): take what comes
        board.wait(
            lambda vs: bool(vs) and all(v.count >= 2 for v in vs.values()), max(0.0, deadline - time.monotonic())
        )
    views = board.views()
    if not views:
        print(f"drape top: no stats from any Drape server on {source} within {args.wait:g} s", file=sys.stderr)
        return 1
    print_frame(views, source, sys.stdout)
    return 0


QUIT_KEYS = frozenset("qQ")


def quits(typed: str) -> bool:
    """Whether keys typed in the live view ask it to quit (``q`` or ``Q``, like htop)."""
    return any(c in QUIT_KEYS for c in typed)


class KeyReader:
    """Keys typed on a terminal, read without blocking: while open, the terminal on ``fd`` is in
    cbreak mode (each key is readable at once, no echo; Ctrl-C still interrupts) and is restored
    as it was on close, whatever ends the view. On a non-terminal ``fd`` (stdin a pipe or a file)
    it reads nothing and :meth:`wait` only sleeps."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self._saved: list[Any] | None = None

    def __enter__(self) -> KeyReader:
        if os.isatty(self.fd):
            import termios
            import tty

            self._saved = termios.tcgetattr(self.fd)
            tty.setcbreak(self.fd, termios.TCSANOW)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is not None:
            import termios

            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            self._saved = None

    def wait(self, timeout: float) -> str:
        """The keys typed within ``timeout`` seconds (returns as soon as there are some)."""
        if self._saved is None:
            time.sleep(timeout)
            return ""
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return ""
        try:
            data = os.read(self.fd, 64)
        except OSError:
            return ""
        return data.decode("utf-8", "replace")


def _live(board: StatsBoard, source: str, refresh: float, keys_fd: int | None = None) -> int:
    """Redraw every ``refresh`` s until ``q`` (on a terminal's stdin) or Ctrl-C."""
    console = Console()
    fd = sys.stdin.fileno() if keys_fd is None and sys.stdin is not None and sys.stdin.isatty() else keys_fd
    if fd is not None:
        source += "  (q quits)"
    try:
        with (
            KeyReader(fd if fd is not None else -1) as keys,
            Live(
                render(board.views(), source, width=console.width),
                console=console,
                refresh_per_second=max(1.0, 1.0 / refresh),
                screen=False,
                transient=False,
            ) as live,
        ):
            deadline = time.monotonic() + refresh
            while True:
                if quits(keys.wait(max(0.0, deadline - time.monotonic()))):
                    return 0
                if time.monotonic() >= deadline:
                    live.update(render(board.views(), source, width=console.width))
                    deadline = time.monotonic() + refresh
    except KeyboardInterrupt:
        return 0
