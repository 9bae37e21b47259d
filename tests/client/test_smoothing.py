"""Rendering between states (client/smoothing.py): interpolation a tick behind the newest state,
extrapolation past it, the render clock mapped onto the server's, and a 144 Hz renderer that
moves the cloth in every frame where the raw states would repeat."""

from __future__ import annotations

import numpy as np

from drape.client.protocol import ClothState
from drape.client.smoothing import ServerClock, sample

TICK = 16_666_667  # ns at 60 Hz


def _state(tick: int, x: float, latency_ns: int = 5_000_000, offset_ns: int = 123_456_789) -> ClothState:
    pos = np.array([[x, 0.0, 0.0], [x, 1.0, 0.0]], np.float32)
    server = 1_000_000_000_000 + tick * TICK
    return ClothState(tick, server, pos, receive_time_ns=server + offset_ns + latency_ns)


def test_interpolation_runs_one_tick_behind_and_holds_at_the_ends():
    a, b = _state(10, 1.0), _state(11, 2.0)
    at = b.server_time_ns  # a render time at the newest state: shows a, one tick behind
    np.testing.assert_allclose(sample(a, b, at)[:, 0], 1.0)
    np.testing.assert_allclose(sample(a, b, at + TICK // 2)[:, 0], 1.5, atol=1e-6)
    np.testing.assert_allclose(sample(a, b, at + 5 * TICK)[:, 0], 2.0)  # held: no state past b yet
    np.testing.assert_allclose(sample(a, b, at - 5 * TICK)[:, 0], 1.0)
    np.testing.assert_allclose(sample(a, b, at, delay_ns=0)[:, 0], 2.0)
    assert sample(None, None, at) is None
    np.testing.assert_array_equal(sample(None, b, at), b.positions)


def test_extrapolation_carries_the_velocity_past_the_newest_state_up_to_a_cap():
    a, b = _state(10, 1.0), _state(11, 2.0)
    np.testing.assert_allclose(sample(a, b, b.server_time_ns + TICK // 2, extrapolate=True)[:, 0], 2.5, atol=1e-6)
    np.testing.assert_allclose(sample(a, b, b.server_time_ns + 10 * TICK, extrapolate=True)[:, 0], 3.0)


def test_the_server_clock_is_the_smallest_offset_seen_lately():
    clock = ServerClock(window=4)
    assert clock.to_server(5) is None
    for t, lat in enumerate([9_000_000, 5_000_000, 7_000_000]):
        clock.observe(_state(t, 0.0, latency_ns=lat))
    assert clock.offset_ns == 123_456_789 + 5_000_000
    for t in range(3, 7):  # the fast one leaves the window
        clock.observe(_state(t, 0.0, latency_ns=8_000_000))
    assert clock.offset_ns == 123_456_789 + 8_000_000
    assert clock.to_server(clock.offset_ns + 42) == 42


def test_a_144_hz_renderer_moves_the_cloth_every_frame():
    """States at 60 Hz, frames at 144 Hz: drawn raw, most frames repeat the newest state; drawn
    with sample(), every frame differs from the one before."""
    states = [_state(t, 0.01 * t) for t in range(60)]
    clock = ServerClock()
    frame_ns = 1_000_000_000 // 144
    start = states[2].receive_time_ns
    raw, smooth = [], []
    k = 0
    for f in range(120):  # 0.83 s: within the states' second
        now = start + f * frame_ns
        while k + 1 < len(states) and states[k + 1].receive_time_ns <= now:
            k += 1
            clock.observe(states[k])
        raw.append(states[k].positions[0, 0])
        smooth.append(sample(states[k - 1], states[k], clock.to_server(now))[0, 0])
    raw_still = sum(1 for p, q in zip(raw, raw[1:], strict=False) if p == q)
    smooth_still = sum(1 for p, q in zip(smooth, smooth[1:], strict=False) if p == q)
    assert raw_still > 60  # 144 / 60: more than half of the frames repeat a state
    assert smooth_still == 0
    assert all(q >= p for p, q in zip(smooth, smooth[1:], strict=False))  # never backwards
