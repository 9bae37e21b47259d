"""Memory a cloth's preparation may take and must give back (issue 26): the build child's bound
(``build_memory_mb``: a child past it is killed, the cloth that asked is refused ``too_large``
with a message naming the setting, it is not built in the server instead, and the server goes on
serving; the bound here is below what any child takes, a Python process with OpenCL being over
100 MB, so every build passes it), and the fabric cache's byte bound on what it keeps."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import collect, connect, make_config

from drape.client import DrapeError
from drape.client import protocol as P
from drape.server.service import Server
from drape.server.service.cook.buildhelper import BuildHelper, BuildMemoryExceeded, cook_in_child
from drape.server.service.cook.fabrics import FabricStore, cook_fabric, fabric_bytes
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams, Features, LinkOptions
from drape.server.tools.chaos_builds import mesh_request

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

BOUND_MB = 40.0


def test_a_build_child_past_its_memory_bound_is_killed_with_a_clear_error():
    helper = BuildHelper("workgroup", "cpu", memory_mb=BOUND_MB)
    try:
        with pytest.raises(BuildMemoryExceeded) as e:
            helper.warm(cook_grid(8, 8, pinned=[0, 7]), ClothParams(features=Features(tethers=True)))
        assert "build_memory_mb" in str(e.value) and "killed" in str(e.value)
        assert helper.memory_kills == 1 and helper.runs == 0 and helper._proc is None  # nothing left running
    finally:
        helper.close()


def test_the_server_refuses_that_cloth_and_goes_on():
    cfg = make_config(build_in_child="always", build_memory_mb=BOUND_MB)
    with Server(cfg) as srv:
        c = connect(srv)
        try:
            plain = c.submit_grid(8, 8, pinned=[0, 7])  # a warm-up's kernels: no child needed
            with pytest.raises(DrapeError) as e:  # 4096 vertices: another kernel group (PoCL: 8 pack lanes, not 16)
                c.submit_grid(64, 64, pinned=[0, 63], features=["wind"])
            assert e.value.code == "too_large" and "build_memory_mb" in e.value.message
            assert srv.cook.helper is not None and srv.cook.helper.memory_kills == 1
            assert len(collect(plain, 10)) == 10  # still served
        finally:
            c.close()


def test_a_released_big_fabric_is_not_kept_for_resubmission_past_the_byte_bound():
    """The fabric cache keeps unused fabrics for resubmissions, at most ``retain_bytes`` of them:
    a big mesh's fabric goes when its cloth goes (issue 26: its memory was never given back)."""
    small, big = cook_grid(8, 8, pinned=[0, 7]), cook_grid(64, 64, pinned=[0, 63])
    store = FabricStore(retain_bytes=fabric_bytes(small) * 3)
    assert fabric_bytes(big) > store.retain_bytes
    for key, fab in (("small", small), ("big", big)):
        assert store.acquire(key, lambda fab=fab: fab) is fab
        store.release(fab)
    assert store.spare_bytes == fabric_bytes(small)  # the big one went, the small one is kept
    assert store.acquire("small", lambda: cook_grid(2, 2)) is small and store.cooked == 2


def test_a_big_cook_in_a_child_gives_the_fabric_the_server_would_cook():
    """cook_in_child (cloths of COOK_IN_CHILD_VERTICES or more, builds in a child): the same
    arrays as the in-process cook, tethers and long-range links included; an invalid mesh is a
    ValueError as in-process; past the memory bound, BuildMemoryExceeded."""
    req = mesh_request("m", side=24)
    links, pinned = LinkOptions(), np.unique(req.pinned.astype(np.int64))
    here, there = cook_fabric(req, links, pinned), cook_in_child(req, links, pinned)
    for name in ("rest_positions", "links", "rest_length", "colour_offsets", "jacobi_adj", "vtri"):
        np.testing.assert_array_equal(getattr(here, name), getattr(there, name))
    for a, b in zip((*here.tethers(), *here.long_range()), (*there.tethers(), *there.long_range()), strict=True):
        np.testing.assert_array_equal(a, b)
    bad = P.SubmitRequest(client="m", mesh=P.MeshSpec(req.mesh.vertices, req.mesh.triangles[:, [0, 0, 1]]))
    with pytest.raises(ValueError, match="repeated vertex"):
        cook_in_child(bad, links, np.zeros(0, np.int64))
    with pytest.raises(BuildMemoryExceeded, match="build_memory_mb"):
        cook_in_child(mesh_request("m", side=90), links, pinned, memory_mb=BOUND_MB)
