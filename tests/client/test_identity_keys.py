"""The 1.4 client-scoped keys (PROTOCOL.md 2 and 11.2) as ``drape.client.protocol.Keys`` spells
and parses them, and the client id a deployment gives the SDK (``DRAPE_CLIENT_ID``, the Zenoh
file's ``.client_id`` sidecar). No network."""

from __future__ import annotations

import pytest

from drape.client import protocol as P
from drape.client.session import deployment_client_id


@pytest.mark.parametrize("ns", ["drape", "game/eu"])
def test_client_scoped_keys_name_the_client_and_parse_back(ns):
    k = P.Keys(ns)
    assert k.client_request("submit", "eu-1", "alice") == f"{ns}/server/eu-1/client/alice/submit"
    assert k.client_state("alice", "c0ffee") == f"{ns}/client/alice/cloth/c0ffee/state"
    assert k.client_all("alice") == f"{ns}/client/alice/**"
    # the bundle and the per-cloth states share the client's prefix: one ACL rule covers both
    assert k.bundle("alice").startswith(k.client_all("alice")[:-2])
    assert k.client_state("alice", "x").startswith(k.client_all("alice")[:-2])
    for kind in P.CLIENT_REQUESTS:
        key = k.client_request(kind, "eu-1", "alice")
        assert k.request_client(key, kind) == "alice"
        other = "remove" if kind != "remove" else "submit"
        assert k.request_client(key, other) is None
    with pytest.raises(ValueError):
        k.client_request("info", "eu-1", "alice")  # info stays server-wide


@pytest.mark.parametrize(
    "key",
    [
        "drape/server/eu-1/client/*/submit",  # a wildcard names no single client
        "drape/server/eu-1/client/**/submit",
        "drape/server/eu-1/client/al$*/submit",
        "drape/server/eu-1/submit",  # the 1.0-1.3 server-wide key
        "other/server/eu-1/client/alice/submit",  # another namespace
        "drape/server/eu-1/client/alice/extra/submit",
        "drape/server/eu-1/clients/alice/submit",
    ],
)
def test_keys_naming_no_single_client_parse_to_none(key):
    assert P.Keys().request_client(key, "submit") is None


def test_the_deployment_gives_the_client_id(tmp_path):
    zf = tmp_path / "zenoh-client-tls.json5"
    zf.write_text("{}")
    assert deployment_client_id(None, env={}) is None
    assert deployment_client_id(str(zf), env={}) is None  # no sidecar
    (tmp_path / "zenoh-client-tls.json5.client_id").write_text("alice\n")
    assert deployment_client_id(str(zf), env={}) == "alice"
    assert deployment_client_id(str(zf), env={"DRAPE_CLIENT_ID": "bob"}) == "bob"  # the environment wins
    assert deployment_client_id(None, env={"DRAPE_CLIENT_ID": " carol "}) == "carol"
