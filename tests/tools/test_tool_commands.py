"""Smoke runs of the ``drape`` tool subcommands as a user types them (each a real process: real
OpenCL on PoCL, a real server and Zenoh for the demo), checking what they write, and the clear
message a tool gives when its extra is not installed."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from drape.server.tools.procs import free_port, require_extra

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def drape(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(
        [sys.executable, "-m", "drape.server.cli", *args], capture_output=True, text=True, timeout=timeout
    )
    assert r.returncode == 0, f"drape {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}"
    return r


def test_devices_names_the_chosen_one():
    assert "chosen: " in drape("devices").stdout


def test_bench_quick_writes_its_records(tmp_path):
    out = tmp_path / "bench.json"
    drape("bench", "seed", "--quick", "--solvers", "workgroup", "--quiet", "--json", str(out))
    records = json.loads(out.read_text())
    assert [r["solver"] for r in records] == ["no-solver", "workgroup"]
    assert all(r["ms_per_frame"] > 0 for r in records)


def test_tradeoff_quick_writes_records_and_plots(tmp_path):
    drape(
        "tradeoff",
        "--quick",
        "--solvers",
        "workgroup",
        "--duration",
        "0.2",
        "--timing-rounds",
        "1",
        "--ref-substeps",
        "4",
        "--ref-iterations",
        "4",
        "--jobs",
        "1",
        "--quiet",
        "--out",
        str(tmp_path),
    )
    records = json.loads((tmp_path / "tradeoff.json").read_text())
    assert any(r["solver"] == "workgroup" and np.isfinite(r["max_strain"]) for r in records)
    plots = sorted(tmp_path.glob("tradeoff-*.png"))
    assert plots
    for p in plots:
        with Image.open(p) as im:
            assert im.size == (1000, 640)


def test_demo_writes_frames_and_a_gif(tmp_path):
    r = drape(
        "demo",
        "--seconds",
        "1.5",
        "--fps",
        "10",
        "--size",
        "200x125",
        "--port",
        str(free_port()),
        "--out",
        str(tmp_path),
    )
    assert "received" in r.stdout
    frames = sorted(tmp_path.glob("frame_*.png"))
    assert len(frames) >= 5
    with Image.open(frames[-1]) as im:
        assert im.size == (200, 125)
        rgb = np.asarray(im.convert("RGB")).astype(int)
    # the flag (red), curtain (blue) and cape (purple) are all in view
    assert ((rgb[..., 0] > 120) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)).sum() > 50
    assert (rgb[..., 2] - rgb[..., 0] > 60).sum() > 50
    with Image.open(tmp_path / "drape-demo.gif") as gif:
        assert gif.n_frames == len(frames) and gif.size == (200, 125)


def test_demo_crossing_writes_two_capes(tmp_path):
    """``drape demo --stage crossing``: two clients' capes in one scene, as frames and a GIF."""
    r = drape(
        "demo",
        "--stage",
        "crossing",
        "--seconds",
        "1.0",
        "--fps",
        "10",
        "--size",
        "200x125",
        "--port",
        str(free_port()),
        "--out",
        str(tmp_path),
    )
    assert "alice" in r.stdout and "bob" in r.stdout
    frames = sorted(tmp_path.glob("crossing_*.png"))
    assert len(frames) >= 3
    with Image.open(frames[-1]) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    assert (rgb[..., 2] - rgb[..., 0] > 60).sum() > 20  # alice's blue cape
    assert (rgb[..., 1] - rgb[..., 0] > 30).sum() > 20  # bob's green one
    with Image.open(tmp_path / "drape-crossing.gif") as gif:
        assert gif.n_frames == len(frames)


def test_demo_body_writes_a_cape_on_a_body_mesh(tmp_path):
    """``drape demo --stage body``: a cape on a body sent as a 1.8 mesh collider and moved by a
    pose per tick, received over Zenoh, as frames and a GIF, with the vertices left inside."""
    r = drape(
        "demo",
        "--stage",
        "body",
        "--seconds",
        "0.5",
        "--fps",
        "10",
        "--size",
        "120x120",
        "--port",
        str(free_port()),
        "--out",
        str(tmp_path),
    )
    assert "received 30 states over Zenoh" in r.stdout and "vertices inside the body: at most" in r.stdout
    frames = sorted(tmp_path.glob("body_*.png"))
    assert len(frames) == 5
    with Image.open(frames[-1]) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    assert (rgb[..., 0] - rgb[..., 2] > 40).sum() > 20  # the red cape
    with Image.open(tmp_path / "drape-body.gif") as gif:
        assert gif.n_frames == len(frames) and gif.size == (120, 120)


def test_tradeoff_collision_writes_its_table(tmp_path):
    """``drape tradeoff --collision`` on the small scenarios: a record per scenario and setting."""
    r = drape(
        "tradeoff",
        "--collision",
        "--collision-scenarios",
        "capsule_hit",
        "--collision-substeps",
        "1,2",
        "--collision-passes",
        "2",
        "--collision-size",
        "small",
        "--out",
        str(tmp_path),
    )
    assert "| substeps | self-collision |" in r.stdout
    records = json.loads((tmp_path / "tradeoff-collision.json").read_text())
    assert len(records) == 4 and all(rec["max_crossed"] == 0 for rec in records)
    assert (tmp_path / "tradeoff-collision.png").exists()


def test_a_missing_extra_is_named():
    with pytest.raises(
        SystemExit,
        match=r"drape top needs the 'tools' extra \(no_such_module_x not installed\): "
        r"pip install 'drape-cloth\[tools\]'",
    ):
        require_extra("tools", "top", ["json", "no_such_module_x"])
    require_extra("tools", "top", ["json"])  # present: nothing happens


def test_version_names_the_distribution_and_the_protocol(capsys):
    """``drape --version``: the installed drape-cloth's version and the wire protocol's; exit 0."""
    from importlib import metadata

    from drape.client.protocol.keys import PROTOCOL_VERSION
    from drape.server import DISTRIBUTION
    from drape.server.cli import main

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == (
        f"drape {metadata.version(DISTRIBUTION)} (protocol {PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]})"
    )


def test_tradeoff_truth_cache_key_follows_the_reference_sources(tmp_path):
    """The ground-truth cache is keyed by the sources it depends on (server/sim): every one of them
    exists, and the key is not the digest of nothing (a cache that never goes stale)."""
    import hashlib
    from pathlib import Path

    from drape.server.tools import tradeofftruth as tt

    sim = Path(tt.__file__).resolve().parent.parent / "sim"
    assert all((sim / name).is_file() for name in tt.TRUTH_SOURCES)
    key = tt.truth_path(tmp_path, "drape", 8, 1.0, 1, 10).name
    assert hashlib.sha1().hexdigest()[:12] not in key
    assert tt._source_digest() in key


def test_decodebench_runs_and_checks_its_paths_agree(tmp_path):
    """A tiny decodebench: it checks the per-entry, whole-bundle and SDK paths decode the same
    bits before timing them (a mismatch is a non-zero exit), and writes its JSON."""
    import json
    import subprocess
    import sys

    out = tmp_path / "d.json"
    cmd = [sys.executable, "-m", "drape.server.tools.decodebench", "--states", "8", "--side", "5"]
    cmd += ["--repeat", "3", "--warmup", "1", "--json", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    assert json.loads(out.read_text())


def test_putbench_copies_under_each_heap_setting(tmp_path):
    """A tiny putbench --copies-only: each heap setting in its own process, a result for each."""
    import json
    import subprocess
    import sys

    out = tmp_path / "p.json"
    cmd = [sys.executable, "-m", "drape.server.tools.putbench", "--copies-only", "--messages", "2", "--mb", "0.2"]
    cmd += ["--seconds", "0.2", "--rounds", "1", "--json", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    doc = json.loads(out.read_text())
    assert set(doc["results"]) == {"glibc", "mmap", "drape"}
    assert all(r[0]["ticks"] > 0 and r[0]["median_ms"] > 0 for r in doc["results"].values())
