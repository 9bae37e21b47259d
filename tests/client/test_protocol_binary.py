"""The binary payloads: the DRPS state layout and its encodings, the DRPB bundle parser against
truncation and corruption."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drape.client import protocol as P


def test_state_header_layout_matches_the_document():
    pos = np.array([[1, 2, 3], [-1, 0.5, 4]], np.float32)
    nrm = np.array([[0, 1, 0], [1, 0, 0]], np.float32)
    data = bytes(P.encode_state(0x0102030405060708, 99, pos, nrm, "float32", P.FLAG_RESET))
    assert len(data) == 64 + 2 * 12 * 2 == P.state_size(2, "float32", True)
    assert data[0:4] == b"DRPS"
    assert data[4] == 1 and data[5] == P.PROTOCOL_MINOR == 9  # major, minor
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


@pytest.mark.parametrize("encoding", P.STATELESS_ENCODINGS)
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
        assert err_p <= 2.0 * 2**-11 and err_n <= 2**-11  # half an ulp of |x| < 2
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


def test_bundle_parser_survives_every_truncation_and_corruption(rng):
    tri = np.arange(9, dtype=np.float32).reshape(3, 3)
    data = bytes(
        P.encode_bundle(
            3, 4, [("a", P.encode_state(3, 4, tri)), ("bb", P.encode_state(3, 4, tri, tri / 10, "quant16"))]
        )
    )
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


def test_a_float32_quant16_decoder_is_within_the_documented_tolerance(rng):
    """PROTOCOL.md section 9: the vectors decode quant16 in float64 rounded to float32; a decoder
    evaluating in float32 is within 4 float32 ulps of max(|min|, |max|) of each axis."""
    for scale in (1.0, 100.0, 1.0e4):
        pos = (rng.normal(0, 1, (500, 3)) * scale + rng.uniform(-scale, scale, 3)).astype(np.float32)
        st = P.decode_state(P.encode_state(1, 2, pos, encoding="quant16"))
        lo, hi = (np.array(b, np.float32) for b in st.bounds)
        data = bytes(P.encode_state(1, 2, pos, encoding="quant16"))
        q = np.frombuffer(data, "<u2", offset=P.STATE_HEADER_SIZE).reshape(-1, 3).astype(np.float32)
        f32 = lo + q * ((hi - lo) / np.float32(P.QUANT_MAX))  # all float32
        assert f32.dtype == np.float32
        ulp = np.spacing(np.maximum(np.abs(lo), np.abs(hi)))
        assert (np.abs(f32 - st.positions) <= 4 * ulp).all()
        # and the encoding error itself is within half a quantisation step (plus float32 rounding)
        step = (hi.astype(np.float64) - lo) / P.QUANT_MAX
        assert (np.abs(st.positions.astype(np.float64) - pos) <= step / 2 + ulp).all()
