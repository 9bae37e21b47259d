"""``drape devices``: what OpenCL sees and what Drape would use."""

from __future__ import annotations

import argparse

from .procs import require_extra


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "devices")
    parser.add_argument("--device", default=None, help="auto, gpu, cpu or a name substring (env DRAPE_DEVICE)")


def run(args: argparse.Namespace) -> int:
    from ..sim.opencl.device import Device, _all_devices, describe

    for d in _all_devices():
        print(f"  {describe(d)}  compute units {d.max_compute_units}, local mem {d.local_mem_size} B")
    dev = Device(args.device)
    print(f"chosen: {dev.info.name}")
    return 0
