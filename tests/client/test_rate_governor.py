"""The SDK's rate step-down (protocol 1.8, 1.9's lower rates; client/rates.py) driven by injected
times: states that arrive late step a subscription down 60 -> 30 -> 20 -> 10 -> 5 Hz (on a 1.8
server no lower than 20 Hz), lost ones too; a quiet period steps it back up, a step up that does
not hold doubles the wait; a constant clock offset is not lateness."""

from __future__ import annotations

import pytest

from drape.client import protocol as P
from drape.client.rates import RateGovernor, fit_rate, rate_option

TICK_NS = 16_666_667
OFFSET = 123_456_789_000  # the client's clock minus the server's: not lateness


def feed(gov: RateGovernor, ticks: range, late_ms=lambda t: 0.0, drop=lambda t: False) -> list[tuple[int, int]]:
    """States of ``ticks`` (those of the governor's rate) sent at tick times, arriving 20 ms plus
    ``late_ms(tick)`` later; (tick, new rate) of each change."""
    changes = []
    for t in ticks:
        if t % gov.rate or drop(t):
            continue
        server = t * TICK_NS
        new = gov.observe(t, server, server + OFFSET + 20_000_000 + int(late_ms(t) * 1e6))
        if new is not None:
            changes.append((t, new))
    return changes


def test_on_time_states_keep_the_full_rate():
    gov = RateGovernor()
    assert feed(gov, range(1, 60 * 30)) == []
    assert gov.rate == 1 and gov.step_downs == 0


def test_a_growing_backlog_steps_down_to_20_hz_and_back_up_after_a_quiet_period():
    gov = RateGovernor(quiet_s=5.0)
    # a link too slow for 60 and 30 Hz: lateness grows at full and half rate, none at 20 Hz
    down = feed(gov, range(1, 60 * 10), late_ms=lambda t: 0.0 if gov.rate == 3 else (t % 600) * 0.5)
    assert [r for _, r in down] == [2, 3]
    assert gov.step_downs == 2
    # then on time: after 5 s of good windows it steps up, one rate at a time
    up = feed(gov, range(60 * 10, 60 * 30))
    assert [r for _, r in up] == [2, 1]
    assert gov.step_ups == 2
    assert 5 * 60 <= up[0][0] - down[-1][0] <= 8 * 60 and 5 * 60 <= up[1][0] - up[0][0] <= 8 * 60


def test_a_link_far_too_slow_steps_straight_to_5_hz():
    gov = RateGovernor()
    changes = feed(gov, range(1, 60 * 3), late_ms=lambda t: 0.0 if gov.rate == 12 else t * 5.0)  # 300 ms a second
    assert [r for _, r in changes] == [12] and gov.step_downs == 1


def test_facing_a_1_8_server_the_ladder_stops_at_20_hz():
    gov = RateGovernor(rates=P.served_rates((1, 8)))
    changes = feed(gov, range(1, 60 * 6), late_ms=lambda t: t * 5.0)  # late at every rate
    assert [r for _, r in changes] == [3] and gov.rate == 3
    # a failover from a 1.9 server at every 12th state onto a 1.8 one: every 3rd from then on
    gov = RateGovernor(rate=12)
    assert gov.limit(P.served_rates((1, 8))) == 3 and gov.rates == (1, 2, 3)
    assert RateGovernor(rate=2).limit(P.served_rates((1, 7))) == 1


def test_the_rates_each_version_serves():
    assert P.served_rates(None) == (1,) and P.served_rates((1, 7)) == (1,)
    assert P.served_rates((1, 8)) == (1, 2, 3) and P.served_rates((1, 9)) == P.RATES == (1, 2, 3, 6, 12)
    assert P.served_rates((1, 12)) == P.RATES
    assert fit_rate(12, (1, 2, 3)) == 3 and fit_rate(6, P.RATES) == 6 and fit_rate(12, (1,)) == 1


def test_lost_states_step_down_too():
    gov = RateGovernor()
    changes = feed(gov, range(1, 60 * 4), drop=lambda t: t % 2 == 1)  # half the states never come
    assert changes and changes[0][1] == 2


def test_a_step_up_that_does_not_hold_doubles_the_wait():
    gov = RateGovernor(quiet_s=2.0)
    late = lambda t: (t % 120) * 2.0 if gov.rate == 1 else 0.0  # noqa: E731 - the full rate never fits
    feed(gov, range(1, 60 * 20), late_ms=late)
    assert gov.rate in (1, 2) and gov.step_downs >= 2 and gov.step_ups >= 1
    assert gov._quiet >= 4.0  # doubled at least once


def test_rate_options():
    assert rate_option(1) == (1, False) and rate_option(3) == (3, False) and rate_option("auto") == (1, True)
    assert rate_option(6) == (6, False) and rate_option(12) == (12, False)
    with pytest.raises(ValueError):
        rate_option(4)
    assert P.every_key("drape/client/c/states", 2) == "drape/client/c/states/every/2"
    assert P.split_every("drape/cloth/x/state/every/3") == ("drape/cloth/x/state", 3)
    assert P.every_key("drape/cloth/x/state", 12) == "drape/cloth/x/state/every/12"
    assert P.split_every("drape/cloth/x/state/every/12") == ("drape/cloth/x/state", 12)
    assert P.split_every("drape/cloth/x/state/every/9") == ("drape/cloth/x/state/every/9", 1)


def test_the_rates_vectors():
    """tests/vectors/rates.json (1.8): the decimated keys, and a stream of every 2nd state that
    decodes in order to its values, each predicted from the key's own states."""
    import json
    from pathlib import Path

    import numpy as np

    vectors = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "rates.json").read_text())
    for v in (v for v in vectors if v["message"] == "key"):
        assert P.every_key(v["input"]["key"], v["input"]["every"]) == v["value"]["key"]
        assert P.split_every(v["value"]["key"]) == (v["input"]["key"], v["input"]["every"])
    stream = P.StateStream("c")
    states = [v for v in vectors if v["message"] == "state"]
    assert len(states) == 3
    for v in states:
        data = bytes.fromhex(v["hex"])
        st = stream.decode(data)
        assert st is not None and st.tick == v["value"]["tick"]
        np.testing.assert_array_equal(st.positions, np.asarray(v["value"]["positions"], np.float32))
        ph = P.read_predictive_header(data)
        assert (ph.order, ph.ref_tick, ph.ref2_tick) == (
            v["value"]["order"],
            v["value"]["ref_tick"],
            v["value"]["ref2_tick"],
        )


def test_the_governor_vectors_replay():
    """tests/vectors/rates.json's ``governor`` traces (what the Rust crate replays too): the
    constants are RateGovernor's defaults and each trace steps at the same states."""
    import json
    from pathlib import Path

    vectors = json.loads((Path(__file__).resolve().parents[1] / "vectors" / "rates.json").read_text())
    traces = [v for v in vectors if v["message"] == "governor"]
    assert len(traces) >= 7
    for v in traces:
        i = v["input"]
        gov = RateGovernor(rates=tuple(i["rates"]))
        assert i["constants"]["late_s"] == gov.late_s and i["constants"]["rates"] == list(P.RATES)
        assert i["rates"] == list(P.served_rates((1, 8) if v["name"].endswith("1_8") else P.PROTOCOL_VERSION))
        changes = []
        for n, (t, late) in enumerate(zip(i["ticks"], i["late_us"], strict=True)):
            server = t * i["tick_ns"]
            new = gov.observe(t, server, server + i["offset_ns"] + i["link_ns"] + late * 1000)
            if new is not None:
                changes += [n, new]
        want = v["value"]
        assert changes == want["changes"], v["name"]
        assert (gov.rate, gov.step_downs, gov.step_ups, gov._quiet) == (
            want["rate"],
            want["step_downs"],
            want["step_ups"],
            want["quiet_s"],
        )
