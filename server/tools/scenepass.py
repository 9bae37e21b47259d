"""The scenes' device time, kernel by kernel (issue 22: "64 scenes of 64 colliding cloths each at
<= 3x the solver time without scenes"): ``drape bench scenes``' crowds (32 x 32 capes, 1 cm thick,
overlapping their neighbours: contacts every frame) on one World, each frame's inter-cloth
collision kernels timed by their OpenCL events, and the candidates they found.

    python -m drape.server.tools.scenepass [--scenes S,C] [--frames F] [--groups 1,256] [--rounds R] [--json FILE]

``--groups`` runs each round once per value of ic_insert's groups (IC_CG; 1 is the code before
h-scenegpu: one atomic a walker on one counter, ic_refind over every vertex), interleaved on one
device: the A/B of the later rounds' lists on a GPU.

Each row: a kernel of kernels/intercollide.cl, its median device milliseconds a frame (its
launches summed), its share of the scenes' time and its fastest frame (on a shared CPU the least
disturbed: compare builds by it, in interleaved runs); then the scenes' total, the mean
candidates of a scene vertex, the share of scene vertices with any and the share that walked the
hash again in the step's last round (the others kept their first round's skin list). On a CPU this steers the
GPU's work (which kernels to cut, by how much), never its ratio: the solver itself runs several
times slower here.

Then the work of one more step counted from each walking launch's inputs, no clock (warp_work):
per kernel the entries its lanes walk, its warp-entries (per warp of 32 consecutive work-items,
the most one lane walks, summed: a GPU's warp waits for its slowest lane, idle lanes included)
and, for the hash walks, its warp reads (the entries of the distinct buckets a warp's lanes walk:
lanes walking one bucket read it together); ``ic_rewalk`` also in the order a GPU's groups give
its list now and in those one counter for it may give on a GPU (the code before: warps shuffled,
or every vertex apart), ``ic_refind`` also the other way (over every vertex, or over the list of
the unmoved: IC_KEPT).
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyopencl as cl

from ..sim import make_world
from ..sim.opencl import scenes as cl_scenes
from ..sim.params import ClothParams, Material
from ..sim.scenes import INTER_COLLISION_MARGIN, INTER_COLLISION_REACH
from ..sim.tethers import morton
from .bench import DT, crowds
from .procs import csv_list


class _Recorder:
    """pyopencl as the scenes' part sees it, each launch's event kept (a tool's probe); ``before``,
    if set, is called with each kernel before it is enqueued."""

    def __init__(self) -> None:
        self.events: list[tuple[cl.Kernel, cl.Event]] = []
        self.before: Callable[[cl.Kernel, tuple[int, ...]], None] | None = None

    def __getattr__(self, name: str) -> object:
        return getattr(cl, name)

    def enqueue_nd_range_kernel(self, queue, kernel, gsize, lsize):  # type: ignore[no-untyped-def]
        if self.before is not None:
            self.before(kernel, gsize)
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


#: Work-items that run in lock step on a GPU (an NVIDIA warp): warp_entries' group.
WARP = 32
#: The kernels that walk the hash or a list, whose work warp_work counts.
WALKS = ("ic_find", "ic_rewalk", "ic_refind", "ic_pass", "ic_pass_ba")


def warp_entries(work: np.ndarray) -> int:
    """The work of a launch as a GPU pays it: over each group of WARP consecutive work-items (a
    warp, which waits for its slowest lane), the most entries one of its lanes walks, summed."""
    w = np.zeros(-(-len(work) // WARP) * WARP, np.int64)
    w[: len(work)] = work
    return int(w.reshape(-1, WARP).max(axis=1).sum())


def _bucket(c: np.ndarray, scene: np.ndarray, mask: int) -> np.ndarray:
    """kernels/intercollide.cl's ic_bucket of cells ``c`` (..., 3) in ``scene`` (...)."""
    u = np.ascontiguousarray(c, np.int32).view(np.uint32)
    h = u[..., 0] * np.uint32(73856093) ^ u[..., 1] * np.uint32(19349663) ^ u[..., 2] * np.uint32(83492791)
    return ((h ^ scene.astype(np.uint32) * np.uint32(2654435761)) & np.uint32(mask)).astype(np.int64)


def hash_walks(
    x0: np.ndarray, scene: np.ndarray, inserted: np.ndarray, inv: float, mask: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each vertex's walk of the hash (ic_walk: the distinct buckets of the 2 x 2 x 2 cells around
    it, each bucket's whole list) for positions ``x0`` (float32, as on the device), their
    ``scene`` and the vertices ``inserted`` into the hash (those of active cloths): the entries
    each walk passes, the buckets it walks (n, 8; -1 for a bucket met twice) and every bucket's size."""
    inv32 = np.float32(inv)
    x = x0.astype(np.float32)
    home = _bucket(np.floor(x[inserted] * inv32), scene[inserted], mask)
    size = np.bincount(home, minlength=mask + 1)
    off = np.array([(dx, dy, dz) for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], np.int32)
    c0 = np.floor(x * inv32 - np.float32(0.5)).astype(np.int32)
    b = np.sort(_bucket(c0[:, None, :] + off[None], np.repeat(scene[:, None], 8, 1), mask), axis=1)
    b[:, 1:][b[:, 1:] == b[:, :-1]] = -1  # each bucket once
    return np.where(b >= 0, size[b], 0).sum(axis=1), b, size


def warp_reads(buckets: np.ndarray, size: np.ndarray, walker: np.ndarray) -> int:
    """The hash entries a GPU reads for a launch whose work-item i walks for vertex ``walker[i]``
    (-1: none), ``buckets`` each vertex's (hash_walks): over each warp, the entries of the distinct
    buckets its lanes walk, summed (lanes that walk one bucket read the same entries, together).
    Against warp_entries, it tells lanes that walk apart (scattered vertices) from lanes that walk
    together (neighbours)."""
    n = -(-len(walker) // WARP) * WARP
    idx = np.full(n, -1, np.int64)
    idx[: len(walker)] = walker
    total = 0
    for lo in range(0, n, WARP * 4096):  # a few thousand warps at a time
        part = idx[lo : lo + WARP * 4096]
        b = np.where(part[:, None] >= 0, buckets[np.maximum(part, 0)], -1).reshape(-1, WARP * 8)
        b.sort(axis=1)
        b[:, 1:][b[:, 1:] == b[:, :-1]] = -1
        total += int(np.where(b >= 0, size[np.maximum(b, 0)], 0).sum())
    return total


def _groups_shuffled(t: np.ndarray, size: int) -> np.ndarray:
    """Vertices ``t`` in groups of ``size`` consecutive vertex numbers, each group's in order, the
    groups in a random order (a list appended a group at a time by concurrent work-groups)."""
    t = np.sort(t)
    starts = np.flatnonzero(np.r_[True, t[1:] // size != t[:-1] // size]) if len(t) else np.zeros(0, np.int64)
    groups = np.split(t, starts[1:])
    order = np.random.default_rng(0).permutation(len(groups))
    return np.concatenate([groups[j] for j in order]) if len(t) else t


def warp_work(w, sc, other_order: np.ndarray | None = None) -> dict[str, dict[str, float]]:  # type: ignore[no-untyped-def]
    """One more step of World ``w`` (its scenes' part ``sc``, already stepped) with the work of
    each launch of the walking kernels (WALKS) counted from its inputs, read back before it
    runs: per work-item, the hash entries it walks (or the list entries it loops over), in the
    order of the launch's work-items. Per kernel: ``entries`` (all lanes' work, summed over the
    step), ``warp_entries`` (warp_entries of each launch, summed: what a GPU pays, the lanes
    that idle in a warp included), their ratio ``lanes_busy`` (entries / (WARP warp_entries))
    and, for the hash walks, ``warp_reads`` (warp_reads: the entries its warps read); with
    ``other_order`` (work-item i walking scene vertex other_order[i]) ``ic_find`` is counted in that
    order too (the scene's vertices numbered the other way: IC_MORTON)."""
    names = {id(k): name for name, k in sc.kernels().items()}
    nv = sc.n_vertices
    cinfo = sc._cinfo.read(0, sc.n_cloths)
    vcl = sc._vcl.read(0, nv)[:, 0]
    scene = cinfo[vcl, 2]
    ic_list = cl_scenes.IC_LIST
    out: dict[str, dict[str, float]] = defaultdict(lambda: defaultdict(float))
    state: dict[str, np.ndarray] = {}

    def count(name: str, work: np.ndarray, walker: np.ndarray | None = None) -> None:
        out[name]["entries"] += float(work.sum())
        out[name]["warp_entries"] += warp_entries(work)
        if walker is not None:
            out[name]["warp_reads"] += warp_reads(state["B"], state["size"], walker)

    def before(kernel: cl.Kernel, gsize: tuple[int, ...]) -> None:
        name = names.get(id(kernel), kernel.function_name)
        if name not in WALKS:
            return
        w.sync()
        if name in ("ic_find", "ic_rewalk"):  # a round's first walk: its hash
            act = sc._active.read(0, sc.n_cloths)[:, 0][vcl] != 0
            xs0 = sc._xs0.read(0, nv)
            state["free"] = act & (xs0[:, 3] > 0)
            e, state["B"], state["size"] = hash_walks(xs0[:, :3], scene, act, sc._inv, sc._nb - 1)
            state["E"] = e * state["free"]
        e, free = state["E"], state["free"]
        n = gsize[0]
        work = np.zeros(n, np.int64)
        walker = np.full(n, -1, np.int64)
        if name == "ic_find":
            work[:nv] = e
            walker[:nv] = np.where(free, np.arange(nv), -1)
            count(name, work, walker)
            if other_order is not None:
                o = other_order
                work[:nv], walker[:nv] = e[o], np.where(free[o], o, -1)
                count(f"ic_find ({'rows' if sc.morton else 'Morton order'})", work, walker)
            return
        nmoved = sc._nmoved.read(0, 2)[:, 0]
        if name == "ic_rewalk":
            nm = int(nmoved[0])
            # ic_insert's list of them: one atomic on one counter a walker before, one a group (of
            # IC_CG, on each list) as launched here with IC_CG > 1
            out["ic_insert_later"]["walkers"] += nm
            out["ic_insert_later"]["list_atomics"] += nm if sc.cg == 1 else (1 + sc.kept) * -(-nv // sc.cg)
            t = sc._moved.read(0, nm)[:, 0].astype(np.int64)
            work[:nm] = e[t]
            walker[:nm] = np.where(free[t], t, -1)
            count(name, work, walker)
            # the same walks in other orders: the GPU's now (ic_insert's groups of IC_CG, in any
            # order), and those one counter for the list may give on a GPU (the code before
            # h-scenegpu): each warp's vertices together, the warps in any order, or every one apart
            for label, size in (("GPU's groups", cl_scenes.IC_CG["gpu"]), ("warps shuffled", WARP), ("shuffled", 1)):
                o = _groups_shuffled(t, size)
                work[:nm], walker[:nm] = e[o], np.where(free[o], o, -1)
                count(f"ic_rewalk ({label})", work, walker)
            return
        c = sc._count.read(0, nv)[:, 0].astype(np.int64)
        if name == "ic_refind":  # the unmoved: their list and extra list, or the hash
            mv = sc._mv.read(0, nv)[:, 0]
            xc = sc._xcount.read(0, nv)[:, 0].astype(np.int64)
            out["ic_rewalk"]["extra_list_atomics"] += float(xc.sum())  # a walker found an unmoved vertex
            lst = np.where(free & (mv != 1), np.where(xc > ic_list, e, c + xc), 0)
            kept = np.flatnonzero(mv != 1)  # IC_KEPT's list: in vertex order within each group
            # as launched here (IC_KEPT on a GPU), and the other way
            for label, on in ((name, sc.kept), (f"{name} ({'every vertex' if sc.kept else 'kept list'})", not sc.kept)):
                work[:] = 0
                if on:
                    work[: len(kept)] = lst[kept]
                else:
                    work[:nv] = lst
                count(label, work)
            return
        work[:nv] = np.where(c > ic_list, e, np.maximum(c, 0))  # a pass: its list, or the hash (overflow)
        count(name, work)

    rec = _Recorder()
    rec.before = before
    cl_scenes.cl = rec  # type: ignore[assignment]
    try:
        w.step(DT)
        w.sync()
    finally:
        cl_scenes.cl = cl  # type: ignore[assignment]
    for r in out.values():
        if "warp_entries" in r:
            r["lanes_busy"] = round(r["entries"] / max(WARP * r["warp_entries"], 1), 4)
    return {k: dict(v) for k, v in out.items()}


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
    # the crowd's scene vertices (every cape one fabric) in the other numbering: Morton or rows
    n = fab.n_vertices
    in_morton = (np.arange(len(places))[:, None] * n + np.argsort(morton(fab.rest_positions), kind="stable")).ravel()
    other = np.argsort(in_morton) if sc.morton else in_morton
    warps = warp_work(w, sc, other)  # before the launches alone, which leave the hash's heads set
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
        "warp_work": warps,
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
    ap.add_argument(
        "--groups",
        type=lambda t: [int(x) for x in csv_list(t)],
        default=None,
        help="A,B,...: each round runs with ic_insert's groups IC_CG of each in turn on this device's kind"
        " (1: one atomic a vertex, the code before h-scenegpu; > 1 with IC_KEPT on a GPU), interleaved",
    )
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    out = []
    for _ in range(a.rounds):
        for groups in [None] if a.groups is None else a.groups:
            r = _profile_with(groups, a)
            out.append(r)
            _report(r, a.frames)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


def _profile_with(groups: int | None, a: argparse.Namespace) -> dict:
    """profile() with ic_insert's groups set to ``groups`` for every device kind (None: as shipped)."""
    saved = dict(cl_scenes.IC_CG), dict(cl_scenes.IC_KEPT)
    if groups is not None:
        for kind in cl_scenes.IC_CG:
            cl_scenes.IC_CG[kind] = groups
            cl_scenes.IC_KEPT[kind] = groups > 1 and saved[1][kind]
    try:
        r = profile(a.scenes[0], a.scenes[1], a.frames, a.device)
    finally:
        cl_scenes.IC_CG.update(saved[0])
        cl_scenes.IC_KEPT.update(saved[1])
    r["ic_cg"] = groups
    return r


def _report(r: dict, frames: int) -> None:
    """One profile() record, printed."""
    g = "" if r.get("ic_cg") is None else f", ic_insert's groups {r['ic_cg']}"
    print(f"{r['scenes']} scenes of {r['per_scene']} ({r['vertices']} vertices), {frames} frames{g}:")
    for k, ms in r["kernels_ms"].items():
        print(f"  {k:<12} {ms:9.3f} ms  {ms / r['scenes_ms']:6.1%}  (min {r['kernels_min_ms'][k]:.3f})")
    print(f"  {'scenes':<12} {r['scenes_ms']:9.3f} ms          (min {r['scenes_min_ms']:.3f})")
    print(f"  candidates a vertex {r['candidates_mean']}, vertices with any {r['with_candidates']:.1%}")
    print(f"  walking the hash again in the last round: {r['moved_last_round']}")
    print(f"  hash entries a vertex walks: {r['entries_walked']}")
    print(f"  alone, fastest of 20 launches: {r['alone_min_ms']}")
    print(f"  work of one step, entries walked (all lanes; warp-entries: a {WARP}-lane warp's slowest lane;")
    print("  warp reads: the entries of the distinct buckets a warp's lanes walk):")
    for k, ww in r["warp_work"].items():
        if "warp_entries" not in ww:
            continue
        e, we = ww["entries"], ww["warp_entries"]
        reads = f"  warp reads {ww['warp_reads']:14,.0f}" if "warp_reads" in ww else ""
        print(f"    {k:<26} {e:12,.0f} entries  {we:12,.0f} warp-entries  lanes busy {ww['lanes_busy']:.1%}{reads}")
    ins, rw = r["warp_work"].get("ic_insert_later", {}), r["warp_work"].get("ic_rewalk", {})
    print(
        f"  atomics of one step: ic_insert's lists {ins.get('walkers', 0):,.0f} with one counter (a walker's),"
        f" {ins.get('list_atomics', 0):,.0f} as launched here; ic_rewalk's extra lists"
        f" {rw.get('extra_list_atomics', 0):,.0f}"
    )


if __name__ == "__main__":
    raise SystemExit(main())
