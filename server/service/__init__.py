"""The Zenoh service around one World: configuration, the server and its parts (server.py).

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
