"""The unit marker is enforced, not remembered: in a unit test, opening Zenoh or OpenCL fails the
test, in its own process and in a Python child it starts (tests/conftest.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def test_this_test_is_a_unit_test(request):
    assert request.node.get_closest_marker("unit") is not None


@pytest.mark.parametrize(
    "module, call", [("zenoh", "zenoh.open(zenoh.Config())"), ("pyopencl", "pyopencl.get_platforms()")]
)
def test_a_unit_test_cannot_open_zenoh_or_opencl_itself_or_in_a_child(module, call):
    mod = pytest.importorskip(module)
    with pytest.raises(pytest.fail.Exception, match="a unit test opened"):
        eval(call, {module: mod})
    child = subprocess.run([sys.executable, "-c", f"import {module}; {call}"], capture_output=True, text=True)
    assert child.returncode == 97 and "unit guard" in child.stderr, child.stderr
