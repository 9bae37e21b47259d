"""Quality presets costed as they run: costs and strains come from the cost file that
`drape tradeoff --costs` writes, only where its record has the preset's own settings."""

from __future__ import annotations

import json
import math

from drape.server.sim import quality
from drape.server.tools.tradeoffcost import write_costs


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
    for name, it, ss, _ in quality._SETTINGS:
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
