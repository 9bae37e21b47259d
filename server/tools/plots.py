"""The tools' charts, drawn with matplotlib (Agg, no pyplot state): a histogram with labelled
markers (load-test latency), line plots (server time per tick phase, load-test summary) and
scatter plots with a highlighted front (tradeoff: error against cost, the Pareto front).

Each function writes one PNG and returns its path. matplotlib is imported inside the functions
(the ``tools`` extra), so importing this module costs nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

MARKERS = ("o", "s", "^", "D", "v", "x", "P")
DPI = 100


def _figure(size: tuple[int, int]) -> Any:
    """A figure on its own Agg canvas: no pyplot, no global backend, safe in any thread."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] / DPI, size[1] / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | Path) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, format="png")
    return p


def _scales(ax: Any, logx: bool, logy: bool) -> None:
    """Log axes where asked, their ticks written as plain numbers (0.5, 2, 100)."""
    from matplotlib.ticker import FuncFormatter

    def minor_label(axis: Any) -> Any:
        def fmt(v: float, _: Any) -> str:
            lo, hi = axis.get_view_interval()
            if v <= 0 or lo <= 0 or hi / lo > 100:  # two decades or more: the powers of ten suffice
                return ""
            return f"{v:g}" if round(v / 10 ** math.floor(math.log10(v))) in (2, 3, 5) else ""

        return FuncFormatter(fmt)

    for on, axis, scale in ((logx, ax.xaxis, ax.set_xscale), (logy, ax.yaxis, ax.set_yscale)):
        if on:
            scale("log")
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(minor_label(axis))


def _finite(xs: Any, ys: Any, logx: bool = False, logy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The points with finite coordinates (and positive ones on log axes)."""
    x = np.asarray(xs, np.float64).ravel()
    y = np.asarray(ys, np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in length: {x.shape[0]} and {y.shape[0]}")
    ok = np.isfinite(x) & np.isfinite(y)
    if logx:
        ok &= x > 0
    if logy:
        ok &= y > 0
    return x[ok], y[ok]


def histogram(
    path: str | Path,
    values: Any,
    *,
    bins: int = 60,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "count",
    markers: Mapping[str, float] | None = None,
    size: tuple[int, int] = (800, 500),
) -> Path:
    """Histogram of the finite ``values`` with a dashed vertical line per marker
    (``{"p50": 1.2, "p99": 3.4}``); the legend gives the sample count and each marker's value."""
    v = np.asarray(values, np.float64).ravel()
    bad = int(np.count_nonzero(~np.isfinite(v)))
    v = v[np.isfinite(v)]
    fig = _figure(size)
    ax = fig.add_subplot()
    label = f"n = {len(v)}" + (f", {bad} non-finite skipped" if bad else "")
    if len(v):
        ax.hist(v, bins=max(1, int(bins)), color="tab:blue", edgecolor="#14507f", linewidth=0.5, label=label)
    else:
        ax.text(0.5, 0.5, "no samples", transform=ax.transAxes, ha="center", va="center")
    colours = ("tab:red", "tab:orange", "tab:green", "tab:purple")
    for i, (name, x) in enumerate(sorted((markers or {}).items(), key=lambda kv: kv[1])):
        if x is None or not math.isfinite(float(x)):
            continue
        ax.axvline(
            float(x), color=colours[i % len(colours)], linestyle="--", linewidth=1.5, label=f"{name} = {float(x):.4g}"
        )
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid(alpha=0.3)
    if len(v):
        ax.legend()
    return _save(fig, path)


def _lines(ax: Any, series: Mapping[str, tuple[Any, Any]], dashed: Sequence[str], logx: bool, logy: bool) -> None:
    for i, (name, (xs, ys)) in enumerate(series.items()):
        x, y = _finite(xs, ys, logx, logy)
        if name in dashed:
            ax.plot(x, y, linestyle="--", color="0.35", label=name)
        else:
            ax.plot(x, y, marker=MARKERS[i % len(MARKERS)], markersize=3, linewidth=1.2, label=name)
    _scales(ax, logx, logy)
    ax.grid(alpha=0.3, which="both")
    if series:
        ax.legend(fontsize="small")


def line_plot(
    path: str | Path,
    series: Mapping[str, tuple[Any, Any]],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    dashed: Sequence[str] = (),
    size: tuple[int, int] = (800, 500),
) -> Path:
    """One line per series ``{label: (xs, ys)}``; series named in ``dashed`` are dashed without
    markers (budgets, limits). Non-finite points are left out."""
    fig = _figure(size)
    ax = fig.add_subplot()
    _lines(ax, series, dashed, logx, logy)
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    return _save(fig, path)


def stacked_line_plots(
    path: str | Path,
    panels: Sequence[tuple[str, Mapping[str, tuple[Any, Any]]]],
    *,
    title: str = "",
    xlabel: str = "",
    logx: bool = False,
    dashed: Sequence[str] = (),
    size: tuple[int, int] = (800, 700),
) -> Path:
    """Panels ``(ylabel, series)`` stacked over one shared x axis, each drawn as in :func:`line_plot`."""
    fig = _figure(size)
    axes = fig.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    for ax, (ylabel, series) in zip(axes, panels, strict=True):
        _lines(ax, series, dashed, logx, False)
        ax.set(ylabel=ylabel)
    axes[0].set(title=title)
    axes[-1].set(xlabel=xlabel)
    return _save(fig, path)


def scatter_plot(
    path: str | Path,
    series: Mapping[str, tuple[Any, Any]],
    *,
    title: str = "",
    xlabel: str = "",
    ylabel: str = "",
    logx: bool = False,
    logy: bool = False,
    highlight: tuple[Any, Any] | None = None,
    highlight_label: str = "",
    size: tuple[int, int] = (1000, 640),
) -> Path:
    """Points per series ``{label: (xs, ys)}`` (a colour and marker each); ``highlight`` is drawn
    as a black line with dots over them (a Pareto front)."""
    fig = _figure(size)
    ax = fig.add_subplot()
    for i, (name, (xs, ys)) in enumerate(series.items()):
        x, y = _finite(xs, ys, logx, logy)
        ax.scatter(x, y, s=22, marker=MARKERS[(i // 10) % len(MARKERS)], color=f"C{i % 10}", label=name)
    if highlight is not None:
        x, y = _finite(*highlight, logx, logy)
        order = np.argsort(x, kind="stable")
        ax.plot(x[order], y[order], "k-", marker="o", markersize=4, linewidth=1.5, label=highlight_label or None)
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    _scales(ax, logx, logy)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize="small", loc="best")
    return _save(fig, path)
