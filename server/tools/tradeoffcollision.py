"""``drape tradeoff --collision``: the collision axis of the speed/accuracy trade (issue 22): what
substeps and self-collision (on or off, and its passes) cost against the penetration they leave,
on the penetration scenarios (drape.server.tools.penetration: every tick's pairs closer than the
thickness, vertices behind a collider, vertices that crossed one).

Each configuration runs every scenario once on a fresh World and gives, per scenario, the ticks
with anything left, the worst tick's pairs / behind / crossed, and the median ms per tick (the
World's step and the positions' read-back, one cloth: on a CPU shared with other runs a rough
ratio only). Self-collision's passes are the kernels' build constant
(``params.SELF_COLLISION_PASSES``): a device solver builds each count as its own program; the
reference always runs the constant's passes, so ``--collision-passes`` is for the OpenCL solvers.
The table, the records (JSON) and a plot of ticks with penetration against ms per tick go to OUT.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

from ..sim import make_world, params
from . import penetration as pen

log = logging.getLogger(__name__)


@contextlib.contextmanager
def self_collision_passes(n: int) -> Iterator[None]:
    """Device programs built meanwhile run ``n`` self-collision passes (Features.build_options
    reads the constant when it builds the options)."""
    was = params.SELF_COLLISION_PASSES
    params.SELF_COLLISION_PASSES = n
    try:
        yield
    finally:
        params.SELF_COLLISION_PASSES = was


def sweep(
    scenarios: list[str],
    substeps: list[int],
    passes: list[int],
    solver: str = "workgroup",
    size: str = "full",
    self_collision: tuple[bool, ...] = (True, False),
) -> list[dict]:
    """One record per scenario and configuration (substeps x self-collision on with each pass
    count, and off)."""
    configs = [(s, True, p) for s in substeps for p in passes if True in self_collision]
    configs += [(s, False, 0) for s in substeps if False in self_collision]
    out = []
    for sub, on, npasses in configs:
        base = pen.BASE.with_(substeps=sub, features=replace(pen.BASE.features, self_collision=on))
        for name in scenarios:
            with self_collision_passes(npasses or params.SELF_COLLISION_PASSES):
                world = make_world(solver)
                try:
                    records = pen.run(name, world, pen.SIZES[size], base=base)
                finally:
                    world.close()
            s = pen.summary(records)
            rec = {"scenario": name, "solver": solver, "size": size, "substeps": sub, "self_collision": on}
            rec["passes"] = npasses
            rec.update(s)
            log.info("%s", rec)
            out.append(rec)
    return out


def format_table(records: list[dict]) -> str:
    """Per configuration: each scenario's ticks with anything left / worst pairs / worst behind
    (crossed added where any), and the cape's ms per tick."""
    scenarios = list(dict.fromkeys(r["scenario"] for r in records))
    keys = list(dict.fromkeys((r["substeps"], r["self_collision"], r["passes"]) for r in records))
    head = "| substeps | self-collision | " + " | ".join(f"`{s}`" for s in scenarios) + " | ms per tick |"
    lines = [head, "|" + " --- |" * (3 + len(scenarios))]
    for sub, on, npasses in keys:
        cells, ms = [], []
        for s in scenarios:
            r = next(
                (
                    r
                    for r in records
                    if (r["scenario"], r["substeps"], r["self_collision"], r["passes"]) == (s, sub, on, npasses)
                ),
                None,
            )
            if r is None:
                cells.append("-")
                continue
            cell = f"{r['ticks_over_0']} / {r['max_pairs']} / {r['max_behind']}"
            cells.append(cell + (f" / {r['max_crossed']} crossed" if r["max_crossed"] else ""))
            ms.append(f"{r['ms_per_tick']:.1f}")
        label = f"on, {npasses} passes" if on else "off"
        lines.append(f"| {sub} | {label} | " + " | ".join(cells) + f" | {' / '.join(ms)} |")
    return "\n".join(lines)


def plot(records: list[dict], path: Path) -> Path | None:
    """Ticks with penetration left against ms per tick: a series per scenario and self-collision
    setting, its points the substeps (and pass counts)."""
    from .plots import scatter_plot

    series: dict[str, tuple[list[float], list[float]]] = {}
    for r in records:
        label = f"{r['scenario']}, self-collision " + (f"on ({r['passes']} passes)" if r["self_collision"] else "off")
        xs, ys = series.setdefault(label, ([], []))
        xs.append(r["ms_per_tick"])
        ys.append(r["ticks_over_0"] + 1)
    if not series:
        return None
    return scatter_plot(
        path,
        series,
        title="collision: penetration left against cost (points: substeps 1, 2, 4, 8 ...)",
        xlabel="ms per tick (one cloth, World step + read-back)",
        ylabel="ticks with penetration left + 1",
        logx=True,
        logy=True,
    )


def run(args) -> int:
    """``drape tradeoff --collision``: the sweep, its table, records and plot under ``args.out``."""
    from .procs import csv_list

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = sweep(
        csv_list(args.collision_scenarios),
        [int(v) for v in csv_list(args.collision_substeps)],
        [int(v) for v in csv_list(args.collision_passes)],
        solver=args.collision_solver,
        size=args.collision_size,
    )
    print(
        "each cell: ticks with anything left / the worst tick's pairs / vertices behind a collider; "
        "ms per tick per scenario, in the columns' order\n"
    )
    print(format_table(records))
    json_path = Path(args.json) if args.json else out / "tradeoff-collision.json"
    json_path.write_text(json.dumps(records, indent=1))
    print(f"\nrecords: {json_path}")
    p = plot(records, out / "tradeoff-collision.png")
    if p:
        print(f"plot: {p}")
    return 0
