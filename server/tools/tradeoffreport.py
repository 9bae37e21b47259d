"""What ``drape tradeoff`` reports: the Pareto front, the tables, the error-against-cost plots,
the preset summary and the code version of the records."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------
# Pareto front, table, plot


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both cost (x) and error (y), by cost."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        x, y = points[i]
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        if y < best:
            front.append(i)
            best = y
    return front


def _pct(v: float) -> str:
    return "   inf" if not math.isfinite(v) else f"{100 * v:6.2f}"


def _mm(v: float) -> str:
    return "    nan" if v is None or not math.isfinite(v) else f"{1e3 * v:7.1f}"


def format_table(records: list[dict], encoding: str = "float32") -> str:
    head = (
        f"{'scene':10} {'solver':9} {'mode':8} {'it':>3} {'ss':>3} {'teth':4} {'Hz':>3} {'ms/frame':>8} "
        f"{'load%':>6} {'max%':>6} {'mean%':>6} {'late%':>6} {'end%':>6} {'rms mm':>7} {'early mm':>8} {'max mm':>7} "
        f"{'energy':>7}  tag"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        if r["encoding"] != encoding:
            continue
        mode = "xpbd" if r["xpbd"] else "pbd"
        if r["xpbd"] and r["compliance"]:
            mode = f"x{r['compliance']:.0e}"
        if r.get("chebyshev_rho"):
            mode += f"+c{r['chebyshev_rho']:g}"
        energy = r["energy_drift"]
        lines.append(
            f"{r['scene'] + str(r['size']):10} {r['solver']:9} {mode:8} {r['iterations']:>3} {r['substeps']:>3} "
            f"{'on' if r['tethers'] else 'off':4} {r['tick_hz']:>3} {r['ms_per_frame']:8.2f} "
            f"{100 * r['load']:6.1f} {_pct(r['max_strain'])} {_pct(r['mean_strain'])} "
            f"{_pct(r['late_max_strain'])} {_pct(r['end_max_strain'])} {_mm(r['rms_dev'])} "
            f"{_mm(r['rms_dev_early']):>8} {_mm(r['max_dev'])} "
            f"{energy:7.3f}  {r['tag']}"
        )
    return "\n".join(lines)


def format_encoding_table(records: list[dict]) -> str:
    head = (
        f"{'scene':10} {'config':38} {'encoding':8} {'enc rms mm':>10} {'enc max mm':>10} {'max%':>6} "
        f"{'mean%':>6} {'rms mm':>7}"
    )
    lines = [head, "-" * len(head)]
    for r in records:
        if not (
            r["tag"].startswith("preset:")
            or (
                r["iterations"] == 10
                and r["substeps"] == 1
                and not r["xpbd"]
                and not r["tethers"]
                and r["tick_hz"] == 60
            )
        ):
            continue
        cfg = (
            f"{r['solver']} {'xpbd' if r['xpbd'] else 'pbd'} {r['iterations']}x{r['substeps']}"
            + (" +teth" if r["tethers"] else "")
            + (f" ({r['tag']})" if r["tag"].startswith("preset") else "")
        )
        lines.append(
            f"{r['scene'] + str(r['size']):10} {cfg:38} {r['encoding']:8} {1e3 * r['enc_err_rms']:10.3f} "
            f"{1e3 * r['enc_err_max']:10.3f} {_pct(r['max_strain'])} {_pct(r['mean_strain'])} {_mm(r['rms_dev'])}"
        )
    return "\n".join(lines)


def plot(records: list[dict], path: Path, scene: str, size: int, error: str = "max_strain") -> Path | None:
    """Error against cost (ms per 1/60 s simulated), a series per solver, Pareto front marked."""
    from .plots import scatter_plot

    pts = [
        r
        for r in records
        if r["scene"] == scene
        and r["size"] == size
        and r["encoding"] == "float32"
        and r["finite"]
        and r.get(error) is not None
        and math.isfinite(r[error])
        and r[error] > 0
    ]
    if not pts:
        return None
    series: dict[str, tuple[list[float], list[float]]] = {}
    for r in pts:
        family = (
            f"{r['solver']} {'XPBD' if r['xpbd'] else 'PBD'}{' +tethers' if r['tethers'] else ''}"
            f"{' +Chebyshev' if r.get('chebyshev_rho') else ''}"
        )
        if r["tag"].startswith("preset:"):
            family = (
                "quality presets ("
                + "/".join(q["tag"][7:] for q in pts if q["tag"].startswith("preset:") and q["solver"] == r["solver"])
                + ")"
            )
        xs, ys = series.setdefault(family, ([], []))
        xs.append(r["ms_per_60hz"])
        ys.append(r[error] * (100.0 if "strain" in error else 1e3))
    allp = [(r["ms_per_60hz"], r[error]) for r in pts]
    front = pareto_front(allp)
    hx = [allp[i][0] for i in front]
    hy = [allp[i][1] * (100.0 if "strain" in error else 1e3) for i in front]
    unit = "%" if "strain" in error else "mm"
    label = {
        "max_strain": "max structural strain",
        "mean_strain": "mean structural strain",
        "rms_dev": "RMS deviation from reference",
        "rms_dev_early": "RMS deviation, first 0.5 s",
    }.get(error, error)
    scatter_plot(
        path,
        {k: series[k] for k in sorted(series)},
        title=f"{scene} {size}x{size}: {label} vs cost",
        xlabel=f"ms per 1/60 s simulated (step + blocking fetch), {_short_device(pts[0]['device'])}",
        ylabel=f"{label} ({unit})",
        logx=True,
        logy=True,
        highlight=(hx, hy),
        highlight_label="Pareto front",
        size=(1000, 640),
    )
    return path


def _short_device(name: str) -> str:
    return name.replace("Portable Computing Language", "PoCL").replace("pthread-", "")[:60]


def code_version() -> str:
    """The git commit of the running code, with "+dirty" when the tree has changes."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "unknown") + ("+dirty" if dirty else "")


def preset_summary(records: list[dict]) -> str:
    """Each preset's error and its cost relative to the plain 10-iteration PBD solve of the same
    scene, size, solver and tick rate, measured in this process."""
    lines = []
    base = {
        (r["scene"], r["size"], r["solver"], r["tick_hz"]): r
        for r in records
        if r["encoding"] == "float32"
        and not r["xpbd"]
        and not r["tethers"]
        and r["iterations"] == 10
        and r["substeps"] == 1
    }
    for r in records:
        if r["encoding"] != "float32" or not r["tag"].startswith("preset:"):
            continue
        b = base.get((r["scene"], r["size"], r["solver"], r["tick_hz"]))
        ratio = r["ms_per_frame"] / b["ms_per_frame"] if b else float("nan")
        lines.append(
            f"{r['scene'] + str(r['size']):10} {r['tag'][7:]:9} {r['solver']:9} "
            f"{r['ms_per_frame']:7.2f} ms ({ratio:4.2f}x the 10-iteration PBD solve)  strain max "
            f"{_pct(r['max_strain'])}% mean {_pct(r['mean_strain'])}%  rms dev {_mm(r['rms_dev'])} mm"
        )
    return ("Presets against the plain 10-iteration solve:\n" + "\n".join(lines)) if lines else ""


def _jsonable(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return _jsonable(obj.item())
    return obj
