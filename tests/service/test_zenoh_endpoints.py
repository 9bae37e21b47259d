"""``--zenoh-config`` endpoints honoured (issue 26): a configuration file's ``listen`` endpoints
are opened, not replaced by Drape's default; ``--listen`` adds to them; the server logs what it
really listens on, and a client-mode server says it listens on nothing. Real Zenoh on loopback."""

from __future__ import annotations

import json
import logging

import pytest
import zenoh
from conftest import connect, endpoint, make_config

from drape.client import protocol as P
from drape.client.session import file_listen, listening, zenoh_config
from drape.server.service import Server


def _file(tmp_path, body: dict) -> str:
    path = tmp_path / "zenoh.json5"
    path.write_text(json.dumps(body))
    return str(path)


def test_a_files_listen_endpoints_are_kept_and_listen_adds_to_them(tmp_path):
    mine, extra = endpoint(), endpoint()
    f = _file(tmp_path, {"mode": "peer", "listen": {"endpoints": [mine]}})
    cfg = zenoh_config("peer", [], [], False, f, [P.DEFAULT_ENDPOINT])
    assert listening(cfg, "peer") == [mine]  # not replaced by the default
    assert listening(zenoh_config("peer", [extra], [], False, f, [P.DEFAULT_ENDPOINT]), "peer") == [mine, extra]
    bare = _file(tmp_path, {"mode": "peer"})  # a file without listen endpoints: the default
    assert file_listen(zenoh.Config.from_file(bare), "peer") == []
    assert listening(zenoh_config("peer", [], [], False, bare, [P.DEFAULT_ENDPOINT]), "peer") == [P.DEFAULT_ENDPOINT]
    by_mode = _file(tmp_path, {"listen": {"endpoints": {"peer": [mine], "router": [extra]}}})
    assert listening(zenoh_config("peer", [], [], False, by_mode), "peer") == [mine]
    assert listening(zenoh_config("client", [], [mine], False, f), "client") == []  # client mode: nothing


@pytest.mark.opencl
@pytest.mark.zenoh
def test_a_server_listens_on_its_files_endpoints_and_logs_them(tmp_path, caplog):
    mine = endpoint()
    f = _file(tmp_path, {"listen": {"endpoints": [mine]}})
    cfg = make_config(listen=[P.DEFAULT_ENDPOINT], server_id="endpoints-file", zenoh_config=f)
    caplog.set_level(logging.INFO, logger="drape.server.service.server")
    with Server(cfg) as srv:
        assert srv.listening == [mine]
        srv.config.listen = [mine]  # connect() takes the first listen endpoint
        c = connect(srv)
        try:
            assert c.submit_grid(4, 4, pinned=[0, 3]).id  # reached on the file's endpoint
        finally:
            c.close()
    assert any(f"listening on ['{mine}']" in r.getMessage() for r in caplog.records), caplog.text


@pytest.mark.opencl
@pytest.mark.zenoh
def test_a_client_mode_server_says_it_listens_on_nothing(caplog):
    router = endpoint()
    peer = zenoh.open(zenoh_config("peer", listen=[router]))
    caplog.set_level(logging.INFO, logger="drape.server.service.server")
    try:
        cfg = make_config(listen=[P.DEFAULT_ENDPOINT], server_id="endpoints-client", mode="client", connect=[router])
        with Server(cfg) as srv:
            assert srv.listening == []
    finally:
        peer.close()
    ups = [r.getMessage() for r in caplog.records if " up: " in r.getMessage()]
    assert ups and "listening on nothing (client mode)" in ups[0] and P.DEFAULT_ENDPOINT not in ups[0], ups
