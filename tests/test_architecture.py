"""The package's house rules, checked statically on the source tree (no imports executed).

1. No library module imports ``cblrs.cli``: the CLI is a thin layer on top of the library.
2. No import cycle among cblrs modules at module level (imports inside functions or under
   ``if TYPE_CHECKING:`` are not part of the import-time graph and are ignored).
3. No module over ``MAX_LINES`` lines unless its docstring says why it stays one module: the
   docstring contains a sentence with the words "one module" (for example "It stays one module
   because ...").
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SOURCE = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SOURCE / "cblrs"
MAX_LINES = 600


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SOURCE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {_module_name(path): path for path in sorted(PACKAGE.rglob("*.py"))}


def _resolve(module: str, path: Path, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _top_level_imports(module: str, path: Path) -> set[str]:
    """cblrs modules imported when ``module`` is imported (module level, try/if bodies included)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: set[str] = set()

    def visit(statements: list[ast.stmt]) -> None:
        for statement in statements:
            if isinstance(statement, ast.Import):
                found.update(alias.name for alias in statement.names)
            elif isinstance(statement, ast.ImportFrom):
                target = _resolve(module, path, statement)
                found.add(target)
                # "from cblrs.x import y" imports cblrs.x.y when y is a submodule.
                found.update(f"{target}.{alias.name}" for alias in statement.names)
            elif isinstance(statement, ast.If) and not _is_type_checking(statement.test):
                visit(statement.body)
                visit(statement.orelse)
            elif isinstance(statement, ast.Try):
                visit(statement.body)
                for handler in statement.handlers:
                    visit(handler.body)
                visit(statement.orelse)
                visit(statement.finalbody)

    visit(tree.body)
    return {name for name in found if name in MODULES}


def _all_imports(path: Path) -> set[str]:
    """Every cblrs module named by an import anywhere in the file (functions included)."""
    module = _module_name(path)
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(_resolve(module, path, node))
    return names


def test_the_scan_sees_the_package():
    assert "cblrs.cli.main" in MODULES and "cblrs.matching" in MODULES
    assert len(MODULES) > 100


# ``cblrs.__main__`` is ``python -m cblrs``: an entry point like the console script, not library.
ENTRY_POINTS = {"cblrs.__main__"}


@pytest.mark.parametrize(
    "module",
    [name for name in MODULES if not name.startswith("cblrs.cli") and name not in ENTRY_POINTS],
)
def test_no_library_module_imports_the_cli(module):
    offending = sorted(
        name for name in _all_imports(MODULES[module])
        if name == "cblrs.cli" or name.startswith("cblrs.cli.")
    )
    assert not offending, f"{module} imports {offending}; move what it needs into the library"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative enough here)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    counter = 0

    def connect(node: str) -> None:
        nonlocal counter
        index[node] = low[node] = counter
        counter += 1
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph.get(node, ())):
            if successor not in index:
                connect(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            connect(node)
    return components


def _graph() -> dict[str, set[str]]:
    graph = {}
    for module, path in MODULES.items():
        # A package's __init__ importing its own submodules is not a cycle in practice
        # (Python runs the submodule with the package already in sys.modules), and a
        # submodule importing a sibling through the package is the same edge: drop
        # parent -> child edges so that only real module-to-module loops count.
        graph[module] = {
            name for name in _top_level_imports(module, path)
            if name != module and not name.startswith(module + ".")
        }
    return graph


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_at_module_level():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(cycle) for cycle in cycles)


def _docstring(path: Path) -> str:
    return ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""


@pytest.mark.parametrize("module", sorted(MODULES))
def test_long_modules_say_why(module):
    path = MODULES[module]
    lines = len(path.read_text(encoding="utf-8").splitlines())
    if lines <= MAX_LINES:
        return
    assert "one module" in " ".join(_docstring(path).split()), (
        f"{module} has {lines} lines (> {MAX_LINES}): split it by responsibility, or say in its "
        f"docstring why it stays one module"
    )
