"""Quality presets: named solver settings picked from the measured speed/accuracy Pareto front.

``apply_preset(params, name)`` returns the cloth's parameters with the preset's iterations,
substeps, XPBD and tether switches. The substeps depend on the cloth's features, read at cook
time: a cloth in the wind or among colliders (``MOVING_FEATURES``) gets the preset's
``moving_substeps``, more than a still one's ``substeps`` (wind, colliders and the motion they
bring need short steps, which tethers and long-range links do not replace; docs/accuracy.md).
Presets never touch the material: an XPBD preset uses the material's own compliance (0, the
default, is an inextensible cloth, what PBD with stiffness 1 aims at); a material authored for
PBD with stiffness below 1 should give a compliance too.

The strains behind each preset (``drape tradeoff``, docs/accuracy.md) are for the hanging
cloth, 64 x 64, 60 Hz. ``cost`` is each preset's cost as it runs, in multiples of the plain
10-iteration PBD solve: measured in full packs (CPU) or a full device (GPU), interleaved against
PBD-10 in one process, by ``drape tradeoff --costs``, which writes ``COSTS_FILE``; this module
reads it (``costs(kind)``; ``Preset.cost`` is the CPU figure), never a number typed in. A moving
cloth's settings are costed the same way on a moving scene (``drape tradeoff --costs --cost-scene
flag``: the file's ``MOVING_KIND`` record, ``Preset.moving_cost``). A server uses them to estimate
what a change of preset frees or costs (QualityGovernor).

Adaptive quality, for a server under load (the tick loop owns the policy; this is the API):

    name = degrade(name)          # one step cheaper (the cheapest stays itself)
    name = restore(name, wanted)  # one step back up toward the preset the client asked for
    QualityGovernor               # a small hysteresis loop built on the two, optional

``degrade``/``restore`` only move along ``ORDER``; apply the result with ``apply_preset``
(``World.set_params``) between ticks. Changing iterations or tethers keeps a cloth in the same
kernel group; switching XPBD on or off or changing substeps regroups it (see clworld).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

from .params import ClothParams

COSTS_FILE = Path(__file__).with_name("preset_costs.json")  # written by `drape tradeoff --costs`
PRESET_TICK_HZ = 60.0  # the tick rate the presets' substeps are given for


MOVING_KIND = "{kind}-moving"  # the cost file's key of a moving scene's record (``--cost-scene flag``)


def measured(kind: str = "cpu", path: Path | None = None, moving: bool = False) -> dict[str, dict]:
    """Each configuration measured on a device of ``kind`` ("cpu" or "gpu") in the cost file:
    its record (``cost``: median ratio to PBD-10 over interleaved rounds, ``min``/``max``,
    ``iterations``/``substeps``, and where measured ``max_strain``/``mean_strain``); {} where
    none was measured. ``moving``: the record of a moving scene (``MOVING_KIND``: the presets at
    their moving settings against PBD-10 on that scene) instead of the hanging cloth's."""
    p = COSTS_FILE if path is None else Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError):
        return {}
    entry = data.get(MOVING_KIND.format(kind=kind) if moving else kind) or {}
    return dict(entry.get("configs", {}))


def costs(kind: str = "cpu", path: Path | None = None, moving: bool = False) -> dict[str, float]:
    """Each measured configuration's cost on a device of ``kind`` (see ``measured``)."""
    return {name: float(c["cost"]) for name, c in measured(kind, path, moving).items()}


def _unmeasured_cost(iterations: int, substeps: int) -> float:
    """A stand-in where the cost file has no figure: link sweeps per frame over PBD-10's."""
    return iterations * substeps / 10.0


# Features that make a cloth "moving" for the presets: it gets their ``moving_substeps``. Moving
# pins alone cannot be seen at cook time (the game moves them later); a cloth on a moving
# character usually has its body as a collider.
MOVING_FEATURES: tuple[str, ...] = ("wind", "colliders")


def is_moving(params: ClothParams) -> bool:
    """Whether ``params`` has one of ``MOVING_FEATURES`` on."""
    return any(getattr(params.features, f) for f in MOVING_FEATURES)


@dataclass(frozen=True)
class Preset:
    name: str
    iterations: int
    substeps: int  # at 60 Hz, for a cloth without MOVING_FEATURES (cost and strains: this one's)
    moving_substeps: int  # at 60 Hz, for a cloth with one of MOVING_FEATURES on
    xpbd: bool
    tethers: bool
    cost: float  # measured cost / the 10-iteration PBD solve's (hanging 64 x 64, 60 Hz; COSTS_FILE, CPU)
    max_strain: float  # measured on the same scene: largest structural strain over 2 s (nan: not)
    mean_strain: float  # mean structural strain, averaged over 2 s (nan: not measured)
    note: str = ""
    moving_iterations: int = 0  # iterations for a cloth with MOVING_FEATURES (0: ``iterations``)
    moving_cost: float = math.nan  # the moving settings' cost / PBD-10's on a moving scene (MOVING_KIND)

    def iterations_for(self, params: ClothParams) -> int:
        """The iterations this preset gives ``params``: ``moving_iterations`` where the cloth has
        one of MOVING_FEATURES (and the preset sets them), else ``iterations``."""
        return (self.moving_iterations or self.iterations) if is_moving(params) else self.iterations

    def cost_for(self, moving: bool) -> float:
        """The cost that predicts this preset on a moving (MOVING_FEATURES) or a still cloth."""
        return self.moving_cost if moving else self.cost

    def params(self, base: ClothParams) -> ClothParams:
        return apply_preset(base, self.name)

    def substeps_for(self, params: ClothParams, tick_hz: float = PRESET_TICK_HZ) -> int:
        """The substeps this preset gives ``params`` at ``tick_hz``: ``moving_substeps`` where the
        cloth has one of MOVING_FEATURES, else ``substeps``, scaled from 60 Hz so that the substep
        length stays the same (at most 100, at least 1)."""
        if not (math.isfinite(tick_hz) and tick_hz > 0):
            raise ValueError("tick_hz must be a positive number")
        n = self.moving_substeps if is_moving(params) else self.substeps
        return min(100, max(1, round(n * PRESET_TICK_HZ / tick_hz)))


# Cheapest first: (name, iterations, substeps at 60 Hz still, moving (MOVING_FEATURES) iterations
# and substeps, note).
# Cost and strains (hanging 64 x 64, float32 on the device, 2 s) come from COSTS_FILE (drape
# tradeoff --costs --cost-front), where the file's record was measured with the same iterations and
# substeps; docs/accuracy.md has the other scenes (cape, flag, curtain: moving), whose settings
# are the fewest substeps that keep every one of them within the strains of the presets before
# issue 24 (medians over 15 jittered starts, drape.server.tools.tradeoffstarts: their max strain is
# chaotic), and their costs (COSTS_FILE's moving record, Preset.moving_cost).
_SETTINGS = (
    ("fast", 1, 2, 1, 9, "at most the plain 10-iteration solve's cost; hanging 64 x 64 within 50 % / 1.5 %"),
    ("balanced", 1, 8, 1, 20, "at most 3x the plain solve; hanging 64 x 64 within 10 % / 0.3 %"),
    # moving: 100 substeps (80 left the cape's max and the curtain's max and mean above the old
    # accurate's on the same colliders; 100 only the curtain's max, which rises as the solve
    # converges on this code: docs/accuracy.md)
    ("accurate", 1, 80, 1, 100, "the old accurate's substeps on a still cloth"),
    # moving: 3 iterations at the substep cap (2 x 100 left the curtain's and the cape's max above
    # the old exact's on the same colliders; 3 x 100 is not above them, at 1.5x the sweeps)
    ("exact", 2, 100, 3, 100, "reference-like"),
)


def _preset(
    name: str, iterations: int, substeps: int, moving_it: int, moving_ss: int, note: str, kind: str = "cpu"
) -> Preset:
    """The preset with its costs and strains from COSTS_FILE's records for ``kind`` (the hanging
    cloth's for the still settings, MOVING_KIND's for the moving ones), each only where the
    record was measured with the same iterations and substeps (else link sweeps / 10, no strains)."""
    rec = measured(kind).get(name, {})
    same = rec.get("iterations") == iterations and rec.get("substeps") == substeps
    mrec = measured(kind, moving=True).get(name, {})
    msame = mrec.get("iterations") == moving_it and mrec.get("substeps") == moving_ss
    nan = float("nan")
    return Preset(
        name,
        iterations,
        substeps,
        moving_ss,
        True,
        True,
        float(rec["cost"]) if same else _unmeasured_cost(iterations, substeps),
        float(rec.get("max_strain", nan)) if same else nan,
        float(rec.get("mean_strain", nan)) if same else nan,
        note,
        moving_iterations=moving_it if moving_it != iterations else 0,
        moving_cost=float(mrec["cost"]) if msame else _unmeasured_cost(moving_it, moving_ss),
    )


PRESETS: dict[str, Preset] = {p.name: p for p in (_preset(*s) for s in _SETTINGS)}
ORDER: tuple[str, ...] = tuple(PRESETS)
DEFAULT = "balanced"


def preset(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown quality preset {name!r}; choose from {list(ORDER)}") from None


def apply_preset(params: ClothParams, name: str, tick_hz: float = PRESET_TICK_HZ) -> ClothParams:
    """``params`` with the preset's iterations, substeps, XPBD and tethers switched on or off.
    Material (stiffness, compliance, tether limit), gravity, wind and other features are kept.
    The substeps (and iterations) are the preset's moving ones where ``params`` has wind or
    colliders on (``MOVING_FEATURES``), else its still ones.

    Presets are defined at 60 Hz; at another ``tick_hz`` the substeps scale so that the substep
    length (what accuracy depends on, Small Steps) and the cost per simulated second stay the
    same: 20 substeps at 60 Hz are 10 at 120 Hz and 40 at 30 Hz (at most 100, at least 1)."""
    p = preset(name)
    substeps = p.substeps_for(params, tick_hz)
    features = replace(params.features, xpbd=p.xpbd, tethers=p.tethers)
    out = params.with_(iterations=p.iterations_for(params), substeps=substeps, features=features)
    out.validate()
    return out


def preset_of(params: ClothParams, tick_hz: float = PRESET_TICK_HZ) -> str | None:
    """The preset whose solver settings ``params`` has (at ``tick_hz``), or None."""
    for p in PRESETS.values():
        q = apply_preset(params, p.name, tick_hz)
        if (params.iterations, params.substeps, params.features) == (q.iterations, q.substeps, q.features):
            return p.name
    return None


def degrade(name: str) -> str:
    """The next cheaper preset (``fast`` stays ``fast``)."""
    i = ORDER.index(preset(name).name)
    return ORDER[max(i - 1, 0)]


def restore(name: str, wanted: str | None = None) -> str:
    """One step back up from ``name`` toward ``wanted`` (default: the most accurate), never
    above it; ``wanted`` itself once reached."""
    i = ORDER.index(preset(name).name)
    top = ORDER.index(preset(wanted).name) if wanted is not None else len(ORDER) - 1
    if i >= top:
        return ORDER[top] if i > top else name
    return ORDER[i + 1]


def can_degrade(name: str) -> bool:
    return ORDER.index(preset(name).name) > 0


class QualityGovernor:
    """Hysteresis around ``degrade``/``restore`` for one server (or one cloth).

    Call ``update(frame_ms)`` once per tick with the measured device time of the tick; it returns
    the preset to use next. Over ``budget_ms`` for ``patience`` ticks in a row: one step down.
    Under ``headroom`` x budget for ``patience * 4`` ticks in a row (and the next preset up is
    predicted to fit, from the presets' costs measured on a device of ``kind``, "cpu" or "gpu",
    in COSTS_FILE): one step back up toward ``wanted``.

    ``moving``: the share (0..1, or a bool) of the governed work that is moving cloths (wind or
    colliders: MOVING_FEATURES), whose presets run other settings at other costs (COSTS_FILE's
    MOVING_KIND record); a preset's predicted cost is the still and the moving cost mixed by it."""

    def __init__(
        self,
        wanted: str = DEFAULT,
        budget_ms: float = 16.0,
        patience: int = 3,
        headroom: float = 0.6,
        kind: str = "cpu",
        moving: float = 0.0,
    ) -> None:
        presets = [_preset(*s, kind=kind) for s in _SETTINGS]
        self.still_cost = {p.name: p.cost_for(False) for p in presets}
        self.moving_cost = {p.name: p.cost_for(True) for p in presets}
        self.moving = float(moving)
        self.wanted = preset(wanted).name
        self.current = self.wanted
        self.budget_ms = float(budget_ms)
        self.patience = int(patience)
        self.headroom = float(headroom)
        self._over = 0
        self._under = 0

    @property
    def cost(self) -> dict[str, float]:
        """Each preset's predicted cost (x PBD-10) for the governed mix of still and moving cloths."""
        m = min(max(self.moving, 0.0), 1.0)
        return {n: (1.0 - m) * c + m * self.moving_cost[n] for n, c in self.still_cost.items()}

    def update(self, frame_ms: float) -> str:
        if frame_ms > self.budget_ms:
            self._over += 1
            self._under = 0
            if self._over >= self.patience and can_degrade(self.current):
                self.current = degrade(self.current)
                self._over = 0
        else:
            self._over = 0
            up = restore(self.current, self.wanted)
            cost = self.cost
            predicted = frame_ms * cost[up] / cost[self.current]
            if up != self.current and frame_ms < self.headroom * self.budget_ms and predicted < self.budget_ms:
                self._under += 1
                if self._under >= 4 * self.patience:
                    self.current = up
                    self._under = 0
            else:
                self._under = 0
        return self.current
