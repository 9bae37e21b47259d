"""drape.client.failover.resume_from: what a failover resubmits from a handle's last two states
(PROTOCOL.md 11.1): the newer state's positions, velocities (x_k - x_{k-1}) / (dt (t_k - t_{k-1}))
against a float64 reference, and no resume from nothing or from a non-finite state. The resume
then encodes and decodes as protocol 1.3 says."""

from __future__ import annotations

import numpy as np
import pytest

from drape.client import protocol as P
from drape.client.failover import resume_from


def _state(tick: int, positions: np.ndarray) -> P.ClothState:
    return P.ClothState(tick, 0, np.asarray(positions, np.float32), cloth="c0")


def test_velocities_from_the_last_two_states(rng):
    x0 = rng.uniform(-2, 2, (7, 3))
    v = rng.uniform(-3, 3, (7, 3))
    gap = int(rng.integers(1, 4))  # states lost in between: the tick difference counts
    x1 = x0 + v * gap / 60.0
    rs = resume_from((_state(100, x0), _state(100 + gap, x1)), "s1", "c0", 60.0)
    assert rs is not None and rs.tick == 100 + gap and (rs.from_server, rs.cloth) == ("s1", "c0")
    assert np.array_equal(rs.positions, np.asarray(x1, np.float32))
    want = (np.asarray(x1, np.float32).astype(np.float64) - np.asarray(x0, np.float32)) * 60.0 / gap
    assert rs.velocities is not None and np.isfinite(rs.velocities).all()
    assert np.abs(rs.velocities - want).max() < 1e-3 * max(1.0, np.abs(want).max())
    # a 1.3 submission carrying it decodes to the same arrays
    req = P.SubmitRequest(
        client="c", mesh=P.MeshSpec(np.zeros((7, 3), np.float32), np.zeros((0, 3), np.uint32)), resume=rs
    )
    got = P.decode_submit(P.encode_submit(req)).resume
    assert got == rs


def test_one_state_resumes_without_velocities():
    rs = resume_from((None, _state(5, np.ones((2, 3)))), "s", "c0", 60.0)
    assert rs is not None and rs.velocities is None and rs.positions.shape == (2, 3)


@pytest.mark.parametrize("bad", ["none", "nan_last", "nan_prev", "same_tick"])
def test_nothing_usable_starts_from_rest_or_drops_velocities(bad):
    good = np.zeros((2, 3))
    nan = np.array([[0, np.nan, 0], [0, 0, 0]])
    if bad == "none":
        assert resume_from((None, None), "s", "c", 60.0) is None
    elif bad == "nan_last":
        assert resume_from((_state(1, good), _state(2, nan)), "s", "c", 60.0) is None
    elif bad == "nan_prev":
        rs = resume_from((_state(1, nan), _state(2, good)), "s", "c", 60.0)
        assert rs is not None and rs.velocities is None
    else:
        rs = resume_from((_state(2, good), _state(2, good)), "s", "c", 60.0)
        assert rs is not None and rs.velocities is None


def test_resume_refuses_a_wrong_vertex_count_with_a_clear_error():
    req = P.SubmitRequest(client="c", grid=P.GridSpec(2, 2), resume=P.ResumeState(np.zeros((3, 3), np.float32)))
    with pytest.raises(P.ProtocolError) as e:
        P.decode_submit(P.encode_submit(req))
    assert e.value.code == P.ERR_INVALID_VALUE
    assert "'resume.positions' has 3 vertices but the cloth has 4" in str(e.value)
