"""The CLWorld's phases with a program of their own (opencl/phase.py: inter-cloth collision and
mesh colliders): nothing built until a phase is used, its program then built once with its
options, its kernels and aliases (a second handle on one kernel function) by name, and its
tables marked stale by ``changed``."""

from __future__ import annotations

from drape.server.sim.opencl.clworld import CLWorld
from drape.server.sim.opencl.phase import WorldPhase


def test_phases_build_their_program_once_on_first_use(device):
    world = CLWorld("workgroup", device=device, pack_lanes=0)
    phases = (world.scene_collision, world.mesh_collision)
    for phase, ls in zip(phases, ("-DIC_LS=", "-DMC_LS="), strict=True):
        assert isinstance(phase, WorldPhase) and phase._kernels is None
        assert phase.options[0] == f"{ls}{phase.ls}"
        kernels = phase.kernels()
        assert phase.kernels() is kernels and set(kernels) == {*phase.KERNELS, *phase.ALIASES}
        assert device.built(phase.options, phase.SOURCE)
        phase._dirty = False
        phase.changed()
        assert phase._dirty
    k = world.scene_collision.kernels()
    assert k["ic_pass_ba"] is not k["ic_pass"] and k["ic_pass_ba"].function_name == "ic_pass"
