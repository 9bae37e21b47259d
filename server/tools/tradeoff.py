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
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..sim.params import SOLVERS
from .procs import progress, require_extra
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
    SCENE_VERSION,
    SCENES,
    TIMING_FRAMES,
    TIMING_ROUNDS,
    Config,
    Scene,
    make_scene,
    reference_config,
    simulate,
    time_config,
)

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# Ground truth (cached)


def _source_digest() -> str:
    here = Path(__file__).resolve().parent
    h = hashlib.sha1()
    for name in ("reference.py", "fabric.py"):
        p = here / name
        if p.exists():
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


def truth_path(cache: Path, scene: str, size: int, duration: float, substeps: int, iterations: int) -> Path:
    key = f"{scene}-{size}-{duration:g}s-{substeps}x{iterations}-v{SCENE_VERSION}-{_source_digest()}"
    return cache / f"truth-{key}.npz"


def _compute_truth(args: tuple[str, int, float, int, int, str]) -> str:
    scene_name, size, duration, substeps, iterations, path = args
    scene = make_scene(scene_name, size)
    t0 = time.perf_counter()
    res = simulate(
        scene, reference_config(substeps, iterations), encodings=("float32",), duration=duration, keep_snapshots=True
    )
    stats = {
        **res.metrics["float32"],
        "energy_drift": res.energy_drift,
        "energy_gain": res.energy_gain,
        "seconds": time.perf_counter() - t0,
        "finite": res.finite,
    }
    tmp = path + ".tmp.npz"
    np.savez_compressed(tmp, snapshots=np.array(res.snapshots), stats=json.dumps(stats))
    os.replace(tmp, path)
    return path


def ensure_truths(
    wanted: list[tuple[str, int]], cache: Path, duration: float, substeps: int, iterations: int, jobs: int
) -> dict[tuple[str, int], tuple[np.ndarray, dict]]:
    """Ground truths of every (scene, size), computed in ``jobs`` processes where not cached."""
    cache.mkdir(parents=True, exist_ok=True)
    paths = {w: truth_path(cache, *w, duration, substeps, iterations) for w in wanted}
    missing = [w for w, p in paths.items() if not p.exists()]
    if missing:
        log.info(
            "computing %d ground truth(s) (float64 reference, XPBD %d substeps x %d iterations) in %d process(es): %s",
            len(missing),
            substeps,
            iterations,
            min(jobs, len(missing)),
            ", ".join(f"{s}{n}" for s, n in missing),
        )
        t0 = time.perf_counter()
        work: list[tuple[str, int, float, int, int, str]] = [
            (s, n, duration, substeps, iterations, str(paths[(s, n)])) for s, n in missing
        ]
        # largest first so the pool finishes together
        work.sort(key=lambda w: -w[1])
        if jobs > 1 and len(work) > 1:
            with ProcessPoolExecutor(max_workers=min(jobs, len(work))) as ex:
                for p in ex.map(_compute_truth, work):
                    log.info("  ground truth written: %s (%.0f s so far)", Path(p).name, time.perf_counter() - t0)
        else:
            for item in work:
                log.info(
                    "  ground truth written: %s (%.0f s so far)",
                    Path(_compute_truth(item)).name,
                    time.perf_counter() - t0,
                )
    out = {}
    for w, path in paths.items():
        z = np.load(path)
        out[w] = (z["snapshots"], json.loads(str(z["stats"])))
    return out


# ---------------------------------------------------------------------------------------------
# Sweeps

PBD_ITERS_DEFAULT = (1, 2, 5, 10, 20, 50, 100)
XPBD_SUBSTEPS_DEFAULT = (1, 2, 5, 10, 20)


def main_sweep(level: str, solvers: list[str]) -> list[Config]:
    """Every knob on the main scene. ``level``: quick, default or full."""
    cfgs: list[Config] = []
    gpu_solvers = [s for s in ("workgroup", "coloured", "jacobi") if s in solvers]
    iters: tuple[int, ...]
    subs: tuple[int, ...]
    grid: tuple[tuple[int, int], ...]
    teth_iters: tuple[int, ...]
    teth_subs: tuple[int, ...]
    ref_iters: tuple[int, ...]
    ticks: tuple[int, ...]
    compl: tuple[float, ...]
    cheb_iters: tuple[int, ...]
    rhos: tuple[float, ...]
    if level == "quick":
        iters = (1, 5, 10, 30)
        subs = (1, 5, 10)
        grid = ((5, 2),)
        teth_iters = (2, 10)
        teth_subs = (5,)
        ref_iters = (10,)
        ticks = (30, 120)
        compl = ()
        cheb_iters, rhos = (10,), (0.95,)
    elif level == "full":
        iters = (1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100)
        subs = (1, 2, 3, 4, 5, 7, 10, 15, 20)
        grid = ((2, 2), (2, 5), (3, 3), (4, 2), (5, 2), (5, 3), (5, 5), (10, 2), (10, 3), (10, 5), (20, 2), (20, 5))
        teth_iters = (1, 2, 3, 5, 10, 20)
        teth_subs = (1, 2, 3, 4, 5, 7, 10, 15, 20, 30, 40, 50, 60, 70, 100)
        ref_iters = (1, 10, 100)
        ticks = (30, 120)
        compl = (1e-7, 1e-5, 1e-3)
        cheb_iters, rhos = (5, 10, 20, 50, 100), (0.9, 0.95, 0.99)
    else:
        iters = PBD_ITERS_DEFAULT
        subs = XPBD_SUBSTEPS_DEFAULT
        grid = ((2, 2), (4, 2), (5, 2), (10, 2), (5, 5))
        teth_iters = (1, 2, 5, 10, 20)
        teth_subs = (1, 2, 3, 5, 10, 30, 50, 100)
        ref_iters = (10, 100)
        ticks = (30, 120)
        compl = (1e-6, 1e-3)
        cheb_iters, rhos = (5, 10, 20, 50), (0.95,)
    for s in gpu_solvers:
        cfgs += [Config(s, i, 1, tag="pbd-iterations") for i in iters]
        cfgs += [Config(s, 1, n, xpbd=True, tag="xpbd-substeps") for n in subs]
    if "jacobi" in solvers:
        cfgs += [Config("jacobi", i, 1, chebyshev_rho=rho, tag="jacobi-chebyshev") for i in cheb_iters for rho in rhos]
        cfgs += [Config("jacobi", 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in (5, 10, 20)]
    if "reference" in solvers:
        cfgs += [Config("reference", i, 1, tag="pbd-iterations") for i in ref_iters]
        cfgs += [Config("reference", 1, 5, xpbd=True, tag="xpbd-substeps")]
    main = gpu_solvers[0] if gpu_solvers else "reference"
    for n, i in grid:
        cfgs.append(Config(main, i, n, xpbd=True, tag="xpbd-substeps-x-iterations"))
    cfgs += [Config(main, i, 1, tethers=True, tag="pbd-tethers") for i in teth_iters]
    cfgs += [Config(main, 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in teth_subs]
    for s in gpu_solvers[1:]:
        cfgs.append(Config(s, 10, 1, tethers=True, tag="pbd-tethers"))
        cfgs.append(Config(s, 1, 5, xpbd=True, tethers=True, tag="xpbd-tethers"))
    cfgs += [Config(main, 1, 10, xpbd=True, compliance=a, tag="xpbd-compliance") for a in compl]
    for hz in ticks:
        cfgs.append(Config(main, 10, 1, tick_hz=hz, tag="tick-rate"))
        cfgs.append(Config(main, 1, max(1, 5 * 60 // hz), xpbd=True, tethers=True, tick_hz=hz, tag="tick-rate"))
    if level != "quick" and main != "reference":
        # the ground truth's own settings in float32 on the device: how far float32 alone drifts
        cfgs.append(Config(main, REF_ITERATIONS, REF_SUBSTEPS, xpbd=True, tag="noise-floor"))
    cfgs += preset_configs(main)
    return _dedupe(cfgs)


def side_sweep(level: str, solvers: list[str]) -> list[Config]:
    """A few points on the other scenes and sizes: the baseline, Small Steps, tethers, presets."""
    gpu_solvers = [s for s in ("workgroup", "coloured", "jacobi") if s in solvers]
    main = gpu_solvers[0] if gpu_solvers else "reference"
    cfgs = [Config(main, i, 1, tag="pbd-iterations") for i in (5, 10, 20)]
    cfgs += [Config(main, 1, n, xpbd=True, tag="xpbd-substeps") for n in (5, 10)]
    cfgs += [Config(main, 10, 1, tethers=True, tag="pbd-tethers")]
    for s in gpu_solvers[1:]:
        cfgs.append(Config(s, 10, 1, tag="pbd-iterations"))
    cfgs += preset_configs(main)
    if level == "full":
        cfgs += [Config(main, i, 1, tag="pbd-iterations") for i in (1, 2, 50, 100)]
        cfgs += [Config(main, 1, n, xpbd=True, tag="xpbd-substeps") for n in (1, 2, 20)]
        cfgs += [Config(main, 1, n, xpbd=True, tethers=True, tag="xpbd-tethers") for n in (2, 5, 10)]
    return _dedupe(cfgs)


def sweep_layout(level: str, scenes: list[str], sizes: list[str] | None) -> list[tuple[str, int, bool]]:
    """(scene, size, main sweep?) for every scene and size to run. Without --sizes: --quick runs
    the main sweep on hanging 32 x 32; the default runs it on hanging 64 x 64 plus a few points
    on every scene at 32 x 32; --full runs it on every scene at 64 x 64 plus a few points at 32
    and 150."""
    if sizes is not None:
        ns = [int(v) for v in sizes]
        return [
            (s, n, (i == 0 and j == 0) or (level == "full" and j == 0))
            for i, s in enumerate(scenes)
            for j, n in enumerate(ns)
        ]
    if level == "quick":
        return [(s, 32, i == 0) for i, s in enumerate(scenes)]
    if level == "full":
        return [(s, 64, True) for s in scenes] + [(s, n, False) for n in (32, 150) for s in scenes]
    return [(scenes[0], 64, True)] + [(s, 32, False) for s in scenes]


def preset_configs(solver: str) -> list[Config]:
    try:
        from ..sim.quality import PRESETS
    except ImportError:
        return []
    return [Config.from_preset(name, solver) for name in PRESETS]


def _dedupe(cfgs: list[Config]) -> list[Config]:
    seen: dict[str, Config] = {}
    for c in cfgs:
        k = replace(c, tag="").__repr__()
        if k not in seen or c.tag.startswith("preset:"):
            seen[k] = c
    return list(seen.values())


# ---------------------------------------------------------------------------------------------
# CLI


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


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
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ..sim.opencl.device import Device

    level = "quick" if args.quick else "full" if args.full else "default"
    scenes = _csv(args.scenes) if args.scenes else (["hanging"] if level == "quick" else list(SCENES))
    for s in scenes:
        if s not in SCENES:
            raise SystemExit(f"unknown scene {s!r}; choose from {SCENES}")
    solvers = _csv(args.solvers)
    for s in solvers:
        if s not in SOLVERS:
            raise SystemExit(f"unknown solver {s!r}; choose from {SOLVERS}")
    ref_substeps = args.ref_substeps or (QUICK_REF_SUBSTEPS if level == "quick" else REF_SUBSTEPS)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    plan: list[tuple[str, int, Config]] = []
    for scene_name, size, main in sweep_layout(level, scenes, _csv(args.sizes) if args.sizes else None):
        cfgs = main_sweep(level, solvers) if main else side_sweep(level, solvers)
        plan += [(scene_name, size, c) for c in cfgs]
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
    scene_cache: dict[tuple[str, int], Scene] = {}
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

    for (s, n), (_, st) in truths.items():
        records.append(
            {
                "scene": s,
                "size": n,
                "solver": "reference",
                "iterations": args.ref_iterations,
                "substeps": ref_substeps,
                "xpbd": True,
                "tethers": False,
                "compliance": 0.0,
                "tick_hz": REF_TICK_HZ,
                "encoding": "float64",
                "tag": "ground-truth",
                "device": "numpy float64",
                "ms_per_frame": 1e3 * st["seconds"] / (args.duration * REF_TICK_HZ),
                "ms_p90": None,
                "ms_per_60hz": 1e3 * st["seconds"] / (args.duration * REF_TICK_HZ),
                "load": None,
                "finite": st["finite"],
                "energy_drift": st["energy_drift"],
                "energy_gain": st["energy_gain"],
                **{
                    k: st.get(k, float("nan"))
                    for k in ("max_strain", "mean_strain", "end_max_strain", "end_mean_strain", "late_max_strain")
                },
                "rms_dev": 0.0,
                "max_dev": 0.0,
                "rms_dev_early": 0.0,
                "enc_err_max": 0.0,
                "enc_err_rms": 0.0,
                "code": version,
            }
        )

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
