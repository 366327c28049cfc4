"""Every private torch API the package touches, each wrapped once, with why it is needed.

torch offers no public way to do the few things below (or offers one only in versions newer
than the oldest the package supports), so the package reaches into its internals here and
nowhere else: a torch release that moves one of them breaks this module alone, and
``tests/project/test_torch_compat.py`` checks with an AST scan that no other module names a private
torch attribute or module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

import torch

__all__ = [
    "assert_async",
    "capture_dynamic_output_shape_ops",
    "data_dependent_size",
    "disable_current_modes",
    "disable_functorch",
    "disable_torch_function_subclass",
    "forward_ad_active",
    "functorch_active",
    "functorch_unwrapped",
    "make_wrapper_subclass",
    "mark_constant_result",
    "sparse_internal_accessors",
    "version_counter",
    "vmap_active",
]


# --- tensor subclasses (the SparseOperator type) ---------------------------------------------


def make_wrapper_subclass(
    cls: type, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device
) -> Any:
    """A tensor of type ``cls`` with ``shape``, ``dtype`` and ``device`` but no storage.

    Why: the operator is a tensor that holds other tensors (its pattern and value array);
    torch's wrapper-subclass constructor is the only way to make one, and torch's own
    subclasses (FakeTensor, DTensor, NestedTensor) use it too.
    """
    return torch.Tensor._make_wrapper_subclass(
        cls, shape, dtype=dtype, device=device, requires_grad=False
    )


def disable_torch_function_subclass() -> AbstractContextManager[Any]:
    """A context in which torch functions skip the subclasses' ``__torch_function__``.

    Why: the operator answers shape and metadata queries (and torch.compile's tracer's
    inspections) with torch's own implementation on the wrapper, which would otherwise route
    back into its ``__torch_function__``; ``torch.Tensor.__torch_function__`` itself uses this
    context.
    """
    return torch._C.DisableTorchFunctionSubclass()


def sparse_internal_accessors() -> dict[str, Callable[..., Any]]:
    """The underscore accessors of torch sparse tensors: ``{"_values": Tensor._values, ...}``.

    Why: torch's own sparse code (and libraries written against torch sparse tensors) calls
    ``_values()``, ``_indices()`` and ``_nnz()``; the operator answers them as it answers
    ``values()``, ``indices()`` and the number of stored entries.
    """
    return {
        "_values": torch.Tensor._values,
        "_indices": torch.Tensor._indices,
        "_nnz": torch.Tensor._nnz,
    }


def version_counter(t: torch.Tensor) -> int:
    """The version counter of ``t``, which every in-place write increments.

    Why: the topology cache (keyed on a faces tensor) and the solver cache (keyed on an
    operator's values) must notice in-place edits; torch exposes no public counter.
    """
    return int(t._version)


# --- torch.compile ---------------------------------------------------------------------------


def mark_constant_result(fn: Callable[..., Any]) -> None:
    """Mark ``fn`` so that torch.compile runs it at trace time and keeps its result constant.

    Why: this is what ``torch._dynamo.assume_constant_result`` does (torch 2.1 to 2.13), without
    importing ``torch._dynamo`` at import time: that import alone takes about a second in every
    process (DataLoader workers, the command line), whether or not it ever compiles.
    """
    fn._dynamo_marked_constant = True  # type: ignore[attr-defined]


def assert_async(cond: torch.Tensor, message: str) -> None:
    """An assertion inside a traced graph that ``cond`` (a 0-dim bool tensor) holds.

    Why: a traced graph cannot read ``cond`` on the host; ``torch._assert_async`` is the op
    that torch.compile keeps in the graph (``torch._check`` needs a host value).
    """
    torch._assert_async(cond, message)


def capture_dynamic_output_shape_ops() -> bool:
    """Whether torch.compile may trace operators whose output shape depends on the data.

    Why: the union of two unrelated sparsity patterns has such a size; without the setting
    the operator refuses it with a message that names the setting, instead of torch's graph
    break deep inside. Read only while tracing, when ``torch._dynamo`` is loaded already.
    """
    import torch._dynamo

    return bool(torch._dynamo.config.capture_dynamic_output_shape_ops)


def data_dependent_size(ctx: Any) -> Any:
    """A new size symbol for a custom operator's fake kernel (``ctx`` from
    ``torch.library.get_ctx()``): ``ctx.new_dynamic_size()``, also without ``fullgraph=True``.

    Why: ``new_dynamic_size`` refuses outside a full graph unless
    ``capture_dynamic_output_shape_ops`` is set, and torch.compile then breaks the graph at
    the operator: a step that builds the operators and calls ``torch.autograd.grad`` loses its
    gradient path at that break. The mesh's topology operator has such sizes (stored entries),
    which the rest of the graph handles as symbols; this allocates the symbol the way
    ``new_dynamic_size`` does, without its check.
    """
    from torch._library.fake_impl import allocate_size

    shape_env = ctx._shape_env
    if shape_env is None:
        return ctx.new_dynamic_size()  # raises torch's own error
    return allocate_size(shape_env, 0)


def disable_current_modes() -> AbstractContextManager[Any]:
    """A context in which torch's active dispatch modes (the tracer's fake mode) are off.

    Why: whether one operator's pattern contains another's is decided on the real index
    tensors kept by the pattern registry, also while the tracer propagates fake tensors.
    """
    from torch.utils._python_dispatch import _disable_current_modes

    context: AbstractContextManager[Any] = _disable_current_modes()
    return context


# --- torch.func and forward-mode AD ------------------------------------------------------------


def functorch_active() -> bool:
    """Whether a torch.func transform (grad, vjp, jvp, jacrev, jacfwd, vmap) is active.

    Why: under a transform the assembly must stay out of place and the topology lookup must
    read plain tensors; torch has no public query for the transform stack.
    """
    return torch._C._functorch.peek_interpreter_stack() is not None


def vmap_active() -> bool:
    """Whether one of the active torch.func transforms is ``vmap`` (data cannot steer control
    flow there). Why: as for :func:`functorch_active`."""
    from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters

    vmap = torch._C._functorch.TransformType.Vmap
    return any(i.key() == vmap for i in retrieve_all_functorch_interpreters())


@contextmanager
def disable_functorch() -> Iterator[None]:
    """A context in which torch.func's transforms are paused.

    Why: the faces are read on the host (the cache's stamp, the topology build); inside a
    transform their wrapped tensors have no storage to read, and connectivity is never
    differentiated.
    """
    with torch._C._DisableFuncTorch():
        yield


def functorch_unwrapped(t: torch.Tensor, refuse_batched: str) -> torch.Tensor:
    """The plain tensor under torch.func's wrappers of ``t``; ``ValueError(refuse_batched)``
    when a wrapper is a vmap batch.

    Why: inside a transform tensor arguments are wrapped without storage, but the faces'
    content is that of the plain tensor, which the topology cache keys on.
    """
    functorch = torch._C._functorch
    while functorch.is_functorch_wrapped_tensor(t):
        if functorch.is_batchedtensor(t):
            raise ValueError(refuse_batched)
        t = functorch.get_unwrapped(t)
    return t


def forward_ad_active() -> bool:
    """Whether a forward-mode AD level is entered (``torch.autograd.forward_ad.dual_level``).

    Why: a product must keep its differentiable path when a tangent may flow through it, and
    forward-mode AD has no public query for an entered level.
    """
    return int(torch.autograd.forward_ad._current_level) >= 0
