"""Machine-readable descriptions for clients in other languages, generated from this package:
a JSON Schema (draft 2020-12) for every msgpack map (requests, replies, stats; here) and a C
header of the binary layouts (the DRPS state and DRPB bundle headers as packed structs, with the
constants; cheader.py). This module writes both.

    python -m drape.client.protocol.schemagen      # rewrites client/protocol/schema/*.json and drape_wire.h

Everything comes from the vocabulary, limits, error codes and struct field tables of the other
modules; nothing is transcribed. JSON has no binary type, so a msgpack ``bin`` field appears in
the schemas in the JSON form the test vectors use, ``{"u32": [...]}`` or ``{"f32": [...]}`` (its
little-endian elements), marked ``"x-msgpack": "bin"``. What a schema cannot say (finite floats,
indices below the vertex count, equal pin and target counts) is the decoder's job: PROTOCOL.md
states it, and :mod:`.codec` enforces it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .cheader import c_header
from .errors import ERROR_CODES
from .keys import ID_RE, PROTOCOL_MAJOR, SCENE_ANYONE, TOKEN_RE, VERSION_STRING
from .requestfields import CONTROL_FIELDS, SUBMIT_FIELDS, RequestField
from .stats import STATS_FIELDS
from .vocabulary import (
    COLLIDER_SHAPES,
    DEFAULT_LIMITS,
    ENCODINGS,
    FEATURE_NAMES,
    MATERIAL_DEFAULTS,
    MATERIAL_FIELDS,
    MAX_MAP_KEYS,
    MAX_SCENE_COLLIDERS,
    MAX_SCENE_MEMBERS,
    MESH_MAX_TRIANGLES,
    MESH_MAX_VERTICES,
    ORIENTATIONS,
    QUALITY_PRESETS,
    STEP_MAX,
    STEP_MIN,
    LinkSpec,
)

HERE = Path(__file__).resolve().parent
SCHEMA_DIR = HERE / "schema"
C_HEADER = HERE / "drape_wire.h"
BASE_URI = "https://drape.invalid/protocol/1/"  # schema ids only; nothing is fetched
L = DEFAULT_LIMITS
U64_MAX = (1 << 64) - 1


def _nullable(s: dict[str, Any]) -> dict[str, Any]:
    """An optional request field: absent, nil, or ``s``."""
    return {"anyOf": [s, {"type": "null"}]}


def _num(lo: float | None = None, hi: float | None = None, lo_inclusive: bool = True) -> dict[str, Any]:
    s: dict[str, Any] = {"type": "number", "description": "any msgpack int or float, finite"}
    if lo is not None:
        s["minimum" if lo_inclusive else "exclusiveMinimum"] = lo
    if hi is not None:
        s["maximum"] = hi
    return s


def _int(lo: int, hi: int) -> dict[str, Any]:
    return {"type": "integer", "minimum": lo, "maximum": hi}


def _vec3(bound: float) -> dict[str, Any]:
    return {"type": "array", "items": _num(-bound, bound), "minItems": 3, "maxItems": 3}


def _bin(elem: str, max_items: int | None = None) -> dict[str, Any]:
    item = {"u32": _int(0, (1 << 32) - 1), "f32": {"type": "number"}}[elem]
    arr: dict[str, Any] = {"type": "array", "items": item}
    if max_items is not None:
        arr["maxItems"] = max_items
    return {
        "type": "object",
        "x-msgpack": "bin",
        "x-element": elem,
        "description": f"msgpack bin of little-endian {elem} values, here in JSON form",
        "properties": {elem: arr},
        "required": [elem],
        "additionalProperties": False,
    }


def _obj(props: dict[str, Any], required: tuple[str, ...] = (), closed: bool = False, **extra: Any) -> dict[str, Any]:
    s: dict[str, Any] = {"type": "object", "properties": props, "maxProperties": MAX_MAP_KEYS}
    if required:
        s["required"] = list(required)
    if closed:
        s["additionalProperties"] = False
    s.update(extra)
    return s


def _defs() -> dict[str, Any]:
    cap = L.max_material_value
    material = {}
    for name, (width, lo, lo_inc, hi) in MATERIAL_FIELDS.items():
        one = _num(lo, cap if hi is None else hi, lo_inc)
        s = one if width == 1 else {"type": "array", "items": one, "minItems": width, "maxItems": width}
        material[name] = {**_nullable(s), "default": MATERIAL_DEFAULTS[name]}
    bound = L.max_coordinate
    colliders = {
        shape.name: {f.name: _vec3(bound) if f.vec3 else _num(-bound if f.signed else 0.0, bound) for f in shape.fields}
        for shape in COLLIDER_SHAPES
    }
    return {
        "version": {
            "type": "array",
            "description": "[major, minor]",
            "minItems": 2,
            "maxItems": 2,
            "prefixItems": [{"const": PROTOCOL_MAJOR}, _int(0, 255)],
            "items": _int(0, 255),
        },
        "rid": _int(0, U64_MAX),
        "id": {"type": "string", "pattern": ID_RE.pattern},
        "token": {"type": "string", "pattern": TOKEN_RE.pattern},
        "features": {"type": "array", "items": {"enum": list(FEATURE_NAMES)}, "maxItems": L.max_features},
        "material": _obj(material),
        "collider": {"oneOf": [_obj({"type": {"const": k}, **v}, ("type", *v)) for k, v in colliders.items()]},
        "colliders": {"type": "array", "items": {"$ref": "#/$defs/collider"}, "maxItems": L.max_colliders},
        "pins": _obj(
            {"indices": _bin("u32", L.max_pin_updates), "targets": _bin("f32", 3 * L.max_pin_updates)},
            ("indices", "targets"),
        ),
        "state": _obj(
            {
                "normals": _nullable({"type": "boolean"}),
                "encoding": _nullable({"enum": list(ENCODINGS)}),
                "bundle": _nullable({"type": "boolean"}),
                "step": _nullable({"type": "number", "minimum": STEP_MIN, "maximum": STEP_MAX}),
            }
        ),
        "quality": {"enum": list(QUALITY_PRESETS)},
        "mesh_collider": _obj(
            {
                "vertices": _bin("f32", 3 * MESH_MAX_VERTICES),
                "triangles": _bin("u32", 3 * MESH_MAX_TRIANGLES),
                "position": _vec3(bound),
                "rotation": {"type": "array", "items": _num(), "minItems": 4, "maxItems": 4},
                "remove": {"const": True},
            },
            closed=True,
            description="1.8: a mesh collider (PROTOCOL.md 5.4): {remove: true} alone; vertices and "
            "triangles (a new mesh), vertices alone (a re-pose) or neither (a rigid move), with the pose "
            "(position, rotation as w, x, y, z)",
        ),
        "tick": _int(0, U64_MAX),
        "error": _obj(
            {
                "code": {
                    "type": "string",
                    "description": f"known codes: {', '.join(ERROR_CODES)}; treat unknown ones as errors",
                },
                "message": {"type": "string"},
            },
            ("code",),
        ),
    }


#: kind -> the JSON Schema of a field of that kind (requestfields.FIELD_KINDS), nullable.
_KIND_SCHEMAS: dict[str, Callable[[RequestField], dict[str, Any]]] = {
    "pins": lambda f: {"$ref": "#/$defs/pins"},
    "colliders": lambda f: {"$ref": "#/$defs/colliders"},
    "vec3": lambda f: _vec3(getattr(L, f.limit)),
    "material": lambda f: {"$ref": "#/$defs/material"},
    "features": lambda f: {"$ref": "#/$defs/features"},
    "int": lambda f: _int(f.lo, getattr(L, f.limit)),
    "fraction": lambda f: {"type": "number", "minimum": 0, "exclusiveMaximum": 1},
    "state": lambda f: {"$ref": "#/$defs/state"},
    "quality": lambda f: {"$ref": "#/$defs/quality"},
    "flag": lambda f: {"type": "boolean"},
    "mesh": lambda f: {"$ref": "#/$defs/mesh_collider"},
}


def _solver_fields() -> dict[str, Any]:
    """The fields a submission shares with a control."""
    return {f.name: _nullable(_KIND_SCHEMAS[f.kind](f)) for f in SUBMIT_FIELDS}


def _control_item() -> dict[str, Any]:
    return {
        "cloth": {"$ref": "#/$defs/id"},
        "token": {"$ref": "#/$defs/token"},
        **{f.name: _nullable(_KIND_SCHEMAS[f.kind](f)) for f in CONTROL_FIELDS},
    }


def _head() -> dict[str, Any]:
    return {"v": {"$ref": "#/$defs/version"}, "rid": {"$ref": "#/$defs/rid"}}


def _reply(props: dict[str, Any], required: tuple[str, ...]) -> dict[str, Any]:
    return _obj({**_head(), "ok": {"const": True}, **props}, ("v", "ok", *required))


#: The JSON Schema of each stats field type (drape.client.protocol.stats.STAT_TYPES).
_STAT_TYPE_SCHEMAS: dict[str, dict[str, Any]] = {
    "integer": {"type": "integer", "minimum": 0},
    "number": {"type": "number"},
    "id": {"$ref": "#/$defs/id"},
    "counts": {"type": "object", "additionalProperties": {"type": "integer"}},
    "map": {"type": "object", "additionalProperties": {"type": "object"}},
    "object": {"type": "object"},
}


def _stats() -> dict[str, Any]:
    """The stats publication: every field of the stats table (open: fields may be added)."""
    props = {**_head(), **{f.name: {**_STAT_TYPE_SCHEMAS[f.type], "description": f.meaning} for f in STATS_FIELDS}}
    return _obj(props, ("v", *(f.name for f in STATS_FIELDS if f.required)))


def schemas() -> dict[str, dict[str, Any]]:
    """Every message's JSON Schema, by message name (the ``message`` of the test vectors)."""
    bound = L.max_coordinate
    link = {k: _nullable({"type": "boolean", "default": v}) for k, v in vars(LinkSpec()).items()}
    grid = _obj(
        {
            "cols": _int(1, L.max_vertices),
            "rows": _int(1, L.max_vertices),
            "width": _nullable(_num(0.0, bound, False)),
            "height": _nullable(_num(0.0, bound, False)),
            "orientation": _nullable({"enum": list(ORIENTATIONS)}),
            "origin": _nullable(_vec3(bound)),
        },
        ("cols", "rows"),
    )
    mesh = _obj(
        {"vertices": _bin("f32", 3 * L.max_vertices), "triangles": _bin("u32", 3 * L.max_triangles)},
        ("vertices", "triangles"),
    )
    resume = _obj(
        {
            "positions": _bin("f32", 3 * L.max_vertices),
            "velocities": _nullable(_bin("f32", 3 * L.max_vertices)),
            "tick": _nullable(_int(0, U64_MAX)),
            "from_server": _nullable({"$ref": "#/$defs/id"}),
            "cloth": _nullable({"$ref": "#/$defs/id"}),
        },
        ("positions",),
        description="1.3: continue the cloth from this state (positions within max_coordinate, "
        "velocities within max_acceleration m/s, both of the cloth's vertex count, finite)",
    )
    moves = _obj(
        {
            "cloths": {"type": "array", "items": {"$ref": "#/$defs/id"}, "minItems": 1, "maxItems": L.max_batch_moves},
            "tokens": {
                "type": "array",
                "items": {"$ref": "#/$defs/token"},
                "minItems": 1,
                "maxItems": L.max_batch_moves,
            },
            "indices": _bin("u32", L.max_pin_updates),
            "targets": _bin("f32", 3 * L.max_pin_updates * L.max_batch_moves),
        },
        ("cloths", "tokens", "indices", "targets"),
        description="1.4: pin moves of many cloths (PROTOCOL.md 5.1.1): as many tokens as cloths, 1.. distinct "
        "indices shared by every cloth, targets n x k x 3 finite values within max_coordinate, cloth by cloth",
    )
    out: dict[str, dict[str, Any]] = {
        "submit": _obj(
            {
                **_head(),
                "client": {"$ref": "#/$defs/id"},
                "grid": grid,
                "mesh": mesh,
                "pinned": _nullable(_bin("u32", L.max_vertices)),
                "links": _nullable(_obj(link)),
                **_solver_fields(),
                "resume": _nullable(resume),
                "scene": _nullable({"$ref": "#/$defs/id", "description": "1.7: the scene the cloth collides in"}),
            },
            ("v", "client"),
            oneOf=[{"required": ["grid"]}, {"required": ["mesh"]}],
        ),
        "scene": _obj(
            {
                **_head(),
                "client": {"$ref": "#/$defs/id"},
                "scene": {"$ref": "#/$defs/id"},
                "colliders": _nullable(
                    {"type": "array", "items": {"$ref": "#/$defs/collider"}, "maxItems": MAX_SCENE_COLLIDERS}
                ),
                "members": _nullable(
                    {
                        "type": "array",
                        "maxItems": MAX_SCENE_MEMBERS,
                        "items": {"anyOf": [{"$ref": "#/$defs/id"}, {"const": SCENE_ANYONE}]},
                    }
                ),
                "mesh_collider": _nullable({"$ref": "#/$defs/mesh_collider"}),
            },
            ("v", "client", "scene"),
            description="1.7: a scene's colliders and members, from its owner (PROTOCOL.md 5.3)",
        ),
        "control": _obj({**_head(), **_control_item()}, ("v", "cloth", "token")),
        "control_batch": _obj(
            {
                **_head(),
                "client": {"$ref": "#/$defs/id"},
                "items": {
                    "type": "array",
                    "maxItems": L.max_batch_items,
                    "items": _obj(_control_item(), ("cloth", "token")),
                },
                "moves": _nullable(moves),
            },
            ("v", "client"),
            description="items: 1..max_batch_items controls; with moves (1.4) also absent or empty",
            anyOf=[
                {"required": ["items"], "properties": {"items": {"minItems": 1}}},
                {"required": ["moves"], "properties": {"moves": {"type": "object"}}},
            ],
        ),
        "remove": _obj(
            {**_head(), "cloth": {"$ref": "#/$defs/id"}, "token": {"$ref": "#/$defs/token"}}, ("v", "cloth", "token")
        ),
        "info": _obj(_head(), ("v",)),
        "reply_submit": _reply(
            {
                "cloth": {"$ref": "#/$defs/id"},
                "token": {"$ref": "#/$defs/token"},
                "key": {"type": "string"},
                "vertices": _int(1, (1 << 32) - 1),
                "tick": {"$ref": "#/$defs/tick"},
                "bundle_key": {"type": "string"},
            },
            ("cloth", "token", "key", "vertices", "tick"),
        ),
        "reply_control": _reply(
            {"tick": {"$ref": "#/$defs/tick"}, "features": {"type": "array", "items": {"type": "string"}}}, ("tick",)
        ),
        "reply_remove": _reply({"tick": {"$ref": "#/$defs/tick"}}, ("tick",)),
        "reply_scene": _reply(
            {
                "tick": {"$ref": "#/$defs/tick"},
                "owner": {"$ref": "#/$defs/id"},
                "cloths": _int(0, (1 << 32) - 1),
                "members": {"type": "array", "items": {"type": "string"}},
            },
            ("tick", "owner", "cloths"),
        ),
        "reply_control_batch": _reply(
            {
                "tick": {"$ref": "#/$defs/tick"},
                "failed": _int(0, L.max_batch_items),
                "results": {
                    "type": "array",
                    "items": {
                        "oneOf": [
                            _obj(
                                {
                                    "ok": {"const": True},
                                    "tick": {"$ref": "#/$defs/tick"},
                                    "features": {"type": "array", "items": {"type": "string"}},
                                },
                                ("ok", "tick"),
                            ),
                            _obj({"ok": {"const": False}, "error": {"$ref": "#/$defs/error"}}, ("ok", "error")),
                        ]
                    },
                },
                "moves_tick": {"$ref": "#/$defs/tick"},
                "moves_failed": {
                    "type": "array",
                    "maxItems": L.max_batch_moves,
                    "description": "1.4: [position in the moves block, error code, message] of each refused move",
                    "items": {
                        "type": "array",
                        "prefixItems": [_int(0, L.max_batch_moves - 1), {"type": "string"}, {"type": "string"}],
                        "minItems": 3,
                        "maxItems": 3,
                    },
                },
            },
            ("tick", "failed", "results"),
        ),
        "reply_info": _reply(
            {
                "server": {"$ref": "#/$defs/id"},
                "version": {"type": "string", "pattern": r"^[0-9]+\.[0-9]+$"},
                "solver": {"type": "string"},
                "device": {"type": "string"},
                "tick_rate": {"type": "number"},
                "tick": {"$ref": "#/$defs/tick"},
                "cloths": {"type": "integer"},
                "clients": {"type": "integer"},
                "vertices": {"type": "integer"},
                "limits": _obj(
                    {
                        k: {"type": "integer", "minimum": 0}
                        for k in (
                            "max_cloths",
                            "max_cloths_per_client",
                            "max_vertices_per_cloth",
                            "max_total_vertices",
                            "max_message_bytes",
                            "max_pin_updates",
                            "max_batch_items",
                            "max_colliders",
                            "max_iterations",
                            "max_substeps",
                        )
                    }
                ),
                "encodings": {"type": "array", "items": {"type": "string"}},
                "features": {"type": "array", "items": {"type": "string"}},
                "grace_period_s": {"type": "number"},
                "stats_period_s": {"type": "number"},
            },
            ("server", "version", "limits"),
        ),
        "error": _obj({**_head(), "ok": {"const": False}, "error": {"$ref": "#/$defs/error"}}, ("v", "ok", "error")),
        "stats": _stats(),
    }
    defs = _defs()
    for name, s in out.items():
        s["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        s["$id"] = f"{BASE_URI}{name}.json"
        s["title"] = f"Drape protocol {VERSION_STRING}: {name}"
        s["$defs"] = defs
    return {name: dict(sorted(s.items(), key=lambda kv: not kv[0].startswith("$"))) for name, s in out.items()}


def write(folder: Path = HERE) -> list[Path]:
    """Write schema/<message>.json and drape_wire.h under ``folder``; returns the paths."""
    paths = []
    (folder / "schema").mkdir(parents=True, exist_ok=True)
    for name, s in schemas().items():
        p = folder / "schema" / f"{name}.json"
        p.write_text(json.dumps(s, indent=1) + "\n")
        paths.append(p)
    p = folder / "drape_wire.h"
    p.write_text(c_header())
    paths.append(p)
    return paths


if __name__ == "__main__":
    for path in write():
        print(f"wrote {path}")
