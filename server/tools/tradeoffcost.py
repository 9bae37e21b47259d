"""``drape tradeoff --costs``: each quality preset's cost as it runs, in multiples of PBD-10.

Full packs of the hanging 64 x 64 cloth (on a CPU device: the pack solver's lanes times the
device's compute units, so every core steps a full pack; on a GPU: ``--cost-cloths``, default
256), one world per configuration, all in one process, timed in interleaved rounds: each round
steps every configuration one frame in turn, ``frames`` times (the order rotating from round to
round), takes each one's median ms of step + blocking fetch and divides it by the PBD-10
world's median of the same round. A neighbour's load that lands on one round lands on both sides of its ratios; the
median over rounds is the cost, the min and max its spread.

The result is written to the presets' cost file (``drape.server.sim.quality.COSTS_FILE``,
``server/sim/preset_costs.json``), under the device's kind (``cpu`` or ``gpu``; a moving scene's,
``--cost-scene flag``, whose presets run their moving settings, under ``cpu-moving`` or
``gpu-moving``: ``quality.MOVING_KIND``), which ``quality.PRESETS`` and ``QualityGovernor`` read;
never typed in by hand.
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
from ..sim.quality import MOVING_KIND, is_moving
from .tradeoffrun import Config, make_scene, simulate

log = logging.getLogger(__name__)

COST_SIZE = 64
COST_ROUNDS = 7
COST_FRAMES = 24
COST_WARMUP = 4
GPU_CLOTHS = 256
BASELINE = Config("workgroup", 10, 1, False, False, tag="pbd10")


def cost_configs(extra: list[Config] | None = None, base: ClothParams | None = None) -> dict[str, Config]:
    """PBD-10, every preset (with the substeps it gives a cloth like ``base``: a moving one's where
    it has wind or colliders), and any ``extra`` configurations (by their description)."""
    from ..sim.quality import PRESETS

    out = {"pbd10": BASELINE}
    for name in PRESETS:
        out[name] = Config.from_preset(name, base=base)
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
    accuracy: bool = False,
    scene_name: str = "hanging",
) -> dict[str, Any]:
    """Interleaved rounds of every configuration against PBD-10 (module docstring), on
    ``scene_name`` (hanging by default; a moving scene's pins and colliders stay where they are
    at t = 0, which costs what they cost in motion)."""
    from ..sim import make_world
    from ..sim.opencl.device import Device

    scene = make_scene(scene_name, size)
    configs = cost_configs(extra, scene.params)
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
                    h = w.add(scene.fabric, cfg.apply(_base(scene)), scene.positions)
                    lanes.append(max(1, w.groups[w.rec[h].group].pack))
                    w.remove(h)
                n = max(lanes) * int(dev.info.compute_units)
        assert n is not None
        for name, cfg in configs.items():
            w = worlds[name]
            params = cfg.apply(_base(scene))
            for _ in range(n):
                h = w.add(scene.fabric, params, scene.positions)
                if scene.motion is not None:
                    targets, colliders = scene.motion(0.0)
                    w.set_pin_targets(h, scene.pins, targets)
                    w.set_colliders(h, colliders)
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
        strains: dict[str, dict[str, float]] = {}
        if accuracy:  # one cloth of each configuration over 2 s on this device (float32)
            for name, cfg in configs.items():
                m = simulate(scene, cfg, device=dev, encodings=("float32",))
                strains[name] = {
                    "max_strain": m.metrics["float32"]["max_strain"],
                    "mean_strain": m.metrics["float32"]["mean_strain"],
                    "finite": m.finite,
                }
        lanes_used = {k: worlds[k].groups[next(iter(worlds[k].groups))].pack for k in names}
    finally:
        for w in worlds.values():
            w.close()
    base = np.array(ms["pbd10"])
    out: dict[str, Any] = {
        "kind": kind,
        "moving": is_moving(scene.params),
        "device": dev_name,
        "scene": f"{scene_name} {size} x {size}, 60 Hz",
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
            "iterations": configs[name].iterations,
            "substeps": configs[name].substeps,
            "ms": [round(x, 4) for x in ms[name]],
            "ratios": [round(x, 4) for x in ratio.tolist()],
            "cost": round(float(np.median(ratio)), 3),
            "min": round(float(ratio.min()), 3),
            "max": round(float(ratio.max()), 3),
            **strains.get(name, {}),
        }
    return out


def _base(scene) -> ClothParams:
    p = scene.params
    return replace(p, material=replace(p.material, tether_limit=Material().tether_limit))


def write_costs(result: dict[str, Any], path: Path | None = None) -> Path:
    """Store ``result`` under its kind in the presets' cost file (other kinds kept): a moving
    scene's under ``quality.MOVING_KIND`` of its kind."""
    from ..sim.quality import COSTS_FILE

    path = Path(path) if path is not None else COSTS_FILE
    data = json.loads(path.read_text()) if path.exists() else {}
    kind = result["kind"]
    data[MOVING_KIND.format(kind=kind) if result.get("moving") else kind] = result
    path.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    return path


# targets of issue 24 on the hanging 64 x 64: (name, cost at most, max stretch, mean stretch)
TARGETS = (("fast", 1.0, 0.50, 0.015), ("balanced", 3.0, 0.10, 0.003))


def plot_front(result: dict[str, Any], path: Path, title: str = "") -> Path:
    """Two panels, max and mean structural stretch against cost in multiples of PBD-10 (median of
    the interleaved rounds, bars from their min to max), log-log: the measured configurations as
    labelled front points, the presets as distinct markers on top, the issue's targets as lines
    (each up to its cost bound)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfgs = result["configs"]
    scene = result.get("scene", "hanging 64 x 64").split(",")[0]
    hanging = scene.startswith("hanging")  # the targets are the hanging cloth's
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    markers = {"fast": "o", "balanced": "s", "accurate": "D", "exact": "^", "pbd10": "X"}
    for ax, key, label in zip(
        axes, ("max_strain", "mean_strain"), ("max structural stretch", "mean structural stretch"), strict=True
    ):
        front = [(n, c) for n, c in cfgs.items() if n not in markers and key in c]
        front.sort(key=lambda nc: nc[1]["cost"])
        if front:
            x = [c["cost"] for _, c in front]
            y = [100 * c[key] for _, c in front]
            err = [[c["cost"] - c["min"] for _, c in front], [c["max"] - c["cost"] for _, c in front]]
            ax.errorbar(x, y, xerr=err, fmt="-", color="0.55", marker=".", ms=6, lw=1, capsize=2, zorder=2)
            for (n, _c), xi, yi in zip(front, x, y, strict=True):
                short = n.replace("workgroup xpbd ", "").replace(" +tethers 60Hz", "").replace("it x ", "x")
                short = short.replace("ss", "")
                ax.annotate(short, (xi, yi), textcoords="offset points", xytext=(4, 4), fontsize=7, color="0.3")
        for n, mk in markers.items():
            c = cfgs.get(n)
            if c is None or key not in c:
                continue
            err = [[c["cost"] - c["min"]], [c["max"] - c["cost"]]]
            ax.errorbar(
                [c["cost"]],
                [100 * c[key]],
                xerr=err,
                fmt=mk,
                ms=9,
                capsize=3,
                zorder=5,
                label=f"{n} ({c['describe'].replace('workgroup ', '').replace(' 60Hz', '')})",
            )
        for (n, cmax, mx, mean), col in zip(TARGETS if hanging else (), ("tab:red", "tab:purple"), strict=False):
            t = 100 * (mx if key == "max_strain" else mean)
            ax.plot([0.5, cmax], [t, t], ls="--", color=col, lw=1)
            ax.axvline(cmax, ls=":", color=col, lw=0.8)
            ax.annotate(f"{n} target", (cmax, t), textcoords="offset points", xytext=(-60, 4), fontsize=7, color=col)
        ax.set_xscale("log")
        ax.set_xlim(left=0.5)
        ax.set_yscale("log")
        ax.set_xlabel("cost, x PBD-10 (median of interleaved rounds; bars: min..max)")
        ax.set_ylabel(f"{label}, % ({scene}, 2 s)")
        ax.grid(True, which="both", alpha=0.25)
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(
        title or f"{result['kind'].upper()}: {result['device']}, {result['cloths']} cloths per world", fontsize=10
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
