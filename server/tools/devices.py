"""``drape devices``: what OpenCL sees, each device's verdict from the device check, and the one
Drape would use (its driver and CPU pack width). ``--check`` checks every device afresh (what
``deploy/setup.sh`` runs); the exit code is 1 when no device can run Drape's kernels."""

from __future__ import annotations

import argparse

from .procs import require_extra


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "devices")
    parser.add_argument("--device", default=None, help="auto, gpu, cpu or a name substring (env DRAPE_DEVICE)")
    parser.add_argument(
        "--check",
        action="store_true",
        help="check every device afresh (build and run Drape's kernels in a child process) instead of "
        "reading the cached verdicts",
    )


def run(args: argparse.Namespace) -> int:
    from ..sim.opencl.device import Device
    from ..sim.opencl.devicecheck import INSTALL_HINT, prove
    from ..sim.opencl.platforms import all_devices

    for d in all_devices():
        v = prove(d, fresh=args.check)
        how = "cached" if v.cached else f"checked in {v.seconds:.1f} s"
        print(f"  {v.summary()}  [{how}; compute units {d.max_compute_units}, local mem {d.local_mem_size} B]")
    try:
        dev = Device(args.device)
    except RuntimeError as e:
        print(f"no usable device: {e}")
        print(f"  {INSTALL_HINT}")
        return 1
    lanes = f", CPU pack lanes {dev.info.pack_lanes}" if not dev.info.is_gpu else ""
    print(f"chosen: {dev.info.name} (driver {dev.device.driver_version.strip()}{lanes})")
    return 0
