"""The wire protocol alone: round trips, validation of hostile input, the binary state layout,
the committed test vectors (both ways), and that the client side needs no server code."""
from __future__ import annotations

import dataclasses
import json
import math
import struct
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest

from drape.client import protocol as P

VECTORS = Path(__file__).resolve().parent / "vectors"
sys.path.insert(0, str(VECTORS))
from generate import json_to_wire, vectors as fresh_vectors  # noqa: E402

TOKEN = "0123456789abcdef0123456789abcdef"


def load(group: str) -> list[dict]:
    return json.loads((VECTORS / f"{group}.json").read_text())


def raw(m) -> bytes:
    return msgpack.packb(m, use_bin_type=True)


# ---------------------------------------------------------------------------------------------
# Round trips


def full_submit() -> P.SubmitRequest:
    return P.SubmitRequest(
        client="c-1",
        grid=P.GridSpec(5, 3, 2.0, 1.0, "vertical", (1.0, 2.0, 3.0)),
        pinned=np.array([0, 4], np.uint32),
        links=P.LinkSpec(True, False, True),
        material={"mass": 2.0, "stiffness": (1.0, 0.5, 0.25), "compliance": (0.0, 1e-4, 1e-3), "damping": 0.1,
                  "friction": 0.3, "drag": 0.2, "lift": 0.1, "air_density": 1.0, "tether_limit": 1.1},
        features=("xpbd", "tethers", "wind"),
        gravity=(0.0, -9.81, 0.0),
        wind=(3.0, 0.0, 1.0),
        iterations=0,
        substeps=4,
        chebyshev_rho=0.9,
        colliders=(P.Sphere((0, 0, 0), 1.0), P.Capsule((0, 0, 0), (1, 0, 0), 0.1), P.Plane((0, 2, 0), -1.0)),
        state=P.StateOptions(True, "quant16"),
        rid=2**64 - 1,
    )


def test_submit_round_trip():
    req = full_submit()
    assert P.decode_submit(P.encode_submit(req)) == req
    mesh = P.SubmitRequest("c", mesh=P.MeshSpec(np.random.rand(10, 3).astype(np.float32),
                                                np.array([[0, 1, 2], [2, 3, 4]], np.uint32)))
    back = P.decode_submit(P.encode_submit(mesh))
    assert back == mesh and back.n_vertices == 10 and back.grid is None


def test_control_remove_info_replies_round_trip():
    ctl = P.ControlRequest(
        "abc", TOKEN, pins=P.PinUpdate(np.array([1, 2], np.uint32), np.ones((2, 3), np.float32)),
        colliders=(), gravity=(0, 0, 0), material={"damping": 0.5}, features=(), iterations=3, substeps=2,
        chebyshev_rho=0.0, state=P.StateOptions(None, "float16"), reset=True, rid=4,
    )
    back = P.decode_control(P.encode_control(ctl))
    assert back == ctl and back.colliders == () and back.features == ()
    assert P.decode_remove(P.encode_remove(P.RemoveRequest("abc", TOKEN, 3))) == P.RemoveRequest("abc", TOKEN, 3)
    assert P.decode_info(b"") == P.InfoRequest(0)
    assert P.decode_info(P.encode_info(P.InfoRequest(8))).rid == 8
    rep = P.SubmitReply("abc", TOKEN, "drape/cloth/abc/state", 10, 77, 5)
    assert P.submit_reply_from_map(P.decode_reply(P.encode_submit_reply(rep))) == rep
    assert P.tick_reply_from_map(P.decode_reply(P.encode_control_reply(P.ControlReply(9, 1)))) == 9
    assert P.tick_reply_from_map(P.decode_reply(P.encode_remove_reply(P.RemoveReply(8, 1)))) == 8
    with pytest.raises(P.Forbidden) as e:
        P.decode_reply(P.encode_error("forbidden", "not yours", 12))
    assert (e.value.code, e.value.message, e.value.rid) == ("forbidden", "not yours", 12)
    with pytest.raises(ValueError):
        P.encode_error("no_such_code", "x")


def test_error_classes():
    assert isinstance(P.error_for("not_found", "x"), P.NotFound)
    assert isinstance(P.error_for("limit_exceeded", "x"), P.LimitExceeded)
    for code in ("malformed", "invalid_type", "invalid_value", "index_out_of_range", "too_large",
                 "missing_field", "unsupported_version"):
        err = P.error_for(code, "x")
        assert isinstance(err, P.ProtocolError) and isinstance(err, P.DrapeError) and err.code == code
    assert type(P.error_for("some_future_code", "x")) is P.DrapeError  # unknown codes still raise


def test_unknown_keys_and_minor_versions_are_accepted():
    m = P.submit_to_map(P.SubmitRequest("c", grid=P.GridSpec(2, 2)))
    m["v"] = [1, 99]
    m["from_the_future"] = {"anything": [1, 2, 3]}
    m["grid"]["texture"] = "silk"
    req = P.submit_from_map(m)
    assert req.grid == P.GridSpec(2, 2)


# ---------------------------------------------------------------------------------------------
# Validation

G = {"v": [1, 0], "rid": 1, "client": "c", "grid": {"cols": 3, "rows": 3}}


def sub(**kw):
    m = {**G, **kw}
    return {k: v for k, v in m.items() if v is not None}


LIMITS = P.Limits(max_message_bytes=4096, max_vertices=100, max_triangles=200, max_pin_updates=4)

BAD_SUBMITS = [
    (b"", "malformed"),
    (raw(G)[:-1], "malformed"),
    (raw(G) + b"\x00", "malformed"),  # trailing bytes
    (b"\x92\x01", "malformed"),  # truncated array
    (b"\xdd\xff\xff\xff\xff", "malformed"),  # a 4-billion-element array header on 5 bytes
    (b"\x91" * 5000, "too_large"),
    (b"\x91" * 3000 + b"\x00", "malformed"),  # nesting too deep
    (b"\x81\x01\x02", "malformed"),  # integer map key
    (b"\xa2\xff\xfe", "malformed"),  # invalid utf-8
    (raw([G]), "malformed"),
    (raw(sub(v=[2, 0])), "unsupported_version"),
    (raw(sub(v=None)), "missing_field"),
    (raw(sub(v="1.0")), "invalid_type"),
    (raw(sub(v=[1])), "invalid_type"),
    (raw(sub(client=None)), "missing_field"),
    (raw(sub(client=5)), "invalid_type"),
    (raw(sub(client="")), "invalid_value"),
    (raw(sub(client="a" * 65)), "invalid_value"),
    (raw(sub(client="a/b")), "invalid_value"),
    (raw(sub(client="*")), "invalid_value"),
    (raw(sub(rid=-1)), "invalid_value"),
    (raw(sub(rid="x")), "invalid_type"),
    (raw(sub(grid=[3, 3])), "invalid_type"),
    (raw(sub(grid={"cols": 3})), "missing_field"),
    (raw(sub(grid={"cols": 3.0, "rows": 3})), "invalid_type"),
    (raw(sub(grid={"cols": 0, "rows": 3})), "invalid_value"),
    (raw(sub(grid={"cols": 11, "rows": 10})), "too_large"),
    (raw(sub(grid={"cols": 2**64 - 1, "rows": 1})), "too_large"),
    (raw(sub(grid={"cols": 3, "rows": 3, "width": 0.0})), "invalid_value"),
    (raw(sub(grid={"cols": 3, "rows": 3, "width": float("nan")})), "invalid_value"),
    (raw(sub(grid={"cols": 3, "rows": 3, "orientation": "diagonal"})), "invalid_value"),
    (raw(sub(grid={"cols": 3, "rows": 3, "origin": [0, 0]})), "invalid_type"),
    (raw(sub(grid={"cols": 3, "rows": 3, "origin": [0, "0", 0]})), "invalid_type"),
    (raw(sub(grid={"cols": 3, "rows": 3, "origin": [0, 1e9, 0]})), "invalid_value"),
    (raw(sub(pinned=np.array([9], "<u4").tobytes())), "index_out_of_range"),
    (raw(sub(pinned=b"\x01\x02")), "invalid_value"),
    (raw(sub(pinned=np.zeros(101, "<u4").tobytes())), "too_large"),
    (raw(sub(links={"bending": "yes"})), "invalid_type"),
    (raw(sub(links=True)), "invalid_type"),
    (raw(sub(material={"mass": 0.0})), "invalid_value"),
    (raw(sub(material={"mass": -1.0})), "invalid_value"),
    (raw(sub(material={"damping": 1.5})), "invalid_value"),
    (raw(sub(material={"stiffness": [1, 1, 2]})), "invalid_value"),
    (raw(sub(material={"compliance": [0, -1, 0]})), "invalid_value"),
    (raw(sub(material={"tether_limit": 0.5})), "invalid_value"),
    (raw(sub(material={"friction": float("inf")})), "invalid_value"),
    (raw(sub(material={"drag": 1e300})), "invalid_value"),
    (raw(sub(material="steel")), "invalid_type"),
    (raw(sub(features="xpbd")), "invalid_type"),
    (raw(sub(features=["xpbd", 3])), "invalid_type"),
    (raw(sub(features=["warp"])), "invalid_value"),
    (raw(sub(features=["xpbd"] * 17)), "too_large"),
    (raw(sub(gravity=[0, -1e5, 0])), "invalid_value"),
    (raw(sub(wind=[0, float("-inf"), 0])), "invalid_value"),
    (raw(sub(iterations=-1)), "invalid_value"),
    (raw(sub(iterations=101)), "invalid_value"),
    (raw(sub(iterations=True)), "invalid_type"),
    (raw(sub(substeps=0)), "invalid_value"),
    (raw(sub(chebyshev_rho=1.0)), "invalid_value"),
    (raw(sub(colliders={"type": "sphere"})), "invalid_type"),
    (raw(sub(colliders=[{"type": "sphere", "center": [0, 0, 0]}])), "missing_field"),
    (raw(sub(colliders=[{"type": "sphere", "center": [0, 0, 0], "radius": -1}])), "invalid_value"),
    (raw(sub(colliders=[{"type": "plane", "normal": [0, 0, 0], "offset": 0}])), "invalid_value"),
    (raw(sub(colliders=[{"type": "capsule", "p0": [0, 0, 0], "p1": [1, 0, float("nan")], "radius": 1}])),
     "invalid_value"),
    (raw(sub(colliders=[{"type": "sphere", "center": [0, 0, 0], "radius": 1}] * 33)), "too_large"),
    (raw(sub(state={"encoding": "png"})), "invalid_value"),
    (raw(sub(state={"normals": 1})), "invalid_type"),
    (raw(sub(mesh={"vertices": b"", "triangles": b""})), "invalid_value"),  # grid and mesh
    (raw(sub(grid=None)), "missing_field"),
]


def _mesh(v, t, **kw):
    return raw(sub(grid=None, mesh={"vertices": np.asarray(v, "<f4").tobytes(), "triangles": np.asarray(t, "<u4").tobytes()},
                   **kw))


TRI = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
BAD_MESHES = [
    (_mesh(np.zeros((0, 3)), np.zeros((0, 3))), "invalid_value"),
    (_mesh(TRI, [[0, 1, 3]]), "index_out_of_range"),
    (_mesh(TRI, [[0, 1, 1]]), "invalid_value"),
    (_mesh([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]]), "invalid_value"),
    (_mesh(np.zeros((101, 3)), [[0, 1, 2]]), "too_large"),
    (_mesh(TRI, np.zeros((201, 3))), "too_large"),
    (raw(sub(grid=None, mesh={"vertices": b"\x00" * 10, "triangles": b""})), "invalid_value"),
    (raw(sub(grid=None, mesh={"vertices": [[0, 0, 0]], "triangles": b""})), "invalid_type"),
    (raw(sub(grid=None, mesh={"triangles": b""})), "missing_field"),
    (_mesh(TRI, [[0, 1, 2]], pinned=np.array([3], "<u4").tobytes()), "index_out_of_range"),
]


@pytest.mark.parametrize("payload,code", BAD_SUBMITS + BAD_MESHES)
def test_hostile_submissions_raise_protocol_errors(payload, code):
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(payload, LIMITS)
    assert e.value.code == code, e.value.message
    assert e.value.message
    if code not in ("malformed", "too_large", "unsupported_version") and isinstance(msgpack.unpackb(payload), dict):
        assert e.value.rid in (0, 1)


C = {"v": [1, 0], "rid": 3, "cloth": "abc", "token": TOKEN}


def ctl(**kw):
    m = {**C, **kw}
    return raw({k: v for k, v in m.items() if v is not None})


def pins(idx, tgt):
    return {"indices": np.asarray(idx, "<u4").tobytes(), "targets": np.asarray(tgt, "<f4").tobytes()}


BAD_CONTROLS = [
    (ctl(token=None), "missing_field"),
    (ctl(token=TOKEN.upper()), "invalid_value"),
    (ctl(token=TOKEN[:-1]), "invalid_value"),
    (ctl(cloth=None), "missing_field"),
    (ctl(cloth="a b"), "invalid_value"),
    (ctl(pins=pins([0, 1], [[0, 0, 0]])), "invalid_value"),
    (ctl(pins=pins([0], [[0, np.nan, 0]])), "invalid_value"),
    (ctl(pins=pins([0], [[0, 1e7, 0]])), "invalid_value"),
    (ctl(pins=pins(range(5), np.zeros((5, 3)))), "too_large"),
    (ctl(pins=pins([10], [[0, 0, 0]])), "index_out_of_range"),
    (ctl(pins={"indices": b"\x00\x00\x00\x00"}), "missing_field"),
    (ctl(reset="yes"), "invalid_type"),
    (ctl(material={"damping": -0.1}), "invalid_value"),
    (ctl(features=["hair"]), "invalid_value"),
]


@pytest.mark.parametrize("payload,code", BAD_CONTROLS)
def test_hostile_controls_raise_protocol_errors(payload, code):
    with pytest.raises(P.ProtocolError) as e:
        P.decode_control(payload, LIMITS, n_vertices=10)
    assert e.value.code == code, e.value.message
    assert e.value.rid == 3


def test_error_messages_name_the_problem():
    cases = {
        raw(sub(grid={"cols": 3, "rows": 3, "width": float("nan")})): "grid.width",
        raw(sub(material={"stiffness": [1, 1, 2]})): "material.stiffness[2]",
        raw(sub(colliders=[{"type": "sphere", "center": [0, 0, 0], "radius": -1}])): "colliders[0].radius",
        raw(sub(pinned=np.array([9], "<u4").tobytes())): "vertex 9",
        raw(sub(v=[3, 1])): "3.1",
    }
    for payload, needle in cases.items():
        with pytest.raises(P.ProtocolError) as e:
            P.decode_submit(payload, LIMITS)
        assert needle in e.value.message, e.value.message
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(raw(sub(v=[3, 1])))
    assert P.VERSION_STRING in e.value.message  # names the supported version


# ---------------------------------------------------------------------------------------------
# Binary state


def test_state_header_layout_matches_the_document():
    pos = np.array([[1, 2, 3], [-1, 0.5, 4]], np.float32)
    nrm = np.array([[0, 1, 0], [1, 0, 0]], np.float32)
    data = bytes(P.encode_state(0x0102030405060708, 99, pos, nrm, "float32", P.FLAG_RESET))
    assert len(data) == 64 + 2 * 12 * 2 == P.state_size(2, "float32", True)
    assert data[0:4] == b"DRPS"
    assert data[4] == 1 and data[5] == P.PROTOCOL_MINOR == 1  # major, minor
    assert struct.unpack_from("<H", data, 6)[0] == 64  # header size
    assert data[8] == 0 and data[9] == 0  # encoding float32, reserved
    assert struct.unpack_from("<H", data, 10)[0] == P.FLAG_NORMALS | P.FLAG_RESET == 3
    assert struct.unpack_from("<I", data, 12)[0] == 2
    assert struct.unpack_from("<Q", data, 16)[0] == 0x0102030405060708
    assert struct.unpack_from("<Q", data, 24)[0] == 99
    assert struct.unpack_from("<6f", data, 32) == (-1.0, 0.5, 3.0, 1.0, 2.0, 4.0)
    assert data[56:64] == bytes(8)
    np.testing.assert_array_equal(np.frombuffer(data, "<f4", 6, 64).reshape(2, 3), pos)
    np.testing.assert_array_equal(np.frombuffer(data, "<f4", 6, 88).reshape(2, 3), nrm)


@pytest.mark.parametrize("encoding", P.ENCODINGS)
def test_state_encodings_round_trip_within_their_precision(encoding):
    rng = np.random.default_rng(1)
    pos = (rng.random((500, 3)) * [4.0, 2.0, 1.0] - [2.0, 0.0, 0.5]).astype(np.float32)
    nrm = rng.normal(size=(500, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    data = P.encode_state(5, 6, pos, nrm, encoding)
    assert len(data) == P.state_size(500, encoding, True)
    st = P.decode_state(bytes(data), "cid", 7)
    assert (st.tick, st.server_time_ns, st.receive_time_ns, st.cloth, st.encoding) == (5, 6, 7, "cid", encoding)
    assert st.positions.dtype == np.float32 and st.positions.shape == (500, 3)
    err_p = np.abs(st.positions - pos).max()
    err_n = np.abs(st.normals - nrm).max()
    if encoding == "float32":
        assert err_p == 0 and err_n == 0
    elif encoding == "float16":
        assert err_p <= 2.0 * 2 ** -11 and err_n <= 2 ** -11  # half an ulp of |x| < 2
    else:
        ext = pos.max(0) - pos.min(0)
        assert np.all(np.abs(st.positions - pos) <= ext / 65535 * 0.5 + 1e-6)
        assert err_n <= 0.5 / 32767 + 1e-7
    assert np.allclose(st.bounds[0], pos.min(0)) and np.allclose(st.bounds[1], pos.max(0))


def test_quant16_degenerate_axis_and_float16_clamp():
    flat = np.array([[0, 1, 0], [1, 1, 0], [2, 1, 0]], np.float32)  # y and z constant
    st = P.decode_state(bytes(P.encode_state(1, 1, flat, None, "quant16")))
    np.testing.assert_array_equal(st.positions[:, 1:], flat[:, 1:])  # a flat axis decodes exactly
    np.testing.assert_allclose(st.positions[:, 0], flat[:, 0], atol=2 / 65535 / 2)
    far = np.array([[70000.0, 0, 0], [-1e5, 0, 0]], np.float32)
    st = P.decode_state(bytes(P.encode_state(1, 1, far, None, "float16")))
    assert np.isfinite(st.positions).all() and st.positions[0, 0] == 65504.0


def test_state_decoder_is_strict_where_it_must_be_and_lenient_where_it_may():
    pos = np.ones((4, 3), np.float32)
    good = bytes(P.encode_state(1, 2, pos))
    for bad, code in [
        (good[:63], "malformed"),
        (good[:-1], "malformed"),
        (b"XXXX" + good[4:], "malformed"),
        (good[:4] + b"\x02" + good[5:], "unsupported_version"),
        (good[:8] + b"\x07" + good[9:], "invalid_value"),
        (good[:6] + struct.pack("<H", 32) + good[8:], "malformed"),
    ]:
        with pytest.raises(P.ProtocolError) as e:
            P.decode_state(bad)
        assert e.value.code == code
    # a later minor version: more header bytes, unknown flags, trailing sections
    longer = bytearray(good[:64] + b"\xee" * 16 + good[64:] + b"extra")
    longer[5] = 3
    struct.pack_into("<H", longer, 6, 80)
    struct.pack_into("<H", longer, 10, 0x8000)
    st = P.decode_state(bytes(longer))
    np.testing.assert_array_equal(st.positions, pos)
    assert st.normals is None
    st = P.decode_state(memoryview(good))
    np.testing.assert_array_equal(st.positions, pos)


# ---------------------------------------------------------------------------------------------
# Test vectors, both ways

REENCODE = {
    "submit": (P.decode_submit, P.encode_submit, P.submit_from_map),
    "control": (P.decode_control, P.encode_control, P.control_from_map),
    "remove": (P.decode_remove, P.encode_remove, P.remove_from_map),
    "info": (P.decode_info, P.encode_info, None),
}


def _reply_encoders(kind: str, m: dict) -> bytes:
    if kind == "reply_submit":
        return P.encode_submit_reply(P.submit_reply_from_map(m))
    if kind == "reply_control":
        return P.encode_control_reply(P.ControlReply(P.tick_reply_from_map(m), m["rid"]))
    if kind == "reply_remove":
        return P.encode_remove_reply(P.RemoveReply(P.tick_reply_from_map(m), m["rid"]))
    if kind == "reply_control_batch":
        return P.encode_control_batch_reply(P.control_batch_reply_from_map(m))
    err = P.decode_error_map(m)
    return P.encode_error(err.code, err.message, err.rid)


def _batch_request(d: P.DecodedControlBatch) -> P.ControlBatchRequest:
    assert all(isinstance(it, P.ControlRequest) for it in d.items), d.items
    return P.ControlBatchRequest(d.client, list(d.items), d.rid)  # type: ignore[arg-type]


REENCODE["control_batch"] = (
    lambda data: _batch_request(P.decode_control_batch(data)),
    P.encode_control_batch,
    lambda m: _batch_request(P.control_batch_from_map(m)),
)


@pytest.mark.parametrize("vec", load("submit") + load("control") + load("misc"), ids=lambda v: v["name"])
def test_message_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    wire = json_to_wire(vec["value"])
    # bytes -> meaning
    assert msgpack.unpackb(data, raw=False) == wire
    # meaning -> identical bytes (float fields as float64, smallest ints, bin for arrays, key order)
    assert msgpack.packb(wire, use_bin_type=True) == data
    kind = vec["message"]
    if kind in REENCODE:
        decode, encode, from_map = REENCODE[kind]
        typed = decode(data)
        assert encode(typed) == data
        if from_map is not None:
            assert encode(from_map(wire)) == data
        assert typed.rid == wire.get("rid", 0)
    else:
        if kind == "error":
            with pytest.raises(P.DrapeError) as e:
                P.decode_reply(data)
            assert e.value.code == wire["error"]["code"] and e.value.message == wire["error"]["message"]
            m = P.unpack_message(data)
        else:
            m = P.decode_reply(data)
        assert _reply_encoders(kind, m) == data


@pytest.mark.parametrize("vec", load("state"), ids=lambda v: v["name"])
def test_state_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    st = P.decode_state(data)
    assert data[:4].decode() == val["magic"] and (data[4], data[5]) == (val["major"], val["minor"])
    assert struct.unpack_from("<H", data, 6)[0] == val["header_size"]
    assert st.encoding == val["encoding"] and st.flags == val["flags"] and st.n_vertices == val["vertex_count"]
    assert st.tick == val["tick"] and st.server_time_ns == val["server_time_ns"]
    assert list(st.bounds[0]) == val["bounds_min"] and list(st.bounds[1]) == val["bounds_max"]
    assert st.positions.tolist() == val["positions"]
    assert (st.normals is None and val["normals"] is None) or st.normals.tolist() == val["normals"]
    inp = vec["input"]
    normals = None if inp["normals"] is None else np.array(inp["normals"], np.float32)
    again = P.encode_state(val["tick"], val["server_time_ns"], np.array(inp["positions"], np.float32), normals,
                           val["encoding"], inp["flags"])
    assert bytes(again) == data


@pytest.mark.parametrize("vec", load("bundle"), ids=lambda v: v["name"])
def test_bundle_vectors(vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    # bytes -> meaning, read with struct as the document's offset table says
    magic, major, minor, hsize, count, flags, tick, t_ns = struct.unpack_from("<4sBBHIIQQ", data, 0)
    assert (magic.decode(), major, minor, hsize, count, flags, tick, t_ns) == (
        val["magic"], val["major"], val["minor"], val["header_size"], val["count"], val["flags"], val["tick"],
        val["server_time_ns"])
    assert len(data) == val["size"] and len(data) % 8 == 0
    for e in val["entries"]:
        at = e["entry_offset"]
        h, id_len, reserved, size = struct.unpack_from("<HBBI", data, at)
        assert (h, size, reserved) == (e["entry_header_size"], e["state_size"], 0)
        assert data[at + 8:at + 8 + id_len].decode() == e["cloth"] and not any(data[at + 8 + id_len:at + h])
        assert at % 8 == 0 and e["state_offset"] == at + h and e["state_offset"] % 8 == 0
        st = P.decode_state(data[at + h:at + h + size], e["cloth"])
        sv = e["state"]
        assert (st.tick, st.server_time_ns, st.encoding, st.flags, st.n_vertices) == (
            sv["tick"], sv["server_time_ns"], sv["encoding"], sv["flags"], sv["vertex_count"])
        assert st.positions.tolist() == sv["positions"]
        assert (st.normals is None and sv["normals"] is None) or st.normals.tolist() == sv["normals"]
    # the decoder agrees
    b = P.parse_bundle(data)
    assert (b.tick, b.server_time_ns, b.flags, len(b.entries)) == (val["tick"], val["server_time_ns"], 0, val["count"])
    assert [s.cloth for s in P.decode_bundle(data, 5)] == [e["cloth"] for e in val["entries"]]
    # meaning -> identical bytes
    inp = vec["input"]
    again = P.encode_bundle(inp["tick"], inp["server_time_ns"], [(s["cloth"], bytes.fromhex(s["hex"])) for s in inp["states"]])
    assert bytes(again) == data
    for s, e in zip(inp["states"], val["entries"]):
        assert data[e["state_offset"]:e["state_offset"] + e["state_size"]].hex() == s["hex"]


DECODERS = {"submit": P.decode_submit, "control": P.decode_control, "remove": P.decode_remove,
            "control_batch": P.decode_control_batch, "bundle": P.decode_bundle}


@pytest.mark.parametrize("vec", load("invalid"), ids=lambda v: v["name"])
def test_invalid_vectors(vec):
    decode = DECODERS[vec["message"]]
    data = bytes.fromhex(vec["hex"])
    if vec["error"] is None:  # a batch with a valid envelope: per-item errors
        batch = decode(data)
        codes = [it.code if isinstance(it, P.ProtocolError) else None for it in batch.items]
        assert codes == vec["item_errors"]
        assert all(it.rid == batch.rid for it in batch.items if isinstance(it, P.ProtocolError))
        return
    with pytest.raises(P.ProtocolError) as e:
        decode(data)
    assert e.value.code == vec["error"]


def test_accepted_vectors():
    for vec in load("accepted"):
        data = bytes.fromhex(vec["hex"])
        if vec["message"] == "bundle":
            (st,) = P.decode_bundle(data)
            assert st.cloth == "c" and st.tick == 7 and st.encoding == "float16"
            continue
        req = P.decode_submit(data)
        assert req.grid == P.GridSpec(2, 2)


V10 = VECTORS / "v1.0"


def _as_current(wire: dict) -> dict:
    """A 1.0 message as this version writes it: the same map with v = [1, PROTOCOL_MINOR]."""
    return {**wire, "v": [P.PROTOCOL_MAJOR, P.PROTOCOL_MINOR]} if "v" in wire else wire


@pytest.mark.parametrize("vec", [v for g in ("submit", "control", "misc") for v in json.loads((V10 / f"{g}.json").read_text())],
                         ids=lambda v: v["name"])
def test_v1_0_message_vectors_still_read(vec):
    """Minor-version compatibility: every frozen 1.0 message means the same under 1.1; writing it
    again changes the version field only."""
    data = bytes.fromhex(vec["hex"])
    wire = json_to_wire(vec["value"])
    assert wire["v"] == [1, 0]
    kind = vec["message"]
    if kind in REENCODE:
        decode, encode, _ = REENCODE[kind]
        again = encode(decode(data))
    elif kind == "error":
        err = P.decode_error_map(P.unpack_message(data))
        again = P.encode_error(err.code, err.message, err.rid)
    else:
        again = _reply_encoders(kind, P.decode_reply(data))
    assert msgpack.unpackb(again, raw=False) == _as_current(wire)


@pytest.mark.parametrize("vec", json.loads((V10 / "state.json").read_text()), ids=lambda v: v["name"])
def test_v1_0_state_vectors_still_read(vec):
    data = bytes.fromhex(vec["hex"])
    val = vec["value"]
    assert (data[4], data[5]) == (1, 0)
    st = P.decode_state(data)
    assert st.positions.tolist() == val["positions"] and st.tick == val["tick"] and st.flags == val["flags"]
    assert (st.normals is None and val["normals"] is None) or st.normals.tolist() == val["normals"]
    inp = vec["input"]
    normals = None if inp["normals"] is None else np.array(inp["normals"], np.float32)
    again = bytes(P.encode_state(val["tick"], val["server_time_ns"], np.array(inp["positions"], np.float32), normals,
                                 val["encoding"], inp["flags"]))
    assert again[:5] + again[6:] == data[:5] + data[6:] and again[5] == P.PROTOCOL_MINOR  # only the minor byte


def test_committed_vectors_are_current():
    """The generator reproduces the committed files (a protocol change must update both)."""
    for group, items in fresh_vectors().items():
        assert json.loads(json.dumps(items)) == load(group), f"tests/vectors/{group}.json is stale"


# ---------------------------------------------------------------------------------------------
# The client mirrors the server's vocabulary and geometry without importing it


def test_vocabulary_matches_the_server_params():
    from drape.server.sim.params import ClothParams, Features, LinkOptions, Material

    assert tuple(f.name for f in dataclasses.fields(Features)) == P.FEATURE_NAMES
    assert tuple(f.name for f in dataclasses.fields(LinkOptions)) == tuple(f.name for f in dataclasses.fields(P.LinkSpec))
    assert dataclasses.asdict(LinkOptions()) == dataclasses.asdict(P.LinkSpec())
    assert set(P.MATERIAL_FIELDS) == {f.name for f in dataclasses.fields(Material)}
    assert dataclasses.asdict(Material()) == P.MATERIAL_DEFAULTS
    d = ClothParams()
    assert (d.gravity, d.wind, d.iterations, d.substeps, d.chebyshev_rho) == (
        P.DEFAULT_GRAVITY, P.DEFAULT_WIND, P.DEFAULT_ITERATIONS, P.DEFAULT_SUBSTEPS, P.DEFAULT_CHEBYSHEV_RHO)
    # every per-cloth parameter can be sent in a submission and changed by a control
    submit_fields = {f.name for f in dataclasses.fields(P.SubmitRequest)}
    control_fields = {f.name for f in dataclasses.fields(P.ControlRequest)}
    for f in dataclasses.fields(ClothParams):
        assert f.name in submit_fields and f.name in control_fields, f.name


def test_material_map_accepts_the_server_dataclass():
    from drape.server.sim.params import Material

    m = P.material_to_map(Material(mass=2.0))
    assert m["mass"] == 2.0 and m["stiffness"] == [1.0, 1.0, 1.0] and set(m) == set(P.MATERIAL_FIELDS)
    with pytest.raises(ValueError):
        P.material_to_map({"colour": 1})


@pytest.mark.parametrize("orientation", ["horizontal", "vertical"])
def test_grid_geometry_matches_the_server(orientation):
    from drape.server.sim.fabric import grid_mesh

    for cols, rows in [(1, 1), (2, 5), (7, 3)]:
        v, t = P.grid_geometry(cols, rows, 1.5, 0.7, orientation, (1, 2, 3))
        sv, st = grid_mesh(cols, rows, 1.5, 0.7, orientation, (1, 2, 3))
        np.testing.assert_array_equal(v, sv.astype(np.float32))
        np.testing.assert_array_equal(t, st)


def test_obj_parser_matches_the_server():
    from drape.server.sim.fabric import parse_obj

    text = "# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\nf -1 -2 -3\n"
    v, t = P.parse_obj(text)
    sv, st = parse_obj(text)
    np.testing.assert_array_equal(v, sv.astype(np.float32))
    np.testing.assert_array_equal(t, st)


def test_client_needs_no_server_code():
    code = (
        "import sys\n"
        "import drape.client.protocol\n"
        "assert 'zenoh' not in sys.modules, 'protocol must not import zenoh'\n"
        "import drape.client\n"
        "assert 'zenoh' not in sys.modules, 'the package must not import zenoh before the SDK is used'\n"
        "from drape.client import DrapeClient, ClothHandle\n"
        "import drape.client.sdk\n"
        "bad = [m for m in sys.modules if m.startswith('drape.server') or m.startswith('pyopencl')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_keys():
    k = P.Keys("game/eu")
    assert k.submit("s1") == "game/eu/server/s1/submit"
    assert k.state("abc") == "game/eu/cloth/abc/state"
    assert k.alive_client("c9") == "game/eu/alive/client/c9"
    assert k.all_servers_alive == "game/eu/alive/server/*"
    for bad in ("", "a//b", "a/*", "$x", "a b"):
        with pytest.raises(ValueError):
            P.Keys(bad)
    assert math.isclose(P.DEFAULT_GRAVITY[1], -9.81)


# ---------------------------------------------------------------------------------------------
# 1.1: bundles and batch control


def test_bundle_option_and_reply_round_trip():
    req = P.SubmitRequest("c", grid=P.GridSpec(2, 2), state=P.StateOptions(None, None, True))
    assert P.decode_submit(P.encode_submit(req)).state == P.StateOptions(None, None, True)
    rep = P.SubmitReply("abc", TOKEN, "drape/cloth/abc/state", 4, 9, 1, "drape/client/c/states")
    assert P.submit_reply_from_map(P.decode_reply(P.encode_submit_reply(rep))) == rep
    plain = P.SubmitReply("abc", TOKEN, "drape/cloth/abc/state", 4, 9, 1)
    assert "bundle_key" not in P.decode_reply(P.encode_submit_reply(plain))  # a 1.0 reply, byte for byte
    assert P.Keys("g").bundle("c7") == "g/client/c7/states"
    assert P.Keys("g").control_batch("s") == "g/server/s/control_batch"
    # bundling is chosen at submission: a control cannot switch it
    with pytest.raises(P.ProtocolError) as e:
        P.decode_control(ctl(state={"bundle": False}))
    assert e.value.code == "invalid_value" and "state.bundle" in e.value.message


def test_control_batch_round_trip_and_item_errors_name_the_item():
    items = [P.ControlRequest("a", TOKEN, pins=P.PinUpdate(np.array([1], np.uint32), np.ones((1, 3), np.float32))),
             P.ControlRequest("b", TOKEN, gravity=(0, 0, 0), colliders=(), reset=True)]
    req = P.ControlBatchRequest("me", items, rid=77)
    back = P.decode_control_batch(P.encode_control_batch(req))
    assert (back.client, back.rid) == ("me", 77)
    assert back.items == [dataclasses.replace(it, rid=77) for it in items]  # errors of an item echo the batch's rid
    bad = raw({"v": [1, 1], "rid": 3, "client": "me", "items": [
        {"cloth": "a", "token": TOKEN, "pins": pins([0], [[0, np.inf, 0]])},
        {"cloth": "a", "token": TOKEN, "material": {"stiffness": [1, 1, 2]}},
        {"cloth": "a", "token": TOKEN, "pins": pins(range(5), np.zeros((5, 3)))},
        {"cloth": "a", "token": TOKEN},
    ]})
    got = P.decode_control_batch(bad, LIMITS).items
    assert [getattr(x, "code", None) for x in got] == ["invalid_value", "invalid_value", "too_large", None]
    assert "items[0].pins.targets" in got[0].message and "items[1].material.stiffness[2]" in got[1].message
    assert "items[2].pins.indices" in got[2].message
    # the envelope is all or nothing
    lim = P.Limits(max_batch_items=2)
    with pytest.raises(P.ProtocolError) as e:
        P.decode_control_batch(raw({"v": [1, 1], "client": "me", "items": [{}] * 3}), lim)
    assert e.value.code == "too_large" and "2" in e.value.message
    with pytest.raises(P.ProtocolError) as e:
        P.decode_control_batch(raw({"v": [2, 0], "client": "me", "items": [{}]}))
    assert e.value.code == "unsupported_version"
    # the reply
    rep = P.ControlBatchReply(12, [P.BatchItemResult(12), P.BatchItemResult(None, "not_found", "gone")], 5)
    m = P.decode_reply(P.encode_control_batch_reply(rep))
    assert m["failed"] == 1 and P.control_batch_reply_from_map(m) == rep
    assert isinstance(rep.results[1].exception(), P.NotFound) and rep.results[0].exception() is None


def test_bundle_parser_survives_every_truncation_and_corruption(rng):
    tri = np.arange(9, dtype=np.float32).reshape(3, 3)
    data = bytes(P.encode_bundle(3, 4, [("a", P.encode_state(3, 4, tri)),
                                        ("bb", P.encode_state(3, 4, tri, tri / 10, "quant16"))]))
    assert len(data) % 8 == 0
    b = P.parse_bundle(data)
    end = b.entries[-1].offset + b.entries[-1].size  # the last entry's padding is not needed
    for n in range(end):
        with pytest.raises(P.ProtocolError):
            P.decode_bundle(data[:n])
    assert len(P.decode_bundle(data[:end])) == 2
    for _ in range(300):
        bad = bytearray(data)
        for i in rng.integers(0, len(bad), 3):
            bad[i] = int(rng.integers(0, 256))
        try:
            for st in P.decode_bundle(bytes(bad)):
                assert st.positions.shape[1] == 3
        except P.ProtocolError:
            pass
    with pytest.raises(ValueError):
        P.encode_bundle(1, 1, [("not/an/id", b"")])
    assert P.decode_bundle(bytes(P.encode_bundle(1, 2, []))) == []  # an empty bundle is well formed


def test_the_document_s_hex_examples_are_the_vectors():
    """Every hex dump in PROTOCOL.md is byte for byte one of the committed vectors."""
    text = (Path(__file__).resolve().parents[1] / "PROTOCOL.md").read_text()
    known = {v["hex"] for g in ("misc", "state", "bundle") for v in load(g)}
    dumps = []
    for block in text.split("```")[1::2]:
        data = []
        for line in block.splitlines():
            for tok in line.split():
                if len(tok) != 2 or not all(c in "0123456789abcdef" for c in tok):
                    break
                data.append(tok)
        if len(data) >= 16:
            dumps.append("".join(data))
    assert len(dumps) == 3, "the remove message, a state and a bundle"
    for d in dumps:
        assert d in known, d[:64]
