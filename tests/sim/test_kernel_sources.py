"""The kernel sources as the device builds them (drape.server.sim.opencl.device): every file in
kernels/ is part of a program, opens with a comment saying what it does, and the text a program is
built from changes when any file it includes changes (the drivers' program caches key on that
text), whatever build option reaches the file."""

from __future__ import annotations

import shutil

import pytest

from drape.server.sim.opencl.device import kernel_dir, kernel_sources, program_text

PROGRAMS = ("cloth.cl", "encode.cl")  # the files Device.program builds; the others are included


def _kernel_files() -> set[str]:
    return {p.name for p in kernel_dir().iterdir() if p.suffix in (".cl", ".h")}


def test_every_kernel_file_is_part_of_a_program_and_says_what_it_does():
    reached = set().union(*(kernel_sources(p) for p in PROGRAMS))
    assert reached == _kernel_files()
    assert {"layout.h", "links.cl", "pack.cl", "tethers.cl"} <= set(kernel_sources("cloth.cl"))
    for name in _kernel_files():
        text = (kernel_dir() / name).read_text()
        assert text.startswith("/* "), f"kernels/{name} must open with a comment saying what it does"


@pytest.mark.parametrize("changed", ["links.cl", "layout.h", "pack.cl", "colliders.cl"])
def test_a_changed_included_file_changes_the_program_text(tmp_path, changed):
    root = tmp_path / "kernels"
    shutil.copytree(kernel_dir(), root)
    before = program_text("cloth.cl", root)
    assert program_text("cloth.cl", root) == before  # the same files: the same text
    assert before.startswith((root / "cloth.cl").read_text())  # line numbers stay the file's own
    with open(root / changed, "a") as f:
        f.write("\n/* changed */\n")
    after = program_text("cloth.cl", root)
    assert after != before
    assert after.startswith((root / "cloth.cl").read_text())
    assert program_text("encode.cl", root) == program_text("encode.cl")  # encode.cl includes none of them


def test_a_missing_program_source_is_an_error_and_a_missing_include_is_left_to_the_compiler(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.cl"):
        program_text("nope.cl")
    (tmp_path / "main.cl").write_text('/* test */\n#include "absent.h"\n')
    assert set(kernel_sources("main.cl", tmp_path)) == {"main.cl"}
