"""Log output: JSON lines with stable keys (in-process through the handler, and from a real
``drape serve`` process), cloth/client context, text lines, and where the settings come from."""

from __future__ import annotations

import argparse
import io
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from conftest import WAIT, free_port  # shared helpers

from drape.client import DrapeClient
from drape.server import cli
from drape.server.service.config import add_arguments
from drape.server.service.process import logs

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

TIMEOUT = 20.0
STABLE = ("time", "level", "logger", "message")


@pytest.fixture
def capture():
    """A logger writing through a drape handler into a string."""
    out = io.StringIO()
    logger = logging.getLogger(f"drape.test.logs.{id(out)}")
    logger.propagate = False
    logger.setLevel(logging.DEBUG)

    def use(fmt: str, server_id: str | None = None) -> logging.Logger:
        for h in list(logger.handlers):
            logger.removeHandler(h)
        logger.addHandler(logs.make_handler(fmt, out, server_id))
        return logger

    yield use, out


def lines(out: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in out.getvalue().splitlines()]


def test_json_lines_with_context(capture):
    use, out = capture
    log = use("json", server_id="eu-1")
    log.info("plain %d", 1)
    log.warning("cloth %s reset", "c1", extra=logs.log_context(cloth="c1", client="k1"))
    with logs.context(client="k2"):
        log.info("in context\nwith a newline")
        with logs.context(cloth="c9", server_id="other"):
            log.debug("nested")
    try:
        raise ValueError("boom")
    except ValueError:
        log.exception("failed")
    got = lines(out)
    assert len(got) == 5 and len(out.getvalue().splitlines()) == 5  # one object per line
    for rec in got:
        assert all(k in rec for k in STABLE) and rec["logger"] == log.name
        assert rec["time"].endswith("Z") and time.strptime(rec["time"][:19], "%Y-%m-%dT%H:%M:%S")
    assert got[0] == {
        **{k: got[0][k] for k in ("time", "logger")},
        "level": "info",
        "message": "plain 1",
        "server_id": "eu-1",
    }
    assert (got[1]["level"], got[1]["cloth"], got[1]["client"]) == ("warning", "c1", "k1")
    assert got[2]["client"] == "k2" and "cloth" not in got[2] and got[2]["message"] == "in context\nwith a newline"
    assert (got[3]["cloth"], got[3]["client"], got[3]["server_id"], got[3]["level"]) == ("c9", "k2", "other", "debug")
    assert "cloth" not in got[4] and "ValueError: boom" in got[4]["exception"]
    with pytest.raises(ValueError, match="unknown log context"):
        logs.log_context(tick=3)


def test_text_lines_name_cloth_and_client(capture):
    use, out = capture
    log = use("text")
    log.info("added", extra=logs.log_context(cloth="c1", client="k1"))
    log.info("nothing")
    first, second = out.getvalue().splitlines()
    assert first.endswith("INFO " + log.name + ": added [cloth=c1 client=k1]")
    assert second.endswith(": nothing")
    with pytest.raises(ValueError, match="log format"):
        logs.make_handler("xml")


def test_setup_replaces_its_own_handler_only():
    root = logging.getLogger()
    level = root.level
    other = logging.NullHandler()
    root.addHandler(other)
    try:
        a = logs.setup("text", "warning", zenoh_level=None)
        b = logs.setup("json", "debug", server_id="s", zenoh_level=None)
        assert a not in root.handlers and b in root.handlers and other in root.handlers
        assert root.level == logging.DEBUG
        with pytest.raises(ValueError, match="unknown log level"):
            logs.setup("json", "loud", zenoh_level=None)
    finally:
        for h in list(root.handlers):
            if h.get_name() == "drape" or h is other:
                root.removeHandler(h)
        root.setLevel(level)


def test_settings_precedence(tmp_path, monkeypatch):
    """serve's own flag > the flag before the subcommand > TOML/env > text, info."""
    monkeypatch.delenv("DRAPE_LOG_FORMAT", raising=False)
    monkeypatch.delenv("DRAPE_LOG_LEVEL", raising=False)
    monkeypatch.delenv("DRAPE_CONFIG", raising=False)
    toml = tmp_path / "drape.toml"
    toml.write_text('log_format = "json"\nlog_level = "warning"\nserver_id = "from-toml"\n')

    def settings(pre: list[str], sub: list[str], serve: bool = True):
        p = argparse.ArgumentParser()
        p.add_argument("-v", "--verbose", action="count", default=0)
        p.add_argument("--log-format")
        p.add_argument("--log-level")
        s = argparse.ArgumentParser()
        if serve:
            add_arguments(s)
        return cli._log_settings(p.parse_args(pre), s.parse_args(sub))

    assert settings([], [], serve=False) == ("text", "info", None)
    assert settings(["-vv"], [], serve=False) == ("text", "debug", None)
    assert settings([], ["--config", str(toml)]) == ("json", "warning", "from-toml")
    assert settings(["--log-format", "text"], ["--config", str(toml)])[0] == "text"
    assert settings(["--log-format", "text"], ["--config", str(toml), "--log-format", "json", "--log-level", "debug"])[
        :2
    ] == ("json", "debug")
    monkeypatch.setenv("DRAPE_LOG_FORMAT", "json")
    assert settings([], [], serve=False)[0] == "json"
    assert settings([], ["--server-id", "x"]) == ("json", "info", "x")


def test_drape_serve_writes_json_lines(tmp_path):
    port = free_port()
    sid = f"logs-{port}"
    env = {**os.environ, "RUST_LOG": "error"}
    env.pop("DRAPE_CONFIG", None)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "drape.server.cli",
            "serve",
            "--log-format",
            "json",
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--server-id",
            sid,
            "--solver",
            "reference",
            "--no-multicast-scouting",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    raw: list[str] = []
    up = threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            raw.append(line)
            if '" up: ' in line or " up: " in line:
                up.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert up.wait(TIMEOUT), f"the server did not come up: {''.join(raw)}"
        with DrapeClient(f"tcp/127.0.0.1:{port}", server_id=sid, timeout=TIMEOUT) as client:
            with client.submit_grid(4, 4, pinned=[0, 3]) as h:
                h.next_state(WAIT)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(TIMEOUT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(TIMEOUT)
    records = [json.loads(line) for line in raw if line.strip()]  # every line is one JSON object
    assert records and all(all(k in r for k in STABLE) for r in records)
    assert all(r.get("server_id") == sid for r in records)
    by_message = {r["message"].split(":")[0]: r for r in records}
    assert by_message[f"drape server {sid} up"]["logger"].startswith("drape.server.service.")
    assert any("added for client" in r["message"] for r in records)
    assert any(r["message"].startswith(f"drape server {sid} stopped") for r in records)
