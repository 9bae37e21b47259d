"""A world of many cloths stepped together: the interface the tick loop drives.

``make_world(solver)`` returns a ``ReferenceWorld`` (numpy, float64, the tests' ground truth) or a
``CLWorld`` (drape.server.sim.opencl.clworld: OpenCL work-group, coloured or Jacobi solver). Both keep the
same bookkeeping: cloths are added and removed between steps without touching the others, each
with its own parameters, pin targets and colliders.
"""
from __future__ import annotations

import itertools
import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from . import reference
from .fabric import Fabric, vertex_masses
from .params import MAX_COLLIDERS_PER_CLOTH, SOLVERS, ClothParams

log = logging.getLogger(__name__)


@dataclass
class Cloth:
    handle: int
    fabric: Fabric
    params: ClothParams
    colliders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 4), np.float32))


@dataclass
class Frame:
    """Host copy of every cloth's state after a step. ``positions[h]`` is (n, 3) float32."""

    step: int
    positions: dict[int, np.ndarray]
    normals: dict[int, np.ndarray]

    def finite(self, handle: int) -> bool:
        return bool(np.isfinite(self.positions[handle]).all())


class World(ABC):
    solver: str = "?"

    def __init__(self) -> None:
        self.cloths: dict[int, Cloth] = {}
        self._handles = itertools.count(1)
        self.steps = 0

    # --- cloth lifecycle -------------------------------------------------------------------
    def add(self, fabric: Fabric, params: ClothParams, positions: np.ndarray | None = None) -> int:
        params.validate()
        if positions is not None:
            positions = np.asarray(positions, np.float64).reshape(fabric.n_vertices, 3)
            if not np.all(np.isfinite(positions)):
                raise ValueError("positions must be finite")
        h = next(self._handles)
        cloth = Cloth(h, fabric, params)
        self.cloths[h] = cloth
        self._add(cloth, positions)
        return h

    def remove(self, handle: int) -> None:
        cloth = self.cloths.pop(handle)
        self._remove(cloth)

    def set_params(self, handle: int, params: ClothParams) -> None:
        params.validate()
        cloth = self.cloths[handle]
        old = cloth.params
        cloth.params = params
        self._set_params(cloth, old)

    def set_pin_targets(self, handle: int, indices: np.ndarray, targets: np.ndarray) -> None:
        """Where pinned vertices ``indices`` are at the end of the next step (interpolated
        over its substeps). Every index must be a pinned vertex of the cloth's fabric."""
        cloth = self.cloths[handle]
        idx = np.asarray(indices, np.int64).reshape(-1)
        tgt = np.asarray(targets, np.float64).reshape(-1, 3)
        if len(idx) != len(tgt):
            raise ValueError("one target per index")
        if idx.size and (idx.min() < 0 or idx.max() >= cloth.fabric.n_vertices):
            raise ValueError("pin index out of range")
        if idx.size and not cloth.fabric.pinned[idx].all():
            raise ValueError("only pinned vertices can be given targets")
        if not np.all(np.isfinite(tgt)):
            raise ValueError("targets must be finite")
        self._set_targets(cloth, idx, tgt)

    def set_colliders(self, handle: int, packed: np.ndarray) -> None:
        """Collider poses (see params.pack_colliders) for the end of the next step."""
        cloth = self.cloths[handle]
        packed = np.asarray(packed, np.float32).reshape(-1, 2, 4)
        if len(packed) > MAX_COLLIDERS_PER_CLOTH:
            raise ValueError(f"at most {MAX_COLLIDERS_PER_CLOTH} colliders per cloth")
        if not np.all(np.isfinite(packed)):
            raise ValueError("collider values must be finite")
        cloth.colliders = packed.copy()
        self._set_colliders(cloth)

    def reset(self, handle: int, positions: np.ndarray | None = None) -> None:
        """Put a cloth back at ``positions`` (default: its rest pose) with zero velocity."""
        cloth = self.cloths[handle]
        pos = cloth.fabric.rest_positions if positions is None else np.asarray(positions, np.float64)
        self._reset(cloth, pos.reshape(-1, 3))

    # --- stepping ------------------------------------------------------------------------
    @abstractmethod
    def step(self, dt: float) -> None:
        """Advance every cloth by dt (may return before the device has finished)."""

    @abstractmethod
    def fetch(self) -> Frame:
        """Wait for the last step and return host copies of every cloth's state."""

    def positions(self, handle: int) -> np.ndarray:
        return self.fetch().positions[handle]

    def sync(self) -> None:
        """Wait until every step asked for so far has finished (for timing)."""

    def close(self) -> None:
        pass

    # --- stats ----------------------------------------------------------------------------
    @property
    def n_cloths(self) -> int:
        return len(self.cloths)

    @property
    def n_vertices(self) -> int:
        return sum(c.fabric.n_vertices for c in self.cloths.values())

    @property
    def n_links(self) -> int:
        return sum(c.fabric.n_links for c in self.cloths.values())

    # --- backend hooks --------------------------------------------------------------------
    @abstractmethod
    def _add(self, cloth: Cloth, positions: np.ndarray | None) -> None: ...

    @abstractmethod
    def _remove(self, cloth: Cloth) -> None: ...

    @abstractmethod
    def _set_params(self, cloth: Cloth, old: ClothParams) -> None: ...

    @abstractmethod
    def _set_targets(self, cloth: Cloth, idx: np.ndarray, targets: np.ndarray) -> None: ...

    @abstractmethod
    def _set_colliders(self, cloth: Cloth) -> None: ...

    @abstractmethod
    def _reset(self, cloth: Cloth, positions: np.ndarray) -> None: ...


def inverse_masses(fabric: Fabric, params: ClothParams) -> np.ndarray:
    m = vertex_masses(fabric, params.material.mass)
    return np.where(fabric.pinned, 0.0, 1.0 / m)


class ReferenceWorld(World):
    """Every cloth stepped by drape.server.sim.reference on the CPU."""

    solver = "reference"

    def __init__(self, mode: str = "coloured", dtype=np.float64) -> None:
        super().__init__()
        self.mode = mode
        self.dtype = dtype
        self.states: dict[int, reference.ClothState] = {}
        self.device_name = f"numpy {np.dtype(dtype).name} ({mode})"

    def _add(self, cloth, positions):
        st = reference.ClothState.initial(cloth.fabric, cloth.params, self.dtype, positions)
        self.states[cloth.handle] = st

    def _remove(self, cloth):
        del self.states[cloth.handle]

    def _set_params(self, cloth, old):
        if old.material.mass != cloth.params.material.mass:
            self.states[cloth.handle].invm[:] = inverse_masses(cloth.fabric, cloth.params)

    def _set_targets(self, cloth, idx, targets):
        self.states[cloth.handle].target[idx] = targets

    def _set_colliders(self, cloth):
        self.states[cloth.handle].set_colliders(cloth.colliders.astype(self.dtype))

    def _reset(self, cloth, positions):
        st = self.states[cloth.handle]
        st.x[:] = positions
        st.v[:] = 0.0

    def step(self, dt: float) -> None:
        for h, cloth in self.cloths.items():
            st = self.states[h]
            reference.step(st, cloth.fabric, cloth.params, dt, self.mode)
            st.colliders_prev = st.colliders  # a collider not moved again stays where it is
        self.steps += 1

    def fetch(self) -> Frame:
        pos = {h: st.x.astype(np.float32) for h, st in self.states.items()}
        nrm = {
            h: st.normals.astype(np.float32)
            for h, st in self.states.items()
            if st.normals is not None and self.cloths[h].params.features.normals
        }
        return Frame(self.steps, pos, nrm)

    def state(self, handle: int) -> reference.ClothState:
        return self.states[handle]


def make_world(solver: str = "workgroup", device: str | None = None, **kw) -> World:
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose from {SOLVERS}")
    if solver == "reference":
        return ReferenceWorld(**kw)
    from .opencl.clworld import CLWorld  # OpenCL only when asked for

    return CLWorld(strategy=solver, device=device, **kw)
