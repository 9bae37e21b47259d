"""Rates per subscriber end to end (protocol 1.8, 1.9's every 6th and 12th): a real server on
loopback publishes every k-th state of a cloth or bundle on its own key, predicted against that
key's own states, only while someone subscribes (counted); the SDK's decimated states decode
within half a step of the full-rate float32 states of the same motion; a keyframe query on a
decimated key makes that stream's next state intra-coded; on the device encoder
(sim/opencl/devrates.py) as on the host. An SDK told its server speaks 1.8 takes at most every
3rd state."""

from __future__ import annotations

import dataclasses
import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh
from conftest import WAIT, collect, connect, make_config, wait_until

from drape.client import protocol as P
from drape.server.service.server import Server

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

STEP = 0.002


@pytest.fixture(scope="module", params=[True, False], ids=["device", "host"])
def server(request):
    # decimated predictive streams coded by the device encoder (sim/opencl/devrates.py) and the host path
    with Server(make_config(keyframe_interval=30, device_encode=request.param)) as srv:
        yield srv


def _session(server) -> zenoh.Session:
    ep = server.config.listen[0]
    conf = f'{{mode: "peer", connect: {{endpoints: ["{ep}"]}}, scouting: {{multicast: {{enabled: false}}}}}}'
    return zenoh.open(zenoh.Config.from_json5(conf))


def _device_rate_frames(server) -> int | None:
    """Decimated frames the device encoder coded (None: the host path)."""
    frames = getattr(server.ticker.world, "device_frames", None)
    return frames.rates.frames if frames is not None else None


@pytest.mark.parametrize("every,bundle", [(2, False), (3, True), (6, False), (12, True)])
def test_decimated_states_stay_within_half_a_step_of_float32(server, every, bundle):
    c = connect(server, rate=every)
    n = 40 if every <= 3 else 24  # states taken (at 5 Hz, 24 are 5 s)
    full = connect(server, queue_size=n * every + 10)  # holds every full-rate state of the run
    counters = server.registry.counters
    published, unserved, coded = counters["rate_published"], counters["rate_unserved"], _device_rate_frames(server)
    try:
        opts = dict(pinned=[0, 11], features=["tethers"])
        pred = c.submit_grid(12, 12, encoding="predictive", step=STEP, bundle=bundle, **opts)
        f32 = full.submit_grid(12, 12, **opts)  # the same motion at full rate, float32
        assert pred.rate == every and f32.rate == 1
        got = [s for s in collect(pred, n, timeout=3 * n * every / 60 + 10) if not s.extrapolated]
        ref = {s.tick - f32.first_tick: s.positions for s in collect(f32, n * every + 10)}
        assert all(s.tick % every == 0 for s in got)
        # every k-th (a frame the server coalesced on a busy machine is missing: the next still decodes)
        assert all((b.tick - a.tick) % every == 0 and b.tick > a.tick for a, b in zip(got, got[1:], strict=False))
        common = [s for s in got if s.tick - pred.first_tick in ref]
        assert len(common) > n // 2
        for s in common:
            err = np.abs(ref[s.tick - pred.first_tick] - s.positions).max()
            assert err <= STEP / 2 + 1e-5, (s.tick, err)
        assert pred.gaps == 0 and pred.stream.undecodable == 0
        # predicted against its own states: most are not keyframes
        assert pred.stream.keyframes < len(got) // 3  # (the first, then one every 30 ticks or so)
        assert counters["rate_published"] >= published + len(got)
        # served by the encoder of the frame (the device's decimated frames, no host fallback); a
        # subscription seen after its tick's frame was encoded waits for its next tick (one state)
        assert counters["rate_unserved"] <= unserved + 1
        if coded is not None:
            assert _device_rate_frames(server) >= coded + len(got)
    finally:
        c.close()
        full.close()


def test_an_sdk_facing_a_1_8_server_takes_every_3rd_state_at_most(server):
    """1.9's every 6th and 12th come from a 1.9 server only: a client asking for 12 from a server
    whose info it is told says 1.8 (the real server still publishes ``every/12``) takes every 3rd
    state instead, on its own key and in its bundle, and ``auto``'s ladder stops at 3 there."""
    c = connect(server, rate=12)
    auto = connect(server, rate="auto")
    try:
        for client in (c, auto):
            old = client.connection.info_of(server.server_id)
            client.connection.set_info(server.server_id, dataclasses.replace(old, version=(1, 8)))
        own = c.submit_grid(6, 6, pinned=[0, 5], encoding="predictive", step=STEP)
        bundled = c.submit_grid(6, 6, pinned=[0, 5], origin=(1.0, 1.0, 0.0), bundle=True)
        assert own.rate == 3 and c.bundles.rate == 3 and bundled.rate == 3
        for h in (own, bundled):
            ticks = [s.tick for s in collect(h, 12) if not s.extrapolated]
            assert all(t % 3 == 0 for t in ticks) and any(t % 12 for t in ticks), ticks
        own.set_rate(6)  # not served by a 1.8 server: the rate below it
        assert own.rate == 3
        governed = auto.submit_grid(6, 6, pinned=[0, 5])
        assert governed.governor is not None and governed.governor.rates == (1, 2, 3)
    finally:
        c.close()
        auto.close()


def test_a_decimated_key_is_encoded_only_while_subscribed_and_keyframes_on_its_own_query(server):
    c = connect(server)
    try:
        pred = c.submit_grid(12, 12, pinned=[0, 11], encoding="predictive", step=STEP)
        collect(pred, 5)
        counters = server.registry.counters
        before = counters["rate_published"]
        collect(pred, 10)
        assert counters["rate_published"] == before  # nobody takes every 2nd state: none encoded
        key = P.every_key(pred.key, 2)
        stream = P.StateStream(pred.id)
        got: list[tuple[int, int | None]] = []  # (tick, order of the state or None: not decodable)
        lock = threading.Lock()

        def on_sample(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()
            st = stream.decode(data)
            order = P.read_predictive_header(data).order if st is not None else None
            with lock:
                got.append((P.read_state_header(data, len(data))[4], order))

        session = _session(server)
        try:
            sub = session.declare_subscriber(key, on_sample)
            assert wait_until(lambda: counters["rate_published"] >= before + 5)
            assert wait_until(lambda: len(got) >= 5)
            queries = counters["keyframe_queries"]
            replies = list(session.get(key, timeout=WAIT))
            assert len(replies) == 1
            answer = msgpack.unpackb(replies[0].ok.payload.to_bytes())
            assert answer["cloths"] == 1 and answer["tick"] % 2 == 0
            assert counters["keyframe_queries"] == queries + 1
            assert wait_until(lambda: any(t >= answer["tick"] + 4 for t, _ in got))
            with lock:
                near = [o for t, o in got if answer["tick"] - 2 <= t <= answer["tick"] + 4]
                ticks = [t for t, _ in got]
            # the stream's next state is a keyframe: the answer's tick is the earliest, which a
            # publisher already past its request takes, the host path one tick sooner (its state
            # coded as it is put) and the device one of the rate's ticks later (decided a frame ahead)
            assert 0 in near, near
            assert all(t % 2 == 0 for t in ticks)
            sub.undeclare()

            def quiet() -> bool:  # nothing more encoded for it over 12 ticks (one in flight at most)
                stopped = counters["rate_published"]
                collect(pred, 12)
                return counters["rate_published"] <= stopped + 1

            assert wait_until(quiet), "the listener should see it go"  # however late a loaded machine runs it
            # a subscriber coming back after nobody watched (once the server has forgotten the
            # rate's streams: the host path's on a tick of the rate, the device's plan with them)
            # gets a keyframe first
            frames = getattr(server.ticker.world, "device_frames", None)
            rates = server.publisher.rates
            assert wait_until(lambda: not rates.streams[2].streams and (frames is None or 2 not in frames.rates.rates))
            again = P.StateStream(pred.id)
            firsts: list[int | None] = []

            def on_again(sample: zenoh.Sample) -> None:
                data = sample.payload.to_bytes()
                with lock:  # decoded and counted in one go (samples may come on several threads)
                    st = again.decode(data)
                    firsts.append(P.read_predictive_header(data).order if st is not None else None)

            sub = session.declare_subscriber(key, on_again)
            assert wait_until(lambda: len(firsts) >= 3)
            sub.undeclare()
            with lock:
                assert firsts[0] == 0 and None not in firsts, firsts
            assert again.undecodable == 0
        finally:
            session.close()
    finally:
        c.close()


def _decimated_orders(session: zenoh.Session, key: str, cloth: str) -> tuple[zenoh.Subscriber, P.StateStream, list]:
    """A subscriber of ``key`` (one cloth's decimated key) decoding its states in order: the
    stream and each state's predictor order as received (None: not decodable)."""
    stream = P.StateStream(cloth)
    orders: list[int | None] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        data = sample.payload.to_bytes()
        with lock:  # decoded and counted in one go (samples may come on several threads)
            st = stream.decode(data)
            orders.append(P.read_predictive_header(data).order if st is not None else None)

    return session.declare_subscriber(key, on_sample), stream, orders


@pytest.mark.parametrize("beside", [False, True], ids=["alone", "beside"])
def test_a_key_watched_again_restarts_on_a_keyframe(server, beside):
    """A decimated key watched, unwatched for a few of its rate's ticks and watched again: the
    key's own forgetting (rates.py: a key that lost its last subscriber; the device's decimated
    plan without it) makes the returning subscriber's first state a keyframe, and it decodes
    every state with no keyframe query; alone (nobody watches the rate meanwhile) and beside
    another cloth's key of the same rate watched throughout (whose subscriber misses nothing)."""
    c = connect(server)
    try:
        opts = dict(pinned=[0, 11], encoding="predictive", step=STEP)
        a, b = c.submit_grid(12, 12, **opts), c.submit_grid(10, 10, **opts)
        collect(a, 3)
        collect(b, 3)
        rates, publisher = server.publisher.rates, server.publisher
        counters = server.registry.counters
        session = _session(server)
        try:
            keep, kept, _ = _decimated_orders(session, P.every_key(b.key, 2), b.id) if beside else (None, None, [])
            sub, first, orders = _decimated_orders(session, P.every_key(a.key, 2), a.id)
            assert wait_until(lambda: len(orders) >= 5 and (kept is None or kept.decoded >= 5))
            queries = counters["keyframe_queries"]
            sub.undeclare()
            assert wait_until(lambda: a.id not in rates.watching().get(2, frozenset()))  # the listener saw it go
            # the publisher puts 6 more ticks (3 of the rate, encoded after it went: the frames
            # in flight then are 2 at most), the key unwatched on them
            t0 = publisher.last_tick
            assert wait_until(lambda: publisher.last_tick >= t0 + 6)
            assert (b.id in rates.watching().get(2, frozenset())) == beside
            decoded = kept.decoded if kept is not None else 0
            sub, again, orders_again = _decimated_orders(session, P.every_key(a.key, 2), a.id)
            assert wait_until(lambda: len(orders_again) >= 4 and (kept is None or kept.decoded >= decoded + 4))
            sub.undeclare()
            if keep is not None:
                keep.undeclare()
        finally:
            session.close()
        assert None not in orders and first.undecodable == 0
        assert orders_again[0] == 0 and None not in orders_again, orders_again
        assert again.undecodable == 0 and (kept is None or kept.undecodable == 0)
        assert counters["keyframe_queries"] == queries  # nobody asked
    finally:
        c.close()


@pytest.mark.parametrize("bundle", [False, True])
def test_a_subscription_switches_rate_and_resyncs_on_a_keyframe(server, bundle):
    c = connect(server)
    try:
        pred = c.submit_grid(12, 12, pinned=[0, 11], encoding="predictive", step=STEP, bundle=bundle)
        collect(pred, 5)
        (c.bundles if bundle else pred).set_rate(3)
        assert pred.rate == 3
        assert wait_until(lambda: pred.stream.keyframes >= 2)  # the new key's stream starts on a keyframe
        pred.clear()
        got = [s for s in collect(pred, 8) if not s.extrapolated]
        assert len(got) >= 7 and all(s.tick % 3 == 0 for s in got)
    finally:
        c.close()


def test_a_non_finite_cloth_on_a_decimated_key_comes_back_at_rest(server):
    """A cloth gone non-finite is reset by the server; on its decimated key (every 2nd state,
    with normals) every state stays finite, decodes and lies near the rest pose (on a decimated
    tick the device codes its rate frame again with the reset, as the full-rate frame, never the
    non-finite positions: three resets, some land on a decimated tick)."""
    c = connect(server, rate=2)
    try:
        with c.submit_grid(6, 5, pinned=[0], normals=True, encoding="predictive", step=STEP) as h:
            collect(h, 3)
            handle = server.world_handle(h.id)
            for _ in range(3):
                server.call(lambda w: w.reset(handle, np.full((30, 3), np.nan)))
                for s in collect(h, 4):
                    assert np.isfinite(s.positions).all() and np.isfinite(s.normals).all()
                    # a few ticks' fall from rest at most (a state coded from non-finite positions
                    # would lie at the grid's clamp, kilometres away)
                    assert np.abs(s.positions - h.rest_positions).max() <= 0.5
            assert h.stream.undecodable == 0
    finally:
        c.close()


@pytest.mark.parametrize("device_encode", [True, False], ids=["device", "host"])
def test_frames_dropped_on_decimated_ticks_keep_the_stream_predicted(device_encode):
    """A publisher late for a few ticks drops frames whole, some on the decimated stream's ticks:
    its states after each gap are predicted from the last two it sent (the device's decimated
    streams taken back, as the host path, which never coded them): the subscriber of every 2nd
    state decodes every one, none is a keyframe, and the server writes no more keyframes."""
    server = Server(make_config(device_encode=device_encode, keyframe_interval=100_000)).start()
    try:
        c = connect(server, rate=2)
        try:
            with c.submit_grid(12, 12, pinned=[0, 11], encoding="predictive", step=STEP) as h:
                collect(h, 8)  # past its first keyframes
                first = h.stream.keyframes
                publisher = server.publisher
                publish, stalls = publisher.publish, [0]

                def late(job) -> None:  # the publisher descheduled for 3 ticks, now and then
                    stalls[0] += 1
                    if stalls[0] % 7 == 0:
                        time.sleep(0.05)
                    publish(job)

                counters = server.registry.counters
                skipped, keyframes = counters["skipped_frames"], counters["keyframes"]
                unserved = counters["rate_unserved"]
                publisher.publish = late  # type: ignore[method-assign]
                states = collect(h, 40)
                publisher.publish = publish  # type: ignore[method-assign]
                ticks = [s.tick for s in states]
                assert all(t % 2 == 0 for t in ticks)
                assert counters["skipped_frames"] > skipped and any(
                    b - a > 2 for a, b in zip(ticks, ticks[1:], strict=False)
                )
                assert not any(s.extrapolated for s in states)
                assert h.stream.undecodable == 0
                assert h.stream.keyframes == first  # none since
                assert counters["keyframes"] == keyframes and counters["rate_unserved"] == unserved
                frames = getattr(server.ticker.world, "device_frames", None)
                assert (frames is not None) == device_encode
                if frames is not None:
                    assert frames.rates.frames >= len(states)
        finally:
            c.close()
    finally:
        server.stop()
    assert server.failure is None
