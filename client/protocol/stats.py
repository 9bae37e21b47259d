"""The fields of the stats publication (PROTOCOL.md section 10): one table, read by the schema
generator (the ``stats`` JSON Schema), the server (which fields it publishes and which registry
counters it reports) and the Prometheus exposition (which stats field each metric family reads,
its type and its help text). A field added here is published, described and exported; a test
(tests/service/test_stats_fields.py) fails when any of them diverges.

Stats are informational: fields may be added in any minor version, and a reader treats a missing
one as unknown.
"""

from __future__ import annotations

from dataclasses import dataclass

#: JSON types of stats fields: ``integer`` (>= 0), ``number``, ``id`` (a server id), ``counts``
#: (a map of name -> integer), ``map`` (a map of name -> map), ``object`` (a map of its own shape).
STAT_TYPES = ("integer", "number", "id", "counts", "map", "object")
#: What a field is: ``counter`` (cumulative since the server started, counted by its registry),
#: ``gauge`` (a current value), ``info`` (descriptive: who, when, the tick), ``detail`` (a map).
STAT_KINDS = ("counter", "gauge", "info", "detail")


@dataclass(frozen=True)
class StatField:
    name: str  # the key in the stats map
    type: str  # one of STAT_TYPES
    kind: str  # one of STAT_KINDS
    meaning: str  # one line: PROTOCOL.md's meaning and the help of the field's Prometheus metric
    required: bool = False  # every stats message carries it
    reported: bool = True  # False: readers use it when a server reports it; the Drape server does not


STATS_FIELDS: tuple[StatField, ...] = (
    StatField("server", "id", "info", "The server's id", required=True),
    StatField("tick", "integer", "info", "The last tick number", required=True),
    StatField("time_ns", "integer", "info", "Server time of the message (ns since the Unix epoch)"),
    StatField("uptime_s", "number", "info", "Seconds since the server started"),
    StatField("tick_rate", "number", "info", "Configured ticks per second"),
    StatField("cloths", "integer", "gauge", "Cloths on the server (accepted, including those still being cooked)"),
    StatField("clients", "integer", "gauge", "Clients owning cloths"),
    StatField("alive_clients", "integer", "gauge", "Clients whose liveliness token is present"),
    StatField("vertices", "integer", "gauge", "Vertices of all cloths"),
    StatField("links", "integer", "gauge", "Links of all cloths (when the server reports it)", reported=False),
    StatField("ticks", "integer", "counter", "Ticks run"),
    StatField("missed_ticks", "integer", "counter", "Tick deadlines skipped because a tick overran"),
    StatField(
        "skipped_frames", "integer", "counter", "Frames the publisher had not sent when the next was ready (coalesced)"
    ),
    StatField("nan_resets", "integer", "counter", "Cloths reset to their rest pose because they went non-finite"),
    StatField("reclaimed", "integer", "counter", "Cloths removed because their client's liveliness token vanished"),
    StatField("published", "integer", "counter", "Cloth states published (bundled ones included)"),
    StatField(
        "published_bytes",
        "integer",
        "counter",
        "Bytes of state payloads published (when the server reports it)",
    ),
    StatField("unwatched", "integer", "counter", "States not encoded because nobody subscribed to their key"),
    StatField("publish_errors", "integer", "counter", "States that failed to publish"),
    StatField("bundles", "integer", "counter", "Bundle publications (protocol 1.1)"),
    StatField("batch_items", "integer", "counter", "Items received in batch control requests"),
    StatField("overload_refusals", "integer", "counter", "Submits refused because the server is overloaded"),
    StatField(
        "nan_removals",
        "integer",
        "counter",
        "Cloths removed because they kept going non-finite",
    ),
    StatField("controls_applied", "integer", "counter", "Controls applied by the tick thread"),
    StatField(
        "controls_coalesced",
        "integer",
        "counter",
        "Controls replaced by a newer one for the same cloth before a tick",
    ),
    StatField("batch_moves", "integer", "counter", "Moves received in batch controls' moves blocks (protocol 1.4)"),
    StatField("keyframes", "integer", "counter", "Intra-coded predictive states written (protocol 1.5)"),
    StatField("keyframe_queries", "integer", "counter", "Keyframe queries answered (protocol 1.5)"),
    StatField("rate_published", "integer", "counter", "Cloth states published on decimated keys (protocol 1.8)"),
    StatField(
        "rate_unserved",
        "integer",
        "counter",
        "Cloth states of watched decimated keys not published: predictive on a device-encoded frame (protocol 1.8)",
    ),
    StatField("moves_applied", "integer", "counter", "Moves applied by the tick thread (protocol 1.4)"),
    StatField("move_blocks", "integer", "counter", "Moves blocks applied by the tick thread (protocol 1.4)"),
    StatField(
        "move_blocks_superseded",
        "integer",
        "counter",
        "Moves blocks replaced by an identical newer one before their tick (protocol 1.4)",
    ),
    StatField("requests", "counts", "detail", "Requests received, by queryable"),
    StatField("errors", "counts", "detail", "Error replies, by error code"),
    StatField(
        "phases", "map", "detail", "For each tick phase: mean and max ms over the last period, count, total mean"
    ),
    StatField("quality", "object", "detail", "Adaptive quality: cloths at each preset, degradation, changes"),
)

#: The cumulative counters a server's registry keeps and its stats report (the reported counters).
STAT_COUNTERS: tuple[str, ...] = tuple(f.name for f in STATS_FIELDS if f.kind == "counter" and f.reported)


def stat_field(name: str) -> StatField:
    """The field called ``name`` (KeyError when the stats have none)."""
    for f in STATS_FIELDS:
        if f.name == name:
            return f
    raise KeyError(name)
