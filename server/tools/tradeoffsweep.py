"""``drape tradeoff``'s sweeps: which configurations run on which scene and size. The main sweep
turns every knob (solver, PBD iterations, XPBD substeps, their grid, tethers, Chebyshev, compliance,
tick rate, the noise floor, the quality presets) on the main scene; the side sweep puts a few
points on the other scenes and sizes; ``level`` is quick, default or full."""

from __future__ import annotations

from dataclasses import replace

from .tradeoffrun import REF_ITERATIONS, REF_SUBSTEPS, Config

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
