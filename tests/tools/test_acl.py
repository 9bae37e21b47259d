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
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from drape.client.protocol import Keys
from drape.server.tools import acl
from drape.server.tools.procs import free_port

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "deploy" / "users.example.toml"
WAIT = 20.0  # seconds to wait for a positive event (a loaded CI machine), never asserted on
SERVER_WAIT = 90.0  # a drape serve starting (OpenCL warm-up) on a loaded CI machine

USERS = """
namespace = "drape"
[[user]]
name = "eu-1"
role = "server"
id = "eu-1"
password = "pw-server"
[[user]]
name = "alice"
role = "client"
id = "alice"
password = "pw-alice"
[[user]]
name = "bob"
role = "client"
id = "bob"
password = "pw-bob"
"""


def test_example_users_file_generates_a_section_zenoh_loads(tmp_path):
    users = acl.load_users(EXAMPLE)
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
            str(EXAMPLE),
            "--router-config",
            str(REPO / "deploy/zenoh-router.json5"),
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


def test_client_rules_bind_keys_to_the_client_id():
    users = acl.load_users(EXAMPLE)
    keys = Keys(users.namespace)
    section = acl.access_control(users)
    rules = {r["id"]: r for r in section["rules"]}
    assert rules["u-alice-token-liveliness_token"]["key_exprs"] == [keys.alive_client("alice")]
    assert rules["u-alice-subscribe-declare_subscriber"]["key_exprs"] == sorted([keys.bundle("alice"), keys.stats("*")])
    assert all(
        "declare_queryable" not in r["messages"] or r["flows"] == ["egress"]
        for r in section["rules"]
        if r["id"].startswith(("u-alice", "u-bob"))
    )
    opened = acl.access_control(users, cloth_states="any")
    bob_reads = {k for r in opened["rules"] if r["id"] == "u-bob-subscribe-declare_subscriber" for k in r["key_exprs"]}
    assert keys.state("*") in bob_reads


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


def _session(
    endpoint: str, user: str | None, password: str | None, tls: dict[str, str] | None, cert: str | None = None
) -> zenoh.Session:
    """A client-mode session; ``cert``: present that certificate (``{cert}.pem``, mutual TLS)."""
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    if tls:
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
    if tls and cert:
        d = Path(tls["ca"]).parent
        c.insert_json5("transport/link/tls/enable_mtls", "true")  # the connecting side must say so too
        c.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(d / f"{cert}-key.pem")))
        c.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(d / f"{cert}.pem")))
    if user:
        c.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        c.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(c)


def _make_certs(d: Path) -> dict[str, str]:
    """A CA and a router certificate for localhost, as deploy/certs/README.md makes them."""

    def ossl(*a: str) -> None:
        subprocess.run(["openssl", *a], cwd=d, check=True, capture_output=True)

    ossl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-subj",
        "/CN=drape-test-ca",
        "-keyout",
        "ca-key.pem",
        "-out",
        "ca.pem",
    )
    ossl(
        "req",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-subj",
        "/CN=localhost",
        "-keyout",
        "router-key.pem",
        "-out",
        "router.csr",
    )
    (d / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    ossl(
        "x509",
        "-req",
        "-in",
        "router.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca-key.pem",
        "-CAcreateserial",
        "-days",
        "2",
        "-extfile",
        "san.ext",
        "-out",
        "router.pem",
    )
    (d / "client.ext").write_text("extendedKeyUsage=clientAuth\n")
    for name in ("eu-1", "alice", "bob"):  # mutual TLS: one certificate per party, CN = name.drape.test
        ossl(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            f"/CN={name}.drape.test",
            "-keyout",
            f"{name}-key.pem",
            "-out",
            f"{name}.csr",
        )
        ossl(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca-key.pem",
            "-CAcreateserial",
            "-days",
            "2",
            "-extfile",
            "client.ext",
            "-out",
            f"{name}.pem",
        )
    return {"ca": str(d / "ca.pem"), "key": str(d / "router-key.pem"), "cert": str(d / "router.pem")}


@pytest.fixture(params=["tcp", "tls"])
def router(request, tmp_path):
    """A Zenoh router with the generated access control and user/password authentication."""
    users_file = tmp_path / "users.toml"
    users_file.write_text(USERS)
    users = acl.load_users(users_file)
    (tmp_path / "dict.txt").write_text(acl.dictionary(users))
    port = free_port()
    c = zenoh.Config.from_file(str(REPO / "deploy/zenoh-router.json5"))
    tls = None
    if request.param == "tls":
        if shutil.which("openssl") is None:
            pytest.skip("openssl not installed")
        tls = _make_certs(tmp_path)
        endpoint = f"tls/localhost:{port}"
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls["ca"]))
        c.insert_json5("transport/link/tls/listen_private_key", json.dumps(tls["key"]))
        c.insert_json5("transport/link/tls/listen_certificate", json.dumps(tls["cert"]))
    else:
        endpoint = f"tcp/127.0.0.1:{port}"
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "dict.txt")))
    c.insert_json5("access_control", json.dumps(acl.access_control(users)))
    r = zenoh.open(c)
    opened: list[zenoh.Session] = []

    def connect(user: str | None, password: str | None = None) -> zenoh.Session:
        s = _session(endpoint, user, password, tls)
        opened.append(s)
        return s

    yield connect
    for s in reversed(opened):
        s.close()
    r.close()


class Inbox:
    """Samples received on a subscriber (or liveliness subscriber), with an event per key."""

    def __init__(self) -> None:
        self.keys: list[str] = []
        self.payloads: list[bytes] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self.keys.append(str(sample.key_expr))
                self.payloads.append(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait_for(self, predicate) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self), WAIT)


def test_bob_cannot_act_as_alice_through_the_router(router):
    keys = Keys("drape")
    server = router("eu-1", "pw-server")
    alice = router("alice", "pw-alice")
    bob = router("bob", "pw-bob")

    # The server: its control queryable answers "server"; it sees client liveliness tokens.
    served = []

    def on_control(q: zenoh.Query) -> None:
        served.append(q.payload.to_bytes() if q.payload is not None else b"")
        q.reply(q.key_expr, b"server")

    server_q = server.declare_queryable(keys.control("eu-1"), on_control)
    tokens = Inbox()
    server_lv = server.liveliness().declare_subscriber(keys.all_clients_alive, tokens, history=True)
    bundle_a = server.declare_publisher(keys.bundle("alice"))
    bundle_b = server.declare_publisher(keys.bundle("bob"))

    def server_reachable(s: zenoh.Session, ping: bytes) -> list[bytes]:
        return [
            r.ok.payload.to_bytes()
            for r in s.get(keys.control("eu-1"), payload=ping, target=zenoh.QueryTarget.ALL, timeout=WAIT)
            if r.ok
        ]

    # 1. Liveliness: bob declares alice's token (refused), then his own (positive control).
    bob_as_alice = bob.liveliness().declare_token(keys.alive_client("alice"))
    bob_token = bob.liveliness().declare_token(keys.alive_client("bob"))
    assert tokens.wait_for(lambda i: keys.alive_client("bob") in i.keys), "the server never saw bob's own token"
    assert keys.alive_client("alice") not in tokens.keys

    # 2. Subscriptions: bob subscribes to alice's bundle (refused) and to his own.
    a_inbox, b_inbox = Inbox(), Inbox()
    alice.declare_subscriber(keys.bundle("alice"), a_inbox)
    bob.declare_subscriber(keys.bundle("alice"), b_inbox)
    bob.declare_subscriber(keys.bundle("bob"), b_inbox)
    bob.declare_subscriber("drape/**", b_inbox)  # a wildcard is no way round
    # 3. Spoofing: bob publishes a state into alice's bundle and on a cloth key (refused).
    bob.put(keys.bundle("alice"), b"spoofed")
    bob.put(keys.state("0123456789abcdef"), b"spoofed")
    # 4. Impostor: bob declares a queryable on the server's control key (refused).
    impostor = []

    def on_impostor(q: zenoh.Query) -> None:
        impostor.append(q.payload.to_bytes() if q.payload is not None else b"")
        q.reply(q.key_expr, b"impostor")

    bob_q = bob.declare_queryable(keys.control("eu-1"), on_impostor)
    # Bob's query reaches the server only after the router handled all of the above from bob
    # (his own session also answers it locally, from his own queryable: that stays in his process).
    assert b"server" in server_reachable(bob, b"bob")
    # Alice's query to every matching queryable: only the server answers, bob never sees it.
    assert server_reachable(alice, b"alice") == [b"server"]
    assert b"alice" not in impostor
    # Publications to both bundles, then a marker each: anything let through arrives before it.
    bundle_a.put(b"for-alice")
    bundle_b.put(b"for-bob")
    assert a_inbox.wait_for(lambda i: b"for-alice" in i.payloads)
    assert b_inbox.wait_for(lambda i: b"for-bob" in i.payloads)
    assert a_inbox.payloads == [b"for-alice"], "alice got something besides her own bundle (bob's spoof?)"
    # (bob's own session delivers his spoofs to his own subscribers locally: not a leak)
    assert b"for-alice" not in b_inbox.payloads, "bob read alice's bundle"
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
def test_mutual_tls_binds_each_user_to_its_certificate(tmp_path):
    """enable_mtls on the router and cert_common_name in the users file: a session needs a CA-signed
    certificate, and a user presenting another user's certificate matches no subject (denied)."""
    keys = Keys("drape")
    users_file = tmp_path / "users.toml"
    text = USERS
    for name, pw in (("eu-1", "pw-server"), ("alice", "pw-alice"), ("bob", "pw-bob")):
        text = text.replace(f'password = "{pw}"', f'password = "{pw}"\ncert_common_name = "{name}.drape.test"')
    users_file.write_text(text)
    users = acl.load_users(users_file)
    assert all(u.cert_common_name for u in users.users)
    (tmp_path / "dict.txt").write_text(acl.dictionary(users))
    tls = _make_certs(tmp_path)
    endpoint = f"tls/localhost:{free_port()}"
    c = zenoh.Config.from_file(str(REPO / "deploy/zenoh-router.json5"))
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
            opened.append(_session(endpoint, "alice", "pw-alice", tls))
        server = _session(endpoint, "eu-1", "pw-server", tls, cert="eu-1")
        opened.append(server)
        server.declare_queryable(keys.info("eu-1"), lambda q: q.reply(q.key_expr, b"server"))

        def ask(s: zenoh.Session) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in s.get(keys.info("eu-1"), timeout=WAIT) if r.ok]

        bob = _session(endpoint, "bob", "pw-bob", tls, cert="bob")
        bob_with_alices_cert = _session(endpoint, "bob", "pw-bob", tls, cert="alice")
        opened += [bob, bob_with_alices_cert]
        assert ask(bob) == [b"server"]
        assert ask(bob_with_alices_cert) == []
    finally:
        for sess in reversed(opened):
            sess.close()
        router.close()


def test_routerless_the_servers_own_peer_session_enforces_the_acl(tmp_path):
    """No router: the ACL and the user dictionary in the server's own (peer) session; clients in
    client mode connect straight to it. Zenoh applies the ACL on each of that session's transports."""
    keys = Keys("drape")
    users_file = tmp_path / "users.toml"
    users_file.write_text(USERS)
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
    alice = _session(endpoint, "alice", "pw-alice", None)
    bob = _session(endpoint, "bob", "pw-bob", None)
    try:
        tokens = Inbox()
        server.liveliness().declare_subscriber(keys.all_clients_alive, tokens, history=True)
        server.declare_queryable(keys.control("eu-1"), lambda q: q.reply(q.key_expr, b"server"))
        impostor: list[bytes] = []
        bob.declare_queryable(
            keys.control("eu-1"), lambda q: impostor.append(q.payload.to_bytes() if q.payload is not None else b"")
        )
        bob.liveliness().declare_token(keys.alive_client("alice"))
        bob.liveliness().declare_token(keys.alive_client("bob"))
        assert tokens.wait_for(lambda i: keys.alive_client("bob") in i.keys)
        assert keys.alive_client("alice") not in tokens.keys

        b_inbox = Inbox()
        bob.declare_subscriber(keys.bundle("alice"), b_inbox)
        bob.declare_subscriber(keys.bundle("bob"), b_inbox)
        pub_a, pub_b = server.declare_publisher(keys.bundle("alice")), server.declare_publisher(keys.bundle("bob"))

        def published_until_bob_has_his() -> bool:
            for _ in range(int(WAIT / 0.05)):
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
            for r in alice.get(keys.control("eu-1"), payload=b"alice", target=zenoh.QueryTarget.ALL, timeout=WAIT)
            if r.ok
        ]
        assert replies == [b"server"] and b"alice" not in impostor
    finally:
        for sess in (bob, alice, server):
            sess.close()


# ---------------------------------------------------------------------------------------------
# Drape itself behind the router: drape serve and the SDK, in client mode, with the generated ACL


def _user_file(d: Path, user: str, password: str) -> str:
    p = d / f"{user}.json5"
    auth = {"usrpwd": {"user": user, "password": password}}
    p.write_text(json.dumps({"mode": "client", "transport": {"auth": auth}}))
    return str(p)


def test_drape_serve_and_the_sdk_work_through_the_acl_router(tmp_path):
    from drape.client import DrapeClient, NotFound
    from drape.client import protocol as P

    users_file = tmp_path / "users.toml"
    users_file.write_text(USERS)
    users = acl.load_users(users_file)
    (tmp_path / "dict.txt").write_text(acl.dictionary(users))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    c = zenoh.Config.from_file(str(REPO / "deploy/zenoh-router.json5"))
    c.insert_json5("listen/endpoints", json.dumps([endpoint]))
    c.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "dict.txt")))
    c.insert_json5("access_control", json.dumps(acl.access_control(users)))
    router = zenoh.open(c)
    log = open(tmp_path / "server.log", "w")
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "drape.server.cli",
            "serve",
            "--mode",
            "client",
            "--connect",
            endpoint,
            "--zenoh-config",
            _user_file(tmp_path, "eu-1", "pw-server"),
            "--server-id",
            "eu-1",
            "--stats-period",
            "0.5",
            "--no-admission",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
    )  # admission: not this test's subject
    clients: list[DrapeClient] = []
    try:
        alice = DrapeClient(
            endpoint,
            mode="client",
            client_id="alice",
            timeout=SERVER_WAIT,
            zenoh_config_file=_user_file(tmp_path, "alice", "pw-alice"),
        )
        clients.append(alice)
        assert alice.server_id == "eu-1"  # found through the server's liveliness token
        cloth = alice.submit_grid(8, 8, pinned=[0, 7], bundle=True)
        state = cloth.next_state(timeout=WAIT)
        assert state.positions.shape == (64, 3)
        with pytest.raises(NotFound):  # an error reply crosses the router too
            alice.request("remove", P.encode_remove(P.RemoveRequest("0123456789abcdef", "0" * 32)))

        bob = DrapeClient(
            endpoint,
            mode="client",
            client_id="bob",
            timeout=WAIT,
            zenoh_config_file=_user_file(tmp_path, "bob", "pw-bob"),
        )
        clients.append(bob)
        stolen = Inbox()
        bob.session.declare_subscriber(Keys("drape").bundle("alice"), stolen)
        own = bob.submit_grid(8, 8, pinned=[0, 7], bundle=True)
        # alice's bundle is published every tick: 10 of bob's own states later, any let through is here
        first = own.next_state(timeout=WAIT).tick
        own.wait_for_tick(first + 10, timeout=WAIT)
        assert stolen.payloads == []
        assert cloth.next_state(timeout=WAIT).tick > state.tick  # alice is still served
    finally:
        for cl in reversed(clients):
            cl.close()
        server.terminate()
        server.wait(30)
        log.close()
        router.close()
