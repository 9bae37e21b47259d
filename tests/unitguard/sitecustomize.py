"""The unit guard of a unit test's Python children: tests/conftest.py puts this folder first on
PYTHONPATH while a unit test runs, so every Python process it starts loads this file, and there
opening Zenoh (``zenoh.open``) or OpenCL (``pyopencl.get_platforms``, ``Context``,
``create_some_context``) ends the process at once with status 97 and a message: a unit test cannot
reach OpenCL or Zenoh through a child either. (Not a mock: the modules stay real, the calls refuse.)"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import os
import sys
from typing import Any

STATUS = 97
REFUSED = {"zenoh": ("open",), "pyopencl": ("get_platforms", "Context", "create_some_context")}


def _refuse(module: str, name: str) -> Any:
    def refuse(*args: Any, **kwargs: Any) -> None:
        sys.stderr.write(
            f"unit guard: a child of a unit test called {module}.{name}; mark the test's module "
            "pytest.mark.opencl or pytest.mark.zenoh (tests/conftest.py)\n"
        )
        sys.stderr.flush()
        os._exit(STATUS)

    return refuse


class _Finder(importlib.abc.MetaPathFinder):
    """Finds ``zenoh`` and ``pyopencl`` as usual, then replaces the calls that open them."""

    def find_spec(self, fullname: str, path: Any, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in REFUSED:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        loader = spec.loader if spec is not None else None
        if loader is None or not hasattr(loader, "exec_module"):
            return spec
        run = loader.exec_module

        def exec_module(module: Any) -> None:
            run(module)
            for name in REFUSED[fullname]:
                setattr(module, name, _refuse(fullname, name))

        loader.exec_module = exec_module  # type: ignore[method-assign]
        return spec


sys.meta_path.insert(0, _Finder())
