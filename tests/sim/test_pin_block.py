"""World.set_pin_targets_block (protocol 1.4 moves): one vectorised call equals per-cloth
set_pin_targets on the OpenCL world (PoCL on CI) and the reference world; a later call of the
same step wins; pins reach their targets after a step; the validating variant refuses bad input."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim import make_world
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams

PINS = [0, 3, 12, 15]  # the corners of a 4x4 grid


def _world(kind: str, device):
    return make_world("reference") if kind == "reference" else make_world("workgroup", device=device)


def _fill(world, rng: np.random.Generator, n: int) -> list[int]:
    """n cloths of two fabrics (4x4 and 4x5, both pinned at PINS), a few removed to leave holes."""
    handles = []
    for i in range(n + 3):
        rows = 4 if i % 2 else 5
        handles.append(world.add(cook_grid(4, rows, pinned=PINS), ClothParams()))
    for h in rng.choice(handles, 3, replace=False).tolist():
        world.remove(h)
        handles.remove(h)
    return handles


def _pinned_positions(world, handles: list[int], idx: np.ndarray) -> np.ndarray:
    frame = world.fetch()
    return np.stack([frame.positions[h][idx] for h in handles])


@pytest.mark.parametrize("kind", ["opencl", "reference"])
def test_block_equals_per_cloth_targets(kind, device, rng):
    a, b = _world(kind, device), _world(kind, device)
    ha, hb = _fill(a, np.random.default_rng(1), 9), _fill(b, np.random.default_rng(1), 9)
    assert ha == hb
    order = rng.permutation(len(ha))
    handles = np.array(ha)[order]
    idx = np.array(rng.permutation(PINS)[: int(rng.integers(1, 5))], np.int64)
    targets = rng.uniform(-2, 2, (len(handles), len(idx), 3)).astype(np.float32)
    a.set_pin_targets_block(handles, idx.astype(np.uint32), targets)
    for j, h in enumerate(handles.tolist()):
        b.set_pin_targets(h, idx, targets[j])
    a.step(1 / 60)
    b.step(1 / 60)
    pa, pb = a.fetch(), b.fetch()
    for h in ha:
        np.testing.assert_array_equal(pa.positions[h], pb.positions[h])
    got = _pinned_positions(a, handles.tolist(), idx)
    np.testing.assert_allclose(got, targets, rtol=0, atol=1e-5)  # pins reached after one step


def test_later_block_wins_and_items_mix(device, rng):
    """Two blocks and a per-cloth call in one step on the device: the last call wins per vertex,
    whatever the device scatter's order."""
    w = _world("opencl", device)
    hs = _fill(w, rng, 6)
    handles = np.array(hs, np.int64)
    idx = np.array(PINS, np.int64)
    first = rng.uniform(-1, 1, (len(hs), 4, 3)).astype(np.float32)
    second = rng.uniform(-1, 1, (len(hs), 4, 3)).astype(np.float32)
    w.set_pin_targets_block(handles, idx, first)
    w.set_pin_targets(hs[0], np.array([0, 3]), np.ones((2, 3)))  # overridden by the second block
    w.set_pin_targets_block(handles[1:], idx[:2], second[1:, :2])
    w.set_pin_targets(hs[1], np.array([0]), np.full((1, 3), 0.5))  # the last word on hs[1] vertex 0
    w.step(1 / 60)
    want = first.copy()
    want[0, :2] = 1.0
    want[1:, :2] = second[1:, :2]
    want[1, 0] = 0.5
    np.testing.assert_allclose(_pinned_positions(w, hs, idx), want, rtol=0, atol=1e-5)


def test_validating_variant_refuses(device):
    w = _world("opencl", device)
    h = w.add(cook_grid(4, 4, pinned=PINS), ClothParams())
    one = np.zeros((1, 1, 3), np.float32)
    with pytest.raises(ValueError, match="pinned"):
        w.set_pin_targets_block(np.array([h]), np.array([5]), one)
    with pytest.raises(ValueError, match="range"):
        w.set_pin_targets_block(np.array([h]), np.array([16]), one)
    with pytest.raises(ValueError, match="finite"):
        w.set_pin_targets_block(np.array([h]), np.array([0]), np.full((1, 1, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="distinct"):
        w.set_pin_targets_block(np.array([h, h]), np.array([0]), np.zeros((2, 1, 3), np.float32))
    with pytest.raises(KeyError):
        w.set_pin_targets_block(np.array([h + 1]), np.array([0]), one)
    assert w.live(np.array([h, h + 1, -1, 10**6])).tolist() == [True, False, False, False]
    w.remove(h)
    assert not w.live(np.array([h]))[0]
