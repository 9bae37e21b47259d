"""A World phase with a program of its own (the shared base of the CLWorld's parts that run once
per step after the solvers' launches: scenes.SceneCollision, meshes.MeshCollision): the World's
memory, slots, cloths and scenes it works on, its work-group size, its build options, its kernels
built on first use (so a World that never needs the phase builds nothing, and the solvers'
programs keep their build options) and the flag that its tables are stale.

A phase names its kernel file (``SOURCE``), the kernels it launches (``KERNELS``) and further
handles on them (``ALIASES``: a name for a second ``cl.Kernel`` of one kernel function, whose
arguments are set apart), and gives its build options (``build_options``, which may use ``ls``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import pyopencl as cl

from ..scenes import Scene
from ..world import Cloth
from .buffers import ClothSlot, DeviceMemory
from .device import Device

#: A phase's work-group size on a GPU (1 on a CPU).
PHASE_LS = 64


class WorldPhase:
    """A phase of a CLWorld's step with its own program, given the World's memory, slots, cloths and scenes."""

    SOURCE: ClassVar[str]
    KERNELS: ClassVar[tuple[str, ...]]
    ALIASES: ClassVar[Mapping[str, str]] = {}

    def __init__(
        self,
        dev: Device,
        mem: DeviceMemory,
        rec: Mapping[int, ClothSlot],
        cloths: Mapping[int, Cloth],
        scenes: Mapping[str, Scene],
    ) -> None:
        self.dev, self.mem, self.rec, self.cloths, self.scenes = dev, mem, rec, cloths, scenes
        self.ls = PHASE_LS if dev.info.is_gpu else 1
        self.options = self.build_options()
        self._kernels: dict[str, cl.Kernel] | None = None
        self._dirty = True

    def build_options(self) -> list[str]:
        """The program's ``-D`` options (its constants' one copy is in the sim module it twins)."""
        raise NotImplementedError

    def changed(self) -> None:
        """A cloth joined or left a scene, or a cloth's material changed: the phase's tables rebuilt
        before the next step."""
        self._dirty = True

    def kernels(self) -> dict[str, cl.Kernel]:
        """The phase's kernels by name (and ALIASES), its program built on the first call."""
        if self._kernels is None:
            prg = self.dev.program(self.options, source=self.SOURCE)
            self._kernels = {name: cl.Kernel(prg, name) for name in self.KERNELS}
            self._kernels.update({alias: cl.Kernel(prg, name) for alias, name in self.ALIASES.items()})
        return self._kernels
