"""The protocol package exports by ``__all__``, never by ``import *``: every name the tree imports
from ``drape.client.protocol`` (or reads as ``P.<name>`` off it) is in ``__all__``, and ``__all__``
holds the protocol's own names only (no numpy, msgpack or typing)."""

from __future__ import annotations

import ast
import types
from pathlib import Path

import drape.client.protocol as P

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = "drape.client.protocol"
#: folder -> the package it is installed as (pyproject.toml's package-dir); tests import absolutely
FOLDERS = {"client": "drape.client", "server": "drape.server", "tests": "tests"}


def _module_of(path: Path, node: ast.ImportFrom) -> str:
    """The absolute module an ImportFrom in the file ``path`` names."""
    if node.level == 0:
        return node.module or ""
    parts = path.relative_to(ROOT).with_suffix("").parts
    base = [*FOLDERS[parts[0]].split("."), *parts[1:-1]]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def _names_used() -> dict[str, str]:
    """{name: a file that takes it from the protocol package}."""
    used: dict[str, str] = {}
    for folder in FOLDERS:
        for path in (ROOT / folder).rglob("*.py"):
            if "target" in path.parts:  # cargo's build output
                continue
            tree = ast.parse(path.read_text())
            aliases: set[str] = set()
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom):
                    module = _module_of(path, node)
                    for a in node.names:
                        if module == PACKAGE:
                            used.setdefault(a.name, str(path))
                        elif module == "drape.client" and a.name == "protocol":
                            aliases.add(a.asname or a.name)
                elif isinstance(node, ast.Import):
                    aliases |= {a.asname for a in node.names if a.name == PACKAGE and a.asname}
            for node in ast.walk(tree):
                if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                    used.setdefault(node.attr, str(path))
    return used


def test_every_name_the_tree_takes_from_the_protocol_is_exported():
    submodules = {p.stem for p in (ROOT / "client" / "protocol").glob("*.py")}
    missing = {n: f for n, f in _names_used().items() if n not in P.__all__ and n not in submodules and n != "__all__"}
    assert not missing, f"add these to client/protocol/__init__.py's imports and __all__: {missing}"


def test_all_holds_the_protocols_own_names_only():
    assert len(set(P.__all__)) == len(P.__all__)
    for name in P.__all__:
        obj = getattr(P, name)
        assert not isinstance(obj, types.ModuleType), name
        module = getattr(obj, "__module__", None)
        if isinstance(obj, (type, types.FunctionType)):
            assert module is not None and module.startswith(PACKAGE), f"{name} comes from {module}"
