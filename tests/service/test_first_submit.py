"""What a newcomer meets (issue 20), end to end on a real server: refusals that say what was
wrong and come before anything is built for them, and a first cloth the server is already warm for.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from conftest import collect, connect, make_config

from drape.client import ProtocolError
from drape.client import protocol as P
from drape.server.service import Server

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


@pytest.fixture(scope="module")
def server():
    s = Server(make_config()).start()
    yield s
    s.stop()
    assert s.failure is None


def test_leaving_after_unwaited_batches_and_moves_logs_nothing(server, caplog):
    """The README's many-cloth forms (bundles, ``client.batch(wait=False)``, ``move_pins_many``)
    right before the client's exit removes the cloths: an item or move of a cloth this client is
    removing, answered ``not_found``, is the removal's outcome, not a failure to log or count."""
    caplog.set_level(logging.DEBUG, logger="drape.client")
    with connect(server) as client:
        capes = [client.submit_grid(8, 8, pinned=[0, 7], bundle=True) for _ in range(3)]
        collect(capes[-1], 2)
        targets = np.zeros((len(capes), 2, 3), np.float32)
        for _ in range(3):
            with client.batch(wait=False) as b:
                for c in capes:
                    b.move_pins(c, [0, 7], targets[0])
            client.move_pins_many(capes, [0, 7], targets, wait=False)
    assert all(c.closed and c.close_reason == "removed" for c in capes)
    assert client.send_errors == 0
    assert [f"{r.name}: {r.getMessage()}" for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_an_out_of_range_pin_names_the_index_and_the_range(server):
    with connect(server) as client:
        # the SDK's own check, before anything is sent
        with pytest.raises(ValueError, match=r"^pinned index 1030 out of range 0\.\.1023 for a 32x32 grid$"):
            client.submit_grid(32, 32, pinned=[0, 1030])
        with pytest.raises(ValueError, match=r"^pinned index -1 out of range 0\.\.1023 for a 32x32 grid$"):
            client.submit_grid(32, 32, pinned=[0, -1])
        tri = ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
        with pytest.raises(ValueError, match=r"^pinned index 7 out of range 0\.\.2 for a mesh of 3 vertices$"):
            client.submit_mesh(*tri, pinned=[7])
        # the server's reply to a request the SDK did not check: the same words
        grid = P.GridSpec(32, 32, 1.0, 1.0, "horizontal", (0.0, 0.0, 0.0))
        req = P.SubmitRequest(client=client.client_id, grid=grid, pinned=np.array([0, 1030, 2000], np.uint32))
        with pytest.raises(ProtocolError) as e:
            client.request("submit", P.encode_submit(req))
        assert e.value.code == P.ERR_INDEX_OUT_OF_RANGE
        assert e.value.message == "pinned index 1030 out of range 0..1023 for a 32x32 grid"


def test_a_grid_too_large_is_refused_before_anything_is_built(server):
    """A 4000x4000 grid took 22 s to be refused: the SDK built its 16M-vertex rest pose first.
    Now the SDK refuses it by the server's advertised limit before sending (and before building
    anything), and the server, asked directly, refuses it in its decoder: nothing is cooked."""
    reg, fabrics = server.registry, server.cook.fabrics
    with connect(server) as client:
        before = fabrics.cooked
        with client.submit_grid(5, 3) as h:  # a geometry new to this server: cooked, and counted
            collect(h, 1)
        cooked, submits = fabrics.cooked, reg.requests["submit"]
        assert cooked == before + 1
        with pytest.raises(ProtocolError) as e:
            client.submit_grid(4000, 4000, pinned=[0, 3999])
        assert e.value.code == P.ERR_TOO_LARGE
        assert e.value.message == "grid of 4000x4000 = 16000000 vertices exceeds the limit of 4096 vertices per cloth"
        assert reg.requests["submit"] == submits  # the SDK never sent it
        grid = P.GridSpec(4000, 4000, 1.0, 1.0, "horizontal", (0.0, 0.0, 0.0))
        with pytest.raises(ProtocolError) as e:
            client.request("submit", P.encode_submit(P.SubmitRequest(client=client.client_id, grid=grid)))
        assert e.value.code == P.ERR_TOO_LARGE
        assert e.value.message == "grid of 4000x4000 = 16000000 vertices exceeds the limit of 4096 vertices per cloth"
        assert reg.requests["submit"] == submits + 1 and reg.errors[P.ERR_TOO_LARGE] >= 1
        assert fabrics.cooked == cooked  # refused before the cook
        with client.submit_grid(64, 64) as big:  # the limit itself is fine, and its rest pose is there
            assert big.n_vertices == 4096 and big.rest_positions.shape == (4096, 3)
            assert big.triangles.shape == (2 * 63 * 63, 3)
            assert collect(big, 1)[0].positions.shape == (4096, 3)


def test_the_first_cloths_of_the_default_features_build_nothing():
    """The server builds and runs the default feature set's kernels before it serves: for a small
    cloth and for the largest it admits (on the CPU 65,536 vertices take the global-memory
    kernels, which the first such submit built on the way in: 2.2 s for a 256x256 cloth). Counted
    on the Device's builds, not timed."""
    s = Server(make_config(max_vertices_per_cloth=65536, max_total_vertices=70000)).start()
    try:
        dev = s.ticker.world.dev
        built = len(dev.builds)
        assert built >= 1  # at start-up, before the server was up
        with connect(s) as client:
            for cols, rows in ((32, 32), (1, 65536)):  # a strip: the largest cloth, cheap to cook and step
                with client.submit_grid(cols, rows, pinned=[0], timeout=30.0) as h:  # slack for a busy machine
                    assert collect(h, 2, 30.0)[-1].positions.shape == (cols * rows, 3)
        assert dev.builds[built:] == []
    finally:
        s.stop()
    assert s.failure is None


def test_the_feature_sets_a_deployment_declares_are_warm_at_start():
    """``warm_features`` (default "tethers", the README's first cloth): their kernels are built
    and run before the server serves, so that such a first cloth builds nothing (counted)."""
    s = Server(make_config(warm_features="tethers,xpbd+colliders")).start()
    try:
        dev = s.ticker.world.dev
        built = len(dev.builds)
        with connect(s) as client:
            for features in (["tethers"], ["xpbd", "colliders"]):
                with client.submit_grid(32, 32, pinned=[0, 31], features=features, timeout=30.0) as h:
                    collect(h, 2, 30.0)
        assert dev.builds[built:] == []
    finally:
        s.stop()
    assert s.failure is None
    with pytest.raises(ValueError, match="unknown feature"):
        make_config(warm_features="tethers+hologram")
