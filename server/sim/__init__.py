"""The simulation core: cloth parameters, fabric cooking, the float64 reference, Worlds and
quality presets. numpy and OpenCL only: no Zenoh, no threads.

``make_world(solver)`` is the one place that picks a World back end (world.py defines the
interface and the reference back end, opencl/clworld.py the OpenCL one; neither imports the
other's module the other way round)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .world import World

__all__ = ["make_world"]


def make_world(solver: str = "workgroup", device: Any = None, **kw: Any) -> World:
    from .params import SOLVERS

    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; choose from {SOLVERS}")
    if solver == "reference":
        from .world import ReferenceWorld

        return ReferenceWorld(**kw)
    from .opencl.clworld import CLWorld  # OpenCL only when asked for

    return CLWorld(strategy=solver, device=device, **kw)
