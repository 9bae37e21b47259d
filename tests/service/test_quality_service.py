"""Quality presets through the service: chosen at submit or by control, lowered by the server
while ticks overrun and restored afterwards, reported in stats."""

from __future__ import annotations

import msgpack
import pytest
from conftest import WAIT, make_config, wait_until

from drape.client import DrapeClient, ProtocolError
from drape.client import protocol as P
from drape.server.service import Server
from drape.server.sim import quality

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

TIMEOUT = 10.0


def test_protocol_carries_quality_both_ways():
    req = P.SubmitRequest(
        client="c1", grid=P.GridSpec(4, 4, 1.0, 1.0, "horizontal", (0.0, 0.0, 0.0)), quality="accurate", rid=3
    )
    back = P.decode_submit(P.encode_submit(req))
    assert back.quality == "accurate" and back == req
    ctl = P.ControlRequest("a" * 16, "0" * 32, quality="fast", rid=4)
    assert P.decode_control(P.encode_control(ctl)).quality == "fast"
    m = P.submit_to_map(req)
    m["quality"] = "ultra"
    with pytest.raises(ProtocolError, match="quality"):
        P.decode_submit(msgpack.packb(m))
    assert P.QUALITY_PRESETS == quality.ORDER  # one list of names on both sides


def _params(srv: Server, cloth_id: str):
    return srv.call(lambda w: w.cloths[srv.world_handle(cloth_id)].params)


def test_preset_at_submit_and_by_control():
    with (
        Server(make_config(adaptive_quality=False)) as srv,
        DrapeClient(srv.config.listen[0], server_id=srv.server_id, timeout=TIMEOUT) as client,
    ):
        with client.submit_grid(8, 8, pinned=[0, 7], quality="balanced") as h:
            h.next_state(WAIT)
            p = _params(srv, h.id)
            want = quality.apply_preset(p, "balanced", srv.config.tick_rate)
            assert (p.iterations, p.substeps, p.features.xpbd, p.features.tethers) == (
                want.iterations,
                want.substeps,
                True,
                True,
            )
            tick = h.set(quality="fast")
            h.wait_for_tick(tick, WAIT)
            assert _params(srv, h.id).substeps == quality.PRESETS["fast"].substeps
            assert srv.stats()["quality"]["presets"] == {"fast": 1}


def test_the_server_governor_predicts_with_its_share_of_moving_cloths():
    """A cloth among colliders runs the presets' moving settings, whose costs (the cost file's
    moving record) the server's governor predicts with once it has seen the cloths."""
    with (
        Server(make_config(quality_budget=0.05)) as srv,
        DrapeClient(srv.config.listen[0], server_id=srv.server_id, timeout=TIMEOUT) as client,
    ):
        srv.quality.measure = lambda seconds: 2.0 * srv.config.quality_budget * srv.config.dt
        still = client.submit_grid(8, 8, pinned=[0, 7], quality="accurate")
        moving = client.submit_grid(8, 8, pinned=[0, 7], quality="accurate", features=["colliders"])
        assert wait_until(lambda: srv.stats()["quality"]["presets"].get("fast") == 2)
        # the share is taken on the tick after the one that added the second cloth, which the
        # stats may already count: waited for, not read at once
        assert wait_until(lambda: srv.quality.governor.moving == 0.5)
        fast = quality.PRESETS["fast"]
        assert (_params(srv, still.id).substeps, _params(srv, moving.id).substeps) == (
            fast.substeps,
            fast.moving_substeps,
        )


def test_server_lowers_quality_under_load_and_restores_it():
    # Deterministic: the governor is fed injected tick costs (counted ticks, no wall-clock
    # dependence): first twice the budget, every tick, then nothing.
    with (
        Server(make_config(quality_budget=0.05)) as srv,
        DrapeClient(srv.config.listen[0], server_id=srv.server_id, timeout=TIMEOUT) as client,
    ):
        budget_s = srv.config.quality_budget * srv.config.dt
        srv.quality.measure = lambda seconds: 2.0 * budget_s
        cloths = [client.submit_grid(16, 16, pinned=[0, 15], quality="accurate") for _ in range(2)]
        assert wait_until(lambda: srv.stats()["quality"]["presets"].get("fast") == 2)
        st = srv.stats()["quality"]
        assert st["degraded"] == 2 and st["changes"] >= 2 and st["last_change"]["direction"] == "down"
        assert st["degraded_since_ns"] is not None
        assert all(_params(srv, c.id).substeps == quality.PRESETS["fast"].substeps for c in cloths)
        # the load goes away: back up, one preset at a time, to what was asked
        srv.quality.measure = lambda seconds: 0.0
        assert wait_until(lambda: srv.stats()["quality"]["presets"].get("accurate") == 2)
        st = srv.stats()["quality"]
        assert st["degraded"] == 0 and st["degraded_since_ns"] is None and st["degraded_s"] > 0
        assert st["last_change"]["direction"] == "up"
        for c in cloths:
            assert c.next_state(WAIT).tick > 0
