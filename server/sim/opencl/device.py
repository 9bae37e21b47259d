"""OpenCL device choice and the kernel program cache.

Device choice: ``DRAPE_DEVICE`` (or the ``device`` argument) is ``auto`` (a GPU when one is
present, else a CPU device such as PoCL), ``gpu``, ``cpu``, ``gpu:N`` / ``cpu:N`` (the N-th such
device, from 0: one server per GPU on a multi-GPU host), or a substring of the platform or
device name. Programs are built once per build-option set and cached for the context; the
service releases the ones no cloth has used for a while (:meth:`Device.release_idle`: the PoCL
CPU device holds about 1.5 MB of compiler state per program, returned to the OS only once the
program is released and the heap trimmed) and builds them again when asked (from the OpenCL
driver's own program cache on disk, about 25 ms each on PoCL).

A program's source includes other kernel files (``#include "..."``); :func:`program_text` puts
them together into the one text the driver compiles, so the build needs no include path and a
driver's program cache keyed on that text rebuilds whenever any of the files changes.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import pyopencl as cl

from .devicecheck import INSTALL_HINT, PACK_LANES_CPU, Verdict, clear_pocl_cache, private_pocl_cache, prove
from .platforms import all_devices, describe, kernel_dir

log = logging.getLogger(__name__)

private_pocl_cache()  # before OpenCL lists its platforms: PoCL reads POCL_CACHE_DIR then


@lru_cache(maxsize=1)
def layout() -> dict[str, int]:
    """The ``#define NAME int`` constants of kernels/layout.h."""
    text = (kernel_dir() / "layout.h").read_text()
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^#define\s+(\w+)\s+(-?\d+)\b", text, re.M)}


_INCLUDE = re.compile(r'^[ \t]*#[ \t]*include[ \t]+"([^"]+)"')


def _expand(name: str, root: Path, stack: tuple[str, ...], seen: dict[str, str]) -> str:
    """Kernel file ``name`` with each ``#include "file"`` line replaced by that file, expanded in
    turn, between ``#line`` directives naming the file and line the compiler is in."""
    if name in stack:
        raise ValueError(f"kernel files include each other: {' -> '.join((*stack, name))}")
    path = root / name
    if not path.is_file():
        where = f" (included by {stack[-1]})" if stack else ""
        raise FileNotFoundError(f"no kernel file {name!r} in {root}{where}")
    seen[name] = text = path.read_text()
    out = [f'#line 1 "{name}"']
    for i, line in enumerate(text.splitlines(), 1):
        m = _INCLUDE.match(line)
        if m:
            out.append(_expand(m.group(1), root, (*stack, name), seen))
            out.append(f'#line {i + 1} "{name}"')
        else:
            out.append(line)
    return "\n".join(out)


def program_text(source: str, root: Path | None = None) -> str:
    """The whole text of the program in kernel file ``source`` (in ``root``, by default
    :func:`kernel_dir`): every quoted include, whatever the build options, replaced by the file's
    text (``#line`` keeps the compiler's messages naming the file and line they are about). The
    compiler then reads no file: nothing in the working directory can stand in for a kernel file
    (a compiler looks for a quoted include there first), and a driver's program cache keyed on
    the text it is given (NVIDIA's, PoCL's) builds again whenever any of the files changes.
    An included file that is missing, or files that include each other, are errors."""
    return _expand(source, root or kernel_dir(), (), {}) + "\n"


def kernel_sources(source: str, root: Path | None = None) -> dict[str, str]:
    """Kernel file ``source`` and every file it includes, directly or not, by name: the files
    :func:`program_text` puts together."""
    seen: dict[str, str] = {}
    _expand(source, root or kernel_dir(), (), seen)
    return seen


_warned: set[str] = set()  # devices whose failed check this process has logged


def _proven(dev: cl.Device) -> Verdict:
    """``dev``'s verdict (devicecheck.prove: a child process's, cached per device, driver and
    kernel sources); a failure logged once per process."""
    v = prove(dev)
    if not v.ok and v.device not in _warned:  # a warning only when no device is left (_choose raises)
        _warned.add(v.device)
        log.info("OpenCL device %s cannot run Drape's kernels; skipping it: %s", describe(dev), v.summary())
    return v


def choose_device(spec: str | None = None) -> cl.Device:
    """The device ``spec`` (default ``DRAPE_DEVICE``, else ``auto``) names, among those that pass
    the device check (devicecheck.py); an error naming each candidate's failed kernel if none does."""
    return _choose(spec)[0]


def _choose(spec: str | None = None) -> tuple[cl.Device, Verdict]:
    """:func:`choose_device`, with the chosen device's verdict (each candidate proved once)."""
    spec = (spec or os.environ.get("DRAPE_DEVICE") or "auto").strip()
    devs = all_devices()
    if not devs:
        raise RuntimeError("no OpenCL device found (install pocl-binary-distribution for a CPU device)")
    gpus = [d for d in devs if d.type & cl.device_type.GPU]
    cpus = [d for d in devs if d.type & cl.device_type.CPU]
    low = spec.lower()

    def first_usable(cands: list[cl.Device], what: str) -> tuple[cl.Device, Verdict]:
        """The first GPU that passes the check, else the CPU device that runs the widest packs."""
        proven: list[tuple[cl.Device, Verdict]] = []
        for d in cands:
            if d.type & cl.device_type.GPU:
                proven.append((d, _proven(d)))
                if proven[-1][1].ok:
                    return proven[-1]
        proven += [(d, _proven(d)) for d in cands if not d.type & cl.device_type.GPU]
        usable = [(d, v) for d, v in proven if v.ok]
        if usable:
            return max(usable, key=lambda dv: dv[1].lanes)  # the first of the widest
        failures = "; ".join(v.summary() for _, v in proven)
        raise RuntimeError(f"no {what} OpenCL device can run Drape's kernels ({failures}); {INSTALL_HINT}")

    if low == "auto":
        return first_usable(gpus + cpus or devs, "usable")
    kind, sep, index = low.partition(":")
    if sep and kind in ("gpu", "cpu") and index.isdigit():
        of_kind = gpus if kind == "gpu" else cpus
        if int(index) >= len(of_kind):
            raise RuntimeError(
                f"DRAPE_DEVICE={spec} but there are {len(of_kind)} OpenCL {kind.upper()} device(s): "
                f"{[describe(d) for d in of_kind]}"
            )
        return first_usable([of_kind[int(index)]], spec)
    if low == "gpu":
        if not gpus:
            raise RuntimeError("DRAPE_DEVICE=gpu but no OpenCL GPU is present")
        return first_usable(gpus, "GPU")
    if low == "cpu":
        if not cpus:
            raise RuntimeError("DRAPE_DEVICE=cpu but no OpenCL CPU device is present")
        return first_usable(cpus, "CPU")
    matches = [d for d in devs if low in describe(d).lower()]
    if not matches:
        raise RuntimeError(f"no OpenCL device matches {spec!r}; have: {[describe(d) for d in devs]}")
    return first_usable(matches, f"{spec!r}")


@dataclass
class DeviceInfo:
    name: str
    is_gpu: bool
    local_mem: int
    max_work_group: int
    compute_units: int
    is_nvidia: bool
    pack_lanes: int  # CPU pack width that runs here (the device check's verdict); 0 on a GPU


class Device:
    """A context, a queue and a cache of built programs. ``spec`` chooses among the devices that
    pass the device check (:func:`choose_device`); ``device`` takes that OpenCL device as it is
    (the check's own child process, which is what proves it)."""

    def __init__(self, spec: str | None = None, *, device: cl.Device | None = None) -> None:
        self.verdict: Verdict | None = None  # None: taken as it is (the check's own child)
        if device is None:
            device, self.verdict = _choose(spec)
        self.device = device
        self.ctx = cl.Context([self.device])
        try:  # event timestamps give the device time of a tick (the service's cost model)
            self.queue = cl.CommandQueue(self.ctx, properties=cl.command_queue_properties.PROFILING_ENABLE)
        except cl.Error:
            self.queue = cl.CommandQueue(self.ctx)
        self._programs: dict[tuple[str, ...], cl.Program] = {}
        self._kernels: dict[tuple[str, ...], cl.Kernel] = {}
        self._lock = threading.Lock()  # guards the caches, never held while a program builds
        self._building: dict[tuple[str, ...], threading.Lock] = {}
        self.builds: list[tuple[tuple[str, ...], str]] = []  # (program key, thread that built it), in order
        self._used: dict[tuple[str, ...], float] = {}  # program key -> last program()/kernel() (monotonic)
        self._pinned: set[tuple[str, ...]] = set()  # never released (pin())
        self.released = 0  # programs released by release_idle, in all
        d = self.device
        self.info = DeviceInfo(
            name=describe(d),
            is_gpu=bool(d.type & cl.device_type.GPU),
            local_mem=int(d.local_mem_size),
            max_work_group=int(d.max_work_group_size),
            compute_units=int(d.max_compute_units),
            is_nvidia="nvidia" in d.platform.name.lower(),
            pack_lanes=self._pack_lanes(),
        )
        log.info(
            "OpenCL device: %s (local mem %d B, max work-group %d)",
            self.info.name,
            self.info.local_mem,
            self.info.max_work_group,
        )

    def _pack_lanes(self) -> int:
        """The CPU pack width: ``DRAPE_PACK_LANES``, else the one the device check found runs."""
        if self.device.type & cl.device_type.GPU:
            return 0
        env = os.environ.get("DRAPE_PACK_LANES")
        if env:
            return int(env)
        return self.verdict.lanes if self.verdict is not None else PACK_LANES_CPU

    def program(self, options: list[str], source: str = "cloth.cl") -> cl.Program:
        """The program of ``source`` built with ``options``, built once. Thread-safe: a build
        holds only its own key's lock, so other threads keep using built kernels meanwhile."""
        key = (source, *sorted(options))
        with self._lock:
            prg = self._programs.get(key)
            if prg is not None:
                self._used[key] = time.monotonic()
                return prg
            building = self._building.setdefault(key, threading.Lock())
        with building:
            with self._lock:
                prg = self._programs.get(key)
            if prg is None:
                text = program_text(source)
                opts = [*options, *os.environ.get("DRAPE_CL_FLAGS", "").split()]
                log.debug("building %s with %s", source, " ".join(options))
                prg = self._build(text, opts)
                with self._lock:
                    self._programs[key] = prg
                    self._used[key] = time.monotonic()
                    self.builds.append((key, threading.current_thread().name))
                    self._building.pop(key, None)
            return prg

    def _build(self, text: str, opts: list[str]) -> cl.Program:
        """Build, and once more after clearing Drape's PoCL kernel cache if that fails there (an
        entry a crashed build left behind)."""
        try:
            return cl.Program(self.ctx, text).build(options=opts)
        except (cl.Error, RuntimeError):
            if not clear_pocl_cache(self.device):
                raise
            return cl.Program(self.ctx, text).build(options=opts)

    def built(self, options: list[str], source: str = "cloth.cl") -> bool:
        """Whether the program of ``source`` with ``options`` is built already."""
        with self._lock:
            return (source, *sorted(options)) in self._programs

    def kernel(self, options: list[str], name: str) -> cl.Kernel:
        opts = sorted(options)
        key = ("kernel", name, *opts)
        with self._lock:
            k = self._kernels.get(key)
            if k is not None:
                self._used[("cloth.cl", *opts)] = time.monotonic()
        if k is None:
            try:
                k = cl.Kernel(self.program(options), name)
            except cl.Error as e:  # a program whose cached binary lost its kernels (a crashed build)
                if "INVALID_KERNEL_NAME" not in str(e) or not clear_pocl_cache(self.device):
                    raise
                with self._lock:
                    self._programs.pop(("cloth.cl", *opts), None)
                k = cl.Kernel(self.program(options), name)
            with self._lock:
                self._kernels[key] = k
        return k

    def pin(self) -> int:
        """Keep every program built so far for good (the server's warm-up: its default kernels,
        the frame encoder's); :meth:`release_idle` releases only later ones. Returns how many."""
        with self._lock:
            self._pinned.update(self._programs)
            return len(self._pinned)

    def release_idle(self, idle_s: float, now: float | None = None) -> int:
        """Release the programs (and their kernels) that are not pinned and that no
        :meth:`program` or :meth:`kernel` call asked for in the last ``idle_s`` seconds: the tick
        fetches the kernels of every live group each tick, so these are the feature combinations
        no cloth uses any more. A holder of one of their kernels keeps it working (OpenCL counts
        references). A later call builds the program again. Returns how many were released."""
        now = time.monotonic() if now is None else now
        with self._lock:
            idle = [
                k
                for k in self._programs
                if k not in self._pinned and k not in self._building and now - self._used.get(k, now) >= idle_s
            ]
            for key in idle:
                del self._programs[key]
                self._used.pop(key, None)
            gone = {key[1:] for key in idle if key[0] == "cloth.cl"}  # kernel() builds cloth.cl only
            for kkey in [k for k in self._kernels if k[2:] in gone]:  # ("kernel", name, *options)
                del self._kernels[kkey]
            self.released += len(idle)
        if idle:
            log.debug("released %d idle program(s)", len(idle))
        return len(idle)

    @property
    def program_count(self) -> int:
        with self._lock:
            return len(self._programs)
