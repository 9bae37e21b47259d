"""Identity bound to the keys (protocol 1.4, PROTOCOL.md 11.2), on loopback without a router: a real
in-process Server and real Zenoh sessions.

- ``identity = "open"`` (the default) serves a 1.3 client on the server-wide keys exactly as before
  and a 1.4 client on its client-scoped keys, side by side;
- ``identity = "keys"`` declares only the client-scoped queryables; the server takes every
  request's client id from its key: a payload ``client`` that differs, a control, batch item or
  remove of another client's cloth (even with that cloth's token), a key naming no single client,
  are refused ``forbidden``; ``max_cloths_per_client`` holds per key identity; the SDK's failover
  probe goes to the client-scoped key.

What a router adds (only the user whose id a key names may use it) is tests/tools/test_identity.py.
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zenoh
from conftest import TIMEOUT, collect, connect, make_config, wait_until  # shared helpers

from drape.client import DrapeClient, Forbidden, LimitExceeded
from drape.client import protocol as P
from drape.server.service import Server

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def as_13(payload: bytes) -> bytes:
    """The same request as a 1.3 client writes it (``v = [1, 3]``)."""
    m = msgpack.unpackb(payload, raw=False)
    m["v"] = [1, 3]
    return msgpack.packb(m, use_bin_type=True)


def ask(session: zenoh.Session, key: str, payload: bytes) -> list[dict | P.DrapeError]:
    """Every reply to one query: the success map, or the DrapeError of an error reply."""
    out: list[dict | P.DrapeError] = []
    for r in session.get(key, payload=payload, timeout=TIMEOUT):
        data = r.ok.payload.to_bytes() if r.ok is not None else r.err.payload.to_bytes()
        try:
            out.append(P.decode_reply(data))
        except P.DrapeError as e:
            out.append(e)
    return out


def submit_request(client: str, rid: int = 1) -> P.SubmitRequest:
    return P.SubmitRequest(client=client, grid=P.GridSpec(4, 4, 1.0, 1.0), pinned=np.array([0, 3], np.uint32), rid=rid)


@pytest.fixture(scope="module")
def open_server():
    s = Server(make_config()).start()
    yield s
    s.stop()
    assert s.failure is None


@pytest.fixture(scope="module")
def keys_server():
    s = Server(make_config(identity="keys", max_cloths_per_client=2)).start()
    yield s
    s.stop()
    assert s.failure is None


def test_open_mode_serves_a_1_3_client_on_the_old_keys_and_a_1_4_client_on_its_own(open_server):
    keys, sid = P.Keys(), open_server.server_id
    old = DrapeClient(open_server.config.listen[0], server_id=sid, client_id="old13", timeout=TIMEOUT)
    new = connect(open_server)
    try:
        # 1.3: server-wide submit, the 1.0 state key, control and remove on server-wide keys
        (rep,) = ask(old.session, keys.submit(sid), as_13(P.encode_submit(submit_request("old13"))))
        assert isinstance(rep, dict) and rep["ok"], rep
        assert rep["key"] == keys.state(rep["cloth"])
        inbox: list[P.ClothState] = []
        sub = old.session.declare_subscriber(rep["key"], lambda s: inbox.append(P.decode_state(s.payload.to_bytes())))
        assert wait_until(lambda: len(inbox) >= 3)
        ctl = P.encode_control(P.ControlRequest(rep["cloth"], rep["token"], gravity=(0.0, 0.0, -1.0), rid=2))
        (c,) = ask(old.session, keys.control(sid), as_13(ctl))
        assert isinstance(c, dict) and c["ok"]
        # 1.4: the SDK found the version and uses its own keys; its state key names it
        h = new.submit_grid(4, 4, pinned=[0, 3])
        assert new.connection.key("submit", sid) == keys.client_request("submit", sid, new.client_id)
        assert h.key == keys.client_state(new.client_id, h.id)
        assert len(collect(h, 3)) == 3
        h.move_pins([0, 3], [[0, 0, 0], [1, 0, 0]], wait=True)
        ticks = new.move_pins_many([h], [0, 3], [[[0, 0, 0], [1, 0, 0.1]]], wait=True)  # control_batch
        assert ticks is not None and all(isinstance(t, int) for t in ticks), ticks
        h.remove()
        rm = P.encode_remove(P.RemoveRequest(rep["cloth"], rep["token"], rid=3))
        (r,) = ask(old.session, keys.remove(sid), as_13(rm))
        assert isinstance(r, dict) and r["ok"]
        sub.undeclare()
    finally:
        new.close()
        old.close()


def test_keys_mode_declares_only_the_client_scoped_queryables(keys_server):
    keys, sid = P.Keys(), keys_server.server_id
    with connect(keys_server) as c:
        for kind in P.CLIENT_REQUESTS:  # no queryable: no reply at all (a 1.3 client is not served)
            assert ask(c.session, getattr(keys, kind)(sid), P.encode_submit(submit_request(c.client_id))) == []
        with c.submit_grid(4, 4, pinned=[0, 3], bundle=True) as b, c.submit_grid(4, 4, pinned=[0, 3]) as h:
            assert h.key == keys.client_state(c.client_id, h.id) and b.bundle_key == keys.bundle(c.client_id)
            assert len(collect(h, 2)) == 2 and len(collect(b, 2)) == 2
            h.move_pins([0, 3], [[0, 0, 0], [1, 0, 0]], wait=True)
            assert c.info()["cloths"] == 2


def test_a_request_naming_another_client_than_its_key_is_forbidden(keys_server):
    keys, sid = P.Keys(), keys_server.server_id
    with connect(keys_server, client_id="alice") as alice, connect(keys_server, client_id="bob") as bob:
        cloth = alice.submit_grid(4, 4, pinned=[0, 3])
        # bob on his own key, submitting for alice: refused before anything is counted for alice
        with pytest.raises(Forbidden, match="alice"):
            bob.request("submit", P.encode_submit(submit_request("alice")))
        # bob on his own key with alice's cloth AND her token: not his cloth
        steal = P.ControlRequest(cloth.id, cloth.token, gravity=(0.0, 0.0, 9.81), rid=5)
        with pytest.raises(Forbidden, match="not a cloth of client 'bob'"):
            bob.request("control", P.encode_control(steal))
        with pytest.raises(Forbidden, match="not a cloth of client 'bob'"):
            bob.request("remove", P.encode_remove(P.RemoveRequest(cloth.id, cloth.token, rid=6)))
        rep = P.control_batch_reply_from_map(
            bob.request("control_batch", P.encode_control_batch(P.ControlBatchRequest("bob", [steal], 7)))
        )
        assert rep.results[0].code == P.ERR_FORBIDDEN
        with pytest.raises(Forbidden):  # a batch naming alice on bob's key
            bob.request("control_batch", P.encode_control_batch(P.ControlBatchRequest("alice", [steal], 8)))
        # a key naming no single client (a wildcard query) binds no identity
        wild = ask(bob.session, keys.client_request("submit", sid, "*"), P.encode_submit(submit_request("bob")))
        assert [e.code for e in wild if isinstance(e, P.DrapeError)] == [P.ERR_FORBIDDEN] and len(wild) == 1
        # alice's cloth is untouched and still hers
        assert alice.info()["cloths"] == 1
        cloth.move_pins([0, 3], [[0, 0, 0], [1, 0, 0]], wait=True)
        cloth.remove()


def test_max_cloths_per_client_holds_per_key_identity(keys_server):
    with connect(keys_server, client_id="alice") as alice, connect(keys_server, client_id="bob") as bob:
        mine = [bob.submit_grid(4, 4, pinned=[0, 3]) for _ in range(2)]  # bob's quota (2)
        with pytest.raises(LimitExceeded):
            bob.submit_grid(4, 4, pinned=[0, 3])
        with pytest.raises(Forbidden):  # and he cannot spend alice's
            bob.request("submit", P.encode_submit(submit_request("alice")))
        hers = [alice.submit_grid(4, 4, pinned=[0, 3]) for _ in range(2)]
        assert {h.key.split("/")[2] for h in hers} == {"alice"} and {h.key.split("/")[2] for h in mine} == {"bob"}
        for h in mine + hers:
            h.remove()


def test_failover_probes_on_the_client_scoped_key(keys_server):
    """SDK failover against a keys-only server: a cloth reclaimed while its client was away is
    found by the probe (an empty control, on the client's own key) and resubmitted there."""
    with connect(keys_server, failover=True) as c:
        events: list = []
        c.on_failover(events.append)
        h = c.submit_grid(4, 4, pinned=[0, 3])
        collect(h, 2)
        assert c._failover is not None
        c._failover.pause()  # away: the failover thread held still, the token withdrawn
        c.connection.token.undeclare()
        assert wait_until(lambda: keys_server.registry.get(h.id) is None, 10 * TIMEOUT), "not reclaimed"
        c.connection.token = c.session.liveliness().declare_token(c.keys.alive_client(c.client_id))
        c._failover.resume()
        assert wait_until(lambda: len(events) >= 1, 10 * TIMEOUT), "the reclaim was never detected"
        assert events[0].ok and events[0].reason == "reclaimed", events
        assert h.key == P.Keys().client_state(c.client_id, h.id) and collect(h, 1)


def test_the_identity_setting_is_open_or_keys():
    from drape.server.service.config import ServerConfig

    assert ServerConfig().identity == "open"
    assert ServerConfig.load(env={"DRAPE_IDENTITY": "keys"}).identity == "keys"
    with pytest.raises(ValueError, match="identity must be one of"):
        ServerConfig.load(env={"DRAPE_IDENTITY": "strict"})
