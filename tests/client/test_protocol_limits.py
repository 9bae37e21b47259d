"""Protocol 1.2 and hostile input: decoding caps (nesting, keys, array and string lengths, element
count) give documented bad-request errors, never a traceback; masses float32 cannot hold are
refused; features_add / features_remove and the pure feature-set rule resolve_features; the
overloaded error code."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from drape.client import protocol as P

TOKEN = "0123456789abcdef0123456789abcdef"
GRID = {"v": [1, 2], "client": "c", "grid": {"cols": 2, "rows": 2}}
CONTROL = {"v": [1, 2], "cloth": "abc", "token": TOKEN}


def packed(m) -> bytes:
    return msgpack.packb(m, use_bin_type=True)


def nested(depth: int) -> bytes:
    """``depth`` one-element arrays around a 0, as msgpack bytes (msgpack-python itself will not
    pack beyond its own recursion limit, which is the point of the test)."""
    return b"\x91" * depth + b"\x00"


def packed_with(m: dict, key: str, raw: bytes) -> bytes:
    """The map ``m`` plus ``key`` whose value is the msgpack bytes ``raw`` (fixmap: < 16 keys)."""
    assert len(m) < 15
    return bytes([0x80 | (len(m) + 1)]) + b"".join(packed(k) + packed(v) for k, v in m.items()) + packed(key) + raw


DECODERS = [
    P.decode_submit,
    P.decode_control,
    P.decode_remove,
    P.decode_info,
    P.decode_control_batch,
    P.decode_reply,
    P.decode_stats,
    P.unpack_message,
]


@pytest.mark.parametrize("depth", [P.MAX_NESTING + 1, 1000, 5000])
@pytest.mark.parametrize("where", ["v", "extra", "gravity", "material.mass", "top"])
def test_deep_nesting_is_a_malformed_request_not_a_recursion_error(depth, where):
    deep = nested(depth)
    if where == "top":
        data = deep
    elif where == "material.mass":
        data = packed_with(GRID, "material", packed_with({}, "mass", deep))
    else:
        data = packed_with({k: v for k, v in GRID.items() if k != where}, where, deep)
    for decode in DECODERS:
        with pytest.raises(P.ProtocolError) as e:
            decode(data)
        assert e.value.code == P.ERR_MALFORMED, (decode.__name__, e.value)
        assert e.value.code in P.BAD_REQUEST_CODES


def test_nesting_up_to_the_cap_is_still_parsed():
    data = packed_with(GRID, "future", nested(P.MAX_NESTING - 1))  # the map is level 1
    assert P.decode_submit(data).grid == P.GridSpec(2, 2)


def test_a_map_of_200k_keys_is_refused_by_the_parser_before_any_field_is_read():
    big = {**GRID, **{f"k{i}": 0 for i in range(200_000)}}
    data = packed(big)
    assert len(data) < P.DEFAULT_LIMITS.max_message_bytes  # the size cap alone would let it through
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(data)
    assert e.value.code == P.ERR_MALFORMED and "max_map_len" in e.value.message


@pytest.mark.parametrize(
    "value,what",
    [
        (["wind"] * (P.MAX_ARRAY_LENGTH + 1), "max_array_len"),
        ("x" * (P.MAX_STRING_BYTES + 1), "max_str_len"),
        (msgpack.ExtType(3, b"abc"), "max_ext_len"),
    ],
)
def test_unknown_keys_are_bounded_in_length(value, what):
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(packed({**GRID, "unknown": value}))
    assert e.value.code == P.ERR_MALFORMED and what in e.value.message


def test_unknown_keys_within_the_caps_are_ignored():
    m = {**GRID, **{f"k{i}": [1] * 100 for i in range(P.MAX_MAP_KEYS - len(GRID))}}
    assert P.decode_submit(packed(m)).grid == P.GridSpec(2, 2)


def test_too_many_values_in_one_message_is_too_large_and_cheap():
    """1024 arrays of 1024 zeros: 1 M values in 1 MB, under every per-container cap."""
    data = packed({**GRID, "x": [[0] * 1024] * 1024})
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(data)
    assert e.value.code == P.ERR_TOO_LARGE and str(P.MAX_ELEMENTS) in e.value.message


def test_every_truncation_of_a_message_is_a_protocol_error():
    data = P.encode_control(
        P.ControlRequest(
            "abc",
            TOKEN,
            pins=P.PinUpdate(np.array([0], np.uint32), np.zeros((1, 3), np.float32)),
            colliders=(P.Sphere((0, 0, 0), 1.0),),
            features_add=("wind",),
        )
    )
    for n in range(len(data)):
        with pytest.raises(P.ProtocolError):
            P.decode_control(data[:n])


@pytest.mark.parametrize("mass", [5e-324, 1e-310, 1e-38, 1e-20, P.MIN_MASS * 0.999, 0.0, -1.0, 1.0e7])
def test_masses_float32_cannot_hold_are_refused_at_validation(mass):
    for data in (packed({**GRID, "material": {"mass": mass}}), packed({**CONTROL, "material": {"mass": mass}})):
        decode = P.decode_submit if b"client" in data else P.decode_control
        with pytest.raises(P.ProtocolError) as e:
            decode(data)
        assert e.value.code == P.ERR_INVALID_VALUE and "material.mass" in e.value.message


def test_the_least_mass_is_accepted_and_its_vertex_masses_are_normal_float32():
    req = P.decode_submit(packed({**GRID, "material": {"mass": P.MIN_MASS}}))
    assert req.material["mass"] == P.MIN_MASS
    per_vertex = np.float32(P.MIN_MASS / P.DEFAULT_LIMITS.max_vertices)  # the smallest even share
    assert per_vertex >= np.finfo(np.float32).tiny and np.isfinite(np.float32(1.0) / per_vertex)


def test_the_server_params_use_the_protocol_s_mass_range():
    from drape.server.sim.params import ClothParams, Material

    with pytest.raises(ValueError, match="mass"):
        ClothParams(material=Material(mass=5e-324)).validate()
    ClothParams(material=Material(mass=P.MIN_MASS)).validate()


# ---------------------------------------------------------------------------------------------
# 1.2: features_add / features_remove, resolve_features


def test_features_add_and_remove_round_trip_and_are_validated_like_features():
    req = P.ControlRequest("abc", TOKEN, features_add=("wind", "normals"), features_remove=("tethers",), rid=4)
    back = P.decode_control(P.encode_control(req))
    assert back == req and back.features is None
    assert P.decode_control(P.encode_control(P.ControlRequest("abc", TOKEN))).features_add is None
    for bad, code in [
        ({"features_add": "wind"}, P.ERR_INVALID_TYPE),
        ({"features_remove": ["air"]}, P.ERR_INVALID_VALUE),
        ({"features_add": ["wind"] * 17}, P.ERR_TOO_LARGE),
        ({"features_add": ["wind"], "features_remove": ["wind"]}, P.ERR_INVALID_VALUE),
    ]:
        with pytest.raises(P.ProtocolError) as e:
            P.decode_control(packed({**CONTROL, **bad}))
        assert e.value.code == code, bad
        assert "features_" in e.value.message
    # in a batch, a bad item is refused alone and named
    items = P.decode_control_batch(
        packed(
            {
                "v": [1, 2],
                "client": "me",
                "items": [
                    {"cloth": "a", "token": TOKEN, "features_add": ["wind"]},
                    {"cloth": "a", "token": TOKEN, "features_remove": ["nope"]},
                ],
            }
        )
    ).items
    assert items[0].features_add == ("wind",) and items[1].code == P.ERR_INVALID_VALUE
    assert "items[1].features_remove" in items[1].message


def _ctl(**kw) -> P.ControlRequest:
    return P.ControlRequest("abc", TOKEN, **kw)


@pytest.mark.parametrize(
    "current,req,want",
    [
        ({"normals", "colliders"}, _ctl(), {"normals", "colliders"}),
        # the 1.1 trap, unchanged in meaning: features replaces the set
        ({"normals"}, _ctl(features=("wind",)), {"wind"}),
        ({"colliders", "tethers"}, _ctl(features=("normals",)), {"normals"}),
        # 1.2: add and remove keep everything else
        ({"normals"}, _ctl(features_add=("wind",)), {"normals", "wind"}),
        ({"colliders", "tethers"}, _ctl(features_add=("normals",)), {"colliders", "tethers", "normals"}),
        ({"colliders", "tethers", "xpbd"}, _ctl(features_remove=("tethers", "wind")), {"colliders", "xpbd"}),
        ({"xpbd"}, _ctl(features=("wind",), features_add=("normals",), features_remove=("wind",)), {"normals"}),
        # colliders and state.normals switch their features, after the lists
        ({"wind"}, _ctl(colliders=(P.Sphere((0, 0, 0), 1.0),)), {"wind", "colliders"}),
        ({"colliders"}, _ctl(colliders=()), {"colliders"}),
        ({"colliders"}, _ctl(features_remove=("colliders",), colliders=(P.Plane((0, 1, 0), 0.0),)), {"colliders"}),
        ({"wind"}, _ctl(state=P.StateOptions(normals=True)), {"wind", "normals"}),
        ({"normals"}, _ctl(features_add=("normals",), state=P.StateOptions(normals=False)), set()),
        ({"normals"}, _ctl(state=P.StateOptions(encoding="quant16")), {"normals"}),
    ],
)
def test_resolve_features(current, req, want):
    got = P.resolve_features(frozenset(current), req)
    assert got == frozenset(want) and isinstance(got, frozenset)
    # the reply carries it in the protocol's order, and a decoded reply gives it back
    listed = P.feature_list(got)
    assert list(listed) == [f for f in P.FEATURE_NAMES if f in want]
    rep = P.control_reply_from_map(P.decode_reply(P.encode_control_reply(P.ControlReply(7, 1, listed))))
    assert rep.features == listed and rep.tick == 7


def test_resolve_features_refuses_unknown_names_it_is_handed():
    with pytest.raises(ValueError, match="hologram"):
        P.resolve_features(frozenset({"hologram"}), _ctl())


def test_a_pre_1_2_control_reply_has_no_feature_set():
    m = P.decode_reply(P.encode_control_reply(P.ControlReply(9, 2)))
    assert "features" not in m and P.control_reply_from_map(m).features is None
    assert P.tick_reply_from_map(m) == 9


def test_batch_reply_items_carry_their_feature_sets():
    rep = P.ControlBatchReply(5, [P.BatchItemResult(5, features=("xpbd",)), P.BatchItemResult(None, "forbidden", "no")])
    back = P.control_batch_reply_from_map(P.decode_reply(P.encode_control_batch_reply(rep)))
    assert back.results[0].features == ("xpbd",) and back.results[1].features is None and back.failed == 1


def test_overloaded_is_a_known_code_with_its_own_exception():
    assert P.ERR_OVERLOADED == "overloaded" and P.ERR_OVERLOADED in P.ERROR_CODES
    assert P.ERR_OVERLOADED not in P.BAD_REQUEST_CODES
    with pytest.raises(P.Overloaded) as e:
        P.decode_reply(P.encode_error("overloaded", "tick budget", 3))
    assert e.value.code == "overloaded" and e.value.rid == 3 and not isinstance(e.value, P.ProtocolError)
    assert type(P.error_for("overloaded", "x")) is P.Overloaded
    from drape.client import Overloaded

    assert Overloaded is P.Overloaded


def test_corrupted_vectors_never_raise_anything_but_protocol_errors(rng):
    """Every committed message vector, corrupted at random (bytes changed, cut, repeated): each
    decoder either accepts it or raises ProtocolError (decode_reply: the DrapeError an error reply
    carries), never another exception."""
    import json
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "vectors"
    seeds = [
        bytes.fromhex(v["hex"])
        for g in ("submit", "control", "misc", "invalid", "accepted")
        for v in json.loads((folder / f"{g}.json").read_text())
    ]
    decoders = [*DECODERS, P.decode_error, P.decode_state, P.decode_bundle]
    for _ in range(3000):
        data = bytearray(seeds[int(rng.integers(len(seeds)))])
        for _ in range(int(rng.integers(1, 4))):
            kind = int(rng.integers(3))
            if kind == 0 and data:
                data[int(rng.integers(len(data)))] = int(rng.integers(256))
            elif kind == 1 and data:
                data = data[: int(rng.integers(len(data)))]
            else:
                at = int(rng.integers(len(data) + 1))
                data = data[:at] + data[at : at + int(rng.integers(1, 16))] * 2 + data[at + 16 :]
        for decode in decoders:
            try:
                decode(bytes(data))
            except P.ProtocolError:
                pass
            except P.DrapeError:
                assert decode is P.decode_reply


def test_a_binary_map_key_anywhere_is_malformed():
    """PROTOCOL.md §8: map keys are strings; msgpack's strict_map_key alone lets bin keys through."""
    for payload in ({"v": [1, 2], "rid": 1, b"cloth": "x"}, {"v": [1, 2], "rid": 1, "material": {b"mass": 1.0}}):
        data = msgpack.packb(payload, use_bin_type=True)
        with pytest.raises(P.ProtocolError) as e:
            P.unpack_message(data)
        assert e.value.code == P.ERR_MALFORMED
