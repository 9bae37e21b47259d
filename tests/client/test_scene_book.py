"""What the SDK remembers of a scene for its failover (client/scenes.py): every field its scene
requests last set, the mesh collider as a whole mesh at its last pose, replayed as one request."""

from __future__ import annotations

import numpy as np

from drape.client import protocol as P
from drape.client.scenes import SceneState

TRIS = np.array([[0, 1, 2]], np.uint32)


def _verts(rng) -> np.ndarray:
    return rng.uniform(-1.0, 1.0, (3, 3)).astype(np.float32)


def test_nothing_set_replays_nothing():
    assert SceneState().replay("c", "s", 1) is None


def test_the_last_of_each_field_is_replayed(rng):
    st = SceneState()
    ball = P.Sphere(tuple(rng.uniform(-1, 1, 3)), 0.1)
    st.sent(P.SceneRequest("c", "s", colliders=(ball,), members=("m1",)))
    st.sent(P.SceneRequest("c", "s", members=("m2", "*")))  # colliders absent: kept
    v = _verts(rng)
    st.sent(P.SceneRequest("c", "s", mesh_collider=P.MeshCollider(v, TRIS)))
    moved = P.MeshCollider.pose(rng.uniform(-1, 1, 3), (0.0, 1.0, 0.0, 0.0))
    st.sent(P.SceneRequest("c", "s", mesh_collider=moved))  # a rigid move of that mesh
    v2 = _verts(rng)
    st.sent(P.SceneRequest("c", "s", mesh_collider=P.MeshCollider(v2, None, moved.position, moved.rotation)))
    req = st.replay("c", "s", 7)
    assert req is not None and req.rid == 7 and req.colliders == (ball,) and req.members == ("m2", "*")
    mc = req.mesh_collider
    assert mc is not None and np.array_equal(mc.vertices, v2) and np.array_equal(mc.triangles, TRIS)
    assert mc.position == moved.position and mc.rotation == moved.rotation


def test_a_removed_mesh_is_not_replayed(rng):
    st = SceneState()
    st.sent(P.SceneRequest("c", "s", mesh_collider=P.MeshCollider(_verts(rng), TRIS)))
    st.sent(P.SceneRequest("c", "s", mesh_collider=P.MeshCollider.removal()))
    assert st.replay("c", "s", 1) is None and st.mesh_removed
