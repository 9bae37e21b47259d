"""The protocol's vocabulary and geometry are the server's (one definition, imported by the
server), and the client side needs no server code."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from drape.client import protocol as P


def test_vocabulary_matches_the_server_params():
    from drape.server.sim.params import ClothParams, Features, LinkOptions, Material

    assert tuple(f.name for f in dataclasses.fields(Features)) == P.FEATURE_NAMES
    assert tuple(f.name for f in dataclasses.fields(LinkOptions)) == tuple(
        f.name for f in dataclasses.fields(P.LinkSpec)
    )
    assert dataclasses.asdict(LinkOptions()) == dataclasses.asdict(P.LinkSpec())
    assert set(P.MATERIAL_FIELDS) == {f.name for f in dataclasses.fields(Material)}
    assert dataclasses.asdict(Material()) == P.MATERIAL_DEFAULTS
    d = ClothParams()
    assert (d.gravity, d.wind, d.iterations, d.substeps, d.chebyshev_rho) == (
        P.DEFAULT_GRAVITY,
        P.DEFAULT_WIND,
        P.DEFAULT_ITERATIONS,
        P.DEFAULT_SUBSTEPS,
        P.DEFAULT_CHEBYSHEV_RHO,
    )
    # every per-cloth parameter can be sent in a submission and changed by a control
    submit_fields = {f.name for f in dataclasses.fields(P.SubmitRequest)}
    control_fields = {f.name for f in dataclasses.fields(P.ControlRequest)}
    for f in dataclasses.fields(ClothParams):
        assert f.name in submit_fields and f.name in control_fields, f.name


def test_material_map_accepts_the_server_dataclass():
    from drape.server.sim.params import Material

    m = P.material_to_map(Material(mass=2.0))
    assert m["mass"] == 2.0 and m["stiffness"] == [1.0, 1.0, 1.0] and set(m) == set(P.MATERIAL_FIELDS)
    with pytest.raises(ValueError):
        P.material_to_map({"colour": 1})


@pytest.mark.parametrize("orientation", ["horizontal", "vertical"])
def test_grid_geometry_matches_the_server(orientation):
    from drape.server.sim.fabric import grid_mesh

    for cols, rows in [(1, 1), (2, 5), (7, 3)]:
        v, t = P.grid_geometry(cols, rows, 1.5, 0.7, orientation, (1, 2, 3))
        sv, st = grid_mesh(cols, rows, 1.5, 0.7, orientation, (1, 2, 3))
        np.testing.assert_array_equal(v, sv.astype(np.float32))
        np.testing.assert_array_equal(t, st)


def test_obj_parser_matches_the_server():
    from drape.server.sim.fabric import parse_obj

    text = "# quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/1 4/1\nf -1 -2 -3\n"
    v, t = P.parse_obj(text)
    sv, st = parse_obj(text)
    np.testing.assert_array_equal(v, sv.astype(np.float32))
    np.testing.assert_array_equal(t, st)


def test_client_needs_no_server_code():
    code = (
        "import sys\n"
        "import drape.client.protocol\n"
        "assert 'zenoh' not in sys.modules, 'protocol must not import zenoh'\n"
        "import drape.client\n"
        "assert 'zenoh' not in sys.modules, 'the package must not import zenoh before the SDK is used'\n"
        "from drape.client import DrapeClient, ClothHandle\n"
        "import drape.client.sdk\n"
        "bad = [m for m in sys.modules if m.startswith('drape.server') or m.startswith('pyopencl')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
