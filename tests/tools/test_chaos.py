"""``drape chaos``: the fuzz scenario at a CI size against a real ``drape serve`` on loopback (PoCL).

Asserted on counted events only (never on speed: CI is a loaded 2-core machine): no traceback in
the server's log, no ``internal`` error reply, every malformed message answered with a Drape error
map, and a valid submit still served afterwards. The generator itself is checked to be
deterministic and to cover every queryable and every kind of hostile message.
"""

from __future__ import annotations

import argparse
from collections import Counter
from types import SimpleNamespace

import msgpack
import pytest

from drape.client import protocol as P
from drape.server.tools import (
    chaos,
    chaos_admission,
    chaos_failover,
    chaos_faults,
    chaos_fuzz,
    chaos_hostload,
    chaos_placement,
    chaos_window,
)

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

CI_COUNT = 600
CI_MAX_BYTES = 1 << 20


def test_generator_is_deterministic_and_covers_every_queryable_and_kind():
    a = list(chaos_fuzz.messages(CI_COUNT, 3, "fuzzer", "0123456789abcdef", "0" * 32, CI_MAX_BYTES))
    b = list(chaos_fuzz.messages(CI_COUNT, 3, "fuzzer", "0123456789abcdef", "0" * 32, CI_MAX_BYTES))
    assert a == b and len(a) == CI_COUNT
    assert {q for q, _, _ in a} == set(chaos_fuzz.QUERYABLES)
    kinds = Counter(k.split(" ")[0] for _, k, _ in a)
    for kind in (
        "type",
        "truncated",
        "random",
        "deep-array",
        "deep-map",
        "deep-field",
        "huge-map",
        "over-limit",
        "trailing",
        "bad-utf8",
        "non-string-keys",
    ):
        assert kinds[kind] > 0, kind
    assert max(len(p) for _, _, p in a) == CI_MAX_BYTES + 1  # one just over the limit
    assert all(len(p) <= CI_MAX_BYTES for _, k, p in a if k != "over-limit")


def test_valid_bases_decode_and_their_mutations_do_not():
    """The fuzzer starts from requests the protocol accepts: a mutation is what makes them hostile."""
    bases = chaos_fuzz.valid_requests("fuzzer", "0123456789abcdef", "0" * 32)
    decoders = {
        "submit": P.decode_submit,
        "control": P.decode_control,
        "control_batch": P.decode_control_batch,
        "remove": P.decode_remove,
        "info": P.decode_info,
    }
    for b in bases:
        decoders[b.queryable](msgpack.packb(b.message))
    deep = chaos_fuzz.deep(chaos_fuzz.DEPTH)
    for decode in decoders.values():
        with pytest.raises(P.ProtocolError) as e:
            decode(deep)
        assert e.value.code == "malformed"


def test_fuzz_leaves_no_traceback_no_internal_error_and_the_server_serving(tmp_path):
    # Admission control off: on a loaded CI machine it may refuse the final valid submit with
    # `overloaded`, which is right for a server but not what this test is about.
    ctx = chaos_faults.Context(
        out=tmp_path,
        fuzz_count=CI_COUNT,
        max_message_bytes=CI_MAX_BYTES,
        grace_period=1.0,
        program_idle_s=1.0,  # RSS is read after grace + this + 3 s: keep the CI run short
        baseline_s=0.5,
        seed=11,
        serve_args=("--no-admission",),
    )
    r = chaos_faults.fuzz(ctx)
    assert r["sent"] == CI_COUNT
    assert r["server_alive"]
    assert r["tracebacks"] == 0, f"tracebacks in {tmp_path}"
    assert r["internal"] == 0, r["internal_kinds"]
    assert r["outcomes"].get("unparseable", 0) == 0
    assert r["no_reply"] == 0
    assert r["valid_submit_after"] == "ok"
    assert sum(r["outcomes"].values()) == CI_COUNT


def test_kills_of_either_server_lose_no_cloth(tmp_path):
    """The kill scenario at CI size: two servers, two failover game clients whose 4 cloths the SDK
    placed by load (both servers get some), each server killed once in turn and restarted: every
    cloth of each killed server comes back on the other, none is lost, each within 1 cm."""
    ctx = chaos_faults.Context(
        out=tmp_path, grace_period=1.0, serve_args=("--no-admission",), kill_servers=2, kills=2, kill_gap=0.5
    )
    r = chaos_failover.kill(ctx, cloths=4)
    print({k: v for k, v in r.items() if k != "per_kill"})
    assert sum(r["cloths_per_server_at_start"]) == 4 and min(r["cloths_per_server_at_start"]) > 0
    assert len({k["server"] for k in r["per_kill"]}) == 2  # each server once
    assert all(k["back"] == k["held"] for k in r["per_kill"]), r["per_kill"]
    assert r["per_kill"][0]["held"] == r["cloths_per_server_at_start"][0]
    assert r["per_kill"][1]["held"] == 4  # all of them were on the second server by then
    assert r["failovers"] == r["per_kill"][0]["held"] + 4
    assert r["lost"] == 0 and r["tracebacks"] == 0
    assert r["max_first_state_jump_cm"] is not None and r["max_first_state_jump_cm"] < 1.0


def test_command_lists_scenarios_and_refuses_unknown_ones(capsys):
    parser = argparse.ArgumentParser()
    chaos.configure(parser)
    assert chaos.run(parser.parse_args(["--list"])) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in chaos.SCENARIOS)
    assert chaos.run(parser.parse_args(["no-such-scenario"])) == 2


def test_table_reports_failures_as_failures():
    report = {
        "passed": False,
        "scenarios": {
            "kill": {
                "passed": False,
                "fails": ["0 of 4 cloths of the killed server came back (0.0 %)"],
                "back_pct": 0.0,
            },
            "fuzz": {"passed": True, "fails": [], "good_rate_hz": 60.0, "errors": {"malformed": 3}},
        },
    }
    text = chaos.format_table(report)
    assert "kill: FAIL 0 of 4 cloths" in text and "overall: FAIL" in text
    assert "malformed:3" in text


def test_missed_ticks_lost_states_and_gaps_are_the_servers_own_unless_other_work_took_the_machine():
    """The judgement of issue 26's 0 missed ticks, 0 lost and no gap over 50 ms on a shared machine:
    a stats period (or a gap, or a run of lost states) counts as the machine's only where processes
    other than the run's took ``MACHINE_BUSY`` cores or more during it (HostLoad's samples, here
    set at times long past so that its live sampling does not meet them)."""
    host = chaos_hostload.HostLoad.shared()
    busy, idle = chaos_hostload.MACHINE_BUSY + 0.5, 0.0
    with host._lock:
        host.samples[:0] = [(10.0 + 0.1 * i, busy if 12 <= i < 16 else idle) for i in range(60)]
    stats = [(10.0 + 0.5 * k, {"missed_ticks": m}) for k, m in enumerate([0, 0, 3, 7, 7, 9, 9, 9])]
    # periods: 10.5-11.0 +3 (idle: own), 11.0-11.5 +4 (busy from 11.2 s: the machine's), 12.0-12.5 +2 (own)
    server = SimpleNamespace(stats=SimpleNamespace(samples=stats))
    w = chaos_window.Window(server, 10.0, stats[0][1], 0.0, {}, n0=1)  # type: ignore[arg-type]
    out: dict = {}
    w.attribute(out, gaps=[(11.3, 11.45), (13.1, 13.3)])  # one gap under the other work, one not
    assert out["missed_ticks_own"] == 5 and out["missed_ticks_machine"] == 4
    assert out["quiet_periods"] == 6  # of 7: the window judged (a window with none is marked ~ in the table)
    assert out["good_worst_gap_own_ms"] == pytest.approx(200.0) and out["good_gaps_over_limit"] == 2
    fails = chaos_faults.judge({**out, "missed_ticks": 9, "good_rate_hz": 60.0, "good_lost": 3, "good_lost_own": 0})
    assert any("5 missed ticks (of 9)" in f for f in fails) and any("gap of 200.0 ms" in f for f in fails)
    assert not any("lost" in f for f in fails)  # all 3 lost under the other work


def test_placement_behind_the_acl_router_sees_every_server_and_places_on_both(tmp_path):
    """acl-placement at CI size (plain TCP behind the router): both servers' loads seen, the 8
    cloths spread over both and served (its 1 s target is not asserted: CI is a loaded machine)."""
    ctx = chaos_faults.Context(out=tmp_path, grace_period=1.0, serve_args=("--no-admission",), auth="tcp")
    r = chaos_placement.acl_placement(ctx)
    print(r)
    assert r["loads_seen"] == 2 and len(r["placement"]) == 2 and sum(r["placement"].values()) == 8
    assert r["served"] == 8 and r["tracebacks"] == 0


def test_heavy_control_runs_in_the_authenticated_deployment(tmp_path):
    """heavy-control with ``--auth tcp``: the server (``--identity keys``) and the good client
    behind the ACL router as their users, the abuser's submit and control on its own keys: the
    plain cloth is served and the control priced (refused 'overloaded' or served)."""
    ctx = chaos_faults.Context(out=tmp_path, grace_period=1.0, seconds=1.0, baseline_s=0.5, auth="tcp")
    r = chaos_admission.heavy_control(ctx)
    print({k: v for k, v in r.items() if k != "fails"}, r["fails"])
    assert r["submit_outcome"] == "ok" and r["control_outcome"] in ("ok", "overloaded")
    assert r["good_states"] > 0 and r["tracebacks"] == 0
