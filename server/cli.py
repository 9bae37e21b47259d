"""The ``drape`` command: one subcommand per job, each defined in its own module.

Each module named in SUBCOMMANDS provides ``configure(parser)`` and ``run(args) -> int``; it is
imported only when its subcommand runs, so ``drape bench`` never imports Zenoh and
``drape loadtest`` never builds kernels it does not need.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import sys

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("drape.server.tools.demo", "run a server and demo clients on loopback, write PNG frames and a GIF"),
    "serve": ("drape.server.service.daemon", "run the cloth server daemon"),
    "bench": ("drape.server.tools.bench", "solver benchmarks (the talk's table and beyond)"),
    "tradeoff": ("drape.server.tools.tradeoff", "measure speed against accuracy, write table, JSON and plot"),
    "loadtest": ("drape.server.tools.loadtest", "load-test a server with many client processes"),
    "devices": ("drape.server.tools.devices", "list OpenCL devices and the one Drape would pick"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="drape", description="Cloth of many game clients on one OpenCL device, over Zenoh.")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in SUBCOMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    # Parse the command name first, then let its module define the rest of the arguments.
    pre, rest = parser.parse_known_args(argv)
    if pre.command is None:
        parser.print_help()
        return 2
    module = importlib.import_module(SUBCOMMANDS[pre.command][0])
    cmd_parser = argparse.ArgumentParser(prog=f"drape {pre.command}", description=SUBCOMMANDS[pre.command][1])
    module.configure(cmd_parser)
    args = cmd_parser.parse_args(rest)
    level = logging.WARNING - 10 * pre.verbose if pre.verbose else logging.INFO
    logging.basicConfig(level=max(level, logging.DEBUG), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
