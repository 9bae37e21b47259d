"""The program cache gives back what no one uses (drape.server.sim.opencl.device): programs not
pinned and not asked for within ``idle_s`` are released, with their kernels; a kernel someone still
holds keeps working; asking again builds the program again. Time is passed in, never waited for."""

from __future__ import annotations

import time

import numpy as np
import pyopencl as cl
import pytest

from drape.server.sim.opencl.device import Device
from drape.server.sim.params import Features

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)


def _options(tag: int) -> list[str]:
    return [*Features().build_options(), "-DUSE_LOCAL=0", f"-DDRAPE_TEST_RELEASE={tag}"]


def test_idle_programs_are_released_pinned_and_recent_ones_kept_and_released_ones_rebuilt():
    dev = Device("cpu")
    base = _options(0)
    dev.kernel(base, "pack_rows")
    assert dev.pin() == 1  # the warm-up's programs stay for good
    a, b = _options(1), _options(2)
    held = dev.kernel(a, "pack_rows")
    dev.kernel(b, "pack_rows")
    assert dev.release_idle(3600.0) == 0  # both were just asked for
    builds = len(dev.builds)

    assert dev.release_idle(1800.0, now=time.monotonic() + 900.0) == 0  # used 15 min ago: kept
    assert dev.release_idle(1800.0, now=time.monotonic() + 1800.0) == 2  # 30 min: both released
    assert dev.released == 2 and not dev.built(a) and not dev.built(b) and dev.built(base)
    assert dev.program_count == 1

    # the released program's kernel, still held, runs (OpenCL counts references)
    n = 3
    src = cl.Buffer(dev.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=np.arange(n, dtype=np.int32))
    pts = np.arange(4 * n, dtype=np.float32)
    frm = cl.Buffer(dev.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=pts)
    out = cl.Buffer(dev.ctx, cl.mem_flags.WRITE_ONLY, 3 * n * 4)
    held(dev.queue, (64,), (64,), np.int32(n), src, frm, out)
    got = np.empty(3 * n, np.float32)
    cl.enqueue_copy(dev.queue, got, out)
    np.testing.assert_array_equal(got, pts.reshape(n, 4)[:, :3].ravel())

    dev.kernel(a, "pack_rows")  # asked again: built again
    assert dev.built(a) and len(dev.builds) == builds + 1
    assert dev.release_idle(0.0, now=time.monotonic() + 1.0) == 1  # a again; base is pinned
    assert dev.built(base) and dev.released == 3


def test_release_idle_with_nothing_built_since_pin_releases_nothing():
    dev = Device("cpu")
    dev.kernel(_options(0), "pack_rows")
    dev.pin()
    assert dev.release_idle(0.0, now=time.monotonic() + 1e6) == 0 and dev.released == 0
