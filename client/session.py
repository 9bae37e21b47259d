"""Zenoh session configuration shared by the SDK and the server (PROTOCOL.md section 1).

One function builds every Drape Zenoh configuration: an optional JSON5 base file (TLS,
authentication, access control; ``deploy/zenoh-peer.json5`` and ``deploy/zenoh-client.json5`` are
samples), then the mode, the listen and connect endpoints and multicast scouting set explicitly.
``deployment_client_id`` finds a client id the deployment chose (the id its router binds to the
client's user, PROTOCOL.md 11.2). Imports Zenoh; ``drape.client.protocol`` does not.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from pathlib import Path

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


CLIENT_ID_ENV = "DRAPE_CLIENT_ID"
CLIENT_ID_SIDECAR = ".client_id"  # appended to the Zenoh file's name: zenoh-client-tls.json5.client_id


def deployment_client_id(zenoh_config_file: str | None = None, env: Mapping[str, str] | None = None) -> str | None:
    """The client id the deployment gives this client, or None: ``$DRAPE_CLIENT_ID``, else the
    first line of the sidecar file ``<zenoh_config_file>.client_id`` when there is one (it sits
    next to the Zenoh file holding the user and password the router binds to that id)."""
    env = os.environ if env is None else env
    if env.get(CLIENT_ID_ENV, "").strip():
        return env[CLIENT_ID_ENV].strip()
    if zenoh_config_file:
        sidecar = Path(zenoh_config_file + CLIENT_ID_SIDECAR)
        if sidecar.is_file():
            lines = sidecar.read_text().split()
            return lines[0] if lines else None
    return None


__all__ = ["CLIENT_ID_ENV", "CLIENT_ID_SIDECAR", "MODES", "deployment_client_id", "zenoh_config"]
