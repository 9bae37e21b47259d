"""What OpenCL offers this process: the platforms' devices, how Drape names them, and where the
kernel files are (the package ``drape.kernels``). Beneath device choice (device.py) and the
device check (devicecheck.py), which both need these and nothing else of each other."""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path

import pyopencl as cl

KERNEL_PACKAGE = "drape.kernels"


@lru_cache(maxsize=1)
def kernel_dir() -> Path:
    return Path(str(resources.files(KERNEL_PACKAGE)))


def all_devices() -> list[cl.Device]:
    """Every device of every platform, in the platforms' order."""
    devs: list[cl.Device] = []
    for p in cl.get_platforms():
        try:
            devs.extend(p.get_devices())
        except cl.Error:  # a platform without devices
            continue
    return devs


def describe(dev: cl.Device) -> str:
    """ "platform / device", the name logs, errors and ``DRAPE_DEVICE`` substrings use."""
    return f"{dev.platform.name.strip()} / {dev.name.strip()}"


def driver_of(dev: cl.Device) -> str:
    """The device's driver version, as its platform reports it ("3.1+debian", "550.54.15")."""
    return dev.driver_version.strip()
