"""Zenoh session configuration shared by the SDK and the server (PROTOCOL.md section 1).

One function builds every Drape Zenoh configuration: an optional JSON5 base file (TLS,
authentication, access control; ``deploy/zenoh-peer.json5`` and ``deploy/zenoh-client.json5`` are
samples), then the mode, the listen and connect endpoints and multicast scouting set explicitly.
``deployment_client_id`` finds a client id the deployment chose (the id its router binds to the
client's user, PROTOCOL.md 11.2). Imports Zenoh; ``drape.client.protocol`` does not.

Endpoints are checked here before Zenoh sees them (``check_endpoint``: a protocol, an address,
a port where the protocol has one), and Zenoh's own errors, when a configuration is refused or a
session does not open (``open_session``), are raised with their message only, without the Rust
source locations Zenoh appends.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")
PORTED = ("tcp", "udp", "tls", "quic", "ws")  # protocols whose address ends in :port
_PROTOCOL = re.compile(r"[a-z][a-z0-9-]*")
_PORT = re.compile(r":(\d+)$")
_RUST_AT = re.compile(r"\s*\bat \S+\.rs:\d+\.?")  # " at /root/.cargo/.../endpoint.rs:615."
_JSON5_MSG = re.compile(r'msg: "(.*?)", location')


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` when it has the form ``<protocol>/<address>`` (``tcp/127.0.0.1:7447``), with a
    port 0..65535 for tcp, udp, tls, quic and ws; else a ValueError saying how to write it."""
    if not isinstance(endpoint, str):
        raise TypeError(f"an endpoint is a string such as 'tcp/127.0.0.1:7447', got {endpoint!r}")
    proto, sep, rest = endpoint.partition("/")
    if not sep or not _PROTOCOL.fullmatch(proto):
        raise ValueError(f"endpoint {endpoint!r} has no protocol; write tcp/{endpoint.lstrip('/')}")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not address:
        raise ValueError(f"endpoint {endpoint!r} has no address; write e.g. {proto}/127.0.0.1:7447")
    if proto in PORTED:
        port = _PORT.search(address)
        if port is None:
            raise ValueError(f"endpoint {endpoint!r} has no port; write e.g. {proto}/{address}:7447")
        if int(port.group(1)) > 65535:
            raise ValueError(f"endpoint {endpoint!r}: port {port.group(1)} is out of range 0..65535")
    return endpoint


def zenoh_message(err: BaseException) -> str:
    """Zenoh's error message without the Rust source locations it carries."""
    text = str(err)
    inner = _JSON5_MSG.search(text)
    if inner is not None:
        text = inner.group(1)
    return _RUST_AT.sub("", text).strip()


def open_session(config: zenoh.Config, what: str = "") -> zenoh.Session:
    """``zenoh.open(config)``; when Zenoh refuses, a ConnectionError with Zenoh's message only
    (``what``: the endpoints, for the message; the full error is logged at debug level)."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as e:
        log.debug("zenoh.open failed: %r", e)
        where = f" ({what})" if what else ""
        raise ConnectionError(f"cannot open a Zenoh session{where}: {zenoh_message(e)}") from None


def _endpoints(cfg: zenoh.Config, key: str, mode: str) -> list[str]:
    """The endpoints ``cfg`` gives under ``key`` for ``mode`` (a list, or a map by mode)."""
    try:
        raw = json.loads(cfg.get_json(key))
    except (zenoh.ZError, ValueError, TypeError):
        return []
    if isinstance(raw, dict):
        raw = raw.get(mode, [])
    return [str(e) for e in raw] if isinstance(raw, list) else []


def file_listen(cfg: zenoh.Config, mode: str) -> list[str]:
    """The listen endpoints a configuration file set for ``mode`` (none where it left Zenoh's
    own defaults)."""
    got = _endpoints(cfg, "listen/endpoints", mode)
    return [] if got == _endpoints(zenoh.Config(), "listen/endpoints", mode) else got


def listening(cfg: zenoh.Config, mode: str) -> list[str]:
    """The endpoints a session of ``cfg`` listens on (client mode: none)."""
    return [] if mode == "client" else _endpoints(cfg, "listen/endpoints", mode)


def zenoh_config(
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    multicast_scouting: bool = False,
    base_file: str | None = None,
    default_listen: Iterable[str] = (),
) -> zenoh.Config:
    """A Zenoh configuration: ``base_file`` (JSON5: TLS, auth, access control...) if given,
    then mode, listen and connect endpoints and multicast scouting set explicitly. The listen
    endpoints are the file's (a TLS file's ``tls/`` port is opened, never replaced), then
    ``listen``'s others; where neither gives one, ``default_listen``. A client-mode session listens
    on nothing (Zenoh refuses listen endpoints in client mode; :func:`listening` says what a
    configuration listens on). Every endpoint is checked first (``check_endpoint``); a base file
    or endpoint Zenoh refuses is a ValueError with Zenoh's message."""
    if mode not in MODES:
        raise ValueError(f"unknown Zenoh mode {mode!r}; choose from {MODES}")
    listen = [check_endpoint(e) for e in listen]
    connect = [check_endpoint(e) for e in connect]
    try:
        cfg = zenoh.Config.from_file(base_file) if base_file else zenoh.Config()
    except zenoh.ZError as e:
        raise ValueError(f"Zenoh configuration {base_file}: {zenoh_message(e)}") from None
    own = file_listen(cfg, mode) if base_file else []
    listen = own + [e for e in listen if e not in own] or [check_endpoint(e) for e in default_listen]
    cfg.insert_json5("mode", json.dumps(mode))
    try:
        if mode != "client":
            cfg.insert_json5("listen/endpoints", json.dumps(listen))
        cfg.insert_json5("connect/endpoints", json.dumps(connect))
    except zenoh.ZError as e:
        raise ValueError(f"endpoints (listen {listen}, connect {connect}): {zenoh_message(e)}") from None
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


__all__ = [
    "CLIENT_ID_ENV",
    "CLIENT_ID_SIDECAR",
    "MODES",
    "check_endpoint",
    "deployment_client_id",
    "open_session",
    "zenoh_config",
    "zenoh_message",
]
