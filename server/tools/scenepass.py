"""The scenes' device time, kernel by kernel (issue 22: "64 scenes of 64 colliding cloths each at
<= 3x the solver time without scenes"): ``drape bench scenes``' crowds (32 x 32 capes, 1 cm thick,
overlapping their neighbours: contacts every frame) on one World, each frame's inter-cloth
collision kernels timed by their OpenCL events, and the candidates they found.

    python -m drape.server.tools.scenepass [--scenes S,C] [--frames F] [--json FILE]

Each row: a kernel of kernels/intercollide.cl, its median device milliseconds a frame (its
launches summed), its share of the scenes' time and its fastest frame (on a shared CPU the least
disturbed: compare builds by it, in interleaved runs); then the scenes' total, the mean
candidates of a scene vertex, the share of scene vertices with any and the share that walked the
hash again in the step's last round (the others kept their first round's skin list). On a CPU this steers the
GPU's work (which kernels to cut, by how much), never its ratio: the solver itself runs several
times slower here.
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyopencl as cl

from ..sim import make_world
from ..sim.opencl import scenes as cl_scenes
from ..sim.params import ClothParams, Material
from ..sim.scenes import INTER_COLLISION_MARGIN, INTER_COLLISION_REACH
from .bench import DT, crowds
from .procs import csv_list


class _Recorder:
    """pyopencl as the scenes' part sees it, each launch's event kept (a tool's probe)."""

    def __init__(self) -> None:
        self.events: list[tuple[cl.Kernel, cl.Event]] = []

    def __getattr__(self, name: str) -> object:
        return getattr(cl, name)

    def enqueue_nd_range_kernel(self, queue, kernel, gsize, lsize):  # type: ignore[no-untyped-def]
        ev = cl.enqueue_nd_range_kernel(queue, kernel, gsize, lsize)
        self.events.append((kernel, ev))
        return ev


def _ms(ev: cl.Event) -> float:
    return (ev.profile.end - ev.profile.start) * 1e-6


def walk_work(
    x0: np.ndarray, cloth: np.ndarray, scene: np.ndarray, d: float, reach: float, walkers: np.ndarray
) -> dict[str, float]:
    """The candidate walk's work a vertex, counted (no clock: a shared CPU's load does not move
    it), for vertices at ``x0`` (their ``cloth``, ``scene``; every one active and free, one contact
    distance ``d``) and a candidate ``reach`` (in contact distances): kernels/intercollide.cl's
    2 x 2 x 2 cells of edge 2 ``reach`` ``d`` nearest each vertex, the hash entries it passes
    (``entries``), those of another cloth of its scene (``other``: the ones whose position it
    reads) and its candidates (``candidates``, closer than ``reach`` ``d``), averaged over the
    vertices ``walkers``."""
    edge = 2 * reach * d
    cell = np.floor(x0 / edge).astype(np.int64)
    low = np.floor(x0 / edge - 0.5).astype(np.int64)

    def key(c: np.ndarray, sc: np.ndarray = scene) -> np.ndarray:
        return ((c[:, 0] * 4099 + c[:, 1]) * 4099 + c[:, 2]) * 4099 + sc

    order = np.argsort(key(cell), kind="stable")
    keys = key(cell)[order]
    entries = np.zeros(len(walkers))
    other = np.zeros(len(walkers))
    cand = np.zeros(len(walkers))
    for off in np.array([(dx, dy, dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)]):
        kc = key(low[walkers] + off, scene[walkers])
        lo, hi = np.searchsorted(keys, kc, "left"), np.searchsorted(keys, kc, "right")
        entries += hi - lo
        for i, t in enumerate(walkers):  # the vertices met in this cell
            us = order[lo[i] : hi[i]]
            us = us[cloth[us] != cloth[t]]
            other[i] += len(us)
            cand[i] += int((((x0[us] - x0[t]) ** 2).sum(axis=1) < (reach * d) ** 2).sum())
    return {
        "entries": round(float(entries.mean()), 2),
        "other": round(float(other.mean()), 2),
        "candidates": round(float(cand.mean()), 2),
    }


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
        # each launch by its name in the phase (an alias apart from its kernel function)
        names = {id(k): name for name, k in w.scene_collision.kernels().items()}  # type: ignore[attr-defined]
        per: dict[str, list[float]] = defaultdict(list)
        total: list[float] = []
        for _ in range(frames):
            rec.events.clear()
            w.step(DT)
            w.sync()
            frame: dict[str, float] = defaultdict(float)
            for kern, ev in rec.events:
                frame[names.get(id(kern), kern.function_name)] += _ms(ev)
            for name, ms in frame.items():
                per[name].append(ms)
            total.append(sum(frame.values()))
    finally:
        cl_scenes.cl = cl  # type: ignore[assignment]
    sc = w.scene_collision  # type: ignore[attr-defined]
    alone: dict[str, list[float]] = defaultdict(list)
    q, clear = w.dev.queue, sc.kernels()["ic_clear"]  # type: ignore[attr-defined]
    for _ in range(20):  # the hash built again and walked, then one pass: each alone, fastest of 20
        clear(q, (sc._nb,), None, sc._heads.buf, np.int32(sc._nb))
        evs = [(k.function_name, cl.enqueue_nd_range_kernel(q, k, g, ls)) for k, g, ls in sc._launches[:5]]
        w.sync()
        for name, ev in evs[3:]:
            alone[name].append(_ms(ev))
    count = sc._count.read(0, sc.n_vertices)[:, 0]
    # the later rounds' walkers: the share of scene vertices that walked the whole hash in the last
    # round (moved further than the skin since the first round), None before the skin lists
    mv = sc._mv.read(0, sc.n_vertices)[:, 0] if hasattr(sc, "_mv") else None
    x0 = sc._xs0.read(0, sc.n_vertices)[:, :3].astype(np.float64)
    cloth = sc._vcl.read(0, sc.n_vertices)[:, 0]
    scene = cloth // per_scene
    d = p.material.thickness * INTER_COLLISION_MARGIN
    sample = np.random.default_rng(0).choice(len(x0), min(len(x0), 4096), replace=False)
    work = {  # the walk's work at this reach and at the one before (1.5), on a sample of vertices
        f"reach {reach}": walk_work(x0, cloth, scene, d, reach, sample) for reach in (1.5, INTER_COLLISION_REACH)
    }
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
        "moved_last_round": None if mv is None else round(float((mv == 1).mean()), 4),
        "entries_walked": work,
        "alone_min_ms": {k: round(min(v), 4) for k, v in alone.items()},
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
        print(f"  walking the hash again in the last round: {r['moved_last_round']}")
        print(f"  hash entries a vertex walks: {r['entries_walked']}")
        print(f"  alone, fastest of 20 launches: {r['alone_min_ms']}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
