"""Protocol 1.1 end to end: state bundles and batch control over real Zenoh on loopback (own
ports, no scouting), one module-scoped server; and the publisher's vectorised encoder against
the reference encoders of drape.client.protocol, byte for byte."""

from __future__ import annotations

import dataclasses
import struct
import threading
import time

import msgpack
import numpy as np
import pytest
from conftest import WAIT, connect, make_config, wait_until

from drape.client import BatchError, Forbidden
from drape.client import protocol as P
from drape.server.service import Server
from drape.server.sim.statecodec import FrameEncoder

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

MAX_ITEMS = 8


@pytest.fixture(scope="module", params=[True, False], ids=["device-encode", "host-encode"])
def server(request):
    """One server per publication path: states encoded on the OpenCL device, or by the host."""
    s = Server(make_config(max_cloths_per_client=12, max_batch_items=MAX_ITEMS, device_encode=request.param)).start()
    yield s
    s.stop()
    assert s.failure is None


def drain(handle, until_tick: int, timeout: float = WAIT) -> list[P.ClothState]:
    """The handle's states up to tick `until_tick` (a deadline for states that must come, never a rate)."""
    out: list[P.ClothState] = []
    deadline = time.monotonic() + timeout
    while not out or out[-1].tick < until_tick:
        out.append(handle.next_state(max(0.0, deadline - time.monotonic())))
    return out


def gaps(ticks: list[int]) -> int:
    """Ticks missing between the first and the last of an increasing sequence."""
    assert ticks == sorted(set(ticks)), f"ticks out of order or repeated: {ticks}"
    return ticks[-1] - ticks[0] + 1 - len(ticks) if ticks else 0


class Recorder:
    """A raw subscriber to a bundle key: (tick, [cloth ids], bundle) of every publication."""

    def __init__(self, session, key: str) -> None:
        self.got: list[tuple[int, list[str], P.Bundle]] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        b = P.parse_bundle(sample.payload.to_bytes())
        with self._lock:
            self.got.append((b.tick, [e.cloth for e in b.entries], b))

    def snapshot(self) -> list[tuple[int, list[str], P.Bundle]]:
        with self._lock:
            return list(self.got)

    def close(self) -> None:
        self.sub.undeclare()


# ---------------------------------------------------------------------------------------------
# The vectorised encoder writes exactly what the reference encoders write


def test_frame_encoder_matches_the_reference_encoders(rng):
    sizes = [int(n) for n in rng.integers(1, 300, 9)] + [1]
    pos = (rng.normal(size=(sum(sizes), 3)) * rng.uniform(0.1, 50)).astype(np.float32)
    pos[: sizes[0], 1] = 0.5  # a flat axis: quant16's degenerate case
    pos[5, 0] = 70000.0  # beyond float16's range: clamped
    off = np.zeros(len(sizes) + 1, np.int64)
    np.cumsum(sizes, out=off[1:])
    encs = [int(e) for e in rng.integers(0, 3, len(sizes))]
    normals = [rng.normal(size=(n, 3)).astype(np.float32) if rng.random() < 0.4 else None for n in sizes]
    flags = [int(f) for f in rng.integers(0, 4, len(sizes))]
    ids = [f"{i:016x}" if i % 2 else f"c{i}" for i in range(len(sizes))]

    def ref(i: int) -> bytes:
        return bytes(
            P.encode_state(99, 1234, pos[off[i] : off[i + 1]], normals[i], P.ENCODING_NAMES[encs[i]], flags[i])
        )

    enc = FrameEncoder()
    for subset in (list(range(len(sizes))), [1, 3, 4], [len(sizes) - 1]):
        enc.begin(99, 1234, pos, off)
        enc.prepare(subset, encs)
        for i in subset:
            buf = bytearray(b"\xff" * (enc.state_size(i, encs[i], normals[i] is not None) + 5))
            end = enc.write_state(buf, 5, i, encs[i], flags[i], normals[i])
            assert bytes(buf[5:end]) == ref(i) and end == len(buf), (i, P.ENCODING_NAMES[encs[i]])
        entries = [(ids[i], i, encs[i], normals[i] is not None) for i in subset]
        buf = bytearray(b"\xee" * enc.bundle_size(entries))  # a reused buffer full of old bytes
        size = enc.write_bundle(buf, [(ids[i], i, encs[i], flags[i], normals[i]) for i in subset])
        assert size == len(buf)
        assert bytes(buf) == bytes(P.encode_bundle(99, 1234, [(ids[i], ref(i)) for i in subset]))


# ---------------------------------------------------------------------------------------------
# Bundles end to end


def test_bundle_carries_every_tick_of_every_cloth_as_its_own_key_would(server, client):
    """Bundled cloths: every tick from the first, in order, through the same ClothHandle API;
    each position equal to an unbundled twin's the same number of steps in."""
    skipped = server.stats()["skipped_frames"]
    twin = client.submit_grid(6, 5, pinned=[0, 5])
    cloths = [client.submit_grid(6, 5, pinned=[0, 5], bundle=True) for _ in range(3)]
    odd = client.submit_grid(4, 4, pinned=[0], bundle=True, normals=True, encoding="quant16")
    try:
        assert all(h.bundled and h.bundle_key == client.bundle_key for h in cloths + [odd]) and not twin.bundled
        assert client.bundle_key == P.Keys().bundle(client.client_id)
        seen: list[int] = []
        cloths[0].on_state(lambda st: seen.append(st.tick))
        end = odd.first_tick + 40
        got = {h.id: drain(h, end) for h in cloths + [odd]}
        ref = {s.tick: s for s in drain(twin, end + 10)}
        # A frame the server had to coalesce (its publisher still busy with the previous one on a
        # loaded machine) is the one documented way to miss a tick: it is counted.
        coalesced = server.stats()["skipped_frames"] - skipped
        for h in cloths + [odd]:
            ticks = [s.tick for s in got[h.id]]
            missing = sorted(set(range(h.first_tick, end + 1)) - set(ticks))
            assert ticks == sorted(set(ticks)) and ticks[-1] == end, f"{h.id}: ticks {ticks}"
            assert len(missing) <= coalesced, f"{h.id}: ticks {missing} missing, {coalesced} frames coalesced"
            assert all(s.cloth == h.id for s in got[h.id])
        assert len(seen) >= 30 and seen == sorted(set(seen))  # callbacks too
        assert seen[-1] - seen[0] + 1 - len(seen) <= coalesced
        for h in cloths:
            shift = twin.first_tick - h.first_tick
            pairs = [(s, ref[s.tick + shift]) for s in got[h.id] if s.tick + shift in ref]
            assert len(pairs) >= 30
            for s, r in pairs:
                np.testing.assert_array_equal(s.positions, r.positions)
                assert s.bounds == r.bounds and s.encoding == "float32" and s.normals is None
        last = got[odd.id][-1]
        assert last.encoding == "quant16" and last.normals is not None and last.normals.shape == (16, 3)
        assert np.isfinite(last.positions).all() and last.positions[:, 1].min() < -0.01
    finally:
        for h in cloths + [odd, twin]:
            h.remove()


def test_unwatched_states_are_not_encoded_and_watched_ones_never_skip(server, client):
    """A cloth (or a bundle) nobody subscribes to is counted unwatched and not published; once
    subscribed, every tick arrives."""
    other = connect(server)
    try:
        sub_req = P.SubmitRequest(other.client_id, grid=P.GridSpec(4, 4), state=P.StateOptions(bundle=True), rid=1)
        rep = P.submit_reply_from_map(other.request("submit", P.encode_submit(sub_req)))
        plain = P.submit_reply_from_map(
            other.request("submit", P.encode_submit(P.SubmitRequest(other.client_id, grid=P.GridSpec(4, 4), rid=2)))
        )
        assert rep.bundle_key == P.Keys().bundle(other.client_id) and plain.bundle_key is None
        time.sleep(0.2)
        before = server.stats()
        time.sleep(0.5)
        after = server.stats()
        ticks = after["ticks"] - before["ticks"]
        assert after["unwatched"] - before["unwatched"] >= 2 * (ticks - 2), "both cloths unwatched every tick"
        # now watch both, from a third session: every tick from then on
        skipped = server.stats()["skipped_frames"]
        rec = Recorder(client.session, rep.bundle_key)
        plain_ticks: list[int] = []
        psub = client.session.declare_subscriber(
            plain.key, lambda smp: plain_ticks.append(P.decode_state(smp.payload.to_bytes()).tick)
        )
        try:
            assert wait_until(lambda: len(rec.snapshot()) >= 40 and len(plain_ticks) >= 40)
            coalesced = server.stats()["skipped_frames"] - skipped  # the only excuse for a gap: counted
            assert gaps([g[0] for g in rec.snapshot()]) <= coalesced, "a bundle went missing while watched"
            assert gaps(list(plain_ticks)) <= coalesced, "a state went missing while watched"
            assert all(ids == [rep.cloth] for _, ids, _ in rec.snapshot())
        finally:
            rec.close()
            psub.undeclare()
        other.request("remove", P.encode_remove(P.RemoveRequest(rep.cloth, rep.token)))
        other.request("remove", P.encode_remove(P.RemoveRequest(plain.cloth, plain.token)))
    finally:
        other.close()


def test_remove_from_a_bundle_keeps_the_ordering_guarantee(server, client):
    a, b = (client.submit_grid(4, 4, pinned=[0], bundle=True) for _ in range(2))
    rec = Recorder(client.session, client.bundle_key)
    try:
        assert wait_until(lambda: len(rec.snapshot()) >= 5)
        last = a.remove()
        assert last is not None and a.closed
        drain(b, last + 20)
        got = rec.snapshot()
        assert all(a.id not in ids for tick, ids, _ in got if tick > last), "a state after the remove reply's tick"
        assert any(a.id in ids for tick, ids, _ in got if tick <= last)
        after = [ids for tick, ids, _ in got if tick > last]
        assert len(after) >= 15 and all(ids == [b.id] for ids in after)
        ticks = [t for t, _, _ in got]
        assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
        b.remove()
        n = len(rec.snapshot())
        time.sleep(0.3)
        assert len(rec.snapshot()) == n, "bundles kept coming after the client's last bundled cloth went"
    finally:
        rec.close()


def test_non_finite_cloth_in_a_bundle_is_reset_others_untouched(server, client):
    a, b = (client.submit_grid(5, 5, pinned=[0], bundle=True) for _ in range(2))
    try:
        drain(a, a.first_tick + 3)
        handle = server.world_handle(a.id)
        server.call(lambda w: w.reset(handle, np.full((25, 3), np.nan)))
        sa = drain(a, a.first_tick + 20)
        sb = drain(b, a.first_tick + 20)
        assert all(np.isfinite(s.positions).all() for s in sa + sb)
        resets = [s for s in sa if s.reset]
        assert resets and not any(s.reset for s in sb)
        np.testing.assert_allclose(resets[0].positions, a.rest_positions, atol=1e-6)
    finally:
        a.remove()
        b.remove()


# ---------------------------------------------------------------------------------------------
# Batch control


def test_batch_control_applies_good_items_and_refuses_bad_ones_each_alone(server, client):
    other = connect(server)
    try:
        mine = [client.submit_grid(4, 4, pinned=[0, 3], bundle=True) for _ in range(3)]
        theirs = other.submit_grid(4, 4, pinned=[0, 3])
        drain(mine[0], mine[-1].first_tick + 1)
        tgt = np.array([[0.25, 0.5, 0.0]], np.float32)

        def pins(idx, t=tgt):
            return {"indices": np.asarray(idx, "<u4").tobytes(), "targets": np.asarray(t, "<f4").tobytes()}

        def item(h, **kw):
            return {"cloth": h.id, "token": h.token, **kw}

        items = [
            item(mine[0], pins=pins([0])),  # ok
            item(theirs, pins=pins([0])),  # right token, another client's cloth
            {**item(mine[1], pins=pins([0])), "token": theirs.token},  # a real token, not for this cloth
            item(mine[1], pins=pins([1])),  # vertex 1 is not pinned
            item(mine[1], pins=pins([16])),  # no vertex 16
            "not a map",
            {"cloth": "0123456789abcdef", "token": mine[1].token, "reset": True},  # no such cloth
            item(mine[1], material={"damping": 3.0}),  # out of range
        ]
        req = {"v": [1, 1], "rid": 42, "client": client.client_id, "items": items}
        skipped = server.stats()["skipped_frames"]
        rep = P.control_batch_reply_from_map(client.request("control_batch", msgpack.packb(req, use_bin_type=True)))
        codes = [r.code or None for r in rep.results]
        assert codes == [
            None,
            "forbidden",
            "forbidden",
            "invalid_value",
            "index_out_of_range",
            "invalid_type",
            "not_found",
            "invalid_value",
        ], [(r.code, r.message) for r in rep.results]
        assert rep.rid == 42 and rep.failed == 7 and rep.results[0].tick == rep.tick
        assert "items[7].material.damping" in rep.results[7].message
        st = mine[0].wait_for_tick(rep.tick, WAIT)  # or a later one where its frame was coalesced (counted)
        assert rep.tick <= st.tick <= rep.tick + server.stats()["skipped_frames"] - skipped
        np.testing.assert_array_equal(st.positions[0], tgt[0])  # applied from the reply's tick on
        assert np.allclose(theirs.wait_for_tick(rep.tick + 2, WAIT).positions[0], 0.0)  # not moved
        assert np.allclose(mine[1].wait_for_tick(rep.tick + 2, WAIT).positions[0], 0.0)

        # The SDK's forms: a waited batch raises BatchError carrying every outcome ...
        with pytest.raises(BatchError) as e:
            with client.batch(wait=True) as b:
                b.move_pins(mine[1], [3], [[1.0, 0.1, 0.0]]).reset(mine[2]).move_pins(mine[0], [1], [[0, 0, 0]])
        res = e.value.results
        assert isinstance(res[0], int) and res[0] == res[1] and e.value.code == "invalid_value"
        assert isinstance(res[2], P.ProtocolError) and mine[0].id in res[2].message
        # ... an unwaited one counts refused items in send_errors and hands them to on_error
        errors: list[P.DrapeError] = []
        with client.batch(on_error=errors.append) as b:
            b.move_pins(mine[2], [0], [[0.0, 0.3, 0.0]])
            b.add(mine[1], pins=P.PinUpdate(np.array([2], np.uint32), np.zeros((1, 3), np.float32)))
        assert wait_until(lambda: errors)
        assert len(errors) == 1 and errors[0].code == "invalid_value" and client.send_errors == 1
        assert wait_until(lambda: np.allclose(mine[2].latest().positions[0], [0.0, 0.3, 0.0]))
        # a handle of another client is refused before anything is sent
        with pytest.raises(ValueError):
            client.batch().move_pins(theirs, [0], tgt)
        # move_pins_many: more cloths than one request may carry is split in several
        many = mine * 4  # 12 items > MAX_ITEMS
        ticks = client.move_pins_many(
            many, [0, 3], [np.array([[0, 0.1 * k, 0], [1, 0, 0]]) for k in range(12)], wait=True
        )
        assert len(ticks) == 12 and all(isinstance(t, int) for t in ticks)
        s = mine[0].wait_for_tick(max(ticks), WAIT)
        np.testing.assert_allclose(s.positions[0], [0, 0.9, 0], atol=1e-6)  # the last item for it wins
        # a 1.0 server has no batch control: the SDK falls back to one control per item
        sid = mine[0].server_id  # what its info says, as a 1.0 server's
        client.connection.set_info(sid, dataclasses.replace(client.connection.info_of(sid), version=(1, 0)))
        try:
            before = server.stats()["requests"].get("control", 0)
            out = client.move_pins_many(mine, [[0], [3], [0]], [tgt, tgt, tgt], wait=True)
            assert all(isinstance(t, int) for t in out)
            assert server.stats()["requests"]["control"] - before == 3
        finally:
            client.connection.set_info(sid, None)
        for h in mine:
            h.remove()
        theirs.remove()
    finally:
        other.close()


def _raw(m) -> bytes:
    return msgpack.packb(m, use_bin_type=True)


def test_hostile_batch_and_bundle_requests_get_errors_and_the_server_keeps_serving(server, client):
    with client.submit_grid(4, 4, pinned=[0], bundle=True) as bystander:
        drain(bystander, bystander.first_tick + 2)
        ok_item = {"cloth": bystander.id, "token": bystander.token}
        env = {"v": [1, 1], "rid": 7, "client": client.client_id}
        hostile = [
            (b"", "malformed"),
            (_raw({**env, "items": [ok_item]})[:-3], "malformed"),
            (_raw([env]), "malformed"),
            (_raw({**env, "v": [2, 0], "items": [ok_item]}), "unsupported_version"),
            (_raw({**env, "items": None}), "missing_field"),
            (_raw({k: v for k, v in env.items() if k != "client"} | {"items": [ok_item]}), "missing_field"),
            (_raw({**env, "client": "../x", "items": [ok_item]}), "invalid_value"),
            (_raw({**env, "items": {"0": ok_item}}), "invalid_type"),
            (_raw({**env, "items": []}), "invalid_value"),
            (_raw({**env, "items": [ok_item] * (MAX_ITEMS + 1)}), "too_large"),
            (_raw({**env, "items": [ok_item], "padding": b"\0" * (1 << 20)}), "too_large"),
            (b"\x91" * 100000, "malformed"),
        ]
        for payload, code in hostile:
            with pytest.raises(P.DrapeError) as e:
                client.request("control_batch", payload)
            assert e.value.code == code, (payload[:40], e.value)
        # items hostile on their own: each refused, the good one applied
        big = {"indices": np.zeros(65, "<u4").tobytes(), "targets": np.zeros(65 * 3, "<f4").tobytes()}
        nan = {"indices": np.zeros(1, "<u4").tobytes(), "targets": np.array([0, np.nan, 0], "<f4").tobytes()}
        items = [
            {**ok_item, "pins": big},
            {**ok_item, "pins": nan},
            {**ok_item, "gravity": "down"},
            {**ok_item, "state": {"bundle": False}},
            {**ok_item, "token": 5},
            {},
            ok_item,
        ]
        rep = P.control_batch_reply_from_map(client.request("control_batch", _raw({**env, "items": items})))
        assert [r.code or None for r in rep.results] == [
            "too_large",
            "invalid_value",
            "invalid_type",
            "invalid_value",
            "invalid_type",
            "missing_field",
            None,
        ]
        # bundle option abuse
        sub = {"v": [1, 1], "client": client.client_id, "grid": {"cols": 2, "rows": 2}}
        for m, code in [
            ({**sub, "state": {"bundle": "yes"}}, "invalid_type"),
            ({**sub, "state": {"bundle": 1}}, "invalid_type"),
        ]:
            with pytest.raises(P.DrapeError) as e:
                client.request("submit", _raw(m))
            assert e.value.code == code
        with pytest.raises(P.ProtocolError) as e:
            client.request("control", _raw({**ok_item, "v": [1, 1], "state": {"bundle": False}}))
        assert e.value.code == "invalid_value" and "submission" in e.value.message
        # still served: every tick, controllable, by the batch key too
        bystander.clear()
        skipped = server.stats()["skipped_frames"]
        states = drain(bystander, server.tick + 10)
        assert gaps([s.tick for s in states]) <= server.stats()["skipped_frames"] - skipped
        res = client.batch(wait=True).move_pins(bystander, [0], [[0.0, 0.2, 0.0]]).send()
        assert bystander.wait_for_tick(res[0], WAIT).positions[0, 1] == pytest.approx(0.2)


# ---------------------------------------------------------------------------------------------
# A 1.0 client is served as before


def test_a_v1_0_client_is_served_unchanged(server, client):
    """Messages stamped 1.0, without any 1.1 field: the same replies (new keys absent), states on
    the cloth's own key in the 1.0 layout (only the minor byte says 1)."""
    v10 = {"v": [1, 0], "rid": 3}
    m = client.request(
        "submit",
        _raw(
            {
                **v10,
                "client": client.client_id,
                "grid": {"cols": 3, "rows": 3},
                "pinned": np.array([0], "<u4").tobytes(),
            }
        ),
    )
    assert m["v"][0] == 1 and set(m) == {"v", "rid", "ok", "cloth", "token", "key", "vertices", "tick"}
    got: list[bytes] = []
    sub = client.session.declare_subscriber(m["key"], lambda smp: got.append(smp.payload.to_bytes()))
    try:
        assert wait_until(lambda: len(got) >= 3)
        data = got[-1]
        magic, major, minor, hsize, enc, _, flags, n, tick = struct.unpack_from("<4sBBHBBHIQ", data)
        assert (magic, major, hsize, enc, flags, n) == (b"DRPS", 1, 64, 0, 0, 9) and len(data) == 64 + 9 * 12
        c = client.request(
            "control",
            _raw(
                {
                    **v10,
                    "cloth": m["cloth"],
                    "token": m["token"],
                    "pins": {
                        "indices": np.array([0], "<u4").tobytes(),
                        "targets": np.array([0, 1, 0], "<f4").tobytes(),
                    },
                }
            ),
        )
        assert set(c) == {"v", "rid", "ok", "tick"} and c["rid"] == 3
        with pytest.raises(Forbidden):
            client.request("control", _raw({**v10, "cloth": m["cloth"], "token": "0" * 32}))
        r = client.request("remove", _raw({**v10, "cloth": m["cloth"], "token": m["token"]}))
        assert r["ok"] and r["tick"] >= c["tick"] - 1
    finally:
        sub.undeclare()
