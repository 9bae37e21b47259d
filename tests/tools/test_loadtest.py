"""A short load test as CI runs it: a real ``drape serve`` process, client processes moving pins
every tick over Zenoh on loopback. Nothing may be lost, duplicated or reordered, and every tick
must be published (no frame coalesced). Deadlines may slip on a busy CI box; tick numbers do
not, so that is reported, not asserted."""
from __future__ import annotations

import json

from drape.server.tools import loadtest as lt


def test_short_load_loses_nothing_and_publishes_every_tick(tmp_path):
    spec = lt.LoadSpec(clients=2, cloths=3, size=12, seconds=3.0, iterations=4)
    server = lt.ServerProcess(spec.tick_rate, "workgroup", None, [])
    try:
        stats = lt.StatsWatch(server.endpoint, server.server_id)
        try:
            report, results, window = lt.run_load(spec, server.endpoint, server.server_id, server, stats)
        finally:
            stats.close()
    finally:
        server.stop()
    assert server.proc.returncode == 0, "drape serve did not stop cleanly"
    print(json.dumps(lt.asdict(report), indent=1))
    assert len(results) == 2 and all(r.cloths == 3 for r in results)
    assert report.ticks > 0.5 * spec.seconds * spec.tick_rate
    assert report.lost == 0 and report.duplicated == 0 and report.out_of_order == 0
    assert report.skipped_frames == 0, "every tick is published"
    assert report.send_errors == 0
    # every cloth saw a contiguous run of ticks covering most of the window
    for r in results:
        assert r.received >= r.cloths * 0.5 * spec.seconds * spec.tick_rate
    assert report.latency_ms["p50"] > 0 and report.latency_ms["max"] < 5000
    assert {"solve", "publish", "tick"} <= set(report.server["phases_ms"])
    paths = lt.write_plots(tmp_path, report, results, window, "ci")
    assert all(p.stat().st_size > 1000 for p in paths)
