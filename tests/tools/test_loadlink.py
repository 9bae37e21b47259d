"""``drape loadtest`` with a home link (issue 21, server/tools/loadlink.py): which clients are
shaped, the per-group summary on plain data, then a tiny load end to end with one of two clients
behind a shaper taking every 2nd state (protocol 1.8): its states, latency and gaps are reported
apart from the unshaped client's. Counts are asserted, never durations."""

from __future__ import annotations

import numpy as np
import pytest

from drape.server.tools import loadtest as lt
from drape.server.tools.loadclient import ClientResult
from drape.server.tools.loadlink import LinkSpec, group_summary, longest_gap_ms

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)


def _result(shaped: bool, states: list[int], gap: float) -> ClientResult:
    return ClientResult(
        index=0, offered=len(states), admitted=len(states), refused={}, received=sum(states), expected=0, lost=0,
        duplicated=0, out_of_order=0, latencies_ms=np.arange(1, 101, dtype=np.float32), decode_us_per_state=0.0,
        decode_us_per_payload=0.0, decode_s=0.0, payloads=0, bytes=0, send_errors=0, cpu_s=0.0,
        extra={"shaped": shaped, "per_cloth_states": states, "longest_gap_ms": gap, "rate_at_end": 2},
    )  # fmt: skip


def test_the_last_clients_are_shaped_and_summarised_apart():
    assert LinkSpec().shaped(4) == [False] * 4
    assert LinkSpec(rate_mbit=5, share=0.5).shaped(4) == [False, False, True, True]
    assert LinkSpec(delay_ms=10, share=0.01).shaped(3) == [False, False, True]  # one at least
    specs = lt.LoadSpec(clients=2, cloths=4, link=LinkSpec(rate_mbit=5, share=0.5, client_rate="2")).client_specs()
    assert [c.client_rate for c in specs] == ["1", "2"]
    g = group_summary([_result(True, [60, 30], 40.0), _result(True, [45], 70.0)], 2.0)
    assert g["clients"] == 2 and g["cloths"] == 3
    assert g["states_per_s_per_cloth_min"] == 15.0 and g["states_per_s_per_cloth_mean"] == 22.5
    assert g["longest_gap_ms"] == 70.0 and g["latency_ms"]["p50"] == pytest.approx(50.5)
    assert longest_gap_ms(np.array([0, 10_000_000, 50_000_000])) == 40.0


def test_a_load_with_one_client_behind_a_home_link(load_on_server):
    link = LinkSpec(rate_mbit=20, delay_ms=5, share=0.5, client_rate="2")
    spec = lt.LoadSpec(clients=2, cloths=4, size=8, seconds=2.0, iterations=2, encoding="quant16", link=link)
    args = ["--tick-rate", "60", "--stats-period", "0.5", "--no-admission", "--solver", "workgroup"]
    report, results, _ = load_on_server(spec, args, "ll-ci")
    links = report.links
    assert links["link"]["rate_mbit"] == 20 and links["link"]["client_rate"] == "2"
    shaped, plain = links["shaped"], links["unshaped"]
    assert shaped["clients"] == 1 and plain["clients"] == 1 and shaped["cloths"] == plain["cloths"] == 2
    assert shaped["rate_at_end"] == [2] and plain["rate_at_end"] == [1]
    # the shaped client takes every 2nd state, the unshaped one every state of every frame the
    # server did not coalesce (counted: a busy CI box coalesces frames, missing for both; the
    # counter counts one at the next tick, so one at either edge of the window may fall outside it)
    (s,) = [r for r in results if r.extra["shaped"]]
    (p,) = [r for r in results if not r.extra["shaped"]]
    assert 0 < max(s.extra["per_cloth_states"]) <= report.ticks // 2 + 1
    assert min(p.extra["per_cloth_states"]) >= report.ticks - report.skipped_frames - 2, report.skipped_frames
    assert np.isfinite(shaped["latency_ms"]["p99"]) and shaped["longest_gap_ms"] > 0
    # the report's own figures are the unshaped client's (the server's, not the link's)
    assert report.expected_states == 2 * report.ticks and report.states == sum(p.extra["per_cloth_states"])
    # the server's decimated-key counters over the window (1.8): the shaped client's 2 cloths'
    # every 2nd state (a tick's slip at either end of the window at most)
    assert 0 < report.rates["rate_published"] <= 2 * (report.ticks // 2 + 2)
    assert report.rates["rate_unserved"] >= 0
