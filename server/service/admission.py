"""Admission control: refuse a submission that would push the tick over its budget.

The tick thread reports each tick's cost (its own host work, the device's time for the step and
readback, and the publisher's encode and put of the frame before) with the number of vertices
stepped; :class:`MeasuredCost` keeps an EWMA of
the cost and of the cost per vertex (above the cost of an empty tick). A submit is refused with
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

    def predict(self, vertices: int) -> float | None:
        return self.base_s + self.per_vertex_s * vertices


class MeasuredCost:
    """EWMA of the whole-tick cost, of an empty tick's cost and of the marginal cost per vertex."""

    def __init__(self, alpha: float = 0.1) -> None:
        self.alpha = alpha
        self.tick_s: float | None = None
        self.base_s = 0.0
        self.per_vertex_s: float | None = None
        self._lock = threading.Lock()

    def observe(self, tick_s: float, vertices: int) -> None:
        a = self.alpha
        with self._lock:
            if vertices <= 0:
                self.base_s += a * (tick_s - self.base_s)
                return
            self.tick_s = tick_s if self.tick_s is None else self.tick_s + a * (tick_s - self.tick_s)
            marginal = max(tick_s - self.base_s, 0.0) / vertices
            self.per_vertex_s = marginal if self.per_vertex_s is None else (
                self.per_vertex_s + a * (marginal - self.per_vertex_s))

    def predict(self, vertices: int) -> float | None:
        with self._lock:
            if self.per_vertex_s is None:
                return None
            return self.base_s + self.per_vertex_s * vertices


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
        predicted = self.model.predict(vertices_before + n_vertices)
        if predicted is not None and predicted > self.budget_s:
            raise _OVERLOADED_EXC(ERR_OVERLOADED, f"server overloaded: a tick would take {1e3 * predicted:.1f} ms with "
                                  f"this cloth, over the budget of {1e3 * self.budget_s:.1f} ms; retry later or "
                                  "elsewhere", rid)
