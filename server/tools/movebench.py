"""Host cost of a tick's pin moves: protocol 1.4 ``moves`` blocks against 1.1 batch items.

``python -m drape.server.tools.movebench --cloths 4096 --clients 16`` puts N cloths of 8 x 8
vertices (pinned at two corners) in an OpenCL world and a service registry, split over C clients,
then times, per tick, what the server does with one batch control per client moving every
cloth's two pins, in the service's own code (no Zenoh):

- items: ``decode_control_batch`` of N / C items per message, ``Handlers.check_control`` of each
  item, the intake's per-cloth slots, and the ticker's gathering of pins-only slots into one
  ``set_pin_targets_many``;
- moves: ``decode_control_batch`` of one N / C block per message, ``MoveChecker.check``, the
  intake, ``apply_blocks`` (one ``set_pin_targets_block`` per block);

both then the world's single upload of the targets (the scatter launch before the step).
Medians over ``--repeat`` ticks after a warm-up, both paths in the same process, alternating.
"""

from __future__ import annotations

import argparse
import logging
import queue
import statistics
import time
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..service.commands import BatchControl, Intake
from ..service.config import ServerConfig
from ..service.registry import ClothRecord, Registry
from ..service.replies import Replies
from ..service.requests.admission import Admission
from ..service.requests.handlers import Handlers
from ..service.tick.moves import apply_blocks
from ..sim import make_world
from ..sim.fabric import cook_grid
from ..sim.params import ClothParams

log = logging.getLogger(__name__)
SIDE = 8
PINS = np.array([0, SIDE - 1], np.uint32)


def _setup(cloths: int, clients: int, device: str | None) -> tuple[Any, Handlers, list[list[ClothRecord]]]:
    per = -(-cloths // clients)
    cfg = ServerConfig(
        max_cloths=cloths,
        max_cloths_per_client=per,
        max_total_vertices=cloths * SIDE * SIDE,
        max_batch_items=per,
        max_pending_requests=4 * cloths,
        multicast_scouting=False,
    ).validate()
    world = make_world("workgroup", device=device)
    registry = Registry(cfg)
    fabric = cook_grid(SIDE, SIDE, pinned=PINS.tolist())
    handlers = Handlers(
        cfg,
        P.Keys(),
        registry,
        Replies(registry),
        Intake(cfg.max_pending_requests),
        queue.Queue(),
        Admission(cfg),
        None,  # no request thread here: the handlers are called directly
        lambda: 0,
        dict,
        lambda: False,
    )
    recs: list[list[ClothRecord]] = [[] for _ in range(clients)]
    for i in range(cloths):
        c = i % clients
        rec = ClothRecord(f"c{i:05d}", f"k{c}", f"{i:032x}", "", SIDE * SIDE, fabric=fabric)
        registry.reserve(rec, 0)
        rec.handle = world.add(fabric, ClothParams())
        recs[c].append(rec)
    return world, handlers, recs


def _payloads(recs: list[list[ClothRecord]], rng: np.random.Generator) -> tuple[list[bytes], list[bytes]]:
    items, moves = [], []
    for c, mine in enumerate(recs):
        tgt = rng.uniform(-1, 1, (len(mine), len(PINS), 3)).astype(np.float32)
        reqs = [P.ControlRequest(r.id, r.token, pins=P.PinUpdate(PINS, tgt[j])) for j, r in enumerate(mine)]
        items.append(P.encode_control_batch(P.ControlBatchRequest(f"k{c}", reqs, c + 1)))
        mv = P.PinMoves([r.id for r in mine], [r.token for r in mine], PINS, tgt)
        moves.append(P.encode_control_batch(P.ControlBatchRequest(f"k{c}", [], c + 1, mv)))
    return items, moves


def _tick_items(world: Any, h: Handlers, payloads: list[bytes]) -> None:
    for data in payloads:
        batch = P.decode_control_batch(data, h.limits)
        waiter = BatchControl(None, batch.rid, [None] * len(batch.items))  # type: ignore[arg-type]
        todo = []
        for i, item in enumerate(batch.items):
            assert isinstance(item, P.ControlRequest)
            rec, packed = h.check_control(item, batch.client)
            todo.append((rec, item, packed, waiter, i))
        waiter.pending = len(todo)
        h.intake.put_controls(todo, batch.rid)
    pins: tuple[list[int], list[np.ndarray], list[np.ndarray]] = ([], [], [])
    for slot in h.intake.take_controls():  # what Ticker._apply_control does with a pins-only control
        assert slot.req.pins is not None and slot.record.handle is not None
        pins[0].append(slot.record.handle)
        pins[1].append(slot.req.pins.indices)
        pins[2].append(slot.req.pins.targets)
    world.set_pin_targets_many(*pins, validated=True)


def _tick_moves(world: Any, h: Handlers, payloads: list[bytes]) -> None:
    for data in payloads:
        batch = P.decode_control_batch(data, h.limits)
        assert batch.moves is not None
        waiter = BatchControl(None, batch.rid, [])  # type: ignore[arg-type]
        block = h.moves.check(batch.moves, batch.client, waiter)
        assert block is not None and not waiter.moves_failed
        waiter.pending = 1
        h.intake.put_controls([], batch.rid, block)
    apply_blocks(world, h.intake.take_moves(), 1, set(), h.registry, [])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m drape.server.tools.movebench", description=__doc__.splitlines()[0])
    ap.add_argument("--cloths", type=int, default=4096)
    ap.add_argument("--clients", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--device", default=None, help="OpenCL device (default: DRAPE_DEVICE or auto)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    world, handlers, recs = _setup(args.cloths, args.clients, args.device)
    items, moves = _payloads(recs, np.random.default_rng(1))
    times: dict[str, list[float]] = {"items": [], "moves": []}
    runs = {"items": lambda: _tick_items(world, handlers, items), "moves": lambda: _tick_moves(world, handlers, moves)}
    for r in range(args.repeat + 2):
        for name, run in runs.items():
            t = time.perf_counter()
            run()
            world.targets.upload()  # the single upload before the step (CLWorld._flush)
            world.sync()
            if r >= 2:  # two warm-up ticks
                times[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    n = args.cloths
    print(f"{n} cloths x {len(PINS)} pins, {args.clients} messages per tick, {world.device_name}:")
    for k in ("items", "moves"):
        print(f"  {k:5s}  {med[k]:8.2f} ms per tick  {med[k] * 1e3 / n:7.2f} us per cloth")
    print(f"  items / moves: {med['items'] / med['moves']:.1f}x")


if __name__ == "__main__":
    main()
