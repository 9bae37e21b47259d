"""Admission control: price each submission and control by its work and refuse (``overloaded``)
what would push the tick over its budget or its client past its share.

What a load of work costs, and which tick it is measured on, is the cost model's
(``admission_model.py``: :class:`MeasuredCost`, whose docstring gives its rules); this module
prices cloths in its units and applies the budget and the shares.

**Work, not vertices** (issue 26). A 64 x 64 cloth at 100 iterations x 100 substeps costs what
1,500 plain ones do; priced by its vertices it was admitted, and so was a control raising an
admitted cloth to it. Every figure of the cost model is in *work units*: a cloth's work is its vertices x
its solve's cost per frame relative to the plain 10-iteration PBD solve (:class:`Pricing`,
fitted over ``server/sim/preset_costs.json``'s measured configurations of the device's kind,
each measured configuration at its own figure) x its topology's link density (triangles per
vertex against a grid's) x its features' factors (:data:`FEATURE_WORK`). A default cloth's work
is its vertex count. The tick thread reports the work of the cloths it stepped (the records'
``work``, priced on admission); the model fits seconds per work unit, so the device's measured
per-sweep cost prices a submission and every control that changes work (``worldparams.
changes_params``: iterations, substeps, features, quality, a first collider, normals): a control
that raises a cloth's work is checked like a submission of the difference.

**Shares.** One client must not lock the others out: the work the model says fits the budget
(:meth:`MeasuredCost.capacity`) is the server's capacity, and a client that would hold more
than ``admission_client_share`` of it is admitted more only while ``admission_newcomer_reserve``
of the capacity stays free, for clients under their share. A lone client fills all but the
reserve; a newcomer's small cloth is admitted while another client holds its share.

Tests and operators may replace the model (``Admission.model``) with a ``admission_model.FixedCost``.
"""

from __future__ import annotations

import json
import logging
import math
import statistics
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from drape.client import protocol as P

from ...sim import quality
from ...sim.params import ClothParams, Features
from ...sim.scenes import INTER_COLLISION_PASSES
from ..config import ServerConfig
from ..registry import ClothRecord, Registry
from ..worldparams import changes_params, params_after_control, params_from_submit, with_preset
from .admission_model import UNMEASURED, CostModel, MeasuredCost

log = logging.getLogger(__name__)

ERR_OVERLOADED: str = getattr(P, "ERR_OVERLOADED", "overloaded")
_OVERLOADED_EXC: type = getattr(P, "Overloaded", P.Busy)

#: Each feature's factor on a cloth's work where it is on (features not named: 1, their cost in
#: the measured per-work cost). self_collision: docs/collision.md's cost table, at most 4.8x.
FEATURE_WORK: dict[str, float] = {"self_collision": 5.0}
DENSITY_LIMITS = (0.5, 4.0)  # a topology's link density against a grid's is taken within these
GRID_TRIANGLES_PER_VERTEX = 2.0  # a grid's (two per cell): density 1
SCENE_VERTICES = 64 * 64  # the cost file's scene: hanging 64 x 64
#: One inter-collision pass's work per vertex of a scene cloth (scenes of two cloths or more: each
#: pass a hash build and walk over every scene vertex), in plain solves of that vertex, by device
#: kind: measured by `drape bench scenes` as the time a frame takes in scenes less the same cloths'
#: frame without, over the passes and the cloths' own frame (docs/reliability.md, issue 26;
#: docs/collision.md's cost table, session 16's contacts found once: CPU pack 6.1 -> 9.8 ms for 4
#: scenes of 8 in a quiet moment, 0.08 rounded up; H100 1.056 -> 5.47 ms for 64 scenes of 64).
#: Session 17: the candidates found again in each of 4 rounds (a pile of scene cloths holds) made
#: the scenes' part of a CPU frame 2.5-2.7x what it was (`drape bench scenes --scenes 4,8`, the
#: code before and after in turn: 5.2-6.4 -> 14.1-16.4 ms), so the CPU's price is 0.1 x 2.7,
#: rounded up; the H100's is estimated from the counted device reads per scene vertex and step
#: (440 in session 16's code, 225 after the cheaper walk, 610 with four walks: 0.52 x 610 / 440),
#: not measured (no device time this session): docs/collision.md. Then the later rounds walked
#: the hash only for the vertices that moved (branch h-scenerounds): the scenes' part of the CPU
#: frame 14.0, 15.2 -> 10.8, 11.5 ms (`drape bench scenes --scenes 4,8`, before and after in turn,
#: docs/results/scenerounds/), 0.76x: the CPU's 0.27 x 0.76 rounded up. Session 18, measured on
#: one H100 (`bash deploy/h100.sh bench scenes --scenes 64,64 --frames 20`): 1.031 -> 15.171 ms a
#: frame, (15.171 - 1.031) / 1.031 / 8 passes = 1.71 plain solves a vertex and pass, rounded up
#: (the estimate of 0.75 was low: the later rounds' re-walk, cheap on the CPU, is 56 % of the
#: scenes' time on the GPU: docs/results/s18/scenepass-h100.txt). Then the later rounds' lists
#: shaped for a GPU (branch h-scenegpu), the same command in a later machine session: 1.039 ->
#: 12.603 ms, (12.603 - 1.039) / 1.039 / 8 = 1.39 plain solves a vertex and pass, rounded up.
SCENE_PASS_WORK: dict[str, float] = {"cpu": 0.25, "gpu": 1.4}
#: 1.8: a cloth's own mesh collider's work per vertex of the cloth, a part per cloth vertex and a
#: part per cloth vertex and triangle, in plain solves of that vertex: docs/collision.md's meshbench
#: on this CPU (128 capes of 1,024 vertices, 23.6 us a cape's plain solve): 25 us a cape with the
#: 5,972-triangle body, 26 us with the 12,220-triangle one (the cost follows the vertices near the
#: surface more than the triangles). Those capes never touched the body (session 17): with
#: contacts (`python -m drape.server.tools.meshab --into 0.08`, 128 capes) the mesh kernel takes
#: 11.2 ms a launch on this CPU against 3.0 ms for the capes' plain solve, 3.7 plain solves a
#: vertex, the price on a CPU. A GPU's, with contacts, measured in session 18 on one H100
#: (`bash deploy/h100.sh tool meshbench --cloths 4096 --frames 10 --rounds 3 --into 0.08`): 4096
#: capes 1.566 ms a frame bare, 2.970 with the 5,972-triangle body (1.90x), 3.479 with the
#: 12,220-triangle one (2.22x): 0.84 and 1.10 plain solves a vertex once the triangle part is
#: taken off; 1.0 stands.
MESH_VERTEX_WORK: dict[str, float] = {"cpu": 3.7, "gpu": 1.0}
MESH_TRIANGLE_WORK = 1.0e-5
assert set(FEATURE_WORK) <= set(Features().__dataclass_fields__), FEATURE_WORK


class Pricing:
    """A solve's cost per frame relative to the plain 10-iteration PBD solve, on a device of
    ``kind`` (``preset_costs.json``, written by ``drape tradeoff --costs``): a configuration
    measured with the same iterations, substeps and XPBD switch costs its figure; any other the
    least-squares line ``a + substeps x (b + c x iterations)`` over the measured ones (a frame's
    fixed part, then each substep's integration and each sweep of links; coefficients kept
    non-negative), or, with nothing measured, ``iterations x substeps / 10``."""

    def __init__(self, kind: str = "cpu") -> None:
        self.kind = kind
        try:
            self._entry: dict = json.loads(quality.COSTS_FILE.read_text()).get(kind) or {}
        except (OSError, ValueError):
            self._entry = {}
        measured = quality.measured(kind)
        self.exact = {  # (iterations, substeps, xpbd): cost ("workgroup pbd 10it x 1ss 60Hz": PBD)
            (int(c["iterations"]), int(c["substeps"]), str(c.get("describe", "")).split()[1:2] != ["pbd"]): c["cost"]
            for c in measured.values()
            if "iterations" in c and "substeps" in c
        }
        self.coef: tuple[float, float, float] | None = None
        if len(measured) >= 3:
            x = np.array([[1.0, c["substeps"], c["substeps"] * c["iterations"]] for c in measured.values()])
            y = np.array([c["cost"] for c in measured.values()])
            co = np.linalg.lstsq(x, y, rcond=None)[0]
            if np.all(co >= 0.0):
                self.coef = (float(co[0]), float(co[1]), float(co[2]))

    @property
    def work_s(self) -> float:
        """The device's seconds per work unit as the cost file measured it: the plain solve's
        median frame over its cloths' vertices (0: not measured)."""
        entry = self._entry
        ms, cloths = entry.get("pbd10_ms") or [], entry.get("cloths") or 0
        if not ms or not cloths:
            return 0.0
        return 1e-3 * statistics.median(ms) / (cloths * SCENE_VERTICES)

    def scene_work(self, n_vertices: int) -> float:
        """The work units of ``n_vertices`` of scene cloths in inter-collision: every pass of a step
        (``INTER_COLLISION_PASSES``) walks each of them once."""
        return n_vertices * INTER_COLLISION_PASSES * SCENE_PASS_WORK.get(self.kind, max(SCENE_PASS_WORK.values()))

    def frame_cost(self, iterations: int, substeps: int, xpbd: bool) -> float:
        got = self.exact.get((iterations, substeps, xpbd))
        if got is not None:
            return got
        if self.coef is None:
            return max(iterations * substeps, 1) / 10.0
        a, b, c = self.coef
        return a + substeps * (b + c * iterations)

    @staticmethod
    def density(n_vertices: int, n_triangles: int | None) -> float:
        """Links per vertex against a grid's, from triangles per vertex (links follow the edges
        and their bends); None (a grid): 1."""
        if n_triangles is None or n_vertices <= 0:
            return 1.0
        lo, hi = DENSITY_LIMITS
        return min(hi, max(lo, n_triangles / n_vertices / GRID_TRIANGLES_PER_VERTEX))

    def work(self, n_vertices: int, params: ClothParams, density: float = 1.0, mesh_triangles: int = 0) -> float:
        """A cloth's work units: vertices x relative frame cost x link density x features' factors,
        and its own mesh collider's (1.8) of ``mesh_triangles`` (0: none)."""
        w = n_vertices * density * self.frame_cost(params.iterations, params.substeps, params.features.xpbd)
        for name in params.features.names():
            w *= FEATURE_WORK.get(name, 1.0)
        if mesh_triangles:
            vertex = MESH_VERTEX_WORK.get(self.kind, max(MESH_VERTEX_WORK.values()))
            w += n_vertices * (vertex + MESH_TRIANGLE_WORK * mesh_triangles)
        return w


@dataclass(frozen=True)
class Priced:
    """What admission priced a cloth at: its parameters as admitted (the submission's, then each
    admitted control's; the World's own may be lower under adaptive quality), its topology's
    link density and its work units. Kept on the cloth's record (``ClothRecord.priced``)."""

    params: ClothParams
    density: float
    work: float
    mesh_triangles: int = 0  # 1.8: its own mesh collider's, as submitted


def work_of(rec: ClothRecord) -> float:
    """A record's work units as priced (a record admission never priced: its vertices)."""
    return rec.priced.work if isinstance(rec.priced, Priced) else float(rec.n_vertices)


class Admission:
    def __init__(self, config: ServerConfig) -> None:
        self.config = config
        self.pricing = Pricing("cpu")  # the CPU's costs until the server knows its World's device
        self.model: CostModel = MeasuredCost(
            unmeasured=config.admission_unmeasured_vertices, prior_s=self.pricing.work_s
        )
        self.generation = 0  # bumped whenever a record's work changes (the tick thread's sum is cached by it)

    def use_device(self, is_gpu: bool) -> None:
        """Price by the measured costs of the World's kind of device (the server calls it once the
        World exists)."""
        self.pricing = Pricing("gpu" if is_gpu else "cpu")
        if isinstance(self.model, MeasuredCost):
            self.model.prior_s = self.pricing.work_s

    @property
    def budget_s(self) -> float:
        return self.config.admission_budget * self.config.dt

    # --- pricing -----------------------------------------------------------------------------
    def price_submit(self, req: P.SubmitRequest) -> Priced:
        """A submission's parameters (as the cook worker will build them) and work."""
        params = params_from_submit(req)
        if req.quality is not None:
            params = with_preset(self.config, params, req.quality, req.rid)
        n = req.n_vertices
        density = Pricing.density(n, None if req.mesh is None else len(req.mesh.triangles))
        mc = req.mesh_collider
        tris = len(mc.triangles) if mc is not None and mc.triangles is not None else 0
        return Priced(params, density, self.pricing.work(n, params, density, tris), tris)

    def price_control(self, rec: ClothRecord, req: P.ControlRequest) -> Priced | None:
        """The cloth's price once ``req`` applies; None where it changes no parameter
        (``worldparams.changes_params``: pins, a moved collider) and sets or removes no mesh
        collider (1.8), or is invalid (the applier refuses it with its own error)."""
        old = rec.priced
        if not isinstance(old, Priced):
            return None
        tris, mc = old.mesh_triangles, req.mesh_collider  # 1.8: a new mesh or a removal re-prices
        if mc is not None and (mc.remove or mc.triangles is not None):
            tris = 0 if mc.remove or mc.triangles is None else len(mc.triangles)
        new = old.params
        if changes_params(req, old.params):
            try:
                new = params_after_control(req, old.params)
            except (TypeError, ValueError):
                return None
            if req.quality is not None:
                new = with_preset(self.config, new, req.quality, req.rid)
        elif tris == old.mesh_triangles:
            return None
        work = self.pricing.work(rec.n_vertices, new, old.density, tris)
        return Priced(new, old.density, work, tris)

    def total_work(self, records: Iterable[ClothRecord]) -> float:
        """The work units of these cloths stepped together: each one's price, plus the
        inter-collision of every scene of two cloths or more among them (:meth:`Pricing.scene_work`
        of its vertices; a scene of one cloth collides with nothing and costs nothing)."""
        total = 0.0
        scenes: dict[str, list[int]] = {}
        for r in records:
            total += work_of(r)
            if r.scene is not None:
                scenes.setdefault(r.scene, []).append(r.n_vertices)
        return total + sum(self.pricing.scene_work(sum(vs)) for vs in scenes.values() if len(vs) > 1)

    def scene_growth(self, records: Iterable[ClothRecord], scene: str | None, n_vertices: int) -> float:
        """The inter-collision work a cloth of ``n_vertices`` adds by joining ``scene``: its own
        vertices' passes, and the scene's first cloth's where it makes a scene of one a scene of
        two (a cloth founding a scene adds none)."""
        if scene is None:
            return 0.0
        there = [r.n_vertices for r in records if r.scene == scene]
        if not there:
            return 0.0
        return self.pricing.scene_work(n_vertices + (there[0] if len(there) == 1 else 0))

    # --- admitting ---------------------------------------------------------------------------
    def admit_submit(self, registry: Registry, rec: ClothRecord, req: P.SubmitRequest) -> None:
        """Price a submission onto ``rec.priced`` and refuse it (``overloaded``) where its work,
        with the inter-collision it adds to its scene (:meth:`scene_growth`), does not fit the
        tick budget or its client's share (request thread)."""
        rec.priced = self.price_submit(req)
        with registry.lock:
            grows = self.scene_growth(list(registry.cloths.values()), rec.scene, rec.n_vertices)
        self.admit(registry, rec.client, rec.priced.work + grows, req.rid, cloth_vertices=rec.n_vertices)

    def admit_control(self, registry: Registry, rec: ClothRecord, req: P.ControlRequest) -> None:
        """Re-price a cloth a control changes; a control that raises its work is admitted like a
        submission of the difference, or refused (``overloaded``; the cloth keeps its settings)."""
        new = self.price_control(rec, req)
        if new is None:
            return
        added = new.work - work_of(rec)
        if added > 0.0:
            self.admit(registry, rec.client, added, req.rid, "this control", rec.n_vertices)
        if added != 0.0:
            self.generation += 1
        rec.priced = new

    def admit(
        self, registry: Registry, client: str, work: float, rid: int, what: str = "this cloth", cloth_vertices: int = 0
    ) -> None:
        """Raise ``overloaded`` where ``work`` more units of ``client`` would not fit the tick
        budget (:meth:`check`) or would take its client past its share (:meth:`check_share`)."""
        if not self.config.admission:
            return
        with registry.lock:
            total = self.total_work(registry.cloths.values())
            mine = sum(work_of(registry.cloths[c]) for c in registry.by_client.get(client, ()) if c in registry.cloths)
        if self.check(total, work, rid, what, cloth_vertices):
            self.check_share(total, mine, work, rid)

    def check_share(self, total: float, mine: float, work: float, rid: int) -> None:
        """A client past ``admission_client_share`` of the capacity is admitted only while
        ``admission_newcomer_reserve`` of it stays free (the module docstring). Asked only where
        the budget check judged by a prediction: where it admitted without one (no steady tick
        yet, or on trust at a light load), the model's capacity is the proportional line's, which
        counts a light load's fixed costs per work unit, and would refuse a client holding nothing
        a cloth the budget check let in (a plain 64 x 64 beside a small load measured at 2.4-2.8 ms
        a tick: `drape chaos heavy-control`, 10 retries refused on a quiet machine)."""
        cfg = self.config
        if total <= 0 or cfg.admission_client_share >= 1.0:
            return
        cap = self.model.capacity(self.budget_s)
        if cap is None or not math.isfinite(cap) or cap < total + work:
            # below what the budget check just admitted: it admitted on trust (one light load, whose
            # proportional line counts fixed costs per unit), and this capacity says nothing
            return
        free = (1.0 - cfg.admission_newcomer_reserve) * cap
        if mine + work > cfg.admission_client_share * cap and total + work > free:
            log.debug("admission: refused %.0f work units: the client holds %.0f of %.0f", work, mine, cap)
            raise _OVERLOADED_EXC(
                ERR_OVERLOADED,
                f"server overloaded for this client: it holds {mine:.0f} of the {cap:.0f} work units the tick "
                f"budget holds, over its share of {cfg.admission_client_share:g}; the rest is kept for other "
                "clients; retry later or elsewhere",
                rid,
            )

    def check(
        self, vertices_before: float, n_vertices: float, rid: int, what: str = "this cloth", cloth_vertices: int = 0
    ) -> bool:
        """Raise ``overloaded`` when ``n_vertices`` more work units would not fit the tick budget;
        True where a prediction admitted them, False where they were admitted without one."""
        if not self.config.admission or vertices_before <= 0:
            return False
        total = math.ceil(vertices_before + n_vertices)
        stages = self.model.predict(total, self.budget_s, cloth_vertices or math.ceil(n_vertices))
        if not stages:
            log.debug("admission: admitted %d vertices without a prediction", total)
            return False
        stage, predicted = max(stages.items(), key=lambda kv: kv[1])
        if stage == UNMEASURED:
            log.debug("admission: refused %d vertices: no steady tick measured yet", total)
            raise _OVERLOADED_EXC(
                ERR_OVERLOADED,
                f"server overloaded: {vertices_before:.0f} work units admitted and no tick of them measured yet; "
                "retry later or elsewhere",
                rid,
            )
        if log.isEnabledFor(logging.DEBUG):
            shown = ", ".join(f"{s} {1e3 * v:.2f}" for s, v in stages.items())
            verdict = "refused" if predicted > self.budget_s else "admitted"
            log.debug("admission: %s %d vertices: predicted %s ms", verdict, total, shown)
        if predicted > self.budget_s:
            raise _OVERLOADED_EXC(
                ERR_OVERLOADED,
                f"server overloaded: the tick's {stage} stage would take {1e3 * predicted:.1f} ms with "
                f"{what}, over the budget of {1e3 * self.budget_s:.1f} ms; retry later or "
                "elsewhere",
                rid,
            )
        return True
