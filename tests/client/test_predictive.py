"""The predictive state encoding's codec (client/protocol/predictive.py): exact integer round
trips, the error bound of half a step at every state of a long stream with drops and keyframes,
the packed layout as docs/codec.md writes it, and refusal of malformed data."""

from __future__ import annotations

import numpy as np
import pytest

from drape.client.protocol import predictive as P


def _motion(rng: np.random.Generator, n: int, states: int, speed: float = 0.02) -> np.ndarray:
    """A smooth random motion: positions (states, n, 3) float32 around 1-2 m from the origin."""
    x = rng.uniform(-2, 2, (n, 3))
    v = rng.normal(0, speed, (n, 3))
    out = np.empty((states, n, 3), np.float32)
    for t in range(states):
        v = 0.95 * v + rng.normal(0, speed * 0.1, (n, 3))
        x = x + v
        out[t] = x
    return out


@pytest.mark.parametrize("n", [1, 31, 32, 33, 100, 1024])
def test_symbols_and_packing_round_trip_exactly(rng, n):
    q = rng.integers(-P.Q_LIMIT, P.Q_LIMIT + 1, (n, 3)).astype(np.int32)
    q1 = rng.integers(-P.Q_LIMIT, P.Q_LIMIT + 1, (n, 3)).astype(np.int32)
    q2 = rng.integers(-P.Q_LIMIT, P.Q_LIMIT + 1, (n, 3)).astype(np.int32)
    for order in (P.ORDER_INTRA, P.ORDER_PREVIOUS, P.ORDER_LINEAR):
        p = P.prediction(order, q1, q2, q.shape)
        z = P.symbols(q, p)
        data = P.encode_residuals(z)
        back, size = P.decode_residuals(data, n)
        assert size == len(data) == P.packed_size(n, np.frombuffer(data, np.uint8, 3 * (-(-n // 32))))
        np.testing.assert_array_equal(back, z)
        np.testing.assert_array_equal(P.unsymbols(back, p), q)


def test_the_packed_layout_is_the_documented_one():
    """docs/codec.md's example: 2 vertices, residuals x (1, -1), y (0, 0), z (5, 3)."""
    q = np.array([[1, 0, 5], [-1, 0, 3]], np.int32)
    z = P.symbols(q, np.zeros_like(q))
    # x: d = (1, -2) -> zig-zag (2, 3), width 2; y: (0, 0), width 0; z: d = (5, -2) -> (10, 3), width 4
    np.testing.assert_array_equal(z, [[2, 3], [0, 0], [10, 3]])
    data = P.encode_residuals(z)
    # widths 2, 0, 4 and a pad byte; then a block of width w takes w words (32 values of w bits):
    # x's 2 words, 2 | 3 << 2 = 0x0e then 0; z's 4 words, 10 | 3 << 4 = 0x3a then 0, 0, 0
    assert data.hex(" ") == "02 00 04 00 " + "0e 00 00 00 " + "00 " * 4 + "3a 00 00 00 " + "00 " * 11 + "00"


def test_the_error_stays_within_half_a_step_for_10000_ticks_with_drops_and_keyframes(rng):
    """Closed loop: the encoder predicts from what the decoder rebuilt. A decoder that misses a
    state waits for a keyframe (periodic, or requested) and resumes; the error of every state it
    shows is at most half a step, and nothing drifts."""
    n, step = 64, float(rng.choice([0.00025, 0.001, 0.004]))
    x = _motion(rng, n, 10_000, speed=0.01)
    enc, dec = P.History(), P.History()
    have = True  # the decoder holds the stream's last two states
    shown = dropped = requested = skipped = keys_shown = keys_sent = 0
    bound = step / 2 + 4 * np.spacing(np.float32(np.abs(x).max()))
    want_key = False
    for t, pos in enumerate(x):
        keyframe = t % 60 == 0 or want_key
        want_key = False
        data, order, ref1, ref2 = P.encode_step(pos, step, enc, t, keyframe)
        keys_sent += order == P.ORDER_INTRA
        if rng.random() < 0.02:  # lost on the way
            dropped += 1
            have = False
            if rng.random() < 0.5:
                want_key, requested = True, requested + 1  # the client asks for a keyframe
            continue
        if order != P.ORDER_INTRA and (not have or ref1 != dec.tick1 or (order == 2 and ref2 != dec.tick2)):
            skipped += 1
            continue  # predicted from a state this decoder lacks: not decodable, never shown
        got, _ = P.decode_step(data, n, step, order, dec, t)
        have = True
        shown += 1
        keys_shown += order == P.ORDER_INTRA
        assert np.isfinite(got).all()
        assert np.abs(got - pos).max() <= bound, t
    assert shown + skipped + dropped == len(x)
    assert dropped > 100 and requested > 0 and shown > 0.7 * len(x)
    assert keys_shown > 0.95 * keys_sent  # every keyframe that arrives resyncs the decoder


def test_grid_values_are_clamped_so_no_sum_overflows():
    step = 0.001
    far = np.array([[1e9, -1e9, 0.0]], np.float32)
    q = P.quantise(far, step)
    assert q.tolist() == [[P.Q_LIMIT, -P.Q_LIMIT, 0]]
    p = P.prediction(P.ORDER_LINEAR, -q, q, q.shape)  # 2 q1 - q2 at its extreme
    z = P.symbols(q, p)
    np.testing.assert_array_equal(P.unsymbols(z, p), q)


def test_malformed_data_is_refused():
    z = np.array([[1, 2, 3]], np.uint32).repeat(3, axis=0)
    data = bytearray(P.encode_residuals(z))
    with pytest.raises(ValueError, match="shorter"):
        P.decode_residuals(data[:-1], 3)
    with pytest.raises(ValueError, match="width bytes"):
        P.decode_residuals(data[:2], 3)
    data[0] = 33
    with pytest.raises(ValueError, match="width of 33"):
        P.decode_residuals(data, 3)
    with pytest.raises(ValueError, match="needs the previous state"):
        P.prediction(P.ORDER_PREVIOUS, None, None, (1, 3))
    with pytest.raises(ValueError, match="unknown predictor order"):
        P.prediction(7, None, None, (1, 3))


def test_many_states_decode_at_once_as_each_alone(rng):
    """protocol.decode_predictive_many (a bundle's predictive states in one pass) gives what each
    stream's decode gives, state for state, lacking references included."""
    from drape.client import protocol as Q

    counts = [int(c) for c in rng.integers(1, 200, 6)]
    encs = [P.History() for _ in counts]
    alone = [Q.StateStream(f"c{i}") for i in range(len(counts))]
    together = [Q.StateStream(f"c{i}") for i in range(len(counts))]
    x = [rng.uniform(-1, 1, (n, 3)).astype(np.float32) for n in counts]
    for tick in range(1, 8):
        payloads = []
        for i, n in enumerate(counts):
            x[i] = (x[i] + rng.normal(0, 0.002, (n, 3))).astype(np.float32)
            nrm = x[i] / np.linalg.norm(x[i], axis=1, keepdims=True) if i % 2 else None
            payloads.append(bytes(Q.encode_predictive_state(tick, 9, x[i], 0.001, encs[i], tick == 1, nrm)))
        if tick == 4:  # one stream lost its states: both paths must skip its next ones alike
            alone[2].history.clear()
            together[2].history.clear()
        buf = bytearray()
        offsets = []
        for p in payloads:
            offsets.append(len(buf))
            buf += p + bytes(-len(p) % 8)
        got = Q.decode_predictive_many(bytes(buf), offsets, together)
        for i, p in enumerate(payloads):
            want = alone[i].decode(p)
            assert (got[i] is None) == (want is None), (tick, i)
            if want is not None:
                assert got[i].positions.tobytes() == want.positions.tobytes()
                assert (got[i].normals is None) == (want.normals is None)
                if want.normals is not None:
                    assert got[i].normals.tobytes() == want.normals.tobytes()
                assert (got[i].tick, got[i].flags, got[i].bounds) == (want.tick, want.flags, want.bounds)
    assert [s.undecodable for s in together] == [s.undecodable for s in alone]
    assert together[2].undecodable > 0


def test_like_cloths_decode_as_one_frame_as_each_alone(rng):
    """Like cloths (one vertex count, a bundle's usual case) decode as one (C, n, 3) frame: the
    same bytes as each stream alone, through keyframes at different ticks, a lost state, two
    steps, blocks of 30 bits and more, and the cloths' order changing between bundles
    (each stream's last two states are rows of earlier frames: used whole only in place)."""
    from drape.client import protocol as Q

    k, n = 9, 70
    encs = [P.History() for _ in range(k)]
    alone = [Q.StateStream(f"c{i}") for i in range(k)]
    together = [Q.StateStream(f"c{i}") for i in range(k)]
    x = [rng.uniform(-1, 1, (n, 3)).astype(np.float32) for _ in range(k)]
    for tick in range(1, 14):
        order = list(range(k)) if tick < 9 else list(rng.permutation(k))
        payloads = []
        for i in range(k):
            jump = 1e6 if (tick + i) % 5 == 0 else 0.003  # blocks of 30+ bits now and then (clamped grid values)
            x[i] = (x[i] + rng.normal(0, jump, (n, 3))).astype(np.float32)
            step = 0.001 if i % 3 else 0.0025
            key = tick == 1 or (tick + i) % 4 == 0
            payloads.append(bytes(Q.encode_predictive_state(tick, 9, x[i], step, encs[i], key)))
        if tick == 6:
            alone[4].history.clear()
            together[4].history.clear()
        buf = bytearray()
        offsets = []
        for i in order:
            offsets.append(len(buf))
            buf += payloads[i] + bytes(-len(payloads[i]) % 8)
        got = Q.decode_predictive_many(bytes(buf), offsets, [together[i] for i in order])
        for g, i in zip(got, order, strict=True):
            want = alone[i].decode(payloads[i])
            assert (g is None) == (want is None), (tick, i)
            if want is not None:
                assert g.positions.tobytes() == want.positions.tobytes(), (tick, i)
                assert g.positions.shape == (n, 3) and g.positions.dtype == np.float32
    assert [s.undecodable for s in together] == [s.undecodable for s in alone]
    assert together[4].undecodable > 0


def test_a_broken_header_among_many_raises_as_alone(rng):
    """A bundle's headers are checked all at once; one that breaks a reading rule raises the
    error its state raises alone (the receiver then decodes each alone: only it is lost)."""
    from drape.client import protocol as Q
    from drape.client.protocol.state import STATE_HEADER_SIZE

    x = rng.uniform(-1, 1, (40, 3)).astype(np.float32)
    payloads = [bytearray(Q.encode_predictive_state(1, 9, x, 0.001, P.History(), True)) for _ in range(4)]
    for where, value in ((STATE_HEADER_SIZE + 4, 7), (0, ord("X")), (STATE_HEADER_SIZE, 0)):
        bad = [bytearray(p) for p in payloads]
        bad[2][where] = value
        if where == STATE_HEADER_SIZE:  # the step: 0.0 (not a positive number)
            bad[2][where : where + 4] = bytes(4)
        with pytest.raises(Q.ProtocolError) as alone:
            Q.StateStream("c").decode(bytes(bad[2]))
        buf, offsets = bytearray(), []
        for p in bad:
            offsets.append(len(buf))
            buf += p + bytes(-len(p) % 8)
        with pytest.raises(Q.ProtocolError) as many:
            Q.decode_predictive_many(bytes(buf), offsets, [Q.StateStream(f"c{i}") for i in range(4)])
        assert many.value.message == alone.value.message, where


def test_the_predictive_vectors_both_ways():
    """tests/vectors/predictive.json: the stream's states decode, in order, to their values and
    re-encode from their inputs to the same bytes; the submit asks for the encoding and step."""
    import json
    from pathlib import Path

    from drape.client import protocol as Q

    vectors = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "predictive.json").read_text())
    states = [v for v in vectors if v["message"] == "state"]
    assert [v["value"]["order"] for v in states] == [0, 1, 2, 2, 0]
    stream, history = Q.StateStream("c"), P.History()
    for v in states:
        data, want, given = bytes.fromhex(v["hex"]), v["value"], v["input"]
        st = stream.decode(data)
        assert st is not None and st.encoding == "predictive"
        np.testing.assert_array_equal(st.positions, np.array(want["positions"], np.float32))
        assert (st.tick, st.flags, st.server_time_ns) == (want["tick"], want["flags"], want["server_time_ns"])
        ph = Q.read_predictive_header(data)
        assert (ph.order, ph.ref_tick, ph.ref2_tick, ph.data_size) == (
            want["order"],
            want["ref_tick"],
            want["ref2_tick"],
            want["data_size"],
        )
        nrm = None if given["normals"] is None else np.array(given["normals"], np.float32)
        again = Q.encode_predictive_state(
            want["tick"],
            want["server_time_ns"],
            np.array(given["positions"], np.float32),
            given["step"],
            history,
            keyframe=given["keyframe"],
            normals=nrm,
        )
        assert bytes(again) == data, v["name"]
    sub = next(v for v in vectors if v["name"] == "submit_predictive")
    req = Q.decode_submit(bytes.fromhex(sub["hex"]))
    assert req.state is not None and req.state.encoding == "predictive" and req.state.step == pytest.approx(0.002)
