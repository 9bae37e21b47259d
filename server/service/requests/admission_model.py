"""Admission's cost model: each tick stage's seconds at a load, measured on the server's own ticks.

The tick thread, the device and the publisher thread run as a pipeline: the device steps tick
N + 1 while the tick thread applies commands and the publisher encodes and puts frame N. So a
tick's period is bounded by its slowest stage, not by the sum of the stages. The tick thread
reports each steady tick's cost (no cloth came or went since the frame before: those ticks carry
one-off rebuilds) as a :class:`TickCost`, one figure per stage:

- ``tick``: the tick thread's own work (apply, enqueue, checks), without its wait for the device;
- ``device``: the device's step and readback (its profiling; the tick thread's wait without it);
- ``publisher``: the publisher's encode (or copy) and put of a frame.

(Python in the tick and publisher threads shares one GIL; a put releases it. Where the GIL
becomes the limit, the tick thread's work plus the publisher's encode would be a fourth stage;
on the machines measured so far one of the three above limits first: docs/loadtest.md.)

:class:`MeasuredCost` fits each stage as ``base + slope x vertices`` over recent steady ticks
at several loads and predicts each stage at a new load; a submit is refused with the protocol's
``overloaded`` error when the largest predicted stage, with the submit's vertices and those of
every cloth already admitted but not yet stepped, exceeds ``admission_budget`` of a tick, so the
cloths already admitted keep their rate. Refusals are counted (``overload_refusals``). A server
with no cloth admits (there is nothing to protect and nothing to predict from).

Four rules keep the prediction on the side that holds. Offered twice what this 2-core CPU holds
(docs/loadtest.md, session 13; docs/results/loadtest-cpu-s13-admission-*.json), the model before
them admitted 198-768 ``fast`` cloths where about 256 hold, and 5 runs of 10 missed 41-700 ticks;
with them, 177-272 in 5 runs, at most 4 missed ticks, p99 at most 31 ms:

- **Each load's point is the 90th percentile of its ticks** (``QUANTILE``), not the median. A
  pipeline keeps its rate only while nearly every tick fits, and on a CPU device the spread is
  wide: at 305 cloths the device took 14.6 ms at the median (under the 14.2 ms budget: admitted)
  and 18-22 ms at the 90th percentile, 16.4 ms on average: 65 missed ticks. The budget of 0.85 is
  margin for what the measurement did not see (other load on the machine later), not for the
  spread of the ticks measured.
- **Never below the proportional line through the largest load measured**: each stage's
  prediction is at least that load's point x ``vertices / load``. A line fitted over small and
  large loads takes its base from the small ones and under-predicts past the largest (on the
  CPU the device's time grows in proportion to the load near the knee: 256 -> 312 cloths, x1.22
  and x1.22); during a burst of submits the last measured load may be a half or a third of what
  is being admitted. For any cost with a non-negative fixed part the proportional line is on the
  safe side past that load and under the truth below it, so it never refuses inside what was
  measured.
- **A burst is judged on several ticks, not the last one.** While submits arrive every tick no
  load is seen for ``MIN_SAMPLES`` ticks, and the model used to stand on the latest load's one
  or two ticks: a cheap one (6.9 ms where the ticks around it took 12-16) admitted 24 cloths in
  one go. Now the median of the last ``MIN_SAMPLES`` ticks, each scaled to the latest load,
  stands in (:meth:`MeasuredCost.stand_in`).
- **Nothing measured, little admitted.** Before the first steady tick the model has no opinion;
  it used to admit everything then, and a burst arriving while the first cloths' kernels built
  was admitted whole (session 13, four logged runs: 12 to 204 cloths; one unlogged run of the
  old model admitted all 768 offered and ran at 25.9 Hz). Now a server with
  nothing measured admits up to ``admission_unmeasured_vertices`` (server/service/config.py;
  default 65,536, 64 cloths of 32 x 32: what a CPU device surely holds), and
  refuses (``overloaded``: retry later) past it until a steady tick is measured. A GPU holds
  thousands: its operator raises the setting so that a level's first burst is not refused.

The loads are in work units (the pricing in ``admission.py``); the budget (``admission_budget`` x dt,
server/service/config.py) is the share of a tick the slowest stage may take.
"""

from __future__ import annotations

import logging
import math
import statistics
import threading
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from ..config import ServerConfig

log = logging.getLogger(__name__)

STAGES: tuple[str, ...] = ("tick", "device", "publisher")

# MeasuredCost's defaults (model constants: not server settings)
PER_LOAD = 60  # steady ticks kept per load (one second at 60 Hz): each load's QUANTILE per stage
QUANTILE = 0.9  # each load's point per stage: this quantile of its ticks (nearest rank; the max below 10 ticks)
LOADS = 8  # distinct loads kept (the least recently observed goes first)
MIN_SAMPLES = 5  # a load enters the fit once it has this many steady ticks; before any has, the last
# this many ticks (of loads down to 1 / STAND_IN_SPAN of the latest) stand in, each scaled to the latest load
STAND_IN_SPAN = 2.0
UNMEASURED_VERTICES = ServerConfig.admission_unmeasured_vertices  # admitted before the first steady tick (the default)
UNMEASURED = "unmeasured"  # the "stage" of a prediction refused because nothing was measured yet
MIN_SPREAD = 1.1  # the fit needs its largest load at least this many times its smallest
TRUST = 0.5  # below this share of the budget, a load that cannot be fitted admits (once a load) ...
TRUST_LIMIT = 4.0  # ... a submit that, were every second measured per vertex, would take at most this many budgets
TRUST_GROWTH = 2.0  # ... and that at most this many times the load measured, or a cloth of at most
TRUST_SMALL = 4096  # vertices (a 64x64): one 256x256 beside a small steady load is not trusted (issue 26)
PRIOR_MARGIN = 3.0  # trust also where the device's cost file, this many times over, puts the load within budget
# (this shared CPU ran 2-3x slower under others' load, docs/collision.md): a small load's proportional line
# counts its fixed costs per work unit and refused any heavy-solve cloth beside it (drape chaos share)


@dataclass(frozen=True)
class TickCost:
    """One steady tick: the vertices it stepped and each pipeline stage's seconds."""

    vertices: int
    tick_s: float  # the tick thread's own work, not its wait for the device
    device_s: float  # the device's step and readback
    publish_s: float  # the publisher's encode (or copy) and put

    def stages(self) -> dict[str, float]:
        return {"tick": self.tick_s, "device": self.device_s, "publisher": self.publish_s}


@dataclass(frozen=True)
class Line:
    """``base_s + slope_s * vertices``."""

    base_s: float
    slope_s: float

    def __call__(self, vertices: int) -> float:
        return self.base_s + self.slope_s * vertices


def quantile(xs: list[float], q: float = QUANTILE) -> float:
    """The ``q`` quantile of ``xs`` by nearest rank: the smallest value with at least ``q`` of
    them at or below it (0.5: the lower median; 0.9 of fewer than 10 values: the largest)."""
    if not xs:
        raise ValueError("quantile needs at least one value")
    return sorted(xs)[max(0, math.ceil(q * len(xs) - 1e-9) - 1)]  # 1e-9: 0.9 x 10 is not quite 9 in binary


def separable(loads: list[int], min_spread: float = MIN_SPREAD) -> bool:
    """Whether costs at these loads can tell a fixed cost from a per-vertex one: at least two
    loads, the largest at least ``min_spread`` times the smallest."""
    return len(loads) >= 2 and max(loads) >= min_spread * min(loads)


def fit_line(points: list[tuple[int, float, int]], min_spread: float = MIN_SPREAD) -> Line:
    """Weighted least squares of ``(vertices, seconds, weight)`` points (one per load) with a
    non-negative base and slope. When the loads are not :func:`separable`, or the fit comes out
    with a negative slope (noise, or a cost that does not grow), the line goes through the
    origin and the largest load's point: every second counted per vertex, which over-predicts
    any larger load (the conservative side)."""
    if not points:
        raise ValueError("fit_line needs at least one point")
    big = max(points, key=lambda p: p[0])
    proportional = Line(0.0, big[1] / big[0])
    if not separable([p[0] for p in points], min_spread):
        return proportional
    w = sum(p[2] for p in points)
    mv = sum(p[2] * p[0] for p in points) / w
    mc = sum(p[2] * p[1] for p in points) / w
    svv = sum(p[2] * (p[0] - mv) ** 2 for p in points)
    slope = sum(p[2] * (p[0] - mv) * (p[1] - mc) for p in points) / svv
    if slope <= 0.0:
        return proportional
    base = mc - slope * mv
    if base < 0.0:  # through the origin: the least-squares slope of a line with no fixed cost
        return Line(0.0, sum(p[2] * p[0] * p[1] for p in points) / sum(p[2] * p[0] ** 2 for p in points))
    return Line(base, slope)


def describe(costs: list[TickCost]) -> str:
    """Each stage's median / ``QUANTILE`` (what the model takes, :func:`quantile`) / max over
    ``costs``, in ms (for the logs)."""
    out = []
    for s in STAGES:
        xs = [c.stages()[s] for c in costs]
        out.append(f"{s} {1e3 * statistics.median(xs):.2f}/{1e3 * quantile(xs):.2f}/{1e3 * max(xs):.2f}")
    return ", ".join(out) + f" ms (median/q{QUANTILE:g}/max)"


class Fit(NamedTuple):
    """What :meth:`MeasuredCost.fit` found: the latest load, each stage's fitted line, whether
    the loads were :func:`separable`, and each stage's proportional line through the largest
    load's point (the floor of every prediction)."""

    latest: int
    lines: dict[str, Line]
    fitted: bool
    floors: dict[str, Line]


class CostModel(Protocol):
    def observe(self, cost: TickCost) -> None: ...

    def predict(
        self, vertices: int, budget_s: float = float("inf"), cloth_vertices: int = 0
    ) -> dict[str, float] | None: ...

    def capacity(self, budget_s: float) -> float | None: ...


def _room(line: Line, budget_s: float) -> float:
    """The largest load ``line`` puts within ``budget_s`` (inf: a line that does not grow)."""
    if line.base_s > budget_s:
        return 0.0
    return math.inf if line.slope_s <= 0.0 else (budget_s - line.base_s) / line.slope_s


@dataclass
class FixedCost:
    """A cost model that does not measure: one stage of ``base_s + per_vertex_s * vertices``."""

    per_vertex_s: float
    base_s: float = 0.0

    def observe(self, cost: TickCost) -> None:
        pass

    def predict(
        self, vertices: int, budget_s: float = float("inf"), cloth_vertices: int = 0
    ) -> dict[str, float] | None:
        return {"fixed": self.base_s + self.per_vertex_s * vertices}

    def capacity(self, budget_s: float) -> float | None:
        return _room(Line(self.base_s, self.per_vertex_s), budget_s)


class MeasuredCost:
    """Each stage of the tick as ``base + slope x vertices``, fitted over the loads seen lately.

    Steady ticks are kept by load (vertices stepped): the last ``per_load`` ticks of each of the
    last ``loads`` loads. Each load with ``min_samples`` ticks gives one point per stage, its
    ``quantile`` (0.9: one tick in ten stretched by a one-off, a burst of requests taking the GIL,
    a descheduled thread, does not count; one in five does), weighted by its tick count;
    :func:`fit_line` fits them. Until some load has ``min_samples`` ticks, the last ticks of any
    nearby load stand in (:meth:`stand_in`: a burst of submits changes the load every tick, and
    the model must not wait for a quiet moment to have an opinion). ``predict`` takes each
    stage's line or, where it is larger, the proportional line through the largest load's point
    (the module docstring says why); before the first steady tick it has no opinion (None) up to
    ``unmeasured`` vertices and refuses past them (the stage ``UNMEASURED``, infinite).

    A server that has measured only one load cannot tell its fixed costs from its per-vertex
    ones, and counting them all per vertex (the conservative fallback) would refuse a second
    cloth next to one small one. So while the loads are not separable and the largest stage at
    the latest load is under ``trust`` of the budget, ``predict`` answers None (no opinion:
    admit) **once per load measured**, and only for a submit that the conservative line puts
    under ``trust_limit`` budgets and that at most doubles the load or is a cloth of at most
    ``TRUST_SMALL`` vertices (a 256 x 256 beside a small steady load was trusted in 3 runs of 5
    and took the server to 13-34 Hz, issue 26): the next submit is predicted conservatively
    until a tick with a new load is measured. The old rule (admit while light) let a burst of submits arriving
    between two measurements through unchecked (docs/loadtest.md, session 12: 494 cloths
    admitted where 384 hold), and any one huge cloth beside a small one (``drape chaos``'s
    big-submit); now a burst grows the load by one trusted cloth, then by what the conservative
    line allows, and once two loads are measured by what the fit allows."""

    def __init__(
        self,
        per_load: int = PER_LOAD,
        loads: int = LOADS,
        min_samples: int = MIN_SAMPLES,
        trust: float = TRUST,
        min_spread: float = MIN_SPREAD,
        trust_limit: float = TRUST_LIMIT,
        q: float = QUANTILE,
        unmeasured: int = UNMEASURED_VERTICES,
        prior_s: float = 0.0,
    ) -> None:
        if per_load < min_samples or min_samples < 1 or loads < 1 or not 0.0 < q <= 1.0:
            raise ValueError("MeasuredCost needs 1 <= min_samples <= per_load, loads >= 1 and 0 < q <= 1")
        self.per_load, self.loads, self.min_samples = per_load, loads, min_samples
        self.trust, self.min_spread, self.trust_limit, self.q = trust, min_spread, trust_limit, q
        self.unmeasured = unmeasured
        self.prior_s = prior_s  # the device's seconds per work unit as measured offline (Pricing.work_s)
        self._by_load: OrderedDict[int, deque[TickCost]] = OrderedDict()  # least recently observed first
        self._trusted_at = 0  # the latest load when predict last answered None on trust
        self._observed = 0  # steady ticks observed so far (the fit is cached until the next one)
        self._fit: tuple[int, Fit | None] = (-1, None)
        self._lock = threading.Lock()
        self._recent: deque[TickCost] = deque(maxlen=min_samples)  # the last steady ticks, of any load
        self._unlogged: dict[int, int] = {}  # each kept load's ticks since its figures were last logged

    def observe(self, cost: TickCost) -> None:
        if cost.vertices <= 0:
            return
        with self._lock:
            q = self._by_load.get(cost.vertices)
            if q is None:
                q = self._by_load[cost.vertices] = deque(maxlen=self.per_load)
            q.append(cost)
            self._recent.append(cost)
            self._observed += 1
            self._by_load.move_to_end(cost.vertices)
            while len(self._by_load) > self.loads:
                self._unlogged.pop(self._by_load.popitem(last=False)[0], None)
            unlogged = self._unlogged[cost.vertices] = self._unlogged.get(cost.vertices, 0) + 1
            full = unlogged >= self.per_load
            if full:  # once a window of ticks a load: what was measured (debug log)
                self._unlogged[cost.vertices] = 0
                costs = list(q)
        if full and log.isEnabledFor(logging.DEBUG):
            log.debug("admission: %d vertices, %d steady ticks: %s", cost.vertices, len(costs), describe(costs))

    def points(self) -> tuple[int, dict[str, list[tuple[int, float, int]]]]:
        """The latest load (0: none yet) and, per stage, each load's (vertices, ``q`` quantile,
        ticks) for the loads with ``min_samples`` ticks; none such (a burst): one point at the
        latest load, :meth:`stand_in`."""
        with self._lock:
            loads = [(v, list(q)) for v, q in self._by_load.items()]
            recent = list(self._recent)
        if not loads:
            return 0, {s: [] for s in STAGES}
        latest = loads[-1][0]
        enough = [(v, costs) for v, costs in loads if len(costs) >= self.min_samples]
        out: dict[str, list[tuple[int, float, int]]] = {s: [] for s in STAGES}
        if not enough:
            for s, (point, n) in self.stand_in(latest, recent).items():
                out[s].append((latest, point, n))
            return latest, out
        for v, costs in enough:
            per_stage = [c.stages() for c in costs]
            for s in STAGES:
                out[s].append((v, quantile([st[s] for st in per_stage], self.q), len(costs)))
        return latest, out

    @staticmethod
    def stand_in(latest: int, recent: list[TickCost]) -> dict[str, tuple[float, int]]:
        """Each stage's point at the ``latest`` load while no load has ``min_samples`` ticks (a
        burst of submits: each load is seen for a tick or two), and how many ticks it stands on:
        the median of the last ticks of loads within ``STAND_IN_SPAN`` below it, each scaled to it
        in proportion to the vertices. One tick's time swings by half either way on a loaded
        CPU (docs/loadtest.md, session 13: 6.9 to 16.5 ms a tick at 300-330 cloths, in one
        burst); taking the latest tick at its word let one cheap tick admit a third more."""
        near = [c for c in recent if c.vertices * STAND_IN_SPAN >= latest] or recent[-1:]
        return {s: (statistics.median(c.stages()[s] * latest / c.vertices for c in near), len(near)) for s in STAGES}

    def fit(self) -> Fit | None:
        """The latest load, each stage's line, whether the loads were :func:`separable` and
        each stage's proportional line through the largest load (None before the first steady
        tick). Computed once per steady tick observed: a burst of submits between two ticks
        reuses it."""
        with self._lock:
            observed = self._observed
            if self._fit[0] == observed:
                return self._fit[1]
        latest, points = self.points()
        got = None
        if points[STAGES[0]]:
            lines = {s: fit_line(points[s], self.min_spread) for s in STAGES}
            big = {s: max(points[s], key=lambda p: p[0]) for s in STAGES}
            floors = {s: Line(0.0, big[s][1] / big[s][0]) for s in STAGES}
            if log.isEnabledFor(logging.DEBUG):  # what the predictions until the next steady tick stand on
                loads = ", ".join(f"{v} ({n} ticks)" for v, _, n in points[STAGES[0]])
                at = ", ".join(f"{s} {1e3 * big[s][1]:.2f}" for s in STAGES)
                log.debug("admission: fit over %s; at the largest: %s ms", loads, at)
            got = Fit(latest, lines, separable([p[0] for p in points[STAGES[0]]], self.min_spread), floors)
        with self._lock:
            self._fit = (observed, got)
        return got

    def capacity(self, budget_s: float) -> float | None:
        """The load every stage's prediction (line and floor) puts within ``budget_s``; before
        the first steady tick, ``unmeasured``. No trust here: it is what the fit says."""
        got = self.fit()
        if got is None:
            return float(self.unmeasured)
        return min(min(_room(got.lines[s], budget_s), _room(got.floors[s], budget_s)) for s in got.lines)

    def predict(
        self, vertices: int, budget_s: float = float("inf"), cloth_vertices: int = 0
    ) -> dict[str, float] | None:
        """Each stage's seconds at a load of ``vertices`` work units (None: no opinion, admit);
        ``cloth_vertices``: the vertices of the cloth asking (trust is for small cloths)."""
        got = self.fit()
        if got is None:  # no steady tick yet: no opinion up to a first load, then wait for one
            return None if vertices <= self.unmeasured else {UNMEASURED: math.inf}
        latest, lines, fitted, floors = got
        stages = {s: max(line(vertices), floors[s](vertices)) for s, line in lines.items()}
        if (
            not fitted
            and max(line(latest) for line in lines.values()) < self.trust * budget_s
            and (
                max(stages.values()) <= self.trust_limit * budget_s
                or 0.0 < self.prior_s
                and lines["device"](latest) + PRIOR_MARGIN * self.prior_s * (vertices - latest) <= budget_s
            )
            and (vertices <= TRUST_GROWTH * latest or cloth_vertices <= TRUST_SMALL)
        ):
            with self._lock:  # lightly loaded, fixed and per-vertex costs not told apart: admit, once a load
                if self._trusted_at != latest:
                    self._trusted_at = latest
                    return None
        return stages
