"""Zenoh session configuration shared by the SDK and the server (PROTOCOL.md section 1).

One function builds every Drape Zenoh configuration: an optional JSON5 base file (TLS,
authentication, access control; ``deploy/zenoh-peer.json5`` and ``deploy/zenoh-client.json5`` are
samples), then the mode, the listen and connect endpoints and multicast scouting set explicitly.
Imports Zenoh; ``drape.client.protocol`` does not.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

import zenoh

MODES = ("peer", "client", "router")


def zenoh_config(
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    multicast_scouting: bool = False,
    base_file: str | None = None,
) -> zenoh.Config:
    """A Zenoh configuration: ``base_file`` (JSON5: TLS, auth, access control...) if given,
    then mode, listen and connect endpoints and multicast scouting set explicitly. A client-mode
    session listens on nothing (Zenoh refuses listen endpoints in client mode)."""
    if mode not in MODES:
        raise ValueError(f"unknown Zenoh mode {mode!r}; choose from {MODES}")
    cfg = zenoh.Config.from_file(base_file) if base_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    if mode != "client":
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    return cfg


__all__ = ["MODES", "zenoh_config"]
