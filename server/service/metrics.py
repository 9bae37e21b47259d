"""Prometheus metrics of a running Server, read at scrape time.

``DrapeCollector(server)`` is a custom ``prometheus_client`` collector: each scrape calls
``server.stats()`` and ``server.info()`` (the same counters the Zenoh stats publication carries,
PROTOCOL.md section 10) and reads the per-phase histograms of the server's PhaseTimers
(drape.server.service.telemetry). Nothing is counted twice and the tick loop does no extra
work for metrics: a scrape costs a few short lock acquisitions and no per-cloth work of its own.

``METRICS`` lists every metric family (name without the ``_total`` a counter gets in the
exposition, type, help); docs/operations.md shows the same list. ``exposition(server)`` renders the
text format; ``drape.server.service.ops`` serves ``registry(...)`` on ``/metrics``, with its
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

from .telemetry import PHASES, PhaseTimer

log = logging.getLogger(__name__)

PREFIX = "drape"

#: Every family this module exports: (name, type, help). Counters appear as ``<name>_total``.
METRICS: tuple[tuple[str, str, str], ...] = (
    ("drape_server", "info", "The server: id, solver, OpenCL device, protocol version, namespace"),
    ("drape_up_seconds", "gauge", "Seconds since the server started"),
    ("drape_ready", "gauge", "1 when /readyz answers 200 (device built, Zenoh up, ticking on time), else 0"),
    ("drape_tick_age_seconds", "gauge", "Seconds since the tick counter last advanced (as the operator listener saw)"),
    ("drape_tick_rate_hertz", "gauge", "Configured ticks per second"),
    ("drape_tick", "gauge", "The last tick number"),
    ("drape_ticks", "counter", "Ticks run"),
    ("drape_missed_ticks", "counter", "Tick deadlines skipped because a tick overran"),
    ("drape_skipped_frames", "counter", "Frames the publisher had not sent when the next was ready (coalesced)"),
    (
        "drape_tick_phase_seconds",
        "histogram",
        "Duration of each tick phase (apply, solve, readback, encode, "
        "publish; tick = apply to readback, the tick's own work)",
    ),
    ("drape_cloths", "gauge", "Cloths on the server (accepted, including those still being cooked)"),
    ("drape_clients", "gauge", "Clients owning cloths"),
    ("drape_alive_clients", "gauge", "Clients whose liveliness token is present"),
    ("drape_vertices", "gauge", "Vertices of all cloths"),
    ("drape_links", "gauge", "Links of all cloths (when the server reports it)"),
    ("drape_published_states", "counter", "Cloth states published (bundled ones included)"),
    ("drape_published_bytes", "counter", "Bytes of state payloads published (when the server reports it)"),
    ("drape_unwatched_states", "counter", "States not encoded because nobody subscribed to their key"),
    ("drape_publish_errors", "counter", "States that failed to publish"),
    ("drape_bundles_published", "counter", "Bundle publications (protocol 1.1)"),
    ("drape_batch_items", "counter", "Items received in batch control requests"),
    ("drape_requests", "counter", "Requests received, by queryable"),
    ("drape_errors", "counter", "Error replies, by error code"),
    ("drape_overload_refusals", "counter", "Submits refused because the server is overloaded"),
    ("drape_nan_resets", "counter", "Cloths reset to their rest pose because they went non-finite"),
    ("drape_reclaimed_cloths", "counter", "Cloths removed because their client's liveliness token vanished"),
    ("drape_nan_removals", "counter", "Cloths removed because they kept going non-finite (when the server reports it)"),
    ("drape_controls_applied", "counter", "Controls applied by the tick thread (when the server reports it)"),
    (
        "drape_controls_coalesced",
        "counter",
        "Controls replaced by a newer one for the same cloth before a tick (when the server reports it)",
    ),
    ("drape_batch_moves", "counter", "Moves received in batch controls' moves blocks (protocol 1.4)"),
    ("drape_moves_applied", "counter", "Moves applied by the tick thread (protocol 1.4)"),
    (
        "drape_move_blocks_superseded",
        "counter",
        "Moves blocks replaced by an identical newer one before their tick (protocol 1.4)",
    ),
    ("drape_quality_cloths", "gauge", "Cloths at each quality preset now"),
    ("drape_quality_degraded_cloths", "gauge", "Cloths below the preset their client asked for"),
    ("drape_quality_degraded_seconds", "counter", "Seconds with any cloth degraded"),
    ("drape_quality_changes", "counter", "Adaptive quality preset changes"),
)

#: stats() key -> counter name, for the plain cumulative counters.
_COUNTERS = {
    "ticks": "drape_ticks",
    "missed_ticks": "drape_missed_ticks",
    "skipped_frames": "drape_skipped_frames",
    "published": "drape_published_states",
    "unwatched": "drape_unwatched_states",
    "publish_errors": "drape_publish_errors",
    "bundles": "drape_bundles_published",
    "batch_items": "drape_batch_items",
    "nan_resets": "drape_nan_resets",
    "reclaimed": "drape_reclaimed_cloths",
}
#: stats() key -> gauge name, for the current load.
_GAUGES = {
    "cloths": "drape_cloths",
    "clients": "drape_clients",
    "alive_clients": "drape_alive_clients",
    "vertices": "drape_vertices",
}
#: stats() key -> (name, type) of the counters and gauges exported only when the stats carry them.
OPTIONAL = {
    "published_bytes": ("drape_published_bytes", "counter"),
    "links": ("drape_links", "gauge"),
    "nan_removals": ("drape_nan_removals", "counter"),
    "controls_applied": ("drape_controls_applied", "counter"),
    "controls_coalesced": ("drape_controls_coalesced", "counter"),
    "batch_moves": ("drape_batch_moves", "counter"),
    "moves_applied": ("drape_moves_applied", "counter"),
    "move_blocks_superseded": ("drape_move_blocks_superseded", "counter"),
}

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
    for key, name in _COUNTERS.items():
        yield _counter(name, stats.get(key))
    for key, name in _GAUGES.items():
        yield _gauge(name, stats.get(key))
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
    ``() -> (ready, seconds since the tick counter advanced)`` (drape.server.service.ops)."""

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
