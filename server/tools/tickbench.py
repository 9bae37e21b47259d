"""The tick thread's host work per tick and per roster change, stage by stage (issue 21).

``python -m drape.server.tools.tickbench --cloths 1024 4096 8192`` lays out N predictive cloths
of S x S vertices in bundles of B (one client's bundle each, as the load test's clients submit
them) exactly as the service's tick thread sees them (the registry's records, the World's
layout and vertex bases) and times, median over ``--repeat`` rounds:

- a **roster change** (one cloth comes or goes at N: the rounds alternate between the N cloths
  and N - 1 of them), what the tick thread does before it can enqueue the frame: ``roster``
  (Roster.of, ticker.py), ``plan`` (FramePlan.for_roster: the entries, the layout, the static
  bytes), ``set_plan`` (DeviceEncoder.set_plan: the kernel and the tables uploaded, the
  buffers sized (kept across plans while they fit), the static bytes enqueued; with a device
  only), ``fill`` (then waiting for those static bytes on the device: kernels/static.cl's
  words, no zero fill since encode.cl writes every state's padding; device work that the next
  frame waits for, not the tick thread's;
  waited for after each change so that it does not overlap the next stage), ``follow`` (DeviceStreams.follow: the
  predictive streams carried over) and ``change`` (devencode.DeviceFrames._plan end to end,
  which is plan + set_plan + follow);
- a **steady tick** (the same roster): ``enqueue`` (DeviceFrames.encode: the streams'
  decisions and the encoder's launches and copy, host time of the call), ``decide``
  (DeviceStreams.decide alone), ``wait`` (the frame read back and wrapped: on a CPU device this
  is the encode kernel itself, not host work) and ``wire`` (DeviceWire's hold and non-finite
  check).

The process's heap is set as ``drape serve`` sets it, and the records are frozen out of the
garbage collector's scans as its ``freeze_long_lived`` does. On a shared machine other
processes' time lands in some rounds: the JSON keeps every sample (compare the minima too).
Everything the World's step, the applier's commands
and the publisher do is left out: this is the host work that grows with the cloth count.
``--watch-rate K`` adds ``rate``: DeviceRates.follow when rate K's watched set changes (every
publication's ``/every/K`` key watched, then all but one: a decimated plan rebuilt from the frame
plan's columns, its encoder's set_plan, its streams followed; device only).
``--no-device`` times the host-only stages (roster, plan, follow, decide) without OpenCL.
``--profile`` prints cProfile's top functions of a roster change at the largest N. ``--json
PATH`` writes the raw medians (and every sample).
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import json
import logging
import pstats
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from drape.client import protocol as P

from ..service.config import ServerConfig
from ..service.process.memory import configure_heap
from ..service.registry import ClothRecord
from ..sim.frame import Layout
from ..sim.opencl.devstreams import DeviceStreams
from ..sim.opencl.frameplan import FramePlan
from ..sim.roster import Roster

log = logging.getLogger(__name__)


@dataclass
class Load:
    """N cloths as the tick thread holds them, and the layouts with all of them and one fewer."""

    records: dict[int, ClothRecord]  # handle -> record (the applier's ``live``)
    slots: dict[int, SimpleNamespace]  # handle -> its vertex base (the World's ``rec``)
    layouts: tuple[Layout, Layout]  # every cloth; one gone (the middle one)
    nv: int

    @classmethod
    def make(cls, cloths: int, side: int, bundle: int, encoding: str, step: float) -> Load:
        nv = side * side
        records, slots = {}, {}
        for h in range(cloths):
            cid, client = f"c{h:05d}", f"client{h // max(bundle, 1):04d}"
            records[h] = ClothRecord(
                cid,
                client,
                "0" * 32,
                f"drape/bench/cloth/{cid}",
                nv,
                encoding,
                step,
                handle=h,
                bundle_key=f"drape/bench/bundle/{client}" if bundle > 0 else None,
            )
            slots[h] = SimpleNamespace(vbase=h * nv)
        full = np.arange(cloths, dtype=np.int64)
        less = np.delete(full, cloths // 2)
        layouts = tuple(
            Layout(
                v,
                hs,
                np.arange(len(hs) + 1, dtype=np.int64) * nv,
                np.zeros(len(hs), bool),
                {h: i for i, h in enumerate(hs.tolist())},
            )
            for v, hs in ((1, full), (2, less))
        )
        return cls(records, slots, layouts, nv)  # type: ignore[arg-type]

    def roster(self, lay: Layout) -> Roster:
        """What Ticker._roster_for builds on a layout change."""
        return Roster.of((lay.version, 0), [self.records[h] for h in lay.handles.tolist()], lay.normals)

    def plan(self, roster: Roster, lay: Layout) -> FramePlan:
        """What DeviceFrames._plan builds."""
        vbase = [self.slots[h].vbase for h in lay.handles.tolist()]
        return FramePlan.for_roster(roster, vbase, np.diff(lay.offsets).tolist())


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    t = time.perf_counter()
    out = fn()
    return 1e3 * (time.perf_counter() - t), out


def run(load: Load, repeat: int, dev: Any | None, watch_rate: int = 0) -> dict[str, list[float]]:
    """Every stage's samples (ms): ``repeat`` roster changes, then ``repeat`` steady ticks (then,
    with ``watch_rate`` k, ``repeat`` changes of rate k's watched set)."""
    samples: dict[str, list[float]] = {}

    def add(name: str, ms: float) -> None:
        samples.setdefault(name, []).append(ms)

    frames = None
    if dev is not None:
        import pyopencl as cl

        from ..sim.opencl.devencode import DeviceFrames

        n_vert = max(len(load.records) * load.nv, 1)
        pos = cl.Buffer(dev.ctx, cl.mem_flags.READ_WRITE, 16 * n_vert)
        cl.enqueue_fill_buffer(dev.queue, pos, np.full(1, 0.25, np.float32), 0, 16 * n_vert).wait()
        mem = SimpleNamespace(pos=SimpleNamespace(buf=pos), nrm=SimpleNamespace(buf=pos))
        frames = DeviceFrames(dev, mem, load.slots, SimpleNamespace(step_marker=None))  # type: ignore[arg-type]
        frames.build_all()
    streams = DeviceStreams()
    # roster changes: one cloth comes or goes each round (the first round of each layout is a warm-up)
    for r in range(repeat + 2):
        lay = load.layouts[r % 2]
        ms_roster, roster = _timed(lambda: load.roster(lay))  # noqa: B023
        ms_plan, plan = _timed(lambda: load.plan(roster, lay))  # noqa: B023
        ms_follow, _ = _timed(lambda: streams.follow(plan))  # noqa: B023
        if r >= 2:
            add("roster", ms_roster)
            add("plan", ms_plan)
            add("follow", ms_follow)
        if frames is not None:
            ms_set, _ = _timed(lambda: frames.encoder.set_plan(plan))  # noqa: B023
            ms_fill, _ = _timed(frames.encoder.wait_static)
            roster = Roster.of((lay.version, 1000 + r), [load.records[h] for h in lay.handles.tolist()], lay.normals)
            ms_change, _ = _timed(lambda: frames._plan(roster, lay))  # noqa: B023
            frames.encoder.wait_static()
            if r >= 2:
                add("set_plan", ms_set)
                add("fill", ms_fill)
                add("change", ms_change)
    # steady ticks on the full roster
    lay = load.layouts[0]
    roster = load.roster(lay)
    if frames is None:
        streams.follow(load.plan(roster, lay))
        for tick in range(1, repeat + 3):
            ms, _ = _timed(lambda: streams.decide(tick, None))  # noqa: B023
            if tick > 2:
                add("decide", ms)
        return samples
    from ..sim.statecodec import PredictiveStreams

    frames._plan(roster, lay)
    watched = list(range(len(roster.publications())))
    for tick in range(1, repeat + 3):
        ms_enq, pending = _timed(lambda: frames.encode(roster, tick, lay, tick))  # noqa: B023
        ms_wait, wire = _timed(pending.wait)
        t = time.perf_counter()
        wire.hold()
        wire.set_time(time.time_ns())
        wire.nonfinite()
        ms_wire = 1e3 * (time.perf_counter() - t)
        for _ in wire.payloads(watched, PredictiveStreams()):  # the publisher's part, not timed
            pass
        wire.release()
        if tick > 2:
            add("enqueue", ms_enq)
            add("wait", ms_wait)
            add("wire", ms_wire)
    for tick in range(repeat + 3, 2 * repeat + 3):
        ms, _ = _timed(lambda: frames.streams.decide(tick, None))  # noqa: B023
        add("decide", ms)
    if watch_rate:
        _rate_changes(frames, roster, watch_rate, repeat, add)
    frames.close()
    return samples


def _rate_changes(frames: Any, roster: Roster, k: int, repeat: int, add: Callable[[str, float], None]) -> None:
    """``rate``: DeviceRates.follow when rate ``k``'s watched set changes (a subscriber of every
    publication's ``/every/k`` key comes, or the last one's goes: the rounds alternate between
    every publication and all but one), on a tick of k, as the tick thread runs it: the rate's
    plan built from the frame plan's columns, its encoder's set_plan, its streams followed."""
    assert frames.encoder.plan is not None
    idents = [p[0] for p in roster.publications()]
    sets = (dict.fromkeys(idents, 0), dict.fromkeys(idents[:-1], 0))  # ident -> times it lost its subscribers
    for r in range(repeat + 2):
        frames.rates.watch(lambda s=sets[r % 2]: {k: s})
        ms, _ = _timed(lambda: frames.rates.follow(roster, frames.encoder.plan, 60, k * (r + 1)))  # noqa: B023
        if r >= 2:
            add("rate", ms)


STAGES = ("roster", "plan", "set_plan", "fill", "follow", "change", "enqueue", "decide", "wait", "wire", "rate")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drape.server.tools.tickbench", description=__doc__.splitlines()[0])
    ap.add_argument("--cloths", type=int, nargs="+", default=[1024, 4096, 8192], help="cloth counts")
    ap.add_argument("--side", type=int, default=32, help="grid side: side x side vertices per cloth (default 32)")
    ap.add_argument("--bundle", type=int, default=64, help="cloths per bundle; 0 = each cloth on its own key")
    ap.add_argument("--encoding", default="predictive", choices=list(P.ENCODING_IDS), help="every cloth's encoding")
    ap.add_argument("--step", type=float, default=P.DEFAULT_STEP, help="predictive: grid step, metres")
    ap.add_argument("--repeat", type=int, default=10, help="timed rounds per stage (median)")
    ap.add_argument("--device", default=None, help="DRAPE_DEVICE: auto, gpu, cpu or part of a name")
    ap.add_argument("--no-device", action="store_true", help="host-only stages, no OpenCL")
    ap.add_argument(
        "--watch-rate", type=int, default=0, metavar="K", help="time rate K's plan rebuilt when its subscribers change"
    )
    ap.add_argument("--profile", action="store_true", help="cProfile a roster change at the largest count")
    ap.add_argument("--json", type=Path, default=None, help="write the medians and samples here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    configure_heap(ServerConfig().malloc_mmap_threshold)
    dev = None
    if not args.no_device:
        from ..sim.opencl.device import Device

        dev = Device(args.device)
    where = dev.info.name if dev is not None else "no device"
    print(
        f"{where}; {args.encoding} {args.side}x{args.side} cloths, "
        f"{'bundles of ' + str(args.bundle) if args.bundle > 0 else 'singles'}; median ms over {args.repeat} rounds"
    )
    print(f"{'cloths':>6} | " + " ".join(f"{s:>8}" for s in STAGES))
    results: dict[str, Any] = {"device": where, "args": {k: str(v) for k, v in vars(args).items()}, "runs": []}
    for n in args.cloths:
        load = Load.make(n, args.side, args.bundle, args.encoding, args.step)
        gc.collect()
        gc.freeze()  # as drape serve's freeze_long_lived after a layout change: the records out of the scans
        samples = run(load, args.repeat, dev, args.watch_rate)
        gc.unfreeze()
        med = {s: statistics.median(v) for s, v in samples.items()}
        print(f"{n:6d} | " + " ".join(f"{med[s]:8.2f}" if s in med else f"{'-':>8}" for s in STAGES), flush=True)
        results["runs"].append({"cloths": n, "median_ms": med, "samples_ms": samples})
    if args.profile:
        load = Load.make(max(args.cloths), args.side, args.bundle, args.encoding, args.step)
        streams = DeviceStreams()
        prof = cProfile.Profile()
        for r in range(4):
            lay = load.layouts[r % 2]
            prof.enable()
            roster = load.roster(lay)
            streams.follow(load.plan(roster, lay))
            prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(15)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
