"""``drape tradeoff``'s ground truths: the float64 numpy reference of every (scene, size), run
with XPBD, compliance 0, REF_SUBSTEPS x REF_ITERATIONS at REF_TICK_HZ (tradeoffrun.py), computed
in parallel processes where not cached under ``OUT/refcache`` (keyed by scene, size, duration,
settings, SCENE_VERSION and a digest of the reference's source), and their records."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from .tradeoffrun import REF_TICK_HZ, SCENE_VERSION, make_scene, reference_config, simulate

log = logging.getLogger(__name__)


#: The sources a ground truth depends on (server/sim): a change to any of them invalidates the cache.
TRUTH_SOURCES = ("reference.py", "fabric.py", "links.py", "tethers.py", "params.py")


def _source_digest() -> str:
    sim = Path(__file__).resolve().parent.parent / "sim"
    h = hashlib.sha1()
    for name in TRUTH_SOURCES:
        h.update((sim / name).read_bytes())  # a missing source is an error, never an empty digest
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


def truth_records(
    truths: dict[tuple[str, int], tuple[np.ndarray, dict]],
    ref_iterations: int,
    ref_substeps: int,
    duration: float,
    version: str,
) -> list[dict]:
    """One record per ground truth (its own strain and energy, the cost of computing it), in the
    form of the runs' records (tradeoffrun.RunResult.records)."""
    return [
        {
            "scene": s,
            "size": n,
            "solver": "reference",
            "iterations": ref_iterations,
            "substeps": ref_substeps,
            "xpbd": True,
            "tethers": False,
            "compliance": 0.0,
            "tick_hz": REF_TICK_HZ,
            "encoding": "float64",
            "tag": "ground-truth",
            "device": "numpy float64",
            "ms_per_frame": 1e3 * st["seconds"] / (duration * REF_TICK_HZ),
            "ms_p90": None,
            "ms_per_60hz": 1e3 * st["seconds"] / (duration * REF_TICK_HZ),
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
        for (s, n), (_, st) in truths.items()
    ]
