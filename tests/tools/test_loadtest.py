"""``drape loadtest``: the window arithmetic on plain data (achieved rate from two stats maps,
per-cloth window counts, decode cost from arrival times), then a load as CI runs it: a real
``drape serve`` process and client processes moving pins every tick over Zenoh on loopback,
with one submit more than the server admits. Tick numbers and counters are asserted, never
durations: deadlines may slip on a busy CI box."""

from __future__ import annotations

import argparse
import json
import os

import numpy as np
import pytest
from PIL import Image

from drape.server.tools import loadtest as lt
from drape.server.tools.loadclient import decode_cost, window_counts
from drape.server.tools.loadreport import (
    achieved_rate,
    admission_capacity,
    markdown_table,
    missed_summary,
    timeline,
    write_summary_plot,
)
from drape.server.tools.procs import ServerProcess

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def test_achieved_rate_is_ticks_over_server_time_between_two_publications():
    s0 = {"ticks": 1000, "time_ns": 5_000_000_000, "tick": 1000}
    s1 = {"ticks": 1150, "time_ns": 7_500_000_000, "tick": 1150}
    assert achieved_rate(s0, s1) == pytest.approx(60.0)
    # a slow server: 32 ticks in 2 s
    assert achieved_rate(s0, {"ticks": 1032, "time_ns": 7_000_000_000}) == pytest.approx(16.0)


@pytest.mark.parametrize(
    "s0, s1, match",
    [
        ({}, {"ticks": 1, "time_ns": 1}, "first stats publication lacks ticks, time_ns"),
        ({"ticks": 1, "time_ns": 5}, {"ticks": 2}, "second stats publication lacks time_ns"),
        ({"ticks": 1, "time_ns": 5}, {"ticks": 2, "time_ns": 5}, "not later"),
        ({"ticks": 9, "time_ns": 5}, {"ticks": 2, "time_ns": 6}, "backwards"),
    ],
)
def test_achieved_rate_refuses_what_cannot_be_a_window(s0, s1, match):
    with pytest.raises(ValueError, match=match):
        achieved_rate(s0, s1)


def test_timeline_tells_each_stats_period_of_a_window():
    s0 = {"ticks": 100, "missed_ticks": 5, "skipped_frames": 1, "time_ns": 10_000_000_000}
    window = [
        {"ticks": 130, "missed_ticks": 5, "skipped_frames": 1, "time_ns": 10_500_000_000},
        {"ticks": 150, "missed_ticks": 15, "skipped_frames": 2, "time_ns": 11_000_000_000},
        {"ticks": 180, "missed_ticks": 15, "skipped_frames": 2, "time_ns": 11_500_000_000},
    ]
    periods = timeline(s0, window)
    assert periods == [[0.5, 30, 0, 0], [1.0, 20, 10, 1], [1.5, 30, 0, 0]]
    assert (
        missed_summary(periods)
        == "missed ticks in 1 of 3 stats periods (at most 10 in one, ending 1.0 s into the window)"
    )
    assert missed_summary(periods[:1]) == "no period with a missed tick"


def test_admission_capacity_replays_a_load_tests_figures():
    """Reports whose device takes 2 ms + 0.1 ms a cloth (the slowest stage): with a budget of
    10 ms the model admits 66 cloths once it has measured two loads (the fitted line would allow
    80, but no stage is predicted below the proportional line through the larger load: 6 ms at
    40 cloths is 10 ms at 66.7); with one load (through the origin: 4 ms at 20 cloths) it admits 50."""

    def report(cloths: int) -> dict:
        phases = {"tick": 1.0, "readback": 0.5, "solve": 2.0 + 0.1 * cloths, "encode": 0.1, "publish": 0.4}
        return {
            "cloths": cloths,
            "vertices_per_cloth": 64,
            "server": {"phases_ms": {k: {"mean": v} for k, v in phases.items()}},
        }

    reports = [report(20), report(40)]
    assert admission_capacity(reports, [20, 40], 0.010) == 66
    assert admission_capacity(reports, [20], 0.010) == 50
    with pytest.raises(ValueError, match="no report"):
        admission_capacity(reports, [30], 0.010)


def test_bytes_are_what_the_servers_put_when_they_report_it():
    """MB/s: the servers' published_bytes over the window (a predictive state's real size);
    the clients' received states x state size only when a server does not report it."""
    from types import SimpleNamespace

    from drape.server.tools.loadreport import server_window
    from drape.server.tools.loadrun import bytes_put

    s0 = {"ticks": 0, "time_ns": 0, "published_bytes": 1000}
    s1 = {"ticks": 60, "time_ns": 1_000_000_000, "published_bytes": 5000}
    a, b = server_window("a", s0, s1, []), server_window("b", s0, {**s1, "published_bytes": 2000}, [])
    clients = [SimpleNamespace(bytes=123_456)]
    assert bytes_put([a, b], clients) == 4000 + 1000  # type: ignore[arg-type]
    old = server_window("c", {"ticks": 0, "time_ns": 0}, {"ticks": 60, "time_ns": 10**9}, [])
    assert old["published_bytes"] is None and bytes_put([a, old], clients) == 123_456  # type: ignore[arg-type]


def test_the_decimated_rate_counters_are_reported_over_the_window():
    """Report.rates: each server's window deltas of the stats' decimated-key counters (1.8),
    summed over servers, in words with a rate; a server whose stats lack them adds nothing."""
    from drape.client.protocol.stats import STAT_COUNTERS
    from drape.server.tools.loadreport import RATE_COUNTERS, rate_counts, rates_summary, server_window

    assert set(RATE_COUNTERS) <= set(STAT_COUNTERS)
    s0 = {"ticks": 0, "time_ns": 0, "rate_published": 100, "rate_unserved": 3}
    s1 = {"ticks": 120, "time_ns": 2_000_000_000, "rate_published": 700, "rate_unserved": 5}
    a = server_window("a", s0, s1, [])
    b = server_window("b", s0, {**s1, "rate_published": 300}, [])
    old = server_window("c", {"ticks": 0, "time_ns": 0}, {"ticks": 120, "time_ns": 2_000_000_000}, [])
    assert a["rates"] == {"rate_published": 600, "rate_unserved": 2} and old["rates"] == {}
    assert rate_counts([a, b, old]) == {"rate_published": 800, "rate_unserved": 4}
    assert rate_counts([old]) == {}
    assert (
        rates_summary(rate_counts([a, b]), 2.0)
        == "decimated rates (1.8): 800 states put on decimated keys (400/s), 4 of watched decimated keys not served"
    )


def test_window_counts_only_the_window_ticks():
    # ticks 10..20 are the window (lo=9, hi=20); 5..9 are warm-up, 21.. after it
    ticks = np.array([5, 6, 9, 10, 11, 13, 12, 12, 14, 15, 16, 17, 18, 19, 20, 21, 22])
    received, lost, dup, ooo = window_counts(ticks, 9, 20)
    assert (received, lost, dup, ooo) == (12, 0, 1, 1)
    received, lost, dup, ooo = window_counts(np.array([10, 12, 20]), 9, 20)
    assert (received, lost, dup, ooo) == (3, 8, 0, 0)


def test_decode_cost_groups_states_by_payload():
    # two bundles of three states (arrival 100 and 200 ns) and one single state (300 ns)
    rx = np.array([100, 100, 100, 200, 200, 200, 300])
    delay = np.array([1000, 2000, 3000, 500, 900, 4000, 600])
    per_state_us, per_payload_us, total_s, payloads = decode_cost(rx, delay)
    assert payloads == 3
    assert total_s == pytest.approx((3000 + 4000 + 600) / 1e9)
    assert per_payload_us == pytest.approx(7600 / 3 / 1e3)
    assert per_state_us == pytest.approx(7600 / 7 / 1e3)
    assert np.isnan(decode_cost(np.zeros(0, np.int64), np.zeros(0, np.int64))[0])


def test_clients_share_an_offered_load():
    specs = lt.LoadSpec(clients=3, cloths=10, offered=2.0).client_specs()
    assert [c.offered for c in specs] == [7, 7, 6]
    assert [c.index for c in specs] == [0, 1, 2]
    assert lt.parse_loads("128, 4096:quant16", "float32") == [(128, "float32"), (4096, "quant16")]
    with pytest.raises(Exception, match="positive number"):
        lt.parse_loads("12x", "float32")


def test_clients_decode_a_sample_of_big_predictive_loads():
    """--decode-sample: as set, else (0, auto) one cloth in SAMPLED_DECODE for predictive loads over
    AUTO_SAMPLE_ABOVE cloths with bundles, every cloth otherwise; each client gets it."""
    from drape.server.tools.loadclient import AUTO_SAMPLE_ABOVE, SAMPLED_DECODE

    big = AUTO_SAMPLE_ABOVE + 1
    assert lt.LoadSpec(cloths=big, encoding="predictive").decode_one_in(big) == SAMPLED_DECODE
    assert lt.LoadSpec(cloths=big, encoding="quant16").decode_one_in(big) == 1
    assert lt.LoadSpec(cloths=big, encoding="predictive", bundle=False).decode_one_in(big) == 1
    assert lt.LoadSpec(encoding="predictive").decode_one_in(AUTO_SAMPLE_ABOVE) == 1
    assert lt.LoadSpec(decode_sample=4).decode_one_in(8) == 4
    specs = lt.LoadSpec(clients=2, cloths=big, encoding="predictive").client_specs()
    assert [c.decode_sample for c in specs] == [SAMPLED_DECODE] * 2


def test_a_sampled_load_counts_every_state(load_on_server):
    """Clients that decode one cloth in 2 (predictive states in bundles) count the others' states
    from their headers: every state of the window is received or counted lost, as when all decode."""
    spec = lt.LoadSpec(clients=1, cloths=4, size=8, seconds=1.5, iterations=2, encoding="predictive", decode_sample=2)
    args = ["--tick-rate", "30", "--stats-period", "0.5", "--no-admission", "--solver", "workgroup"]
    report, results, _ = load_on_server(spec, args, "lt-sample")
    assert report.cloths == 4 and report.decode_us["one_in"] == 2
    assert results[0].extra["decoded_cloths"] == 2 and results[0].extra["decode_sample"] == 2
    assert report.expected_states == 4 * report.ticks > 0
    assert report.states == report.expected_states - report.lost and report.lost % 4 == 0
    assert report.duplicated == 0 and report.out_of_order == 0
    per_cloth = results[0].extra["per_cloth_states"]
    assert len(per_cloth) == 4 and len(set(per_cloth)) == 1  # decoded and counted cloths alike


def test_short_load_measures_only_its_window(tmp_path, load_on_server):
    """2 clients offer 3 cloths each to a server admitting 5: one submit is refused (counted by
    its code); the 5 admitted cloths receive every tick of the window."""
    spec = lt.LoadSpec(clients=2, cloths=6, size=12, seconds=2.0, iterations=4)
    args = ["--tick-rate", "60", "--stats-period", "0.5", "--max-cloths", "5", "--no-admission"]
    report, results, window = load_on_server(spec, [*args, "--solver", "workgroup"], "lt-ci")
    print(json.dumps(report.to_dict(), indent=1))
    assert report.offered == 6 and report.cloths == 5
    assert report.refused == {"limit_exceeded": 1}
    # a refused submit means the load was not held (whether the admitted ones were served depends
    # on the CI box's load: missed ticks and p99 are reported, not asserted)
    assert not report.held and report.why_not_held().startswith("1 submits refused (limit_exceeded)")
    # the window is whole server ticks between two publications, after start-up
    lo, hi = report.window_ticks
    assert lo > 0 and hi > lo and report.ticks == hi - lo
    assert report.tick_hz_achieved > 0
    assert report.tick_hz_achieved == pytest.approx(report.ticks / report.seconds, rel=0.01)
    assert report.expected_states == 5 * report.ticks
    # every state of every published frame arrives; a frame the server coalesced (a busy CI box)
    # is missing for every cloth, and only those are counted lost. (The counter counts a
    # coalesced frame at the next tick: one at either edge of the window may fall outside it.)
    assert report.lost % 5 == 0 and abs(report.lost - 5 * report.skipped_frames) <= 5
    assert report.states == report.expected_states - report.lost
    assert report.duplicated == 0 and report.out_of_order == 0
    assert report.send_errors == 0
    assert np.isfinite(report.latency_ms["p99"]) and report.latency_ms["p50"] > 0
    assert report.decode_us["per_state"] > 0 and report.decode_us["per_payload"] >= report.decode_us["per_state"]
    assert {"solve", "publish", "tick"} <= set(report.server["phases_ms"])
    assert report.server["rss_max_mb"] >= report.server["rss_start_mb"] > 0
    assert report.server["rss_max_mb"] >= report.server["rss_window_start_mb"] > 0
    # the window's stats periods add up to the window's counters; the host's load is stated
    assert [sum(p[k] for p in report.timeline) for k in (1, 2, 3)] == [
        report.ticks,
        report.missed_ticks,
        report.skipped_frames,
    ]
    assert report.timeline[-1][0] == pytest.approx(report.seconds, abs=1e-3) and len(report.load_average) == 2
    assert sum(r.admitted for r in results) == 5
    paths = lt.write_plots(tmp_path, report, results, window, "ci")
    paths.append(write_summary_plot(tmp_path / "summary.png", [report, report]))
    for p in paths:
        with Image.open(p) as im:
            assert im.format == "PNG" and im.size == ((800, 700) if p.name == "summary.png" else (800, 500))
            assert np.asarray(im.convert("L")).std() > 5, f"{p.name} is blank"
    table = markdown_table([report])
    assert table.count("\n") == 3 and "| 5 | 6 | 1 | float32 |" in table and table.endswith(" | **no** |\n")


def test_two_servers_share_a_load_placed_by_their_published_load():
    """``--servers 2``: two drape serve processes, 4 clients starting together and placing one
    after another, each its 2 cloths on the server the SDK ranks first by the servers' stats
    (counting the cloths of the clients before it): 4 cloths each
    (spread 0), each server's window counted in its own ticks, every client's states counted in
    its server's ticks."""
    spec = lt.LoadSpec(clients=4, cloths=8, size=8, seconds=2.0, iterations=2)
    fleet = lt.Fleet(2, ["--tick-rate", "60", "--stats-period", "0.5", "--no-admission"])
    try:
        report, results, _ = lt.run_fleet_load(spec, fleet.endpoint, fleet.targets, quiet=True)
    finally:
        fleet.stop()
    print(json.dumps(report.to_dict(), indent=1))
    assert report.cloths == report.offered == 8
    assert [s["server"] for s in report.servers] == [t.server_id for t in fleet.targets]
    assert [s["cloths"] for s in report.servers] == [4, 4] and report.spread == 0.0
    assert all(s["ticks"] > 0 and s["hz"] > 0 for s in report.servers)
    assert report.ticks == min(s["ticks"] for s in report.servers)
    assert report.missed_ticks == sum(s["missed_ticks"] for s in report.servers)
    assert report.states == report.expected_states - report.lost and report.duplicated == 0
    assert sum(r.admitted for r in results) == 8


def test_endpoint_with_several_server_ids_measures_running_workers(tmp_path):
    """``--endpoint E --server-id W-0,W-1`` against one running ``drape serve --workers 2``: the
    clients place by load over both workers, and the report has each worker's window."""
    from drape.server.tools.procs import free_port

    parser = argparse.ArgumentParser()
    lt.configure(parser)
    out = tmp_path / "w.json"
    with ServerProcess(["--workers", "2", "--no-admission", "--stats-period", "0.5"], port=free_port(2)) as sup:
        ids = f"{sup.server_id}-0,{sup.server_id}-1"
        args = parser.parse_args(
            f"--endpoint {sup.endpoint} --server-id {ids} --clients 2 --cloths 2 --size 8 --iterations 2 "
            f"--seconds 1 --quiet --out {tmp_path} --json {out}".split()
        )
        # 0 held or 1 not held (a frame coalesced on a loaded machine): both are a measured run;
        # 2 (bad arguments) and 3 (the run failed) are not
        assert lt.run(args) in (0, 1)
    (report,) = json.loads(out.read_text())
    assert [s["server"] for s in report["servers"]] == ids.split(",")
    assert [s["cloths"] for s in report["servers"]] == [2, 2] and report["cloths"] == report["offered"] == 4
    assert all(s["ticks"] > 0 for s in report["servers"])


def test_scale_out_searches_one_server_then_two(tmp_path, capsys):
    """``--scale-out``: the knee search on one server, then on two from there, and the ratio
    printed; the JSON holds both knees and every load's report (the two-server ones per server).
    Loads of 2 and 4 tiny cloths (``--max-cloths 4``): the structure is asserted, not the knees."""
    parser = argparse.ArgumentParser()
    lt.configure(parser)
    out = tmp_path / "so.json"
    args = parser.parse_args(
        "--scale-out --servers 2 --clients 2 --cloths 1 --size 8 --iterations 2 --seconds 1 "
        f"--max-cloths 4 --bisect 0 --quiet --no-admission --out {tmp_path} --json {out}".split()
    )
    assert lt.run(args) == 0
    doc = json.loads(out.read_text())
    assert set(doc["knees"]) == {"1", "2"}
    one = [r for r in doc["reports"] if not r["servers"]]
    two = [r for r in doc["reports"] if r["servers"]]
    assert one and two and one[0]["cloths"] == 2
    assert all(len(r["servers"]) == 2 and sum(s["cloths"] for s in r["servers"]) == r["cloths"] for r in two)
    assert "scale-out: " in capsys.readouterr().out


def test_knee_search_goes_down_when_the_first_load_is_not_held():
    """The knee search's arithmetic, with a server that holds up to 100 cloths: from 128 it halves
    (each failure run twice) until 64 holds, then bisects between 64 and 128; from 16 it doubles.
    ``run_one`` here stands for a whole load run: only its held / why_not_held are read."""
    from dataclasses import dataclass

    @dataclass
    class Outcome:
        cloths: int

        @property
        def held(self) -> bool:
            return self.cloths <= 100

        def why_not_held(self) -> str:
            return "over 100"

    runs: list[int] = []

    def run_one(spec):
        runs.append(spec.cloths)
        return Outcome(spec.cloths)

    base = lt.LoadSpec(clients=4, cloths=128)
    _, held = lt.knee_search(base, run_one, 8192, 2, None, 0.0)
    assert held == 96 and runs == [128, 128, 64, 96, 112, 112]
    runs.clear()
    _, held = lt.knee_search(lt.LoadSpec(clients=4, cloths=16), run_one, 8192, 0, None, 0.0)
    assert held == 64 and runs == [16, 32, 64, 128, 128]
    runs.clear()
    _, held = lt.knee_search(
        lt.LoadSpec(clients=4, cloths=256), lambda s: runs.append(s.cloths) or Outcome(999), 8192, 2, None, 0.0
    )
    assert held == 0 and runs == [256, 256, 128, 128, 64, 64, 32, 32, 16, 16, 8, 8, 4, 4]


def test_cpu_lists_parse_and_pin_a_server_and_its_threads():
    """``--server-cpus`` / ``--client-cpus`` lists as taskset writes them, and a server started on
    one CPU: the affinity is set before exec, so every thread it starts (Zenoh's, the tick
    thread, the publisher) has it."""
    import psutil

    from drape.server.tools.procs import format_cpus, parse_cpus

    assert (
        parse_cpus("0-3,16-19") == {0, 1, 2, 3, 16, 17, 18, 19}
        and format_cpus({0, 1, 2, 3, 16, 17, 18, 19}) == "0-3,16-19"
    )
    assert format_cpus(parse_cpus("5,0,2,3")) == "0,2-3,5"
    for bad in ("", "a", "3-1", "1,,2", "-1"):
        with pytest.raises(ValueError, match="CPU list"):
            parse_cpus(bad)
    cpu = min(os.sched_getaffinity(0))  # one this machine lets us use
    with ServerProcess(["--stats-period", "0.5"], cpus=frozenset({cpu})) as srv:
        from drape.client import DrapeClient

        with DrapeClient(srv.endpoint, server_id=srv.server_id, timeout=60.0) as client:
            assert client.info()["server"] == srv.server_id  # up: its threads are running
        proc = psutil.Process(srv.proc.pid)
        threads = [t.id for t in proc.threads()]
        assert len(threads) > 3
        assert all(os.sched_getaffinity(t) == {cpu} for t in threads)
