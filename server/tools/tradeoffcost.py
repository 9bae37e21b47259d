"""``drape tradeoff --costs``: each quality preset's cost as it runs, in multiples of PBD-10.

Full packs of the hanging 64 x 64 cloth (on a CPU device: the pack solver's lanes times the
device's compute units, so every core steps a full pack; on a GPU: ``--cost-cloths``, default
256), one world per configuration, all in one process, timed in interleaved rounds: each round
steps every configuration one frame in turn, ``frames`` times (the order rotating from round to
round), takes each one's median ms of step + blocking fetch and divides it by the PBD-10
world's median of the same round. A neighbour's load that lands on one round lands on both sides of its ratios; the
median over rounds is the cost, the min and max its spread.

The result is written to the presets' cost file (``drape.server.sim.quality.COSTS_FILE``,
``server/sim/preset_costs.json``), under the device's kind (``cpu`` or ``gpu``), which
``quality.PRESETS`` and ``QualityGovernor`` read; never typed in by hand.
"""

from __future__ import annotations

import json
import logging
import statistics
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..sim.params import ClothParams, Material
from .tradeoffrun import Config, make_scene

log = logging.getLogger(__name__)

COST_SIZE = 64
COST_ROUNDS = 7
COST_FRAMES = 24
COST_WARMUP = 4
GPU_CLOTHS = 256
BASELINE = Config("workgroup", 10, 1, False, False, tag="pbd10")


def cost_configs(extra: list[Config] | None = None) -> dict[str, Config]:
    """PBD-10, every preset, and any ``extra`` configurations (by their description)."""
    from ..sim.quality import PRESETS

    out = {"pbd10": BASELINE}
    for name in PRESETS:
        out[name] = Config.from_preset(name)
    for c in extra or []:
        out[c.describe()] = c
    return out


def measure_costs(
    device: str | None = None,
    rounds: int = COST_ROUNDS,
    frames: int = COST_FRAMES,
    cloths: int | None = None,
    extra: list[Config] | None = None,
    size: int = COST_SIZE,
    progress=None,
) -> dict[str, Any]:
    """Interleaved rounds of every configuration against PBD-10 (module docstring)."""
    from ..sim import make_world
    from ..sim.opencl.device import Device

    scene = make_scene("hanging", size)
    configs = cost_configs(extra)
    worlds: dict[str, Any] = {}
    n = cloths
    dev = device if isinstance(device, Device) else Device(device)
    try:
        for name in configs:
            worlds[name] = make_world("workgroup", device=dev)
        probe = worlds["pbd10"]
        gpu = bool(dev.info.is_gpu)
        kind = "gpu" if gpu else "cpu"
        if n is None:
            if gpu:
                n = GPU_CLOTHS
            else:
                lanes = []
                for name, cfg in configs.items():
                    w = worlds[name]
                    h = w.add(scene.fabric, cfg.apply(_base(scene)))
                    lanes.append(max(1, w.groups[w.rec[h].group].pack))
                    w.remove(h)
                n = max(lanes) * int(dev.info.compute_units)
        assert n is not None
        for name, cfg in configs.items():
            w = worlds[name]
            params = cfg.apply(_base(scene))
            for _ in range(n):
                w.add(scene.fabric, params)
            for _ in range(COST_WARMUP):
                w.step(1.0 / cfg.tick_hz)
                w.fetch()
        names = list(configs)
        ms: dict[str, list[float]] = {k: [] for k in names}
        for r in range(rounds):
            order = names[r % len(names) :] + names[: r % len(names)]
            times: dict[str, list[float]] = {k: [] for k in names}
            for _ in range(frames):  # frame by frame, every configuration in turn
                for name in order:
                    w, dt = worlds[name], 1.0 / configs[name].tick_hz
                    t0 = time.perf_counter()
                    w.step(dt)
                    w.fetch()
                    times[name].append(time.perf_counter() - t0)
            for name in names:
                ms[name].append(1e3 * statistics.median(times[name]))
            if progress is not None:
                progress(r + 1, rounds)
        dev_name = getattr(probe, "device_name", "?")
        lanes_used = {k: worlds[k].groups[next(iter(worlds[k].groups))].pack for k in names}
    finally:
        for w in worlds.values():
            w.close()
    base = np.array(ms["pbd10"])
    out: dict[str, Any] = {
        "kind": kind,
        "device": dev_name,
        "scene": f"hanging {size} x {size}, 60 Hz",
        "cloths": n,
        "pack_lanes": lanes_used,
        "rounds": rounds,
        "frames_per_round": frames,
        "pbd10_ms": [round(x, 4) for x in base.tolist()],
        "configs": {},
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    for name in names:
        ratio = np.array(ms[name]) / base
        out["configs"][name] = {
            "describe": configs[name].describe(),
            "ms": [round(x, 4) for x in ms[name]],
            "ratios": [round(x, 4) for x in ratio.tolist()],
            "cost": round(float(np.median(ratio)), 3),
            "min": round(float(ratio.min()), 3),
            "max": round(float(ratio.max()), 3),
        }
    return out


def _base(scene) -> ClothParams:
    p = scene.params
    return replace(p, material=replace(p.material, tether_limit=Material().tether_limit))


def write_costs(result: dict[str, Any], path: Path | None = None) -> Path:
    """Store ``result`` under its kind in the presets' cost file (other kinds kept)."""
    from ..sim.quality import COSTS_FILE

    path = Path(path) if path is not None else COSTS_FILE
    data = json.loads(path.read_text()) if path.exists() else {}
    data[result["kind"]] = result
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    return path
