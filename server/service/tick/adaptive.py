"""Adaptive quality for the device-bound case, built on quality.QualityGovernor.

One governor per server holds a *cap*: the most expensive preset any cloth may run while ticks
overrun. Each tick the tick thread feeds it the tick's cost (``observe``, O(1)); when the
governor steps the cap down or back up, every cloth that chose a preset gets ``min(wanted,
cap)`` (the only O(cloths) work, on a change). ``measure`` maps the measured seconds to the
cost fed to the governor; tests replace it to drive the loop deterministically.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from typing import Any, cast

from ...sim import quality
from ...sim.world import World
from ..config import ServerConfig
from ..registry import ClothRecord

log = logging.getLogger(__name__)

QUALITY_PATIENCE = 3  # ticks over budget in a row before presets step down (x4 under, to step up)
QUALITY_HEADROOM = 0.6  # step back up only when ticks take less than this share of the budget

_RANK = {name: i for i, name in enumerate(quality.ORDER)}


class AdaptiveQuality:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.governor: quality.QualityGovernor
        self.use_device(is_gpu=False)  # the CPU's costs until the server knows its World's device
        self.measure: Callable[[float], float] = lambda seconds: seconds
        self.events = 0
        self.last: dict[str, Any] | None = None
        self.degraded_since: int | None = None
        self.degraded_s = 0.0
        self._last_check = time.monotonic()
        self._share_of = -1  # how many cloths in the World the governor's moving share was last taken over

    def use_device(self, is_gpu: bool) -> None:
        """A governor with the presets' costs of the world's kind of device (quality.COSTS_FILE
        keeps the CPU's and the GPU's): the server calls it once the World exists, before the
        first tick."""
        self.governor = quality.QualityGovernor(
            quality.ORDER[-1],
            1e3 * self.config.quality_budget * self.config.dt,
            QUALITY_PATIENCE,
            QUALITY_HEADROOM,
            kind="gpu" if is_gpu else "cpu",
        )

    def preset_for(self, wanted: str) -> str:
        """What a cloth asking for ``wanted`` runs now."""
        cap = self.governor.current
        return wanted if _RANK[wanted] <= _RANK[cap] else cap

    def observe(
        self,
        tick_s: float,
        tick: int,
        records: Callable[[], Iterable[ClothRecord]],
        world: World | None,
        apply: Callable[[ClothRecord, str], bool],
    ) -> None:
        """One tick's cost; steps presets when the governor moves. ``apply(record, preset)``
        sets a cloth's preset (True when it changed)."""
        now = time.monotonic()
        if self.degraded_since is not None:
            self.degraded_s += now - self._last_check
        self._last_check = now
        if not self.config.adaptive_quality:
            return
        g = self.governor
        g.budget_ms = 1e3 * self.config.quality_budget * self.config.dt
        before = g.current
        g.update(1e3 * self.measure(tick_s))
        # the cloths in the World (a submission's record exists, without a handle, from its
        # admission until the tick that adds it: counted then, its share would never be taken)
        recs = [r for r in records() if r.quality_wanted is not None and r.handle is not None]
        if g.current == before and len(recs) == self._share_of:
            return
        if world is not None and recs:  # its next predictions: this share of moving cloths' costs
            # taken again when it steps and when cloths came or went (one arriving after the
            # governor settled would otherwise leave the share of the cloths before it)
            g.moving = sum(quality.is_moving(world.cloths[cast(int, r.handle)].params) for r in recs) / len(recs)
        self._share_of = len(recs)
        if g.current == before:
            return
        if _RANK[g.current] < _RANK[before]:
            top = max((_RANK[r.quality or cast(str, r.quality_wanted)] for r in recs), default=0)
            if top <= _RANK[g.current]:  # the cap was above every cloth: step down from the highest one
                g.current = quality.ORDER[max(top - 1, 0)]
            direction = "down"
        else:
            direction = "up"
        # cast: recs has only records with a wanted preset
        changed = sum(1 for r in recs if apply(r, self.preset_for(cast(str, r.quality_wanted))))
        if not changed:
            if direction == "down" and recs:
                g.current = before  # nothing cheaper to go to
            return
        degraded = sum(1 for r in recs if r.quality != r.quality_wanted)
        if degraded and self.degraded_since is None:
            self.degraded_since = time.time_ns()
        elif not degraded:
            self.degraded_since = None
        self.events += 1
        self.last = {"tick": tick, "time_ns": time.time_ns(), "direction": direction, "cloths": changed}
        log.info(
            "adaptive quality: %d cloths one preset %s at tick %d (%d below what they asked for)",
            changed,
            direction,
            tick,
            degraded,
        )

    def stats(self, records: Iterable[ClothRecord]) -> dict[str, Any]:
        by: dict[str, int] = {}
        degraded = 0
        for r in records:
            if r.quality is not None and r.handle is not None:
                by[r.quality] = by.get(r.quality, 0) + 1
                degraded += r.quality != r.quality_wanted
        return {
            "adaptive": self.config.adaptive_quality,
            "presets": by,
            "degraded": degraded,
            "degraded_since_ns": self.degraded_since,
            "degraded_s": round(self.degraded_s, 3),
            "changes": self.events,
            "last_change": self.last,
        }
