"""The scenes' device time, kernel by kernel (issue 22: "64 scenes of 64 colliding cloths each at
<= 3x the solver time without scenes"): ``drape bench scenes``' crowds (32 x 32 capes, 1 cm thick,
overlapping their neighbours: contacts every frame) on one World, each frame's inter-cloth
collision kernels timed by their OpenCL events, and the candidates they found.

    python -m drape.server.tools.scenepass [--scenes S,C] [--frames F] [--json FILE]

Each row: a kernel of kernels/intercollide.cl, its median device milliseconds a frame (its
launches summed), its share of the scenes' time and its fastest frame (on a shared CPU the least
disturbed: compare builds by it, in interleaved runs); then the scenes' total, the mean
candidates of a scene vertex and the share of scene vertices with any. On a CPU this steers the
GPU's work (which kernels to cut, by how much), never its ratio: the solver itself runs several
times slower here.
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path

import pyopencl as cl

from ..sim import make_world
from ..sim.opencl import scenes as cl_scenes
from ..sim.params import ClothParams, Material
from .bench import DT, crowds
from .procs import csv_list


class _Recorder:
    """pyopencl as the scenes' part sees it, each launch's event kept (a tool's probe)."""

    def __init__(self) -> None:
        self.events: list[tuple[str, cl.Event]] = []

    def __getattr__(self, name: str) -> object:
        return getattr(cl, name)

    def enqueue_nd_range_kernel(self, queue, kernel, gsize, lsize):  # type: ignore[no-untyped-def]
        ev = cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize)
        self.events.append((kernel.function_name, ev))
        return ev


def _ms(ev: cl.Event) -> float:
    return (ev.profile.end - ev.profile.start) * 1e-6


def profile(scenes: int, per_scene: int, frames: int, device: str | None = None) -> dict:
    """The kernels' median device ms a frame and the candidates' statistics."""
    fab, places = crowds(scenes, per_scene)
    w = make_world("workgroup", device=device)
    p = ClothParams(iterations=10, material=Material(thickness=0.01))
    for s, shift in places:
        w.add(fab, p, positions=fab.rest_positions + shift, scene=f"crowd-{s}")
    rec = _Recorder()
    cl_scenes.cl = rec  # type: ignore[assignment]
    try:
        for _ in range(2):
            w.step(DT)
        w.sync()
        per: dict[str, list[float]] = defaultdict(list)
        total: list[float] = []
        for _ in range(frames):
            rec.events.clear()
            w.step(DT)
            w.sync()
            frame: dict[str, float] = defaultdict(float)
            for name, ev in rec.events:
                frame[name] += _ms(ev)
            for name, ms in frame.items():
                per[name].append(ms)
            total.append(sum(frame.values()))
    finally:
        cl_scenes.cl = cl  # type: ignore[assignment]
    sc = w.scene_collision  # type: ignore[attr-defined]
    count = sc._count.read(0, sc.n_vertices)[:, 0]
    w.close()
    med = statistics.median(total)
    return {
        "scenes": scenes,
        "per_scene": per_scene,
        "vertices": int(sc.n_vertices),
        "frames": frames,
        "kernels_ms": {k: round(statistics.median(v), 4) for k, v in per.items()},
        "kernels_min_ms": {k: round(min(v), 4) for k, v in per.items()},
        "scenes_ms": round(med, 4),
        "scenes_min_ms": round(min(total), 4),
        "candidates_mean": round(float(count.mean()), 3),
        "with_candidates": round(float((count > 0).mean()), 4),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="scenepass", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--scenes",
        type=lambda t: [int(x) for x in csv_list(t)],
        default=[2, 64],
        help="S,C: S scenes of C capes (2,64)",
    )
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=1, help="repeat the run (interleaving with another build)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    out = []
    for _ in range(a.rounds):
        r = profile(a.scenes[0], a.scenes[1], a.frames, a.device)
        out.append(r)
        print(f"{r['scenes']} scenes of {r['per_scene']} ({r['vertices']} vertices), {a.frames} frames:")
        for k, ms in r["kernels_ms"].items():
            print(f"  {k:<12} {ms:9.3f} ms  {ms / r['scenes_ms']:6.1%}  (min {r['kernels_min_ms'][k]:.3f})")
        print(f"  {'scenes':<12} {r['scenes_ms']:9.3f} ms          (min {r['scenes_min_ms']:.3f})")
        print(f"  candidates a vertex {r['candidates_mean']}, vertices with any {r['with_candidates']:.1%}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
