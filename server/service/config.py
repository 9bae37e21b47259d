"""Server configuration: every setting declared once, as a field of :class:`ServerConfig` with its
type, default, range or choices and help (:func:`setting`); :data:`SETTINGS` is that table (plus the
environment-only knobs, :data:`ENV_ONLY`), and everything else is made or checked from it: the
validation, the ``DRAPE_<NAME>`` environment variables, ``drape serve``'s ``--name`` flags and their
``--help``, and deploy/drape.toml and the README's settings section (written by
``python -m drape.server.service.settingsdoc``; tests/service/test_settings.py fails when they drift).

A configuration is filled from defaults < a TOML file (its top level or a ``[server]`` table;
``--config`` or ``DRAPE_CONFIG`` names it) < ``DRAPE_*`` environment variables (lists
comma-separated: ``DRAPE_LISTEN=tcp/0.0.0.0:7447,tcp/[::]:7447``) < command-line flags.
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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import MISSING, Field, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from drape.client.protocol import DEFAULT_ENDPOINT, DEFAULT_NAMESPACE, FEATURE_NAMES, ID_RE, NAMESPACE_RE, Limits

from ..sim.params import MAX_COLLIDERS_PER_CLOTH, SOLVERS
from .process.logs import LOG_FORMATS, LOG_LEVELS

log = logging.getLogger(__name__)

ZENOH_MODES = ("peer", "client", "router")
CONGESTION_CHOICES = ("auto", "drop", "block")
#: open: the 1.0-1.3 server-wide request queryables as well as the client-scoped ones (1.4), and a
#: cloth submitted on a server-wide key publishes on {ns}/cloth/{cloth}/state; keys: only the
#: client-scoped ones, so every request's client id is its key's (a router can bind it to a user).
IDENTITY_MODES = ("open", "keys")
BUILD_IN_CHILD = ("off", "start", "always")  # drape.server.service.cook.buildhelper
MAX_WORKERS = 64  # drape serve --workers (drape.server.service.process.workers)
#: The environment variable of a setting: its name in capitals after this.
ENV_PREFIX = "DRAPE_"


def default_server_id() -> str:
    """Host name and process id, as a valid key chunk."""
    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname())[:40] or "drape"
    return f"{host}-{os.getpid()}"


@dataclass(frozen=True)
class Setting:
    """One row of the settings table. ``scope`` "server": a field of ServerConfig, a key of the TOML
    file, ``DRAPE_<NAME>`` and ``--<name-with-dashes>``; "env": an environment variable only, read
    where ``read_in`` says (documented here so that every knob is listed in one place)."""

    name: str
    kind: type  # str, int, float, bool or list (of strings)
    default: Any
    help: str
    group: str
    optional: bool = False  # None (TOML: left out; environment: "" or "none") allowed
    choices: tuple[str, ...] = ()
    low: float | None = None
    high: float | None = None
    low_open: bool = False  # the value must be > low (not >=)
    ignore_case: bool = False  # the choices are matched case-insensitively
    sample: Any = None  # the value deploy/drape.toml shows, when not the default
    commented: bool = False  # deploy/drape.toml shows it commented out
    metavar: str | None = None
    scope: str = "server"
    read_in: str = ""  # env-only knobs: the file that reads the variable

    @property
    def env(self) -> str:
        return ENV_PREFIX + self.name.upper()

    @property
    def flag(self) -> str | None:
        return "--" + self.name.replace("_", "-") if self.scope == "server" else None

    @property
    def shown(self) -> Any:
        """The value the TOML sample shows."""
        return self.default if self.sample is None else self.sample

    def limits_text(self) -> str:
        """The range or the choices, as the help and the documents write them ("" if neither)."""
        if self.choices:
            return " | ".join(self.choices)
        lo = None if self.low is None else _number(self.low)
        hi = None if self.high is None else _number(self.high)
        if lo is not None and hi is not None:
            return f"> {lo}, <= {hi}" if self.low_open else f"{lo}..{hi}"
        if lo is not None:
            return f"> {lo}" if self.low_open else f">= {lo}"
        return "" if hi is None else f"<= {hi}"

    def check(self, value: Any) -> None:
        """ValueError when ``value`` is outside the range or the choices."""
        if value is None:
            if self.optional:
                return
            raise ValueError(f"{self.name} must be given (none is not a value of it)")
        if self.choices:
            v = value.lower() if self.ignore_case and isinstance(value, str) else value
            if v not in self.choices:
                raise ValueError(f"{self.name} must be one of {self.choices}, got {value!r}")
            return
        below = self.low is not None and (value <= self.low if self.low_open else value < self.low)
        if below or (self.high is not None and value > self.high):
            raise ValueError(f"{self.name} must be {self._range_words()}, got {value!r}")

    def _range_words(self) -> str:
        text = self.limits_text()
        return f"in {text}" if ".." in text else text


def _number(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else str(x)


def setting(
    default: Any = None,
    help: str = "",
    *,
    group: str,
    factory: Callable[[], Any] | None = None,
    choices: Sequence[str] = (),
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    ignore_case: bool = False,
    sample: Any = None,
    commented: bool = False,
    metavar: str | None = None,
) -> Any:
    """A ServerConfig field declared with everything its row in :data:`SETTINGS` holds besides the
    name and type (taken from the field)."""
    meta = dict(
        help=help,
        group=group,
        choices=tuple(choices),
        low=low,
        high=high,
        low_open=low_open,
        ignore_case=ignore_case,
        sample=sample,
        commented=commented,
        metavar=metavar,
    )
    if factory is not None:
        return field(default_factory=factory, metadata={"setting": meta})
    return field(default=default, metadata={"setting": meta})


ZENOH, SIM, LIMITS, SERVICE, QUALITY, ADMISSION, OPS = (
    "Zenoh",
    "simulation",
    "limits",
    "service",
    "quality",
    "admission and misbehaving cloths",
    "operations (docs/operations.md)",
)


@dataclass
class ServerConfig:
    """Every setting of ``drape serve``, one field each (declared with :func:`setting`)."""

    # --- Zenoh -------------------------------------------------------------------------------
    mode: str = setting(
        "peer", "Zenoh mode: peer, client (connect to a router) or router", group=ZENOH, choices=ZENOH_MODES
    )
    listen: list[str] = setting(
        help="Zenoh endpoints to listen on (the default: loopback only)",
        group=ZENOH,
        factory=lambda: [DEFAULT_ENDPOINT],
        sample=["tcp/0.0.0.0:7447"],
        metavar="ENDPOINT",
    )
    connect: list[str] = setting(
        help="Zenoh endpoints to connect to (routers or other peers)", group=ZENOH, factory=list, metavar="ENDPOINT"
    )
    multicast_scouting: bool = setting(
        False, "find peers by UDP multicast (off: clients connect to the listen endpoints explicitly)", group=ZENOH
    )
    zenoh_config: str | None = setting(
        None,
        "a Zenoh JSON5 configuration file (TLS endpoints, user/password authentication, access control); the "
        "settings above override it, but its listen endpoints are opened (listen adds to them; its default is "
        "used only where the file sets none). deploy/zenoh-peer.json5 is a sample (deploy/zenoh-client.json5 "
        "the same for a client-mode session)",
        group=ZENOH,
        sample="/etc/drape/zenoh-peer.json5",
        commented=True,
    )
    namespace: str = setting(DEFAULT_NAMESPACE, "first key-expression chunk(s) of every key", group=ZENOH)
    server_id: str = setting(
        "",
        "this server's id in its keys (empty: <hostname>-<pid>); clients can also find it by liveliness",
        group=ZENOH,
        sample="drape-1",
    )
    identity: str = setting(
        "open",
        "open: also serve 1.0-1.3 clients on the server-wide keys (the client id in the payload is believed); "
        "keys: client-scoped request keys only (protocol 1.4 clients), the client id is the key's, which a "
        "router's access control binds to its user (drape acl, docs/reliability.md 3-4, PROTOCOL.md 11.2)",
        group=ZENOH,
        choices=IDENTITY_MODES,
    )
    # --- simulation ----------------------------------------------------------------------------
    tick_rate: float = setting(60.0, "ticks per second (Hz); dt = 1 / tick_rate", group=SIM, low=0.1, high=10000)
    solver: str = setting("workgroup", "World solver (README: Solvers)", group=SIM, choices=SOLVERS)
    device: str | None = setting(
        None,
        "OpenCL device: auto, gpu, cpu, gpu:N / cpu:N (the N-th, from 0) or part of a name (drape devices lists "
        "them; none: auto); with workers > 1 a comma list gives worker k entry k mod its length",
        group=SIM,
        sample="gpu",
        commented=True,
    )
    # --- limits --------------------------------------------------------------------------------
    max_cloths: int = setting(1024, "cloths on this server", group=LIMITS, low=1)
    max_cloths_per_client: int = setting(64, "cloths of one client", group=LIMITS, low=1)
    new_clients_per_s: float = setting(
        10.0,
        "client ids without a cloth here admitted per second (a token bucket); beyond the burst: 'overloaded' "
        "(retry later), so that minting ids cannot fill the server (ids are free without identity = keys)",
        group=LIMITS,
        low=0,
        low_open=True,
    )
    new_clients_burst: int = setting(64, "client ids without a cloth here admitted at once", group=LIMITS, low=1)
    max_vertices_per_cloth: int = setting(65536, "vertices of one cloth", group=LIMITS, low=1)
    max_total_vertices: int = setting(1 << 21, "vertices of all cloths together", group=LIMITS, low=1)
    max_message_bytes: int = setting(8 << 20, "size of one request in bytes", group=LIMITS, low=1)
    max_pin_updates: int = setting(4096, "pin targets in one control request (or one batch item)", group=LIMITS, low=1)
    max_batch_items: int = setting(
        64, "cloths controlled by one batch control request (protocol 1.1)", group=LIMITS, low=1
    )
    max_iterations: int = setting(
        100, "solver iterations a cloth may ask for (the solver's own bound: 1000)", group=LIMITS, low=1, high=1000
    )
    max_substeps: int = setting(
        100,
        "substeps a cloth may ask for (the quality presets go up to 100, exact: lower it to forbid them)",
        group=LIMITS,
        low=1,
        high=100,
    )
    max_pending_requests: int = setting(
        1024,
        "requests waiting for the request thread (and commands for a tick) before new ones get 'busy'",
        group=LIMITS,
        low=1,
    )
    max_pending_request_bytes: int = setting(
        64 << 20,
        "payload bytes of the queued requests before new ones get 'busy' (one request is always taken when none waits)",
        group=LIMITS,
        low=1,
    )
    # --- service -------------------------------------------------------------------------------
    grace_period: float = setting(
        5.0, "seconds a vanished client's cloths are kept (after its liveliness token)", group=SERVICE, low=0
    )
    stats_period: float = setting(
        1.0, "seconds between stats publications ({namespace}/server/<id>/stats)", group=SERVICE, low=0, low_open=True
    )
    state_congestion: str = setting(
        "drop",
        "Zenoh congestion control of state publications; auto: by size, drop_max_bytes (PROTOCOL.md, "
        "'Congestion control')",
        group=SERVICE,
        choices=CONGESTION_CHOICES,
    )
    drop_max_bytes: int = setting(
        60000, "auto congestion: the largest state published with DROP (larger ones: BLOCK)", group=SERVICE
    )
    send_buffer: int = setting(
        0,
        "bytes of each Zenoh TCP link's kernel send buffer (SO_SNDBUF, which Linux doubles; 0: the kernel's own, "
        "grown to megabytes): a small one keeps a slow subscriber's states fresh (DROP drops once it is full: "
        "docs/rates.md; Zenoh's data queue then stays at its 2 batches) but caps each link at about 2 x send_buffer "
        "per round trip (never on a router link)",
        group=SERVICE,
        low=0,
    )
    device_encode: bool = setting(
        True,
        "OpenCL solvers: the device writes every state as it goes on the wire into one packed frame, read back "
        "once per tick; false: the host encodes (the reference solver always does)",
        group=SERVICE,
    )
    keyframe_interval: int = setting(
        60,
        "predictive states (protocol 1.5): ticks between intra-coded states of a stream, besides those asked "
        "for (a late joiner's, a client's that lost one)",
        group=SERVICE,
        low=1,
        high=1_000_000,
    )
    pipeline: bool = setting(
        True,
        "the device steps tick N + 1 while the publisher sends tick N: a tick's period is its slowest stage; "
        "false: each tick is read back and published in the tick that stepped it, one tick less input latency, "
        "the stages adding up (docs/latency.md)",
        group=SERVICE,
    )
    gil_switch_ms: float = setting(
        0.5,
        "the server process's GIL switch interval in ms, sys.setswitchinterval (Python's default is 5: a thread "
        "returning from a Zenoh call waits up to that long behind a busy one)",
        group=SERVICE,
        low=0.01,
        high=100,
    )
    request_yield: bool = setting(
        True,
        "the request thread (decoding, validation, replies) starts a request only while the tick thread sleeps "
        "between ticks, waiting one tick at most (docs/reliability.md: fewer missed ticks under a flood)",
        group=SERVICE,
    )
    program_idle_s: float = setting(
        10.0,
        "seconds after which a kernel program no cloth uses is released and the heap trimmed (built again from "
        "the driver's disk cache when needed; 0: kept for good)",
        group=SERVICE,
        low=0,
    )
    malloc_mmap_threshold: int = setting(
        4 << 20,
        "drape serve: heap blocks of this many bytes or more get their own mapping, given back when freed "
        "(glibc mallopt M_MMAP_THRESHOLD); the heap's top is kept (trimmed on purpose by the memory upkeep) and "
        "every thread allocates from one malloc arena (MALLOC_ARENA_MAX in the environment overrides); 0: "
        "glibc's own thresholds and arenas",
        group=SERVICE,
        low=0,
    )
    build_in_child: str = setting(
        "always",
        "kernels built and first run in a short-lived child process at lower priority, then loaded from the "
        "driver's disk cache (the compiler's memory and first-launch JIT stay off the tick); start: drape serve "
        "builds every feature combination before serving (+2 s start-up with PoCL's cache filled, about 20 s "
        "cold); always (the default): also each new combination a cloth brings, so that no first cloth stalls "
        "a tick; off: built in the server process (tests; a first cloth of a new set stalls ticks)",
        group=SERVICE,
        choices=BUILD_IN_CHILD,
    )
    build_memory_mb: float = setting(
        2048.0,
        "the most memory (resident, MB) a child building kernels or cooking a big cloth (8192 vertices or more) "
        "may take: past it the child is killed, the cloth that asked is refused (too_large: not retried in the "
        "server) and the server goes on; 0: no bound",
        group=SERVICE,
        low=0,
    )
    warm_features: str = setting(
        "tethers",
        "feature sets whose kernels are built and run at start-up besides the default set, so that a first cloth "
        "of one neither waits for a build nor stalls the ticks: comma-separated, each set's names joined by + "
        "(e.g. tethers,xpbd+tethers+colliders); empty: none",
        group=SERVICE,
    )
    # --- quality -------------------------------------------------------------------------------
    adaptive_quality: bool = setting(
        True, "step cloths' quality presets down while ticks overrun, back up after", group=QUALITY
    )
    quality_budget: float = setting(
        0.8, "share of a tick the tick's own work may take before quality is lowered", group=QUALITY, low=0.05, high=10
    )
    # --- admission and misbehaving cloths -------------------------------------------------------
    admission: bool = setting(
        True,
        "refuse submissions and controls ('overloaded') whose work would push the predicted tick cost over "
        "admission_budget",
        group=ADMISSION,
    )
    admission_budget: float = setting(
        0.85,
        "share of a tick the predicted tick cost may take when admitting a cloth",
        group=ADMISSION,
        low=0,
        high=100,
        low_open=True,
    )
    admission_client_share: float = setting(
        0.5,
        "share of the work the tick budget holds that one client may take while others could come; past it, that "
        "client is admitted more only while admission_newcomer_reserve stays free (1: no shares)",
        group=ADMISSION,
        low=0,
        high=1,
        low_open=True,
    )
    admission_newcomer_reserve: float = setting(
        0.1,
        "share of the work the tick budget holds kept free for clients under their admission_client_share",
        group=ADMISSION,
        low=0,
        high=1,
    )
    admission_unmeasured_vertices: int = setting(
        65_536,
        "work units (vertices at the plain 10-iteration solve) admitted before the first steady tick is "
        "measured, then 'overloaded' until one is (64 32x32 "
        "cloths: a CPU's; on a GPU raise it, e.g. 2097152 for 2048 cloths, or a level's first burst at start-up "
        "is refused past 64 cloths)",
        group=ADMISSION,
        low=0,
    )
    nan_max_resets: int = setting(
        5, "resets of one cloth for non-finite state within nan_window before it is removed", group=ADMISSION, low=1
    )
    nan_window: float = setting(10.0, "seconds over which nan_max_resets counts", group=ADMISSION, low=0, low_open=True)
    # --- operations ----------------------------------------------------------------------------
    metrics_listen: str | None = setting(
        None,
        "HOST:PORT of the operator HTTP listener, /metrics /healthz /readyz (none: off); deploy/prometheus.yml "
        "scrapes it, deploy/alerts.yml alerts on it, deploy/grafana-dashboard.json shows it",
        group=OPS,
        sample="127.0.0.1:9464",
    )
    log_format: str = setting(
        "text", "log lines as text or json (one object per line)", group=OPS, choices=LOG_FORMATS, sample="json"
    )
    log_level: str = setting("info", "lowest level logged", group=OPS, choices=LOG_LEVELS, ignore_case=True)
    workers: int = setting(
        1,
        "drape serve: run this many server processes on the device under one supervisor, worker k as "
        "<server_id>-<k> listening on each listen port + k (metrics_listen's too), connected to the others "
        "(README: several server processes on one device)",
        group=OPS,
        low=1,
        high=MAX_WORKERS,
        sample=2,
        commented=True,
    )

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
        """ValueError naming the first setting out of its range or choices (SETTINGS), or invalid."""
        for row in CONFIG_SETTINGS:
            row.check(getattr(self, row.name))
        if not NAMESPACE_RE.match(self.namespace):
            raise ValueError(f"invalid namespace {self.namespace!r}")
        if not ID_RE.match(self.server_id):
            raise ValueError(f"invalid server_id {self.server_id!r}: 1-64 characters of [A-Za-z0-9_.-]")
        for names in self.warm_feature_sets():
            bad = [n for n in names if n not in FEATURE_NAMES]
            if bad:
                raise ValueError(f"warm_features: unknown feature(s) {bad}; known: {list(FEATURE_NAMES)}")
        if self.metrics_listen is not None:
            parse_listen(self.metrics_listen)
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


def _row(f: Field[Any], hint: Any) -> Setting:
    """The settings-table row of a ServerConfig field: its name and type, and what setting() noted."""
    optional = False
    if isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union:
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        hint = args[0]
    kind = list if typing.get_origin(hint) is list else hint
    default = f.default_factory() if f.default_factory is not MISSING else f.default
    return Setting(name=f.name, kind=kind, default=default, optional=optional, **f.metadata["setting"])


ENV = "environment only"
#: Knobs read from the environment only (tuning, caches, tests, the game client): no TOML key, no
#: flag; listed here so that every DRAPE_* variable is documented in one place.
ENV_ONLY: tuple[Setting, ...] = (
    Setting(
        "pack_lanes",
        int,
        None,
        "CPU devices: the pack solver's width, 0, 2, 4, 8 or 16 (0: one cloth per work-item; default: the "
        "widest the device check found runs; docs/cpu-solver.md)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/device.py",
    ),
    Setting(
        "wg_size",
        int,
        None,
        "work-items per cloth of the OpenCL solvers (default: 256 on a GPU, 1024 on its global-memory path; 1 "
        "on a CPU)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/clworld.py",
    ),
    Setting(
        "chunk",
        int,
        1024,
        "vertices per work-group in the coloured and Jacobi solvers' vertex phases",
        ENV,
        scope="env",
        read_in="server/sim/opencl/clworld.py",
    ),
    Setting(
        "link_unroll_local",
        int,
        None,
        "unroll factor of the link loop on the local-memory path (default: LINK_UNROLL_LOCAL, launch.py)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/launch.py",
    ),
    Setting(
        "link_unroll_global",
        int,
        None,
        "unroll factor of the link loop on the global-memory path (default: LINK_UNROLL_GLOBAL, launch.py)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/launch.py",
    ),
    Setting(
        "nv_maxrreg",
        int,
        64,
        "NVIDIA: the register cap of global-path kernels, -cl-nv-maxrregcount (0: none)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/launch.py",
    ),
    Setting(
        "cl_flags",
        str,
        "",
        "extra OpenCL build options, space-separated (e.g. -cl-fast-relaxed-math)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/device.py",
    ),
    Setting(
        "cache_dir",
        str,
        None,
        "the folder of the device check's verdicts and Drape's PoCL cache (default: $XDG_CACHE_HOME/drape or "
        "~/.cache/drape)",
        ENV,
        scope="env",
        read_in="server/sim/opencl/devicecheck.py",
    ),
    Setting(
        "profile",
        str,
        None,
        "drape serve: sample the tick, publish, cook and request threads' stacks at 200 Hz and write PATH.folded and "
        "PATH.txt at the stop (drape.server.service.process.sampler)",
        ENV,
        scope="env",
        read_in="server/service/process/daemon.py",
    ),
    Setting(
        "config",
        str,
        None,
        "drape serve: the TOML configuration file (the flag --config beats it)",
        ENV,
        scope="env",
        read_in="server/service/config.py",
    ),
    Setting(
        "client_id",
        str,
        None,
        "the game client's id (Python SDK, Rust/C client) when none is given in code",
        ENV,
        scope="env",
        read_in="client/session.py",
    ),
    Setting(
        "device_check_fault",
        str,
        None,
        "tests: abort:STAGE or fail:STAGE makes the device check's child abort or raise at that stage",
        ENV,
        scope="env",
        read_in="server/sim/opencl/devicecheck.py",
    ),
    Setting(
        "test_seed",
        int,
        None,
        "tests: the seed of the random test inputs (printed by every test that uses them)",
        ENV,
        scope="env",
        read_in="tests/conftest.py",
    ),
)
_HINTS = typing.get_type_hints(ServerConfig)
#: The settings of ServerConfig, in its field order.
CONFIG_SETTINGS: tuple[Setting, ...] = tuple(_row(f, _HINTS[f.name]) for f in fields(ServerConfig))
#: The settings table: every setting and every environment-only knob, one row each.
SETTINGS: tuple[Setting, ...] = CONFIG_SETTINGS + ENV_ONLY
SETTING: dict[str, Setting] = {row.name: row for row in SETTINGS}


def parse_listen(value: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:9464``, ``:9464`` = every interface) as (host, port)."""
    host, sep, port = value.strip().rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"metrics_listen must be HOST:PORT, got {value!r}")
    return host.strip("[]") or "0.0.0.0", int(port)


def _field_kind(f: Field[Any]) -> tuple[type, bool]:
    """(base type, optional) of a ServerConfig field (its row's kind and optional)."""
    row = SETTING[f.name]
    return row.kind, row.optional


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
    for k, v in data.items():
        row = SETTING.get(k)
        if row is None or row.scope != "server":
            raise ValueError(f"{path}: unknown configuration key {k!r}")
        out[k] = _convert(k, v, row.kind, row.optional, str(path))
    log.debug("configuration from %s: %s", path, out)
    return out


def _from_env(env: Mapping[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for row in CONFIG_SETTINGS:
        if row.env in env:
            out[row.name] = _convert(row.name, env[row.env], row.kind, row.optional, row.env)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--config`` plus one flag per setting (all default to None = not given)."""
    parser.add_argument("--config", metavar="FILE", help="TOML configuration file (default: $DRAPE_CONFIG)")
    for row in CONFIG_SETTINGS:
        flag = "--" + row.name.replace("_", "-")
        limits = f"; {row.limits_text()}" if row.low is not None or row.high is not None else ""
        help_ = f"{row.help} (default: {row.default!r}{limits}; env {row.env})"
        if row.kind is bool:
            action = argparse.BooleanOptionalAction
            parser.add_argument(flag, dest=row.name, action=action, default=None, help=help_)
        elif row.kind is list:
            help_ += "; repeatable"
            parser.add_argument(flag, dest=row.name, action="append", metavar=row.metavar, default=None, help=help_)
        else:
            choices = row.choices or None
            parser.add_argument(flag, dest=row.name, type=row.kind, default=None, choices=choices, help=help_)


def from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> ServerConfig:
    overrides = {row.name: getattr(args, row.name, None) for row in CONFIG_SETTINGS}
    return ServerConfig.load(getattr(args, "config", None), env, overrides)
