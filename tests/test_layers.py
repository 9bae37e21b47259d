"""The house's rules, checked on the code's imports (every import counts, TYPE_CHECKING ones
included): no import circle among the modules of server/ and client/, and each layer imports only
the layers below it (client/protocol -> client -> server/sim -> server/service -> server/tools;
server/sim knows no Zenoh and no service; the client knows no server)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"server": "drape.server", "client": "drape.client"}


def _modules() -> dict[str, tuple[Path, bool]]:
    mods = {}
    for folder, pkg in PACKAGES.items():
        for f in (ROOT / folder).rglob("*.py"):
            if "rust" in f.parts or "csharp" in f.parts:
                continue
            parts = [p for p in f.relative_to(ROOT / folder).with_suffix("").parts if p != "__init__"]
            mods[".".join([pkg, *parts])] = (f, f.name == "__init__.py")
    return mods


def _imports(name: str, path: Path, is_pkg: bool, mods: dict) -> set[str]:
    """The drape modules (or external top-level names) that module ``name`` imports."""
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            for a in node.names:
                cand = f"{prefix}.{a.name}"
                out.add(cand if cand in mods else prefix)
    return out


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(m, f, pkg, mods) for m, (f, pkg) in mods.items()}


def test_no_import_circle(graph):
    edges = {m: {t for t in ts if t in graph and t != m} for m, ts in graph.items()}
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                circles.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


# layer -> prefixes it must not import
FORBIDDEN = {
    "drape.client": ("drape.server",),
    "drape.server.sim": ("drape.server.service", "drape.server.tools", "zenoh"),
    "drape.server.service": ("drape.server.tools",),
}


def test_each_layer_imports_only_those_below(graph):
    bad = [
        f"{m} imports {t}"
        for m, ts in graph.items()
        for layer, banned in FORBIDDEN.items()
        if m == layer or m.startswith(layer + ".")
        for t in ts
        if any(t == b or t.startswith(b + ".") for b in banned)
    ]
    assert not bad, "\n".join(sorted(bad))


def test_the_protocol_needs_no_sdk_zenoh_or_opencl(graph):
    """A game client or tool can use drape.client.protocol with numpy and msgpack alone."""
    banned = ("zenoh", "pyopencl", "drape.server")
    sdk = {m for m in graph if m.startswith("drape.client.") and not m.startswith("drape.client.protocol")}
    bad = [
        f"{m} imports {t}"
        for m, ts in graph.items()
        if m.startswith("drape.client.protocol")
        for t in ts
        if t in sdk or t == "drape.client" or any(t == b or t.startswith(b + ".") for b in banned)
    ]
    assert not bad, "\n".join(sorted(bad))
