"""Proving an OpenCL device before Drape uses it: the server's own programs, built and run in a
child process, and the verdict cached per device, driver and kernel sources.

A driver can list a device whose compiler fails on Drape's kernels while it compiles a one-line
probe: the PoCL 3.0 / LLVM 14 of the pyopencl wheel, on an AVX-512 CPU its LLVM takes for an
older one, aborts the whole process ("LLVM ERROR: Cannot emit physreg copy instruction") when
it generates the 16-lane pack kernel, and cannot select ``fsqrt`` for wind; on a CPU newer than
LLVM 14 (AMD Zen 5) it builds nothing ("unknown target CPU 'generic'"). PoCL generates a
kernel's machine code at its first launch, so building a program proves little: the check
*runs* what the server will run on the device (:func:`_exercise`): the work-group solver with
every feature off and all on (on a CPU, the pack solver at the lane width it would use and every
narrower width a large cloth falls back to, and the work-group kernel on global memory), the
coloured and Jacobi solvers, pin targets, the frame read-back and the device frame encoder.

It runs in a child process (``python -m drape.server.sim.opencl.devicecheck --child ...``), so
an LLVM abort cannot take the caller down, with a PoCL kernel cache of its own that is deleted
afterwards: a build that crashed half-way never leaves an entry behind for later runs. The child
prints each stage before it starts it, so a crash still names the kernel it was on. On a CPU,
the widest pack width that runs is kept (:data:`LANE_CANDIDATES`, or ``DRAPE_PACK_LANES`` alone
when that is set); the device's :class:`Verdict` says which, and CLWorld uses it.

Verdicts are kept in ``$XDG_CACHE_HOME/drape/devices.json`` (``~/.cache`` by default; the
directory ``DRAPE_CACHE_DIR`` when set), under a key of the platform and its version, the
device, the driver version, the candidate widths and a hash of every kernel file: a new driver
or changed kernels are checked again. ``drape devices --check`` (and ``deploy/setup.sh``) runs
the check afresh and prints the verdicts.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import hashlib
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import pyopencl as cl

from .platforms import all_devices, describe, driver_of, kernel_dir

log = logging.getLogger(__name__)

#: CPU pack solver's lanes (cloths per work-item) where the compiler allows, measured fastest on the
#: 2-core Zen 5 (docs/cpu-solver.md).
PACK_LANES_CPU = 16
#: CPU pack widths tried, widest first; 0 = no packs (the work-group kernel, one cloth a work-item).
LANE_CANDIDATES: tuple[int, ...] = (PACK_LANES_CPU, 8, 4, 0)
#: Seconds one child check may take (PoCL generating every kernel on a busy 2-core machine).
CHECK_TIMEOUT_S = 600.0
#: Changes when what the check runs changes, so older verdicts are not trusted.
CHECK_VERSION = 1
#: The child's module: it runs the kernels (it imports the OpenCL world; this module must not).
PROBE_MODULE = "drape.server.sim.opencl.deviceprobe"
#: Fault injection for the tests of the crash path: ``abort:STAGE`` or ``fail:STAGE`` makes the
#: child abort (as LLVM does) or raise when it reaches a stage whose name starts with STAGE.
FAULT_ENV = "DRAPE_DEVICE_CHECK_FAULT"

#: What to do when no device passes (shown with the device and kernel that failed).
INSTALL_HINT = (
    "install a PoCL that knows this CPU (Debian/Ubuntu: apt-get install pocl-opencl-icd; "
    "deploy/setup.sh does it) or a GPU's OpenCL driver, or choose another device with DRAPE_DEVICE"
)


@dataclass(frozen=True)
class Verdict:
    """Whether a device runs Drape's kernels, and how."""

    device: str  # "platform / device"
    driver: str  # the platform's version and the device's driver version
    ok: bool
    lanes: int = 0  # CPU pack width that runs (0: no packs; always 0 on a GPU)
    failed: str = ""  # the stage that failed (a program and its options), when not ok
    error: str = ""  # the compiler's or the crash's last words, when not ok
    seconds: float = 0.0  # how long the check took
    cached: bool = False  # read from the cache rather than checked now

    def summary(self) -> str:
        if self.ok:
            lanes = f", CPU pack lanes {self.lanes}" if self.lanes else ""
            return f"{self.device} (driver {self.driver}){lanes}: ok"
        return f"{self.device} (driver {self.driver}): failed at {self.failed}: {self.error}"


# ---------------------------------------------------------------------------------------------
# The cache


def cache_dir() -> Path:
    env = os.environ.get("DRAPE_CACHE_DIR")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "drape"


def private_pocl_cache() -> Path:
    """Drape's own PoCL kernel cache (``POCL_CACHE_DIR``, unless the environment sets it). PoCL's
    default, ``~/.cache/pocl``, is shared by every program on the machine, and a build that
    crashed half-way leaves an entry there that fails every later run ("INVALID_KERNEL_NAME");
    a directory of Drape's own can be cleared when a build fails (:func:`clear_pocl_cache`).
    Must run before OpenCL's platforms are first listed (PoCL reads it then): device.py calls it
    on import."""
    path = cache_dir() / "pocl"
    os.environ.setdefault("POCL_CACHE_DIR", str(path))
    return path


def clear_pocl_cache(dev: cl.Device) -> bool:
    """After a failed build on a PoCL device: empty Drape's own PoCL kernel cache (never a
    directory the operator chose) so that the build is tried afresh. Whether it did."""
    ours = cache_dir() / "pocl"
    if "portable computing language" not in dev.platform.name.lower():
        return False
    if Path(os.environ.get("POCL_CACHE_DIR", "")) != ours or not ours.is_dir():
        return False
    shutil.rmtree(ours, ignore_errors=True)
    ours.mkdir(parents=True, exist_ok=True)
    log.warning("a kernel build failed on %s: cleared Drape's PoCL kernel cache %s", describe(dev), ours)
    return True


def kernels_hash() -> str:
    h = hashlib.sha256()
    for p in sorted(kernel_dir().iterdir()):
        if p.suffix in (".cl", ".h"):
            h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _candidates(dev: cl.Device) -> tuple[int, ...]:
    if dev.type & cl.device_type.GPU:
        return (0,)
    env = os.environ.get("DRAPE_PACK_LANES")
    return (int(env),) if env else LANE_CANDIDATES


def cache_key(dev: cl.Device) -> str:
    lanes = ",".join(map(str, _candidates(dev)))
    platform = dev.platform.version.strip()
    return f"{describe(dev)} | {platform} | {driver_of(dev)} | lanes {lanes} | {kernels_hash()} | {CHECK_VERSION}"


@contextlib.contextmanager
def _locked_cache():
    """The cache file's lock, held while a process reads, checks and writes (so two servers
    starting together check a device once)."""
    d = cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "devices.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield d / "devices.json"
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _read(path: Path) -> dict[str, dict]:
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def _write(path: Path, data: dict[str, dict]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    tmp.replace(path)


# ---------------------------------------------------------------------------------------------
# The parent's side


def _indices(dev: cl.Device) -> tuple[int, int]:
    for pi, p in enumerate(cl.get_platforms()):
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        for di, d in enumerate(devs):
            if d.int_ptr == dev.int_ptr:
                return pi, di
    raise ValueError(f"device {dev.name!r} is not among the OpenCL platforms' devices")


def prove(dev: cl.Device, fresh: bool = False) -> Verdict:
    """The device's verdict: from the cache, or checked now in a child process (``fresh``:
    checked now whatever the cache holds) and cached."""
    key = cache_key(dev)
    with _locked_cache() as path:
        if not fresh:
            known = _read(path).get(key)
            if known is not None:
                with contextlib.suppress(TypeError):
                    return Verdict(**{**known, "cached": True})
        verdict = check(dev)
        data = _read(path)
        data[key] = asdict(verdict)
        _write(path, data)
    return verdict


def check(dev: cl.Device) -> Verdict:
    """Run the check in child processes, one lane width at a time, widest first, until one runs."""
    pi, di = _indices(dev)
    name, driver = describe(dev), driver_of(dev)
    t0 = time.monotonic()
    first_failure: Verdict | None = None
    last_failure: Verdict | None = None
    log.info("checking OpenCL device %s (driver %s): building and running Drape's kernels", name, driver)
    for lanes in _candidates(dev):
        failed, error = _run_child(pi, di, lanes)
        if not failed:
            v = Verdict(name, driver, True, lanes, seconds=round(time.monotonic() - t0, 1))
            if first_failure is not None:
                log.warning(
                    "OpenCL device %s: %s failed (%s); using %d lanes",
                    name,
                    first_failure.failed,
                    first_failure.error,
                    lanes,
                )
            log.info("OpenCL device %s passed the check in %.1f s", name, v.seconds)
            return v
        last_failure = Verdict(name, driver, False, lanes, failed, error, round(time.monotonic() - t0, 1))
        first_failure = first_failure or last_failure
        log.info("OpenCL device %s: lane width %d failed at %s: %s", name, lanes, failed, error)
        if not failed.startswith("pack_step"):
            break  # a failure that no narrower pack avoids
    assert last_failure is not None
    return last_failure  # the narrowest tried: what failed even there


def _run_child(platform: int, device: int, lanes: int) -> tuple[str, str]:
    """("", "") when the child ran every stage; else (stage, error)."""
    cache = tempfile.mkdtemp(prefix="drape-devicecheck-pocl-")
    env = {**os.environ, "POCL_CACHE_DIR": cache, "PYTHONUNBUFFERED": "1", "DRAPE_PACK_LANES": str(lanes)}
    cmd = [sys.executable, "-m", PROBE_MODULE, str(platform), str(device), str(lanes)]
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=CHECK_TIMEOUT_S)
        out, err, rc = proc.stdout, proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else e.stdout or ""
        err, rc = f"timed out after {CHECK_TIMEOUT_S:.0f} s", -1
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    stages = [ln[6:] for ln in out.splitlines() if ln.startswith("stage ")]
    if rc == 0 and "passed" in out.splitlines():
        return "", ""
    stage = stages[-1] if stages else "start-up"
    return stage, _last_words(err, rc)


def _last_words(err: str, rc: int) -> str:
    """The most telling line of a failed child's output: LLVM's error, else the compiler's, else
    the exception a traceback ends with, else its last line; and how the child ended."""
    lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
    picks = (
        [ln for ln in lines if ln.startswith("LLVM ERROR")]
        or [ln for ln in lines if ln.startswith("error:") or ": error:" in ln]
        or [ln for ln in lines if re.match(r"^[\w.]+(Error|Exception)\b.*:", ln)][-1:]
        or lines[-1:]
    )
    how = f"killed by signal {-rc}" if rc < -1 else f"exit code {rc}" if rc > 0 else ""
    return "; ".join(s for s in (picks[0][:300] if picks else "", how) if s)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m drape.server.sim.opencl.devicecheck", description=__doc__)
    ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for d in all_devices():
        print(prove(d, fresh=True).summary())
    return 0


if __name__ == "__main__":
    sys.exit(main())
