"""The package's import graph, read from its source with ``ast``: no circle among its modules
nor among its parts (no upward arrow), the command line imported by no library module, and no
private name taken from another subpackage.

Every import statement counts wherever it stands: at module level, under ``if TYPE_CHECKING:``
and inside functions. A function-local import still ties the two modules together (it only
defers the tie to the first call), so counting it keeps a lazy import from hiding a circle; an
import for type checking is a dependency of the module's interface, and a circle through one
would turn into an import error the day it is needed at run time. The one edge not counted is
the implicit one from a module to the packages that contain it (Python runs
``torch_polylap/__init__.py`` before any submodule): it is the same for every module, and
counting it would make every ``from torch_polylap.x import y`` in a subpackage a circle.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from conftest import ROOT

PACKAGE = ROOT / "torch_polylap"
NAME = PACKAGE.name


def _modules() -> dict[str, tuple[Path, bool]]:
    """``{dotted name: (file, is a package)}`` of every module of the package."""
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts.pop()
        modules[".".join(parts)] = (path, is_package)
    return modules


MODULES = _modules()


def _base(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from ... import`` statement imports from."""
    if not node.level:
        return node.module or ""
    parts = module.split(".")
    if not is_package:
        parts.pop()  # a module's relative imports start from its package
    parts = parts[: len(parts) - (node.level - 1)]
    return ".".join([*parts, *([node.module] if node.module else [])])


def _imports(module: str) -> list[tuple[str, str | None, int]]:
    """``(imported module, name taken from it or None, line)`` of every import statement of
    ``module`` that reaches into the package (a submodule imported by ``from pkg import sub``
    counts as the submodule)."""
    path, is_package = MODULES[module]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(a.name, None, node.lineno) for a in node.names if a.name.startswith(NAME)]
        elif isinstance(node, ast.ImportFrom):
            base = _base(module, is_package, node)
            if base != NAME and not base.startswith(NAME + "."):
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append(
                    (sub, None, node.lineno) if sub in MODULES else (base, alias.name, node.lineno)
                )
    return found


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for module in MODULES:
        for target, _, _ in _imports(module):
            if target in MODULES and target != module:
                graph[module].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle through each strongly connected component of more than one module
    (Tarjan's algorithm, iterative), or of one module that imports itself."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1 or node in graph[node]:
                    components.append(sorted(component))
    return components


def test_the_reader_sees_imports_of_every_kind():
    """The graph holds module-level, TYPE_CHECKING and function-local imports (its claims are
    only as good as this), resolved relative to the importing module."""
    graph = _graph()
    assert "torch_polylap.linalg.eigenpairs" in graph["torch_polylap.linalg"]  # relative
    assert "torch_polylap.batch" in graph["torch_polylap.nn.spectrum"]  # under TYPE_CHECKING
    assert "torch_polylap.plot" in graph["torch_polylap.cli.smooth"]  # inside a function
    assert len(graph) == len(list(PACKAGE.rglob("*.py")))


def test_the_cycle_finder_finds_circles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert sorted(_cycles(graph)) == [["a", "b", "c"], ["e"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle():
    circles = _cycles(_graph())
    assert not circles, f"import circles among the package's modules: {circles}"


def test_the_parts_are_layered():
    """No upward arrow: the parts of the package (subpackages and top-level modules, a
    subpackage's modules taken together) import each other without a circle, so they stack
    in layers (sparse below linalg below apps, ...). The root package, which imports every
    part to export its names, is left out."""
    parts: dict[str, set[str]] = {}
    for module, targets in _graph().items():
        part = _subpackage(module)
        parts.setdefault(part, set())
        if part != NAME:
            parts[part] |= {_subpackage(t) for t in targets} - {part, NAME}
    circles = _cycles(parts)
    assert not circles, f"parts of the package that import each other: {circles}"


def _reaches(graph: dict[str, set[str]], start: str) -> set[str]:
    """Every module that ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for target in graph[todo.pop()] - seen:
            seen.add(target)
            todo.append(target)
    return seen


def _part_modules(part: str) -> list[str]:
    return [m for m in MODULES if m == part or m.startswith(part + ".")]


def test_the_torch_compat_module_is_the_bottom_layer():
    """The wrappers of private torch APIs depend on torch alone, so every layer may use them."""
    assert _reaches(_graph(), f"{NAME}._torch_compat") == set()


@pytest.mark.parametrize("lower", ["kernels", "topology", "sparse", "tracing"])
def test_the_assembly_sits_above_what_it_assembles(lower):
    """The assembly imports the per-face kernels, the topology, the operator and the tracing
    helpers; none of them reaches back into it (kernels/ holds the blocks alone, sparse/ the
    operator alone)."""
    graph = _graph()
    assembly = f"{NAME}.assembly"
    assert any(
        t.startswith(f"{NAME}.{lower}") for m in _part_modules(assembly) for t in _reaches(graph, m)
    )
    for module in _part_modules(f"{NAME}.{lower}"):
        reached = {t for t in _reaches(graph, module) if t.startswith(assembly)}
        assert not reached, f"{module} reaches {sorted(reached)}"


def test_no_library_module_imports_the_command_line():
    cli = f"{NAME}.cli"
    offenders = [
        f"{module} (line {line})"
        for module in MODULES
        if module != cli and not module.startswith(cli + ".")
        for target, _, line in _imports(module)
        if target == cli or target.startswith(cli + ".")
    ]
    assert not offenders, f"library modules that import {cli}: {offenders}"


def _subpackage(module: str) -> str:
    """The first-level part of the package a module belongs to (``torch_polylap.linalg`` for
    ``torch_polylap.linalg.factor``; a top-level module is its own)."""
    return ".".join(module.split(".")[:2])


def _private_to(target: str) -> str | None:
    """The package a private module is shared within (``torch_polylap`` for
    ``torch_polylap._typing``, ``torch_polylap.linalg`` for ``torch_polylap.linalg._x``), or None
    for a public module."""
    parts = target.split(".")
    for i, part in enumerate(parts):
        if part.startswith("_") and part != "__init__":
            return ".".join(parts[:i])
    return None


def test_private_modules_are_shared_within_their_package():
    assert _private_to("torch_polylap._typing") == "torch_polylap"
    assert _private_to("torch_polylap.linalg._shared") == "torch_polylap.linalg"
    assert _private_to("torch_polylap.linalg.factor") is None
    assert _private_to("torch_polylap") is None


@pytest.mark.parametrize("module", sorted(MODULES))
def test_private_names_stay_inside_their_subpackage(module):
    """Across subpackages (and top-level modules), only public names are imported: a name with
    a leading underscore (dunders such as ``__version__`` are public) is the other side's
    business, and a private module is shared only within the package that holds it."""
    offenders = []
    for target, name, line in _imports(module):
        shared_within = _private_to(target)
        if shared_within is not None and not module.startswith(shared_within + "."):
            offenders.append(f"line {line}: {target} (private to {shared_within})")
        private_name = name is not None and name.startswith("_") and not name.endswith("__")
        if private_name and _subpackage(target) != _subpackage(module):
            offenders.append(f"line {line}: {target}.{name}")
    assert not offenders, f"{module} imports private names of other parts: {offenders}"
