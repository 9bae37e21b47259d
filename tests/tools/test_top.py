"""``drape top``: one plain-text frame against real servers over Zenoh on loopback, rates from
two publications, and the answer when no server is there."""

from __future__ import annotations

import logging
import re
import sys
import time

import pytest
from conftest import WAIT, free_port, make_config  # shared helpers

from drape.client import DrapeClient
from drape.client import protocol as P
from drape.server.cli import main
from drape.server.service import Server
from drape.server.tools.top import COLUMNS, PRIORITY, StatsBoard, fit_columns, print_frame, render, row_cells

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

TIMEOUT = 10.0


@pytest.fixture(autouse=True)
def root_logging():
    """``main`` configures the root logger: give the next tests the one they had."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def frame_rows(text: str, prefix: str = "test-") -> dict[str, list[str]]:
    """Row cells by server id (cells are separated by two or more spaces)."""
    rows = {}
    for line in text.splitlines():
        cells = re.split(r"\s{2,}", line.strip())
        if cells and cells[0].startswith(prefix):
            rows[cells[0].split()[0]] = cells
    return rows


def test_once_renders_every_server_on_the_network(capsys):
    a = Server(make_config()).start()
    # A second server connected to the first: top, connected to the first only, sees both.
    b = Server(make_config(connect=a.config.listen)).start()
    try:
        with DrapeClient(a.config.listen[0], server_id=a.server_id, timeout=TIMEOUT) as client:
            cloths = [client.submit_grid(5, 4, pinned=[0, 4], quality="fast") for _ in range(2)]
            for c in cloths:
                c.next_state(WAIT)
            capsys.readouterr()
            assert main(["top", "--once", "--endpoint", a.config.listen[0], "--wait", str(TIMEOUT)]) == 0
            out = capsys.readouterr().out
            for c in cloths:
                c.remove()
    finally:
        b.stop()
        a.stop()
    head = out.splitlines()[0]
    assert head.startswith("drape top - ") and "2 server(s), 2 cloths, 1 clients, 40 vertices" in head
    header = next(line for line in out.splitlines() if line.strip().startswith("SERVER"))
    assert re.split(r"\s{2,}", header.strip()) == list(COLUMNS)
    rows = frame_rows(out)
    assert set(rows) == {a.server_id, b.server_id}
    ra = dict(zip(COLUMNS, rows[a.server_id], strict=True))
    assert (ra["CLOTHS"], ra["CLIENTS"], ra["VERTICES"], ra["QUALITY"]) == ("2", "1", "40", "fast:2")
    assert ra["TICK/s"].endswith("/60") and ra["OVERLOAD"] == "0"
    assert dict(zip(COLUMNS, rows[b.server_id], strict=True))["CLOTHS"] == "0"
    assert "\x1b[" not in out  # plain text: no terminal control codes


def test_once_one_server_only(capsys):
    a = Server(make_config()).start()
    try:
        assert (
            main(["top", "--once", "--endpoint", a.config.listen[0], "--server", a.server_id, "--wait", str(TIMEOUT)])
            == 0
        )
    finally:
        a.stop()
    out = capsys.readouterr().out
    assert set(frame_rows(out)) == {a.server_id} and "1 server(s), 0 cloths" in out


def test_once_without_servers_says_so(capsys):
    ep = f"tcp/127.0.0.1:{free_port()}"
    assert main(["top", "--once", "--endpoint", ep, "--wait", "0.5"]) == 1
    assert "no stats from any Drape server" in capsys.readouterr().err
    assert main(["top", "--once", "--server", "bad/id"]) == 2


def test_rates_from_two_publications(capsys):
    board = StatsBoard(P.Keys())
    base = {
        "server": "s1",
        "tick_rate": 60.0,
        "cloths": 3,
        "clients": 1,
        "vertices": 300,
        "uptime_s": 3725.0,
        "errors": {"overloaded": 4, "busy": 1},
        "quality": {"presets": {"balanced": 2, "fast": 1}, "degraded": 1},
        "phases": {"tick": {"mean_ms": 2.5, "max_ms": 9.0}, "solve": {"mean_ms": 1.25}},
    }
    board.add(
        "s1",
        {
            **base,
            "time_ns": 1_000_000_000,
            "ticks": 100,
            "published": 1000,
            "published_bytes": 10_000,
            "missed_ticks": 2,
        },
    )
    board.add(
        "s1",
        {
            **base,
            "time_ns": 3_000_000_000,
            "ticks": 220,
            "published": 1600,
            "published_bytes": 5_010_000,
            "missed_ticks": 6,
        },
    )
    print_frame(board.views(), "test", sys.stdout)
    row = dict(zip(COLUMNS, frame_rows(capsys.readouterr().out, "s1")["s1"], strict=True))
    assert row["TICK/s"] == "60.0/60" and row["STATES/s"] == "300" and row["BYTES/s"] == "2.5 MB"
    assert row["MISSED/s"] == "2.0" and row["TICK ms"] == "2.50" and row["MAX ms"] == "9.00"
    assert row["SOLVE"] == "1.25" and row["READBK"] == "-"
    assert row["QUALITY"] == "fast:1 balanced:2 (1 down)" and row["OVERLOAD"] == "4" and row["ERRORS"] == "5"
    assert row["UPTIME"] == "1:02:05"


@pytest.mark.parametrize("payload", [b"", b"\xc1garbage"])
def test_undecodable_stats_are_counted_not_shown(payload):
    import zenoh

    port = free_port()
    board = StatsBoard(P.Keys())
    cfg = zenoh.Config()
    cfg.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(cfg) as s:
        sub = s.declare_subscriber(P.Keys().stats("*"), board.on_sample)
        s.put(P.Keys().stats("x"), payload)
        deadline = time.monotonic() + WAIT
        while board.invalid == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        sub.undeclare()
    assert board.invalid == 1 and board.views() == []


def test_narrow_terminals_keep_the_important_columns_in_order():
    board = StatsBoard(P.Keys())
    board.add("a-long-server-name", {"server": "a-long-server-name", "time_ns": 1, "ticks": 1, "tick_rate": 60.0})
    rows = [row_cells(v, time.monotonic()) for v in board.views()]
    assert fit_columns(rows, None) == list(COLUMNS)
    assert fit_columns(rows, 10) == ["SERVER"]  # the server is always shown
    for width in (40, 80, 120):
        cols = fit_columns(rows, width)
        assert cols[:3] == ["SERVER", "TICK/s", "TICK ms"] and cols == [c for c in COLUMNS if c in cols]
        assert set(PRIORITY[:3]) <= set(cols)
    assert len(fit_columns(rows, 80)) < len(fit_columns(rows, 120)) < len(COLUMNS)
    from rich.console import Console

    console = Console(width=80, force_terminal=False, color_system=None, record=True)
    console.print(render(board.views(), "test", width=80))
    lines = console.export_text().splitlines()
    assert all(len(line.rstrip()) <= 80 for line in lines) and not any("…" in line for line in lines)
