"""The libraries' import structure, read from every module's syntax tree (imports inside functions counted):
no cycle between modules or between subpackages, no private name imported from another module, and only the
two commands import the command line's modules."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("attnloop", "slam")
#: the command line's modules, and the only modules that may import them (the commands themselves)
CLI_MODULES = ("slam.cli", "slam.options")
COMMANDS = ("slam.cli", "slam.eval.cli", "attnloop.vpr.cli")  # the commands build on the flag table


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


MODULES = _modules()


def _imports(name: str) -> list[tuple[str, str | None, int]]:
    """``(module imported, name taken from it or None, line)`` for every import statement at any depth."""
    is_package = MODULES[name].name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(MODULES[name].read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package of this module, up level - 1
                pkg = name.split(".") if is_package else name.split(".")[:-1]
                base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
            out += [(base, a.name, node.lineno) for a in node.names]
    return out


def _target(base: str, taken: str | None) -> str | None:
    """The module of the libraries an import loads: ``from a.b import c`` is ``a.b.c`` when that is a module."""
    if taken is not None and f"{base}.{taken}" in MODULES:
        return f"{base}.{taken}"
    while base and base not in MODULES:  # import a.b.c of a name below a module, or outside the libraries
        base = base.rpartition(".")[0]
    return base or None


def _edges() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    for m in MODULES:
        for base, taken, _ in _imports(m):
            t = _target(base, taken)
            if t is not None and t != m:
                edges[m].add(t)
    return edges


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan's algorithm), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while not comp or comp[-1] != v:
                comp.append(stack.pop())
                on_stack.discard(comp[-1])
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def _subpackage(module: str) -> str:
    """``slam.io.tum`` -> ``slam.io``; a top-level module (``slam.threads``) is its own node."""
    return ".".join(module.split(".")[:2])


def test_the_cycle_finder_finds_a_cycle_and_the_graph_holds_known_imports():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
    edges = _edges()
    assert "slam.system" in edges["slam.pipeline"]  # a top-level import
    assert "slam.maps" in edges["slam.pipeline"]  # an import inside a function
    assert "slam.io.sequence" in edges["slam.io.tum"]


def test_no_import_cycle_between_modules():
    cycles = _cycles(_edges())
    assert cycles == [], f"modules importing each other (imports inside functions counted): {cycles}"


def test_no_import_cycle_between_subpackages():
    sub: dict[str, set[str]] = {}
    for m, targets in _edges().items():
        node = _subpackage(m)
        sub.setdefault(node, set()).update(_subpackage(t) for t in targets if _subpackage(t) != node)
    cycles = _cycles(sub)
    assert cycles == [], f"subpackages importing each other: {cycles}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_private_name_imported_from_another_module_and_no_cli_in_the_libraries(module):
    for base, taken, line in _imports(module):
        source = _target(base, taken)
        if source is None:
            continue
        where = f"{MODULES[module].relative_to(ROOT)}:{line}"
        if taken is not None and source == base and taken.startswith("_") and not taken.startswith("__"):
            pytest.fail(f"{where} imports the private name {taken} of {base}: make it public or move it")
        if module not in COMMANDS and source in CLI_MODULES:
            pytest.fail(f"{where} imports {source}, the command line's module: the libraries never do")
