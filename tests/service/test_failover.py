"""Failover that loses nothing (protocol 1.3 ``resume``): the sim starts a resumed cloth from the
given positions and velocities on every back end; a server killed with SIGKILL has its cloths
resubmitted by the SDK to another live server under the same handles, continuing from their last
state; a client whose cloths were reclaimed while it was away gets them back when it returns.
Real Zenoh sessions on loopback, real ``drape serve`` processes, PoCL's CPU OpenCL."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import time

import numpy as np
import pytest

from drape.client import protocol as P
from drape.server.sim import make_world
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

DT = 1.0 / 60.0


@pytest.mark.parametrize("solver", ["reference", "workgroup", "coloured", "jacobi"])
def test_resumed_cloth_moves_by_its_velocity(solver, device, rng):
    """A free cloth (no pins) resumed with velocity v moves by v*dt + g*dt^2 in its first step
    (semi-implicit Euler: v += g dt, x += v dt); its links are at rest length, so the solver has
    nothing to correct. Checked against the float64 formula; NaN never passes."""
    fab = cook_grid(6, 5, 0.5, 0.4, pinned=[])
    params = ClothParams()
    x0 = fab.rest_positions + np.array([0.3, 1.0, -0.2])
    vel = rng.uniform(-2.0, 2.0, 3)
    velocities = np.broadcast_to(vel, x0.shape).copy()
    world = make_world(solver) if solver == "reference" else make_world(solver, device=device)
    h = world.add(fab, params, x0, velocities)
    world.step(DT)
    got = world.fetch().positions[h].astype(np.float64)
    g = np.asarray(params.gravity, np.float64)
    want = x0 + (vel + g * DT) * DT
    err = np.abs(got - want).max()
    assert np.isfinite(got).all() and err < 1e-4, f"{solver}: max error {err} m"
    # and the velocity was not ignored: a cloth resumed at rest ends elsewhere by |v| dt
    assert np.abs(got - (x0 + g * DT * DT)).max() > 0.5 * np.abs(vel).max() * DT


@pytest.mark.parametrize("solver", ["reference", "workgroup"])
def test_resumed_pinned_vertices_stay_put(solver, device):
    """Pinned vertices start where ``positions`` puts them, with their targets there and no velocity."""
    fab = cook_grid(4, 4, pinned=[0, 3])
    x0 = fab.rest_positions + np.array([1.0, 2.0, 3.0])
    world = make_world(solver) if solver == "reference" else make_world(solver, device=device)
    h = world.add(fab, ClothParams(), x0, np.full(x0.shape, 5.0))
    world.step(DT)
    got = world.fetch().positions[h]
    assert np.allclose(got[[0, 3]], x0[[0, 3]], atol=1e-5)


# ---------------------------------------------------------------------------------------------
# End to end: real `drape serve` processes, the SDK with failover=True

SERVER_WAIT = 90.0  # a drape serve starting (OpenCL warm-up) on a loaded CI machine
EVENT_WAIT = 30.0  # generous: the loaded CI machine


class Serve:
    """One ``drape serve`` child process on its own port (stopped by ``stop``; ``kill`` = SIGKILL)."""

    def __init__(self, tmp_path, name: str, port: int | None = None, extra: tuple[str, ...] = ()) -> None:
        from drape.server.tools.procs import free_port, serve_command

        self.port = port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.server_id = name
        self.log = open(tmp_path / f"{name}-{self.port}.log", "w")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(
            serve_command(
                self.endpoint,
                name,
                *("--grace-period", "1", "--stats-period", "0.25", "--no-admission", "--device", "cpu"),
                *extra,
            ),
            stdout=self.log,
            stderr=subprocess.STDOUT,
        )

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.log.close()


@pytest.fixture
def two_servers(tmp_path):
    servers = [Serve(tmp_path, "fo-a"), Serve(tmp_path, "fo-b")]
    try:
        yield servers
    finally:
        for s in servers:
            s.stop()


def _wait(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def _client(servers, server_id: str, **kw):
    from drape.client import DrapeClient

    c = DrapeClient([s.endpoint for s in servers], server_id=server_id, timeout=10.0, **kw)  # failover: the default
    assert _wait(lambda: {s.server_id for s in servers} <= set(c.live_servers()), SERVER_WAIT), (
        f"servers not up: {c.live_servers()}"
    )
    return c


def _settle(handles, n: int = 30) -> None:
    """Consume ``n`` states of each (the submit's first states may be close to the reply)."""
    for h in handles:
        for _ in range(n):
            h.next_state(EVENT_WAIT)


def test_kill_9_fails_every_cloth_over_under_the_same_handle(two_servers):
    """SIGKILL of server A: every cloth comes back on B under the same handle, its first state
    within 1 cm of the last one received from A (a slow cloth: damped, hanging still) and with
    continuous velocity; states keep arriving; bundled cloths too; pins re-sent."""
    a, b = two_servers
    with _client(two_servers, a.server_id) as client:
        events = []
        client.on_failover(events.append)
        # horizontal at rest, hanging from two corners after a second: far from its rest pose
        handles = [
            client.submit_grid(
                6,
                6,
                0.5,
                0.5,
                origin=(1.0 * j, 2.0, 0.0),
                pinned=[0, 5],
                material={"damping": 0.2},
                bundle=(j % 2 == 1),
            )
            for j in range(4)
        ]
        handles[0].move_pins([0, 5], [[0.0, 2.0, 0.0], [0.5, 2.0, 0.0]], wait=True)
        _settle(handles, 120)  # 2 s: hanging nearly still
        assert all(h.server_id == a.server_id for h in handles)
        before = {id(h): h.last_states() for h in handles}
        rest = P.grid_geometry(6, 6, 0.5, 0.5, "horizontal", (0.0, 2.0, 0.0))[0]
        assert float(np.abs(before[id(handles[0])][1].positions - rest).max()) > 0.1  # the check below can fail
        old_ids = {id(h): h.id for h in handles}
        for h in handles:
            h.clear()
        a.kill()
        assert _wait(lambda: len(events) >= len(handles), EVENT_WAIT), f"{len(events)} failover events"
        assert all(e.ok and not e.kept and e.new_server == b.server_id for e in events), events
        assert {e.handle for e in events} == set(handles)
        for h in handles:
            assert h.server_id == b.server_id and h.id != old_ids[id(h)] and not h.closed and not h.lost
            prev, last = before[id(h)]
            first = h.next_state(EVENT_WAIT)  # the first state from B (A's stale ones were cleared)
            while first.cloth != h.id:
                first = h.next_state(EVENT_WAIT)
            assert np.isfinite(first.positions).all()
            jump = float(np.linalg.norm(first.positions - last.positions, axis=1).max())
            assert jump < 0.01, f"cloth {h.id}: first state after failover {jump * 100:.2f} cm from the last before"
            second = h.next_state(EVENT_WAIT)
            v_before = (last.positions - prev.positions) * 60.0 / (last.tick - prev.tick)
            v_after = (second.positions - first.positions) * 60.0 / (second.tick - first.tick)
            assert float(np.abs(v_after - v_before).max()) < 0.5, "velocity not continuous"
            _settle([h], 30)  # states keep arriving
        assert np.allclose(handles[0].latest().positions[[0, 5]], [[0.0, 2.0, 0.0], [0.5, 2.0, 0.0]], atol=1e-5)
        assert handles[0].move_pins([0, 5], [[0.0, 2.1, 0.0], [0.5, 2.1, 0.0]]) is not None  # controls go to B


def test_a_failover_onto_a_server_older_than_1_8_takes_every_state(two_servers):
    """A client at rate 2 (1.8) fails over onto a server whose info says 1.7: such a server has no
    decimated keys, so each cloth (own key or bundle) falls back to the full-rate key and its
    states keep coming, every tick. B is a real 1.8 ``drape serve`` whose info the client is told
    says 1.7 (as test_bundles fakes a 1.0 server): it still publishes ``every/2``, so a client that
    kept rate 2 would see even ticks only."""
    a, b = two_servers
    with _client(two_servers, a.server_id, rate=2) as client:
        events = []
        client.on_failover(events.append)
        handles = [client.submit_grid(5, 5, origin=(j, 1.0, 0.0), pinned=[0, 4], bundle=(j == 1)) for j in range(2)]
        _settle(handles, 10)
        assert all(h.rate == 2 for h in handles) and client.bundles.rate == 2
        assert all(h.next_state(EVENT_WAIT).tick % 2 == 0 for h in handles)
        old = client.connection.info_of(b.server_id)
        client.connection.set_info(b.server_id, dataclasses.replace(old, version=(1, 7)))
        a.kill()
        assert _wait(lambda: len(events) >= len(handles), EVENT_WAIT), f"{len(events)} failover events"
        assert all(e.ok and e.new_server == b.server_id for e in events), events
        assert all(h.rate == 1 and h.served == (1,) for h in handles) and client.bundles.rate == 1
        for h in handles:
            h.clear()
            ticks = []
            while len(ticks) < 12:
                st = h.next_state(EVENT_WAIT)
                if st.cloth == h.id and not st.extrapolated:
                    ticks.append(st.tick)
            assert any(t % 2 for t in ticks), f"cloth {h.id}: even ticks only {ticks}"
        handles[0].set_rate(2)  # refused quietly on a 1.7 server
        assert handles[0].rate == 1


def test_reclaimed_cloths_come_back_when_the_client_returns(tmp_path):
    """A client away longer than lease + grace (its liveliness withdrawn, as the server sees a
    SIGSTOPped client): the server reclaims its cloths; when the client is back, the stalled
    states are probed, answered not_found, and every cloth is resubmitted from its last state."""
    from drape.client import DrapeClient

    srv = Serve(tmp_path, "fo-pause")
    try:
        with (
            _client([srv], srv.server_id) as client,
            DrapeClient(srv.endpoint, server_id=srv.server_id, timeout=10.0) as watcher,
        ):
            stats = []
            watcher.on_stats(stats.append)
            events = []
            client.on_failover(events.append)
            handles = [
                client.submit_grid(
                    5,
                    5,
                    0.5,
                    0.5,
                    orientation="vertical",
                    origin=(j, 1.0, 0.0),
                    pinned=[0, 4],
                    material={"damping": 0.2},
                )
                for j in range(3)
            ]
            _settle(handles, 60)
            # away: the failover thread stops (as the whole process would) and the token goes
            client._failover.pause()
            client.connection.token.undeclare()
            assert _wait(lambda: any(s.get("reclaimed", 0) >= len(handles) for s in stats), EVENT_WAIT), (
                "the server should reclaim the absent client's cloths"
            )
            last = {id(h): h.latest() for h in handles}  # the last states before the reclaim
            for h in handles:
                h.clear()
            alive = client.keys.alive_client(client.client_id)
            client.connection.token = client.session.liveliness().declare_token(alive)
            t_back = time.monotonic()
            client._failover.resume()
            assert _wait(lambda: len(events) >= len(handles), EVENT_WAIT), f"{len(events)} failover events"
            assert all(e.ok and e.reason == "reclaimed" and e.new_server == srv.server_id for e in events), events
            for h in handles:
                first = h.next_state(EVENT_WAIT)
                assert first.cloth == h.id and np.isfinite(first.positions).all()
                jump = float(np.linalg.norm(first.positions - last[id(h)].positions, axis=1).max())
                assert jump < 0.01, f"first state after the resubmission {jump * 100:.2f} cm from the last before"
            back_s = max(e.done_ns for e in events) / 1e9 - t_back
            print(f"cloths back {back_s:.2f} s after the client returned")
    finally:
        srv.stop()


def test_a_server_restarted_under_the_same_id_gets_the_cloths_back(tmp_path):
    """The only server is killed and comes back (same id, same endpoint, a new process): the
    client waits for it, finds its cloths gone there (probe: not_found) and resubmits them to it."""
    srv = Serve(tmp_path, "fo-restart")
    again = None
    try:
        with _client([srv], srv.server_id) as client:
            events = []
            client.on_failover(events.append)
            handles = [
                client.submit_grid(5, 5, 0.5, 0.5, origin=(j, 1.0, 0.0), pinned=[0, 4], material={"damping": 0.2})
                for j in range(2)
            ]
            _settle(handles, 60)
            old_ids = [h.id for h in handles]
            srv.kill()
            assert _wait(lambda: all(h.lost for h in handles), EVENT_WAIT), "the loss should be noticed"
            last = {id(h): h.latest() for h in handles}
            for h in handles:
                h.clear()
            again = Serve(tmp_path, "fo-restart", port=srv.port)
            assert _wait(lambda: len(events) >= len(handles), SERVER_WAIT), f"{len(events)} failover events"
            assert all(e.ok and not e.kept and e.new_server == srv.server_id for e in events), events
            for h, old in zip(handles, old_ids, strict=True):
                assert h.id != old and not h.closed
                first = h.next_state(EVENT_WAIT)
                assert first.cloth == h.id
                assert float(np.linalg.norm(first.positions - last[id(h)].positions, axis=1).max()) < 0.01
    finally:
        srv.stop()
        if again is not None:
            again.stop()


def test_a_resubmission_refused_for_itself_is_reported_at_once(tmp_path):
    """PROTOCOL.md 11.3: only overloaded, busy, limit_exceeded or no reply send a cloth on to the
    next server; any other refusal (here the survivor's vertex limit, too_large) ends its failover
    at once with that error, instead of retrying until give_up_after (set far beyond the wait)."""
    a = Serve(tmp_path, "fo-big")
    b = Serve(tmp_path, "fo-small", extra=("--max-vertices-per-cloth", "16"))
    try:
        events = []
        c = _client([a, b], "fo-big", failover_give_up=3600.0)
        try:
            c.on_failover(events.append)
            h = c.submit_grid(6, 6, pinned=[0, 5])  # 36 vertices: fo-small refuses it
            _settle([h], 5)
            a.kill()
            assert _wait(lambda: events, EVENT_WAIT), "the failover never ended"
            (ev,) = events
            assert ev.error is not None and ev.error.code == P.ERR_TOO_LARGE, ev
            assert h.closed
        finally:
            c.close()
    finally:
        a.stop()
        b.stop()


def test_with_failover_turned_off_a_killed_servers_cloths_are_closed(tmp_path):
    """``failover=False`` (failover is on by default since issue 26): the old behaviour, the
    handles close when their server goes, nothing is resubmitted."""
    srv = Serve(tmp_path, "fo-off")
    try:
        with _client([srv], srv.server_id, failover=False) as client:
            assert not client.failover
            handles = [client.submit_grid(4, 4, pinned=[0, 3]) for _ in range(2)]
            _settle(handles, 5)
            srv.kill()
            assert _wait(lambda: all(h.closed for h in handles), EVENT_WAIT), "the handles should close"
            assert client.failover_events == []
    finally:
        srv.stop()
