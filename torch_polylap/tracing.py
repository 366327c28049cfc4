"""Where the calling code runs: eagerly, under a torch.func transform, or traced by torch.compile.

The package reads data on the host in three places: the topology cache (it keys on the faces'
content), input validation (a non-finite coordinate or a zero-area face raises an error naming
it) and the assembly's chunking.  A traced graph cannot read data, and a vmapped function
cannot branch on batched data, so each of those places asks here which mode it is in and does
the equivalent that the mode allows: :func:`require` checks a condition without a host sync
under torch.compile and across the whole batch under vmap.
"""

from __future__ import annotations

import itertools
import sys
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import torch

from ._torch_compat import (
    assert_async,
    disable_functorch,
    functorch_active,
    mark_constant_result,
    vmap_active,
)

__all__ = [
    "tracing",
    "in_functorch",
    "in_vmap",
    "functional",
    "require",
    "run_eagerly",
    "outside_transforms",
]

T = TypeVar("T")

# > 0 while run_eagerly executes a function on real values in the middle of a trace
_eager_depth = 0


def tracing() -> bool:
    """Whether torch.compile (dynamo) or ``torch.export`` is tracing the calling code.

    False inside a function that :func:`run_eagerly` runs on real values during a trace.
    """
    return torch.compiler.is_compiling() and _eager_depth == 0


# Results of functions run at trace time are kept as attributes of this module, one fresh
# name per result: the traced code reads them through a module attribute, which torch.compile
# guards on (a result evicted here fails the guard and the caller is traced again). Objects
# returned directly by an assume_constant_result function would be constants without a source,
# and methods cannot be called on those in traced code.
_PIN_LIMIT = 512
_pin_names: deque[str] = deque()
_pin_count = itertools.count()
_this_module = sys.modules[__name__]


def _pin(fn: Callable[..., Any], *args: Any) -> str:
    global _eager_depth
    _eager_depth += 1
    try:
        result = fn(*args)
    finally:
        _eager_depth -= 1
    name = f"_pinned_{next(_pin_count)}"
    setattr(_this_module, name, result)
    _pin_names.append(name)
    while len(_pin_names) > _PIN_LIMIT:
        delattr(_this_module, _pin_names.popleft())
    return name


# run at trace time, its result (the name of the pinned attribute) a constant of the graph
mark_constant_result(_pin)


def run_eagerly(fn: Callable[..., T], *args: Any) -> T:
    """``fn(*args)`` on real values, also when torch.compile traces the caller.

    Traced, ``fn`` runs once at trace time on the real arguments (tensors included) and its
    result enters the graph as a constant: for what depends on data but is fixed for a mesh
    (its topology, a pattern's transpose). ``fn`` must not depend on values that change from
    call to call without changing the objects passed to it.
    """
    if not tracing():
        with outside_transforms():
            return fn(*args)
    result: T = getattr(_this_module, _pin(fn, *args))
    return result


def in_functorch() -> bool:
    """Whether a torch.func transform (grad, vjp, jvp, jacrev, jacfwd, vmap) is active
    (eagerly: torch.compile traces transforms itself and lets the code below see plain
    tensors)."""
    return not tracing() and functorch_active()


@contextmanager
def outside_transforms() -> Iterator[None]:
    """A context for building connectivity that is cached (patterns, views, plans, layouts).

    Inside an eager torch.func transform every tensor created, even by ``torch.arange``, is
    wrapped at the transform's level. Kept in a cache, such a wrapper outlives its transform
    without storage and breaks every later host read (``data_ptr``, numpy, scipy). The context
    pauses the transforms, so what is built is plain; connectivity is never differentiated.
    """
    if in_functorch():
        with disable_functorch():
            yield
    else:
        yield


def in_vmap() -> bool:
    """Whether a ``torch.func.vmap`` is active eagerly (data cannot steer control flow)."""
    return in_functorch() and vmap_active()


def functional() -> bool:
    """Whether the caller must stay functional: traced, or under a torch.func transform.

    Then the assembly writes out of place (a vmapped value array cannot be updated in place
    from a batched one) and in one pass per degree group (a traced loop over chunks unrolls).
    """
    return tracing() or in_functorch()


@torch.library.custom_op("torch_polylap::require", mutates_args=())
def _require_op(cond: torch.Tensor, message: str) -> None:
    if not bool(cond.all()):
        raise ValueError(message)


@_require_op.register_fake
def _require_fake(cond: torch.Tensor, message: str) -> None:
    return None


def _require_vmap(
    info: object, in_dims: tuple[int | None, ...], cond: torch.Tensor, message: str
) -> tuple[None, None]:
    # every batch entry must pass; the message stays the one the caller wrote
    _require_op(cond, message)
    return None, None


_require_op.register_vmap(_require_vmap)


def require(cond: torch.Tensor, message: str) -> bool:
    """Check that every entry of the boolean tensor ``cond`` holds, in any mode.

    Eagerly outside vmap, returns ``bool(cond.all())`` (one host sync) so that the caller can
    raise an error that names the offending element.  Traced, inserts an asynchronous assertion
    into the graph (a ``RuntimeError`` with ``message`` when it fails) and returns True; under
    vmap, checks every batch entry (a ``ValueError`` with ``message``) and returns True.
    """
    if tracing():
        assert_async(cond.all(), message)
        return True
    if in_vmap():
        _require_op(cond, message)
        return True
    return bool(cond.all())
