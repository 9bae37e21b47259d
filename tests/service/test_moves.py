"""Protocol 1.4 ``moves`` end to end (PROTOCOL.md 5.1.1) over real Zenoh on loopback with PoCL:
a block moves pins; refused moves (wrong token, another client's cloth) are listed in
``moves_failed`` while the rest apply; a block and an item for the same cloth in one request (the
block wins) or with a reset (the reset wins); an invalid block refuses the request; the SDK's
vectorised ``move_pins_many`` and ``ControlBatch`` send blocks; a 1.3-style batch still works."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TIMEOUT, WAIT, connect, make_config

from drape.client import protocol as P
from drape.server.service import Server

pytestmark = [pytest.mark.opencl, pytest.mark.zenoh]  # not unit (tests/conftest.py)

PINS = [0, 7]  # the two ends of the first row of an 8x8 grid


@pytest.fixture(scope="module")
def server():
    s = Server(make_config(max_cloths_per_client=8)).start()
    yield s
    s.stop()
    assert s.failure is None


def cloths(client, n: int) -> list:
    return [client.submit_grid(8, 8, pinned=PINS, bundle=True) for _ in range(n)]


def batch(client, moves: P.PinMoves | None, items: list[P.ControlRequest] | None = None) -> P.ControlBatchReply:
    req = P.ControlBatchRequest(client.client_id, items or [], client.connection.next_rid(), moves)
    return P.control_batch_reply_from_map(client.request("control_batch", P.encode_control_batch(req)))


def block(handles: list, targets: np.ndarray, tokens: list[str] | None = None) -> P.PinMoves:
    return P.PinMoves(
        [h.id for h in handles],
        tokens or [h.token for h in handles],
        np.array(PINS, np.uint32),
        np.asarray(targets, np.float32).reshape(len(handles), len(PINS), 3),
    )


def pins_at(handle, tick: int) -> np.ndarray:
    return handle.wait_for_tick(tick, WAIT).positions[PINS]


def test_block_moves_pins_and_refuses_per_move(client, server):
    hs = cloths(client, 4)
    tgt = np.random.default_rng(3).uniform(-1, 1, (4, 2, 3)).astype(np.float32)
    tokens = [h.token for h in hs]
    tokens[2] = "f" * 32 if tokens[2] != "f" * 32 else "e" * 32  # not its token
    rep = batch(client, block(hs, tgt, tokens))
    assert rep.results == [] and rep.moves_tick is not None and rep.tick >= rep.moves_tick
    assert [(p, c) for p, c, _ in rep.moves_failed or []] == [(2, P.ERR_FORBIDDEN)]
    for j in (0, 1, 3):
        np.testing.assert_allclose(pins_at(hs[j], rep.moves_tick), tgt[j], atol=1e-5)
    assert np.abs(pins_at(hs[2], rep.moves_tick) - tgt[2]).max() > 1e-3  # not moved
    assert server.stats()["moves_applied"] >= 3
    assert server.registry.errors[P.ERR_FORBIDDEN] >= 1


def test_other_clients_cloth_and_unknown_cloth_refused(client, server):
    other = connect(server)
    try:
        theirs = cloths(other, 1)[0]
        mine = cloths(client, 1)[0]
        tgt = np.full((3, 2, 3), 0.25, np.float32)
        mv = P.PinMoves(
            [mine.id, theirs.id, "0123456789abcdef"],
            [mine.token, theirs.token, "0" * 32],
            np.array(PINS, np.uint32),
            tgt,
        )
        rep = batch(client, mv)
        assert [(p, c) for p, c, _ in rep.moves_failed or []] == [(1, P.ERR_FORBIDDEN), (2, P.ERR_NOT_FOUND)]
        np.testing.assert_allclose(pins_at(mine, rep.moves_tick), tgt[0], atol=1e-5)
        assert np.abs(pins_at(theirs, rep.moves_tick) - 0.25).max() > 1e-3
    finally:
        other.close()


def test_block_wins_over_item_and_reset_wins_over_block(client):
    a, b = cloths(client, 2)
    item_tgt = np.full((2, 3), -0.5, np.float32)
    tgt = np.full((2, 2, 3), 0.75, np.float32)
    items = [
        P.ControlRequest(a.id, a.token, pins=P.PinUpdate(np.array(PINS, np.uint32), item_tgt)),
        P.ControlRequest(b.id, b.token, reset=True),
    ]
    rep = batch(client, block([a, b], tgt), items)
    assert rep.failed == 0 and rep.moves_failed == []
    assert rep.tick == rep.moves_tick  # all of it between the same two ticks
    np.testing.assert_allclose(pins_at(a, rep.moves_tick), tgt[0], atol=1e-5)  # the block wins
    rest = b.rest_positions[PINS]
    np.testing.assert_allclose(pins_at(b, rep.moves_tick), rest, atol=1e-5)  # the reset wins


def test_invalid_block_refuses_the_request(client):
    (a,) = cloths(client, 1)
    item = P.ControlRequest(a.id, a.token, pins=P.PinUpdate(np.array(PINS, np.uint32), np.ones((2, 3), np.float32)))
    m = P.control_batch_to_map(P.ControlBatchRequest(client.client_id, [item], 1, block([a], np.zeros((1, 2, 3)))))
    m["moves"]["targets"] = m["moves"]["targets"][:-4]
    with pytest.raises(P.DrapeError) as e:
        client.request("control_batch", P.pack(m))
    assert e.value.code == P.ERR_INVALID_VALUE
    m["moves"]["indices"] = P.pack({})[:0]  # an empty index list
    with pytest.raises(P.DrapeError):
        client.request("control_batch", P.pack(m))


def test_unpinned_index_refused_per_move(client):
    (a,) = cloths(client, 1)
    mv = P.PinMoves([a.id], [a.token], np.array([0, 9], np.uint32), np.zeros((1, 2, 3), np.float32))
    rep = batch(client, mv)
    assert [(p, c) for p, c, _ in rep.moves_failed or []] == [(0, P.ERR_INVALID_VALUE)]
    mv = P.PinMoves([a.id], [a.token], np.array([64], np.uint32), np.zeros((1, 1, 3), np.float32))
    rep = batch(client, mv)
    assert [(p, c) for p, c, _ in rep.moves_failed or []] == [(0, P.ERR_INDEX_OUT_OF_RANGE)]


def test_sdk_move_pins_many_and_batch(client, server):
    hs = cloths(client, 3)
    tgt = np.random.default_rng(5).uniform(-1, 1, (3, 2, 3)).astype(np.float32)
    moves = server.registry.counters["batch_moves"]
    ticks = client.move_pins_many(hs, PINS, tgt, wait=True)
    assert ticks is not None and len(ticks) == 3 and all(isinstance(t, int) for t in ticks)
    assert server.registry.counters["batch_moves"] == moves + 3  # one block, not three items
    for h, t, tick in zip(hs, tgt, ticks, strict=True):
        np.testing.assert_allclose(pins_at(h, tick), t, atol=1e-5)
    with client.batch(wait=True) as b:  # same indices, pins only: one block; the collider item stays an item
        b.move_pins(hs[0], PINS, tgt[1])
        b.move_pins(hs[1], PINS, tgt[2])
        b.move_pins(hs[2], PINS, tgt[0], colliders=[P.Sphere((0.0, -5.0, 0.0), 0.1)])
    assert b.results is not None and len(b.results) == 3
    assert server.registry.counters["batch_moves"] == moves + 5  # the two pins-only items as a block
    for h, t, tick in zip(hs, (tgt[1], tgt[2], tgt[0]), b.results, strict=True):
        np.testing.assert_allclose(pins_at(h, tick), t, atol=1e-5)  # type: ignore[arg-type]


def test_items_only_batch_of_a_1_3_client(client):
    (a,) = cloths(client, 1)
    item = P.ControlRequest(a.id, a.token, pins=P.PinUpdate(np.array(PINS, np.uint32), np.ones((2, 3), np.float32)))
    m = P.control_batch_to_map(P.ControlBatchRequest(client.client_id, [item], 9))
    m["v"] = [1, 3]
    rep_map = client.request("control_batch", P.pack(m))
    assert "moves_tick" not in rep_map and "moves_failed" not in rep_map
    rep = P.control_batch_reply_from_map(rep_map)
    assert rep.failed == 0 and rep.moves_tick is None
    np.testing.assert_allclose(pins_at(a, rep.tick), np.ones((2, 3)), atol=1e-5)


def test_last_targets_recorded_for_failover(client):
    """A failover re-sends each handle's last pin targets: the vectorised path records them as a
    view of its last block, folded into the handle's own record in the order things were sent."""
    hs = cloths(client, 2)
    first = np.full((2, 2, 3), 0.1, np.float32)
    client.move_pins_many(hs, PINS, first)
    hs[0].move_pins([7], [[0.2, 0.2, 0.2]], wait=True)  # its own control after the block
    second = np.full((2, 2, 3), 0.3, np.float32)
    second[1, 1] = 0.4
    client.move_pins_many(hs, PINS, second)
    for h in hs:
        client.moves.fold(h)
    np.testing.assert_allclose(np.stack([hs[0]._last_pins[i] for i in PINS]), second[0])
    np.testing.assert_allclose(np.stack([hs[1]._last_pins[i] for i in PINS]), second[1])
    hs[1].move_pins([0], [[0.9, 0.9, 0.9]])
    client.moves.fold(hs[1])
    np.testing.assert_allclose(hs[1]._last_pins[0], 0.9)
    np.testing.assert_allclose(hs[1]._last_pins[7], 0.4)


def test_controls_take_the_wire_form_of_their_cloths_own_server(server):
    """A client whose default server is another one (here one that does not exist) sends its
    cloths' controls in the wire forms of the server they live on (moves block, batch, features
    delta: 1.4 and 1.2), asking that server's info only: never the default server's."""
    from drape.client import DrapeClient

    c = DrapeClient(server.config.listen[0], server_id="ghost", timeout=TIMEOUT)
    try:
        hs = [c.submit_grid(8, 8, pinned=PINS, server=server.server_id) for _ in range(2)]
        ticks = c.move_pins_many(hs, PINS, np.zeros((2, 2, 3), np.float32), wait=True)  # one moves block
        assert ticks is not None and all(isinstance(t, int) for t in ticks)
        with c.batch(wait=True) as b:
            b.set(hs[0], gravity=(0.0, -1.0, 0.0))
            b.move_pins(hs[1], [0], [[0.0, 0.1, 0.0]])
        assert b.results is not None and all(isinstance(t, int) for t in b.results)
        assert isinstance(hs[0].set(features_add=["normals"]), int)
        assert c.connection.known_info("ghost") is None
        assert c.connection.info_of(server.server_id).version >= (1, 4)
        for h in hs:
            h.remove()
    finally:
        c.close(remove=False)


def test_apply_blocks_refuses_removed_and_drops_reset_cloths(device):
    """The tick's side without Zenoh: a cloth removed after its block was accepted is refused
    not_found; one reset in the same tick keeps its rest pose; the request is answered once."""
    from drape.server.service.commands import BatchControl, MoveBlock
    from drape.server.service.registry import Registry
    from drape.server.service.tick.moves import apply_blocks
    from drape.server.sim import make_world
    from drape.server.sim.fabric import cook_grid
    from drape.server.sim.params import ClothParams

    world = make_world("workgroup", device=device)
    fabric = cook_grid(8, 8, pinned=PINS)
    hs = [world.add(fabric, ClothParams()) for _ in range(3)]
    waiter = BatchControl(None, 5, [], moves_failed=[], pending=1)  # type: ignore[arg-type]
    tgt = np.full((3, 2, 3), 0.5, np.float32)
    b = MoveBlock(np.array(hs), np.array([0, 1, 2]), ["x", "y", "z"], np.array(PINS), tgt, waiter)
    world.remove(hs[1])
    world.reset(hs[2])
    registry = Registry(make_config())
    before: list = []
    apply_blocks(world, [b], 42, {hs[2]}, registry, before)
    assert [(p, c) for p, c, _ in waiter.moves_failed or []] == [(1, P.ERR_NOT_FOUND)]
    assert waiter.moves_tick == 42 and len(before) == 1 and registry.counters["moves_applied"] == 1
    world.step(1 / 60)
    frame = world.fetch()
    np.testing.assert_allclose(frame.positions[hs[0]][PINS], tgt[0], atol=1e-5)
    np.testing.assert_allclose(frame.positions[hs[2]][PINS], fabric.rest_positions[PINS], atol=1e-5)
    rep = P.control_batch_reply_from_map(P.decode_reply(before[0].payload()))
    assert rep.tick == 42 and rep.moves_tick == 42 and [p for p, _, _ in rep.moves_failed or []] == [1]


def test_identical_blocks_coalesce_latest_wins_and_each_request_is_answered(device):
    """Two blocks of the same client moving the same cloths wait for one tick: the intake keeps
    the later one only (one World call), both requests are answered with that tick, the pins end
    at the later targets. A cloth removed in between (the registry's generation) voids the
    checker's memo, so a block checked after it is checked afresh and never coalesced with one
    checked before."""
    from drape.server.service.commands import BatchControl, Intake
    from drape.server.service.registry import ClothRecord, Registry
    from drape.server.service.requests.moves import MoveChecker
    from drape.server.service.tick.moves import apply_blocks
    from drape.server.sim import make_world
    from drape.server.sim.fabric import cook_grid
    from drape.server.sim.params import ClothParams

    world = make_world("workgroup", device=device)
    fabric = cook_grid(8, 8, pinned=PINS)
    registry = Registry(make_config())
    recs = []
    for i in range(3):
        rec = ClothRecord(f"c{i}", "alice", f"{i:032x}", "", 64, fabric=fabric)
        registry.reserve(rec, 0)
        rec.handle = world.add(fabric, ClothParams())
        recs.append(rec)
    checker, intake = MoveChecker(registry), Intake(max_pending=16)

    def send(targets: float, rid: int) -> BatchControl:
        mv = P.PinMoves(
            ["c0", "c1"],
            [recs[0].token, recs[1].token],
            np.array(PINS, np.uint32),
            np.full((2, 2, 3), targets, np.float32),
        )
        w = BatchControl(None, rid, [], pending=1)  # type: ignore[arg-type]
        intake.put_controls([], rid, checker.check(mv, "alice", w))
        return w

    w1, w2 = send(0.25, 1), send(0.75, 2)
    blocks = intake.take_moves()
    assert len(blocks) == 1 and blocks[0].waiter is w2 and blocks[0].superseded == [w1]
    before: list = []
    apply_blocks(world, blocks, 9, set(), registry, before)
    assert len(before) == 2 and w1.moves_tick == w2.moves_tick == 9 and not w1.moves_failed
    assert registry.counters["move_blocks_superseded"] == 1
    world.step(1 / 60)
    np.testing.assert_allclose(world.fetch().positions[recs[0].handle][PINS], 0.75, atol=1e-5)

    w3 = send(0.5, 3)
    registry.unreserve(recs[2])  # another cloth goes: the memo of what alice's block owns is void
    w4 = send(0.5, 4)
    blocks = intake.take_moves()
    assert [b.waiter for b in blocks] == [w3, w4] and not blocks[1].superseded
    assert blocks[0].handles is not blocks[1].handles
    apply_blocks(world, blocks, 10, set(), registry, before)
    assert len(before) == 4
