"""tickbench (issue 21): the tick thread's host stages timed on a small load, host-only and on
the OpenCL device, every stage reported (no timed assertion: figures live in docs/)."""

from __future__ import annotations

import json
import os

import pytest

from drape.server.tools import tickbench


def _medians(path) -> dict[int, dict[str, float]]:
    return {r["cloths"]: r["median_ms"] for r in json.loads(path.read_text())["runs"]}


def test_host_stages_without_a_device(tmp_path, capsys):
    out = tmp_path / "tick.json"
    assert (
        tickbench.main(["--no-device", "--cloths", "8", "70", "--side", "4", "--repeat", "2", "--json", str(out)]) == 0
    )
    med = _medians(out)
    assert set(med) == {8, 70}
    assert set(med[70]) == {"roster", "plan", "follow", "decide"}
    assert "roster" in capsys.readouterr().out


@pytest.mark.opencl
@pytest.mark.parametrize("encoding", ["predictive", "quant16"])
def test_every_stage_on_the_device(tmp_path, encoding):
    out = tmp_path / "tick.json"
    args = [
        "--cloths",
        "70",
        "--side",
        "4",
        "--bundle",
        "16",
        "--repeat",
        "2",
        "--encoding",
        encoding,
        "--watch-rate",
        "2",
    ]
    args += ["--json", str(out)] + (["--device", os.environ["DRAPE_DEVICE"]] if "DRAPE_DEVICE" in os.environ else [])
    assert tickbench.main(args) == 0
    assert set(_medians(out)[70]) == set(tickbench.STAGES)
