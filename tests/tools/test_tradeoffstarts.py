"""``python -m drape.server.tools.tradeoffstarts``: a scene's strains over jittered starts (the
medians docs/accuracy.md compares presets by)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drape.server.sim.quality import PRESETS
from drape.server.tools import tradeoffstarts
from drape.server.tools.tradeoffrun import make_scene

pytestmark = pytest.mark.opencl


def test_starts_are_the_scene_own_then_jittered_within_the_bound():
    scene = make_scene("cape", 4)
    assert tradeoffstarts.jittered(scene, 0) is scene
    x0 = scene.positions
    x1 = tradeoffstarts.jittered(scene, 1).positions
    free = ~scene.fabric.pinned
    assert np.array_equal(x1[~free], x0[~free])
    assert 0 < np.abs(x1[free] - x0[free]).max() <= tradeoffstarts.JITTER_M
    assert np.array_equal(x1, tradeoffstarts.jittered(scene, 1).positions)  # seeded


def test_every_start_runs_and_prints_one_line_per_scene_and_configuration(tmp_path, capsys):
    out = tmp_path / "starts.json"
    args = ["--scenes", "curtain", "--size", "4", "--configs", "pbd,1x2,fast", "--starts", "2", "--out", str(out)]
    assert tradeoffstarts.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    fast = PRESETS["fast"]
    moving = f"{fast.iterations_for(make_scene('curtain', 4).params)}x{fast.moving_substeps}"
    assert [ln.split()[:2] for ln in lines] == [["curtain4", "pbd"], ["curtain4", "1x2"], ["curtain4", moving]]
    runs = json.loads(out.read_text())
    assert [len(r["max"]) for r in runs] == [2, 2, 2]
    assert all(np.isfinite(r["max"]).all() and min(r["mean"]) >= 0 for r in runs)
