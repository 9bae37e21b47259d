"""Logging setup for every ``drape`` command: text lines for a terminal, or one JSON object per
line for a log shipper (``--log-format json``), and Zenoh's own log level.

JSON lines have stable keys: ``time`` (ISO 8601, UTC, milliseconds), ``level``, ``logger``,
``message``, then, where known, ``server_id``, ``cloth``, ``client`` and ``exception``. A log call
names its cloth and client with ``extra=log_context(cloth=..., client=...)``; code that handles
one cloth for a while can instead wrap it in ``with context(cloth=..., client=...)`` (contextvars,
so each thread keeps its own). ``server_id`` is the process's (``setup(..., server_id=)``)
unless the context names another.

Zenoh writes its own log lines (Rust ``tracing``, not Python ``logging``) to the terminal:
``setup`` starts them at level ``error`` unless ``RUST_LOG`` says otherwise (``RUST_LOG=zenoh=info``).
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import logging
import sys
import time
from collections.abc import Iterator
from typing import Any, TextIO

LOG_FORMATS = ("text", "json")
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
CONTEXT_KEYS = ("server_id", "cloth", "client")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_HANDLER_NAME = "drape"

_context: dict[str, contextvars.ContextVar[str | None]] = {
    k: contextvars.ContextVar(f"drape_log_{k}", default=None) for k in CONTEXT_KEYS
}
_zenoh_logging = False


def log_context(**values: str | None) -> dict[str, str]:
    """The ``extra=`` of a log call about a cloth or client: ``log.info(..., extra=log_context(cloth=c))``."""
    unknown = set(values) - set(CONTEXT_KEYS)
    if unknown:
        raise ValueError(f"unknown log context key(s) {sorted(unknown)}; known: {CONTEXT_KEYS}")
    return {k: v for k, v in values.items() if v is not None}


@contextlib.contextmanager
def context(**values: str | None) -> Iterator[None]:
    """Every log record made inside (in this thread or task) carries these keys."""
    tokens = [(_context[k], _context[k].set(v)) for k, v in log_context(**values).items()]
    try:
        yield
    finally:
        for var, tok in reversed(tokens):
            var.reset(tok)


class ContextFilter(logging.Filter):
    """Gives every record the context keys (None where unknown): from the call's ``extra=``
    first, then the current ``context()``, then the process defaults (``server_id``)."""

    def __init__(self, **defaults: str | None) -> None:
        super().__init__()
        self.defaults = {k: v for k, v in defaults.items() if k in CONTEXT_KEYS}

    def filter(self, record: logging.LogRecord) -> bool:
        for k in CONTEXT_KEYS:
            if getattr(record, k, None) is None:
                setattr(record, k, _context[k].get() or self.defaults.get(k))
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per record, on one line (newlines inside values are escaped)."""

    def format(self, record: logging.LogRecord) -> str:
        t = time.gmtime(record.created)
        out: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", t) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        for k in CONTEXT_KEYS:
            v = getattr(record, k, None)
            if v is not None:
                out[k] = str(v)
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        elif record.exc_text:
            out["exception"] = record.exc_text
        if record.stack_info:
            out["stack"] = self.formatStack(record.stack_info)
        return json.dumps(out, ensure_ascii=False, default=str)


class TextFormatter(logging.Formatter):
    """The classic line, with ``[cloth=... client=...]`` appended when the record names them."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        ctx = " ".join(f"{k}={getattr(record, k)}" for k in ("cloth", "client") if getattr(record, k, None))
        if not ctx:
            return line
        head, nl, rest = line.partition("\n")  # keep a traceback below the first line
        return f"{head} [{ctx}]{nl}{rest}"


def parse_level(level: str | int) -> int:
    if isinstance(level, int):
        return level
    value = logging.getLevelName(level.strip().upper())
    if not isinstance(value, int):
        raise ValueError(f"unknown log level {level!r}")
    return value


def make_handler(fmt: str = "text", stream: TextIO | None = None, server_id: str | None = None) -> logging.Handler:
    """A stream handler (stderr by default) in the given format, with the context filter."""
    if fmt not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {LOG_FORMATS}, got {fmt!r}")
    handler = logging.StreamHandler(stream or sys.stderr)
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    handler.addFilter(ContextFilter(server_id=server_id))
    return handler


def setup(
    fmt: str = "text",
    level: str | int = "info",
    server_id: str | None = None,
    stream: TextIO | None = None,
    zenoh_level: str | None = "error",
) -> logging.Handler:
    """Configure the root logger: one handler in ``fmt`` at ``level`` (replacing the one a
    previous call installed, so calling again, e.g. once the server id is known, is fine), and
    Zenoh's own log at ``zenoh_level`` unless ``RUST_LOG`` is set (None: leave Zenoh alone, for
    commands that never import it)."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if h.get_name() == _HANDLER_NAME:
            root.removeHandler(h)
    handler = make_handler(fmt, stream, server_id)
    root.addHandler(handler)
    root.setLevel(parse_level(level))
    if zenoh_level is not None:
        init_zenoh_log(zenoh_level)
    return handler


def init_zenoh_log(level: str = "error") -> None:
    """Start Zenoh's log (once per process; later calls do nothing): ``RUST_LOG`` or ``level``."""
    global _zenoh_logging
    if _zenoh_logging:
        return
    _zenoh_logging = True
    try:
        import zenoh
    except ImportError:  # tools that never talk Zenoh may run without it
        return
    try:
        zenoh.init_log_from_env_or(level)
    except Exception as e:  # already initialised by someone else
        logging.getLogger(__name__).debug("zenoh log not initialised: %s", e)
