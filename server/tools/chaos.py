"""``drape chaos``: the fault and abuse suite of issue 11 ("No cloth lost, no one let in").

Scenario by scenario it starts its own ``drape serve`` processes on 127.0.0.1 (PoCL's CPU device),
good game clients in their own processes (the SDK, one small cloth each, every state recorded),
measures a baseline, applies one fault or abuse, and measures

- the good clients' state rate, states lost and worst gap between states; the server's tick rate
  and missed ticks (from its stats publications);
- the server's RSS (psutil) before, at peak and after; error replies by code; lines containing
  'Traceback' (and warnings) in the server's log;

and judges each against the issue's targets: good clients at 60 Hz with 0 missed ticks and nothing
lost, 0 tracebacks, RSS back within 10 %, fuzz: 0 ``internal`` replies and a valid submit still
served; kill: 100 % of the killed servers' cloths back within 1 s and 0 lost over ``--kills``
kills of ``--kill-servers`` servers (the game clients' cloths placed by load, each killed server
restarted ``--kill-gap`` s later); pause: 100 % back within 1 s of SIGCONT. Failures are
reported as failures (exit status 1). Missed ticks, lost states and gaps over 50 ms are judged
where they are the server's own: not in stats periods where other processes took the machine
(:class:`.chaos_hostload.HostLoad`; the raw counts are reported beside). ``--auth tls|tcp`` runs
the one-server scenarios in the authenticated deployment (:mod:`.chaos_router`).

Scenarios (``drape chaos --list``): fuzz, flood-ids, big-submit, big-cook, tiny-mass,
new-features, cold-burst, big-mesh (builds and big preparations, issue 26: :mod:`.chaos_builds`),
heavy-control, big-beside-small, share (admission, issue 26: :mod:`.chaos_admission`), acl-placement
(:mod:`.chaos_placement`), kill, pause.
Each is bounded in messages and seconds; a server passing
``--rss-limit-mb`` is killed (and that is a failure). Prints a table; ``--json`` writes the report.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import shlex
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ..service.config import ServerConfig
from . import chaos_admission, chaos_builds, chaos_failover, chaos_faults, chaos_hostload, chaos_placement, chaos_window
from .chaos_faults import Context

#: Every scenario, by the name the command takes, in the order ``drape chaos`` runs them.
SCENARIOS: dict[str, Callable[[Context], dict[str, Any]]] = {
    "fuzz": chaos_faults.fuzz,
    "flood-ids": chaos_faults.flood_ids,
    "big-submit": chaos_faults.big_submit,
    "big-cook": chaos_faults.big_cook,
    "tiny-mass": chaos_faults.tiny_mass,
    "new-features": chaos_faults.new_features,
    "cold-burst": chaos_builds.cold_burst,
    "big-mesh": chaos_builds.big_mesh,
    "heavy-control": chaos_admission.heavy_control,
    "big-beside-small": chaos_admission.big_beside_small,
    "share": chaos_admission.share,
    "acl-placement": chaos_placement.acl_placement,
    "kill": chaos_failover.kill,
    "pause": chaos_failover.pause,
}

log = logging.getLogger(__name__)


def run_scenarios(names: list[str], ctx: Context) -> dict[str, Any]:
    """Run the named scenarios one after the other; a scenario that raises is a failure too."""
    report: dict[str, Any] = {
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "load_avg": os.getloadavg(),
        },
        "context": {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(ctx).items()},
        "scenarios": {},
    }
    for name in names:
        log.info("chaos: %s", name)
        t0 = time.monotonic()
        try:
            result = SCENARIOS[name](ctx)
        except Exception as e:  # the suite reports, it does not stop at the first broken scenario
            log.exception("scenario %s failed to run", name)
            result = {"fails": [f"scenario did not run to the end: {type(e).__name__}: {e}"], "error": repr(e)}
        result["wall_s"] = round(time.monotonic() - t0, 1)
        result["passed"] = not result["fails"]
        report["scenarios"][name] = result
        log.info("chaos: %s %s %s", name, "PASS" if result["passed"] else "FAIL", "; ".join(result["fails"]))
    report["passed"] = all(r["passed"] for r in report["scenarios"].values())
    report["judging"] = chaos_window.judging()
    return report


COLUMNS = (
    ("scenario", 13),
    ("verdict", 7),
    ("base Hz/missed", 14),
    ("good Hz", 8),
    ("missed/own", 10),
    ("lost", 6),
    ("gap ms", 8),
    ("tb", 4),
    ("RSS MB before>after", 20),
    ("errors", 30),
)


def _cell(r: dict[str, Any], key: str) -> str:
    v = r.get(key)
    return "-" if v is None else str(v)


def format_table(report: dict[str, Any]) -> str:
    lines = ["  ".join(h.ljust(w) for h, w in COLUMNS)]
    for name, r in report["scenarios"].items():
        errors = ",".join(f"{k}:{v}" for k, v in (r.get("errors") or {}).items())
        rss = f"{_cell(r, 'rss_before_mb')}>{_cell(r, 'rss_after_mb')}"
        b = r.get("baseline") or {}
        base = f"{_cell(b, 'good_rate_hz')}/{_cell(b, 'missed_ticks')}" if b else "-"
        cells = [
            name,
            ("PASS" if r["passed"] else "FAIL") + ("~" if r.get("quiet_periods") == 0 else ""),
            base,
            _cell(r, "good_rate_hz"),
            f"{_cell(r, 'missed_ticks')}/{_cell(r, 'missed_ticks_own')}",
            _cell(r, "good_lost"),
            _cell(r, "good_worst_gap_ms"),
            _cell(r, "tracebacks"),
            rss,
            errors[:30],
        ]
        lines.append("  ".join(c.ljust(w) for c, (_, w) in zip(cells, COLUMNS, strict=True)))
    lines.append(
        "(base: the good client and missed ticks before the abuse, the machine's own noise; missed/own: "
        "missed ticks, and those in stats periods where other processes took under "
        f"{chaos_hostload.MACHINE_BUSY} cores (judged); gap: worst gap between a good client's states; "
        "tb: tracebacks in the server log; ~: no stats period quiet enough to judge missed ticks, lost states "
        "and gaps: other processes took the machine throughout)"
    )
    lines.append("")
    for name, r in report["scenarios"].items():
        for f in r["fails"]:
            lines.append(f"{name}: FAIL {f}")
    lines.append(f"overall: {'PASS' if report['passed'] else 'FAIL'}")
    return "\n".join(lines)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = "Judging: " + chaos_window.judging()["rule"] + " (docs/reliability.md 1)."
    parser.add_argument(
        "scenarios", nargs="*", metavar="SCENARIO", help=f"scenarios to run (default: all): {', '.join(SCENARIOS)}"
    )
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    parser.add_argument("--json", metavar="FILE", help="write the report as JSON")
    parser.add_argument("--out", metavar="DIR", help="server logs go here (default: a temporary directory)")
    parser.add_argument("--seconds", type=float, default=5.0, help="measured window after an abuse (default 5)")
    parser.add_argument("--baseline", type=float, default=2.0, help="undisturbed window before it (default 2)")
    parser.add_argument("--fuzz-count", type=int, default=2000, help="fuzz: malformed messages (default 2000)")
    parser.add_argument("--flood-ids", type=int, default=2000, help="flood-ids: client ids (default 2000)")
    parser.add_argument("--pause-seconds", type=float, default=20.0, help="pause: SIGSTOP length (default 20)")
    parser.add_argument(
        "--max-message-bytes",
        type=int,
        default=8 << 20,
        help="the servers' max_message_bytes, the fuzzer's largest message (default 8 MiB)",
    )
    parser.add_argument(
        "--rss-limit-mb", type=float, default=4096.0, help="kill a server whose RSS passes this (default 4096)"
    )
    parser.add_argument("--grace-period", type=float, default=5.0, help="the servers' grace period (default 5)")
    parser.add_argument(
        "--program-idle-s",
        type=float,
        default=ServerConfig.program_idle_s,
        help="the servers' program_idle_s; fuzz measures RSS after grace period + this + 3 s "
        f"(default {ServerConfig.program_idle_s})",
    )
    parser.add_argument("--seed", type=int, default=1, help="fuzz seed (default 1)")
    parser.add_argument("--kill-servers", type=int, default=2, help="kill: servers, 2-4 (default 2)")
    parser.add_argument("--kills", type=int, default=1, help="kill: kills one after the other (default 1)")
    parser.add_argument(
        "--kill-gap", type=float, default=1.0, help="kill: seconds before a killed server restarts (default 1)"
    )
    parser.add_argument(
        "--auth",
        choices=("tls", "tcp"),
        default="",
        help="run each scenario's server and clients behind an authenticated ACL router (drape acl's "
        "configuration, user/password, over TLS or TCP; servers with --identity keys): the documented "
        "deployment, for the scenarios built on one server and its good client (not fuzz, flood-ids, kill, pause)",
    )
    parser.add_argument(
        "--serve-args",
        default="",
        metavar="ARGS",
        help="extra `drape serve` arguments for every server, e.g. --serve-args=--no-admission",
    )


def run(args: argparse.Namespace) -> int:
    if args.list:
        for name, fn in SCENARIOS.items():
            print(f"{name:13s} {(fn.__doc__ or '').strip().splitlines()[0]}")
        return 0
    names = args.scenarios or list(SCENARIOS)
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        log.error("unknown scenario(s) %s; choose from %s", unknown, list(SCENARIOS))
        return 2
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="drape-chaos-"))
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(
        out=out,
        seconds=args.seconds,
        baseline_s=args.baseline,
        fuzz_count=args.fuzz_count,
        flood_ids=args.flood_ids,
        pause_s=args.pause_seconds,
        max_message_bytes=args.max_message_bytes,
        rss_limit_mb=args.rss_limit_mb,
        seed=args.seed,
        grace_period=args.grace_period,
        program_idle_s=args.program_idle_s,
        serve_args=tuple(shlex.split(args.serve_args)),
        kill_servers=args.kill_servers,
        kills=args.kills,
        kill_gap=args.kill_gap,
        auth=args.auth,
    )
    report = run_scenarios(names, ctx)
    print(format_table(report))
    print(f"server logs: {out}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2, default=str) + "\n")
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    _p = argparse.ArgumentParser(prog="drape chaos", description=__doc__.splitlines()[0])
    configure(_p)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    sys.exit(run(_p.parse_args()))
