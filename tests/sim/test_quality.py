"""Quality presets costed as they run: costs and strains come from the cost file that
`drape tradeoff --costs` writes, only where its record has the preset's own settings; a cloth in the
wind or among colliders gets the preset's moving substeps."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest

from drape.server.sim import quality
from drape.server.sim.params import ClothParams, Features
from drape.server.tools.tradeoffcost import write_costs
from drape.server.tools.tradeoffrun import Config, make_scene


def _record(kind: str, configs: dict) -> dict:
    return {"kind": kind, "device": "test", "cloths": 1, "rounds": 1, "configs": configs}


def test_presets_take_cost_and_strain_from_the_cost_file_only_for_their_own_settings(tmp_path, monkeypatch):
    path = tmp_path / "costs.json"
    monkeypatch.setattr(quality, "COSTS_FILE", path)
    fast = quality._SETTINGS[0]
    good = {"cost": 0.9, "min": 0.8, "max": 1.0, "iterations": fast[1], "substeps": fast[2]}
    good |= {"max_strain": 0.3, "mean_strain": 0.01}
    stale = {"cost": 7.0, "min": 7.0, "max": 7.0, "iterations": 1, "substeps": 999}
    write_costs(_record("cpu", {"fast": good, "balanced": stale}), path)
    write_costs(_record("gpu", {"fast": dict(good, cost=1.3)}), path)
    assert set(json.loads(path.read_text())) == {"cpu", "gpu"}  # one kind's run keeps the other's
    p = quality._preset(*fast)
    assert (p.cost, p.max_strain, p.mean_strain) == (0.9, 0.3, 0.01)
    assert quality._preset(*fast, kind="gpu").cost == 1.3
    bal = quality._SETTINGS[1]
    b = quality._preset(*bal)  # a record of other settings is not this preset's cost
    assert b.cost == bal[1] * bal[2] / 10.0 and math.isnan(b.max_strain)
    gov = quality.QualityGovernor("balanced", kind="gpu")
    assert gov.cost["fast"] == 1.3


def test_the_governor_predicts_with_the_measured_costs(tmp_path, monkeypatch):
    """From fast up to balanced only when the measured ratio says the next preset fits."""
    path = tmp_path / "costs.json"
    monkeypatch.setattr(quality, "COSTS_FILE", path)
    recs = {}
    for name, it, ss, *_ in quality._SETTINGS:
        recs[name] = {"cost": {"fast": 1.0, "balanced": 5.0}.get(name, 20.0), "min": 0, "max": 0}
        recs[name] |= {"iterations": it, "substeps": ss}
    write_costs(_record("cpu", recs), path)
    gov = quality.QualityGovernor("balanced", budget_ms=16.0, patience=1)
    gov.current = "fast"
    for _ in range(10):  # 3 ms x 5 = 15 ms < 16 ms: predicted to fit, goes up
        gov.update(3.0)
    assert gov.current == "balanced"
    gov.current = "fast"
    recs["balanced"]["cost"] = 6.0  # 3 ms x 6 = 18 ms > 16 ms: stays
    write_costs(_record("cpu", recs), path)
    gov = quality.QualityGovernor("balanced", budget_ms=16.0, patience=1)
    gov.current = "fast"
    for _ in range(10):
        gov.update(3.0)
    assert gov.current == "fast"


def test_the_governor_predicts_a_moving_cloth_with_the_moving_costs(tmp_path, monkeypatch):
    """A moving scene's costs (`drape tradeoff --costs --cost-scene flag`) are stored under the
    kind's moving record, read as the presets' moving_cost only for their moving settings, and
    the governor of moving cloths predicts a step up with them, not with the still cloth's."""
    path = tmp_path / "costs.json"
    monkeypatch.setattr(quality, "COSTS_FILE", path)
    still, moving = {}, {}
    for name, it, ss, mit, mss, _ in quality._SETTINGS:
        still[name] = {"cost": {"fast": 1.0, "balanced": 2.0}.get(name, 20.0), "iterations": it, "substeps": ss}
        moving[name] = {"cost": {"fast": 1.0, "balanced": 6.0}.get(name, 40.0), "iterations": mit, "substeps": mss}
    write_costs(_record("cpu", still), path)
    write_costs(dict(_record("cpu", moving), moving=True), path)
    assert set(json.loads(path.read_text())) == {"cpu", quality.MOVING_KIND.format(kind="cpu")}
    assert quality.costs("cpu")["balanced"] == 2.0 and quality.costs("cpu", moving=True)["balanced"] == 6.0
    bal = quality._preset(*quality._SETTINGS[1])
    assert (bal.cost_for(False), bal.cost_for(True)) == (2.0, 6.0)
    for share, goes_up in ((0.0, True), (1.0, False)):  # 3 ms x 2 = 6 ms fits 8 ms; 3 ms x 6 does not
        gov = quality.QualityGovernor("balanced", budget_ms=8.0, patience=1, headroom=0.6, moving=share)
        gov.current = "fast"
        for _ in range(10):
            gov.update(3.0)
        assert (gov.current == "balanced") is goes_up, share
    assert quality.QualityGovernor(moving=0.5).cost["balanced"] == 4.0
    stale = dict(moving, balanced=dict(moving["balanced"], substeps=999))
    write_costs(dict(_record("cpu", stale), moving=True), path)  # other settings: not this preset's cost
    b = quality._preset(*quality._SETTINGS[1])
    assert b.moving_cost == b.iterations_for(make_scene("flag", 4).params) * b.moving_substeps / 10.0


@pytest.mark.parametrize("feature", quality.MOVING_FEATURES)
def test_a_cloth_in_the_wind_or_among_colliders_gets_the_moving_substeps(feature):
    """Wind and colliders need short steps that tethers do not replace: the preset gives such a
    cloth its moving substeps (scaled with the tick rate like the still ones), and knows it again."""
    still = ClothParams()
    moving = still.with_(features=replace(still.features, **{feature: True}))
    for p in quality.PRESETS.values():
        assert p.moving_substeps >= p.substeps
        assert quality.apply_preset(still, p.name).substeps == p.substeps
        assert quality.apply_preset(moving, p.name).substeps == p.moving_substeps
        assert quality.apply_preset(moving, p.name).iterations == (p.moving_iterations or p.iterations)
        assert quality.apply_preset(still, p.name).iterations == p.iterations
        assert quality.apply_preset(moving, p.name, tick_hz=30).substeps == min(100, 2 * p.moving_substeps)
        assert quality.preset_of(quality.apply_preset(moving, p.name)) == p.name
        assert quality.preset_of(quality.apply_preset(moving, p.name, 120), 120) == p.name
    assert quality.PRESETS["fast"].moving_substeps > quality.PRESETS["fast"].substeps


def test_tradeoff_runs_each_scene_at_the_substeps_its_preset_gives_it():
    """drape tradeoff measures a preset on a scene with the scene's own substeps: the flag (wind),
    cape and curtain (colliders) the moving ones, the hanging cloth the still ones."""
    fast = quality.PRESETS["fast"]
    cfg = Config.from_preset("fast")
    assert cfg.substeps == fast.substeps and Config(tag="x").for_scene(ClothParams()) == Config(tag="x")
    for name in ("flag", "cape", "curtain"):
        assert quality.is_moving(make_scene(name, 4).params)
        assert cfg.for_scene(make_scene(name, 4).params).substeps == fast.moving_substeps
    assert cfg.for_scene(make_scene("hanging", 4).params) == cfg
    assert not quality.is_moving(ClothParams(features=Features(xpbd=True, tethers=True)))


def test_costs_on_a_moving_scene_run_the_presets_moving_substeps(device):
    """`drape tradeoff --costs --cost-scene flag` costs each preset at the settings it gives a flag
    (a moving record: the cost file keeps it beside the hanging cloth's)."""
    from drape.server.tools.tradeoffcost import measure_costs

    res = measure_costs(device=device, rounds=1, frames=2, cloths=2, size=4, scene_name="flag")
    assert res["scene"].startswith("flag 4 x 4") and res["moving"]
    flag = make_scene("flag", 4).params
    for name, p in quality.PRESETS.items():
        assert res["configs"][name]["substeps"] == p.moving_substeps
        assert res["configs"][name]["iterations"] == p.iterations_for(flag)
        assert res["configs"][name]["cost"] > 0
