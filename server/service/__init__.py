"""The Zenoh service around one World: the server and its parts (server.py composes them), one
folder per thread: ``requests/`` (the request thread), ``cook/`` (the cook thread), the tick and
publisher threads' parts, ``process/`` (the daemon, its workers and the operator's side); the
pieces several threads share at the top (config, registry, commands, replies, worldparams).

``Server`` is imported lazily, so that ``drape.server.service.config`` (and the daemon's
argument parsing) needs neither Zenoh's session nor OpenCL."""

from __future__ import annotations

from typing import Any

__all__ = ["Server"]


def __getattr__(name: str) -> Any:
    if name == "Server":
        from .server import Server

        return Server
    raise AttributeError(name)
