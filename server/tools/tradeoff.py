"""``drape tradeoff``: how much accuracy each millisecond of device time buys.

Scenes (all 1 m x 1 m, 1 kg, n x n vertices with structural and shear links, gravity -9.81,
simulated for 2 s from rest):

- ``hanging``: flat (horizontal) at a height of 1 m, the two corners of one edge pinned;
- ``flag``: vertical, pinned along one vertical edge, in a steady wind (wind feature, drag and
  lift on);
- ``cape``: vertical, its top row pinned to the shoulders of a character that accelerates to a
  run along a circle (pins follow the path, turning with the heading, bobbing), a capsule
  collider as the body (colliders feature, friction 0.3).

Knobs: solver (jacobi, coloured, workgroup, reference), iterations, substeps, PBD or XPBD
(compliance, 0 by default: an inextensible cloth like PBD's stiffness 1), tethers, the state
encoding on the wire (float32, float16, 16-bit quantised against the cloth's axis-aligned
bounds) and the tick rate.

Ground truth: the float64 numpy reference (``ReferenceWorld``, colour-ordered Gauss-Seidel)
with XPBD, compliance 0, ``REF_SUBSTEPS`` x ``REF_ITERATIONS`` at 60 Hz (see docs/accuracy.md
for the convergence study behind the choice). It is cached under ``OUT/refcache``.

Metrics of one run (every one over the 2 s, on what a client would decode):

- ``max_strain`` / ``mean_strain``: relative strain ``|l - l0| / l0`` over the structural links
  only; ``max_strain`` is the largest over every link and every frame, ``mean_strain`` the mean
  over links, averaged over frames. ``end_max_strain`` / ``end_mean_strain``: the same at t = 2 s;
  ``late_max_strain``: the largest over the frames from t = 1 s on (after the first fall).
- ``rms_dev`` / ``max_dev``: position deviation from the ground truth in metres, over every
  vertex at t = 0.1, 0.2, ..., 2.0 s; ``rms_dev_early``: the same up to t = 0.5 s, before the
  falling cloth folds (the folding is chaotic: two converged references part by centimetres
  after 1 s, so late deviation is partly noise; see the docs).
- ``energy_drift``: (E(2 s) - E(0)) / (M g 1 m), E = kinetic (from frame-to-frame velocities)
  + gravitational potential of the free vertices; negative is numerical (or real) damping.
  ``energy_gain``: the largest (E(t) - E(0)) / (M g 1 m), > 0 means energy was created.
- ``enc_err_max`` / ``enc_err_rms``: the encoding's own position error in metres.
- ``ms_per_frame``: median wall time of ``world.step(dt)`` plus a blocking ``world.fetch()``
  over the frames after ``WARMUP_FRAMES`` (kernel builds happen in the first), the lowest of
  ``TIMING_ROUNDS`` such medians: the measured run's and short re-runs spread over the sweep,
  so that a burst of other load on the machine does not land on one configuration; ``load``: the
  fraction of real time the device spends (ms_per_frame x tick rate / 1000);
  ``ms_per_60hz``: cost of 1/60 s of simulated time, to compare tick rates.

This module is the command (arguments, the plan, the timing rounds, the output); its parts:
tradeoffrun (scenes, configurations, one run and its metrics), tradeoffsweep (which
configurations run where), tradeofftruth (the cached ground truths) and tradeoffreport (tables,
plots, the presets' summary); ``--collision`` is tradeoffcollision (the collision axis).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

from ..sim.params import SOLVERS
from .procs import csv_list, progress, require_extra
from .tradeoffreport import (
    _jsonable,
    _pct,
    code_version,
    format_encoding_table,
    format_table,
    plot,
    preset_summary,
)
from .tradeoffrun import (
    DURATION,
    QUICK_REF_SUBSTEPS,
    REF_ITERATIONS,
    REF_SUBSTEPS,
    REF_TICK_HZ,
    SCENES,
    TIMING_FRAMES,
    TIMING_ROUNDS,
    Config,
    Scene,
    make_scene,
    simulate,
    time_config,
)
from .tradeoffsweep import main_sweep, side_sweep, sweep_layout
from .tradeofftruth import ensure_truths, truth_records

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------------
# CLI


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "tradeoff")
    require_extra("tools", "tradeoff")
    parser.add_argument(
        "--scenes", default=None, help=f"comma list of {','.join(SCENES)} (default: all; --quick: hanging)"
    )
    parser.add_argument(
        "--sizes",
        default=None,
        help="comma list of grid sizes n (n x n), for every scene; the main sweep runs on "
        "the first scene at the first size (default: the main sweep on hanging 64 and a "
        "few points on every scene at 32; --quick: hanging 32; --full: the main sweep "
        "on every scene at 64, points at 32 and 150)",
    )
    parser.add_argument("--solvers", default=",".join(SOLVERS), help="comma list of solvers to sweep")
    level = parser.add_mutually_exclusive_group()
    level.add_argument("--quick", action="store_true", help="a small sweep (about a minute on 2 CPU cores)")
    level.add_argument("--full", action="store_true", help="every knob densely, every scene and size (long)")
    parser.add_argument("--out", default="out/tradeoff", help="output folder (table, JSON, plots, ground-truth cache)")
    parser.add_argument("--json", default=None, help="write the records here (default OUT/tradeoff.json)")
    parser.add_argument("--duration", type=float, default=DURATION, help="simulated seconds per run")
    parser.add_argument(
        "--ref-substeps",
        type=int,
        default=None,
        help=f"ground-truth substeps (default {REF_SUBSTEPS}; --quick {QUICK_REF_SUBSTEPS})",
    )
    parser.add_argument("--ref-iterations", type=int, default=REF_ITERATIONS, help="ground-truth iterations")
    parser.add_argument(
        "--timing-rounds",
        type=int,
        default=TIMING_ROUNDS,
        help="the cost is the lowest of this many medians (1: the measured run's only)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        help="processes for the ground truths (computed before any timing)",
    )
    parser.add_argument("--device", default=None, help="OpenCL device: auto, gpu, cpu or a name substring")
    parser.add_argument(
        "--costs",
        action="store_true",
        help="instead of the sweep: measure every preset's cost against PBD-10 in full packs, "
        "interleaved rounds in one process, and write it to the presets' cost file "
        "(drape.server.sim.quality.COSTS_FILE), which the quality governor reads",
    )
    parser.add_argument("--cost-rounds", type=int, default=7, help="--costs: interleaved rounds")
    parser.add_argument("--cost-cloths", type=int, default=None, help="--costs: cloths per world (default: full packs)")
    parser.add_argument(
        "--cost-substeps",
        default="",
        help="--costs: also these XPBD 1-iteration + tethers substep counts (comma list: the front)",
    )
    parser.add_argument("--cost-file", default=None, help="--costs: write here (default: the presets' cost file)")
    parser.add_argument(
        "--cost-scene",
        default="hanging",
        help="--costs: the scene (hanging 64 x 64 by default; another, e.g. flag or cape at --sizes, "
        "gets the presets' moving settings and is written under the cost file's <kind>-moving record, "
        "which the governor reads for moving cloths)",
    )
    parser.add_argument(
        "--cost-front",
        default=None,
        help="--costs: also simulate every configuration once (hanging 64 x 64, 2 s, float32 on "
        "the device) and plot stretch against cost to this PNG",
    )
    parser.add_argument(
        "--collision",
        action="store_true",
        help="instead of the sweep: the collision axis (tradeoffcollision): substeps and self-collision "
        "passes against the penetration left in the penetration scenarios",
    )
    parser.add_argument("--collision-scenarios", default="capsule_hit,cape_run,stack", help="--collision: scenarios")
    parser.add_argument("--collision-substeps", default="1,2,4,8", help="--collision: substep counts")
    parser.add_argument("--collision-passes", default="1,2,4", help="--collision: self-collision pass counts")
    parser.add_argument("--collision-solver", default="workgroup", help="--collision: the solver")
    parser.add_argument("--collision-size", default="full", help="--collision: full (32 x 32) or small (9 x 9)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.costs:
        return run_costs(args)
    if args.collision:
        from .tradeoffcollision import run as run_collision

        return run_collision(args)
    from ..sim.opencl.device import Device

    level = "quick" if args.quick else "full" if args.full else "default"
    scenes = csv_list(args.scenes) if args.scenes else (["hanging"] if level == "quick" else list(SCENES))
    for s in scenes:
        if s not in SCENES:
            raise SystemExit(f"unknown scene {s!r}; choose from {SCENES}")
    solvers = csv_list(args.solvers)
    for s in solvers:
        if s not in SOLVERS:
            raise SystemExit(f"unknown solver {s!r}; choose from {SOLVERS}")
    ref_substeps = args.ref_substeps or (QUICK_REF_SUBSTEPS if level == "quick" else REF_SUBSTEPS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    plan: list[tuple[str, int, Config]] = []
    scene_cache: dict[tuple[str, int], Scene] = {}
    for scene_name, size, main in sweep_layout(level, scenes, csv_list(args.sizes) if args.sizes else None):
        cfgs = main_sweep(level, solvers) if main else side_sweep(level, solvers)
        scene = scene_cache.setdefault((scene_name, size), make_scene(scene_name, size))
        plan += [(scene_name, size, c.for_scene(scene.params)) for c in cfgs]  # presets: the scene's substeps
    wanted = list(dict.fromkeys((s, n) for s, n, _ in plan))
    log.info(
        "tradeoff (%s): %d runs over %s, %.1f s simulated each",
        level,
        len(plan),
        ", ".join(f"{s}{n}" for s, n in wanted),
        args.duration,
    )
    truths = ensure_truths(wanted, out / "refcache", args.duration, ref_substeps, args.ref_iterations, args.jobs)
    for (s, n), (_, st) in truths.items():
        log.info(
            "ground truth %s%d: its own max strain %.2f%%, mean %.3f%%, energy drift %.3f (computed in %.0f s)",
            s,
            n,
            100 * st["max_strain"],
            100 * st["mean_strain"],
            st["energy_drift"],
            st["seconds"],
        )

    device = Device(args.device) if any(c.solver != "reference" for _, _, c in plan) else None
    version = code_version()
    records: list[dict] = []
    per_run: list[list[dict]] = []
    bar = progress(total=len(plan) * args.timing_rounds, desc="tradeoff", unit="run", quiet=args.quiet)
    for i, (sname, n, cfg) in enumerate(plan, 1):
        scene = scene_cache.get((sname, n)) or scene_cache.setdefault((sname, n), make_scene(sname, n))
        res = simulate(scene, cfg, device, truth=truths[(sname, n)][0], duration=args.duration)
        recs = res.records()
        for r in recs:
            r["code"] = version
            r["ms_rounds"] = [res.ms_per_frame]
        records += recs
        per_run.append(recs)
        m = res.metrics["float32"]
        bar.set_description(f"{sname}{n} {cfg.describe()}", refresh=False)
        bar.update()
        log.debug(
            "[%d/%d] %s %s: %.2f ms/frame, strain max %.2f%% mean %.3f%%, rms dev %.1f mm (early %.1f mm)",
            i,
            len(plan),
            scene.label,
            cfg.describe(),
            res.ms_per_frame,
            100 * m["max_strain"],
            100 * m["mean_strain"],
            1e3 * m["rms_dev"],
            1e3 * m["rms_dev_early"],
        )

    for rnd in range(1, args.timing_rounds):
        log.debug("timing round %d of %d (%d frames per configuration)", rnd + 1, args.timing_rounds, TIMING_FRAMES)
        order = list(range(len(plan)))
        if rnd % 2:
            order.reverse()  # so no configuration always sits next to the same neighbours in time
        for j in order:
            s, n, cfg = plan[j]
            frames = TIMING_FRAMES if cfg.solver != "reference" else 10
            ms = time_config(scene_cache[(s, n)], cfg, device, frames)
            bar.set_description(f"timing round {rnd + 1}: {s}{n} {cfg.describe()}", refresh=False)
            bar.update()
            for r in per_run[j]:
                r["ms_rounds"].append(ms)
    bar.close()
    for recs in per_run:
        for r in recs:
            r["ms_per_frame"] = min(r["ms_rounds"])
            r["ms_per_60hz"] = r["ms_per_frame"] * r["tick_hz"] / 60.0
            r["load"] = r["ms_per_frame"] * r["tick_hz"] / 1000.0

    records += truth_records(truths, args.ref_iterations, ref_substeps, args.duration, version)

    print(
        f"\nDrape tradeoff ({level}, code {version}) on {records[0]['device'] if records else '?'}; "
        f"{args.duration:g} s simulated "
        f"per run; ground truth: float64 reference, XPBD {ref_substeps} substeps x {args.ref_iterations} "
        f"iterations at {REF_TICK_HZ} Hz\n"
    )
    print(format_table(records))
    for r in records:
        if r["tag"] == "ground-truth":
            print(
                f"ground truth {r['scene']}{r['size']}: float64 reference, XPBD {r['substeps']} substeps x "
                f"{r['iterations']} iterations: its own strain max {_pct(r['max_strain']).strip()}% mean "
                f"{_pct(r['mean_strain']).strip()}%, at 2 s max {_pct(r['end_max_strain']).strip()}%; energy drift "
                f"{r['energy_drift']:.3f}; {r['ms_per_frame']:.0f} ms per frame"
            )
    print("\nEncodings (strain and deviation measured on what the client decodes):\n")
    print(format_encoding_table(records))
    summary = preset_summary(records)
    if summary:
        print("\n" + summary)

    json_path = Path(args.json) if args.json else out / "tradeoff.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(_jsonable(records), indent=1))
    print(f"\nrecords: {json_path}")
    for s, n in wanted:
        for err in ("max_strain", "rms_dev"):
            p = plot(records, out / f"tradeoff-{s}{n}-{err.replace('_', '-')}.png", s, n, err)
            if p:
                print(f"plot: {p}")
    log.info("tradeoff done in %.0f s", time.perf_counter() - t_start)
    return 0


def run_costs(args: argparse.Namespace) -> int:
    """``--costs``: the presets' costs as they run (tradeoffcost), written where quality.py reads."""
    from .tradeoffcost import measure_costs, write_costs

    extra = [Config("workgroup", 1, int(n), True, True, tag="front") for n in csv_list(args.cost_substeps)]
    size = {"size": int(csv_list(args.sizes)[0])} if args.sizes else {}
    res = measure_costs(
        device=args.device,
        rounds=args.cost_rounds,
        cloths=args.cost_cloths,
        extra=extra,
        progress=lambda r, n: print(f"round {r}/{n}", flush=True),
        accuracy=bool(args.cost_front),
        scene_name=args.cost_scene,
        **size,
    )
    for name, c in res["configs"].items():
        acc = f"  max {100 * c['max_strain']:6.2f} %  mean {100 * c['mean_strain']:6.3f} %" if "max_strain" in c else ""
        print(f"{name:<40} {c['cost']:6.3f}x  ({c['min']:.3f} .. {c['max']:.3f})  {np.median(c['ms']):8.3f} ms{acc}")
    path = write_costs(res, args.cost_file)
    if args.cost_front:
        from .tradeoffcost import plot_front

        print(f"front: {plot_front(res, Path(args.cost_front))}")
    print(f"{res['kind']}: {res['device']}, {res['cloths']} cloths, {res['rounds']} rounds -> {path}")
    return 0
