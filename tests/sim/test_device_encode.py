"""The frame encoded on the device (drape.server.sim.opencl.encode, kernels/encode.cl): every
publication's bytes equal drape.client.protocol's encode_state / encode_bundle, on real OpenCL;
predictive states (1.5, devstreams' decisions) equal the host encoder's (statecodec) tick after
tick, and decode within half a step through the SDK's StateStream."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyopencl as cl
import pytest
from conftest import random_grid_fabric

from drape.client import protocol as P
from drape.client.protocol.predictive import Q_LIMIT
from drape.server.sim.opencl.compact import Compactor
from drape.server.sim.opencl.devrates import DeviceRates, RateFrame
from drape.server.sim.opencl.devstreams import DeviceStreams
from drape.server.sim.opencl.encode import (
    HEADER_OFFSETS,
    QUANT16_FP32_TOLERANCE,
    ClothEntry,
    DeviceEncoder,
    FramePlan,
    Publication,
    history_end,
)
from drape.server.sim.roster import Roster
from drape.server.sim.statecodec import FrameEncoder, PredictiveStreams

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
MF = cl.mem_flags
ENCS = (P.ENC_FLOAT32, P.ENC_FLOAT16, P.ENC_QUANT16)


def _buffer(device, host: np.ndarray) -> cl.Buffer:
    return cl.Buffer(device.ctx, MF.READ_ONLY | MF.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(host, np.float32))


def _world_arrays(
    rng: np.random.Generator, cloths: list[ClothEntry], pos: list[np.ndarray], nrm: list[np.ndarray], stride: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """float4 position and normal arrays as the world holds them (stride 3: packed xyz); the
    gaps between cloths and the w components are NaN, so reading outside a cloth's range shows
    in its bounds."""
    end = max((c.vbase + c.n for c in cloths), default=0) + int(rng.integers(0, 8))
    P4 = np.full((max(end, 1), 4), np.nan, np.float32)
    N4 = np.full((max(end, 1), 4), np.nan, np.float32)
    for c, p, m in zip(cloths, pos, nrm, strict=True):
        P4[c.vbase : c.vbase + c.n, :3] = p
        N4[c.vbase : c.vbase + c.n, :3] = m
    if stride == 3:
        return np.ascontiguousarray(P4[:, :3]), np.ascontiguousarray(N4[:, :3])
    return P4, N4


def _random_positions(rng: np.random.Generator, n: int) -> np.ndarray:
    """Positions of one cloth, from a menu of awkward cases."""
    kind = int(rng.integers(0, 7))
    scale = 10.0 ** rng.uniform(-3, 3)
    p = rng.normal(rng.normal(0, 5, 3), scale, (n, 3))
    if kind == 1:  # degenerate bounds: one axis constant, or the whole cloth one point
        p[:, rng.integers(0, 3)] = rng.normal()
    elif kind == 2:
        p[:] = rng.normal(0, 3, 3)
    elif kind == 3:  # beyond float16's range: clamped to +-65504; values near the top
        p = rng.choice([65504.0, 65519.0, 65520.0, 7e4, 1e6, -65519.9, -1e9, 3.0], (n, 3))
    elif kind == 4:  # float16 subnormals and exact quant16 ties: extent 65535, values k + 0.5
        p = rng.integers(0, 65535, (n, 3)) + rng.choice([0.0, 0.5], (n, 3))
        p[0], p[-1] = 0.0, 65535.0
    elif kind == 5:
        p = rng.uniform(-1e-4, 1e-4, (n, 3)) * rng.choice([1.0, 1e-3], (n, 3))
    return p.astype(np.float32)


def _random_normals(rng: np.random.Generator, n: int) -> np.ndarray:
    m = rng.normal(0, 1, (n, 3))
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    m[rng.random(n) < 0.1] *= 1.01  # a little past +-1: snorm16 clamps
    return m.astype(np.float32)


def _random_id(rng: np.random.Generator, taken: set[str]) -> str:
    """A random valid id of 1-64 characters not in ``taken`` (added to it): a server's cloths
    have distinct ids (FramePlan refuses one twice; seed 20 once drew "n" for two cloths)."""
    alphabet = np.array(list("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-"))
    while (cid := "".join(rng.choice(alphabet, int(rng.integers(1, 65))))) in taken:
        pass
    taken.add(cid)
    return cid


def _random_frame(rng: np.random.Generator, k: int, max_n: int = 700):
    """k cloths at random places (gaps, random order) of the world's buffers, random encodings
    and normals, grouped into singles and bundles; some cloths in no publication."""
    sizes = rng.integers(1, max_n, k)
    sizes[rng.random(k) < 0.2] = 1
    order = rng.permutation(k)
    vbase = np.zeros(k, np.int64)
    at = int(rng.integers(0, 5))
    for i in order:
        vbase[i] = at
        at += int(sizes[i]) + int(rng.integers(0, 5))
    taken: set[str] = set()
    cloths = [
        ClothEntry(
            _random_id(rng, taken), int(vbase[i]), int(sizes[i]), int(rng.choice(ENCS)), bool(rng.random() < 0.5)
        )
        for i in range(k)
    ]
    pos = [_random_positions(rng, c.n) for c in cloths]
    nrm = [_random_normals(rng, c.n) for c in cloths]
    published = rng.permutation(k)[: max(1, k - int(rng.integers(0, 3)))]
    pubs: list[Publication] = []
    rest = list(published)
    while rest:
        take = int(rng.integers(1, 6))
        group, rest = rest[:take], rest[take:]
        if take == 1 and rng.random() < 0.6:
            pubs.append(Publication(f"state/{cloths[group[0]].cloth}", (int(group[0]),)))
        else:
            pubs.append(Publication(f"bundle/{len(pubs)}", tuple(int(i) for i in group), bundle=True))
    rng.shuffle(pubs)  # type: ignore[arg-type]
    return cloths, pos, nrm, pubs


def _reference(cloths, pos, nrm, pubs, tick, time_ns, flags) -> list[bytes]:
    def state(i: int) -> bytearray:
        c = cloths[i]
        return P.encode_state(
            tick, time_ns, pos[i], nrm[i] if c.normals else None, P.ENCODING_NAMES[c.encoding], int(flags[i])
        )

    out = []
    for pub in pubs:
        if pub.bundle:
            out.append(bytes(P.encode_bundle(tick, time_ns, [(cloths[i].cloth, state(i)) for i in pub.cloths])))
        else:
            out.append(bytes(state(pub.cloths[0])))
    return out


def _encode(device, enc: DeviceEncoder, P4, N4, tick, time_ns, flags) -> list[bytes]:
    pb, nb = _buffer(device, P4), _buffer(device, N4)
    enc.encode(device.queue, pb, nb, tick, time_ns, flags)
    return [bytes(v) for v in enc.slices()]


def _dirty(device, enc: DeviceEncoder, plan: FramePlan) -> None:
    """The encoder's output buffer filled with garbage, then ``plan`` set again on the buffer kept
    (no zero fill: the kernel writes every byte of every state it codes, padding included)."""
    assert enc._out is not None
    made = enc.buffers_made
    cl.enqueue_fill_buffer(device.queue, enc._out, np.full(1, 0xA5, np.uint8), 0, enc._out.size).wait()
    enc.set_plan(plan)
    assert enc.buffers_made == made


def _assert_same(got: list[bytes], want: list[bytes], pubs) -> None:
    assert len(got) == len(want)
    for g, w, pub in zip(got, want, pubs, strict=True):
        assert len(g) == len(w), pub
        if g != w:
            d = np.flatnonzero(np.frombuffer(g, np.uint8) != np.frombuffer(w, np.uint8))
            pytest.fail(f"{pub.key}: {len(d)} bytes differ, first at {d[:8].tolist()}")


@pytest.mark.parametrize(
    "k, local_size, stride, soft_half",
    [
        (1, None, 4, None),
        (7, None, 4, None),
        (40, None, 4, None),
        (40, 16, 4, False),
        (25, 256, 4, False),
        (30, None, 3, None),
        (30, 64, 3, True),
    ],
)
def test_random_frames_equal_the_protocol_encoder(device, rng, k, local_size, stride, soft_half):
    """local_size None is the device's default (1 on a CPU); GPUs run 256 (a reduction tree).
    stride 4: the world's float4 vertex buffers; 3: packed xyz rows. soft_half None is the
    device's default (integer float16 conversion on a CPU); GPUs use vstore_half_rte (False)."""
    cloths, pos, nrm, pubs = _random_frame(rng, k)
    P4, N4 = _world_arrays(rng, cloths, pos, nrm, stride)
    plan = FramePlan.build(cloths, pubs)
    enc = DeviceEncoder(device, local_size=local_size, stride=stride, soft_half=soft_half)
    enc.set_plan(plan)
    _dirty(device, enc, plan)
    try:
        for tick in (1, 2**40 + 3):  # the same plan over ticks: dynamic fields rewritten, ring of host buffers
            time_ns = int(rng.integers(0, 2**63))
            flags = rng.choice([0, P.FLAG_RESET, P.FLAG_NORMALS, 0x8000], k).astype(np.uint16)
            got = _encode(device, enc, P4, N4, tick, time_ns, flags)
            want = _reference(cloths, pos, nrm, pubs, tick, time_ns, flags)
            _assert_same(got, want, pubs)
            whole = bytearray(plan.size)  # the publications at their offsets, zeros up to 8 bytes
            for w, off in zip(want, plan.pub_offset.tolist(), strict=True):
                whole[off : off + len(w)] = w
            assert bytes(enc.read()) == bytes(whole)
            pos = [p[rng.permutation(len(p))] for p in pos]  # new positions for the next tick
            P4, N4 = _world_arrays(rng, cloths, pos, nrm, stride)
        assert len(enc.nonfinite()) == 0
    finally:
        enc.close()


def test_views_of_the_previous_frame_stay_valid(device, rng):
    cloths, pos, nrm, pubs = _random_frame(rng, 5, 100)
    P4, N4 = _world_arrays(rng, cloths, pos, nrm)
    enc = DeviceEncoder(device, host_buffers=2)
    enc.set_plan(FramePlan.build(cloths, pubs))
    zeros = np.zeros(len(cloths), np.uint16)
    enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), 10, 100, zeros)
    first = enc.slices()
    enc.encode(device.queue, _buffer(device, P4 * 2), _buffer(device, N4), 11, 101, zeros)
    _assert_same([bytes(v) for v in first], _reference(cloths, pos, nrm, pubs, 10, 100, zeros), pubs)
    second = enc.slices()
    enc.set_plan(FramePlan.build(cloths[:1], [Publication("other", (0,))]))  # views outlive their plan
    enc.close()
    _assert_same([bytes(v) for v in first], _reference(cloths, pos, nrm, pubs, 10, 100, zeros), pubs)
    _assert_same([bytes(v) for v in second], _reference(cloths, [p * 2 for p in pos], nrm, pubs, 11, 101, zeros), pubs)


def test_a_held_frame_is_never_reused_and_takes_flags(device, rng):
    """hold() keeps a frame's pinned memory out of the ring until released, however many frames
    follow (the service's publisher holds the frame it is putting); add_flags ORs a flag into
    the given cloths' state headers (a reset flag carried over from a dropped frame)."""
    cloths, pos, nrm, pubs = _random_frame(rng, 6, 80)
    P4, N4 = _world_arrays(rng, cloths, pos, nrm)
    enc = DeviceEncoder(device, host_buffers=2)
    enc.set_plan(FramePlan.build(cloths, pubs))
    zeros = np.zeros(len(cloths), np.uint16)
    pb, nb = _buffer(device, P4), _buffer(device, N4)
    try:
        enc.encode(device.queue, pb, nb, 10, 100, zeros)
        held = enc.hold()
        pb2 = _buffer(device, P4 * 3)
        for t in range(11, 16):  # more frames than host buffers
            enc.encode(device.queue, pb2, nb, t, t * 10, zeros)
            enc.read()
        _assert_same([bytes(v) for v in held.views], _reference(cloths, pos, nrm, pubs, 10, 100, zeros), pubs)
        bad = [int(i) for i in rng.choice(len(cloths), 2, replace=False)]
        held.add_flags(bad, P.FLAG_RESET)
        want = zeros.copy()
        want[bad] = P.FLAG_RESET
        _assert_same([bytes(v) for v in held.views], _reference(cloths, pos, nrm, pubs, 10, 100, want), pubs)
        held.set_time(2**63 + 12345)  # the server time, known after the readback
        _assert_same([bytes(v) for v in held.views], _reference(cloths, pos, nrm, pubs, 10, 2**63 + 12345, want), pubs)
        held.release()
        with pytest.raises(RuntimeError):
            held.add_flags(bad, P.FLAG_RESET)
        hosts = len(enc.hosts)
        for t in range(16, 20):  # released: back in the ring, no new buffer
            enc.encode(device.queue, pb2, nb, t, t * 10, zeros)
        assert len(enc.hosts) == hosts
    finally:
        enc.close()


def test_build_all_leaves_no_plan_to_compile(device, rng):
    """The service builds every encoder program at warm-up: any plan's is built already."""
    enc = DeviceEncoder(device)
    assert enc.build_all() >= 1
    for k, max_n in ((1, 2), (6, 80), (30, 700)):
        cloths, _, _, pubs = _random_frame(rng, k, max_n)
        plan = FramePlan.build(cloths, pubs)
        assert device.built(enc._options(enc._pick_wg(plan.max_n)), source="encode.cl")


def test_state_vectors(device):
    """tests/vectors/state.json (PROTOCOL.md's test vectors) reproduced by the device."""
    vectors = json.loads((VECTORS / "state.json").read_text())
    for v in vectors:
        pos = np.array(v["input"]["positions"], np.float32)
        nrm = v["input"]["normals"]
        enc_id = P.ENCODING_IDS[v["value"]["encoding"]]
        c = ClothEntry("c", 2, len(pos), enc_id, nrm is not None)
        P4 = np.zeros((len(pos) + 4, 4), np.float32)
        N4 = np.zeros_like(P4)
        P4[2 : 2 + len(pos), :3] = pos
        if nrm is not None:
            N4[2 : 2 + len(pos), :3] = np.array(nrm, np.float32)
        enc = DeviceEncoder(device)
        enc.set_plan(FramePlan.build([c], [Publication("k", (0,))]))
        got = _encode(
            device,
            enc,
            P4,
            N4,
            v["value"]["tick"],
            v["value"]["server_time_ns"],
            np.array([v["input"]["flags"]], np.uint16),
        )
        assert got[0] == bytes.fromhex(v["hex"]), v["name"]
        enc.close()


@pytest.mark.parametrize("soft_half", [True, False])
def test_float16_over_every_exponent(device, rng, soft_half):
    """float16 of float32 values of every exponent (subnormal halves, ties, overflow to +-inf,
    float32 subnormals, zeros of both signs) equals numpy's round-to-nearest-even: positions
    (clamped) and normals (not clamped; with the integer conversion also infinities and NaNs)."""
    exps = np.repeat(np.arange(256, dtype=np.uint32), 40)
    mant = rng.integers(0, 1 << 23, len(exps), dtype=np.uint32)
    mant[::4] &= ~np.uint32(0xFFF)  # exact ties and near-ties of the dropped bits
    mant[1::4] |= 0xFFF
    sign = rng.integers(0, 2, len(exps), dtype=np.uint32) << 31
    vals = (sign | (exps << 23) | mant).view(np.float32)
    extra = np.array(
        [
            0.0,
            -0.0,
            65504.0,
            65519.99,
            65520.0,
            -65520.0,
            2.0**-24,
            2.0**-25,
            1.5 * 2.0**-25,
            2.0**-14,
            2.0**-14 * (1 - 2.0**-11),
            1e-45,
            np.inf,
            -np.inf,
        ],
        np.float32,
    )
    vals = np.concatenate([vals, extra])
    vals = np.concatenate([vals, np.zeros((-len(vals)) % 3, np.float32)]).reshape(-1, 3)
    finite = np.isfinite(vals).all(axis=1)
    pos = np.where(np.isfinite(vals), vals, np.float32(1.0))  # positions are finite
    nrm = vals if soft_half else vals[finite]
    if not soft_half:
        pos = pos[finite]
    n = len(pos)
    c = ClothEntry("h", 0, n, P.ENC_FLOAT16, True)
    P4 = np.zeros((n, 4), np.float32)
    N4 = np.zeros((n, 4), np.float32)
    P4[:, :3], N4[:, :3] = pos, nrm
    enc = DeviceEncoder(device, soft_half=soft_half)
    enc.set_plan(FramePlan.build([c], [Publication("k", (0,))]))
    got = _encode(device, enc, P4, N4, 1, 2, np.zeros(1, np.uint16))[0]
    with np.errstate(all="ignore"):
        want = bytes(P.encode_state(1, 2, pos, nrm, "float16"))
    _assert_same([got], [want], [Publication("k", (0,))])
    enc.close()


@pytest.mark.parametrize("local_size", [None, 64])
def test_without_fp64_quant16_within_tolerance(device, rng, local_size):
    """A device without cl_khr_fp64 evaluates quant16 in float: every byte equal but quant16
    positions and snorm16 normals, which differ by at most QUANT16_FP32_TOLERANCE."""
    cloths, pos, nrm, _ = _random_frame(rng, 12, 400)
    cloths = [ClothEntry(c.cloth, c.vbase, c.n, P.ENC_QUANT16, c.normals) for c in cloths]
    pubs = [Publication(str(i), (i,)) for i in range(len(cloths))]
    P4, N4 = _world_arrays(rng, cloths, pos, nrm)
    enc = DeviceEncoder(device, fp64=False, local_size=local_size)
    enc.set_plan(FramePlan.build(cloths, pubs))
    flags = np.zeros(len(cloths), np.uint16)
    got = _encode(device, enc, P4, N4, 5, 6, flags)
    want = _reference(cloths, pos, nrm, pubs, 5, 6, flags)
    worst = 0
    for g, w, c in zip(got, want, cloths, strict=True):
        assert g[: P.STATE_HEADER_SIZE] == w[: P.STATE_HEADER_SIZE]
        qg = np.frombuffer(g, "<u2", c.n * 3, P.STATE_HEADER_SIZE).astype(np.int64)
        qw = np.frombuffer(w, "<u2", c.n * 3, P.STATE_HEADER_SIZE).astype(np.int64)
        worst = max(worst, int(np.abs(qg - qw).max()))
        if c.normals:
            at = P.STATE_HEADER_SIZE + c.n * 6
            sg = np.frombuffer(g, "<i2", c.n * 3, at).astype(np.int64)
            sw = np.frombuffer(w, "<i2", c.n * 3, at).astype(np.int64)
            worst = max(worst, int(np.abs(sg - sw).max()))
        # and what a client decodes is within one quantisation step of the float64 truth
        st = P.decode_state(g)
        lo, hi = np.array(st.bounds, np.float64)
        err = np.abs(st.positions.astype(np.float64) - pos[cloths.index(c)].astype(np.float64))
        step = (hi - lo) / P.QUANT_MAX
        assert np.all(err <= 1.5 * step + 1e-6 * max(np.abs(lo).max(), np.abs(hi).max()) + 1e-30)
    assert worst <= QUANT16_FP32_TOLERANCE
    enc.close()


def test_mixed_signed_zero_bound_may_differ_in_sign_only(device):
    """The one documented byte difference: a bound of zero on an axis holding both +0.0 and
    -0.0 carries either sign (numpy picks by evaluation order); its value is the same."""
    pos = np.array([[0.0, 1.0, 2.0], [-0.0, 3.0, 4.0], [1.0, 5.0, 6.0]], np.float32)
    c = ClothEntry("z", 0, 3, P.ENC_QUANT16)
    P4 = np.zeros((3, 4), np.float32)
    P4[:, :3] = pos
    enc = DeviceEncoder(device)
    enc.set_plan(FramePlan.build([c], [Publication("k", (0,))]))
    got = _encode(device, enc, P4, P4, 1, 2, np.zeros(1, np.uint16))[0]
    want = bytes(P.encode_state(1, 2, pos, encoding="quant16"))
    d = np.flatnonzero(np.frombuffer(got, np.uint8) != np.frombuffer(want, np.uint8))
    assert set(d.tolist()) <= {HEADER_OFFSETS["ST_MIN"] + 3}  # the sign byte of min.x, if anything
    assert P.decode_state(got).bounds == P.decode_state(want).bounds
    assert np.array_equal(P.decode_state(got).positions, P.decode_state(want).positions)
    enc.close()


def test_non_finite_cloths_show_in_their_bounds(device, rng):
    """NaN never passes silently: a cloth holding a NaN or an infinity has non-finite header
    bounds and nonfinite() names it; the other cloths are encoded exactly."""
    cloths, pos, nrm, _ = _random_frame(rng, 6, 200)
    pubs = [Publication(str(i), (i,)) for i in range(6)]
    pos[1][rng.integers(0, cloths[1].n)] = (0.0, np.nan, 0.0)
    pos[4][rng.integers(0, cloths[4].n), 2] = -np.inf
    P4, N4 = _world_arrays(rng, cloths, pos, nrm)
    enc = DeviceEncoder(device)
    enc.set_plan(FramePlan.build(cloths, pubs))
    flags = np.zeros(6, np.uint16)
    got = _encode(device, enc, P4, N4, 3, 4, flags)
    assert sorted(enc.nonfinite().tolist()) == [1, 4]
    b1 = np.frombuffer(got[1], "<f4", 6, HEADER_OFFSETS["ST_MIN"])  # bounds min xyz, max xyz
    b4 = np.frombuffer(got[4], "<f4", 6, HEADER_OFFSETS["ST_MIN"])
    assert np.isnan(b1[1]) and np.isnan(b1[4]) and b4[2] == -np.inf
    finite = [0, 2, 3, 5]
    want = _reference(cloths, pos, nrm, [pubs[i] for i in finite], 3, 4, flags)
    assert [got[i] for i in finite] == want
    enc.close()


def test_bad_plans_are_refused():
    a, b = ClothEntry("a", 0, 4), ClothEntry("b", 4, 4)
    with pytest.raises(ValueError, match="publications 0 and 1"):
        FramePlan.build([a, b], [Publication("x", (0,)), Publication("y", (0, 1), True)])
    with pytest.raises(ValueError, match="has 2 cloths"):
        FramePlan.build([a, b], [Publication("x", (0, 1))])
    with pytest.raises(ValueError, match="no cloth"):
        FramePlan.build([a], [Publication("x", (), True)])
    with pytest.raises(ValueError, match="names cloth 2"):
        FramePlan.build([a, b], [Publication("x", (2,))])
    with pytest.raises(ValueError, match="unknown encoding"):
        FramePlan.build([ClothEntry("a", 0, 4, 7)], [Publication("x", (0,))])
    with pytest.raises(ValueError, match="step"):
        FramePlan.build([ClothEntry("a", 0, 4, P.ENC_PREDICTIVE, step=1.0)], [Publication("x", (0,))])
    with pytest.raises(ValueError, match="invalid cloth id"):
        FramePlan.build([ClothEntry("bad id", 0, 4)], [Publication("x", (0,), True)])
    with pytest.raises(ValueError, match="vertex range"):
        FramePlan.build([ClothEntry("a", -1, 4)], [Publication("x", (0,))])


def test_bad_encode_calls_are_refused_and_lose_nothing(device, rng):
    cloths = [ClothEntry("a", 0, 10, P.ENC_FLOAT16, True), ClothEntry("b", 10, 5, P.ENC_QUANT16)]
    pubs = [Publication("x", (0, 1), True)]
    pos = [rng.normal(0, 1, (10, 3)).astype(np.float32), rng.normal(0, 1, (5, 3)).astype(np.float32)]
    nrm = [_random_normals(rng, 10), _random_normals(rng, 5)]
    P4, N4 = _world_arrays(rng, cloths, pos, nrm)
    enc = DeviceEncoder(device)
    with pytest.raises(RuntimeError, match="before set_plan"):
        enc.encode(device.queue, _buffer(device, P4), None, 0, 0)
    enc.set_plan(FramePlan.build(cloths, pubs))
    pb, nb = _buffer(device, P4), _buffer(device, N4)
    flags = np.zeros(2, np.uint16)
    enc.encode(device.queue, pb, nb, 1, 2, flags)
    before = [bytes(v) for v in enc.slices()]
    with pytest.raises(ValueError, match="positions buffer"):
        enc.encode(device.queue, _buffer(device, P4[:12]), nb, 3, 4)
    with pytest.raises(ValueError, match="no normals buffer"):
        enc.encode(device.queue, pb, None, 3, 4)
    with pytest.raises(ValueError, match="flags of shape"):
        enc.encode(device.queue, pb, nb, 3, 4, np.zeros(3, np.uint16))
    with pytest.raises(ValueError, match="16 bits"):
        enc.encode(device.queue, pb, nb, 3, 4, np.array([0, 70000]))
    with pytest.raises(ValueError, match="unsigned 64-bit"):
        enc.encode(device.queue, pb, nb, -1, 4)
    assert [bytes(v) for v in enc.slices()] == before  # the last good frame is still there
    _assert_same(before, _reference(cloths, pos, nrm, pubs, 1, 2, flags), pubs)
    enc.close()


def test_empty_plan(device):
    enc = DeviceEncoder(device)
    enc.set_plan(FramePlan.build([ClothEntry("a", 0, 3)], []))
    enc.encode(device.queue, _buffer(device, np.zeros((3, 4))), None, 1, 2).wait()
    assert enc.slices() == [] and len(enc.read()) == 0 and len(enc.nonfinite()) == 0
    enc.close()


def test_frame_of_a_real_world(device, rng):
    """Straight from a stepped CLWorld's float4 vertex buffers (each cloth at its vertex base):
    the same bytes as the protocol encoder on the positions and normals those buffers hold."""
    from drape.server.sim.opencl.clworld import CLWorld
    from drape.server.sim.params import ClothParams, Features

    world = CLWorld("workgroup", device=device)
    handles, normals = [], []
    for i in range(5):
        with_normals = bool(i % 2)
        handles.append(world.add(random_grid_fabric(rng), ClothParams(features=Features(normals=with_normals))))
        normals.append(with_normals)
    world.remove(handles.pop(2))  # a hole in the vertex buffers
    normals.pop(2)
    for _ in range(3):
        world.step(1 / 60)
    world.sync()
    cloths = [
        ClothEntry(f"c{j}", world.rec[h].vbase, world.cloths[h].fabric.n_vertices, ENCS[j % 3], nr)
        for j, (h, nr) in enumerate(zip(handles, normals, strict=True))
    ]
    pubs = [Publication("a", (0, 3), True), Publication("b", (1,)), Publication("c", (2,))]
    enc = DeviceEncoder(device)
    enc.set_plan(FramePlan.build(cloths, pubs))
    flags = np.array([0, P.FLAG_RESET, 0, 0], np.uint16)
    enc.encode(device.queue, world.mem.pos.buf, world.mem.nrm.buf, 77, 88, flags)
    got = [bytes(v) for v in enc.slices()]
    end = max(c.vbase + c.n for c in cloths)
    P4 = np.empty((end, 4), np.float32)
    N4 = np.empty((end, 4), np.float32)
    cl.enqueue_copy(device.queue, P4, world.mem.pos.buf)
    cl.enqueue_copy(device.queue, N4, world.mem.nrm.buf)
    pos = [P4[c.vbase : c.vbase + c.n, :3] for c in cloths]
    nrm = [N4[c.vbase : c.vbase + c.n, :3] for c in cloths]
    assert all(np.isfinite(p).all() for p in pos)
    assert all(np.isfinite(m).all() and np.abs(m).max() > 0.5 for m, c in zip(nrm, cloths, strict=True) if c.normals)
    _assert_same(got, _reference(cloths, pos, nrm, pubs, 77, 88, flags), pubs)
    enc.close()
    world.close()


def test_cloth_without_vertices(device):
    """A cloth of 0 vertices: zero bounds and no data, as the protocol encoder writes it."""
    cloths = [ClothEntry("e", 0, 0, P.ENC_QUANT16, True), ClothEntry("f", 0, 2, P.ENC_FLOAT16)]
    pubs = [Publication("b", (0, 1), True), Publication("s", (0,))]
    with pytest.raises(ValueError, match="publications 0 and 1"):
        FramePlan.build(cloths, pubs)
    pubs = [Publication("b", (1, 0), True)]
    P4 = np.array([[1, 2, 3, 0], [4, 5, 6, 0]], np.float32)
    enc = DeviceEncoder(device, local_size=64)
    enc.set_plan(FramePlan.build(cloths, pubs))
    got = _encode(device, enc, P4, P4, 9, 10, np.zeros(2, np.uint16))
    pos = [np.zeros((0, 3), np.float32), P4[:, :3]]
    _assert_same(got, _reference(cloths, pos, pos, pubs, 9, 10, np.zeros(2)), pubs)
    enc.close()


# --- 1.5 predictive states ------------------------------------------------------------------------


def _host_predictive(fe: FrameEncoder, cloths, pos, nrm, pubs, tick, time_ns, flags, watched) -> dict[int, bytes]:
    """The host path's payloads (wire.HostWire.payloads' steps) of the ``watched`` publications."""
    counts = np.array([c.n for c in cloths], np.int64)
    offsets = np.zeros(len(cloths) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    fe.begin(tick, time_ns, np.concatenate(pos), offsets)
    encs = [c.encoding for c in cloths]
    ids = [c.cloth for c in cloths]
    sel = [i for j in watched for i in pubs[j].cloths]
    fe.prepare(sel, encs)
    fe.prepare_predictive(sel, ids, encs, [c.step for c in cloths], flags.tolist())
    chosen = set(sel)
    fe.streams.forget([ids[i] for i, e in enumerate(encs) if e == P.ENC_PREDICTIVE and i not in chosen])
    out = {}
    for j in watched:
        pub = pubs[j]
        entries = [(cloths[i].cloth, i, cloths[i].encoding, bool(cloths[i].normals)) for i in pub.cloths]
        if pub.bundle:
            buf = bytearray(fe.bundle_size(entries))
            n = fe.write_bundle(
                buf,
                [(c, i, e, int(flags[i]), nrm[i] if nr else None) for c, i, e, nr in entries],
            )
            out[j] = bytes(buf[:n])
        else:
            i = pub.cloths[0]
            buf = bytearray(fe.state_size(i, cloths[i].encoding, cloths[i].normals))
            end = fe.write_state(buf, 0, i, cloths[i].encoding, int(flags[i]), nrm[i] if cloths[i].normals else None)
            out[j] = bytes(buf[:end])
    return out


def _predictive_frame(rng: np.random.Generator, k: int, max_n: int = 300):
    """A random frame (_random_frame's) whose cloths are mostly predictive, at random steps; the
    first cloth some publication carries always is (a seed never leaves the predictive streams
    unpublished)."""
    cloths, _, nrm, pubs = _random_frame(rng, k, max_n)
    first = min((i for p in pubs for i in p.cloths), default=-1)
    cloths = [
        ClothEntry(
            c.cloth,
            c.vbase,
            c.n,
            P.ENC_PREDICTIVE if rng.random() < 0.75 or i == first else c.encoding,
            c.normals,
            float(rng.choice([1e-3, 2.5e-4, 4e-3, 1e-5, 0.1])),
        )
        for i, c in enumerate(cloths)
    ]
    pos = [rng.normal(rng.normal(0, 3, 3), 0.5, (c.n, 3)).astype(np.float32) for c in cloths]
    return cloths, pos, nrm, pubs


def _move(rng: np.random.Generator, pos: list[np.ndarray], vel: list[np.ndarray]) -> None:
    """Smooth motion with now and then a jump (a reset's rest pose, a teleport)."""
    for p, v in zip(pos, vel, strict=True):
        v += rng.normal(0, 1e-3, v.shape).astype(np.float32)
        p += v
        if rng.random() < 0.03:
            p += rng.normal(0, 10.0, 3).astype(np.float32)


@pytest.mark.parametrize(
    "k, local_size, compact_wg, short, ticks",
    [(12, None, None, False, 40), (20, 64, 1, True, 25), (6, 256, 256, False, 25), (40, 1, 4, True, 12)],
)
def test_predictive_frames_equal_the_host_encoder(device, rng, k, local_size, compact_wg, short, ticks):
    """Many ticks of device-encoded predictive states (devstreams' decisions, the kernel's
    packing, the compaction on the device) byte for byte the host path's (statecodec.FrameEncoder
    and PredictiveStreams): keyframes at start and every interval, resets, keyframe requests,
    publications nobody watches, frames dropped, a step change (a new plan), bundles mixing
    encodings, normals; the compaction's work-group sizes, and (``short``) every frame's first
    copy too short for it (the rest copied once its index is read). A frame the publisher drops
    whole is learned with the next one (as the service's tick thread does, before it steps
    again): the streams go back, that frame is coded again against the last states sent and its
    states are predicted, not keyframes (counted), as the host path's, which never coded it."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, k)
    vel = [np.zeros_like(p) for p in pos]
    interval = 9
    fe = FrameEncoder(streams=PredictiveStreams(interval))
    ds = DeviceStreams(interval)
    enc = DeviceEncoder(device, local_size=local_size)
    enc.compactor = Compactor(device, local_size=compact_wg)
    if short:
        enc.compactor.guess = lambda size: 8  # type: ignore[method-assign]
    plan = FramePlan.build(cloths, pubs)
    enc.set_plan(plan)
    _dirty(device, enc, plan)
    ds.follow(plan)
    keyframes = predicted_after_drop = drops = 0
    drop_before: int | None = None  # the tick of the frame dropped last tick
    published = plan.predictive & (plan.owner >= 0)  # predictive cloths some publication carries
    try:
        for tick in range(1, ticks + 1):
            if tick == ticks // 2:  # a new step for one cloth: a new plan, the streams go on
                i = int(np.flatnonzero(plan.predictive)[0])
                cloths[i] = ClothEntry(
                    cloths[i].cloth, cloths[i].vbase, cloths[i].n, P.ENC_PREDICTIVE, cloths[i].normals, 5e-4
                )
                plan = FramePlan.build(cloths, pubs)
                _dirty(device, enc, plan)  # the kept buffer as the last plan left it, and garbage
                ds.follow(plan)
            _move(rng, pos, vel)
            time_ns = int(rng.integers(0, 2**63))
            flags = np.where(rng.random(k) < 0.05, P.FLAG_RESET, 0).astype(np.uint16)
            watched = sorted(rng.permutation(len(pubs))[: len(pubs) - int(rng.integers(0, 2))].tolist())
            dropped = tick in (4, 7, 10) or rng.random() < 0.15
            if tick == 3:  # one reset seen on every key, whatever the seed: a keyframe past the start's
                flags[int(np.flatnonzero(published)[0])] = P.FLAG_RESET
                watched, dropped = list(range(len(pubs))), False
            ask = [c.cloth for c in cloths if rng.random() < 0.05]
            if tick == 5:  # after tick 4's dropped frame, whatever the seed: states predicted if they can be
                watched, dropped, ask = list(range(len(pubs))), False, []
                flags[:] = 0
            ds.request(ask)  # in the service the device learns of them a frame later: here both at once
            fe.streams.request(ask)  # a dropped frame's requests: kept for the next state on both paths
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pred, kf = ds.decide(tick, flags)
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, time_ns, flags, predictive=pred)
            after_drop = drop_before is not None
            if drop_before is not None:  # the frame before was dropped: its streams taken back
                drops += 1
                if ds.dropped(drop_before):
                    enc.forget(drop_before)
                pred, kf = ds.redo(tick, flags)
                enc.encode(
                    device.queue, _buffer(device, P4), _buffer(device, N4), tick, time_ns, flags, predictive=pred
                )
                drop_before = None
            frame = enc.hold()
            # the frame read back is the wire bytes, back to back (each padded to 8 bytes)
            assert len(enc.read()) == sum(P.align8(len(v)) for v in frame.views)
            if dropped:  # the publisher dropped it: the host path never coded it
                frame.release()
                drop_before = tick
                continue
            want = _host_predictive(fe, cloths, pos, nrm, pubs, tick, time_ns, flags, watched)
            got = dict(frame.payloads(watched))
            seen = np.zeros(len(pubs) + 1, bool)
            seen[watched] = True
            ds.lost(plan, np.flatnonzero(plan.predictive & ~seen[plan.owner]))
            ds.put(plan, np.flatnonzero(plan.predictive & seen[plan.owner]), tick)
            keyframes += int((kf & seen[plan.owner]).sum())
            if after_drop:
                predicted_after_drop += int((plan.predictive & ~kf & seen[plan.owner]).sum())
            frame.release()
            assert sorted(got) == sorted(want)
            for j in watched:
                _assert_same([got[j]], [want[j]], [pubs[j]])
        assert keyframes == fe.streams.keyframes
        # keyframes came at start (one a published predictive cloth), on resets (one at tick 3 at
        # least), requests, intervals
        assert keyframes > int((plan.predictive & (plan.owner >= 0)).sum())
        assert drops > 0 and predicted_after_drop > 0  # the states after a dropped frame: predicted
        encodes = ticks + drops  # a frame after a dropped one: coded twice
        assert enc.compactor.frames == encodes  # every frame compacted on the device (counted, not timed)
        assert enc.compactor.short == (encodes if short else enc.compactor.short)
    finally:
        enc.close()


def test_a_first_subscriber_never_gets_a_state_predicted_from_one_nobody_got(device, rng):
    """The publisher's news come late (the service decides tick T + 1 before the publisher has
    put T): a stream nobody watches at first, whose subscriber comes while its states go on,
    sends keyframes until one of them is known to have gone out, then predicted states; the
    subscriber decodes every state it gets (the flaky device-predictive test of
    tests/service/test_published_bytes.py: one undecodable first state, then a keyframe)."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, 4, max_n=60)
    cloths = [ClothEntry(c.cloth, c.vbase, c.n, P.ENC_PREDICTIVE, c.normals, 1e-3) for c in cloths]
    plan = FramePlan.build(cloths, pubs)
    vel = [np.zeros_like(p) for p in pos]
    ds = DeviceStreams(keyframe_interval=1000)
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    ds.follow(plan)
    streams = {c.cloth: P.StateStream(c.cloth) for c in cloths}
    news: tuple[int, np.ndarray] | None = None  # the last frame's (tick, put mask), told a tick late
    every = list(range(len(pubs)))
    try:
        for tick in range(1, 13):
            _move(rng, pos, vel)
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pred, _ = ds.decide(tick, None)
            if news is not None:  # the frame before's, only now (after this tick was decided)
                ds.lost(plan, np.flatnonzero(~news[1]))
                ds.put(plan, np.flatnonzero(news[1]), news[0])
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, tick, None, predictive=pred)
            frame = enc.hold()
            watched = [] if tick == 1 else every  # the subscriber comes with the second state
            got = dict(frame.payloads(watched))
            frame.release()
            shown = np.zeros(len(pubs) + 1, bool)
            shown[watched] = True
            news = (tick, shown[plan.owner])
            for j, payload in got.items():
                pub = pubs[j]
                if pub.bundle:
                    b = P.parse_bundle(payload)
                    states = [(e.cloth, b.payload(i)) for i, e in enumerate(b.entries)]
                else:
                    states = [(cloths[pub.cloths[0]].cloth, payload)]
                for cid, data in states:
                    assert streams[cid].decode(data) is not None, (tick, cid)
        published = [streams[cloths[i].cloth] for p in pubs for i in p.cloths]
        assert published and all(s.undecodable == 0 and s.decoded == 11 for s in published)
        assert all(1 < s.keyframes < 11 for s in published), [s.keyframes for s in published]  # then predicted
    finally:
        enc.close()


def test_rows_refer_to_history_ticks_of_their_own(device, rng):
    """One launch, streams whose references differ per row (the groundwork of decimated streams,
    docs/rates.md): half the cloths take every tick's state (references T - 1, T - 2), the
    other half every second tick's (T - 2, T - 4), their decoders getting only those; every
    state decodes within half a step (each row read its own history slots)."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, 6, max_n=80)
    cloths = [ClothEntry(c.cloth, c.vbase, c.n, P.ENC_PREDICTIVE, c.normals, 1e-3) for c in cloths]
    plan = FramePlan.build(cloths, [Publication(f"k/{i}", (i,)) for i in range(len(cloths))])
    every = [1 + i % 2 for i in range(len(cloths))]
    streams = [P.StateStream(c.cloth) for c in cloths]
    vel = [np.zeros_like(p) for p in pos]
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    try:
        for tick in range(1, 14):
            _move(rng, pos, vel)
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pred = np.zeros((len(cloths), 3), np.uint64)
            for i, k in enumerate(every):
                sent = (tick - 1) // k  # this stream's states before this tick's (ticks 1, 1 + k, ...)
                if (tick - 1) % k == 0:
                    pred[i] = (min(sent, 2), tick - k if sent >= 1 else 0, tick - 2 * k if sent >= 2 else 0)
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, tick, None, predictive=pred)
            views = enc.slices()
            for i, k in enumerate(every):
                if (tick - 1) % k:
                    continue
                st = streams[i].decode(bytes(views[i]))
                assert st is not None, (tick, i)
                assert np.abs(st.positions - pos[i]).max() <= 5e-4 * (1 + 1e-5) + 1e-6 * np.abs(pos[i]).max()
        assert [s.decoded for s in streams] == [13 if k == 1 else 7 for k in every]
        assert all(s.keyframes == 1 for s in streams)
    finally:
        enc.close()


def test_predictive_plan_with_nothing_published(device):
    """Predictive cloths in no publication (nobody subscribes yet): an empty frame, no launch of
    the compaction, no copy, nothing to publish."""
    cloths = [ClothEntry("a", 0, 5, P.ENC_PREDICTIVE), ClothEntry("b", 5, 3, P.ENC_QUANT16)]
    enc = DeviceEncoder(device)
    plan = FramePlan.build(cloths, [])
    enc.set_plan(plan)
    ds = DeviceStreams()
    ds.follow(plan)
    P4 = np.ones((8, 4), np.float32)
    try:
        for tick in (1, 2):
            enc.encode(device.queue, _buffer(device, P4), None, tick, 5, None, predictive=ds.decide(tick, None)[0])
            frame = enc.hold()
            assert frame.sizes() == [] and list(frame.payloads([])) == [] and len(enc.read()) == 0
            assert len(enc.nonfinite()) == 0
            frame.release()
    finally:
        enc.close()


def test_compacted_frame_headers(device, rng):
    """A compacted frame's headers as the service edits them after the encode: its bounds show a
    non-finite predictive cloth (nonfinite), and the server time and flags written on the host
    (set_time, add_flags) land in the right states and bundles: the bytes of the frame encoded
    with that time and those flags from the start (keyframes alike, the same streams' decision)."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, 16)
    plan = FramePlan.build(cloths, pubs)
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    ds = DeviceStreams(5)
    ds.follow(plan)
    try:
        for tick in (1, 2, 3):
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            bad = int(rng.choice(np.flatnonzero(plan.predictive & (plan.state_offset >= 0))))
            c = cloths[bad]
            P4[c.vbase + c.n // 2, 1] = np.nan
            pred, _ = ds.decide(tick, None)
            flags = np.zeros(len(cloths), np.uint16)
            flags[rng.permutation(len(cloths))[:3]] = P.FLAG_RESET
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, 123, flags, predictive=pred)
            want = [bytes(v) for v in enc.slices()]
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, 0, None, predictive=pred)
            assert bad in enc.nonfinite().tolist()
            frame = enc.hold()
            frame.set_time(123)
            frame.add_flags(np.flatnonzero(flags).tolist(), P.FLAG_RESET)
            assert [bytes(v) for v in frame.views] == want
            assert dict(frame.payloads(range(len(pubs)))) == dict(enumerate(want))
            frame.release()
            pos = [p + rng.normal(0, 1e-3, p.shape).astype(np.float32) for p in pos]
    finally:
        enc.close()


def test_predictive_closed_loop_with_lost_states_and_keyframe_requests(device, rng):
    """10,000 ticks of device-coded states decoded by the SDK's StateStream while the transport
    loses 3 % of the payloads (the server never knows): every state decoded is within half a
    step of the simulated positions (no drift), a decoder that lost one asks for a keyframe and
    decodes again within a few ticks, and it never shows a state it cannot decode."""
    k, ticks = 5, 10000
    cloths, pos, nrm, pubs = _predictive_frame(rng, k, max_n=80)
    cloths = [ClothEntry(c.cloth, c.vbase, c.n, P.ENC_PREDICTIVE, c.normals, c.step) for c in cloths]
    plan = FramePlan.build(cloths, pubs)
    vel = [np.zeros_like(p) for p in pos]
    ds = DeviceStreams(keyframe_interval=600)
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    ds.follow(plan)
    streams = {c.cloth: P.StateStream(c.cloth) for c in cloths}
    every = list(range(len(pubs)))
    waiting: dict[str, int] = {}  # cloth -> the tick its decoder first asked for a keyframe
    last_ask: dict[str, int] = {}
    decoded = worst_wait = 0
    try:
        for tick in range(1, ticks + 1):
            _move(rng, pos, vel)
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pred, _ = ds.decide(tick, None)
            enc.encode(device.queue, _buffer(device, P4), _buffer(device, N4), tick, tick, None, predictive=pred)
            frame = enc.hold()
            got = dict(frame.payloads(every))
            frame.release()
            ds.put(plan, np.flatnonzero(plan.predictive), tick)
            asked = []
            for j, pub in enumerate(pubs):
                if rng.random() < 0.03:
                    continue  # lost on the way
                if pub.bundle:
                    b = P.parse_bundle(got[j])
                    states = [(e.cloth, b.payload(i)) for i, e in enumerate(b.entries)]
                else:
                    states = [(cloths[pub.cloths[0]].cloth, got[j])]
                for cid, payload in states:
                    i = next(n for n, c in enumerate(cloths) if c.cloth == cid)
                    st = streams[cid].decode(payload)
                    if st is None:  # asks (again, if its keyframe was lost too)
                        waiting.setdefault(cid, tick)
                        if tick - last_ask.get(cid, -100) >= 8:
                            last_ask[cid] = tick
                            asked.append(cid)
                        continue
                    if cid in waiting:
                        worst_wait = max(worst_wait, tick - waiting.pop(cid))
                    # the grid holds +-Q_LIMIT steps (1.3 km at the smallest step): the random walk
                    # may leave it, and the protocol then clamps (PROTOCOL.md 9.2)
                    lim = Q_LIMIT * cloths[i].step
                    want = np.clip(pos[i], -lim, lim)
                    err = np.abs(st.positions - want).max()
                    assert err <= cloths[i].step / 2 * (1 + 1e-5) + 1e-6 * np.abs(want).max(), (tick, cid, err)
                    decoded += 1
            ds.request(asked)
        published = sum(len(p.cloths) for p in pubs)
        assert decoded > 0.8 * published * ticks
        assert worst_wait <= 60
        assert sum(s.undecodable for s in streams.values()) > 0  # losses were noticed and recovered from
    finally:
        enc.close()


# --- 1.8 decimated predictive streams -------------------------------------------------------------


def _roster(cloths: list[ClothEntry], pubs: list[Publication]) -> tuple[Roster, list[Publication]]:
    """The service's Roster of these publications, and the publications in its order."""
    singles = [p.cloths[0] for p in pubs if not p.bundle]
    bundles = [(p.key, np.array(p.cloths, np.int64)) for p in pubs if p.bundle]
    roster = Roster(
        (1, 0),
        [c.cloth for c in cloths],
        [f"state/{c.cloth}" for c in cloths],
        [c.encoding for c in cloths],
        np.array([c.normals for c in cloths], bool),
        np.array(singles, np.int64),
        bundles,
        [c.step for c in cloths],
    )
    ordered = [Publication(key, tuple(idx), bundle) for _, key, idx, bundle in roster.publications()]
    return roster, ordered


def test_a_decimated_key_watched_again_between_its_ticks_restarts_on_a_keyframe(device, rng):
    """A decimated key whose subscriber leaves and a new one comes between two of its rate's
    ticks (the watched set the same on both, only its count of losses up by one): its next state
    is a keyframe, as the host path's (which forgets the key's streams), not one predicted from
    states the new subscriber never had; then predicted again. Every 2nd state, ticks 1-8, the
    loss at tick 5."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, 1, max_n=40)  # one predictive cloth, single or bundled
    roster, pubs = _roster(cloths, pubs)
    ident = roster.publications()[0][0]
    plan = FramePlan.build(cloths, pubs)
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    ds = DeviceStreams(1000)
    ds.follow(plan)
    rates = DeviceRates(device, enc)
    watching = {2: {ident: 0}}
    rates.watch(lambda: watching)
    told = PredictiveStreams(2000)
    vel = [np.zeros_like(p) for p in pos]
    orders = []
    try:
        for tick in range(1, 9):
            if tick == 5:  # the key's last subscriber went and a new one came (the listener's count)
                watching = {2: {ident: 1}}
            _move(rng, pos, vel)
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pb, nb = _buffer(device, P4), _buffer(device, N4)
            rates.follow(roster, plan, 1000, tick)
            pred, _ = ds.decide(tick, None)
            enc.encode(device.queue, pb, nb, tick, tick, None, predictive=pred)
            frames = DeviceRates.hold(rates.encode(device.queue, pb, nb, tick, tick, None))
            main = enc.hold()
            ds.put(plan, np.flatnonzero(plan.predictive), tick)
            main.release()
            for rf in frames.values():
                for _, payload in rates.payloads(rf, [0], told, tick):
                    b = P.parse_bundle(payload) if pubs[0].bundle else None
                    orders.append(P.read_predictive_header(b.payload(0) if b is not None else payload).order)
                rates.release(rf)
        assert orders == [0, 1, 0, 1]  # ticks 2, 4, 6 (restarted), 8
    finally:
        rates.close()
        enc.close()


@pytest.mark.parametrize("seed_ticks", [40, 61])
def test_decimated_streams_equal_the_host_encoder(device, rng, seed_ticks):
    """Decimated predictive streams (1.8: every 2nd and every 3rd state on keys of their own)
    coded on the device (devrates.DeviceRates: a plan per watched rate, encoded behind the
    full-rate frame on its ticks against the full-rate history) byte for byte the host path's
    (statecodec.FrameEncoder with a PredictiveStreams of k x the keyframe interval, given the
    states of the ticks T mod k = 0 only), tick after tick: resets, keyframe requests on the
    decimated streams, subscribers coming and going (seen on the rate's ticks, as the host path
    sees them), a key whose subscriber left and another came between two of its rate's ticks
    (the watched set the same on both: the host path forgets its streams, the device restarts
    them from the count of losses the watched set carries), frames dropped whole on decimated
    ticks (the streams taken back, the next state predicted from the last two sent, as the host
    path, which never coded it), bundles mixing encodings. No decimated work on the other ticks."""
    cloths, pos, nrm, pubs = _predictive_frame(rng, 10, max_n=120)
    roster, pubs = _roster(cloths, pubs)
    vel = [np.zeros_like(p) for p in pos]
    interval = 5
    idents = [p[0] for p in roster.publications()]
    plan = FramePlan.build(cloths, pubs)
    enc = DeviceEncoder(device)
    enc.set_plan(plan)
    ds = DeviceStreams(interval)
    ds.follow(plan)
    rates = DeviceRates(device, enc)
    watching: dict[int, dict[str, int]] = {}  # RatePublishers.watching's: rate -> ident -> keys' losses
    rates.watch(lambda: watching)
    left: dict[int, dict[str, int]] = {2: {}, 3: {}}  # times each key lost its last subscriber
    sets: dict[int, frozenset[str]] = {}
    host = {k: FrameEncoder(streams=PredictiveStreams(k * interval)) for k in (2, 3)}
    told = {k: PredictiveStreams(k * interval) for k in (2, 3)}  # the publisher's (requests, counts)
    compared = {2: 0, 3: 0}
    predicted = {2: 0, 3: 0}
    older: tuple[int, dict[int, RateFrame]] | None = None  # the frame dropped last tick
    unwatched: dict[int, set[str]] = {2: set(), 3: set()}  # keys left unwatched since the last frame put
    drops = 0
    try:
        for tick in range(1, seed_ticks + 1):
            # subscribers: every 2nd state of every publication but one that goes and comes back;
            # every 3rd of half of them from tick 4 on, all of them from tick 20
            gone = {idents[0]} if 9 <= tick < 17 else set()
            before, sets = sets, {2: frozenset(idents) - gone}
            if tick >= 4 and not 24 <= tick < 31:  # nobody for a while: then on keyframes
                sets[3] = frozenset(idents if tick >= 20 else idents[::2])
            # the listeners: keys that lost their last subscriber since the last tick; at tick 33
            # another's subscriber leaves and a new one comes before the rate's next tick
            blip = {2: {idents[1]} if tick == 33 else set(), 3: set()}
            for k in (2, 3):
                for i in (before.get(k, frozenset()) - sets.get(k, frozenset())) | blip[k]:
                    left[k][i] = left[k].get(i, 0) + 1
                unwatched[k] |= (set(idents) - sets.get(k, frozenset())) | blip[k]
            watching = {k: {i: left[k].get(i, 0) for i in s} for k, s in sets.items()}
            _move(rng, pos, vel)
            time_ns = int(rng.integers(0, 2**63))
            flags = np.where(rng.random(len(cloths)) < 0.04, P.FLAG_RESET, 0).astype(np.uint16)
            dropped = tick in (6, 9, 14, 27) or (tick % 2 == 0 and rng.random() < 0.1)
            for k in (2, 3):
                if tick % k == 0 and rng.random() < 0.3:
                    ask = [c.cloth for c in cloths if rng.random() < 0.2]
                    told[k].request(ask)  # a keyframe query on the decimated key
                    host[k].streams.request(ask)
            P4, N4 = _world_arrays(rng, cloths, pos, nrm)
            pb, nb = _buffer(device, P4), _buffer(device, N4)
            rates.follow(roster, plan, interval, tick)
            for k, r in rates.rates.items():  # in the service the device learns them with the payloads
                r.streams.request(told[k].take_requests() if tick % k == 0 else [])
            pred, _ = ds.decide(tick, flags)
            enc.encode(device.queue, pb, nb, tick, time_ns, flags, predictive=pred)
            due = rates.encode(device.queue, pb, nb, tick, time_ns, flags)
            assert sorted(r.every for r, _ in due) == [k for k in (2, 3) if tick % k == 0 and k in watching]
            frames = DeviceRates.hold(due)
            if older is not None:  # the frame before was dropped whole (DeviceWire.after_dropped)
                for rf in older[1].values():
                    rates.dropped(rf, older[0])
                    rates.release(rf)
                if ds.dropped(older[0]):
                    enc.forget(older[0])
                pred, _ = ds.redo(tick, flags)
                enc.encode(device.queue, pb, nb, tick, time_ns, flags, predictive=pred).wait()
                rates.reencode(frames, pb, nb, tick, time_ns, flags)
                older = None
            main = enc.hold()
            ds.put(plan, np.flatnonzero(plan.predictive), tick)
            main.release()
            if dropped:
                older = (tick, frames)
                drops += bool(frames)
                continue
            for k in (2, 3):  # the publisher, at the next frame it puts: their streams forgotten
                host[k].streams.forget(
                    [cloths[i].cloth for j in range(len(pubs)) if idents[j] in unwatched[k] for i in pubs[j].cloths]
                )
                unwatched[k] = set()
            for k, rf in frames.items():
                watched = [j for j, i in enumerate(idents) if i in watching[k]]
                want = _host_predictive(host[k], cloths, pos, nrm, pubs, tick, time_ns, flags, watched)
                kf = int(told[k].keyframes)
                got = dict(rates.payloads(rf, watched, told[k], tick))
                plain = [j for j in watched if not plan.predictive[list(pubs[j].cloths)].any()]
                assert sorted(got) == sorted(set(watched) - set(plain))
                for j in got:
                    _assert_same([got[j]], [want[j]], [pubs[j]])
                compared[k] += len(got)
                predicted[k] += int((rf.frame.plan.predictive & ~rf.keyframes).sum())
                assert told[k].keyframes - kf == int((rf.keyframes & rf.frame.plan.predictive).sum())
                rates.release(rf)
        assert all(told[k].keyframes == host[k].streams.keyframes for k in (2, 3))
        # each rate compared states and some of them predicted (not keyframes only), whatever the seed
        assert compared[2] > 10 and compared[3] > 5 and predicted[2] > 0 and predicted[3] > 0
        assert drops >= 3 and rates.plans >= 4
        # each rate's history: its watched cloths' vertices only (none of the full rate's)
        for r in rates.rates.values():
            assert r.encoder.plan is not None
            assert history_end(r.encoder.plan) <= 2 * sum(c.n for c in r.encoder.plan.cloths) + 4096
    finally:
        rates.close()
        enc.close()
