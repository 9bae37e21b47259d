"""Mesh colliders over the wire (protocol 1.8) through the Python SDK and Zenoh on loopback: a
cape dropped onto a body mesh sent with its submission keeps out of it in every state it
receives, also once the body is moved by a pose; a scene's mesh moved only by the scene's owner;
bad meshes and moves of no mesh refused with errors that say what is wrong."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import WAIT, collect, connect, make_config

from drape.client import protocol as P
from drape.server.service.server import Server
from drape.server.sim.bodymesh import body_mesh
from drape.server.sim.collision import penetration
from drape.server.sim.meshes import pose_matrix

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

N = 9
THICKNESS = 0.01  # the crease case: a vertex went inside the armpit at 10 mm until the body faced out everywhere
QUARTER = (np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0)  # 90 degrees about +y


@pytest.fixture(scope="module")
def server():
    with Server(make_config()) as srv:
        yield srv


@pytest.fixture(scope="module")
def body():
    return body_mesh(0.05)  # 5,972 triangles: the 5,000-triangle body


def behind(states, body, pose) -> list[int]:
    return [penetration(s.positions, s.positions, 0.0, meshes=[(body, pose)]).behind for s in states]


def drop(server, body, with_mesh: bool):
    """A 0.6 m cape (10 mm thick) dropped from 1.65 m onto the body's head and shoulders (the body 0.3 m down,
    turned a quarter about y): its states and the body's pose."""
    c = connect(server)
    try:
        pos = (0.0, -0.3, 0.0)
        opts = dict(material={"thickness": THICKNESS, "friction": 0.3}, substeps=2)
        if with_mesh:
            opts.update(mesh_collider=body, mesh_position=pos, mesh_rotation=QUARTER)
        h = c.submit_grid(N, N, 0.6, 0.6, origin=(-0.3, 1.65, -0.3), **opts)
        return h, c, collect(h, 140), pose_matrix(pos, QUARTER)  # the crease case: from state 113
    except BaseException:
        c.close()
        raise


def test_a_cape_dropped_on_a_body_mesh_keeps_out_of_it(server, body):
    """0 vertices inside the body at every received tick (the penetration metric), also after the
    body is moved 5 cm sideways by a rigid pose; without the mesh the cape falls into the body."""
    h, c, states, pose = drop(server, body, True)
    try:
        got = behind(states, body, pose)
        assert max(got) == 0, [(s.tick, n) for s, n in zip(states, got, strict=True) if n]
        assert min(s.positions[:, 1].min() for s in states[-5:]) > 0.5  # held up by the body
        moved = ((0.05, -0.3, 0.0), QUARTER)  # 5 cm sideways in one tick
        tick = h.set(mesh_collider=P.MeshCollider.pose(*moved))
        after = []
        while len(after) < 25:  # the states queued before the move are older
            s = h.next_state(WAIT)
            if s.tick >= tick:
                after.append(s)
        got = behind(after, body, pose_matrix(*moved))
        assert max(got) == 0, (tick, [(s.tick, n) for s, n in zip(after, got, strict=True) if n])
    finally:
        c.close()
    _, c, states, _ = drop(server, body, False)
    c.close()
    assert max(behind(states, body, pose)) > 0


def test_bad_meshes_and_moves_of_no_mesh_are_refused(server):
    c = connect(server)
    try:
        v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
        with pytest.raises(P.ProtocolError) as e:  # a degenerate triangle: the decoder's check
            c.submit_grid(2, 2, mesh_collider=(v, [[0, 1, 1]]))
        assert e.value.code == P.ERR_INVALID_VALUE and "degenerate" in e.value.message
        with pytest.raises(P.ProtocolError) as e:
            c.submit_grid(2, 2, mesh_collider=(v, [[0, 1, 3]]))
        assert e.value.code == P.ERR_INVALID_VALUE and "out of range" in e.value.message
        h = c.submit_grid(2, 2)
        with pytest.raises(P.DrapeError) as e:  # the tick thread's check: nothing to move
            h.set(mesh_collider=P.MeshCollider.pose((0, 1, 0)))
        assert e.value.code == P.ERR_INVALID_VALUE and "no mesh" in e.value.message
        h.set(mesh_collider=(v, [[0, 1, 2]]))
        with pytest.raises(P.DrapeError) as e:  # a re-pose of another vertex count
            h.set(mesh_collider=P.MeshCollider(np.zeros((4, 3), np.float32)))
        assert e.value.code == P.ERR_INVALID_VALUE and "re-pose" in e.value.message
        h.set(mesh_collider=P.MeshCollider(v * 2))  # a re-pose
        h.set(mesh_collider=P.MeshCollider.pose((0, 1, 0), QUARTER))
        h.set(mesh_collider=False)  # removed, its grid given back
        assert server.call(lambda w: (len(w.mesh_colliders.own), len(w.mesh_colliders._grids))) == (0, 0)
    finally:
        c.close()


def test_only_the_owner_moves_a_scene_mesh(server, body):
    alice, bob = connect(server, client_id="mesh-alice"), connect(server, client_id="mesh-bob")
    try:
        alice.submit_grid(2, 2, scene="stage")
        alice.set_scene("stage", members=["mesh-bob"])
        bob.submit_grid(2, 2, scene="stage")
        rep = alice.set_scene("stage", mesh_collider=body, mesh_position=(0, 0, 1))
        assert rep.tick > 0 and rep.cloths == 2
        with pytest.raises(P.Forbidden):  # a member, not the owner
            bob.set_scene("stage", mesh_position=(0, 0, 2))
        assert alice.set_scene("stage", mesh_position=(0, 0, 2), mesh_rotation=QUARTER).tick >= rep.tick
        alice.set_scene("stage", mesh_collider=False)
        with pytest.raises(P.DrapeError) as e:
            alice.set_scene("stage", mesh_position=(0, 0, 3))
        assert e.value.code == P.ERR_INVALID_VALUE and "no mesh" in e.value.message
    finally:
        alice.close()
        bob.close()


def test_admission_prices_a_cloth_s_own_mesh_per_vertex_and_triangle(body):
    """A submission's mesh adds vertices x (MESH_VERTEX_WORK of the device's kind + MESH_TRIANGLE_WORK x triangles);
    a control that removes it takes that off, one that moves it changes nothing."""
    from types import SimpleNamespace

    from drape.server.service.requests.admission import MESH_TRIANGLE_WORK, MESH_VERTEX_WORK, Admission

    adm = Admission(make_config())
    grid = P.GridSpec(N, N)
    mesh = P.MeshCollider(body.vertices.astype(np.float32), body.triangles.astype(np.uint32))
    plain = adm.price_submit(P.SubmitRequest("c", grid))
    priced = adm.price_submit(P.SubmitRequest("c", grid, mesh_collider=mesh))
    extra = N * N * (MESH_VERTEX_WORK[adm.pricing.kind] + MESH_TRIANGLE_WORK * body.n_triangles)
    assert priced.mesh_triangles == body.n_triangles and priced.work == pytest.approx(plain.work + extra)
    rec = SimpleNamespace(priced=priced, n_vertices=N * N)
    token = "0" * 32
    assert adm.price_control(rec, P.ControlRequest("x", token, mesh_collider=P.MeshCollider.pose((0, 1, 0)))) is None
    removed = adm.price_control(rec, P.ControlRequest("x", token, mesh_collider=P.MeshCollider.removal()))
    assert removed is not None and removed.work == pytest.approx(plain.work) and removed.mesh_triangles == 0
