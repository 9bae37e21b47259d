"""The tick thread's work for a tick that adds (or removes) many cloths at once (issues 21/26).

``python -m drape.server.tools.addbench --base 1024 --adds 64 256 1024`` builds an OpenCL world
of ``--base`` S x S cloths (bending, predictive, in bundles of ``--bundle`` as the load test's
clients submit them), then times, median over ``--repeat`` rounds, a tick that adds K cloths and
a tick that removes them again, stage by stage as the tick thread meets them:

- ``add`` (``World.add`` K times: what Applier._add calls per cloth) or ``remove``;
- ``step`` (``World.step``'s host side: the staged writes, tables and launch groups rebuilt,
  the launches enqueued);
- ``layout`` (``World.layout``: the frame layout and the readback's gather map rebuilt);
- ``fetch`` (``World.fetch_async`` of the tick's roster: with ``--device-encode`` the device
  encoder's plan rebuilt, else the readback enqueued);
- ``total``: the sum, the tick thread's host time for that tick. The device's own work is
  waited for after the timer stops (on a CPU device it would otherwise land in the next stage).

The JSON (``--json PATH``) keeps every sample. ``--profile`` prints cProfile's top functions of
the add ticks at the largest K. On a shared machine other processes' time lands in some rounds:
compare the minima too.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import logging
import pstats
import statistics
import time
from pathlib import Path
from typing import Any

from drape.client import protocol as P

from ..service.registry import ClothRecord
from ..sim.fabric import Fabric, cook_grid
from ..sim.opencl.clworld import CLWorld
from ..sim.params import ClothParams, LinkOptions
from ..sim.roster import Roster

log = logging.getLogger(__name__)

STAGES = ("add", "step", "layout", "fetch", "total")
DT = 1.0 / 60.0


class Bench:
    """One world, its cloths' records (for the roster) and the tick's stages."""

    def __init__(self, world: CLWorld, fabric: Fabric, params: ClothParams, bundle: int) -> None:
        self.world, self.fabric, self.params, self.bundle = world, fabric, params, bundle
        self.records: dict[int, ClothRecord] = {}
        self._n = 0

    def add(self, k: int) -> list[int]:
        hs = []
        for _ in range(k):
            h = self.world.add(self.fabric, self.params)
            cid, client = f"c{self._n:06d}", f"client{self._n // max(self.bundle, 1):05d}"
            self._n += 1
            self.records[h] = ClothRecord(
                cid,
                client,
                "0" * 32,
                f"drape/bench/cloth/{cid}",
                self.fabric.n_vertices,
                "predictive",
                P.STEP_DEFAULT,
                handle=h,
                bundle_key=f"drape/bench/bundle/{client}" if self.bundle > 0 else None,
            )
            hs.append(h)
        return hs

    def remove(self, hs: list[int]) -> None:
        for h in hs:
            self.world.remove(h)
            del self.records[h]

    def tick(self, change) -> dict[str, float]:
        """One tick whose commands are ``change()``: each stage's host ms, then the device waited for."""
        w = self.world
        t0 = time.perf_counter()
        out = change()
        t1 = time.perf_counter()
        w.step(DT)
        t2 = time.perf_counter()
        lay = w.layout()
        t3 = time.perf_counter()
        roster = Roster.of((lay.version, 0), [self.records[h] for h in lay.handles.tolist()], lay.normals)
        pending = w.fetch_async(roster, w.steps)
        t4 = time.perf_counter()
        pending.wait().release()
        w.sync()
        ms = [1e3 * t for t in (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t4 - t0)]
        return dict(zip(STAGES, ms, strict=True)) | {"_out": out}


def run(bench: Bench, adds: list[int], repeat: int, profile: bool) -> dict[str, Any]:
    runs: dict[str, Any] = {}
    prof = cProfile.Profile() if profile else None
    for r in range(repeat + 1):  # round 0 warms (kernels, buffers grown): not counted
        for k in adds:
            prof_on = prof is not None and k == max(adds) and r > 0
            if prof_on:
                prof.enable()  # type: ignore[union-attr]
            a = bench.tick(lambda k=k: bench.add(k))
            if prof_on:
                prof.disable()  # type: ignore[union-attr]
            hs = a.pop("_out")
            d = bench.tick(lambda hs=hs: bench.remove(hs))
            d.pop("_out")
            bench.tick(lambda: None)  # a steady tick between (the roster and plan settle)
            if r == 0:
                continue
            row = runs.setdefault(str(k), {"add": {s: [] for s in STAGES}, "remove": {s: [] for s in STAGES}})
            for what, sample in (("add", a), ("remove", d)):
                for s in STAGES:
                    row[what][s].append(sample[s])
    if prof is not None:
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)
    return runs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drape.server.tools.addbench", description=__doc__.splitlines()[0])
    ap.add_argument("--base", type=int, default=1024, help="cloths already in the world")
    ap.add_argument("--adds", type=int, nargs="+", default=[64, 256, 1024], help="cloths added in one tick")
    ap.add_argument("--side", type=int, default=32, help="grid side: side x side vertices per cloth (default 32)")
    ap.add_argument("--bundle", type=int, default=64, help="cloths per bundle; 0 = each cloth on its own key")
    ap.add_argument("--repeat", type=int, default=5, help="timed rounds (median)")
    ap.add_argument("--device", default=None, help="DRAPE_DEVICE: auto, gpu, cpu or part of a name")
    ap.add_argument("--device-encode", action="store_true", help="encode on the device (as drape serve does)")
    ap.add_argument("--profile", action="store_true", help="cProfile the add ticks at the largest K")
    ap.add_argument("--label", default="", help="a label kept in the JSON (e.g. the commit)")
    ap.add_argument("--json", type=Path, default=None, help="write the medians and samples here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    world = CLWorld("workgroup", device=args.device, device_encode=args.device_encode)
    fabric = cook_grid(args.side, args.side, 1.0, 1.0, LinkOptions(bending=True), [0, args.side - 1])
    bench = Bench(world, fabric, ClothParams(iterations=10), args.bundle)
    world.warm_wire()
    t = time.perf_counter()
    bench.tick(lambda: bench.add(args.base))
    print(
        f"{world.device_name}; {args.base} {args.side}x{args.side} cloths in {time.perf_counter() - t:.2f} s; "
        f"{'device' if args.device_encode else 'host'} encoding; median ms over {args.repeat} rounds {args.label}"
    )
    runs = run(bench, args.adds, args.repeat, args.profile)
    print(f"{'K':>6} {'tick':>6} | " + " ".join(f"{s:>8}" for s in STAGES))
    for k, row in runs.items():
        for what in ("add", "remove"):
            med = {s: statistics.median(v) for s, v in row[what].items()}
            print(f"{k:>6} {what:>6} | " + " ".join(f"{med[s]:8.2f}" for s in STAGES), flush=True)
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        out = {"device": world.device_name, "args": {k: str(v) for k, v in vars(args).items()}, "runs": runs}
        args.json.write_text(json.dumps(out, indent=1))
    world.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
