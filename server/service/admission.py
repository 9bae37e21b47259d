"""Admission control: refuse a submission that would push the tick over its budget.

The tick thread reports the cost of each steady tick (no cloth came or went since the frame
before: those ticks carry one-off rebuilds) — its own host work, the device's time for the step
and readback, and the publisher's encode and put of the frame before — with the number of
vertices stepped; :class:`MeasuredCost` turns that into a cost per vertex (see there). A submit is refused with
the protocol's ``overloaded`` error when the predicted cost with its vertices (and those of every
cloth already admitted but not yet stepped) exceeds ``admission_budget`` of a tick, so the cloths
already admitted keep their rate. Refusals are counted (``overload_refusals``). A server with no
cloth admits (there is nothing to protect and no per-vertex cost to predict from).

Tests and operators may replace the model (``Admission.model``) with a :class:`FixedCost`.
"""

from __future__ import annotations

import logging
import statistics
import threading
from collections import deque
from dataclasses import dataclass

from drape.client import protocol as P

from .config import ServerConfig

log = logging.getLogger(__name__)

ERR_OVERLOADED: str = getattr(P, "ERR_OVERLOADED", "overloaded")
_OVERLOADED_EXC: type = getattr(P, "Overloaded", P.Busy)


@dataclass
class FixedCost:
    """A cost model that does not measure: ``base_s + per_vertex_s * vertices``."""

    per_vertex_s: float
    base_s: float = 0.0

    def observe(self, tick_s: float, vertices: int) -> None:
        pass

    def predict(self, vertices: int, budget_s: float = float("inf")) -> float | None:
        return self.base_s + self.per_vertex_s * vertices


class MeasuredCost:
    """The tick's cost per vertex stepped, as the median over the last ``window`` ticks (so
    ticks stretched by one-offs, an add's rebuild, a burst of requests taking the GIL, a
    descheduled thread, do not count unless they are the rule), times the vertices. It counts
    the per-tick fixed costs as per-vertex ones, so it errs on the side of refusing once loaded;
    ``predict`` answers None (no opinion) while the current cost is under ``trust`` of the
    budget: a lightly loaded server admits rather than extrapolate from a few small cloths."""

    def __init__(self, window: int = 30, trust: float = 0.5) -> None:
        self.trust = trust
        self._samples: deque[tuple[int, float]] = deque(maxlen=window)  # (vertices, cost)
        self._lock = threading.Lock()

    def observe(self, tick_s: float, vertices: int) -> None:
        if vertices > 0:
            with self._lock:
                self._samples.append((vertices, tick_s))

    @property
    def per_vertex_s(self) -> float | None:
        with self._lock:
            if not self._samples:
                return None
            return statistics.median(c / v for v, c in self._samples)

    @property
    def vertices(self) -> int:
        with self._lock:
            return self._samples[-1][0] if self._samples else 0

    def predict(self, vertices: int, budget_s: float = float("inf")) -> float | None:
        per_vertex, now = self.per_vertex_s, self.vertices
        if per_vertex is None or per_vertex * now < self.trust * budget_s:
            return None
        return per_vertex * vertices


class Admission:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.model: MeasuredCost | FixedCost = MeasuredCost()

    @property
    def budget_s(self) -> float:
        return self.config.admission_budget * self.config.dt

    def check(self, vertices_before: int, n_vertices: int, rid: int) -> None:
        """Raise ``overloaded`` when ``n_vertices`` more would not fit the tick budget."""
        if not self.config.admission or vertices_before <= 0:
            return
        predicted = self.model.predict(vertices_before + n_vertices, self.budget_s)
        if predicted is not None and predicted > self.budget_s:
            raise _OVERLOADED_EXC(
                ERR_OVERLOADED,
                f"server overloaded: a tick would take {1e3 * predicted:.1f} ms with "
                f"this cloth, over the budget of {1e3 * self.budget_s:.1f} ms; retry later or "
                "elsewhere",
                rid,
            )
