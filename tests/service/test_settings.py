"""The settings table (drape.server.service.config.SETTINGS) is the one declaration: the TOML
sample and the README section are what it writes, the sample loads to the values it shows, every
setting has its environment variable and flag, and every DRAPE_* variable the code reads is a row."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from drape.server.service import settingsdoc
from drape.server.service.config import CONFIG_SETTINGS, ENV_ONLY, SETTINGS, ServerConfig, add_arguments

ROOT = Path(__file__).resolve().parents[2]
FIX = f"run {settingsdoc.COMMAND} (edit the table in server/service/config.py, not the documents)"


def test_the_toml_sample_and_the_readme_section_are_written_from_the_table():
    assert (ROOT / "deploy" / "drape.toml").read_text() == settingsdoc.toml_sample(), FIX
    readme = (ROOT / "README.md").read_text()
    assert settingsdoc.readme_with_section(readme) == readme, FIX


def test_the_sample_loads_to_the_values_it_shows():
    example = ServerConfig.load(ROOT / "deploy" / "drape.toml", env={})
    for row in CONFIG_SETTINGS:
        expected = row.default if row.commented else row.shown
        if row.name != "server_id" or expected:  # "" = host-pid
            assert getattr(example, row.name) == expected, row.name


def test_every_setting_has_its_flag_environment_variable_and_help():
    names = [row.name for row in SETTINGS]
    assert len(set(names)) == len(names)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    text = parser.format_help()
    for row in CONFIG_SETTINGS:
        assert row.help and row.flag in text and row.env in text, row.name
        assert row.default is None or type(row.default) is row.kind, f"{row.name}: default of another type"
        row.check(row.default)  # every default within its own range
    for row in ENV_ONLY:
        assert row.help and row.flag is None and row.read_in, row.name
        assert row.env in (ROOT / row.read_in).read_text(), f"{row.env} is not read in {row.read_in}"


def test_every_drape_variable_the_code_reads_is_in_the_table():
    declared = {row.env for row in SETTINGS}
    files = [*(ROOT / "server").rglob("*.py"), *(ROOT / "client").glob("*.py"), *(ROOT / "tests").rglob("*.py")]
    found = {
        (m, str(path.relative_to(ROOT)))
        for path in files
        for m in re.findall(r"""["'](DRAPE_[A-Z0-9_]+)["']""", path.read_text())
    }
    missing = sorted((var, path) for var, path in found if var not in declared)
    assert not missing, f"declare these in server/service/config.py (ENV_ONLY or a setting): {missing}"
