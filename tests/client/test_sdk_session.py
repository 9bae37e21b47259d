"""drape.client.session: the Zenoh configuration shared by the SDK and the server, and the sample
JSON5 configurations shipped in deploy/ (they load, and sessions built from them talk over real
Zenoh on loopback); the SDK's side of protocol 1.2 (features_add / features_remove)."""

from __future__ import annotations

import queue
import socket
from pathlib import Path

import pytest
import zenoh

from drape.client import protocol as P

pytestmark = pytest.mark.zenoh  # not unit (tests/conftest.py)

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
SAMPLES = {"peer": DEPLOY / "zenoh-peer.json5", "client": DEPLOY / "zenoh-client.json5"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_zenoh_config_has_one_home_and_the_old_paths_still_work():
    import drape.client
    import drape.client.sdk
    from drape.client.session import zenoh_config

    assert drape.client.zenoh_config is zenoh_config
    assert drape.client.sdk.zenoh_config is zenoh_config
    cfg = zenoh_config("client", listen=["tcp/127.0.0.1:1"], connect=["tcp/127.0.0.1:7447"])
    assert cfg.get_json("mode") == '"client"' and cfg.get_json("connect/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert cfg.get_json("scouting/multicast/enabled") == "false"
    with pytest.raises(ValueError, match="mode"):
        zenoh_config("server")


@pytest.mark.parametrize("mode", SAMPLES)
def test_the_sample_configurations_load(mode):
    cfg = zenoh.Config.from_file(str(SAMPLES[mode]))
    assert cfg.get_json("mode") == f'"{mode}"'
    assert cfg.get_json("connect/endpoints") == f'["{P.DEFAULT_ENDPOINT}"]'
    assert cfg.get_json("scouting/multicast/enabled") == "false"


def test_a_peer_built_from_the_sample_reaches_a_listening_peer():
    """The sample peer configuration as a base file, its endpoint overridden, talks to a peer that
    listens on its own port: a publication arrives (the test waits for the event, not a time)."""
    from drape.client.session import zenoh_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: queue.Queue[bytes] = queue.Queue()
    server = zenoh.open(zenoh_config("peer", listen=[endpoint]))
    try:
        sub = server.declare_subscriber("drape-test/session/ping", lambda s: got.put(s.payload.to_bytes()))
        client = zenoh.open(zenoh_config("peer", connect=[endpoint], base_file=str(SAMPLES["peer"])))
        try:
            pub = client.declare_publisher("drape-test/session/ping")
            for _ in range(600):  # until the subscription has propagated; at most a minute
                pub.put(b"ping")
                try:
                    assert got.get(timeout=0.1) == b"ping"
                    break
                except queue.Empty:
                    continue
            else:
                pytest.fail("no publication arrived in 60 s")
        finally:
            client.close()
        sub.undeclare()
    finally:
        server.close()


def test_sdk_features_delta_is_validated_before_anything_is_sent():
    from drape.client.controls import set_changes

    ch = set_changes(features_add=["wind"], features_remove="tethers")
    req = P.ControlRequest("abc", "0" * 32, **ch)
    assert req.features_add == ("wind",) and req.features_remove == ("tethers",) and req.features is None
    assert P.decode_control(P.encode_control(req)) == req
    with pytest.raises(ValueError, match="hologram"):
        set_changes(features_add=["hologram"])
    with pytest.raises(ValueError, match="both"):
        set_changes(features_add=["wind"], features_remove=["wind"])
    with pytest.raises(TypeError, match="gravty"):
        set_changes(gravty=(0, -9.81, 0))


def test_set_takes_every_control_field_of_the_table():
    """A new control field (protocol.CONTROL_FIELDS) reaches ClothHandle.set / ControlBatch.set
    or this fails: SetOptions is the SDK's one list of set()'s arguments."""
    from dataclasses import fields

    from drape.client.controls import SET_FIELDS, STATE_OPTIONS, SetOptions, set_changes

    own_methods = {"pins", "colliders", "state"}  # move_pins, set_colliders; state's options are flat
    table = {f.name for f in P.CONTROL_FIELDS} - own_methods
    assert {f.name for f in SET_FIELDS} == table
    assert set(SetOptions.__annotations__) == table | set(STATE_OPTIONS)
    assert set(STATE_OPTIONS) == {f.name for f in fields(P.StateOptions)} - {"bundle"}
    ch = set_changes(
        gravity=(0, -1, 0), material={"damping": 0.1}, iterations=4, reset=True, encoding="quant16", step=0.002
    )
    req = P.ControlRequest("abc", "0" * 32, **ch)
    assert req.gravity == (0.0, -1.0, 0.0) and req.iterations == 4 and req.reset
    assert req.state == P.StateOptions(None, "quant16", None, 0.002)
    assert P.decode_control(P.encode_control(req)) == req
    assert set_changes()["state"] is None and set_changes()["material"] == {}


@pytest.mark.parametrize(
    "endpoint,says",
    [
        ("127.0.0.1:7447", "endpoint '127.0.0.1:7447' has no protocol; write tcp/127.0.0.1:7447"),
        ("localhost:7447", "endpoint 'localhost:7447' has no protocol; write tcp/localhost:7447"),
        ("tcp/", "endpoint 'tcp/' has no address; write e.g. tcp/127.0.0.1:7447"),
        ("tcp/127.0.0.1", "endpoint 'tcp/127.0.0.1' has no port; write e.g. tcp/127.0.0.1:7447"),
        ("tcp/127.0.0.1:99999", "endpoint 'tcp/127.0.0.1:99999': port 99999 is out of range 0..65535"),
    ],
)
def test_an_endpoint_zenoh_would_refuse_is_a_clear_value_error_before_any_session(endpoint, says):
    """Issue 20: ``DrapeClient("127.0.0.1:7447")`` printed Zenoh's Rust source paths."""
    from drape.client import DrapeClient
    from drape.client.session import zenoh_config

    with pytest.raises(ValueError) as e:
        DrapeClient(endpoint)
    assert str(e.value) == says
    with pytest.raises(ValueError) as e:
        DrapeClient(listen=[endpoint])
    assert str(e.value) == says
    with pytest.raises(ValueError) as e:  # the server's configuration is built by the same function
        zenoh_config("peer", listen=[endpoint])
    assert str(e.value) == says


@pytest.mark.parametrize(
    "endpoint", ["tcp/127.0.0.1:7447", "tcp/[::1]:0", "tls/host.example:7447#iface=lo", "unixsock-stream//tmp/z.sock"]
)
def test_endpoints_of_every_form_pass_the_check(endpoint):
    from drape.client.session import check_endpoint

    assert check_endpoint(endpoint) == endpoint


def test_zenohs_own_refusal_to_open_is_shown_without_its_rust_paths():
    """A session Zenoh cannot open (here: the listen port is taken) raises ConnectionError with
    Zenoh's message and the endpoints, not the Rust source locations Zenoh appends."""
    from drape.client import DrapeClient

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        ep = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        with pytest.raises(ConnectionError) as e:
            DrapeClient(f"tcp/127.0.0.1:{free_port()}", listen=[ep])
    msg = str(e.value)
    assert msg.startswith("cannot open a Zenoh session (peer, connect [") and ep in msg
    assert "Address already in use" in msg
    assert ".rs:" not in msg and ".cargo" not in msg
    assert e.value.__cause__ is None and e.value.__suppress_context__
