"""The documents written from the settings table (drape.server.service.config.SETTINGS): the TOML
sample deploy/drape.toml and the README's settings section, between its two marker lines.

``python -m drape.server.service.settingsdoc`` writes both; ``--check`` writes nothing and exits 1
when either differs from the table (tests/service/test_settings.py checks the same).
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .config import CONFIG_SETTINGS, ENV_ONLY, Setting

ROOT = Path(__file__).resolve().parents[2]
TOML_PATH = ROOT / "deploy" / "drape.toml"
README_PATH = ROOT / "README.md"
COMMAND = "python -m drape.server.service.settingsdoc"
BEGIN = f"<!-- settings: written from server/service/config.py by `{COMMAND}`; edit the table, not this -->"
END = "<!-- /settings -->"
WIDTH = 100
NBSP = "\u00a0"  # a space textwrap does not break at

TOML_HEAD = f"""\
# drape serve --config deploy/drape.toml
# Written from the settings table (server/service/config.py) by
# `{COMMAND}`: edit the table, not this file.
# Every key is optional; each shows its default unless noted. Each can also be set with an
# environment variable DRAPE_<KEY> (lists comma-separated) or a flag --<key-with-dashes>; flags
# beat the environment, which beats this file. See PROTOCOL.md for what clients see.

[server]"""


def toml_value(value: Any) -> str:
    """``value`` as TOML writes it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string is a JSON string
    return repr(value)


def _groups(rows: Iterable[Setting]) -> dict[str, list[Setting]]:
    out: dict[str, list[Setting]] = {}
    for row in rows:
        out.setdefault(row.group, []).append(row)
    return out


def toml_sample() -> str:
    """deploy/drape.toml as the table writes it."""
    lines = [TOML_HEAD]
    for group, rows in _groups(CONFIG_SETTINGS).items():
        lines += ["", f"# --- {group} ".ljust(WIDTH, "-")]
        for row in rows:
            words = row.help
            if row.limits_text():
                words += " (" + row.limits_text().replace(" ", NBSP) + ")"  # kept on one line
            if row.shown != row.default:
                words += f"; default: {_text(row.default)}"
            lines.append("")
            wrapped = textwrap.wrap(words, WIDTH, initial_indent="# ", subsequent_indent="# ", break_on_hyphens=False)
            lines += [line.replace(NBSP, " ") for line in wrapped]
            line = f"{row.name} = {toml_value(row.shown)}"
            lines.append("# " + line if row.commented else line)
    return "\n".join(lines) + "\n"


def _text(value: Any) -> str:
    """A value as the documents show it: as TOML writes it, or none."""
    return "none" if value is None else toml_value(value)


#: what a setting without a range or choices takes, by its kind
KIND_WORDS = {bool: "true | false", list: "list of strings", str: "text", int: "integer", float: "number"}


def _cell(text: str) -> str:
    """``text`` in a Markdown table cell: its bars and opening angle brackets (HTML to Markdown) escaped."""
    return text.replace("|", "\\|").replace("<", "\\<")


def readme_section() -> str:
    """The README's settings section, marker lines included."""
    lines = [
        BEGIN,
        "`drape serve` takes each setting from its TOML file (`--config FILE` or `DRAPE_CONFIG`;",
        "`deploy/drape.toml` is a sample of every key), an environment variable `DRAPE_<NAME>` (lists",
        "comma-separated) or a flag `--<name-with-dashes>` (`--no-<name>` for false), flags beating the",
        "environment beating the file; `drape serve --help` says the same.",
        "",
        "| setting | default | values | what |",
        "| --- | --- | --- | --- |",
    ]
    for group, rows in _groups(CONFIG_SETTINGS).items():
        lines.append(f"| **{group}** | | | |")
        for row in rows:
            values = row.limits_text() or KIND_WORDS[row.kind]
            lines.append(f"| `{row.name}` | `{_text(row.default)}` | {_cell(values)} | {_cell(row.help)} |")
    lines += [
        "",
        "Environment only (no TOML key, no flag):",
        "",
        "| variable | default | read in | what |",
        "| --- | --- | --- | --- |",
    ]
    for row in ENV_ONLY:
        default = "" if row.default is None else f"`{_text(row.default)}`"
        lines.append(f"| `{row.env}` | {default} | `{row.read_in}` | {_cell(row.help)} |")
    lines.append(END)
    return "\n".join(lines)


def readme_with_section(readme: str) -> str:
    """``readme`` with its settings section (between the markers) written from the table."""
    head, sep, rest = readme.partition(BEGIN)
    _, sep2, tail = rest.partition(END)
    if not sep or not sep2:
        raise ValueError(f"README.md has no settings section between {BEGIN!r} and {END!r}")
    return head + readme_section() + tail


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=COMMAND, description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when a document drifted")
    args = parser.parse_args(argv)
    wanted = {TOML_PATH: toml_sample(), README_PATH: readme_with_section(README_PATH.read_text())}
    stale = [path for path, text in wanted.items() if path.read_text() != text]
    for path in stale:
        if args.check:
            print(f"{path.relative_to(ROOT)} differs from the settings table: run {COMMAND}", file=sys.stderr)
        else:
            path.write_text(wanted[path])
            print(f"wrote {path.relative_to(ROOT)}")
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())
