"""The public API stays small: every public function and method takes at most ten parameters
and has a body of at most a hundred lines.

Knobs that belong together go into an options dataclass passed as one parameter; long functions
are split into private helpers.  The walk covers every public module of the package (no
underscore anywhere in its dotted name): the names in its ``__all__`` where it has one, else its
public callables defined in it, and the public methods (plus a hand-written ``__init__``) of the
public classes among them.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable, Iterator
from types import ModuleType

import pytest

import torch_polylap

MAX_PARAMETERS = 10
MAX_LINES = 100


def _public_modules() -> Iterator[ModuleType]:
    yield torch_polylap
    prefix = torch_polylap.__name__ + "."
    for info in pkgutil.walk_packages(torch_polylap.__path__, prefix):
        if any(part.startswith("_") for part in info.name.split(".")):
            continue
        yield importlib.import_module(info.name)


def _public_names(module: ModuleType) -> list[str]:
    names = getattr(module, "__all__", None)
    if names is not None:
        return list(names)
    return [
        name
        for name, value in vars(module).items()
        if not name.startswith("_") and getattr(value, "__module__", None) == module.__name__
    ]


def _own_source(function: object) -> Callable[..., object] | None:
    """The plain function behind ``function`` when it is written in this package, else None."""
    function = inspect.unwrap(function)
    if isinstance(function, (staticmethod, classmethod)):
        function = function.__func__
    if isinstance(function, property):
        function = function.fget
    if not inspect.isfunction(function):
        return None
    if not function.__module__.startswith(torch_polylap.__name__):
        return None
    try:
        inspect.getsourcelines(function)
    except (OSError, TypeError):  # generated (a dataclass's __init__), no source to measure
        return None
    return function


def _callables() -> dict[str, Callable[..., object]]:
    """Every public function and method, by its qualified name, each once."""
    found: dict[str, Callable[..., object]] = {}
    for module in _public_modules():
        for name in _public_names(module):
            value = getattr(module, name, None)
            if inspect.isclass(value):
                # the class's own methods and those it inherits from the package's classes
                for klass in value.__mro__:
                    if not klass.__module__.startswith(torch_polylap.__name__):
                        continue
                    for attribute, member in vars(klass).items():
                        if attribute.startswith("_") and attribute != "__init__":
                            continue
                        function = _own_source(member)
                        if function is not None:
                            found[f"{function.__module__}.{function.__qualname__}"] = function
            else:
                function = _own_source(value)
                if function is not None:
                    found[f"{function.__module__}.{function.__qualname__}"] = function
    return found


def _parameter_count(function: Callable[..., object]) -> int:
    parameters = list(inspect.signature(function).parameters.values())
    if parameters and parameters[0].name in ("self", "cls"):
        parameters = parameters[1:]
    return len(parameters)


def _line_count(function: Callable[..., object]) -> int:
    lines, _ = inspect.getsourcelines(function)
    return len(lines)


def test_the_walk_finds_the_api():
    # guards the walk itself: an empty or partial walk would pass every check below
    found = _callables()
    assert len(found) > 300
    for name in ("apps.flow.mean_curvature_flow", "fitting.chamfer_distance", "plot.plot_mesh"):
        assert f"torch_polylap.{name}" in found
    assert "torch_polylap.sparse.operator.SparseOperator.with_values" in found


@pytest.mark.parametrize(
    ("measure", "limit", "what"),
    [
        (_parameter_count, MAX_PARAMETERS, "more than {} parameters"),
        (_line_count, MAX_LINES, "longer than {} lines"),
    ],
    ids=["at_most_ten_parameters", "at_most_a_hundred_lines"],
)
def test_public_function_size(measure, limit, what):
    offenders = {
        name: count
        for name, function in _callables().items()
        if (count := measure(function)) > limit
    }
    assert not offenders, f"{what.format(limit)}: {offenders}"


def test_the_top_level_exports_at_most_sixty_names():
    """The top level is the core and the subpackages; helpers, building blocks and type aliases
    live in their own modules, so a user's ``dir(tp)`` stays readable."""
    import torch_polylap as tp

    assert len(tp.__all__) <= 60, sorted(tp.__all__)
    assert all(hasattr(tp, name) for name in tp.__all__)
