"""A tick's adds written as one batch (clworld.py's staged vertex rows): the same positions as
cloths written one by one, whatever else the tick does to them (removes, resets, pin targets,
mass changes, resumed velocities), against the float64 reference too; a few device writes per
tick, not several per cloth; and the readback's gather map kept where the layout kept cloths."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import random_grid_fabric, random_mesh_fabric

from drape.server.sim.frame import Layout
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.opencl.frames import kept_runs
from drape.server.sim.params import ClothParams, Material
from drape.server.sim.world import ReferenceWorld, World

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)

DT = 1 / 60


def _params(rng) -> ClothParams:
    return ClothParams(
        material=Material(mass=float(rng.uniform(0.2, 3.0)), damping=float(rng.uniform(0, 0.05))),
        gravity=(float(rng.normal(0, 1)), float(rng.uniform(-15, -5)), float(rng.normal(0, 1))),
        iterations=int(rng.integers(1, 8)),
        substeps=int(rng.integers(1, 3)),
    )


def _script(rng) -> list[list[tuple]]:
    """Three ticks of commands (the same for every world): adds with and without a start and
    velocities, then removes of cloths just added and of older ones, a reset, pin targets and a
    mass change of cloths added in the same tick."""
    fabs = [random_grid_fabric(rng), random_mesh_fabric(rng), random_grid_fabric(rng)]
    ticks: list[list[tuple]] = []
    n = 0
    for t in range(3):
        cmds: list[tuple] = []
        for _ in range(int(rng.integers(5, 10))):
            f = fabs[int(rng.integers(len(fabs)))]
            pos = f.rest_positions + rng.normal(0, 0.05, f.rest_positions.shape) if rng.random() < 0.7 else None
            vel = rng.normal(0, 0.3, f.rest_positions.shape) if rng.random() < 0.4 else None
            cmds.append(("add", f, _params(rng), pos, vel))
            n += 1
        if t > 0:
            new = list(range(n - len(cmds), n))  # the add indices of this tick's cloths
            cmds.append(("remove", new[1]))
            cmds.append(("remove", int(rng.integers(0, new[0]))))  # an older cloth
            cmds.append(("add", fabs[0], _params(rng), None, None))  # may land in a freed range
            n += 1
            cmds.append(("reset", new[2], 0.03))
            cmds.append(("pins", new[3], 0.1))
            cmds.append(("mass", new[4], float(rng.uniform(0.2, 3.0))))
        ticks.append(cmds)
    return ticks


def _play(world: World, ticks: list[list[tuple]], rng_seed: int, flush_each: bool) -> list[dict[int, np.ndarray]]:
    """Run the script; ``flush_each``: read a frame after every command (each add written alone)."""
    rng = np.random.default_rng(rng_seed)
    handles: list[int | None] = []
    out = []
    for cmds in ticks:
        for cmd in cmds:
            what = cmd[0]
            if what == "add":
                _, f, p, pos, vel = cmd
                handles.append(world.add(f, p, pos, vel))
            else:
                h = handles[cmd[1]]
                if h is None or h not in world.cloths:
                    continue
                cloth = world.cloths[h]
                if what == "remove":
                    world.remove(h)
                    handles[cmd[1]] = None
                elif what == "reset":
                    world.reset(h, cloth.fabric.rest_positions + rng.normal(0, cmd[2], (cloth.fabric.n_vertices, 3)))
                elif what == "pins":
                    idx = np.flatnonzero(cloth.fabric.pinned)
                    world.set_pin_targets(h, idx, cloth.fabric.rest_positions[idx] + cmd[2])
                elif what == "mass":
                    m = cloth.params.material
                    world.set_params(h, cloth.params.with_(material=replace(m, mass=cmd[2])))
            if flush_each:
                world.fetch()
        world.step(DT)
        frame = world.fetch()
        out.append({h: frame.positions[h].copy() for h in frame.handles.tolist()})
    return out


@pytest.mark.parametrize("solver", ["workgroup", "coloured"])
def test_adds_of_a_tick_in_one_batch_equal_one_by_one(device, rng, solver):
    ticks = _script(rng)
    seed = int(rng.integers(2**31))
    one = _play(CLWorld(solver, device=device), ticks, seed, flush_each=True)
    batch = _play(CLWorld(solver, device=device), ticks, seed, flush_each=False)
    ref = _play(ReferenceWorld(), ticks, seed, flush_each=False)
    for t, (a, b, r) in enumerate(zip(one, batch, ref, strict=True)):
        assert list(a) == list(b) == list(r), f"tick {t}: the same cloths in the same order"
        for h in a:
            np.testing.assert_array_equal(b[h], a[h], err_msg=f"tick {t}, cloth {h}")
            scale = max(1.0, float(np.abs(r[h]).max()))
            np.testing.assert_allclose(b[h], r[h], atol=2e-5 * scale * (t + 1), rtol=0, err_msg=f"tick {t}, cloth {h}")


def test_a_tick_of_adds_writes_each_vertex_buffer_once(device, rng):
    world = CLWorld("workgroup", device=device)
    fab = random_grid_fabric(rng)
    world.add(fab, ClothParams())
    world.step(DT)  # the buffers are grown on the next adds while they are staged, before any write
    world.sync()
    calls = {"n": 0}
    pos = world.mem.pos
    write = pos.write

    def counted(start, host, blocking=True):
        calls["n"] += 1
        write(start, host, blocking)

    pos.write = counted  # type: ignore[method-assign]
    hs = [world.add(fab, ClothParams()) for _ in range(40)]
    assert calls["n"] == 0  # staged until something needs the buffers
    world.step(DT)
    assert calls["n"] == 1  # adjacent ranges: one write
    world.remove(hs[3])
    world.remove(hs[10])
    world.add(fab, ClothParams())  # into the first hole
    world.add(fab, ClothParams())  # into the second
    world.step(DT)
    assert calls["n"] == 3  # one per run of adjacent ranges
    frame = world.fetch()
    assert np.isfinite(frame.xyz).all() and len(frame.handles) == 41


def _layout(version: int, handles: list[int], rows: dict[int, int]) -> Layout:
    hs = np.array(handles, np.int64)
    offsets = np.concatenate([[0], np.cumsum([rows[h] for h in handles])]).astype(np.int64)
    return Layout(version, hs, offsets, np.zeros(len(hs), bool), {h: i for i, h in enumerate(handles)})


def test_gather_map_keeps_the_rows_of_cloths_that_stay():
    rows = {1: 2, 2: 3, 3: 2, 4: 1, 5: 4, 6: 3}
    old = _layout(1, [1, 2, 3, 4, 5], rows)
    # 2 and 4 left, 6 came: 1, 3, 5 keep their rows in three runs, 6's are new
    assert kept_runs(old, _layout(2, [1, 3, 5, 6], rows)) == (3, [(0, 0, 2), (5, 2, 2), (8, 4, 4)])
    assert kept_runs(old, _layout(3, [1, 2, 3, 4, 5, 6], rows)) == (5, [(0, 0, 12)])  # only added: in place
    assert kept_runs(old, _layout(4, [6], rows)) == (0, [])  # every cloth new
    assert kept_runs(old, _layout(5, [2, 1, 3, 4, 5], rows)) is None  # reordered: rebuilt whole
    assert kept_runs(None, old) is None
