"""The collider-shape table (vocabulary.COLLIDER_SHAPES) and the control/submit field table
(requestfields.CONTROL_FIELDS) are what every user iterates over: the codec, validation, the JSON
Schema, the device packing and the server's coalescing cover every row, and nothing is dropped."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from drape.client import protocol as P
from drape.client.protocol import codec, schemagen, wiremaps
from drape.client.protocol.requestfields import (
    CONTROL_FIELDS,
    FIELD_KINDS,
    FIELD_MERGES,
    SUBMIT_FIELDS,
    field_given,
    pins_only,
)

TOKEN = "0123456789abcdef0123456789abcdef"
ROOT = Path(__file__).resolve().parents[2]

#: A given value of each field (every one differs from "absent").
EVERY_FIELD = {
    "pins": P.PinUpdate(np.array([0, 2], np.uint32), np.arange(6, dtype=np.float32).reshape(2, 3)),
    "material": {"mass": 2.0, "stiffness": (0.5, 0.5, 0.5)},
    "features": ("wind",),
    "gravity": (0.0, -1.0, 0.0),
    "wind": (1.0, 0.0, 0.0),
    "iterations": 0,
    "substeps": 2,
    "chebyshev_rho": 0.5,
    "colliders": (P.Sphere((0.0, 0.0, 0.0), 0.5), P.Capsule((0, 0, 0), (1, 0, 0), 0.1), P.Plane((0, 2, 0), -1)),
    "state": P.StateOptions(normals=True, encoding="float16"),
    "quality": "fast",
    "features_add": ("xpbd",),
    "features_remove": ("tethers",),
    "reset": True,
    "mesh_collider": P.MeshCollider(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32),
        np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.uint32),
        (0.0, 1.0, 0.0),
        (0.5, 0.5, 0.5, 0.5),
    ),
}


def test_the_request_dataclasses_declare_the_table():
    names = {f.name for f in CONTROL_FIELDS}
    assert set(EVERY_FIELD) == names
    assert {f.name for f in dataclasses.fields(P.ControlRequest)} == names | {"cloth", "token", "rid"}
    assert {f.name for f in SUBMIT_FIELDS} <= {f.name for f in dataclasses.fields(P.SubmitRequest)}


def test_every_kind_has_its_writer_reader_and_schema():
    assert set(wiremaps.WRITERS) == set(FIELD_KINDS)
    assert set(codec._READERS) == set(FIELD_KINDS)
    assert set(schemagen._KIND_SCHEMAS) == set(FIELD_KINDS)
    assert {f.merge for f in CONTROL_FIELDS} <= set(FIELD_MERGES)


def test_a_control_with_every_field_survives_the_wire():
    req = P.ControlRequest("a", TOKEN, rid=3, **EVERY_FIELD)
    m = P.control_to_map(req)
    assert [k for k in m if k not in ("v", "rid", "cloth", "token")] == [
        f.name for f in sorted(CONTROL_FIELDS, key=lambda f: f.wire)
    ]
    back = P.decode_control(P.encode_control(req))
    assert back == req
    for f in CONTROL_FIELDS:
        assert field_given(getattr(back, f.name), f), f.name
    props = schemagen.schemas()["control"]["properties"]
    assert set(props) == {"v", "rid", "cloth", "token", *(f.name for f in CONTROL_FIELDS)}


def test_a_submission_with_every_shared_field_survives_the_wire():
    shared = {f.name: EVERY_FIELD[f.name] for f in SUBMIT_FIELDS}
    req = P.SubmitRequest("c", grid=P.GridSpec(2, 2), **shared)
    m = P.submit_to_map(req)
    assert [k for k in m if k in shared] == [f.name for f in SUBMIT_FIELDS]
    assert P.decode_submit(P.encode_submit(req)) == req


def test_every_collider_shape_round_trips_and_is_described():
    schema = schemagen.schemas()["submit"]["$defs"]["collider"]["oneOf"]
    assert [s["properties"]["type"]["const"] for s in schema] == list(P.COLLIDER_TYPES)
    for shape, s in zip(P.COLLIDER_SHAPES, schema, strict=True):
        assert s["required"] == ["type", *(f.name for f in shape.fields)]
        c = EVERY_FIELD["colliders"][P.COLLIDER_IDS[shape.name]]
        assert P.collider_shape(c) is shape
        m = P.collider_to_map(c)
        assert P.as_collider(m) == c
        assert P.as_collider(dict(m)) == c
    with pytest.raises(TypeError):
        P.collider_to_map(object())


def test_the_kernels_collider_ids_are_the_tables():
    """Each shape's id is defined once in the kernels, in colliders.cl beside its code."""
    ids = re.compile(r"#define COLLIDER_(?!WORDS)([A-Z0-9_]+) (\d+)")
    text = (ROOT / "kernels" / "colliders.cl").read_text()
    assert {m[1].lower(): int(m[2]) for m in ids.finditer(text)} == P.COLLIDER_IDS
    for other in (ROOT / "kernels").glob("*.[ch]*"):
        assert other.name == "colliders.cl" or not ids.search(other.read_text()), other.name


def test_pack_colliders_writes_each_shapes_rows_and_id():
    from drape.server.service.worldparams import pack
    from drape.server.sim.params import pack_colliders

    cs = EVERY_FIELD["colliders"]
    out = pack_colliders(cs)
    assert out.shape == (3, 2, 4) and out.dtype == np.float32
    np.testing.assert_array_equal(out[0], [[0, 0, 0, 0.5], [0, 0, 0, 0]])
    np.testing.assert_array_equal(out[1], np.float32([[0, 0, 0, 0.1], [1, 0, 0, 1]]))
    np.testing.assert_array_equal(out[2], [[0, 1, 0, -1], [0, 0, 0, 2]])
    np.testing.assert_array_equal(pack(cs, 1), out)
    with pytest.raises(P.ProtocolError) as e:
        pack((P.Plane((0, 0, 0), 1.0),), 7)  # what the decoder refuses, were it to get this far
    assert e.value.code == P.ERR_INVALID_VALUE and e.value.rid == 7
    with pytest.raises(P.ProtocolError):
        pack(("not a collider",), 7)  # type: ignore[arg-type]


def test_pins_only_is_pins_and_nothing_else():
    pins = EVERY_FIELD["pins"]
    assert pins_only(P.ControlRequest("a", TOKEN, pins=pins))
    assert pins_only(P.ControlRequest("a", TOKEN, pins=pins, material={}, features_add=()))  # empty: no change
    assert not pins_only(P.ControlRequest("a", TOKEN, pins=P.PinUpdate(np.zeros(0, np.uint32), np.zeros((0, 3)))))
    for name, value in EVERY_FIELD.items():
        if name != "pins":
            assert not pins_only(P.ControlRequest("a", TOKEN, pins=pins, **{name: value})), name


def test_coalescing_drops_no_field():
    """A control then an empty one is the first, and an empty one then a control is the second,
    whatever field it carries (a field the merge left out would be silently dropped)."""
    from drape.server.service.commands import merge_controls

    empty = P.ControlRequest("a", TOKEN)
    for name, value in EVERY_FIELD.items():
        req = P.ControlRequest("a", TOKEN, **{name: value})
        assert merge_controls(req, empty) == req, name
        assert merge_controls(empty, req) == req, name


def test_a_mesh_move_coalesced_after_a_new_mesh_moves_that_mesh():
    """1.8: a new mesh (or a re-pose) then a rigid move, merged, is the mesh at the move's pose;
    a move then a new mesh is the new mesh; a removal wins over an earlier move."""
    from drape.server.service.commands import merge_controls

    mesh = EVERY_FIELD["mesh_collider"]
    move = P.MeshCollider.pose((1.0, 2.0, 3.0), (0.0, 1.0, 0.0, 0.0))

    def merged(a: P.MeshCollider, b: P.MeshCollider) -> P.MeshCollider:
        out = merge_controls(
            P.ControlRequest("a", TOKEN, mesh_collider=a), P.ControlRequest("a", TOKEN, mesh_collider=b)
        )
        assert out.mesh_collider is not None
        return out.mesh_collider

    got = merged(mesh, move)
    assert got.triangles is mesh.triangles and got.position == move.position and got.rotation == move.rotation
    assert merged(move, mesh) == mesh
    assert merged(move, P.MeshCollider.removal()).remove
