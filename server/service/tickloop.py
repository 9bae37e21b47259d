"""Compatibility: the server used to live here; it is now split into parts (server.py says
which). ``from drape.server.service import Server`` is the import to use."""

from .server import Server  # noqa: F401
