"""Prometheus metrics of a running Server, read at scrape time.

``DrapeCollector(server)`` is a custom ``prometheus_client`` collector: each scrape calls
``server.stats()`` and ``server.info()`` (the same counters the Zenoh stats publication carries,
PROTOCOL.md section 10) and reads the per-phase histograms of the server's PhaseTimers
(drape.server.service.process.telemetry). Nothing is counted twice and the tick loop does no extra
work for metrics: a scrape costs a few short lock acquisitions and no per-cloth work of its own.

``METRICS`` lists every metric family (name without the ``_total`` a counter gets in the
exposition, type, help); docs/operations.md shows the same list. The families of stats fields
take their type and help from the stats table (drape.client.protocol.stats), ``STAT_METRICS``
names them. ``exposition(server)`` renders the
text format; ``drape.server.service.process.ops`` serves ``registry(...)`` on ``/metrics``, with its
readiness probe behind ``drape_ready`` and ``drape_tick_age_seconds``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, Protocol

from prometheus_client import CollectorRegistry, ProcessCollector, generate_latest
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector
from prometheus_client.utils import floatToGoString

from drape.client import protocol as P
from drape.client.protocol.stats import stat_field

from .telemetry import PHASES, PhaseTimer

log = logging.getLogger(__name__)

PREFIX = "drape"

#: stats field -> the metric family it is exported as, when the stats carry it; the family's type
#: (counter or gauge) and help are the field's (drape.client.protocol.stats.STATS_FIELDS).
STAT_METRICS: dict[str, str] = {
    "cloths": "drape_cloths",
    "clients": "drape_clients",
    "alive_clients": "drape_alive_clients",
    "vertices": "drape_vertices",
    "links": "drape_links",
    "ticks": "drape_ticks",
    "missed_ticks": "drape_missed_ticks",
    "skipped_frames": "drape_skipped_frames",
    "published": "drape_published_states",
    "published_bytes": "drape_published_bytes",
    "unwatched": "drape_unwatched_states",
    "publish_errors": "drape_publish_errors",
    "bundles": "drape_bundles_published",
    "batch_items": "drape_batch_items",
    "overload_refusals": "drape_overload_refusals",  # always: from the error replies when not counted apart
    "nan_resets": "drape_nan_resets",
    "reclaimed": "drape_reclaimed_cloths",
    "nan_removals": "drape_nan_removals",
    "controls_applied": "drape_controls_applied",
    "controls_coalesced": "drape_controls_coalesced",
    "batch_moves": "drape_batch_moves",
    "moves_applied": "drape_moves_applied",
    "move_blocks": "drape_move_blocks",
    "move_blocks_superseded": "drape_move_blocks_superseded",
    "keyframes": "drape_keyframes",
    "keyframe_queries": "drape_keyframe_queries",
    "rate_published": "drape_rate_published_states",
    "rate_unserved": "drape_rate_unserved_states",
}


def _from_stats(key: str, name: str, kind: str | None = None) -> tuple[str, str, str]:
    """(name, type, help) of the family exporting stats field ``key``: the field's meaning as help."""
    field = stat_field(key)
    return name, kind or field.kind, field.meaning


#: Every family this module exports: (name, type, help). Counters appear as ``<name>_total``.
METRICS: tuple[tuple[str, str, str], ...] = (
    ("drape_server", "info", "The server: id, solver, OpenCL device, protocol version, namespace"),
    _from_stats("uptime_s", "drape_up_seconds", "gauge"),
    ("drape_ready", "gauge", "1 when /readyz answers 200 (device built, Zenoh up, ticking on time), else 0"),
    ("drape_tick_age_seconds", "gauge", "Seconds since the tick counter last advanced (as the operator listener saw)"),
    _from_stats("tick_rate", "drape_tick_rate_hertz", "gauge"),
    _from_stats("tick", "drape_tick", "gauge"),
    *(_from_stats(key, name) for key, name in STAT_METRICS.items()),
    (
        "drape_tick_phase_seconds",
        "histogram",
        "Duration of each tick phase (apply, solve, readback, encode, "
        "publish; tick = apply to readback, the tick's own work)",
    ),
    _from_stats("requests", "drape_requests", "counter"),
    _from_stats("errors", "drape_errors", "counter"),
    ("drape_quality_cloths", "gauge", "Cloths at each quality preset now"),
    ("drape_quality_degraded_cloths", "gauge", "Cloths below the preset their client asked for"),
    ("drape_quality_degraded_seconds", "counter", "Seconds with any cloth degraded"),
    ("drape_quality_changes", "counter", "Adaptive quality preset changes"),
    (
        "drape_kernel_builds",
        "counter",
        "OpenCL programs built in the server process, by the thread that built them (tick: a stalled tick)",
    ),
    ("drape_build_child_cloths", "counter", "First cloths of a kernel group handed to the build child, by outcome"),
)

#: stats key -> (name, type) of the families exported only when the stats carry the key: every
#: family of STAT_METRICS but drape_overload_refusals.
OPTIONAL = {key: (name, stat_field(key).kind) for key, name in STAT_METRICS.items() if key != "overload_refusals"}

_HELP = {name: help_ for name, _, help_ in METRICS}


class StatsSource(Protocol):
    """What the collector reads: a Server, or anything with the same three things."""

    def stats(self) -> dict[str, Any]: ...

    def info(self) -> dict[str, Any]: ...


def phase_timers(server: Any) -> Mapping[str, PhaseTimer]:
    """The server's per-phase timers: ``server.phase_timers`` (a mapping phase -> PhaseTimer, or
    a method returning one) when the server offers it, else ``timers``, else the ``_timers`` it
    kept before the service split; {} when none."""
    for name in ("phase_timers", "timers", "_timers"):
        timers = getattr(server, name, None)
        if callable(timers):
            timers = timers()
        if timers:
            return timers
    return {}


#: the roles ``drape_kernel_builds_total`` always shows (0 when none): the tick's is the one that must stay 0
BUILD_THREADS = ("main", "cook", "tick")


def thread_role(name: str) -> str:
    """A server thread's role from its name: ``drape-tick-<server id>`` -> ``tick``, the main thread
    ``main``, any other ``other``."""
    if name == "MainThread":
        return "main"
    parts = name.split("-")
    return parts[1] if len(parts) > 2 and parts[0] == "drape" else "other"


def kernel_builds(server: Any) -> dict[str, int]:
    """Programs the server's OpenCL Device built, by :func:`thread_role` (``Device.builds``);
    0 for each of ``BUILD_THREADS`` on a server without one (the reference solver)."""
    world = getattr(getattr(server, "ticker", None), "world", None)
    counts = dict.fromkeys(BUILD_THREADS, 0)
    for _, thread in list(getattr(getattr(world, "dev", None), "builds", ())):
        role = thread_role(thread)
        counts[role] = counts.get(role, 0) + 1
    return counts


def build_child_cloths(server: Any) -> dict[str, int]:
    """The cook thread's build child (``BuildHelper``): cloths it built and ran (``ran``), that fell
    back to a build in the server (``failed``), or that it refused past ``build_memory_mb``
    (``memory_killed``); all 0 without a helper (``build_in_child`` other than "always")."""
    helper = getattr(getattr(server, "cook", None), "helper", None)
    return {
        "ran": int(getattr(helper, "runs", 0)),
        "failed": int(getattr(helper, "failures", 0)),
        "memory_killed": int(getattr(helper, "memory_kills", 0)),
    }


#: the families counted from the server's parts rather than its stats, each split by one label:
#: family -> (its label, what reads the counts by label value); the collector and ``drape chaos``
#: (chaos_harness.ChaosServer.build_counts) both go by it
LABELLED: dict[str, tuple[str, Callable[[Any], dict[str, int]]]] = {
    "drape_kernel_builds": ("thread", kernel_builds),
    "drape_build_child_cloths": ("outcome", build_child_cloths),
}


def overload_refusals(stats: Mapping[str, Any]) -> int:
    """Submits refused for overload: the stats' ``overload_refusals`` when the server counts them
    apart, else its ``overloaded`` error replies (0 for a server older than protocol 1.2)."""
    if "overload_refusals" in stats:
        return int(_num(stats["overload_refusals"]))
    return int(_num((stats.get("errors") or {}).get(getattr(P, "ERR_OVERLOADED", "overloaded"), 0)))


def _num(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return 0.0


class DrapeCollector(Collector):
    """The metric families of one server, computed from its stats at each scrape."""

    def __init__(self, server: StatsSource, namespace: str | None = None) -> None:
        self.server = server
        self.namespace = namespace

    def describe(self) -> Iterable[Metric]:
        return []  # computed at scrape time: registering must not call the server

    def collect(self) -> Iterator[Metric]:
        stats = self.server.stats()
        try:
            info = self.server.info()
        except Exception as e:  # info is descriptive only: never lose the counters for it
            log.debug("info() failed during a scrape: %s", e)
            info = {}
        yield from families(stats, info, phase_timers(self.server), self.namespace)
        for name, (label, read) in LABELLED.items():
            fam = CounterMetricFamily(name, _HELP[name], labels=[label])
            for value, n in read(self.server).items():
                fam.add_metric([value], n)
            yield fam


def families(
    stats: Mapping[str, Any], info: Mapping[str, Any], timers: Mapping[str, PhaseTimer], namespace: str | None = None
) -> Iterator[Metric]:
    """Every metric family of METRICS from one stats() dict, one info() dict and the timers."""
    server = str(stats.get("server") or info.get("server") or "")
    i = InfoMetricFamily("drape_server", _HELP["drape_server"])
    i.add_metric(
        [],
        {
            "server": server,
            "solver": str(info.get("solver", "")),
            "device": str(info.get("device", "")),
            "version": str(info.get("version", P.VERSION_STRING)),
            "namespace": str(namespace if namespace is not None else info.get("namespace", "")),
        },
    )
    yield i
    yield _gauge("drape_up_seconds", stats.get("uptime_s"))
    yield _gauge("drape_tick_rate_hertz", stats.get("tick_rate", info.get("tick_rate")))
    yield _gauge("drape_tick", stats.get("tick"))
    for key, (name, kind) in OPTIONAL.items():
        if key in stats:
            yield (_counter if kind == "counter" else _gauge)(name, stats[key])

    requests = CounterMetricFamily("drape_requests", _HELP["drape_requests"], labels=["kind"])
    for kind, n in sorted((stats.get("requests") or {}).items()):
        requests.add_metric([str(kind)], _num(n))
    yield requests
    errors_by_code = dict(stats.get("errors") or {})
    errors = CounterMetricFamily("drape_errors", _HELP["drape_errors"], labels=["code"])
    for code in sorted(set(P.ERROR_CODES) | set(errors_by_code)):
        errors.add_metric([str(code)], _num(errors_by_code.get(code, 0)))
    yield errors
    yield _counter("drape_overload_refusals", overload_refusals(stats))

    quality = stats.get("quality") or {}
    presets = dict(quality.get("presets") or {})
    q = GaugeMetricFamily("drape_quality_cloths", _HELP["drape_quality_cloths"], labels=["preset"])
    for name in list(P.QUALITY_PRESETS) + sorted(set(presets) - set(P.QUALITY_PRESETS)):
        q.add_metric([name], _num(presets.get(name, 0)))
    yield q
    yield _gauge("drape_quality_degraded_cloths", quality.get("degraded"))
    yield _counter("drape_quality_degraded_seconds", quality.get("degraded_s"))
    yield _counter("drape_quality_changes", quality.get("changes"))

    h = HistogramMetricFamily("drape_tick_phase_seconds", _HELP["drape_tick_phase_seconds"], labels=["phase"])
    for phase in list(PHASES) + sorted(set(timers) - set(PHASES)):
        timer = timers.get(phase)
        if timer is None:
            continue
        buckets, total, _ = timer.histogram()
        h.add_metric([phase], [(floatToGoString(b), n) for b, n in buckets], total)
    yield h


def _gauge(name: str, value: Any) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, _HELP[name], value=_num(value))


def _counter(name: str, value: Any) -> CounterMetricFamily:
    return CounterMetricFamily(name, _HELP[name], value=_num(value))


class ReadinessCollector(Collector):
    """``drape_ready`` and ``drape_tick_age_seconds`` from a readiness probe
    ``() -> (ready, seconds since the tick counter advanced)`` (drape.server.service.process.ops)."""

    def __init__(self, probe: Callable[[], tuple[bool, float]]) -> None:
        self.probe = probe

    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterator[Metric]:
        ready, age = self.probe()
        yield _gauge("drape_ready", 1.0 if ready else 0.0)
        yield _gauge("drape_tick_age_seconds", age)


def registry(
    server: StatsSource,
    process: bool = True,
    namespace: str | None = None,
    readiness: Callable[[], tuple[bool, float]] | None = None,
) -> CollectorRegistry:
    """A registry holding the server's collector, the readiness gauges when given a probe, and
    the process' CPU, memory and file descriptors (``process_*``) when ``process``."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(DrapeCollector(server, namespace))
    if readiness is not None:
        reg.register(ReadinessCollector(readiness))
    if process:
        ProcessCollector(registry=reg)
    return reg


def exposition(server: StatsSource) -> bytes:
    """The Prometheus text exposition of one server's metrics (no process metrics)."""
    return generate_latest(registry(server, process=False))
