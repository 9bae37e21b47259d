"""Drape server: fabric cooking, OpenCL solvers, the tick loop and the Zenoh endpoints.

Drape is published on the package index as :data:`DISTRIBUTION` (the name ``drape`` there is an
unrelated project); the import name is ``drape`` and the command ``drape``."""

from __future__ import annotations

from importlib import metadata

#: The distribution's name on the package index: ``pip install drape-cloth`` (the game client),
#: ``pip install 'drape-cloth[server]'`` (the server).
DISTRIBUTION = "drape-cloth"


def version() -> str:
    """The installed distribution's version ("unknown" when run from a tree that is not installed)."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "unknown"


def pip_hint(extra: str | None = None) -> str:
    """The pip command that installs Drape (with ``extra``)."""
    return f"pip install '{DISTRIBUTION}[{extra}]'" if extra else f"pip install {DISTRIBUTION}"


__all__ = ["DISTRIBUTION", "pip_hint", "version"]
