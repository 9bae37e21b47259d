"""The kernel sources as the device builds them (drape.server.sim.opencl.device): every file in
kernels/ is part of a program and opens with a comment saying what it does; a program's text is its
files put together, so it changes when any of them changes (the drivers' program caches key on
that text), the compiler's messages name the file and line, and no file in the working directory
can stand in for a kernel file."""

from __future__ import annotations

import shutil
import uuid

import pyopencl as cl
import pytest

from drape.server.sim.opencl.device import kernel_dir, kernel_sources, program_text
from drape.server.sim.params import Features

# the files Device.program builds; the others are included
PROGRAMS = ("cloth.cl", "encode.cl", "compact.cl", "static.cl", "intercollide.cl", "meshcollide.cl")


def _kernel_files() -> set[str]:
    return {p.name for p in kernel_dir().iterdir() if p.suffix in (".cl", ".h")}


def test_every_kernel_file_is_part_of_a_program_and_says_what_it_does():
    reached = set().union(*(kernel_sources(p) for p in PROGRAMS))
    assert reached == _kernel_files()
    assert {"layout.h", "links.cl", "pack.cl", "tethers.cl"} <= set(kernel_sources("cloth.cl"))
    for name in _kernel_files():
        text = (kernel_dir() / name).read_text()
        assert text.startswith("/* "), f"kernels/{name} must open with a comment saying what it does"


def test_the_program_text_is_every_file_put_together():
    text = program_text("cloth.cl")
    assert "#include" not in text.replace("#include <", "")  # no quoted include left for the compiler
    lines = set(text.splitlines())
    for name, source in kernel_sources("cloth.cl").items():
        body = [ln for ln in source.splitlines() if not ln.lstrip().startswith("#include")]
        assert lines.issuperset(body), name
        assert f'#line 1 "{name}"' in lines


@pytest.mark.parametrize("changed", ["links.cl", "layout.h", "pack.cl", "colliders.cl"])
def test_a_changed_included_file_changes_the_program_text(tmp_path, changed):
    root = tmp_path / "kernels"
    shutil.copytree(kernel_dir(), root)
    before = program_text("cloth.cl", root)
    assert program_text("cloth.cl", root) == before == program_text("cloth.cl")  # the same files: the same text
    with open(root / changed, "a") as f:
        f.write("/* changed */\n")
    assert program_text("cloth.cl", root) != before
    assert program_text("encode.cl", root) == program_text("encode.cl")  # encode.cl includes none of them


def test_missing_and_circular_includes_are_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.cl"):
        program_text("nope.cl")
    (tmp_path / "main.cl").write_text('/* test */\n#include "absent.h"\n')
    with pytest.raises(FileNotFoundError, match=r"'absent.h'.*included by main.cl"):
        program_text("main.cl", tmp_path)
    (tmp_path / "a.h").write_text('#include "b.h"\n')
    (tmp_path / "b.h").write_text('#include "a.h"\n')
    with pytest.raises(ValueError, match="a.h -> b.h -> a.h"):
        program_text("a.h", tmp_path)


def test_a_build_reads_no_file_of_the_working_directory_and_names_the_file_of_an_error(device, tmp_path, monkeypatch):
    # a compiler looks for a quoted include in the working directory first: files there must not count
    for name in ("links.cl", "layout.h", "wind.cl"):
        (tmp_path / name).write_text('#error "the working directory\'s file was included"\n')
    monkeypatch.chdir(tmp_path)
    fresh = f"-DDRAPE_TEST_BUILD={uuid.uuid4().int % 10**9}"  # a new text for no driver cache to know
    opts = [*Features(wind=True).build_options(), "-DUSE_LOCAL=0", fresh]
    device.program(opts)  # builds
    root = tmp_path / "kernels"
    shutil.copytree(kernel_dir(), root)
    lines = (root / "wind.cl").read_text().splitlines()
    at = next(i for i, ln in enumerate(lines) if "float3 r = vel - wind;" in ln)
    lines[at] = "    float3 r = vel - no_such_name;"
    (root / "wind.cl").write_text("\n".join(lines) + "\n")
    with pytest.raises(cl.RuntimeError, match=rf"wind\.cl:{at + 1}:\d+: .*no_such_name"):
        cl.Program(device.ctx, program_text("cloth.cl", root)).build(options=opts)
