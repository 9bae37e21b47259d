"""The device check (server/sim/opencl/devicecheck.py): every kernel the server runs, built and run
on the chosen device in a child process; a crash or a failed build in that child names the stage
it was on, narrows the CPU packs or rules the device out, and never poisons a later run."""

from __future__ import annotations

import os

import pyopencl as cl
import pytest

from drape.server.sim.opencl import devicecheck as dc
from drape.server.sim.opencl.device import Device, choose_device
from drape.server.sim.opencl.platforms import all_devices, describe

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """Verdicts in a directory of the test's own (the machine's cache is left as it is)."""
    monkeypatch.setenv("DRAPE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(dc.FAULT_ENV, raising=False)
    monkeypatch.delenv("DRAPE_PACK_LANES", raising=False)
    return tmp_path


def test_the_chosen_device_builds_and_runs_every_kernel_program(own_cache):
    """What CI's set-up proves: on the device Drape chooses, a fresh check (every kernel file;
    on a CPU the pack solver at its width and every narrower one) passes, and the Device uses
    the width it found."""
    dev = choose_device(os.environ.get("DRAPE_DEVICE"))
    v = dc.prove(dev, fresh=True)
    print(v.summary())
    assert v.ok, v.summary()
    assert not v.cached and v.device == describe(dev)
    if dev.type & cl.device_type.GPU:
        assert v.lanes == 0
    else:
        assert v.lanes in dc.LANE_CANDIDATES
        assert Device(os.environ.get("DRAPE_DEVICE")).info.pack_lanes == v.lanes
    assert dc.prove(dev).cached  # the second time from the cache


@pytest.fixture(scope="module")
def cpu() -> cl.Device:
    """A CPU device that passes the check (by the machine's cached verdicts)."""
    cpus = [d for d in all_devices() if d.type & cl.device_type.CPU and dc.prove(d).ok]
    if not cpus:
        pytest.skip("no CPU OpenCL device that passes the check")
    return cpus[0]


def test_an_llvm_abort_at_16_lanes_narrows_the_packs_and_names_the_kernel(cpu, own_cache, monkeypatch):
    """The wheel's PoCL on an AVX-512 CPU: LLVM aborts the process generating the 16-lane pack
    kernel. The check survives it (a child process), says where and how it died, and keeps the
    next width that runs."""
    dev = cpu
    monkeypatch.setenv(dc.FAULT_ENV, "abort:pack_step (kernels/pack.cl) at 16 lanes")
    v = dc.prove(dev, fresh=True)
    assert v.ok and v.lanes == 8, v
    monkeypatch.delenv(dc.FAULT_ENV)
    assert Device(describe(dev)).info.pack_lanes == 8  # cached verdict: the server packs 8 lanes


def test_a_device_that_fails_every_width_is_never_chosen_and_the_error_says_why(cpu, own_cache, monkeypatch):
    dev = cpu
    monkeypatch.setenv(dc.FAULT_ENV, "abort:start-up")  # the child dies before any kernel
    v = dc.prove(dev, fresh=True)
    assert not v.ok
    assert v.failed == "start-up"
    assert "LLVM ERROR: injected fault" in v.error and "killed by signal 6" in v.error
    with pytest.raises(RuntimeError) as e:
        choose_device(describe(dev))
    msg = str(e.value)
    assert describe(dev) in msg and "start-up" in msg and "pocl-opencl-icd" in msg


def test_a_failure_outside_the_pack_kernel_is_not_retried_narrower(cpu, own_cache, monkeypatch):
    dev = cpu
    monkeypatch.setenv(dc.FAULT_ENV, "fail:encode_frame")
    v = dc.prove(dev, fresh=True)
    assert not v.ok and v.failed.startswith("encode_frame (kernels/encode.cl)")
    assert v.lanes == dc.LANE_CANDIDATES[0]  # the first width's failure, not tried at 8, 4, 0
    assert "RuntimeError: injected fault at encode_frame" in v.error


def test_drape_pack_lanes_is_the_only_width_checked(cpu, own_cache, monkeypatch):
    dev = cpu
    monkeypatch.setenv("DRAPE_PACK_LANES", "4")
    v = dc.prove(dev, fresh=True)
    assert v.ok and v.lanes == 4
    assert "lanes 4 |" in dc.cache_key(dev)


def test_the_cache_key_changes_with_the_kernels(cpu, own_cache, tmp_path, monkeypatch):
    """A verdict holds for one device, driver, set of widths and kernel sources."""
    dev = cpu
    key = dc.cache_key(dev)
    assert describe(dev) in key and dc.driver_of(dev) in key and dc.kernels_hash() in key
    kernels = tmp_path / "kernels"
    kernels.mkdir()
    (kernels / "x.cl").write_text("// a kernel\n")
    monkeypatch.setattr(dc, "kernel_dir", lambda: kernels)
    assert dc.cache_key(dev) != key


def test_drapes_own_pocl_cache_is_cleared_after_a_failed_build_and_no_other(cpu, own_cache, tmp_path, monkeypatch):
    dev = cpu
    ours = dc.cache_dir() / "pocl"
    (ours / "kcache" / "ab").mkdir(parents=True)
    (ours / "kcache" / "ab" / "program.bc").write_bytes(b"half a build")
    monkeypatch.setenv("POCL_CACHE_DIR", str(ours))
    is_pocl = "portable computing language" in dev.platform.name.lower()
    assert dc.clear_pocl_cache(dev) == is_pocl
    if is_pocl:
        assert ours.is_dir() and not any(ours.iterdir())
    theirs = tmp_path / "operator-chose-this"
    (theirs / "kcache").mkdir(parents=True)
    monkeypatch.setenv("POCL_CACHE_DIR", str(theirs))
    assert not dc.clear_pocl_cache(dev)
    assert (theirs / "kcache").is_dir()


def test_the_check_leaves_no_pocl_cache_behind(cpu, own_cache, monkeypatch):
    """Each child check builds into a temporary PoCL cache that is removed afterwards, so a
    crash half-way through a build cannot leave an entry for later runs."""
    import shutil
    import tempfile
    from pathlib import Path

    dev = cpu
    # a temporary folder of this test's own: other processes' checks (a CI machine running
    # something else) make and remove their caches in the shared one meanwhile
    tmp = Path(tempfile.mkdtemp(prefix="drape-test-tmp-"))
    monkeypatch.setenv("TMPDIR", str(tmp))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    monkeypatch.setenv(dc.FAULT_ENV, "abort:wg_step")
    try:
        dc.prove(dev, fresh=True)
        assert list(tmp.glob("drape-devicecheck-pocl-*")) == []
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
