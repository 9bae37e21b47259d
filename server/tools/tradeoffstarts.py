"""Scenes' strains over jittered starts: ``python -m drape.server.tools.tradeoffstarts``.

The max strain of a moving scene (flag, cape, curtain) is chaotic: moving every free vertex by
10 um at the start moves a run's max by tens of per cent, so one run's max is one draw. This
command runs each scene under each configuration from K starts (the scene's own, then K - 1 with
every free vertex moved by up to ``--jitter`` metres, uniform, seed k) and prints the median and
the range of the max and mean structural stretch over the 2 s (float32 on the device, 60 Hz;
tradeoffrun.simulate), one line per scene and configuration:

    curtain32 1x80   max   76.71 (74.9..85.7)  mean  1.118 (1.103..1.125)

Configurations: ``ITxSS`` (XPBD, compliance 0, tethers: the presets' solver), ``pbd`` (PBD,
10 iterations, 1 substep) or a preset's name (its substeps for the scene's features). docs/accuracy.md
("The scenes") compares presets by these medians; ``--out F.json`` keeps every run.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
from dataclasses import replace
from pathlib import Path

import numpy as np

from .procs import csv_list
from .tradeoffrun import Config, Scene, make_scene, simulate

log = logging.getLogger(__name__)

JITTER_M = 1e-5  # the largest start offset of a free vertex (10 um)


def parse_config(text: str, scene: Scene, solver: str) -> Config:
    """``ITxSS`` (XPBD + tethers), ``pbd`` (PBD-10) or a preset's name, on ``scene``'s cloth."""
    if text == "pbd":
        return Config(solver, 10, 1, tag="pbd10")
    if "x" in text:
        it, ss = (int(v) for v in text.split("x"))
        return Config(solver, it, ss, xpbd=True, tethers=True, tag=text)
    return Config.from_preset(text, solver, base=scene.params)


def jittered(scene: Scene, seed: int, jitter: float = JITTER_M) -> Scene:
    """``scene`` from its own start (seed 0) or with every free vertex moved by up to ``jitter``."""
    if seed == 0:
        return scene
    x = (scene.positions if scene.positions is not None else scene.fabric.rest_positions).astype(np.float64)
    rng = np.random.default_rng(seed)
    free = ~scene.fabric.pinned
    x = x.copy()
    x[free] += rng.uniform(-jitter, jitter, (int(free.sum()), 3))
    return replace(scene, positions=x)


def summary(values: list[float]) -> str:
    return f"{statistics.median(values):7.2f} ({min(values):.1f}..{max(values):.1f})"


def run_starts(scene: Scene, cfg: Config, starts: int, jitter: float = JITTER_M) -> list[tuple[float, float]]:
    """(max %, mean %) of ``cfg`` on ``scene`` from ``starts`` starts."""
    out = []
    for k in range(starts):
        r = simulate(jittered(scene, k, jitter), cfg, encodings=("float32",))
        m = r.metrics["float32"]
        out.append((100.0 * m["max_strain"], 100.0 * m["mean_strain"]))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tradeoffstarts", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=csv_list, default=["cape", "flag", "curtain"])
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--configs", type=csv_list, default=["1x80", "2x100"], help="ITxSS, pbd or a preset's name")
    ap.add_argument("--starts", type=int, default=15)
    ap.add_argument("--jitter", type=float, default=JITTER_M, help="metres")
    ap.add_argument("--solver", default="workgroup")
    ap.add_argument("--out", type=Path, help="every run as JSON")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    runs = []
    for name in a.scenes:
        scene = make_scene(name, a.size)
        for text in a.configs:
            cfg = parse_config(text, scene, a.solver)
            res = run_starts(scene, cfg, a.starts, a.jitter)
            mx = [r[0] for r in res]
            mean = [r[1] for r in res]
            label = f"{cfg.iterations}x{cfg.substeps}" if cfg.xpbd else "pbd"
            print(
                f"{scene.label} {label:6s} max {summary(mx)}  mean {statistics.median(mean):6.3f} "
                f"({min(mean):.3f}..{max(mean):.3f})  [{text}, K = {a.starts}]",
                flush=True,
            )
            runs.append(
                {
                    "scene": scene.label,
                    "config": text,
                    "iterations": cfg.iterations,
                    "substeps": cfg.substeps,
                    "xpbd": cfg.xpbd,
                    "max": mx,
                    "mean": mean,
                }
            )
    if a.out:
        a.out.write_text(json.dumps(runs, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
