"""The benchmark scripts and the examples call the library as it is: every name they import from ``attnloop``,
``slam`` or ``benchmarks`` exists, and every call of an imported function or class (or of a method of an object
such a class built in the same scope) binds to its signature.

The scripts run for minutes on real data, so the suite runs only their ``--help``; a library change that removes
a parameter or a name they use would otherwise be found only when someone runs them.
"""
from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("attnloop", "slam", "benchmarks")
SCRIPTS = sorted(str(p.relative_to(ROOT)) for d in ("benchmarks", "examples") for p in (ROOT / d).glob("*.py"))


def _absolute(module: str, level: int, path: Path) -> str:
    if not level:
        return module
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-level])
    return f"{package}.{module}" if module else package


class MissingDependency(Exception):
    """A module the script imports needs a third-party package that is not installed (an optional extra)."""


def _import(module: str, lineno: int):
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and e.name.split(".")[0] not in PACKAGES:
            raise MissingDependency(f"line {lineno}: {module} needs {e.name}") from None
        raise


def _imported(tree: ast.AST, path: Path) -> tuple[dict[str, object], list[str]]:
    """Names bound by the script's imports from :data:`PACKAGES` (at any depth) -> objects; and the problems."""
    names, problems = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = _absolute(node.module or "", node.level, path)
            if module.split(".")[0] not in PACKAGES:
                continue
            try:
                mod = _import(module, node.lineno)
            except ImportError as e:
                problems.append(f"line {node.lineno}: from {module} import ...: {e}")
                continue
            for alias in node.names:
                if not hasattr(mod, alias.name):
                    try:  # a submodule imported by name
                        names[alias.asname or alias.name] = _import(f"{module}.{alias.name}", node.lineno)
                    except ImportError:
                        problems.append(f"line {node.lineno}: {module} has no {alias.name}")
                    continue
                names[alias.asname or alias.name] = getattr(mod, alias.name)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in PACKAGES:
                    try:
                        mod = _import(alias.name, node.lineno)
                    except ImportError as e:
                        problems.append(f"line {node.lineno}: import {alias.name}: {e}")
                        continue
                    names[alias.asname] = mod if alias.asname else importlib.import_module(alias.name.split(".")[0])
    return names, problems


def _resolve(func: ast.expr, names: dict[str, object], built: dict[str, type]):
    """The object a call's function expression names, or None where it cannot be known without running."""
    if isinstance(func, ast.Name):
        return names.get(func.id)
    if isinstance(func, ast.Attribute):
        if isinstance(func.value, ast.Name) and func.value.id in built:
            cls = built[func.value.id]
            if not hasattr(cls, func.attr) and not _instance_attribute(cls, func.attr):
                raise AttributeError(f"{cls.__name__} has no attribute {func.attr}")
            return getattr(cls, func.attr, None)
        base = _resolve(func.value, names, built)
        if inspect.ismodule(base) or inspect.isclass(base):
            if not hasattr(base, func.attr):
                raise AttributeError(f"{getattr(base, '__name__', base)} has no attribute {func.attr}")
            return getattr(base, func.attr)
    return None


def _instance_attribute(cls: type, name: str) -> bool:
    """``name`` is a field of the dataclass ``cls`` or set as ``self.name`` in its source."""
    if name in getattr(cls, "__dataclass_fields__", {}):
        return True
    try:
        return f"self.{name} " in inspect.getsource(cls)
    except (OSError, TypeError):
        return True  # no source to read: assume it is there


def _check_call(call: ast.Call, target, bound_method: bool) -> str | None:
    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):  # a builtin without a signature
        return None
    params = list(sig.parameters.values())
    if bound_method and params and params[0].name in ("self", "cls"):
        sig = sig.replace(parameters=params[1:])
    starred = any(isinstance(a, ast.Starred) for a in call.args) or any(k.arg is None for k in call.keywords)
    args = [None] * sum(not isinstance(a, ast.Starred) for a in call.args)
    kwargs = {k.arg: None for k in call.keywords if k.arg is not None}
    try:
        (sig.bind_partial if starred else sig.bind)(*args, **kwargs)
    except TypeError as e:
        return f"line {call.lineno}: {ast.unparse(call.func)}(...): {e}"
    return None


def _walk_scope(scope: ast.AST):
    """The nodes of ``scope`` (a function or the module) outside the functions defined in it."""
    todo = [scope]
    while todo:
        node = todo.pop(0)
        yield node
        todo.extend(c for c in ast.iter_child_nodes(node) if not isinstance(c, (ast.FunctionDef, ast.AsyncFunctionDef)))


def _scope_problems(scope: ast.AST, names: dict[str, object]) -> list[str]:
    built: dict[str, type] = {}  # names of this scope assigned from an imported class's constructor
    problems = []
    for node in _walk_scope(scope):
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Call):
            cls = _resolve_quietly(node.value.func, names, {})
            if inspect.isclass(cls):
                built.update({t.id: cls for t in node.targets if isinstance(t, ast.Name)})
        if not isinstance(node, ast.Call):
            continue
        try:
            target = _resolve(node.func, names, built)
        except AttributeError as e:
            problems.append(f"line {node.lineno}: {e}")
            continue
        if target is None or not callable(target):
            continue
        method_of_built = (isinstance(node.func, ast.Attribute) and isinstance(node.func.value, ast.Name)
                           and node.func.value.id in built
                           and not isinstance(inspect.getattr_static(built[node.func.value.id], node.func.attr,
                                                                     None), (staticmethod, classmethod)))
        problem = _check_call(node, target, method_of_built)
        if problem:
            problems.append(problem)
    return problems


def _resolve_quietly(func, names, built):
    try:
        return _resolve(func, names, built)
    except AttributeError:
        return None


def script_problems(path: Path) -> list[str]:
    """What in ``path`` does not match the library: missing names, calls that do not bind."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names, problems = _imported(tree, path)
    scopes = [tree, *(n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)))]
    for scope in scopes:  # each function on its own: a constructor's name is known in its own function only
        problems += _scope_problems(scope, names)
    return problems


def test_a_removed_parameter_is_found(tmp_path):
    script = tmp_path / "probe.py"
    script.write_text("from slam.lie import se3_compose\nfrom attnloop.pooling import gem_regions\n"
                      "from slam.timing import StageTimer\n"
                      "def f(a, b):\n    t = StageTimer()\n    t.no_such_method()\n"
                      "    return se3_compose(a, b, c=1), gem_regions(a, 3, (1, 2), 4)\n"
                      "from slam.lie import no_such_function\n")
    problems = script_problems(script)
    assert any("se3_compose" in p and "'c'" in p for p in problems), problems
    assert any("gem_regions" in p and "too many positional" in p for p in problems), problems
    assert any("no_such_function" in p for p in problems), problems
    assert any("no_such_method" in p for p in problems), problems
    assert len(problems) == 4, problems


@pytest.mark.parametrize("script", SCRIPTS)
def test_library_calls_bind(script):
    try:
        problems = script_problems(ROOT / script)
    except MissingDependency as e:
        pytest.skip(f"{script}: {e} (an optional extra)")
    assert problems == []
