"""The machine-readable descriptions against the Python codec: the committed JSON Schemas and C
header are what the generator writes; every vector's decoded map validates against its message's
schema (and the schema refuses what it can express of the invalid ones); the C header's packed
structs have the Python struct layout, checked by compiling a C program with ``cc``."""

from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import jsonschema
import msgpack
import pytest

from drape.client import protocol as P
from drape.client.protocol import schemagen

VECTORS = Path(__file__).resolve().parents[1] / "vectors"
sys.path.insert(0, str(VECTORS))
from generate import wire_to_json  # noqa: E402


def _message_vectors() -> list:
    out = []
    for folder in (VECTORS, *(VECTORS / f"v1.{m}" for m in range(7))):
        for g in ("submit", "control", "misc"):
            for v in json.loads((folder / f"{g}.json").read_text()):
                out.append(pytest.param(v, id=f"{folder.name}-{v['name']}"))
    return out


def _validator(message: str) -> jsonschema.Draft202012Validator:
    return jsonschema.Draft202012Validator(schemagen.schemas()[message])


def test_committed_schemas_and_header_are_generated():
    for name, s in schemagen.schemas().items():
        jsonschema.Draft202012Validator.check_schema(s)
        assert json.loads((schemagen.SCHEMA_DIR / f"{name}.json").read_text()) == json.loads(json.dumps(s)), (
            f"client/protocol/schema/{name}.json is stale: python -m drape.client.protocol.schemagen"
        )
    assert schemagen.C_HEADER.read_text() == schemagen.c_header(), "client/protocol/drape_wire.h is stale"


@pytest.mark.parametrize("vec", _message_vectors())
def test_every_vector_validates_against_its_schema(vec):
    data = bytes.fromhex(vec["hex"])
    decoded = wire_to_json(msgpack.unpackb(data, raw=False))  # bin fields in the schema's JSON form
    assert decoded == vec["value"]
    _validator(vec["message"]).validate(decoded)


def test_a_control_batch_item_validates_as_the_batch_schema_s_item():
    item = P.control_item_to_map(P.ControlRequest("a", "0" * 32, features_add=("wind",), reset=True))
    _validator("control_batch").validate({"v": [1, 2], "client": "me", "items": [item]})


SCHEMA_REFUSES = (
    "unknown_major",
    "no_version",
    "cols_as_string",
    "grid_too_large",
    "token_not_hex",
    "batch_no_items",
    "batch_items_not_array",
    "batch_empty",
    "batch_too_many",
    "batch_bad_client",
    "features_add_unknown",
    "mass_subnormal",
    "mass_below_minimum",
    "map_too_many_keys",
    "array_too_long",
)


@pytest.mark.parametrize("name", SCHEMA_REFUSES)
def test_the_schemas_refuse_the_invalid_vectors_they_can_express(name):
    (vec,) = [v for v in json.loads((VECTORS / "invalid.json").read_text()) if v["name"] == name]
    decoded = wire_to_json(msgpack.unpackb(bytes.fromhex(vec["hex"]), raw=False))
    assert not _validator(vec["message"]).is_valid(decoded)


def _python_layout(fields: tuple[tuple[str, str, str], ...]) -> list[tuple[str, int, int]]:
    """(name, offset, size) of each field, by struct (little-endian, no padding)."""
    out, codes = [], "<"
    for name, code, _ in fields:
        out.append((name, struct.calcsize(codes), struct.calcsize("<" + code)))
        codes += code
    return out


LAYOUTS = {
    "state_header": P.STATE_HEADER_FIELDS,
    "bundle_header": P.BUNDLE_HEADER_FIELDS,
    "bundle_entry": P.BUNDLE_ENTRY_FIELDS,
}


def test_c_header_declares_every_field_of_the_python_layouts():
    text = schemagen.C_HEADER.read_text()
    for struct_name, fields in LAYOUTS.items():
        body = re.search(rf"typedef struct drape_{struct_name} \{{(.*?)\}} drape_{struct_name};", text, re.S)
        assert body, struct_name
        names = re.findall(r"^\s+\w+ (\w+)(?:\[\d+\])?;", body.group(1), re.M)
        assert names == [f[0] for f in fields]
    assert f"#define DRAPE_STATE_HEADER_SIZE {P.STATE_HEADER_SIZE}" in text
    assert f"#define DRAPE_PROTOCOL_MINOR {P.PROTOCOL_MINOR}" in text


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_offsets_and_sizes_equal_the_python_struct_layout(tmp_path):
    prints = []
    for struct_name, fields in LAYOUTS.items():
        t = f"drape_{struct_name}"
        prints.append(f'printf("{struct_name} sizeof %zu\\n", sizeof({t}));')
        for name, _, _ in fields:
            prints.append(
                f'printf("{struct_name} {name} %zu %zu\\n", offsetof({t}, {name}), sizeof((({t} *)0)->{name}));'
            )
    src = tmp_path / "layout.c"
    src.write_text(
        '#include <stddef.h>\n#include <stdio.h>\n#include "drape_wire.h"\n'
        "int main(void) {\n" + "\n".join(prints) + "\nreturn 0;\n}\n"
    )
    exe = tmp_path / "layout"
    subprocess.run(
        ["cc", "-std=c11", "-Wall", "-Werror", "-I", str(schemagen.C_HEADER.parent), str(src), "-o", str(exe)],
        check=True,
    )
    got = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split("\n")
    want = []
    for struct_name, fields in LAYOUTS.items():
        want.append(f"{struct_name} sizeof {struct.calcsize('<' + ''.join(c for _, c, _ in fields))}")
        want += [f"{struct_name} {n} {off} {size}" for n, off, size in _python_layout(fields)]
    assert got[:-1] == want
    assert [line for line in want if "sizeof" in line] == [
        f"state_header sizeof {P.STATE_HEADER_SIZE}",
        f"bundle_header sizeof {P.BUNDLE_HEADER_SIZE}",
        f"bundle_entry sizeof {P.BUNDLE_ENTRY_SIZE}",
    ]
