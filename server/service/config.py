"""Server configuration: one dataclass, filled from defaults < a TOML file < DRAPE_* environment
variables < command-line flags.

A TOML file holds the fields at its top level (or inside a ``[server]`` table)::

    mode = "peer"                      # peer | client | router
    listen = ["tcp/0.0.0.0:7447"]
    connect = []
    namespace = "drape"
    server_id = "eu-1"
    identity = "open"                  # open | keys (PROTOCOL.md 11.2)
    tick_rate = 60.0
    solver = "workgroup"               # workgroup | coloured | jacobi | reference
    device = "auto"                    # see drape devices
    max_cloths = 1024
    max_cloths_per_client = 64
    max_vertices_per_cloth = 65536
    max_total_vertices = 2097152
    grace_period = 5.0                 # seconds a vanished client's cloths are kept
    stats_period = 1.0
    metrics_listen = "127.0.0.1:9464"  # operator HTTP: /metrics /healthz /readyz (default: off)
    log_format = "text"                # text | json (one object per line)
    log_level = "info"                 # debug | info | warning | error
    workers = 1                        # drape serve: server processes sharing the device

Every field is also an environment variable ``DRAPE_<FIELD>`` (``DRAPE_TICK_RATE=30``; lists are
comma-separated: ``DRAPE_LISTEN=tcp/0.0.0.0:7447,tcp/[::]:7447``) and a flag ``--field-name``.
``DRAPE_CONFIG`` or ``--config`` names the TOML file.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import socket
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from drape.client.protocol import DEFAULT_ENDPOINT, DEFAULT_NAMESPACE, FEATURE_NAMES, ID_RE, NAMESPACE_RE, Limits

from ..sim.params import MAX_COLLIDERS_PER_CLOTH, SOLVERS

log = logging.getLogger(__name__)

ZENOH_MODES = ("peer", "client", "router")
CONGESTION_CHOICES = ("auto", "drop", "block")
LOG_FORMATS = ("text", "json")
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
#: open: the 1.0-1.3 server-wide request queryables as well as the client-scoped ones (1.4), and a
#: cloth submitted on a server-wide key publishes on {ns}/cloth/{cloth}/state; keys: only the
#: client-scoped ones, so every request's client id is its key's (a router can bind it to a user).
IDENTITY_MODES = ("open", "keys")
BUILD_IN_CHILD = ("off", "start", "always")  # drape.server.service.buildhelper
MAX_WORKERS = 64  # drape serve --workers (drape.server.service.workers)


def default_server_id() -> str:
    """Host name and process id, as a valid key chunk."""
    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname())[:40] or "drape"
    return f"{host}-{os.getpid()}"


@dataclass
class ServerConfig:
    # --- Zenoh -------------------------------------------------------------------------------
    mode: str = "peer"
    listen: list[str] = field(default_factory=lambda: [DEFAULT_ENDPOINT])
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False  # off: peers find each other through explicit endpoints
    zenoh_config: str | None = None  # a Zenoh JSON5 file (TLS, auth, ACL); the fields above override it
    namespace: str = DEFAULT_NAMESPACE
    server_id: str = ""  # "" = host name and process id
    identity: str = "open"  # open | keys: where a request's client id comes from (IDENTITY_MODES)
    # --- simulation ----------------------------------------------------------------------------
    tick_rate: float = 60.0  # Hz; dt = 1 / tick_rate
    solver: str = "workgroup"
    device: str | None = None  # None = DRAPE_DEVICE or auto
    # --- limits --------------------------------------------------------------------------------
    max_cloths: int = 1024
    max_cloths_per_client: int = 64
    new_clients_per_s: float = 10.0  # client ids the server has no cloth of, admitted per second (a token bucket)
    new_clients_burst: int = 64  # ... and at once; beyond: "overloaded" (ids are free without identity = "keys")
    max_vertices_per_cloth: int = 65536
    max_total_vertices: int = 1 << 21
    max_message_bytes: int = 8 << 20
    max_pin_updates: int = 4096
    max_batch_items: int = 64  # controls in one batch control request (protocol 1.1)
    max_iterations: int = 100
    max_substeps: int = 100  # the quality presets go up to 100 (exact); lower it to forbid them
    max_pending_requests: int = 1024  # queued requests (and commands); beyond this requests get "busy"
    max_pending_request_bytes: int = 64 << 20  # payload bytes of queued requests; beyond this: "busy"
    # --- service -------------------------------------------------------------------------------
    grace_period: float = 5.0  # seconds a client's cloths outlive its liveliness token
    stats_period: float = 1.0  # seconds between stats publications
    state_congestion: str = "drop"  # drop | block | auto (see PROTOCOL.md, "Congestion control")
    drop_max_bytes: int = 60000  # auto: states up to this size use DROP, larger ones BLOCK
    device_encode: bool = True  # OpenCL worlds: states encoded on the device (one launch, one readback)
    keyframe_interval: int = 60  # predictive states (1.5): an intra-coded state every this many ticks
    pipeline: bool = True  # the device steps tick N + 1 while tick N is published (false: one tick less latency)
    gil_switch_ms: float = 0.5  # Python's GIL switch interval in the server process (sys.setswitchinterval)
    request_yield: bool = True  # the request thread starts requests only while the tick thread sleeps
    program_idle_s: float = 10.0  # kernel programs no cloth used this long are released (0: kept for good)
    malloc_mmap_threshold: int = 4 << 20  # bytes: larger blocks mapped apart, returned when freed (0: glibc's)
    build_in_child: str = "off"  # off | start | always: kernels built and first run in a child process
    warm_features: str = "tethers"  # feature sets built and run at start-up besides the default ("a+b,c")
    # --- quality -------------------------------------------------------------------------------
    adaptive_quality: bool = True  # lower cloths' presets while ticks overrun, restore them after
    quality_budget: float = 0.8  # share of a tick the tick's own work may take before that
    # --- admission and misbehaving cloths -------------------------------------------------------
    admission: bool = True  # refuse submits ("overloaded") that would push ticks over admission_budget
    admission_budget: float = 0.85  # share of a tick the predicted tick cost may take
    admission_unmeasured_vertices: int = 65_536  # admitted before the first steady tick (64 32x32 cloths)
    nan_max_resets: int = 5  # a cloth reset this many times for non-finite state within nan_window...
    nan_window: float = 10.0  # ...seconds is removed
    # --- operations ----------------------------------------------------------------------------
    metrics_listen: str | None = None  # host:port of /metrics /healthz /readyz; None = off (127.0.0.1:9464)
    log_format: str = "text"  # text | json (drape.server.service.logs)
    log_level: str = "info"  # debug | info | warning | error | critical
    workers: int = 1  # drape serve: server processes on this device, <server_id>-<k> (drape.server.service.workers)

    def __post_init__(self) -> None:
        if not self.server_id:
            self.server_id = default_server_id()

    def warm_feature_sets(self) -> list[tuple[str, ...]]:
        """``warm_features`` as feature name tuples."""
        return [
            tuple(n.strip() for n in part.split("+") if n.strip())
            for part in self.warm_features.split(",")
            if part.strip()
        ]

    def validate(self) -> ServerConfig:
        if self.mode not in ZENOH_MODES:
            raise ValueError(f"mode must be one of {ZENOH_MODES}, got {self.mode!r}")
        if not NAMESPACE_RE.match(self.namespace):
            raise ValueError(f"invalid namespace {self.namespace!r}")
        if not ID_RE.match(self.server_id):
            raise ValueError(f"invalid server_id {self.server_id!r}: 1-64 characters of [A-Za-z0-9_.-]")
        if self.identity not in IDENTITY_MODES:
            raise ValueError(f"identity must be one of {IDENTITY_MODES}, got {self.identity!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if not (0.1 <= self.tick_rate <= 10000):
            raise ValueError("tick_rate must be in 0.1..10000 Hz")
        if self.state_congestion not in CONGESTION_CHOICES:
            raise ValueError(f"state_congestion must be one of {CONGESTION_CHOICES}")
        if not (0.01 <= self.gil_switch_ms <= 100):
            raise ValueError("gil_switch_ms must be in 0.01..100 ms")
        if not (1 <= self.keyframe_interval <= 1_000_000):
            raise ValueError("keyframe_interval must be in 1..1000000 ticks")
        if not (self.new_clients_per_s > 0 and self.new_clients_burst >= 1):
            raise ValueError("new_clients_per_s must be > 0 and new_clients_burst >= 1")
        if self.program_idle_s < 0:
            raise ValueError("program_idle_s must be >= 0 (0: programs are kept for good)")
        if self.malloc_mmap_threshold < 0:
            raise ValueError("malloc_mmap_threshold must be >= 0 bytes (0: glibc's dynamic threshold)")
        for names in self.warm_feature_sets():
            bad = [n for n in names if n not in FEATURE_NAMES]
            if bad:
                raise ValueError(f"warm_features: unknown feature(s) {bad}; known: {list(FEATURE_NAMES)}")
        if self.build_in_child not in BUILD_IN_CHILD:
            raise ValueError(f"build_in_child must be one of {BUILD_IN_CHILD}, got {self.build_in_child!r}")
        for name in (
            "max_cloths",
            "max_cloths_per_client",
            "max_vertices_per_cloth",
            "max_total_vertices",
            "max_message_bytes",
            "max_pin_updates",
            "max_batch_items",
            "max_iterations",
            "max_substeps",
            "max_pending_requests",
            "max_pending_request_bytes",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1")
        if self.max_iterations > 1000 or self.max_substeps > 100:
            raise ValueError("max_iterations <= 1000 and max_substeps <= 100 (the solver's own bounds)")
        if not (0.05 <= self.quality_budget <= 10.0):
            raise ValueError("quality_budget must be in 0.05..10 (a share of one tick)")
        if not (0.0 < self.admission_budget <= 100.0):
            raise ValueError("admission_budget must be in (0, 100] (a share of one tick)")
        if self.admission_unmeasured_vertices < 0:
            raise ValueError("admission_unmeasured_vertices must be >= 0")
        if self.nan_max_resets < 1 or self.nan_window <= 0:
            raise ValueError("nan_max_resets must be >= 1 and nan_window > 0")
        if self.log_format not in LOG_FORMATS:
            raise ValueError(f"log_format must be one of {LOG_FORMATS}, got {self.log_format!r}")
        if self.log_level.lower() not in LOG_LEVELS:
            raise ValueError(f"log_level must be one of {LOG_LEVELS}, got {self.log_level!r}")
        if self.metrics_listen is not None:
            parse_listen(self.metrics_listen)
        if not 1 <= self.workers <= MAX_WORKERS:
            raise ValueError(f"workers must be in 1..{MAX_WORKERS}, got {self.workers}")
        if self.grace_period < 0 or self.stats_period <= 0:
            raise ValueError("grace_period must be >= 0 and stats_period > 0")
        return self

    @property
    def dt(self) -> float:
        return 1.0 / self.tick_rate

    def limits(self) -> Limits:
        return Limits(
            max_message_bytes=self.max_message_bytes,
            max_vertices=self.max_vertices_per_cloth,
            max_triangles=4 * self.max_vertices_per_cloth,
            max_pin_updates=self.max_pin_updates,
            max_batch_items=self.max_batch_items,
            max_colliders=MAX_COLLIDERS_PER_CLOTH,
            max_iterations=self.max_iterations,
            max_substeps=self.max_substeps,
        )

    # --- sources ---------------------------------------------------------------------------
    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        env: Mapping[str, str] | None = None,
        overrides: Mapping[str, Any] | None = None,
    ) -> ServerConfig:
        """Defaults, then the TOML file (``path`` or $DRAPE_CONFIG), then DRAPE_* variables of
        ``env`` (default os.environ), then ``overrides`` (None values are ignored)."""
        env = os.environ if env is None else env
        values: dict[str, Any] = {}
        path = path or env.get("DRAPE_CONFIG")
        if path:
            values.update(_from_toml(Path(path)))
        values.update(_from_env(env))
        values.update({k: v for k, v in (overrides or {}).items() if v is not None})
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown configuration key(s) {sorted(unknown)}")
        return cls(**values).validate()

    def with_(self, **changes: Any) -> ServerConfig:
        return replace(self, **changes).validate()


def parse_listen(value: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:9464``, ``:9464`` = every interface) as (host, port)."""
    host, sep, port = value.strip().rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"metrics_listen must be HOST:PORT, got {value!r}")
    return host.strip("[]") or "0.0.0.0", int(port)


def _field_kind(f) -> tuple[type, bool]:
    """(base type, optional) of a dataclass field from its annotation."""
    hint = typing.get_type_hints(ServerConfig)[f.name]
    optional = False
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        hint = args[0]
    if typing.get_origin(hint) is list:
        return list, optional
    return hint, optional


def _convert(name: str, value: Any, kind: type, optional: bool, source: str) -> Any:
    try:
        if value is None or (optional and isinstance(value, str) and value.strip().lower() in ("", "none")):
            if optional:
                return None
            raise ValueError("a value is required")
        if kind is list:
            if isinstance(value, str):
                return [v.strip() for v in value.split(",") if v.strip()]
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise ValueError("expected a list of strings")
            return list(value)
        if kind is bool:
            if isinstance(value, bool):
                return value
            s = str(value).strip().lower()
            if s in ("1", "true", "yes", "on"):
                return True
            if s in ("0", "false", "no", "off"):
                return False
            raise ValueError("expected true or false")
        if kind is int:
            if isinstance(value, bool):
                raise ValueError("expected an integer")
            return int(value)
        if kind is float:
            if isinstance(value, bool):
                raise ValueError("expected a number")
            return float(value)
        return str(value)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{source}: bad value {value!r} for {name}: {e}") from None


def _from_toml(path: Path) -> dict[str, Any]:
    with open(path, "rb") as fh:
        data = tomllib.load(fh)
    if "server" in data and isinstance(data["server"], dict):
        data = {**{k: v for k, v in data.items() if k != "server"}, **data["server"]}
    out: dict[str, Any] = {}
    by_name = {f.name: f for f in fields(ServerConfig)}
    for k, v in data.items():
        if k not in by_name:
            raise ValueError(f"{path}: unknown configuration key {k!r}")
        kind, optional = _field_kind(by_name[k])
        out[k] = _convert(k, v, kind, optional, str(path))
    log.debug("configuration from %s: %s", path, out)
    return out


def _from_env(env: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in fields(ServerConfig):
        var = f"DRAPE_{f.name.upper()}"
        if var in env:
            kind, optional = _field_kind(f)
            out[f.name] = _convert(f.name, env[var], kind, optional, var)
    return out


HELP = {
    "mode": "Zenoh mode",
    "listen": "Zenoh endpoint to listen on",
    "connect": "Zenoh endpoint to connect to (a router or other peers)",
    "multicast_scouting": "find peers by UDP multicast",
    "zenoh_config": "Zenoh JSON5 configuration file (TLS, authentication, access control)",
    "namespace": "first key-expression chunk(s) of every key",
    "server_id": "this server's id in its keys (default: host-pid)",
    "identity": "open: also serve 1.0-1.3 clients on the server-wide keys; keys: client-scoped keys only "
    "(a router's ACL then binds every request to its user)",
    "tick_rate": "ticks per second; dt = 1/tick_rate",
    "solver": "World solver",
    "device": "OpenCL device: auto, gpu, cpu, gpu:N / cpu:N (the N-th, from 0) or part of a name",
    "max_cloths": "cloths on this server",
    "max_cloths_per_client": "cloths of one client",
    "new_clients_per_s": "client ids without a cloth here admitted per second (beyond the burst: 'overloaded')",
    "new_clients_burst": "client ids without a cloth here admitted at once",
    "max_vertices_per_cloth": "vertices of one cloth",
    "max_total_vertices": "vertices of all cloths together",
    "max_message_bytes": "size of one request",
    "max_pin_updates": "pin targets in one control request (or one batch item)",
    "max_batch_items": "cloths controlled by one batch control request",
    "max_iterations": "solver iterations a cloth may ask for",
    "max_substeps": "substeps a cloth may ask for",
    "max_pending_requests": "queued requests before new ones get 'busy'",
    "max_pending_request_bytes": "payload bytes of the queued requests before new ones get 'busy' "
    "(one request is always taken when none waits)",
    "grace_period": "seconds a vanished client's cloths are kept",
    "stats_period": "seconds between stats publications",
    "state_congestion": "Zenoh congestion control of state publications",
    "drop_max_bytes": "auto congestion: largest state published with DROP",
    "device_encode": "encode the states on the OpenCL device, one packed frame per tick (reference: host)",
    "pipeline": "the device steps tick N + 1 while the publisher sends tick N: a tick's period is its slowest "
    "stage; false: each tick is read back and published in the tick that stepped it, one tick less input "
    "latency, the stages adding up (docs/latency.md)",
    "keyframe_interval": "predictive states (protocol 1.5): ticks between intra-coded states of a stream, "
    "besides those asked for (a late joiner's, a client's that lost one)",
    "gil_switch_ms": "the server process's GIL switch interval in ms (Python's default is 5: a thread "
    "returning from a Zenoh call waits up to that long behind a busy one)",
    "request_yield": "the request thread (decoding, validation, replies) starts a request only while the tick "
    "thread sleeps between ticks, waiting one tick at most (docs/reliability.md: fewer missed ticks under a flood)",
    "program_idle_s": "seconds after which a kernel program no cloth uses is released and the heap trimmed "
    "(built again from the driver's disk cache when needed; 0: kept for good)",
    "malloc_mmap_threshold": "drape serve: heap blocks of this many bytes or more get their own mapping, "
    "given back when freed (glibc mallopt M_MMAP_THRESHOLD; 0: glibc's dynamic threshold)",
    "warm_features": "feature sets whose kernels are built and run at start-up besides the default set, so that "
    "a first cloth of one neither waits for a build nor stalls the ticks: comma-separated, each set's names "
    "joined by + (e.g. tethers,xpbd+tethers+colliders); empty: none",
    "build_in_child": "drape serve: kernels built and first run in a short-lived child process, then loaded "
    "from the driver's disk cache (the compiler's memory and first-launch JIT stay out of the server); "
    "start: every feature combination before serving; always: also each new combination a cloth brings",
    "adaptive_quality": "step cloths' quality presets down while ticks overrun, back up after",
    "quality_budget": "share of a tick the tick's work may take before quality is lowered",
    "admission": "refuse submissions that would push the tick over admission_budget ('overloaded')",
    "admission_budget": "share of a tick the predicted tick cost may take when admitting a cloth",
    "admission_unmeasured_vertices": "vertices admitted before the first steady tick is measured (then "
    "'overloaded' until one is); raise it on a GPU so that a level's first burst is not refused",
    "nan_max_resets": "non-finite resets of one cloth within nan_window before it is removed",
    "nan_window": "seconds over which nan_max_resets counts",
    "metrics_listen": "HOST:PORT of the operator HTTP listener (/metrics /healthz /readyz), e.g. 127.0.0.1:9464",
    "log_format": "log lines as text or json (one object per line)",
    "log_level": "lowest level logged",
    "workers": "drape serve: run this many server processes on the device under one supervisor, worker k as "
    "<server_id>-<k> listening on each listen port + k, connected to the others; a comma list in device gives "
    "worker k entry k mod its length (README: several workers)",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config`` plus one flag per ServerConfig field (all default to None = not given)."""
    parser.add_argument("--config", metavar="FILE", help="TOML configuration file (default: $DRAPE_CONFIG)")
    for f in fields(ServerConfig):
        kind, _ = _field_kind(f)
        flag = "--" + f.name.replace("_", "-")
        default = f.default_factory() if f.default_factory is not MISSING else f.default  # type: ignore[misc]
        help_ = f"{HELP.get(f.name, '')} (default: {default!r}; env DRAPE_{f.name.upper()})"
        if kind is bool:
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=help_)
        elif kind is list:
            parser.add_argument(
                flag, dest=f.name, action="append", metavar="ENDPOINT", default=None, help=f"{help_}; repeatable"
            )
        else:
            choices = {
                "mode": ZENOH_MODES,
                "identity": IDENTITY_MODES,
                "solver": SOLVERS,
                "state_congestion": CONGESTION_CHOICES,
                "log_format": LOG_FORMATS,
                "log_level": LOG_LEVELS,
                "build_in_child": BUILD_IN_CHILD,
            }.get(f.name)
            parser.add_argument(flag, dest=f.name, type=kind, default=None, choices=choices, help=help_)


def from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> ServerConfig:
    overrides = {f.name: getattr(args, f.name, None) for f in fields(ServerConfig)}
    return ServerConfig.load(getattr(args, "config", None), env, overrides)
