"""``drape bench``: the talk's table and beyond.

Workloads
- ``seed``: one 150x150 cloth, structural + shear links (89,102: the talk's 90k), 10 iterations;
  no solver (iterations 0) / coloured batches / work-group / Jacobi / CPU reference.
- ``many``: N cloths of 32x32 with bending (5,826 links each), N = 64 .. 4096.
- ``hang``: 1 m x 1 m, 1 kg, n x n, flat at 1 m, two corners of one edge pinned, dt 1/60,
  10 iterations: ms per step and max/mean structural stretch (length / rest) after 2 s.
- ``features``: the ``many`` cloths with each scene feature alone, all of them, and a half/half
  mix of bare and windy cloths (two kernels in one tick): the cost of each feature.
- ``self``: self-collision's cost on the work-group solver (docs/collision.md): the seed cloth
  hanging (no contact: the spatial hash's cost alone) and a 32x32 cloth hung by its middle row,
  whose halves swing into each other (contacts), each with and without the feature.

A frame is one ``World.step`` plus waiting for the device (``World.sync``): median of the timed
frames after warm-up. Records go to ``--json PATH``; the table is printed.
"""

from __future__ import annotations

import argparse
import json
import logging
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..sim import make_world
from ..sim.fabric import Fabric, cook_grid
from ..sim.params import Capsule, ClothParams, Features, LinkOptions, Material, Plane, Sphere, pack_colliders
from ..sim.world import World
from .procs import csv_list, progress, require_extra

log = logging.getLogger(__name__)

DT = 1 / 60


@dataclass
class Record:
    workload: str
    solver: str
    device: str
    cloths: int
    vertices: int
    links: int
    iterations: int
    ms_per_frame: float  # median
    link_iters_per_s: float
    frames: int
    ms_min: float
    ms_max: float
    extra: dict = field(default_factory=dict)


class FrameTimes(list):
    """Milliseconds per frame; ``host_ms`` holds the part spent enqueueing (Python + driver)."""

    host_ms: list[float]


def time_frames(world: World, warmup: int, frames: int, max_seconds: float) -> FrameTimes:
    for _ in range(warmup):
        world.step(DT)
    world.sync()
    times = FrameTimes()
    times.host_ms = []
    start = time.perf_counter()
    for _ in range(frames):
        t0 = time.perf_counter()
        world.step(DT)
        t1 = time.perf_counter()
        world.sync()
        times.append((time.perf_counter() - t0) * 1e3)
        times.host_ms.append((t1 - t0) * 1e3)
        if time.perf_counter() - start > max_seconds and len(times) >= 3:
            break
    return times


def _record(workload, solver, world, fabrics_params, times, extra=None) -> Record:
    links = sum(f.n_links for f, _ in fabrics_params)
    iters = max(p.iterations for _, p in fabrics_params)
    li = sum(f.n_links * p.iterations * p.substeps for f, p in fabrics_params)
    med = statistics.median(times)
    rec = Record(
        workload=workload,
        solver=solver,
        device=getattr(world, "device_name", "?"),
        cloths=len(fabrics_params),
        vertices=sum(f.n_vertices for f, _ in fabrics_params),
        links=links,
        iterations=iters,
        ms_per_frame=round(med, 4),
        link_iters_per_s=li / (med / 1e3) if med > 0 else 0.0,
        frames=len(times),
        ms_min=round(min(times), 4),
        ms_max=round(max(times), 4),
        extra=dict(extra or {}),
    )
    if getattr(times, "host_ms", None):
        rec.extra["enqueue_ms"] = round(statistics.median(times.host_ms), 4)
    return rec


Step = Callable[[str], None]


def _no_step(label: str) -> None:
    log.debug("%s", label)


# Lanes of the CPU pack solver for the OpenCL worlds (None: the device's default; 0: one cloth
# per work-item, the kernel before the pack solver). Set by ``run`` per --pack-lanes value.
PACK_LANES: int | None = None


def make(solver: str, device: str | None) -> World:
    if solver == "reference":
        return make_world(solver)
    if PACK_LANES is None:
        return make_world(solver, device=device)
    return make_world(solver, device=device, pack_lanes=PACK_LANES)


def bench_seed(solvers, device, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    fab = cook_grid(150, 150, 1.0, 1.0, LinkOptions(structural=True, shear=True), pinned=[0, 149], origin=(0, 1, 0))
    out = []
    cases = [("no-solver", solvers[0] if solvers[0] != "reference" else "workgroup", 0)]
    cases += [(s, s, 10) for s in solvers]
    for label, solver, iters in cases:
        step(f"seed: {label}")
        w = make(solver, device)
        p = ClothParams(iterations=iters)
        w.add(fab, p)
        n = frames if solver != "reference" else max(3, frames // 10)
        t = time_frames(w, warmup=3 if solver != "reference" else 1, frames=n, max_seconds=max_seconds)
        rec = _record("seed", label if label == "no-solver" else solver, w, [(fab, p)], t)
        rec.extra.update(_launch_shape(w))
        if label == "no-solver":
            rec.extra["strategy"] = solver
        out.append(rec)
        w.close()
    return out


def bench_many(solvers, device, counts, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    fab = cook_grid(32, 32, 1.0, 1.0, LinkOptions(bending=True), pinned=[0, 31], origin=(0, 1, 0))
    out = []
    for solver in solvers:
        for n in counts:
            if solver == "reference" and n > 64:
                continue  # numpy over thousands of cloths says nothing new
            step(f"many: {solver} x {n} cloths")
            w = make(solver, device)
            p = ClothParams(iterations=10)
            for _ in range(n):
                w.add(fab, p)
            t = time_frames(w, warmup=2, frames=frames, max_seconds=max_seconds)
            out.append(_record("many", solver, w, [(fab, p)] * n, t, _launch_shape(w)))
            w.close()
    return out


FEATURE_CASES: list[tuple[str, Features]] = [
    ("none", Features()),
    ("xpbd", Features(xpbd=True)),
    ("tethers", Features(tethers=True)),
    ("colliders", Features(colliders=True)),
    ("wind", Features(wind=True)),
    ("normals", Features(normals=True)),
    ("all", Features(xpbd=True, tethers=True, colliders=True, wind=True, normals=True)),
    ("self_collision", Features(self_collision=True)),
    ("half-wind", Features()),  # half the cloths bare, half with wind: two kernels per tick
]


def bench_features(solvers, device, count, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    fab = cook_grid(32, 32, 1.0, 1.0, LinkOptions(bending=True), pinned=[0, 31], origin=(0, 1, 0))
    colliders = pack_colliders(
        [Sphere((0.5, 0.4, 0.5), 0.2), Capsule((0.0, 0.2, 0.3), (1.0, 0.2, 0.6), 0.05), Plane((0.0, 1.0, 0.0), -0.5)]
    )
    out = []
    for solver in solvers:
        if solver == "reference":
            continue
        for label, feats in FEATURE_CASES:
            step(f"features: {solver} {label} x {count}")
            w = make(solver, device)
            mat = Material(compliance=(1e-6, 1e-6, 1e-4), drag=1.0, lift=0.5, friction=0.3, tether_limit=1.05)
            fps = []
            for i in range(count):
                f = Features(wind=True) if (label == "half-wind" and i % 2) else feats
                p = ClothParams(iterations=10, material=mat, features=f, wind=(2.0, 0.0, 1.0))
                h = w.add(fab, p)
                if f.colliders:
                    w.set_colliders(h, colliders)
                fps.append((fab, p))
            t = time_frames(w, warmup=2, frames=frames, max_seconds=max_seconds)
            rec = _record("features", solver, w, fps, t, {"features": label})
            out.append(rec)
            w.close()
    base = {r.solver: r.ms_per_frame for r in out if r.extra["features"] == "none"}
    for r in out:
        r.extra["vs_none"] = round(r.ms_per_frame / base[r.solver], 3) if base.get(r.solver) else None
    return out


def bench_self(device, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    """Self-collision's cost: each cloth with and without it, on the work-group solver (on a CPU:
    the pack solver, as a server runs it; ``--pack-lanes 0``: wg_step)."""
    n = 32
    cloths = {
        "seed": cook_grid(
            150, 150, 1.0, 1.0, LinkOptions(structural=True, shear=True), pinned=[0, 149], origin=(0, 1, 0)
        ),
        "fold": cook_grid(n, n, 1.0, 1.0, LinkOptions(bending=True), pinned=[(n // 2) * n + c for c in range(n)]),
    }
    out = []
    for name, fab in cloths.items():
        for label, feats in (("none", Features()), ("self_collision", Features(self_collision=True))):
            step(f"self: {name} {label}")
            w = make("workgroup", device)
            p = ClothParams(iterations=10, features=feats)
            w.add(fab, p)
            t = time_frames(w, warmup=2, frames=frames, max_seconds=max_seconds)
            out.append(_record("self", "workgroup", w, [(fab, p)], t, {"cloth": name, "features": label}))
            w.close()
    base = {r.extra["cloth"]: r.ms_per_frame for r in out if r.extra["features"] == "none"}
    for r in out:
        r.extra["vs_none"] = round(r.ms_per_frame / base[r.extra["cloth"]], 3)
    return out


def crowds(scenes: int, per_scene: int) -> tuple[Fabric, list[tuple[int, np.ndarray]]]:
    """bench_scenes' capes: one 32 x 32 fabric and each cape's (scene, shift)."""
    n = 32
    # One fabric, each cape added at its place (cooking 4096 copies took minutes of host time:
    # why session 15's 64 x 64 run never reached its frames).
    fab = cook_grid(n, n, 0.5, 0.5, orientation="vertical", pinned=[0, n - 1], origin=(0.0, 1.0, 0.0))
    places = [
        (s, np.array([0.3 * (j % 8), 0.0, 10.0 * s + 0.012 * (j // 8)]))
        for s in range(scenes)
        for j in range(per_scene)
    ]
    return fab, places


def bench_scenes(device, scenes: int, per_scene: int, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    """Inter-cloth collision's cost (protocol 1.7): ``scenes`` crowds of ``per_scene`` 32 x 32
    capes (0.5 m, pinned at the shoulders) hanging in rows 0.3 m apart, each overlapping its
    neighbours and 12 mm behind the row before (every box meets others: the whole crowd takes part),
    on the work-group solver, with every cloth in its crowd's scene and with no scene at all."""
    fab, places = crowds(scenes, per_scene)
    out = []
    for label in ("none", "scenes"):
        step(f"scenes: {scenes} x {per_scene} {label}")
        w = make("workgroup", device)
        p = ClothParams(iterations=10, material=Material(thickness=0.01))
        t0 = time.perf_counter()
        for s, shift in places:
            w.add(fab, p, positions=fab.rest_positions + shift, scene=f"crowd-{s}" if label == "scenes" else None)
        add_ms = (time.perf_counter() - t0) * 1e3 / len(places)
        t = time_frames(w, warmup=2, frames=frames, max_seconds=max_seconds)
        extra: dict[str, object] = {"features": label, "scenes": scenes if label == "scenes" else 0}
        extra.update(per_scene=per_scene, add_ms=round(add_ms, 4))
        out.append(_record("scenes", "workgroup", w, [(fab, p)] * len(places), t, extra))
        w.close()
    for r in out:
        r.extra["vs_none"] = round(r.ms_per_frame / out[0].ms_per_frame, 3)
    return out


def stretch(x: np.ndarray, fab: Fabric) -> tuple[float, float]:
    s = fab.link_type == 0
    a, b = fab.links[s, 0], fab.links[s, 1]
    ratio = np.linalg.norm(x[b] - x[a], axis=1) / fab.rest_length[s]
    return float(ratio.max()), float(ratio.mean())


def bench_hang(solvers, device, sizes, frames, max_seconds, step: Step = _no_step) -> list[Record]:
    out = []
    for n in sizes:
        fab = cook_grid(
            n, n, 1.0, 1.0, LinkOptions(structural=True, shear=True, bending=True), pinned=[0, n - 1], origin=(0, 1, 0)
        )
        for solver in solvers:
            if solver == "reference" and n > 64:
                continue
            step(f"hang: {solver} {n}x{n}")
            w = make(solver, device)
            p = ClothParams(iterations=10)
            h = w.add(fab, p)
            times = []
            steps = int(round(2.0 / DT))
            for _ in range(steps):
                t0 = time.perf_counter()
                w.step(DT)
                w.sync()
                times.append((time.perf_counter() - t0) * 1e3)
            x = w.positions(h)
            mx, mean = stretch(x, fab)
            rec = _record(f"hang{n}", solver, w, [(fab, p)], times[5:] or times)
            rec.extra.update(
                max_stretch=round(mx, 5),
                mean_stretch=round(mean, 5),
                finite=bool(np.isfinite(x).all()),
                lowest_y=round(float(x[:, 1].min()), 4),
            )
            out.append(rec)
            w.close()
    return out


def _launch_shape(w: World) -> dict:
    """Work-group size and memory path of each kernel group (OpenCL worlds); a CPU pack group
    as ``pack<lanes>x<packs>``."""
    groups = getattr(w, "groups", {})
    if not groups:
        return {}
    limit = w.launches.kernel_limit  # type: ignore[attr-defined]  # an OpenCL world's
    return {
        "wg": ",".join(
            f"pack{g.pack}x{g.n_packs}" if g.pack else f"{g.local_size}{'L' if g.use_local else 'G'}/{limit(g)}"
            for g in groups.values()
        )
    }


def print_table(records: list[Record]) -> None:
    head = (
        f"{'workload':<10} {'solver':<10} {'cloths':>6} {'vertices':>9} {'links':>10} {'it':>3} {'ms/frame':>10} "
        f"{'G link-it/s':>11}  extra"
    )
    print(head)
    print("-" * len(head))
    for r in records:
        extra = " ".join(f"{k}={v}" for k, v in r.extra.items())
        print(
            f"{r.workload:<10} {r.solver:<10} {r.cloths:>6} {r.vertices:>9} {r.links:>10} {r.iterations:>3} "
            f"{r.ms_per_frame:>10.3f} {r.link_iters_per_s / 1e9:>11.3f}  {extra}"
        )
    if records:
        print(f"device: {records[0].device}; host: {platform.node()} {platform.processor() or platform.machine()}")


def markdown_table(records: list[Record]) -> str:
    """The records as a Markdown table (what docs/benchmarks.md quotes)."""
    rows = [
        "| workload | solver | cloths | vertices | links | iterations | ms/frame (median) | G link-it/s | notes |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in records:
        notes = ", ".join(f"{k} {v}" for k, v in r.extra.items())
        rows.append(
            f"| {r.workload} | {r.solver} | {r.cloths} | {r.vertices} | {r.links} | {r.iterations} | "
            f"{r.ms_per_frame:.3f} | {r.link_iters_per_s / 1e9:.2f} | {notes} |"
        )
    if records:
        rows.append(f"\nDevice: {records[0].device}.")
    return "\n".join(rows) + "\n"


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "bench")
    require_extra("tools", "bench")
    parser.add_argument(
        "workloads", nargs="*", metavar="WORKLOAD", help="seed, many, hang, features, self, scenes (default: all)"
    )
    parser.add_argument(
        "--scenes",
        default=None,
        help="the 'scenes' workload: SCENES,CLOTHS_PER_SCENE (default 64,64 on a GPU: issue 22's 4096 cloths "
        "in 64 scenes; 4,8 on a CPU)",
    )
    parser.add_argument(
        "--feature-cloths",
        type=int,
        default=None,
        help="cloths in the 'features' workload (default 4096 on a GPU, 128 on a CPU)",
    )
    parser.add_argument("--solvers", default="coloured,workgroup,jacobi,reference")
    parser.add_argument("--device", default=None, help="OpenCL device: auto, gpu, cpu or a name substring")
    parser.add_argument(
        "--counts", default=None, help="cloth counts for 'many' (default 64..4096 on a GPU, 64..512 on a CPU)"
    )
    parser.add_argument("--sizes", default="32,64,150", help="n for the n x n 'hang' cloths")
    parser.add_argument("--frames", type=int, default=30, help="timed frames per case (median reported)")
    parser.add_argument("--max-seconds", type=float, default=20.0, help="stop timing a case after this long")
    parser.add_argument("--json", type=Path, default=None, help="write the records here")
    parser.add_argument("--markdown", type=Path, default=None, help="write the table as Markdown here")
    parser.add_argument("--quick", action="store_true", help="small counts and few frames (CI smoke run)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--pack-lanes",
        default=None,
        help="CPU pack solver lanes for the workgroup solver, a comma list run back to back "
        "(e.g. 0,16: 0 = one cloth per work-item, the kernel before docs/cpu-solver.md; "
        "default: the device's own choice, 16 on a CPU; no effect on a GPU)",
    )


def run(args: argparse.Namespace) -> int:
    solvers = csv_list(args.solvers)
    known = ["seed", "many", "hang", "features", "self", "scenes"]
    workloads = args.workloads or known
    unknown = set(workloads) - set(known)
    if unknown:
        raise SystemExit(f"drape bench: unknown workload(s) {sorted(unknown)}; choose from {', '.join(known)}")
    frames = 5 if args.quick else args.frames
    from ..sim.opencl.device import Device

    gpu = Device(args.device).info.is_gpu if set(workloads) & {"many", "features", "scenes"} else False
    if args.counts:
        counts = [int(c) for c in args.counts.split(",")]
    elif args.quick:
        counts = [64]
    else:
        counts = [64, 256, 1024, 4096] if gpu else [64, 256, 512]
    feature_cloths = args.feature_cloths or (16 if args.quick else 4096 if gpu else 128)
    sizes = [int(s) for s in args.sizes.split(",")] if not args.quick else [32]
    scenes, per_scene = (
        int(v) for v in (args.scenes or ("2,4" if args.quick else "64,64" if gpu else "4,8")).split(",")
    )
    records: list[Record] = []
    lanes_list: list[int | None] = [int(v) for v in args.pack_lanes.split(",")] if args.pack_lanes else [None]
    global PACK_LANES
    with progress(desc="bench", unit="case", quiet=args.quiet) as bar:

        def step(label: str) -> None:
            log.debug("%s", label)
            bar.set_description(label, refresh=False)
            bar.update()

        for i, lanes in enumerate(lanes_list):
            PACK_LANES = lanes
            # the pack lanes change the workgroup solver only: the others run once
            run_solvers = solvers if i == 0 else [s for s in solvers if s == "workgroup"]
            new: list[Record] = []
            if "seed" in workloads:
                new += bench_seed(run_solvers, args.device, frames, args.max_seconds, step)
            if "many" in workloads:
                new += bench_many(run_solvers, args.device, counts, frames, args.max_seconds, step)
            if "hang" in workloads:
                new += bench_hang(run_solvers, args.device, sizes, frames, args.max_seconds, step)
            if "features" in workloads:
                new += bench_features(run_solvers, args.device, feature_cloths, frames, args.max_seconds, step)
            if "self" in workloads and "workgroup" in run_solvers:
                new += bench_self(args.device, frames, args.max_seconds, step)
            if "scenes" in workloads and "workgroup" in run_solvers:
                new += bench_scenes(args.device, scenes, per_scene, frames, args.max_seconds, step)
            if lanes is not None:
                for r in new:
                    r.extra["pack_lanes"] = lanes
            records += new
        PACK_LANES = None
    print_table(records)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps([asdict(r) for r in records], indent=1))
        print(f"wrote {args.json}")
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(markdown_table(records))
        print(f"wrote {args.markdown}")
    return 0
