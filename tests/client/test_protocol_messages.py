"""The msgpack messages: round trips, validation of hostile input with stable codes and messages
that name the field, 1.1 bundle options and batch control, key expressions."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest

from drape.client import protocol as P

TOKEN = "0123456789abcdef0123456789abcdef"


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
        material={
            "mass": 2.0,
            "stiffness": (1.0, 0.5, 0.25),
            "compliance": (0.0, 1e-4, 1e-3),
            "damping": 0.1,
            "friction": 0.3,
            "drag": 0.2,
            "lift": 0.1,
            "air_density": 1.0,
            "tether_limit": 1.1,
        },
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
    mesh = P.SubmitRequest(
        "c", mesh=P.MeshSpec(np.random.rand(10, 3).astype(np.float32), np.array([[0, 1, 2], [2, 3, 4]], np.uint32))
    )
    back = P.decode_submit(P.encode_submit(mesh))
    assert back == mesh and back.n_vertices == 10 and back.grid is None


def test_control_remove_info_replies_round_trip():
    ctl = P.ControlRequest(
        "abc",
        TOKEN,
        pins=P.PinUpdate(np.array([1, 2], np.uint32), np.ones((2, 3), np.float32)),
        colliders=(),
        gravity=(0, 0, 0),
        material={"damping": 0.5},
        features=(),
        iterations=3,
        substeps=2,
        chebyshev_rho=0.0,
        state=P.StateOptions(None, "float16"),
        reset=True,
        rid=4,
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
    for code in (
        "malformed",
        "invalid_type",
        "invalid_value",
        "index_out_of_range",
        "too_large",
        "missing_field",
        "unsupported_version",
    ):
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
    (
        raw(sub(colliders=[{"type": "capsule", "p0": [0, 0, 0], "p1": [1, 0, float("nan")], "radius": 1}])),
        "invalid_value",
    ),
    (raw(sub(colliders=[{"type": "sphere", "center": [0, 0, 0], "radius": 1}] * 33)), "too_large"),
    (raw(sub(state={"encoding": "png"})), "invalid_value"),
    (raw(sub(state={"normals": 1})), "invalid_type"),
    (raw(sub(mesh={"vertices": b"", "triangles": b""})), "invalid_value"),  # grid and mesh
    (raw(sub(grid=None)), "missing_field"),
]


def _mesh(v, t, **kw):
    return raw(
        sub(
            grid=None,
            mesh={"vertices": np.asarray(v, "<f4").tobytes(), "triangles": np.asarray(t, "<u4").tobytes()},
            **kw,
        )
    )


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
        raw(sub(pinned=np.array([9], "<u4").tobytes())): "pinned index 9 out of range 0..8 for a 3x3 grid",
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
    items = [
        P.ControlRequest("a", TOKEN, pins=P.PinUpdate(np.array([1], np.uint32), np.ones((1, 3), np.float32))),
        P.ControlRequest("b", TOKEN, gravity=(0, 0, 0), colliders=(), reset=True),
    ]
    req = P.ControlBatchRequest("me", items, rid=77)
    back = P.decode_control_batch(P.encode_control_batch(req))
    assert (back.client, back.rid) == ("me", 77)
    assert back.items == [dataclasses.replace(it, rid=77) for it in items]  # errors of an item echo the batch's rid
    bad = raw(
        {
            "v": [1, 1],
            "rid": 3,
            "client": "me",
            "items": [
                {"cloth": "a", "token": TOKEN, "pins": pins([0], [[0, np.inf, 0]])},
                {"cloth": "a", "token": TOKEN, "material": {"stiffness": [1, 1, 2]}},
                {"cloth": "a", "token": TOKEN, "pins": pins(range(5), np.zeros((5, 3)))},
                {"cloth": "a", "token": TOKEN},
            ],
        }
    )
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
