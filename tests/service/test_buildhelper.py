"""The kernel build helper (drape.server.service.cook.buildhelper): a child process builds and runs a
cloth's kernels, exits when idle and is started again when needed; a helper that cannot start
makes the server build in-process (counted), never a failure of the cloth. Counted events only."""

from __future__ import annotations

import pytest
from conftest import wait_until

from drape.server.service.cook.buildhelper import BuildHelper
from drape.server.sim.fabric import cook_grid
from drape.server.sim.params import ClothParams, Features

pytestmark = pytest.mark.opencl  # not unit (tests/conftest.py)


def test_the_helper_builds_and_runs_a_cloth_exits_when_idle_and_starts_again():
    helper = BuildHelper("workgroup", "cpu", idle_s=0.2)
    try:
        params = ClothParams(features=Features.from_names(["tethers", "colliders"]))
        assert helper.warm(cook_grid(5, 5, pinned=[0, 4]), params)
        assert (helper.runs, helper.starts, helper.failures) == (1, 1, 0)
        proc = helper._proc
        assert wait_until(lambda: not proc.is_alive()), "the idle helper did not exit"
        assert helper.warm(cook_grid(5, 5, pinned=[0, 4]), params)
        assert (helper.runs, helper.starts, helper.failures) == (2, 2, 0)
    finally:
        helper.close()
    assert helper._proc is None


def test_a_helper_that_cannot_start_is_counted_and_disabled():
    helper = BuildHelper("no-such-solver", "cpu")
    assert not helper.warm(cook_grid(3, 3, pinned=[0]), ClothParams())
    assert helper.failures == 1 and helper.disabled and helper.starts == 0
    assert not helper.warm(cook_grid(3, 3, pinned=[0]), ClothParams())  # in-process from now on
    assert helper.failures == 1
