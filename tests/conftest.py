"""Shared fixtures: fresh random inputs every run (the seed is printed so a failure can be replayed)
and one OpenCL device per test session (PoCL's CPU device on CI)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from drape.server.sim.fabric import cook, cook_grid, grid_links, grid_mesh, mesh_links
from drape.server.sim.params import LinkOptions


@pytest.fixture
def rng(request) -> np.random.Generator:
    seed = int(os.environ.get("DRAPE_TEST_SEED", np.random.SeedSequence().entropy % 2**32))
    print(f"[{request.node.name}] DRAPE_TEST_SEED={seed}")
    return np.random.default_rng(seed)


@pytest.fixture(scope="session")
def device():
    from drape.server.sim.opencl.device import Device

    return Device(os.environ.get("DRAPE_DEVICE"))


def random_mesh_fabric(rng: np.random.Generator, options: LinkOptions = LinkOptions(bending=True), n_pins: int = 2):
    """A random triangle mesh: a jittered grid of random size, some triangles dropped, vertex
    indices shuffled, random pins."""
    cols, rows = int(rng.integers(3, 12)), int(rng.integers(3, 12))
    v, t = grid_mesh(cols, rows, width=rng.uniform(0.5, 2.0), height=rng.uniform(0.5, 2.0))
    v = v + rng.normal(0, 0.02, v.shape)
    keep = rng.random(len(t)) > 0.15
    keep[0] = True
    t = t[keep]
    perm = rng.permutation(len(v))
    inv = np.argsort(perm)
    v = v[perm]
    t = inv[t]
    used = np.unique(t)
    pins = rng.choice(used, size=min(n_pins, len(used)), replace=False) if n_pins else []
    links, ltype = mesh_links(t.astype(np.int32), options)
    return cook(v, t, links, ltype, pins)


def random_grid_fabric(rng: np.random.Generator, options: LinkOptions = LinkOptions(bending=True), n_pins: int = 2):
    cols, rows = int(rng.integers(3, 14)), int(rng.integers(3, 14))
    pins = rng.choice(cols * rows, size=n_pins, replace=False) if n_pins else []
    return cook_grid(cols, rows, rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), options, pins,
                     orientation=str(rng.choice(["horizontal", "vertical"])))


__all__ = ["random_mesh_fabric", "random_grid_fabric", "grid_links"]
