"""The fields a control may change, and those a submission shares with it, each declared once
(PROTOCOL.md sections 4 and 5): name, kind (how the codec writes and reads it and the JSON Schema
describes it), range, where it acts on the server, how two pending controls' values merge when
coalesced, and whether an empty value changes nothing. The codec, validation, schema generation,
the server's request handling (:func:`pins_only`, ``changes_params``, parameters) and its coalescing
(``merge_controls``) iterate over :data:`CONTROL_FIELDS`; the request dataclasses
(messages.ControlRequest, SubmitRequest) declare the same names, checked at import.

The fields a submission alone has (``client``, ``grid`` / ``mesh``, ``pinned``, ``links``,
``resume``) describe the cloth's shape and origin; they are not in this table."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from operator import attrgetter
from typing import Any

#: kind -> what it is on the wire. Each kind has its writer and reader (codec.py, validate.py)
#: and its schema (schemagen.py); a new field of an existing kind needs none of them changed.
FIELD_KINDS = {
    "pins": "map {indices: bin u32, targets: bin f32}",
    "colliders": "array of collider maps (COLLIDER_SHAPES)",
    "vec3": "array of 3 floats, each within +-the limit",
    "material": "map of MATERIAL_FIELDS",
    "features": "array of FEATURE_NAMES",
    "int": "integer in lo..the limit",
    "fraction": "float in [0, 1)",
    "state": "map of StateOptions",
    "quality": "one of QUALITY_PRESETS",
    "flag": "boolean, written only when true",
    "mesh": "map {vertices: bin f32, triangles: bin u32, position: vec3, rotation: 4 floats, remove: true} (1.8)",
}

#: acts -> where the server applies the field.
FIELD_ACTS = {
    "pins": "moves pinned vertices' targets (the only field of a 'pins only' control)",
    "colliders": "replaces the collider set (a non-empty one switches the colliders feature on)",
    "param": "the cloth parameter of the same name (drape.server.sim.params.ClothParams)",
    "material": "merged over the cloth's material",
    "features": "the cloth's feature set (messages.resolve_features)",
    "quality": "a quality preset, applied after the other fields",
    "state": "the publication's options (state.normals also switches the normals feature)",
    "reset": "back to the rest pose, after the other fields",
    "mesh": "the mesh collider set, re-posed, moved or removed (World.set_mesh / move_mesh), after the colliders",
}

#: merge -> how pending controls ``a`` then ``b`` of one cloth become one (server coalescing).
FIELD_MERGES = {
    "pins": "a's targets then b's, the last target of each vertex wins",
    "latest": "b's value when given, else a's",
    "update": "a's map updated with b's",
    "either": "true when either is",
    "keywise": "b's options where given, else a's",
    "features": "features, features_add and features_remove together (b's replacement wins; else the "
    "additions and removals compose)",
    "mesh": "b's when it sets, re-poses or removes a mesh, else (a move) a's mesh at b's pose",
}


@dataclass(frozen=True)
class RequestField:
    """One control field (and, when ``submit``, the submission field of the same name).

    ``wire``: its position in a control map as the encoder writes it (the test vectors' bytes;
    a new field takes the next number); the table's own order is the submission's and the JSON
    Schema's. ``lo`` and ``limit`` (a :class:`~.vocabulary.Limits` field) bound ``int`` and
    ``vec3`` kinds. ``noop_empty``: an empty value (an empty map or list, false, pins of no
    vertex) changes nothing, as if absent."""

    name: str
    kind: str
    acts: str
    merge: str
    wire: int
    submit: bool = True
    lo: int = 0
    limit: str = ""
    noop_empty: bool = False


CONTROL_FIELDS: tuple[RequestField, ...] = (
    RequestField("pins", "pins", "pins", "pins", 0, submit=False, noop_empty=True),
    RequestField("material", "material", "material", "update", 4, noop_empty=True),
    RequestField("features", "features", "features", "features", 5),
    RequestField("gravity", "vec3", "param", "latest", 2, limit="max_acceleration"),
    RequestField("wind", "vec3", "param", "latest", 3, limit="max_acceleration"),
    RequestField("iterations", "int", "param", "latest", 8, lo=0, limit="max_iterations"),
    RequestField("substeps", "int", "param", "latest", 9, lo=1, limit="max_substeps"),
    RequestField("chebyshev_rho", "fraction", "param", "latest", 10),
    RequestField("colliders", "colliders", "colliders", "latest", 1),
    RequestField("state", "state", "state", "keywise", 11),
    RequestField("quality", "quality", "quality", "latest", 12),
    RequestField("features_add", "features", "features", "features", 6, submit=False, noop_empty=True),
    RequestField("features_remove", "features", "features", "features", 7, submit=False, noop_empty=True),
    RequestField("reset", "flag", "reset", "either", 13, submit=False, noop_empty=True),
    RequestField("mesh_collider", "mesh", "mesh", "mesh", 14),  # 1.8
)
#: The control fields in the order the encoder writes (and the decoder reads) them.
CONTROL_WIRE_ORDER: tuple[RequestField, ...] = tuple(sorted(CONTROL_FIELDS, key=lambda f: f.wire))
#: The fields a submission shares with a control, in its wire order.
SUBMIT_FIELDS: tuple[RequestField, ...] = tuple(f for f in CONTROL_FIELDS if f.submit)

assert [f.wire for f in CONTROL_WIRE_ORDER] == list(range(len(CONTROL_FIELDS))), "wire positions 0..n-1"
for _f in CONTROL_FIELDS:
    assert _f.kind in FIELD_KINDS and _f.acts in FIELD_ACTS and _f.merge in FIELD_MERGES, _f.name


def field_given(value: object, f: RequestField) -> bool:
    """Whether ``value`` (a request's value of field ``f``) asks for a change: not None, and
    for a ``noop_empty`` field not empty."""
    if value is None:
        return False
    if not f.noop_empty:
        return True
    if f.kind == "pins":
        return bool(len(value.indices))  # type: ignore[attr-defined]
    return bool(value)


def _getter(names: tuple[str, ...]) -> Callable[[object], tuple[Any, ...]]:
    if not names:
        return lambda _: ()
    get = attrgetter(*names)
    return (lambda req: (get(req),)) if len(names) == 1 else get  # type: ignore[return-value]


def any_given(fs: Iterable[RequestField]) -> Callable[[object], bool]:
    """A test of whether a request asks for a change through any of ``fs`` (as field_given),
    for the per-control paths: the attributes are read in C, not one by one."""
    fs = tuple(fs)
    plain = _getter(tuple(f.name for f in fs if not f.noop_empty))
    falsy = _getter(tuple(f.name for f in fs if f.noop_empty and f.kind != "pins"))
    pins = tuple(f for f in fs if f.noop_empty and f.kind == "pins")

    def test(req: object) -> bool:
        vals = plain(req)
        if vals.count(None) != len(vals) or any(falsy(req)):
            return True
        for f in pins:
            if field_given(getattr(req, f.name), f):
                return True
        return False

    return test


_any_pins = any_given(f for f in CONTROL_FIELDS if f.acts == "pins")
_any_but_pins = any_given(f for f in CONTROL_FIELDS if f.acts != "pins")


def pins_only(req: object) -> bool:
    """Whether control ``req`` carries pin targets and nothing else (the per-tick game-loop
    control: the server's fast path, and what a 1.4 moves block can carry)."""
    return _any_pins(req) and not _any_but_pins(req)
