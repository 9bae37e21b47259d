"""Protocol 1.4 ``moves`` (PROTOCOL.md 5.1.1): the block's codec and its validation on the bytes
alone, each fault naming its field; ``items`` optional only with ``moves``; the reply's fields."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from drape.client import protocol as P

TOK = ["0123456789abcdef" * 2, "fedcba9876543210" * 2, "00112233445566778899aabbccddeeff"]
IDS = ["a", "b-2", "c.3"]


def block(n: int = 3, k: int = 2, rng: np.random.Generator | None = None) -> P.PinMoves:
    rng = rng or np.random.default_rng(0)
    return P.PinMoves(
        IDS[:n], TOK[:n], np.arange(k, dtype=np.uint32) * 5, rng.uniform(-9, 9, (n, k, 3)).astype(np.float32)
    )


def batch_map(mv: P.PinMoves | None, items: list | None = None, **moves_changes) -> dict:
    m = P.control_batch_to_map(P.ControlBatchRequest("c1", items or [], 3, mv))
    if moves_changes:
        m["moves"].update(moves_changes)
    return m


def refused(m: dict, limits: P.Limits = P.DEFAULT_LIMITS) -> P.ProtocolError:
    with pytest.raises(P.ProtocolError) as e:
        P.decode_control_batch(P.pack(m), limits)
    return e.value


def test_round_trip_without_items(rng):
    mv = block(3, 4, rng)
    data = P.encode_control_batch(P.ControlBatchRequest("c1", [], 3, mv))
    assert "items" not in msgpack.unpackb(data)
    d = P.decode_control_batch(data)
    assert d.items == [] and d.moves == mv and d.rid == 3
    assert d.moves is not None and d.moves.targets.shape == (3, 4, 3) and d.moves.targets.dtype == np.float32
    item = P.ControlRequest(IDS[0], TOK[0], reset=True, rid=3)  # a decoded item carries the batch rid
    d = P.decode_control_batch(P.encode_control_batch(P.ControlBatchRequest("c1", [item], 3, mv)))
    assert d.items == [item] and d.moves == mv


def test_items_optional_only_with_moves():
    m = batch_map(None)
    m.pop("items")
    assert refused(m).code == P.ERR_MISSING_FIELD
    m["items"] = []
    assert refused(m).code == P.ERR_INVALID_VALUE
    m = batch_map(block())
    m["items"] = []
    assert P.decode_control_batch(P.pack(m)).items == []


@pytest.mark.parametrize(
    "changes, code, field",
    [
        (dict(targets=b"\0" * 12), P.ERR_INVALID_VALUE, "moves.targets"),
        (dict(targets=[0.0] * 18), P.ERR_INVALID_TYPE, "moves.targets"),
        (dict(tokens=TOK[:2]), P.ERR_INVALID_VALUE, "moves.tokens"),
        (dict(tokens=[TOK[0], TOK[1], TOK[2].upper()]), P.ERR_INVALID_VALUE, "moves.tokens[2]"),
        (dict(tokens=[TOK[0], 7, TOK[2]]), P.ERR_INVALID_TYPE, "moves.tokens[1]"),
        (dict(cloths=["a", "b\nc", "d"]), P.ERR_INVALID_VALUE, "moves.cloths[1]"),
        (dict(cloths=["a", "b", "c\n"]), P.ERR_INVALID_VALUE, "moves.cloths[2]"),
        (dict(cloths=["a", "", "d"]), P.ERR_INVALID_VALUE, "moves.cloths[1]"),
        (dict(cloths=[], tokens=[]), P.ERR_INVALID_VALUE, "moves.cloths"),
        (dict(cloths="a"), P.ERR_INVALID_TYPE, "moves.cloths"),
        (dict(indices=b""), P.ERR_INVALID_VALUE, "moves.indices"),
        (dict(indices=np.array([4, 4], "<u4").tobytes()), P.ERR_INVALID_VALUE, "moves.indices"),
        (dict(indices=b"\0\0\0"), P.ERR_INVALID_VALUE, "moves.indices"),
    ],
)
def test_invalid_blocks_name_the_field(changes, code, field):
    e = refused(batch_map(block(), **changes))
    assert e.code == code and f"'{field}'" in e.message and e.rid == 3


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 2e5])
def test_targets_finite_within_bounds(rng, bad):
    mv = block(3, 2, rng)
    t = mv.targets.copy()
    t[2, 1, 0] = bad
    e = refused(batch_map(P.PinMoves(mv.cloths, mv.tokens, mv.indices, t)))
    assert e.code == P.ERR_INVALID_VALUE and "value 15 (cloth 2)" in e.message


def test_caps():
    lim = P.Limits(max_batch_moves=2, max_pin_updates=3)
    assert refused(batch_map(block(3, 1)), lim).code == P.ERR_TOO_LARGE
    assert refused(batch_map(block(2, 4)), lim).code == P.ERR_TOO_LARGE
    assert P.decode_control_batch(P.pack(batch_map(block(2, 3))), lim).moves is not None
    assert refused(batch_map(block(1), moves=None) | {"moves": [1]}).code == P.ERR_INVALID_TYPE
    assert P.DEFAULT_LIMITS.max_batch_moves == P.MAX_ARRAY_LENGTH  # the array cap bounds it anyway


def test_many_moves_within_the_decoding_caps(rng):
    n = P.DEFAULT_LIMITS.max_batch_moves
    mv = P.PinMoves(
        [f"c{i}" for i in range(n)],
        [f"{i:032x}" for i in range(n)],
        np.array([0, 31], np.uint32),
        rng.uniform(-1, 1, (n, 2, 3)).astype(np.float32),
    )
    d = P.decode_control_batch(P.encode_control_batch(P.ControlBatchRequest("c1", [], 1, mv)))
    assert d.moves == mv


def test_reply_fields():
    rep = P.ControlBatchReply(1051, [P.BatchItemResult(1051)], 4, 1050, [(2, P.ERR_FORBIDDEN, "not yours")])
    m = P.decode_reply(P.encode_control_batch_reply(rep))
    assert m["moves_tick"] == 1050 and m["moves_failed"] == [[2, "forbidden", "not yours"]] and m["failed"] == 0
    assert P.control_batch_reply_from_map(m) == rep
    plain = P.decode_reply(P.encode_control_batch_reply(P.ControlBatchReply(7, [P.BatchItemResult(7)], 1)))
    assert "moves_tick" not in plain and P.control_batch_reply_from_map(plain).moves_failed is None
    m["moves_failed"] = [[2, "forbidden"]]
    with pytest.raises(P.ProtocolError):
        P.control_batch_reply_from_map(m)


def test_encoder_checks_shapes():
    with pytest.raises(ValueError):
        P.moves_to_map(P.PinMoves(["a"], TOK[:2], np.array([0], np.uint32), np.zeros((1, 1, 3), np.float32)))
    with pytest.raises(ValueError):
        P.moves_to_map(P.PinMoves(["a"], TOK[:1], np.array([0, 1], np.uint32), np.zeros((1, 1, 3), np.float32)))
