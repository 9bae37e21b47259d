"""``drape serve --workers N`` (drape.server.service.process.workers): a real supervisor process with two
real workers on loopback (PoCL's CPU OpenCL) serving one SDK client that places its cloths on
both; a ``kill -9`` of a worker is restarted under the same id and endpoint while the client's
failover keeps every cloth; SIGTERM stops all with status 0. The plan's refusals, and the
supervision rules with short-lived stand-in workers (plain processes, no Zenoh needed).
Counted events only."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

from drape.client import DrapeClient
from drape.server.service.config import ServerConfig
from drape.server.service.process.workerplan import plan, worker_command
from drape.server.service.process.workers import Supervisor
from drape.server.tools.procs import ServerProcess, free_port

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

SERVER_WAIT = 90.0  # two drape serve starting (OpenCL warm-up) on a loaded CI machine
EVENT_WAIT = 30.0
CLOTHS = 8
SERVE = (sys.executable, "-m", "drape.server.cli", "serve")
SERVE_ARGS = ("--device", "cpu", "--grace-period", "1", "--stats-period", "0.25", "--no-admission")


class Supervised:
    """``drape serve --workers 2`` (procs.ServerProcess: its own session, SIGTERM to stop), with
    systemd's variables pointing at our socket; its output (the workers' too) in a file."""

    def __init__(self, tmp_path: Path, monkeypatch, sid: str) -> None:
        port = free_port(2)
        self.ids = [f"{sid}-0", f"{sid}-1"]
        self.endpoints = [f"tcp/127.0.0.1:{port}", f"tcp/127.0.0.1:{port + 1}"]
        self.notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.notify.bind(str(tmp_path / "notify"))
        # READY=1 and watchdog pings (every WATCHDOG_USEC / 2) come to our socket
        monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
        monkeypatch.setenv("WATCHDOG_USEC", "2000000")
        self.log_path = tmp_path / "supervisor.log"
        self.log = open(self.log_path, "w")  # noqa: SIM115 (closed in stop)
        self.server = ServerProcess(["--workers", "2", *SERVE_ARGS], server_id=sid, port=port, output=self.log)

    def text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def worker_pid(self, sid: str) -> int | None:
        """The pid of worker ``sid`` now (a child of the supervisor with that server id)."""
        for child in psutil.Process(self.server.proc.pid).children():
            with contextlib.suppress(psutil.NoSuchProcess):
                cmd = child.cmdline()
                if child.status() != psutil.STATUS_ZOMBIE and cmd[cmd.index("--server-id") + 1] == sid:
                    return int(child.pid)
        return None

    def stop(self) -> int | None:
        rc = self.server.stop(grace=60.0)
        self.notify.close()
        self.log.close()
        return rc


@pytest.fixture
def supervised(tmp_path, monkeypatch):
    s = Supervised(tmp_path, monkeypatch, f"wk-{os.getpid()}")
    try:
        yield s
    finally:
        s.stop()


def test_two_workers_share_the_clients_survive_a_kill_and_stop_cleanly(supervised, svc):
    s = supervised
    # the supervisor says READY=1 (systemd's protocol) once both workers did
    s.notify.settimeout(SERVER_WAIT)
    assert "READY=1" in s.notify.recv(4096).decode().splitlines(), s.text()
    # and pings the watchdog while both workers' ticks advance (they ping it, it forwards)
    assert "WATCHDOG=1" in s.notify.recv(4096).decode().splitlines(), s.text()
    with DrapeClient(s.endpoints, timeout=SERVER_WAIT, failover=True) as client:
        ids = set(s.ids)
        assert svc.wait_until(lambda: set(client.live_servers()) == ids, SERVER_WAIT), s.text()
        assert svc.wait_until(lambda: all(client.placement.stats(i) for i in ids), SERVER_WAIT)
        handles = [client.submit_grid(6, 6, 0.5, 0.5, origin=(j, 1.0, 0.0), pinned=[0, 5]) for j in range(CLOTHS)]
        on = {i: [h for h in handles if h.server_id == i] for i in ids}
        assert all(on[i] for i in ids), {i: len(v) for i, v in on.items()}  # both workers serve some
        for h in handles:
            assert h.next_state(EVENT_WAIT) is not None
        # the workers count them too, in their stats
        assert svc.wait_until(
            lambda: all((client.placement.stats(i) or {}).get("cloths") == len(on[i]) for i in ids), EVENT_WAIT
        )

        # kill -9 of worker 0: the SDK fails its cloths over to worker 1, the supervisor restarts it
        victim, other = s.ids
        pid = s.worker_pid(victim)
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        assert svc.wait_until(lambda: all(h.server_id == other and not h.lost for h in handles), EVENT_WAIT)
        assert sorted(id(e.handle) for e in client.failover_events) == sorted(id(h) for h in on[victim])
        assert all(e.ok for e in client.failover_events)
        for h in handles:  # every cloth keeps getting states
            assert h.next_state(EVENT_WAIT) is not None
        assert svc.wait_until(lambda: f"worker {victim} ready (start 2)" in s.text(), SERVER_WAIT), s.text()
        assert f"worker {victim} exited with signal SIGKILL" in s.text()
        new_pid = s.worker_pid(victim)
        assert new_pid is not None and new_pid != pid
        # same id, same endpoint: its liveliness comes back and a new cloth lands on it (it is empty)
        assert svc.wait_until(lambda: victim in client.live_servers(), EVENT_WAIT)
        assert svc.wait_until(lambda: (client.placement.stats(victim) or {}).get("cloths") == 0, EVENT_WAIT)
        late = client.submit_grid(4, 4, pinned=[0])
        assert late.server_id == victim and late.next_state(EVENT_WAIT) is not None
        with DrapeClient(s.endpoints[0], server_id=victim, timeout=EVENT_WAIT) as direct:  # its own endpoint
            assert direct.submit_grid(4, 4, pinned=[0]).next_state(EVENT_WAIT) is not None
        # the workers' log lines carry their id
        assert f"[{other}] " in s.text() and f"[{victim}] " in s.text()
        workers = [new_pid, s.worker_pid(other)]

    assert s.stop() == 0, s.text()
    for p in workers:
        assert p is not None and not psutil.pid_exists(p)
    assert f"worker {victim} stopped" in s.text() and f"worker {other} stopped" in s.text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--workers", "0"), "workers must be in 1..64"),
        (("--workers", "65"), "workers must be in 1..64"),
        (("--workers", "2", "--listen", "tcp/127.0.0.1:65535"), "port 65536"),
        (("--workers", "2", "--listen", "tcp/127.0.0.1:0"), "has port 0"),
        (
            (
                "--workers",
                "3",
                "--listen",
                "tcp/127.0.0.1:7447",
                "--listen",
                "udp/127.0.0.1:7447",
                "--metrics-listen",
                "127.0.0.1:7448",
            ),
            "tcp port 7448 would be used by workers 0 and 1",
        ),
        (("--workers", "2", "--mode", "client"), "connect must name the router"),
        (("--workers", "2", "--server-id", "x" * 63), "invalid server_id"),
    ],
)
def test_bad_worker_settings_are_refused_with_status_2(args, message):
    r = subprocess.run([*SERVE, *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert "started (pid" not in r.stderr  # refused before any worker started


def test_drape_workers_environment_variable_is_a_setting():
    env = {**os.environ, "DRAPE_WORKERS": "0"}
    r = subprocess.run([*SERVE], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2 and "workers must be in 1..64" in r.stderr
    c = ServerConfig.load(env={"DRAPE_WORKERS": "3"}, overrides={"server_id": "a", "device": "gpu:0,gpu:1"})
    specs = plan(c)
    assert [s.server_id for s in specs] == ["a-0", "a-1", "a-2"]
    assert [s.device for s in specs] == ["gpu:0", "gpu:1", "gpu:0"]  # k mod len
    cmd = worker_command(c, specs[1])
    assert cmd[cmd.index("--workers") + 1] == "1" and cmd[cmd.index("--server-id") + 1] == "a-1"


# ---------------------------------------------------------------------------------------------
# Supervision rules, with stand-in workers (plain Python processes)


def _supervisor(commands: list[list[str]], **kw) -> Supervisor:
    config = ServerConfig(workers=len(commands), server_id="sv", listen=[f"tcp/127.0.0.1:{free_port(2)}"])
    return Supervisor(config.validate(), plan(config), commands=commands, **kw)


def test_a_crashing_worker_is_restarted_then_given_up_on():
    crash = [sys.executable, "-c", "import sys; sys.exit(3)"]
    sup = _supervisor([crash, crash], backoff_s=0.01, max_restarts=3, restart_window_s=600.0)
    assert sup.run() == 1
    assert sup.gave_up is not None and "status 3" in sup.gave_up
    # 3 restarts scheduled, the 4th death within the window ended it (a scheduled restart may
    # not have started yet then)
    assert len(sup.restarts) == 3 and 2 + 2 <= sum(w.starts for w in sup.workers) <= 2 + 3
    assert all(w.proc is None for w in sup.workers)


def test_status_2_is_not_restarted_and_the_others_are_stopped():
    bad = [sys.executable, "-c", "import sys; sys.exit(2)"]
    sleeper = [sys.executable, "-c", "import time; time.sleep(600)"]
    sup = _supervisor([bad, sleeper], backoff_s=0.01)
    assert sup.run() == 1
    assert sup.gave_up is not None and "status 2" in sup.gave_up
    assert [w.starts for w in sup.workers] == [1, 1]
    assert all(w.proc is None for w in sup.workers)  # the sleeper was stopped, not waited for
