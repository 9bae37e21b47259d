"""What each worker of ``drape serve --workers N`` runs (drape.server.service.process.workers supervises
them): worker k's server id ``<server_id>-<k>``, every ``listen`` endpoint's port + k (port 0, a
port past 65535 or two workers on one port are refused: a restarted worker must come back on
its endpoint and the others must know it), ``connect`` the configured endpoints plus the other
workers' first endpoint (a wildcard host as loopback; in ``client`` mode only the configured
router), ``device`` entry ``k mod len`` of a comma list, ``metrics_listen`` port + k (0 stays 0);
the rest of the configuration as ``drape serve`` flags."""

from __future__ import annotations

import logging
import re
import sys
from dataclasses import dataclass, fields

from ..config import ServerConfig, _field_kind, parse_listen

log = logging.getLogger(__name__)

#: the per-worker fields the supervisor sets itself (not copied from its configuration)
PER_WORKER = ("workers", "server_id", "listen", "connect", "device", "metrics_listen")
_ENDPOINT_RE = re.compile(
    r"^(?P<proto>[A-Za-z0-9_\-]+)/(?P<host>\[[^\]]*\]|[^/\[\]?#]*):(?P<port>\d+)(?P<rest>[?#].*)?$"
)
_WILDCARD = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]", "": "127.0.0.1"}


@dataclass
class WorkerSpec:
    """What differs between the workers: the rest of their configuration is the supervisor's."""

    index: int
    server_id: str
    listen: list[str]
    connect: list[str]
    device: str | None
    metrics_listen: str | None
    reach: str | None  # the endpoint the other workers connect to (None in client mode)


def _match(endpoint: str) -> re.Match[str]:
    m = _ENDPOINT_RE.match(endpoint.strip())
    if m is None:
        raise ValueError(f"workers > 1: listen endpoint {endpoint!r} has no PROTOCOL/HOST:PORT form")
    return m


def shift_port(endpoint: str, k: int) -> str:
    """``endpoint`` with its port + k; ValueError when it has no usable port."""
    m = _match(endpoint)
    port = int(m["port"])
    if port == 0:
        raise ValueError(
            f"workers > 1: listen endpoint {endpoint!r} has port 0; give a port (worker k listens on port + k, "
            "the same after a restart, and the other workers connect to it)"
        )
    if port + k > 65535:
        raise ValueError(f"workers > 1: worker {k} would listen on port {port + k} of {endpoint!r} (> 65535)")
    return f"{m['proto']}/{m['host']}:{port + k}{m['rest'] or ''}"


def reachable(endpoint: str) -> str:
    """``endpoint`` as another process on this host connects to it (a wildcard host as loopback)."""
    m = _match(endpoint)
    return f"{m['proto']}/{_WILDCARD.get(m['host'], m['host'])}:{m['port']}{m['rest'] or ''}"


def _port_key(endpoint: str) -> tuple[str, int]:
    """(transport, port) of an endpoint: udp for udp and quic, tcp for the rest (tls, ws...)."""
    m = _match(endpoint)
    return ("udp" if m["proto"] in ("udp", "quic") else "tcp"), int(m["port"])


def shift_metrics(value: str | None, k: int) -> str | None:
    """``metrics_listen`` of worker k: its port + k (0 stays 0: each picks a free one)."""
    if value is None:
        return None
    host, port = parse_listen(value)
    if port and port + k > 65535:
        raise ValueError(f"workers > 1: worker {k}'s metrics port {port + k} > 65535")
    port = port + k if port else 0
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def plan(config: ServerConfig) -> list[WorkerSpec]:
    """The N workers of ``config`` (see the module docstring); ValueError when it cannot work."""
    n = config.workers
    if n < 2:
        raise ValueError("a supervisor needs workers >= 2")
    devices: list[str | None] = [d.strip() for d in (config.device or "").split(",") if d.strip()] or [None]
    if len(devices) > n:
        log.warning("device lists %d entries for %d workers: the last %d unused", len(devices), n, len(devices) - n)
    client_mode = config.mode == "client"
    if client_mode and not config.connect:
        raise ValueError("workers > 1 in client mode: connect must name the router the workers connect to")
    if not client_mode and not config.listen:
        raise ValueError(f"workers > 1 in {config.mode} mode: listen must name at least one endpoint")
    specs: list[WorkerSpec] = []
    taken: dict[tuple[str, int], int] = {}
    for k in range(n):
        listen = list(config.listen) if client_mode else [shift_port(e, k) for e in config.listen]
        metrics = shift_metrics(config.metrics_listen, k)
        ports = [] if client_mode else [_port_key(e) for e in listen]
        if metrics is not None and parse_listen(metrics)[1]:
            ports.append(("tcp", parse_listen(metrics)[1]))
        for key in ports:
            if taken.get(key, k) != k:
                raise ValueError(
                    f"workers > 1: {key[0]} port {key[1]} would be used by workers {taken[key]} and {k} "
                    f"(configured ports fewer than {n} apart)"
                )
            taken[key] = k
        specs.append(
            WorkerSpec(
                index=k,
                server_id=f"{config.server_id}-{k}",
                listen=listen,
                connect=list(config.connect),
                device=devices[k % len(devices)],
                metrics_listen=metrics,
                reach=None if client_mode else reachable(listen[0]),
            )
        )
    for s in specs:
        s.connect += [o.reach for o in specs if o is not s and o.reach is not None]
        # each worker's own configuration must be valid too (its server id's length...)
        config.with_(workers=1, server_id=s.server_id, listen=s.listen, connect=s.connect, device=s.device)
    return specs


def config_flags(config: ServerConfig) -> list[str]:
    """The fields of ``config`` that every worker shares, as ``drape serve`` flags (None left out:
    a worker's default is None too)."""
    out: list[str] = []
    for f in fields(ServerConfig):
        value = getattr(config, f.name)
        if f.name in PER_WORKER or value is None:
            continue
        flag = "--" + f.name.replace("_", "-")
        kind, _ = _field_kind(f)
        if kind is bool:
            out.append(flag if value else "--no-" + flag[2:])
        elif kind is list:
            out += [a for v in value for a in (flag, v)]
        else:
            out += [flag, repr(value) if kind is float else str(value)]
    return out


def worker_command(config: ServerConfig, spec: WorkerSpec) -> list[str]:
    """The command line of worker ``spec`` of ``config``, run by this interpreter."""
    cmd = [sys.executable, "-m", "drape.server.cli", "serve", *config_flags(config), "--workers", "1"]
    cmd += ["--server-id", spec.server_id]
    cmd += [a for e in spec.listen for a in ("--listen", e)]
    cmd += [a for e in spec.connect for a in ("--connect", e)]
    if spec.device is not None:
        cmd += ["--device", spec.device]
    if spec.metrics_listen is not None:
        cmd += ["--metrics-listen", spec.metrics_listen]
    return cmd
