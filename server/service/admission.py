"""Admission control: refuse a submission that would push the tick over its budget.

The tick thread reports each tick's cost (its own host work, the device's time for the step and
readback, and the publisher's encode and put of the frame before) with the number of vertices
stepped; :class:`MeasuredCost` keeps an EWMA of
the cost and the marginal cost per vertex (see MeasuredCost). A submit is refused with
the protocol's ``overloaded`` error when the predicted cost with its vertices (and those of every
cloth already admitted but not yet stepped) exceeds ``admission_budget`` of a tick, so the cloths
already admitted keep their rate. Refusals are counted (``overload_refusals``). A server with no
cloth admits (there is nothing to protect and no per-vertex cost to predict from).

Tests and operators may replace the model (``Admission.model``) with a :class:`FixedCost`.
"""
from __future__ import annotations

import logging
import threading
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
    """The tick's cost ``C`` (EWMA) at the vertex count ``V`` stepped, and the marginal cost per
    vertex: the slope of an exponentially weighted least-squares line through recent (V, cost)
    samples once V has varied enough (as cloths come and go), else the proportional ``C / V``
    (conservative: it counts the fixed per-tick costs as per-vertex ones). ``predict`` answers
    None (no opinion) while nothing was measured, or while only the proportional slope is known
    and the tick takes less than ``trust`` of the budget: a nearly idle server admits rather than
    extrapolate from a few small cloths."""

    def __init__(self, alpha: float = 0.02, trust: float = 0.5) -> None:
        self.alpha, self.trust = alpha, trust
        self.tick_s: float | None = None
        self.vertices = 0
        self._m = [0.0, 0.0, 0.0, 0.0]  # EWMA of V, C, V^2, V*C
        self._lock = threading.Lock()

    def observe(self, tick_s: float, vertices: int) -> None:
        if vertices <= 0:
            return
        a = self.alpha
        with self._lock:
            if self.tick_s is None:
                self.tick_s, self._m = tick_s, [vertices, tick_s, vertices * vertices, vertices * tick_s]
            else:
                self.tick_s += 5 * a * (tick_s - self.tick_s)  # the current cost: a faster average
                for i, x in enumerate((vertices, tick_s, vertices * vertices, vertices * tick_s)):
                    self._m[i] += a * (x - self._m[i])
            self.vertices = vertices

    @property
    def per_vertex_s(self) -> tuple[float, bool] | None:
        """(seconds per vertex, from the regression) or None."""
        with self._lock:
            if self.tick_s is None or self.vertices <= 0:
                return None
            mv, mc, mvv, mvc = self._m
            var = mvv - mv * mv
            if var > (0.1 * mv) ** 2:
                slope = (mvc - mv * mc) / var
                if slope > 0:
                    return slope, True
            return self.tick_s / self.vertices, False

    def predict(self, vertices: int, budget_s: float = float("inf")) -> float | None:
        slope = self.per_vertex_s
        if slope is None or self.tick_s is None:
            return None
        per_vertex, fitted = slope
        if not fitted and self.tick_s < self.trust * budget_s:
            return None
        return self.tick_s + per_vertex * max(vertices - self.vertices, 0)


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
            raise _OVERLOADED_EXC(ERR_OVERLOADED, f"server overloaded: a tick would take {1e3 * predicted:.1f} ms with "
                                  f"this cloth, over the budget of {1e3 * self.budget_s:.1f} ms; retry later or "
                                  "elsewhere", rid)
