"""``drape demo``: its options and its stages, each a module of its own run by name.

- ``three`` (default, server/tools/demo.py): three clients' cloths, a banner, a curtain and a cape;
- ``crossing`` (server/tools/demoscene.py): two characters whose capes brush past each other in one
  scene (protocol 1.7);
- ``body`` (server/tools/demobody.py): a cape on a running body mesh (protocol 1.8 mesh colliders).

Each stage module provides ``run(args) -> int``; the stages share the options below, and the
recorded stages (``three``, ``crossing``: client processes, their recordings rendered afterwards)
share their run (server/tools/demorun.py).
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

from .procs import require_extra

#: stage name -> (module under drape.server.tools, what it shows)
STAGES: dict[str, tuple[str, str]] = {
    "three": ("demo", "three clients' cloths: a banner in gusting wind, a curtain brushed by a ball, a walking cape"),
    "crossing": ("demoscene", "two characters whose capes brush past each other in one scene"),
    "body": ("demobody", "a cape on a running body mesh (1.8 mesh colliders)"),
}


def configure(parser: argparse.ArgumentParser) -> None:
    require_extra("server", "demo")
    require_extra("tools", "demo")
    parser.add_argument("--seconds", type=float, default=5.0, help="how long the clients run")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="where frames and the GIF go")
    parser.add_argument("--fps", type=float, default=15.0, help="frames per second recorded and in the GIF")
    parser.add_argument("--size", default="640x400", help="frame size WxH")
    parser.add_argument("--port", type=int, default=0, help="server port on 127.0.0.1 (0: a free one)")
    parser.add_argument("--solver", default=None, help="server solver (default: the server's)")
    parser.add_argument("--device", default=None, help="OpenCL device for the server")
    parser.add_argument(
        "--stage",
        default="three",
        choices=list(STAGES),
        help="; ".join(f"{name}: {what}" for name, (_, what) in STAGES.items()),
    )


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(f"drape.server.tools.{STAGES[args.stage][0]}")
    result: int = module.run(args)
    return result
