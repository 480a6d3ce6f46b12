"""The package's shape stays a map: size limits, no import cycle, no reach-in to another module's private names.

Static checks on the source (``ast``), so they run in milliseconds: every class of ``windowvo/`` is at most
400 lines and every function at most 60; the import graph of the package's modules (function-level imports
included, ``if TYPE_CHECKING:`` blocks left out since they never run) has no cycle; no module imports a
``_private`` name from another module.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "windowvo"
MAX_CLASS_LINES = 400
MAX_FUNCTION_LINES = 60


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST):
    """Every import statement that runs (at module level or inside functions), TYPE_CHECKING blocks left out."""
    stack = [tree]
    while stack:
        node = stack.pop()
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child):
                stack.extend(child.orelse)
                continue
            if isinstance(child, (ast.Import, ast.ImportFrom)):
                yield child
            stack.append(child)


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _edges() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (a name that is a submodule counts as that module)."""
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module, path in MODULES.items():
        for node in _imports(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                target = _resolve(module, path, node)
                targets = [f"{target}.{a.name}" if f"{target}.{a.name}" in MODULES else target for a in node.names]
            graph[module].update(t for t in targets if t in MODULES and t != module)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of the graph (as a path that returns to its start), or None."""
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return path[path.index(n):] + [n]
            if n not in state and (found := visit(n)) is not None:
                return found
        path.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)) is not None:
            return found
    return None


def test_no_class_over_400_and_no_function_over_60_lines():
    too_long = []
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            n = (node.end_lineno or node.lineno) - node.lineno + 1 if hasattr(node, "lineno") else 0
            if isinstance(node, ast.ClassDef) and n > MAX_CLASS_LINES:
                too_long.append(f"class {module}.{node.name}: {n} lines")
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and n > MAX_FUNCTION_LINES:
                too_long.append(f"function {module}.{node.name}: {n} lines")
    assert not too_long, "\n".join(too_long)


def test_no_import_cycle():
    cycle = find_cycle(_edges())
    assert cycle is None, " -> ".join(cycle or [])


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_private_name_imported_from_another_module():
    reach_ins = []
    for module, path in MODULES.items():
        for node in _imports(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        reach_ins.append(f"{module} imports {a.name} from {_resolve(module, path, node)}")
            else:
                reach_ins += [f"{module} imports {a.name}" for a in node.names
                              if any(p.startswith("_") and not p.startswith("__") for p in a.name.split("."))]
    assert not reach_ins, "\n".join(reach_ins)


def test_every_module_says_what_it_owns():
    bare = [m for m, p in MODULES.items() if ast.get_docstring(ast.parse(p.read_text())) is None]
    assert not bare, f"modules without a docstring: {bare}"


def test_every_relative_import_names_a_module_of_the_package():
    """A relative import inside a function runs only when called: one that points nowhere (a module moved to
    another folder) must fail here, not in a user's run."""
    broken = []
    for module, path in MODULES.items():
        for node in _imports(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level > 0:
                target = _resolve(module, path, node)
                if target not in MODULES:
                    broken.append(f"{module}: from {'.' * node.level}{node.module or ''} -> {target}")
    assert not broken, "\n".join(broken)
