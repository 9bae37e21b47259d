"""``drape acl``: the generated access control loads in Zenoh and is enforced by a real Zenoh router
(user/password authentication, TLS with a CA made by openssl) on loopback: client bob, acting as
alice, is refused (her liveliness token, her bundle, an impostor queryable on the server's control
key, a spoofed state), while the same actions on his own keys pass as positive controls.

Every negative check is ordered behind a positive event that travels the same links after it, so
"nothing arrived" is asserted only once anything that had been let through would have arrived.
"""

from __future__ import annotations

import json
import shutil
import threading

import pytest
import zenoh

from drape.client import protocol as P
from drape.client.protocol import Keys
from drape.server.tools import acl
from drape.server.tools.procs import free_port

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def test_example_users_file_generates_a_section_zenoh_loads(tmp_path, acl_kit):
    users = acl.load_users(acl_kit.EXAMPLE)
    section = acl.access_control(users)
    cfg = zenoh.Config()
    cfg.insert_json5("access_control", json.dumps(section))
    loaded = json.loads(cfg.get_json("access_control"))
    assert loaded["default_permission"] == "deny" and loaded["enabled"] is True
    assert {s["id"] for s in loaded["subjects"]} == {f"s-{u.name}" for u in users.users}
    zenoh.Config.from_json5(json.dumps({"mode": "router", "access_control": section}))
    # the whole router configuration, through the command
    out = tmp_path / "router.json5"
    dict_file = tmp_path / "users.txt"
    args = _parse(
        [
            "acl",
            str(acl_kit.EXAMPLE),
            "--router-config",
            str(acl_kit.REPO / "deploy/zenoh-router.json5"),
            "--out",
            str(out),
            "--dictionary",
            str(dict_file),
        ]
    )
    assert acl.run(args) == 0
    router = zenoh.Config.from_file(str(out))
    assert json.loads(router.get_json("mode")) == "router"
    assert json.loads(router.get_json("access_control"))["rules"] == json.loads(json.dumps(section["rules"]))
    assert dict_file.read_text().splitlines()[0] == "eu-1:change-me-server"
    assert dict_file.stat().st_mode & 0o077 == 0


def test_client_rules_bind_keys_to_the_client_id(acl_kit):
    users = acl.load_users(acl_kit.EXAMPLE)
    keys = Keys(users.namespace)
    section = acl.access_control(users)
    rules = {r["id"]: r for r in section["rules"]}
    assert rules["u-alice-token-liveliness_token"]["key_exprs"] == [keys.alive_client("alice")]
    assert rules["u-alice-subscribe-declare_subscriber"]["key_exprs"] == sorted(
        [keys.client_all("alice"), keys.stats("*")]
    )
    # 1.4: only alice's own request keys (and info), never the server-wide ones of 1.0-1.3; 1.5:
    # keyframe queries on her own bundle and cloth state keys
    assert rules["u-alice-request-query"]["key_exprs"] == sorted(
        [keys.client_request(k, "*", "alice") for k in P.CLIENT_REQUESTS] + [keys.info("*"), keys.client_all("alice")]
    )
    every_key = {k for r in section["rules"] for k in r["key_exprs"]}
    server_wide = {getattr(keys, k)(sid) for k in P.CLIENT_REQUESTS for sid in ("*", "eu-1")} | {keys.state("*")}
    assert not every_key & server_wide
    assert all(
        "declare_queryable" not in r["messages"] or r["flows"] == ["egress"]
        for r in section["rules"]
        if r["id"].startswith(("u-alice", "u-bob"))
    )
    # --cloth-states any is deprecated: it changes nothing (per-cloth states are their owner's)
    assert acl.access_control(users, cloth_states="any") == section


@pytest.mark.parametrize(
    "bad, message",
    [
        ('[[user]]\nname = "a"\nrole = "admin"\nid = "a"\n', "role must be one of"),
        ('[[user]]\nname = "a b"\nrole = "client"\n', "name must be"),
        (
            '[[user]]\nname = "a"\nrole = "client"\nid = "x"\n[[user]]\nname = "b"\nrole = "client"\nid = "x"\n',
            "already belongs",
        ),
        ('namespace = "a//b"\n[[user]]\nname = "a"\nrole = "client"\n', "invalid namespace"),
        ('[[user]]\nname = "a"\nrole = "client"\ncolour = 1\n', "unknown key"),
        ("", "no [[user]]"),
    ],
)
def test_bad_users_files_are_refused_with_a_clear_error(tmp_path, bad, message):
    p = tmp_path / "users.toml"
    p.write_text(bad)
    with pytest.raises(ValueError, match=message.replace("[", r"\[")):
        acl.load_users(p)
    assert acl.run(_parse(["acl", str(p)])) == 2


def _parse(argv: list[str]):
    import argparse

    parser = argparse.ArgumentParser()
    parser.add_argument("cmd")
    acl.configure(parser)
    return parser.parse_args(argv)


# ---------------------------------------------------------------------------------------------
# Enforcement by a real router


def test_bob_cannot_act_as_alice_through_the_router(router, acl_kit):
    """Raw Zenoh sessions of the three users (the server's part played by hand): every key kind."""
    keys = Keys("drape")
    server = router("eu-1", "pw-server")
    alice = router("alice", "pw-alice")
    bob = router("bob", "pw-bob")

    # The server: its control queryable (1.4, client-scoped) answers "server"; it sees client tokens.
    served = []

    def on_control(q: zenoh.Query) -> None:
        served.append(q.payload.to_bytes() if q.payload is not None else b"")
        q.reply(q.key_expr, b"server")

    server_q = server.declare_queryable(keys.client_request("control", "eu-1", "*"), on_control)
    tokens = acl_kit.Inbox()
    server_lv = server.liveliness().declare_subscriber(keys.all_clients_alive, tokens, history=True)
    bundle_a = server.declare_publisher(keys.bundle("alice"))
    bundle_b = server.declare_publisher(keys.bundle("bob"))
    cloth_a = server.declare_publisher(keys.client_state("alice", "a0"))
    cloth_b = server.declare_publisher(keys.client_state("bob", "b0"))

    def ask(s: zenoh.Session, key: str, ping: bytes, timeout: float = acl_kit.WAIT) -> list[bytes]:
        replies = s.get(key, payload=ping, target=zenoh.QueryTarget.ALL, timeout=timeout)
        return [r.ok.payload.to_bytes() for r in replies if r.ok]

    # 1. Liveliness: bob declares alice's token (refused), then his own (positive control).
    bob_as_alice = bob.liveliness().declare_token(keys.alive_client("alice"))
    bob_token = bob.liveliness().declare_token(keys.alive_client("bob"))
    assert tokens.wait_for(lambda i: keys.alive_client("bob") in i.keys), "the server never saw bob's own token"
    assert keys.alive_client("alice") not in tokens.keys

    # 2. Subscriptions: bob subscribes to alice's bundle and cloth (refused) and to his own.
    a_inbox, b_inbox = acl_kit.Inbox(), acl_kit.Inbox()
    alice.declare_subscriber(keys.client_all("alice"), a_inbox)
    bob.declare_subscriber(keys.bundle("alice"), b_inbox)
    bob.declare_subscriber(keys.client_state("alice", "a0"), b_inbox)
    bob.declare_subscriber(keys.client_all("bob"), b_inbox)
    bob.declare_subscriber("drape/**", b_inbox)  # a wildcard is no way round
    # 3. Spoofing: bob publishes into alice's bundle, on her cloth's key and on a 1.3 cloth key (refused).
    bob.put(keys.bundle("alice"), b"spoofed")
    bob.put(keys.client_state("alice", "a0"), b"spoofed")
    bob.put(keys.state("0123456789abcdef"), b"spoofed")
    # 4. Impostor: bob declares a queryable on the server's control keys (refused).
    impostor = []

    def on_impostor(q: zenoh.Query) -> None:
        impostor.append(q.payload.to_bytes() if q.payload is not None else b"")
        q.reply(q.key_expr, b"impostor")

    bob_q = bob.declare_queryable(keys.client_request("control", "eu-1", "*"), on_impostor)
    # 5. Requests: bob on alice's key, on every client's key and on the 1.3 server-wide key (refused)
    # (his own impostor answers him locally: only the server's answer matters)
    assert b"server" not in ask(bob, keys.client_request("control", "eu-1", "alice"), b"bob-as-alice", 1.0)
    assert b"server" not in ask(bob, keys.client_request("control", "eu-1", "*"), b"bob-as-anyone", 1.0)
    assert b"server" not in ask(bob, keys.control("eu-1"), b"bob-server-wide", 1.0)
    # Bob's query on his own key reaches the server only after the router handled all of the above
    # from bob (his own session also answers it locally, from his own queryable: that stays in his process).
    assert b"server" in ask(bob, keys.client_request("control", "eu-1", "bob"), b"bob")
    # Alice's query to every matching queryable: only the server answers, bob never sees it.
    assert ask(alice, keys.client_request("control", "eu-1", "alice"), b"alice") == [b"server"]
    assert b"alice" not in impostor
    # Publications to both clients, then a marker each: anything let through arrives before it.
    bundle_a.put(b"bundle-alice")
    cloth_a.put(b"cloth-alice")
    bundle_b.put(b"bundle-bob")
    cloth_b.put(b"cloth-bob")
    assert a_inbox.wait_for(lambda i: b"cloth-alice" in i.payloads)
    assert b_inbox.wait_for(lambda i: b"cloth-bob" in i.payloads)
    assert sorted(a_inbox.payloads) == [b"bundle-alice", b"cloth-alice"], "alice got bob's spoofs?"
    # (bob's own session delivers his spoofs to his own subscribers locally: not a leak)
    assert not {b"bundle-alice", b"cloth-alice"} & set(b_inbox.payloads), "bob read alice's states"
    assert served == [b"bob", b"alice"]
    for d in (bob_q, bob_token, bob_as_alice, server_lv, server_q):
        d.undeclare()


def test_unknown_user_or_wrong_password_cannot_connect(router):
    with pytest.raises(zenoh.ZError):
        router(None)
    with pytest.raises(zenoh.ZError):
        router("alice", "wrong")
    with pytest.raises(zenoh.ZError):
        router("mallory", "pw-alice")


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")
def test_mutual_tls_binds_each_user_to_its_certificate(tmp_path, acl_kit):
    """enable_mtls on the router and cert_common_name in the users file: a session needs a CA-signed
    certificate, and a user presenting another user's certificate matches no subject (denied)."""
    keys = Keys("drape")
    users_file = tmp_path / "users.toml"
    text = acl_kit.USERS
    for name, pw in (("eu-1", "pw-server"), ("alice", "pw-alice"), ("bob", "pw-bob")):
        text = text.replace(f'password = "{pw}"', f'password = "{pw}"\ncert_common_name = "{name}.drape.test"')
    users_file.write_text(text)
    users = acl.load_users(users_file)
    assert all(u.cert_common_name for u in users.users)
    (tmp_path / "dict.txt").write_text(acl.dictionary(users))
    tls = acl_kit.make_certs(tmp_path)
    endpoint = f"tls/localhost:{free_port()}"
    c = zenoh.Config.from_file(str(acl_kit.REPO / "deploy/zenoh-router.json5"))
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
    c.insert_json5("transport/link/tls/listen_private_key", json.dumps(tls["key"]))
    c.insert_json5("transport/link/tls/listen_certificate", json.dumps(tls["cert"]))
    c.insert_json5("transport/link/tls/enable_mtls", "true")
    c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "dict.txt")))
    c.insert_json5("access_control", json.dumps(acl.access_control(users)))
    router = zenoh.open(c)
    opened: list[zenoh.Session] = []
    try:
        with pytest.raises(zenoh.ZError):  # no client certificate
            opened.append(acl_kit.session(endpoint, "alice", "pw-alice", tls))
        server = acl_kit.session(endpoint, "eu-1", "pw-server", tls, cert="eu-1")
        opened.append(server)
        server.declare_queryable(keys.info("eu-1"), lambda q: q.reply(q.key_expr, b"server"))

        def ask(s: zenoh.Session) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in s.get(keys.info("eu-1"), timeout=acl_kit.WAIT) if r.ok]

        bob = acl_kit.session(endpoint, "bob", "pw-bob", tls, cert="bob")
        bob_with_alices_cert = acl_kit.session(endpoint, "bob", "pw-bob", tls, cert="alice")
        opened += [bob, bob_with_alices_cert]
        assert ask(bob) == [b"server"]
        assert ask(bob_with_alices_cert) == []
    finally:
        for sess in reversed(opened):
            sess.close()
        router.close()


def test_routerless_the_servers_own_peer_session_enforces_the_acl(tmp_path, acl_kit):
    """No router: the ACL and the user dictionary in the server's own (peer) session; clients in
    client mode connect straight to it. Zenoh applies the ACL on each of that session's transports."""
    keys = Keys("drape")
    users_file = tmp_path / "users.toml"
    users_file.write_text(acl_kit.USERS)
    users = acl.load_users(users_file)
    (tmp_path / "dict.txt").write_text(acl.dictionary(users))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "dict.txt")))
    c.insert_json5("access_control", json.dumps(acl.access_control(users)))
    server = zenoh.open(c)
    alice = acl_kit.session(endpoint, "alice", "pw-alice", None)
    bob = acl_kit.session(endpoint, "bob", "pw-bob", None)
    try:
        tokens = acl_kit.Inbox()
        server.liveliness().declare_subscriber(keys.all_clients_alive, tokens, history=True)
        server.declare_queryable(keys.client_request("control", "eu-1", "*"), lambda q: q.reply(q.key_expr, b"server"))
        impostor: list[bytes] = []
        bob.declare_queryable(
            keys.client_request("control", "eu-1", "*"),
            lambda q: impostor.append(q.payload.to_bytes() if q.payload is not None else b""),
        )
        bob.liveliness().declare_token(keys.alive_client("alice"))
        bob.liveliness().declare_token(keys.alive_client("bob"))
        assert tokens.wait_for(lambda i: keys.alive_client("bob") in i.keys)
        assert keys.alive_client("alice") not in tokens.keys

        b_inbox = acl_kit.Inbox()
        bob.declare_subscriber(keys.bundle("alice"), b_inbox)
        bob.declare_subscriber(keys.bundle("bob"), b_inbox)
        pub_a, pub_b = server.declare_publisher(keys.bundle("alice")), server.declare_publisher(keys.bundle("bob"))

        def published_until_bob_has_his() -> bool:
            for _ in range(int(acl_kit.WAIT / 0.05)):
                pub_a.put(b"for-alice")
                pub_b.put(b"for-bob")
                if b"for-bob" in b_inbox.payloads:
                    return True
                threading.Event().wait(0.05)
            return False

        assert published_until_bob_has_his()
        assert b"for-alice" not in b_inbox.payloads
        replies = [
            r.ok.payload.to_bytes()
            for r in alice.get(
                keys.client_request("control", "eu-1", "alice"),
                payload=b"alice",
                target=zenoh.QueryTarget.ALL,
                timeout=acl_kit.WAIT,
            )
            if r.ok
        ]
        assert replies == [b"server"] and b"alice" not in impostor
    finally:
        for sess in (bob, alice, server):
            sess.close()


# ---------------------------------------------------------------------------------------------
# Drape itself behind the router: drape serve and the SDK, in client mode, with the generated ACL


def test_drape_serve_and_the_sdk_work_through_the_acl_router(drape_behind_router, acl_kit):
    """``drape serve`` in the default ``identity = "open"`` behind the router: its server-wide
    queryables are denied by the ACL, the 1.4 SDK uses its client-scoped keys and is served."""
    from drape.client import DrapeClient, NotFound
    from drape.client import protocol as P

    d = drape_behind_router
    clients: list[DrapeClient] = []
    try:
        alice = DrapeClient(
            d.endpoint,
            mode="client",
            client_id="alice",
            timeout=acl_kit.SERVER_WAIT,
            zenoh_config_file=d.client_file("alice"),
        )
        clients.append(alice)
        assert alice.server_id == "eu-1"  # found through the server's liveliness token
        cloth = alice.submit_grid(8, 8, pinned=[0, 7], bundle=True)
        state = cloth.next_state(timeout=acl_kit.WAIT)
        assert state.positions.shape == (64, 3)
        single = alice.submit_grid(4, 4, pinned=[0, 3])  # 1.4: her own per-cloth state key is readable
        assert single.key == Keys("drape").client_state("alice", single.id)
        assert single.next_state(timeout=acl_kit.WAIT).positions.shape == (16, 3)
        with pytest.raises(NotFound):  # an error reply crosses the router too
            alice.request("remove", P.encode_remove(P.RemoveRequest("0123456789abcdef", "0" * 32)))

        bob = DrapeClient(
            d.endpoint, mode="client", client_id="bob", timeout=acl_kit.WAIT, zenoh_config_file=d.client_file("bob")
        )
        clients.append(bob)
        stolen = acl_kit.Inbox()
        bob.session.declare_subscriber(Keys("drape").bundle("alice"), stolen)
        bob.session.declare_subscriber(single.key, stolen)
        own = bob.submit_grid(8, 8, pinned=[0, 7], bundle=True)
        # alice's states are published every tick: 10 of bob's own states later, any let through is here
        first = own.next_state(timeout=acl_kit.WAIT).tick
        own.wait_for_tick(first + 10, timeout=acl_kit.WAIT)
        assert stolen.payloads == []
        assert cloth.next_state(timeout=acl_kit.WAIT).tick > state.tick  # alice is still served
    finally:
        for cl in reversed(clients):
            cl.close()


def test_stats_reach_a_wildcard_subscriber_through_the_acl_router(drape_behind_router, acl_kit):
    """Placement reads every server's stats on ``{ns}/server/*/stats``: behind the generated ACL
    router that wildcard subscription must reach the server (its declaration goes to the server
    so that the server sends its stats), not only the exact key."""
    with drape_behind_router.sdk("alice") as alice:
        inbox = acl_kit.Inbox()
        alice.session.declare_subscriber(Keys("drape").stats("*"), inbox)
        # the server may still be starting (its OpenCL warm-up took over 20 s in a loaded CI run)
        assert inbox.wait_for(lambda i: len(i.payloads) >= 2, acl_kit.SERVER_WAIT), "no stats on the wildcard key"
        assert set(inbox.keys) == {Keys("drape").stats("eu-1")}
        assert acl_kit.wait_until(lambda: alice.placement.loads(["eu-1"])[0].known)  # placement sees its load


def test_keyframe_queries_cross_the_acl_router_for_their_owner_only(drape_behind_router, acl_kit):
    """1.5: alice asks for a keyframe of her predictive cloth on its state key and the server
    answers through the router; bob's query on her key is denied (no answer)."""
    import msgpack

    d = drape_behind_router
    with d.sdk("alice") as alice:
        cloth = alice.submit_grid(6, 6, pinned=[0, 5], encoding="predictive", step=0.002)
        cloth.next_state(timeout=acl_kit.WAIT)
        answers = [r.ok.payload.to_bytes() for r in alice.session.get(cloth.key, timeout=acl_kit.WAIT) if r.ok]
        assert len(answers) == 1 and msgpack.unpackb(answers[0])["cloths"] == 1
        bob = d.session("bob")
        try:
            assert [r for r in bob.get(cloth.key, timeout=2.0) if r.ok] == []
        finally:
            bob.close()
