"""The server's warm-up, on a World: build and run, before a server serves, every kernel its
first cloths can need, so that the first such submission neither waits for a build nor stalls a
tick (PoCL compiles a kernel again at its first launch).

It takes a World, never a Server: the server runs it on its own World before its threads start
(drape.server.service.server), and the build helper's child process on a scratch World of its
own (drape.server.service.cook.buildhelper), filling the driver's disk cache the server then
builds from."""

from __future__ import annotations

import logging
import time

import numpy as np

from drape.client import protocol as P

from ...sim.fabric import Fabric, cook_grid
from ...sim.params import ClothParams, Features, Sphere, pack_colliders
from ...sim.roster import Roster
from ...sim.world import World
from ..config import ServerConfig

log = logging.getLogger(__name__)


def warm_up(world: World, config: ServerConfig) -> None:
    """Build and run on ``world``:

    - a small cloth's kernels, the pin-target scatter included (what the tick thread runs first);
    - with ``device_encode``, the frame encoder's programs and one frame encoded (the encoder's
      first launch cost 8-21 ticks on the tick thread with a cold PoCL cache);
    - a cloth of each feature set the deployment declares (``warm_features``);
    - the largest cloth this server admits (a strip of ``max_vertices_per_cloth`` vertices)
      when its kernels are others: too large for local memory, it takes the global-memory
      ones (a 256x256 cloth's first submit took 2.2 s on the CPU, 0.7 s once warmed)."""
    params = ClothParams()
    t = time.perf_counter()
    step_once(world, cook_grid(2, 2, pinned=[0]), params, config.dt)
    world.warm_wire()  # the frame encoder's programs (an OpenCL World built with device_encode)
    if config.device_encode:  # states encoded on the device: the encoder launched once
        h = world.add(cook_grid(2, 2, pinned=[0]), params)
        world.step(config.dt)
        lay = world.layout()
        f32 = [P.ENCODING_IDS["float32"]]
        roster = Roster((-1, -1), ["warm-up"], ["warm-up"], f32, lay.normals.copy(), np.array([0]), [])
        world.fetch_async(roster, 0).wait().release()
        world.remove(h)
        world.fetch()
    log.debug("warm-up of the default kernels took %.3f s", time.perf_counter() - t)
    for names in config.warm_feature_sets():  # the feature sets a deployment declares
        t0 = time.perf_counter()
        step_once(world, cook_grid(32, 32, pinned=[0, 31]), ClothParams(features=Features.from_names(names)), config.dt)
        log.debug("warm-up of features %s took %.3f s", "+".join(names), time.perf_counter() - t0)
    largest = cook_grid(1, config.max_vertices_per_cloth, pinned=[0])
    if world.ready(largest, params):
        return
    t = time.perf_counter()
    world.prepare(largest, params)
    step_once(world, largest, params, config.dt)
    log.debug("warm-up of a %d-vertex cloth took %.3f s", largest.n_vertices, time.perf_counter() - t)


def step_once(world: World, fabric: Fabric, params: ClothParams, dt: float) -> None:
    """Add a cloth, move its first pin, give it a collider when its features ask for them,
    step it once, read the frame back and remove it: every kernel it needs built and run."""
    h = world.add(fabric, params)
    world.set_pin_targets(h, np.array([0]), np.zeros((1, 3)))
    if params.features.colliders:
        world.set_colliders(h, pack_colliders([Sphere((0.5, -0.5, 0.5), 0.2)]))
    world.step(dt)
    world.fetch()
    world.remove(h)
    world.fetch()
