"""Identity bound to authentication (protocol 1.4, PROTOCOL.md 11.2), end to end: ``drape serve
--identity keys`` behind a real Zenoh router with user/password authentication and the access
control ``drape acl`` generates (tests/tools/conftest.py), the SDK as alice and bob.

Alice's own flow works through the router; every cross-client attack of an authenticated bob is
refused, by the router (alice's keys are not his) or by the server (his key names bob, the payload
or the cloth is alice's). Every "nothing arrived" is ordered behind a positive event that travels
the same links after it (see test_acl.py), never behind a sleep.
"""

from __future__ import annotations

import pytest
import zenoh

from drape.client import DrapeClient, Forbidden, LimitExceeded
from drape.client import protocol as P

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

KEYS = P.Keys("drape")
PINS = [0, 7]


def grid_request(client: str, rid: int = 1) -> bytes:
    return P.encode_submit(P.SubmitRequest(client=client, grid=P.GridSpec(8, 8), rid=rid))


def server_replies(session: zenoh.Session, key: str, payload: bytes, timeout: float) -> list[bytes]:
    """The payloads of every reply (ok or error) to one query."""
    out = []
    for r in session.get(key, payload=payload, target=zenoh.QueryTarget.ALL, timeout=timeout):
        out.append(r.ok.payload.to_bytes() if r.ok is not None else r.err.payload.to_bytes())
    return out


@pytest.mark.serve_args("--identity", "keys", "--max-cloths-per-client", "3", "--grace-period", "1")
def test_bob_authenticated_cannot_act_as_alice_and_alice_is_served(drape_behind_router, acl_kit):
    d = drape_behind_router
    # alice takes her client id from the deployment: the sidecar next to her Zenoh file
    alice_file = d.client_file("alice")
    with open(alice_file + ".client_id", "w") as fh:
        fh.write("alice\n")
    clients: list[DrapeClient] = []
    try:
        alice = DrapeClient(d.endpoint, mode="client", timeout=acl_kit.SERVER_WAIT, zenoh_config_file=alice_file)
        clients.append(alice)
        assert alice.client_id == "alice" and alice.server_id == "eu-1"
        bob = DrapeClient(
            d.endpoint, mode="client", client_id="bob", timeout=acl_kit.WAIT, zenoh_config_file=d.client_file("bob")
        )
        clients.append(bob)
        sid = "eu-1"

        # bob's impostor queryable on the server's submit keys (declared before alice submits)
        impostor: list[bytes] = []
        bob_q = bob.session.declare_queryable(
            KEYS.client_request("submit", sid, "*"),
            lambda q: impostor.append(q.payload.to_bytes() if q.payload is not None else b""),
        )

        # --- alice's own flow, end to end through the router ---------------------------------------
        single = alice.submit_grid(8, 8, pinned=PINS)
        bundled = alice.submit_grid(8, 8, pinned=PINS, bundle=True)
        assert single.key == KEYS.client_state("alice", single.id)
        assert bundled.bundle_key == KEYS.bundle("alice")
        s0 = single.next_state(timeout=acl_kit.WAIT)
        b0 = bundled.next_state(timeout=acl_kit.WAIT)
        single.move_pins(PINS, [[0, 0, 0], [1, 0, 0]], wait=True)
        with alice.batch(wait=True) as batch:
            batch.move_pins(bundled, PINS, [[0, 0, 0], [1, 0, 0]])
        assert all(isinstance(t, int) for t in batch.results)
        assert impostor == [], "bob's impostor queryable received alice's submit"

        # --- bob submitting as alice -----------------------------------------------------------------
        # on alice's key: the router drops his query (no server reply; his own impostor may answer locally)
        denied = server_replies(bob.session, KEYS.client_request("submit", sid, "alice"), grid_request("alice"), 1.0)
        assert not any(b"cloth" in r for r in denied)
        # on the server-wide 1.3 key: denied by the router, and not declared by the server anyway
        assert server_replies(bob.session, KEYS.submit(sid), grid_request("alice"), 1.0) == []
        # on his own key with payload client alice: the server refuses it
        with pytest.raises(Forbidden, match="alice"):
            bob.request("submit", grid_request("alice"))

        # --- bob's control / remove / batch on alice's cloth, with her leaked token even -----------
        steal = P.ControlRequest(single.id, single.token, gravity=(0.0, 0.0, 9.81), rid=11)
        with pytest.raises(Forbidden, match="not a cloth of client 'bob'"):
            bob.request("control", P.encode_control(steal))
        with pytest.raises(Forbidden, match="not a cloth of client 'bob'"):
            bob.request("remove", P.encode_remove(P.RemoveRequest(single.id, single.token, rid=12)))
        rep = P.control_batch_reply_from_map(
            bob.request("control_batch", P.encode_control_batch(P.ControlBatchRequest("bob", [steal], 13)))
        )
        assert rep.results[0].code == P.ERR_FORBIDDEN
        # the same on alice's own key: dropped by the router
        for kind, payload in (
            ("control", P.encode_control(steal)),
            ("remove", P.encode_remove(P.RemoveRequest(single.id, single.token))),
        ):
            assert server_replies(bob.session, KEYS.client_request(kind, sid, "alice"), payload, 1.0) == []

        # --- bob reading alice's states, forging one, declaring her token ---------------------------
        stolen = acl_kit.Inbox()
        bob.session.declare_subscriber(single.key, stolen)
        bob.session.declare_subscriber(KEYS.bundle("alice"), stolen)
        bob.session.declare_subscriber(KEYS.client_all("alice"), stolen)
        bob.session.put(single.key, b"DRPS forged by bob")
        bob.session.put(KEYS.bundle("alice"), b"DRPB forged by bob")
        bob_as_alice = bob.session.liveliness().declare_token(KEYS.alive_client("alice"))
        own = bob.submit_grid(8, 8, pinned=PINS)  # after all of the above: the router handled them first
        first = own.next_state(timeout=acl_kit.WAIT).tick
        own.wait_for_tick(first + 10, timeout=acl_kit.WAIT)  # 10 ticks of alice's publications too
        assert stolen.payloads == [] or all(p.endswith(b"forged by bob") for p in stolen.payloads)  # his own, locally
        assert single.next_state(timeout=acl_kit.WAIT).tick > s0.tick
        assert bundled.next_state(timeout=acl_kit.WAIT).tick > b0.tick
        assert single.invalid == bundled.invalid == alice.bundle_invalid == 0, "alice received bob's forgeries"

        # --- per-identity quota: bob's cloths never count against alice's ---------------------------
        more = [bob.submit_grid(4, 4, pinned=[0, 3]) for _ in range(2)]  # bob: 3 of 3
        with pytest.raises(LimitExceeded):
            bob.submit_grid(4, 4, pinned=[0, 3])
        third = alice.submit_grid(4, 4, pinned=[0, 3])  # alice: 3 of 3, still hers to use
        assert third.key == KEYS.client_state("alice", third.id)
        for h in more:
            h.remove()

        # --- alice goes away; bob's token named "alice" never reached the server -------------------
        assert bob.info()["cloths"] == 4  # alice's 3, bob's 1
        alice.close(remove=False)  # her cloths now live only as long as her (real) token, plus the grace period
        clients.remove(alice)
        # reclaimed: had bob's "alice" token reached the server, it would keep them forever
        assert acl_kit.wait_until(lambda: bob.info()["cloths"] == 1), "alice's cloths were kept alive"
        assert own.next_state(timeout=acl_kit.WAIT).tick > first  # bob's own cloth is still served
        bob_as_alice.undeclare()
        bob_q.undeclare()
    finally:
        for c in reversed(clients):
            c.close()
