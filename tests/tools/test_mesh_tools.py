"""Smoke runs of the mesh colliders' tools as a user types them (real processes, real OpenCL on
PoCL): the cost benchmark writes its records, the demo writes a GIF and frames."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from PIL import Image

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)


def tool(name: str, *args: str) -> str:
    r = subprocess.run(
        [sys.executable, "-m", f"drape.server.tools.{name}", *args], capture_output=True, text=True, timeout=240
    )
    assert r.returncode == 0, f"{name} {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r.stdout


def test_meshbench_writes_every_case(tmp_path):
    out = tmp_path / "mesh.json"
    args = ("--cloths", "2", "--frames", "2", "--rounds", "1", "--cells", "0.08", "--into", "0.08")
    tool("meshbench", *args, "--json", str(out))
    records = json.loads(out.read_text())
    assert [r["extra"]["features"] for r in records] == ["none", "mesh"]
    assert records[1]["extra"]["triangles"] > 0 and records[1]["extra"]["vs_none"] > 0
    assert records[1]["extra"]["into"] == 0.08


def test_meshdemo_writes_a_gif_and_frames(tmp_path):
    out = tmp_path / "demo"
    tool("meshdemo", "--ticks", "6", "--every", "3", "--size", "96", "--out", str(out))
    gif = Image.open(out.with_suffix(".gif"))
    assert gif.size == (96, 96) and gif.n_frames == 2
    assert len(list(tmp_path.glob("demo_*.png"))) >= 1
