"""Operator endpoints of a real server (PoCL, Zenoh on loopback): the Prometheus exposition and
its counters, /healthz and /readyz, systemd's notify protocol over a real Unix datagram socket,
and the metrics_listen setting."""

from __future__ import annotations

import dataclasses
import os
import secrets
import socket
import threading
import time
import urllib.error
import urllib.request

import pytest
from conftest import WAIT, free_port, wait_until  # shared helpers
from conftest import make_config as shared_config
from prometheus_client.openmetrics.parser import text_string_to_metric_families as parse_openmetrics
from prometheus_client.parser import text_string_to_metric_families

from drape.client import DrapeClient, LimitExceeded
from drape.client import protocol as P
from drape.server.service import Server
from drape.server.service.config import ServerConfig, add_arguments, from_args
from drape.server.service.process import ops as OPS
from drape.server.service.process.metrics import METRICS, OPTIONAL, families, overload_refusals, thread_role
from drape.server.service.process.telemetry import PHASES, PhaseTimer

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

TIMEOUT = 10.0


def make_config(**kw) -> ServerConfig:
    """conftest's test server, one cloth per client, with the operator listener on a free port."""
    return shared_config(**{"max_cloths_per_client": 1, "metrics_listen": "127.0.0.1:0", **kw})


def get(url: str, accept: str | None = None) -> tuple[int, str]:
    req = urllib.request.Request(url, headers={"Accept": accept} if accept else {})
    try:
        with urllib.request.urlopen(req, timeout=TIMEOUT) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def scrape(ops: OPS.Ops) -> dict[str, object]:
    status, text = get(ops.url + "/metrics")
    assert status == 200
    return {m.name: m for m in text_string_to_metric_families(text)}


def value(fams: dict, name: str, **labels) -> float:
    """The value of one sample (``name`` as it appears in the exposition) with these labels."""
    family = name.removesuffix("_total").removesuffix("_bucket").removesuffix("_count").removesuffix("_sum")
    for s in fams[family].samples:
        if s.name == name and all(s.labels.get(k) == v for k, v in labels.items()):
            return s.value
    raise KeyError(f"{name}{labels} not in the exposition")


@pytest.fixture(scope="module")
def served():
    server = Server(make_config()).start()
    ops = OPS.start(server, env={})  # never notify a systemd the test run itself may be under
    yield server, ops
    ops.stop()
    server.stop()
    assert server.failure is None


@pytest.fixture
def client(served):
    server, _ = served
    c = DrapeClient(server.config.listen[0], server_id=server.server_id, timeout=TIMEOUT)
    yield c
    c.close()


class TickBlock:
    """Holds the tick thread inside ``server.call`` until released: the tick counter stops."""

    def __init__(self, server: Server) -> None:
        self.server = server
        self.entered = threading.Event()
        self.release = threading.Event()
        self.thread = threading.Thread(target=server.call, args=(self._hold, 60.0), daemon=True)

    def _hold(self, world) -> None:
        self.entered.set()
        self.release.wait(60.0)

    def __enter__(self) -> TickBlock:
        self.thread.start()
        assert self.entered.wait(WAIT), "the tick thread never ran the call"
        return self

    def __exit__(self, *exc) -> None:
        self.release.set()
        self.thread.join(TIMEOUT)


# ---------------------------------------------------------------------------------------------


def test_exposition_parses_and_carries_every_metric_with_its_type(served):
    server, ops = served
    fams = scrape(ops)
    optional = {name: key for key, (name, _) in OPTIONAL.items()}  # only when the server's stats carry them
    stats = server.stats()
    for name, kind, _ in METRICS:
        key = {"drape_server": "drape_server_info"}.get(name, name)
        if name in optional and optional[name] not in stats:
            assert key not in fams
            continue
        assert key in fams, f"{name} missing from /metrics"
        expected = "gauge" if kind == "info" else kind  # the text format has no info type
        assert fams[key].type == expected, (name, fams[key].type)
    assert all(n.startswith(("drape_", "process_")) for n in fams)
    info = fams["drape_server_info"].samples[0]
    assert info.labels["server"] == server.server_id and info.labels["solver"] == "workgroup"
    assert info.labels["device"] == server.device_name and info.labels["namespace"] == "drape"
    assert info.labels["version"] == P.VERSION_STRING
    # Kernel builds by thread: the warm-up's on the main thread, none on the tick; no build child here
    assert value(fams, "drape_kernel_builds_total", thread="main") > 0
    assert value(fams, "drape_kernel_builds_total", thread="tick") == 0
    assert value(fams, "drape_build_child_cloths_total", outcome="ran") == 0
    # Every phase is a histogram with cumulative buckets ending in +Inf == count.
    h = fams["drape_tick_phase_seconds"]
    assert {s.labels["phase"] for s in h.samples} == set(PHASES)
    for phase in PHASES:
        buckets = [s for s in h.samples if s.name.endswith("_bucket") and s.labels["phase"] == phase]
        counts = [s.value for s in buckets]
        assert counts == sorted(counts) and buckets[-1].labels["le"] == "+Inf"
        assert counts[-1] == value(fams, "drape_tick_phase_seconds_count", phase=phase)
    assert value(fams, "drape_tick_phase_seconds_count", phase="tick") > 0
    assert value(fams, "drape_tick_phase_seconds_sum", phase="tick") > 0
    # Every error code has its series, so rate() over a code never starts from nothing.
    assert {s.labels["code"] for s in fams["drape_errors"].samples} >= set(P.ERROR_CODES)
    assert {s.labels["preset"] for s in fams["drape_quality_cloths"].samples} >= set(P.QUALITY_PRESETS)


def test_openmetrics_when_asked(served):
    _, ops = served
    status, text = get(ops.url + "/metrics", accept="application/openmetrics-text; version=1.0.0")
    assert status == 200 and text.rstrip().endswith("# EOF")
    fams = {m.name: m for m in parse_openmetrics(text)}
    assert fams["drape_server"].type == "info"
    assert fams["drape_ticks"].type == "counter" and fams["drape_tick_phase_seconds"].type == "histogram"


def test_counters_follow_submit_control_refusal_and_remove(served, client):
    server, ops = served
    before = scrape(ops)
    with client.submit_grid(6, 5, pinned=[0, 5], quality="fast") as cape:
        cape.next_state(WAIT)  # subscribed and published at least once
        cape.move_pins([0, 5], [[0, 0, 0], [1, 0, 0]])
        with pytest.raises(LimitExceeded):  # max_cloths_per_client = 1
            client.submit_grid(4, 4)
        published = value(before, "drape_published_states_total")
        # The publisher counts a state after putting it, the client's token arrives on its own path.
        assert wait_until(lambda: server.stats()["published"] > published and server.stats()["alive_clients"] >= 1)
        during = scrape(ops)
        assert value(during, "drape_cloths") == 1 and value(during, "drape_vertices") == 30
        assert value(during, "drape_clients") == 1 and value(during, "drape_alive_clients") >= 1
        assert value(during, "drape_quality_cloths", preset="fast") == 1
        assert value(during, "drape_published_states_total") > published
    assert wait_until(lambda: server.stats()["cloths"] == 0)
    after = scrape(ops)

    def moved(name: str, **labels) -> float:
        return (
            value(after, name, **labels) - value(before, name, **labels)
            if _has(before, name, **labels)
            else value(after, name, **labels)
        )

    assert moved("drape_requests_total", kind="submit") == 2
    assert moved("drape_requests_total", kind="control") == 1
    assert moved("drape_requests_total", kind="remove") == 1
    assert moved("drape_errors_total", code="limit_exceeded") == 1
    assert moved("drape_errors_total", code="not_found") == 0
    assert value(after, "drape_cloths") == 0 and value(after, "drape_vertices") == 0
    assert value(after, "drape_quality_cloths", preset="fast") == 0
    assert value(after, "drape_ticks_total") > value(before, "drape_ticks_total")
    assert value(after, "drape_tick") >= value(after, "drape_ticks_total")


def _has(fams: dict, name: str, **labels) -> bool:
    try:
        value(fams, name, **labels)
        return True
    except KeyError:
        return False


def test_thread_roles_of_kernel_builds():
    assert [thread_role(n) for n in ("drape-tick-a-b-1", "drape-cook-s", "MainThread", "Thread-3")] == [
        "tick",
        "cook",
        "main",
        "other",
    ]


def test_overload_refusals_from_stats_or_error_code():
    assert overload_refusals({}) == 0
    assert overload_refusals({"errors": {"overloaded": 3, "busy": 1}}) == 3
    assert overload_refusals({"errors": {"overloaded": 3}, "overload_refusals": 5}) == 5
    timer = PhaseTimer()
    timer.add(0.003)
    fams = {
        m.name: m
        for m in families(
            {"server": "s", "errors": {"overloaded": 2}, "published_bytes": 1234, "links": 99},
            {"solver": "jacobi"},
            {"tick": timer},
        )
    }
    assert fams["drape_overload_refusals"].samples[0].value == 2
    assert fams["drape_published_bytes"].samples[0].value == 1234 and fams["drape_links"].samples[0].value == 99
    h = {(s.name, s.labels.get("le")): s.value for s in fams["drape_tick_phase_seconds"].samples}
    assert h[("drape_tick_phase_seconds_bucket", "0.002")] == 0 and h[("drape_tick_phase_seconds_bucket", "0.004")] == 1
    assert h[("drape_tick_phase_seconds_count", None)] == 1


def test_healthz_and_readyz_follow_the_tick_loop(served):
    server, ops = served
    assert get(ops.url + "/healthz") == (200, "ok\n")
    assert wait_until(lambda: get(ops.url + "/readyz")[0] == 200)
    assert get(ops.url + "/nothing")[0] == 404
    assert wait_until(lambda: value(scrape(ops), "drape_ready") == 1)
    with TickBlock(server):
        assert wait_until(lambda: get(ops.url + "/readyz")[0] == 503)
        status, reason = get(ops.url + "/readyz")
        assert status == 503 and "has not advanced" in reason, reason
        assert get(ops.url + "/healthz")[0] == 200  # stalled, but alive
        stalled = scrape(ops)  # a scrape never needs the tick thread
        assert value(stalled, "drape_ready") == 0
        assert value(stalled, "drape_tick_age_seconds") > ops.watch.stall_s
    assert wait_until(lambda: get(ops.url + "/readyz")[0] == 200)
    assert wait_until(lambda: value(scrape(ops), "drape_ready") == 1)


def test_systemd_ready_watchdog_only_while_ticking_and_stopping(served, tmp_path):
    server, _ = served
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(TIMEOUT)
        env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "100000", "WATCHDOG_PID": str(os.getpid())}
        ops = OPS.start(server, dataclasses.replace(server.config, metrics_listen=None), env=env)
        try:
            assert ops.url is None and ops.watchdog_s == pytest.approx(0.05)
            first = sock.recv(4096).decode().split("\n")
            assert first[0] == "READY=1" and f"MAINPID={os.getpid()}" in first
            assert sock.recv(4096) == b"WATCHDOG=1"
            with TickBlock(server):
                sock.settimeout(0.05)
                _drain(sock)
                n = ops.pings
                tick = server.tick
                for _ in range(10):  # ten watchdog intervals or more: at most the one in flight
                    _drain(sock)
                    time.sleep(0.05)
                assert server.tick == tick
                assert ops.pings <= n + 1, "WATCHDOG=1 sent while the tick counter stood still"
                n = ops.pings
            assert wait_until(lambda: ops.pings >= n + 2)  # ticking again: pinging again
            assert set(_drain(sock)) == {"WATCHDOG=1"}
        finally:
            ops.stop()
        msgs = _drain(sock, 0.5)
        assert msgs[-1] == "STOPPING=1"


def _drain(sock: socket.socket, timeout: float = 0.0) -> list[str]:
    out = []
    sock.settimeout(timeout or 0.001)
    try:
        while True:
            out.append(sock.recv(4096).decode())
    except (TimeoutError, BlockingIOError):
        return out


def test_sd_notify_abstract_namespace_and_no_socket():
    name = f"drape-test-{secrets.token_hex(6)}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.settimeout(TIMEOUT)
        assert OPS.sd_notify("READY=1", {"NOTIFY_SOCKET": "@" + name})
        assert sock.recv(64) == b"READY=1"
    assert not OPS.sd_notify("READY=1", {})
    assert OPS.watchdog_interval({"WATCHDOG_USEC": "3000000"}) == 1.5
    assert OPS.watchdog_interval({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "1"}) is None  # another process's
    assert OPS.watchdog_interval({}) is None


def test_stopped_server_is_not_ready_and_the_listener_closes():
    server = Server(make_config()).start()
    ops = OPS.start(server, env={})  # never notify a systemd the test run itself may be under
    try:
        assert wait_until(lambda: get(ops.url + "/readyz")[0] == 200)
        server.stop()
        status, reason = get(ops.url + "/readyz")
        assert status == 503 and "not up" in reason, reason
        assert get(ops.url + "/healthz")[0] == 200
        assert get(ops.url + "/metrics")[0] == 200  # the last counters stay readable
    finally:
        ops.stop()
        server.stop()
    with pytest.raises(urllib.error.URLError):
        urllib.request.urlopen(ops.url + "/healthz", timeout=2.0)


def test_metrics_listen_setting():
    import argparse

    assert ServerConfig().metrics_listen is None  # off unless asked for
    assert ServerConfig.load(env={"DRAPE_METRICS_LISTEN": "127.0.0.1:9464"}).metrics_listen == "127.0.0.1:9464"
    assert ServerConfig.load(env={"DRAPE_METRICS_LISTEN": ""}).metrics_listen is None
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--metrics-listen", "[::1]:9464", "--log-format", "json", "--log-level", "debug"])
    cfg = from_args(args, env={})
    assert (cfg.metrics_listen, cfg.log_format, cfg.log_level) == ("[::1]:9464", "json", "debug")
    for bad in ("9464", "localhost:http", "host:70000"):
        with pytest.raises(ValueError, match="metrics_listen"):
            ServerConfig(metrics_listen=bad).validate()
    with pytest.raises(ValueError, match="log_format"):
        ServerConfig.load(env={"DRAPE_LOG_FORMAT": "xml"})


def test_operations_files_name_only_metrics_that_exist():
    """The alert rules, the dashboard and docs/operations.md use exposed names, and the docs list
    every family."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    exposed = set()
    for name, kind, _ in METRICS:
        exposed |= {
            "counter": {name + "_total"},
            "histogram": {name + s for s in ("_bucket", "_sum", "_count")},
            "info": {name + "_info"},
        }.get(kind, {name})
    for rel in ("deploy/alerts.yml", "deploy/grafana-dashboard.json", "docs/operations.md"):
        used = set(re.findall(r"\bdrape_[a-z_]+\b", (root / rel).read_text()))
        assert used, rel
        unknown = used - exposed - {name for name, _, _ in METRICS}
        assert not unknown, f"{rel} names metrics that do not exist: {sorted(unknown)}"
    docs = (root / "docs/operations.md").read_text()
    for name, kind, _ in METRICS:
        shown = {"counter": name + "_total", "info": name + "_info"}.get(kind, name)
        assert f"`{shown}`" in docs, f"docs/operations.md does not list {shown}"
    alerts = (root / "deploy/alerts.yml").read_text()
    for metric in (
        "drape_missed_ticks_total",
        "drape_tick_phase_seconds_bucket",
        "drape_overload_refusals_total",
        "drape_nan_resets_total",
    ):
        assert metric in alerts
    assert "histogram_quantile(0.99" in alerts
    unit = (root / "deploy/drape.service").read_text()
    assert "Type=notify" in unit and "WatchdogSec=" in unit
    example = ServerConfig.load(root / "deploy/drape.toml", env={})
    assert example.metrics_listen == "127.0.0.1:9464"


def test_overload_refusals_counted_when_admission_refuses(served):
    """Admission with a cost model that predicts any second cloth over budget: the first submit
    (empty server) is admitted, another client's is refused with ``overloaded``."""
    server, ops = served
    admission = getattr(server, "admission", None)
    if admission is None:
        pytest.skip("this Server has no admission control yet")
    from drape.server.service.requests.admission_model import FixedCost

    before = scrape(ops)
    saved = admission.model
    admission.model = FixedCost(per_vertex_s=1.0)  # one vertex costs a whole second: nothing more fits
    try:
        with (
            DrapeClient(server.config.listen[0], server_id=server.server_id, timeout=TIMEOUT) as a,
            DrapeClient(server.config.listen[0], server_id=server.server_id, timeout=TIMEOUT) as b,
        ):
            with a.submit_grid(4, 4):
                with pytest.raises(P.DrapeError) as refused:
                    b.submit_grid(4, 4)
                assert refused.value.code == getattr(P, "ERR_OVERLOADED", "overloaded")
    finally:
        admission.model = saved
    after = scrape(ops)
    assert value(after, "drape_overload_refusals_total") == value(before, "drape_overload_refusals_total") + 1
    assert (
        value(after, "drape_errors_total", code="overloaded")
        == value(before, "drape_errors_total", code="overloaded") + 1
    )


def test_a_busy_metrics_port_is_a_clear_error(served):
    server, ops = served
    host, port = ops.address
    taken = dataclasses.replace(server.config, metrics_listen=f"{host}:{port}")
    with pytest.raises(OSError, match="cannot listen on metrics_listen"):
        OPS.start(server, taken, env={})


def test_drape_serve_notifies_systemd_and_serves_metrics(tmp_path):
    """The daemon end to end: READY=1, /readyz, /metrics, WATCHDOG=1, STOPPING=1, exit 0; with
    DRAPE_PROFILE its threads' sampled stacks written at the stop."""
    import signal
    import subprocess
    import sys

    port, mport = free_port(), free_port()
    path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(3 * TIMEOUT)
        profile = tmp_path / "prof"
        env = {
            **os.environ,
            "NOTIFY_SOCKET": path,
            "WATCHDOG_USEC": "1000000",
            "RUST_LOG": "error",
            "DRAPE_PROFILE": str(profile),
        }
        env.pop("WATCHDOG_PID", None)
        env.pop("DRAPE_CONFIG", None)
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "drape.server.cli",
                "serve",
                "--listen",
                f"tcp/127.0.0.1:{port}",
                "--server-id",
                f"notify-{port}",
                "--solver",
                "reference",
                "--metrics-listen",
                f"127.0.0.1:{mport}",
                "--no-multicast-scouting",
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            ready = sock.recv(4096).decode().split("\n")
            assert ready[0] == "READY=1", ready
            url = f"http://127.0.0.1:{mport}"
            assert wait_until(lambda: get(url + "/readyz")[0] == 200)
            fams = {m.name: m for m in text_string_to_metric_families(get(url + "/metrics")[1])}
            assert fams["drape_server_info"].samples[0].labels["server"] == f"notify-{port}"
            assert sock.recv(4096) == b"WATCHDOG=1"
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(TIMEOUT) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert "STOPPING=1" in _drain(sock, 1.0)
    summary = (tmp_path / "prof.txt").read_text()
    assert "== drape-tick:" in summary and "ticker.Ticker.run" in summary
    assert (tmp_path / "prof.folded").read_text().startswith("drape-")
