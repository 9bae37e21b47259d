"""The bytes a server puts on Zenoh are drape.client.protocol's encoding of the cloth's positions,
byte for byte, on both publication paths: states encoded on the OpenCL device (one packed frame
per tick, ``device_encode = true``) and by the host's FrameEncoder (``device_encode = false``).

The cloths are random triangle meshes with every vertex pinned, so their positions stay exactly
the submitted float32 vertices at every tick: the expected payload of any tick is
``encode_state(tick, time, vertices, encoding, flags)`` (and ``encode_bundle`` of those for a
client's bundle), with the tick, time and flags read from the received header.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest
from conftest import WAIT, connect, make_config, wait_until

from drape.client import protocol as P
from drape.server.service import Server

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

ENCODINGS = ("float32", "float16", "quant16")


class Raw:
    """A raw subscriber: every payload received on a key, as bytes."""

    def __init__(self, session, key: str) -> None:
        self.got: list[bytes] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        with self._lock:
            self.got.append(sample.payload.to_bytes())

    def payloads(self) -> list[bytes]:
        with self._lock:
            return list(self.got)


def random_mesh(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    cols, rows = int(rng.integers(3, 12)), int(rng.integers(3, 12))
    x, y = np.meshgrid(np.arange(cols), np.arange(rows))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1) * rng.uniform(0.05, 0.3)
    v = (v + rng.normal(0, 0.01, v.shape) + rng.uniform(-5, 5, 3)).astype(np.float32)
    t = []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a = r * cols + c
            t += [(a, a + 1, a + cols), (a + 1, a + cols + 1, a + cols)]
    return v, np.array(t, np.int64)


def expected_state(payload: bytes | memoryview, vertices: np.ndarray, encoding: str) -> bytes:
    st = P.decode_state(payload)
    return bytes(P.encode_state(st.tick, st.server_time_ns, vertices, encoding=encoding, flags=st.flags))


@pytest.mark.parametrize("device_encode", [True, False], ids=["device", "host"])
def test_published_bytes_equal_the_protocol_encoding(device_encode, rng):
    server = Server(make_config(device_encode=device_encode, max_cloths_per_client=12)).start()
    try:
        client = connect(server)
        try:
            cloths = []  # (handle, vertices, encoding, bundled)
            for bundled in (False, True):
                for enc in ENCODINGS + tuple(rng.choice(ENCODINGS, 2)):
                    v, t = random_mesh(rng)
                    h = client.submit_mesh(v, t, pinned=list(range(len(v))), encoding=str(enc), bundle=bundled)
                    cloths.append((h, v, str(enc), bundled))
            raws = {h.id: Raw(client.session, h.key) for h, _, _, b in cloths if not b}
            bundle_raw = Raw(client.session, client.bundle_key)
            assert wait_until(
                lambda: all(len(r.payloads()) >= 5 for r in raws.values()) and len(bundle_raw.payloads()) >= 5, WAIT
            )
            frames = getattr(server.ticker.world, "device_frames", None)
            if device_encode:
                assert frames is not None and frames.plans >= 1
            else:
                assert frames is None
            checked = 0
            for h, v, enc, bundled in cloths:
                if bundled:
                    continue
                for payload in raws[h.id].payloads()[-5:]:
                    assert payload == expected_state(payload, v, enc), f"{enc} single {h.id}"
                    checked += 1
            by_id = {h.id: (v, enc) for h, v, enc, b in cloths if b}
            for payload in bundle_raw.payloads()[-5:]:
                b = P.parse_bundle(payload)
                if {e.cloth for e in b.entries} != set(by_id):
                    continue  # a bundle from before every cloth was added
                states = []
                for i, e in enumerate(b.entries):
                    v, enc = by_id[e.cloth]
                    states.append((e.cloth, expected_state(b.payload(i), v, enc)))
                assert payload == bytes(P.encode_bundle(b.tick, b.server_time_ns, states, b.flags))
                checked += 1
            assert checked >= 5 * 5 + 1  # every single state, and bundles
        finally:
            client.close()
    finally:
        server.stop()
    assert server.failure is None


@pytest.mark.parametrize("encoding", ["float32", "predictive"])
@pytest.mark.parametrize("device_encode", [True, False], ids=["device", "host"])
def test_non_finite_cloth_with_normals_is_published_at_rest_with_rest_normals(device_encode, encoding):
    """A cloth gone non-finite is reset: its next state is its rest pose with the rest pose's
    normals and the reset flag, on both paths (the device path writes the rest normals and
    encodes the frame again; a predictive one's stream goes on, every state decoded)."""
    from drape.server.sim.shared import vertex_normals

    server = Server(make_config(device_encode=device_encode)).start()
    try:
        client = connect(server)
        try:
            kw = {"encoding": "predictive", "step": 1e-3} if encoding == "predictive" else {}
            with client.submit_grid(6, 5, pinned=[0], normals=True, **kw) as h:
                h.next_state(WAIT)
                handle = server.world_handle(h.id)
                fabric = server.call(lambda w: w.cloths[handle].fabric)
                server.call(lambda w: w.reset(handle, np.full((30, 3), np.nan)))
                for _ in range(20):
                    s = h.next_state(WAIT)
                    assert np.isfinite(s.positions).all() and np.isfinite(s.normals).all()
                    if s.reset:
                        break
                assert s.reset, "the reset state is flagged"
                pred = encoding == "predictive"
                np.testing.assert_allclose(s.positions, h.rest_positions, atol=5e-4 + 1e-6 if pred else 1e-6)
                want = vertex_normals(fabric.rest_positions, fabric)[0]
                np.testing.assert_allclose(s.normals, want, atol=1 / 32767 if pred else 1e-6)
                if pred:
                    for _ in range(5):
                        assert not h.next_state(WAIT).extrapolated
                    assert h.stream.undecodable == 0
                assert (getattr(server.ticker.world, "device_frames", None) is not None) == device_encode
        finally:
            client.close()
    finally:
        server.stop()
    assert server.failure is None


@pytest.mark.parametrize("device_encode", [True, False], ids=["device", "host"])
def test_predictive_states_decode_within_half_a_step(device_encode, rng):
    """1.5 on both paths (issue 21: the device path codes them, no host fallback): pinned random
    meshes, single and bundled, at random steps; a raw subscriber's every state after its first
    keyframe decodes (the stream's references held) within half a step of the vertices."""
    server = Server(make_config(device_encode=device_encode, max_cloths_per_client=8, keyframe_interval=4)).start()
    try:
        client = connect(server)
        try:
            cloths = []  # (handle, vertices, step, bundled)
            for bundled in (False, True):
                for _ in range(3):
                    v, t = random_mesh(rng)
                    step = float(rng.choice([2.5e-4, 1e-3, 4e-3]))
                    h = client.submit_mesh(
                        v, t, pinned=list(range(len(v))), encoding="predictive", step=step, bundle=bundled
                    )
                    cloths.append((h, v, step, bundled))
            raws = {h.id: Raw(client.session, h.key) for h, _, _, b in cloths if not b}
            bundle_raw = Raw(client.session, client.bundle_key)
            assert wait_until(
                lambda: all(len(r.payloads()) >= 16 for r in raws.values()) and len(bundle_raw.payloads()) >= 16,
                WAIT,
            )
            frames = getattr(server.ticker.world, "device_frames", None)
            if device_encode:  # a counted event, not a timing: frames with predictive states coded on the device
                assert frames is not None and frames.predictive_frames >= 16
                assert frames.encoder.compactor.frames >= 16  # and compacted there
            else:
                assert frames is None
            streams = {h.id: P.StateStream(h.id) for h, _, _, _ in cloths}
            shown: dict[str, int] = dict.fromkeys(streams, 0)
            by_id = {h.id: (v, step) for h, v, step, _ in cloths}

            def check(cid: str, payload: bytes | memoryview) -> None:
                s = streams[cid]
                st = s.decode(payload)
                if st is None:
                    assert s.keyframes == 0, f"{cid}: undecodable after a keyframe"
                    return
                v, step = by_id[cid]
                assert np.abs(st.positions - v).max() <= step / 2 + 1e-5
                shown[cid] += 1

            for cid, r in raws.items():
                for payload in r.payloads():
                    check(cid, payload)
            for payload in bundle_raw.payloads():
                b = P.parse_bundle(payload)
                for i, e in enumerate(b.entries):
                    check(e.cloth, b.payload(i))
            assert all(n >= 8 for n in shown.values()), shown
            assert all(s.undecodable == 0 or s.keyframes > 0 for s in streams.values())
        finally:
            client.close()
    finally:
        server.stop()
    assert server.failure is None


@pytest.mark.parametrize("device_encode", [True, False], ids=["device", "host"])
def test_published_bytes_count_what_was_put(device_encode, rng):
    """The stats' published_bytes is the bytes the publisher put (what loadtest's MB/s reads):
    a quant16 cloth's states at their fixed size, a predictive cloth's at their real size (far
    under the largest), counted against the payloads a raw subscriber received."""
    server = Server(make_config(device_encode=device_encode, keyframe_interval=30)).start()
    try:
        client = connect(server)
        try:
            v, t = random_mesh(rng)
            fixed = client.submit_mesh(v, t, pinned=list(range(len(v))), encoding="quant16")
            pred = client.submit_mesh(v, t, pinned=list(range(len(v))), encoding="predictive", step=1e-3)
            raws = [Raw(client.session, h.key) for h in (fixed, pred)]
            assert wait_until(lambda: all(len(r.payloads()) >= 40 for r in raws), WAIT)
            s0 = server.stats()
            assert wait_until(lambda: server.stats()["published"] >= s0["published"] + 40, WAIT)
            s1 = server.stats()
            states, put = s1["published"] - s0["published"], s1["published_bytes"] - s0["published_bytes"]
            q16, largest = P.state_size(len(v), "quant16"), P.state_size(len(v), "predictive")
            got = raws[1].payloads()
            assert max(len(p) for p in got) < largest  # pinned: predicted exactly, all but keyframes tiny
            # both cloths' states are put every tick: half of them quant16, half predictive
            assert states // 2 * q16 < put < states // 2 * (q16 + largest)
            assert put < states // 2 * q16 + states * largest // 4  # the predictive states' real size counted
        finally:
            client.close()
    finally:
        server.stop()
    assert server.failure is None
