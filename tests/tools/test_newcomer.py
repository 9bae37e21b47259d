"""What a newcomer meets (issue 20): ``drape demo`` and ``drape loadtest`` say at once that their
server exited (its exit status and last log lines) instead of timing out and blaming a client;
``drape loadtest``'s exit status tells a script whether the load was held; ``drape top``'s live
view quits on ``q``, its terminal restored. Real processes, real Zenoh and PoCL; the servers that
fail do so on a real error (an OpenCL device that does not exist, a SIGKILL). Exit statuses and
messages are asserted; durations only against what the same failure takes alone on the same machine
at the same moment, with generous slack, far below the old timeouts."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import termios
import threading
import time
from types import SimpleNamespace

import pytest

from drape.server.tools import loadtest as lt
from drape.server.tools import top
from drape.server.tools.procs import ServerExited, ServerProcess, free_port

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

#: A run that fails must fail well before the waits it used to sit out (30-67 s in issue 20): within
#: this many times what a failing server alone takes on the same machine at the same moment (the
#: load test is two interpreters: its own and its server's), plus SLACK_S for the clients' starts.
FAIL_FACTOR = 3.0
SLACK_S = 15.0


def drape(*args: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drape.server.cli", *args], capture_output=True, text=True, timeout=timeout
    )


def test_demo_says_its_server_exited_with_its_last_log_lines(tmp_path):
    r = drape("demo", "--device", "no-such-device", "--port", str(free_port()), "--out", str(tmp_path), timeout=120)
    assert r.returncode == 1, r.stderr
    assert "drape demo: server demo exited with code 1 before the demo clients' cloths were accepted" in r.stderr
    tail = r.stderr.split("its last", 1)[1]
    assert "no OpenCL device matches 'no-such-device'" in tail  # the server's own words, in the message
    assert "failed before its cloth was accepted" not in r.stderr and "Traceback" not in r.stderr


def test_loadtest_says_its_server_exited_with_its_last_log_lines(tmp_path):
    # what a failing server alone takes here now: the bound scales with the machine's load
    t0 = time.monotonic()
    alone = drape("serve", "--device", "no-such-device", "--listen", f"tcp/127.0.0.1:{free_port()}", timeout=120)
    assert alone.returncode == 1 and "no OpenCL device matches 'no-such-device'" in alone.stderr, alone.stderr
    alone_s = time.monotonic() - t0
    t0 = time.monotonic()
    r = drape(
        *("loadtest", "--device", "no-such-device", "--clients", "2", "--cloths", "1", "--size", "8"),
        *("--seconds", "1", "--quiet", "--out", str(tmp_path)),
        timeout=120,
    )
    assert r.returncode == 3, r.stderr
    assert "drape loadtest: server loadtest-" in r.stderr
    # the first wait it fails in: the clients connecting (they submit once all are), or their submits
    assert re.search(r"exited with code 1 before the clients( connected|' submits were answered)", r.stderr)
    assert "no OpenCL device matches 'no-such-device'" in r.stderr.split("its last", 1)[1]
    assert "no stats publication" not in r.stderr and "Traceback" not in r.stderr
    took = time.monotonic() - t0
    assert took < FAIL_FACTOR * alone_s + SLACK_S, (took, alone_s)  # not a wait sat out: noticed as it exited


def test_a_server_killed_while_waited_on_is_reported_with_its_signal():
    """A server that was up and is then killed: ``check`` raises with the (negative) status and
    the lines it logged before it died."""
    srv = ServerProcess(["--stats-period", "0.5"], server_id=f"nc-{os.getpid()}")
    try:
        t_end = time.monotonic() + 90
        while not any(" up: " in line for line in srv.last_lines(50)):
            assert srv.alive(), srv.last_lines(50)
            assert time.monotonic() < t_end, "the server did not come up"
            time.sleep(0.1)
        srv.check("anything")  # alive: nothing happens
        os.killpg(srv.proc.pid, signal.SIGKILL)
        srv.proc.wait(30)
        with pytest.raises(ServerExited) as e:
            srv.check("the window closed")
    finally:
        srv.stop()
    text = str(e.value)
    assert text.startswith(f"server nc-{os.getpid()} exited with code -9 (SIGKILL) before the window closed; its last ")
    assert f"drape server nc-{os.getpid()} up: " in text


def test_loadtest_exit_status_is_1_when_a_load_is_not_held(tmp_path):
    """A server that takes one cloth, a load of two: one submit refused, ``held: NO``, status 1."""
    r = drape(
        *("loadtest", "--clients", "1", "--cloths", "2", "--size", "8", "--iterations", "2", "--seconds", "1"),
        *("--no-admission", "--server-arg=--max-cloths", "--server-arg=1", "--quiet", "--out", str(tmp_path)),
    )
    assert r.returncode == 1, r.stdout + r.stderr
    assert "held: NO (1 submits refused (limit_exceeded)" in r.stdout
    assert "exit status 1: not held: 1 cloths (1 submits refused (limit_exceeded)" in r.stdout


def test_loadtest_exit_status_rules():
    held, refused_but_served, unserved = (
        SimpleNamespace(held=True, served=True),
        SimpleNamespace(held=False, served=True),
        SimpleNamespace(held=False, served=False),
    )
    assert lt.exit_status([held, held], 1.0, search=False) == 0
    assert lt.exit_status([held, refused_but_served], 1.0, search=False) == 1
    assert lt.exit_status([], 1.0, search=False) == 1  # nothing measured is not a pass
    # offered past the knee, refusals are the point: what was admitted must be served
    assert lt.exit_status([refused_but_served], 2.0, search=False) == 0
    assert lt.exit_status([refused_but_served, unserved], 2.0, search=False) == 1
    # a knee search fails loads by design: it passes when some load held
    assert lt.exit_status([held, unserved, unserved], 1.0, search=True) == 0
    assert lt.exit_status([unserved, unserved], 1.0, search=True) == 1


def test_loadtest_help_documents_the_exit_statuses():
    r = drape("loadtest", "--help", timeout=60)
    assert r.returncode == 0
    for line in ("exit status:", "0  every load was held", "1  a load was not held", "2  bad arguments", "3  the run"):
        assert line in r.stdout


def test_loadtest_bad_arguments_exit_2():
    r = drape("loadtest", "--clients", "0", timeout=60)
    assert r.returncode == 2 and "drape loadtest: --clients must be 1..256" in r.stderr


# ------------------------------------------------------------------------------------------------
# drape top: q quits


def test_q_and_capital_q_quit_other_keys_do_not():
    assert top.quits("q") and top.quits("Q") and top.quits("xyq")
    assert not top.quits("") and not top.quits("x") and not top.quits("\x1b[A")


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    yield master, slave
    os.close(master)
    os.close(slave)


def test_key_reader_reads_keys_at_once_and_restores_the_terminal(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    assert before[3] & termios.ICANON  # a terminal starts line-buffered
    with top.KeyReader(slave) as keys:
        assert not termios.tcgetattr(slave)[3] & (termios.ICANON | termios.ECHO)  # cbreak: no line, no echo
        assert keys.wait(0.0) == ""  # nothing typed: no block, nothing read
        os.write(master, b"x")  # one key, no Enter
        typed = ""
        for _ in range(100):  # counted tries; each returns as soon as the key is there
            typed += keys.wait(0.1)
            if typed:
                break
        assert typed == "x" and not top.quits(typed)
        os.write(master, b"q")
        for _ in range(100):
            typed = keys.wait(0.1)
            if typed:
                break
        assert top.quits(typed)
    assert termios.tcgetattr(slave) == before


def test_key_reader_on_a_pipe_reads_nothing():
    r, w = os.pipe()
    try:
        os.write(w, b"q")
        with top.KeyReader(r) as keys:
            assert keys.wait(0.0) == ""  # not a terminal: keys are not read (stdin may be a script's)
    finally:
        os.close(r)
        os.close(w)


def test_live_view_quits_on_q_and_restores_the_terminal(pty_pair):
    master, slave = pty_pair
    before = termios.tcgetattr(slave)
    board = top.StatsBoard(top.P.Keys("drape"))
    board.add("nc-1", {"server": "nc-1", "tick": 1, "ticks": 1, "time_ns": 1, "tick_rate": 60.0})
    os.write(master, b"q")  # typed before the view starts: read at its first wait
    result: list[int] = []
    view = threading.Thread(target=lambda: result.append(top._live(board, "test", 0.05, keys_fd=slave)), daemon=True)
    view.start()
    view.join(60)  # a generous bound: the view that does not quit would run forever
    assert result == [0], "the live view did not quit on q"
    assert termios.tcgetattr(slave) == before
