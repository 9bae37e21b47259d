"""The ``drape`` command: one subcommand per job, each defined in its own module.

Each module named in SUBCOMMANDS provides ``configure(parser)`` and ``run(args) -> int``; it is
imported only when its subcommand runs, so ``drape bench`` never imports Zenoh and
``drape loadtest`` never builds kernels it does not need.

Logging is configured here for every subcommand (drape.server.service.process.logs): ``--log-format
text|json`` and ``--log-level`` before the subcommand name, or ``DRAPE_LOG_FORMAT`` /
``DRAPE_LOG_LEVEL``; ``drape serve`` also takes them after its name and from its TOML file
(``log_format``, ``log_level``), like every other setting of the server.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from drape.server import pip_hint, version
from drape.server.service.process import logs

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("drape.server.tools.demostages", "run a server and demo clients on loopback, write PNG frames and a GIF"),
    "serve": ("drape.server.service.process.daemon", "run the cloth server daemon"),
    "top": ("drape.server.tools.top", "live view of the servers on a Zenoh network, from their stats"),
    "bench": ("drape.server.tools.bench", "solver benchmarks (the talk's table and beyond)"),
    "tradeoff": ("drape.server.tools.tradeoff", "measure speed against accuracy, write table, JSON and plot"),
    "loadtest": ("drape.server.tools.loadtest", "load-test a server with many client processes"),
    "devices": ("drape.server.tools.devices", "list OpenCL devices and the one Drape would pick"),
    "chaos": (
        "drape.server.tools.chaos",
        "fault and abuse suite: fuzz, floods, heavy cloths, kill and pause (docs/reliability.md)",
    ),
    "acl": ("drape.server.tools.acl", "generate the Zenoh router's access control from a users file"),
}
#: Subcommands that open Zenoh sessions: their Zenoh log level is set before they do.
ZENOH_COMMANDS = ("demo", "serve", "top", "loadtest")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog="drape", description="Cloth of many game clients on one OpenCL device, over Zenoh."
    )
    parser.add_argument("--version", action=_Version, nargs=0, help="print Drape's and its wire protocol's versions")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    parser.add_argument(
        "--log-format",
        choices=logs.LOG_FORMATS,
        default=None,
        help="log lines as text or JSON objects, one a line (default: $DRAPE_LOG_FORMAT or text)",
    )
    parser.add_argument(
        "--log-level",
        type=str.lower,
        choices=logs.LOG_LEVELS,
        default=None,
        help="lowest level logged (default: $DRAPE_LOG_LEVEL or info)",
    )
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
    fmt, level, server_id = _log_settings(pre, args)
    try:
        logs.setup(fmt, level, server_id=server_id, zenoh_level="error" if pre.command in ZENOH_COMMANDS else None)
    except ValueError as e:
        print(f"drape: {e}", file=sys.stderr)
        return 2
    try:
        return int(module.run(args) or 0)
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] in ("pyopencl", "pocl_binary_distribution"):
            print(
                f"drape {pre.command} needs the 'server' extra ({e.name} is missing): {pip_hint('server')}",
                file=sys.stderr,
            )
            return 2
        raise


class _Version(argparse.Action):
    """``drape --version``: the distribution's version and the wire protocol's (imported only then:
    the protocol package brings numpy and msgpack)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # type: ignore[no-untyped-def]
        from drape.client.protocol.keys import PROTOCOL_VERSION

        major, minor = PROTOCOL_VERSION
        print(f"drape {version()} (protocol {major}.{minor})")
        parser.exit()


def _log_settings(pre: argparse.Namespace, args: argparse.Namespace) -> tuple[str, str, str | None]:
    """(format, level, server id): flags after the subcommand > flags before it > (serve: its
    configuration, i.e. environment and TOML file) > DRAPE_LOG_* > text, info (-v info, -vv debug)."""
    env = os.environ
    fmt = getattr(args, "log_format", None) or pre.log_format
    level = getattr(args, "log_level", None) or pre.log_level
    if level is None and pre.verbose:
        level = "debug" if pre.verbose >= 2 else "info"
    server_id = None
    if hasattr(args, "log_format") and hasattr(args, "config"):  # a ServerConfig command (serve)
        from drape.server.service.config import from_args

        args.log_format, args.log_level = fmt, level
        try:
            cfg = from_args(args)
            fmt, level, server_id = cfg.log_format, cfg.log_level, cfg.server_id
        except (OSError, ValueError):
            pass  # the subcommand reports the bad configuration itself
    fmt = fmt or env.get("DRAPE_LOG_FORMAT") or "text"
    level = level or env.get("DRAPE_LOG_LEVEL") or "info"
    return fmt, level, server_id


if __name__ == "__main__":
    sys.exit(main())
