"""Protocol 1.7 scenes: the submit's ``scene`` and the scene request, both ways and refused as
PROTOCOL.md 5.3 says (a bad id, too many colliders or members, a members entry not an id)."""

from __future__ import annotations

import pytest

from drape.client import protocol as P


def _scene(**kw) -> bytes:
    m = {"v": [1, 7], "rid": 3, "client": "c1", "scene": "arena-1", **kw}
    return P.pack(m)


def test_submit_scene_round_trip():
    req = P.SubmitRequest(client="c1", grid=P.GridSpec(2, 2), scene="arena-1")
    back = P.decode_submit(P.encode_submit(req))
    assert back.scene == "arena-1" and back == req
    assert P.decode_submit(P.encode_submit(P.SubmitRequest(client="c1", grid=P.GridSpec(2, 2)))).scene is None


def test_scene_request_round_trip():
    req = P.SceneRequest("c1", "arena-1", (P.Sphere((0.0, 1.0, 0.0), 0.3),), ("c2", P.SCENE_ANYONE), 9)
    back = P.decode_scene(P.encode_scene(req))
    assert back == req and back.rid == 9
    probe = P.decode_scene(P.encode_scene(P.SceneRequest("c1", "arena-1")))
    assert probe.colliders is None and probe.members is None
    rep = P.SceneReply(7, "c1", 2, ("c2",), 9)
    assert P.scene_reply_from_map(P.decode_reply(P.encode_scene_reply(rep))) == rep


@pytest.mark.parametrize(
    ("data", "code"),
    [
        (P.pack({"v": [1, 7], "client": "c1"}), P.ERR_MISSING_FIELD),
        (_scene(scene="no spaces"), P.ERR_INVALID_VALUE),
        (_scene(members="c2"), P.ERR_INVALID_TYPE),
        (_scene(members=["c2", "not an id"]), P.ERR_INVALID_VALUE),
        (_scene(members=[f"c{i}" for i in range(P.MAX_SCENE_MEMBERS + 1)]), P.ERR_TOO_LARGE),
        (
            _scene(colliders=[{"type": "sphere", "center": [0, 0, 0], "radius": 1}] * (P.MAX_SCENE_COLLIDERS + 1)),
            P.ERR_TOO_LARGE,
        ),
        (P.pack({"v": [1, 7], "client": "c1", "grid": {"cols": 2, "rows": 2}, "scene": 5}), P.ERR_INVALID_TYPE),
    ],
)
def test_bad_scene_requests_are_refused(data, code):
    decode = P.decode_submit if b"grid" in data else P.decode_scene
    with pytest.raises(P.ProtocolError) as e:
        decode(data)
    assert e.value.code == code
