"""Scenes (issue 22, protocol 1.7): cloths of one scene collide with each other on the device as
in the float64 reference, cloths of different scenes never interact, two capes dragged through
each other leave no penetration, a World without scenes builds and launches nothing new."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.sim.fabric import cook_grid
from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.opencl.scenes import SOURCE
from drape.server.sim.params import ClothParams, LinkOptions, Material, Sphere, pack_colliders
from drape.server.sim.scenes import scene_penetration
from drape.server.sim.world import ReferenceWorld
from drape.server.tools import penetration as pen

DT = 1 / 60
N = 17  # a 0.5 m cape, 31 mm between neighbours
THICKNESS = 0.03
PINS = np.array([0, N - 1])  # the shoulders


def capes():
    """Two capes hanging 0.3 m apart in z, the second higher and to the side, pinned by their
    shoulders: dragged 0.3 m towards each other they pass through each other's lower halves."""
    a = cook_grid(
        N, N, 0.5, 0.5, LinkOptions(bending=True), orientation="vertical", pinned=PINS, origin=(-0.25, 1.0, -0.15)
    )
    b = cook_grid(
        N, N, 0.5, 0.5, LinkOptions(bending=True), orientation="vertical", pinned=PINS, origin=(-0.1, 1.25, 0.15)
    )
    return a, b


def params() -> ClothParams:
    return ClothParams(material=Material(thickness=THICKNESS), iterations=10, substeps=2)


def drag(world, scene: str | None, ticks: int = 45) -> list[tuple[np.ndarray, np.ndarray]]:
    """Both capes' positions at each tick while their shoulders are dragged through each other."""
    a, b = capes()
    ha, hb = world.add(a, params(), scene=scene), world.add(b, params(), scene=scene)
    out = []
    for t in range(ticks):
        s = min(1.0, (t + 1) / 30)
        world.set_pin_targets(ha, PINS, a.rest_positions[PINS] + [0, 0, 0.3 * s])
        world.set_pin_targets(hb, PINS, b.rest_positions[PINS] - [0, 0, 0.3 * s])
        world.step(DT)
        f = world.fetch()
        out.append((f.positions[ha].astype(np.float64), f.positions[hb].astype(np.float64)))
    return out


def pairs_left(states) -> list[int]:
    return [scene_penetration([x, y], [THICKNESS, THICKNESS]).pairs for x, y in states]


def test_reference_capes_dragged_through_each_other():
    """Penetration 0 at the end of every tick in one scene; > 0 without the scene."""
    assert max(pairs_left(drag(ReferenceWorld(), "arena"))) == 0
    assert max(pairs_left(drag(ReferenceWorld(), None))) > 0


@pytest.mark.parametrize(("solver", "lanes"), [("workgroup", 0), ("workgroup", 4), ("coloured", 0), ("jacobi", 0)])
def test_device_follows_reference(device, solver, lanes):
    """The OpenCL world's inter-cloth collision against the float64 reference (the mode that
    mirrors the solver) through the whole drag, and penetration 0 at every tick; ``lanes`` 4:
    the CPU pack solver (the server's default on a CPU)."""
    mode = {"workgroup": "coloured", "coloured": "batches", "jacobi": "jacobi"}[solver]
    ref = drag(ReferenceWorld(mode), "arena")
    ref32 = drag(ReferenceWorld(mode, np.float32), "arena")
    got = drag(CLWorld(solver, device=device, pack_lanes=lanes), "arena")
    for (x, y), (rx, ry), (fx, fy) in zip(got, ref, ref32, strict=True):
        slack = 3e-4 + 2 * max(np.abs(fx - rx).max(), np.abs(fy - ry).max())
        assert np.abs(x - rx).max() < slack and np.abs(y - ry).max() < slack
    assert max(pairs_left(got)) == 0


def test_scenes_isolate(device):
    """A cloth in scene A moves exactly as it does alone, whatever cloths of scene B overlap it."""
    for make in (ReferenceWorld, lambda: CLWorld("workgroup", device=device, pack_lanes=0)):
        alone, crowded = make(), make()
        a, b = capes()
        ha = alone.add(a, params(), scene="A")
        hc = crowded.add(a, params(), scene="A")
        crowded.add(b, params(), scene="B")
        crowded.add(
            cook_grid(N, N, 0.5, 0.5, pinned=PINS, orientation="vertical", origin=(-0.25, 1.0, -0.15)),
            params(),
            scene="B",
        )
        for t in range(20):
            for w, h in ((alone, ha), (crowded, hc)):
                w.set_pin_targets(h, PINS, a.rest_positions[PINS] + [0, 0, 0.01 * t])
                w.step(DT)
            np.testing.assert_array_equal(alone.fetch().positions[ha], crowded.fetch().positions[hc])


def test_scene_colliders_act_on_every_cloth():
    """A scene's collider acts on each of its cloths beside their own; it leaves with the scene."""
    from drape.server.sim.params import Features

    w = ReferenceWorld()
    p = ClothParams(features=Features(colliders=True))
    fab = cook_grid(5, 5, 0.4, 0.4, origin=(-0.2, 0.05, -0.2))
    h1, h2 = w.add(fab, p, scene="s"), w.add(fab, p, scene="s")
    w.set_colliders(h1, pack_colliders([Sphere((5.0, 0.0, 0.0), 0.1)]))
    w.set_scene_colliders("s", pack_colliders([Sphere((0.0, -0.5, 0.0), 0.5)]))
    assert len(w.cloths[h1].colliders) == 2 and len(w.cloths[h2].colliders) == 1
    for _ in range(30):
        w.step(DT)
    for h in (h1, h2):
        r = np.linalg.norm(w.state(h).x - [0.0, -0.5, 0.0], axis=1)
        assert r.min() > 0.5 - 1e-6  # every cloth rests on the scene's ball
    w.remove(h1)
    w.remove(h2)
    assert "s" not in w.scenes


def test_no_scene_builds_nothing(device):
    """Without a scene of two cloths the inter-collision program is neither built nor launched."""
    w = CLWorld("workgroup", device=device, pack_lanes=0)
    a, _ = capes()
    w.add(a, params())
    w.add(a, params(), scene="lonely")
    w.step(DT)
    assert w.scene_collision.n_cloths == 0
    assert not device.built(w.scene_collision.options, SOURCE) or w.scene_collision._kernels is None


def test_moving_scene_colliders_on_the_device(device):
    """A scene's ball rising under its two cloths every tick (the per-tick move, which the device
    writes for every cloth at once) moves them as the reference's per-cloth rows do."""
    from drape.server.sim.params import Features

    p = ClothParams(features=Features(colliders=True), material=Material(thickness=THICKNESS), iterations=10)
    fab = cook_grid(9, 9, 0.4, 0.4, pinned=[0, 8], origin=(-0.2, 1.0, -0.2))
    out = []
    # the float64 reference, the same in float32 (how far float32 alone strays: with colliders the
    # continuous test's contact times amplify rounding), the device
    for w in (ReferenceWorld(), ReferenceWorld(dtype=np.float32), CLWorld("workgroup", device=device, pack_lanes=0)):
        hs = [w.add(fab, p, scene="s"), w.add(fab, p, scene="s")]
        w.set_colliders(hs[1], pack_colliders([Sphere((5.0, 0.0, 0.0), 0.1)]))  # its own, before the scene's
        got = []
        for t in range(25):
            w.set_scene_colliders("s", pack_colliders([Sphere((0.0, 0.6 + 0.02 * t, 0.0), 0.3)]))
            w.step(DT)
            got.append([w.fetch().positions[h].astype(np.float64) for h in hs])
        out.append(got)
    ref, f32, dev = (np.array(o) for o in out)
    atol = 1e-4 + 2 * float(np.abs(f32 - ref).max())  # as test_ccd.py (PoCL: device 1.5e-4, float32 7e-5)
    np.testing.assert_allclose(dev, ref, atol=atol, rtol=0)
    assert dev[-1][0][:, 1].max() > 1.05  # the ball lifted them


def test_a_thickness_changed_by_a_control_reaches_the_device(device):
    """A scene cloth's material changed on the fly (0 thickness: no contact, then 3 cm) changes
    the device's scene tables as it changes the reference's contacts."""
    out = []
    for w in (ReferenceWorld(), CLWorld("workgroup", device=device, pack_lanes=0)):
        a, b = capes()
        thin = ClothParams(material=Material(thickness=0.0), iterations=10, substeps=2)
        ha, hb = w.add(a, thin, scene="s"), w.add(b, thin, scene="s")
        got = []
        for t in range(40):
            if t == 10:
                for h in (ha, hb):
                    w.set_params(h, params())
            s = min(1.0, (t + 1) / 30)
            w.set_pin_targets(ha, PINS, a.rest_positions[PINS] + [0, 0, 0.3 * s])
            w.set_pin_targets(hb, PINS, b.rest_positions[PINS] - [0, 0, 0.3 * s])
            w.step(DT)
            f = w.fetch()
            got.append((f.positions[ha].astype(np.float64), f.positions[hb].astype(np.float64)))
        out.append(got)
    for (rx, ry), (x, y) in zip(*out, strict=True):
        assert np.abs(x - rx).max() < 1e-3 and np.abs(y - ry).max() < 1e-3
    assert max(pairs_left(out[1][10:])) == 0


def test_vertices_with_more_candidates_than_listed_follow_the_reference(device):
    """Three coarse cloths stacked 1 cm apart with a 20 cm thickness: every vertex has more
    candidates than the device lists (IC_LIST), so each pass walks the hash for it instead;
    the device still follows the float64 reference, and the count buffer says the walk ran."""
    from drape.server.sim.opencl.scenes import IC_LIST

    thick = ClothParams(material=Material(thickness=0.2), iterations=4)
    fabs = [cook_grid(6, 6, 0.3, 0.3, pinned=[0, 5], origin=(0.0, 1.0 + 0.01 * i, 0.0)) for i in range(3)]
    ref, ref32 = ReferenceWorld("coloured"), ReferenceWorld("coloured", np.float32)
    dev = CLWorld("workgroup", device=device, pack_lanes=0)
    hs = [[w.add(f, thick, scene="pile") for f in fabs] for w in (ref, ref32, dev)]
    sc, most = dev.scene_collision, 0
    for _ in range(10):
        for w in (ref, ref32, dev):
            w.step(DT)
        most = max(most, int(sc._count.read(0, sc.n_vertices)[:, 0].max()))  # the step's last round's
        for hr, h32, hd in zip(*hs, strict=True):
            rx, fx, x = ref.positions(hr), ref32.positions(h32), dev.positions(hd)
            assert np.abs(x - rx).max() < 3e-4 + 2 * np.abs(fx - rx).max()
    assert most > IC_LIST


def test_a_step_is_the_same_launches_whatever_the_scenes(device):
    """The scenes' step enqueues INTER_COLLISION_PASSES + 5 x INTER_COLLISION_ROUNDS - 1 kernels whose
    arguments were set when the tables changed, for 2 scenes as for 6 (no launch, and no Python,
    per scene or cloth)."""
    from drape.server.sim.scenes import INTER_COLLISION_PASSES, INTER_COLLISION_ROUNDS

    fab = cook_grid(5, 5, 0.2, 0.2, pinned=[0, 4])
    counts = []
    for scenes in (2, 6):
        w = CLWorld("workgroup", device=device, pack_lanes=0)
        for s in range(scenes):
            for j in range(3):
                w.add(fab, params(), positions=fab.rest_positions + [0.05 * j, 0.0, 5.0 * s], scene=f"s{s}")
        w.step(DT)
        counts.append(len(w.scene_collision._launches))
        w.close()
    # each round: bounds, active, insert, find (which runs the round's first pass), finish
    assert counts == [INTER_COLLISION_PASSES + 5 * INTER_COLLISION_ROUNDS - 1] * 2  # ic_rewalk: later rounds


def test_the_gpus_later_round_lists_give_the_same_positions(device, monkeypatch):
    """A GPU's shape (ic_insert's lists appended a work-group of IC_CG at a time after a scan,
    ic_refind over the list of the unmoved: IC_KEPT; the scene's vertices in Morton order:
    IC_MORTON), forced on this device, moves the capes as the CPU's (one atomic a walker, ic_refind
    over every vertex, the fabric's order) does, through the drag."""
    from drape.server.sim.opencl import scenes as cl_scenes

    kind = "gpu" if device.info.is_gpu else "cpu"
    runs = []
    for cg, kept in ((1, False), (256, True)):
        monkeypatch.setitem(cl_scenes.IC_CG, kind, cg)
        monkeypatch.setitem(cl_scenes.IC_KEPT, kind, kept)
        monkeypatch.setitem(cl_scenes.IC_MORTON, kind, kept)
        w = CLWorld("workgroup", device=device, pack_lanes=0)
        runs.append(drag(w, "s", ticks=35))
        assert f"-DIC_CG={cg}" in w.scene_collision.options and f"-DIC_KEPT={int(kept)}" in w.scene_collision.options
        w.close()
    assert max(pairs_left(runs[0])) == 0 and max(pairs_left(runs[1])) == 0
    for (a0, b0), (a1, b1) in zip(*runs, strict=True):  # summed in another order at most
        assert np.abs(a0 - a1).max() < 1e-5 and np.abs(b0 - b1).max() < 1e-5


@pytest.mark.parametrize("solver", ["reference", "workgroup", "coloured", "jacobi"])
def test_a_pile_of_scene_cloths_rests_on_a_plane(device, solver):
    """The penetration tool's scene_stack (8 9 x 9 cloths of one scene dropped onto a plane, each
    landing at 4 cm a tick, its contact distance): 0 scene pairs inside the contact distance and 0
    vertices behind the plane at the end of every tick, on the reference and the device alike
    (before: up to 486 pairs and the bottom cloth's 81 vertices behind the plane)."""
    world = ReferenceWorld() if solver == "reference" else CLWorld(solver, device=device)
    ticks = list(pen.SCENARIOS["scene_stack"](world, pen.SIZES["small"]))
    records = [pen.measure(t) for t in ticks]
    assert [(r.tick, r.scene_pairs, r.behind) for r in records if r.scene_pairs or r.behind] == []
    # and it rests: 8 layers a contact distance (3.9 cm) apart, none flung off the pile
    assert max(float(x[:, 1].max()) for x in ticks[-1].x) < 0.32
