"""The registry's scenes (protocol 1.7, PROTOCOL.md 5.3): the client of a scene's first cloth owns
it, others join only as its members, only the owner passes owned_scene, and a scene ends with its
last cloth (the next cloth under its id founds it again)."""

from __future__ import annotations

import pytest
from conftest import make_config

from drape.client import protocol as P
from drape.server.service.registry import ClothRecord, Registry


def _cloth(i: int, client: str, scene: str | None) -> ClothRecord:
    return ClothRecord(id=f"{i:016x}", client=client, token="0" * 32, key="", n_vertices=4, scene=scene)


def test_scene_owner_members_and_end():
    reg = Registry(make_config())
    a1 = _cloth(1, "alice", "hall")
    reg.reserve(a1, 0)
    assert reg.scenes["hall"].owner == "alice"
    with pytest.raises(P.Forbidden):
        reg.reserve(_cloth(2, "bob", "hall"), 0)
    assert "0000000000000002" not in reg.cloths and reg.vertices == 4  # a refused submit takes nothing
    with pytest.raises(P.Forbidden):
        reg.owned_scene("hall", "bob", 0)
    with pytest.raises(P.NotFound):
        reg.owned_scene("yard", "alice", 0)
    reg.owned_scene("hall", "alice", 0).members = ("bob",)
    b = _cloth(3, "bob", "hall")
    reg.reserve(b, 0)
    reg.unreserve(a1)  # the owner's cloths leave; the scene and its ownership stay
    assert reg.scenes["hall"].owner == "alice" and reg.scenes["hall"].cloths == {b.id}
    reg.unreserve(b)  # the last cloth: the scene ends
    assert "hall" not in reg.scenes
    reg.reserve(_cloth(4, "bob", "hall"), 0)  # founded again: bob owns it now
    assert reg.scenes["hall"].owner == "bob"
    reg.owned_scene("hall", "bob", 0).members = (P.SCENE_ANYONE,)
    reg.reserve(_cloth(5, "carol", "hall"), 0)  # anyone
    reg.reserve(_cloth(6, "carol", None), 0)  # a cloth in no scene joins none
    assert reg.scenes["hall"].cloths == {f"{4:016x}", f"{5:016x}"}
