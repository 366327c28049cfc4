"""``SparseOperator``: a sparse matrix as a torch tensor, O(nnz) gradients under torch algebra.

``L`` and ``M0`` are returned as :class:`SparseOperator`: a :class:`torch.Tensor` subclass that
holds a :class:`~torch_polylap.sparse.pattern.SparsityPattern` and a differentiable value array.
What a user writes with it in plain torch -- ``L @ X``, ``torch.mm``, ``torch.sparse.mm``,
``M0 + t * L``, ``L - s * M0``, ``-L``, ``L / 2``, ``L.T``, ``L.to(torch.float32)`` -- is routed by
``__torch_function__`` to the products of :mod:`torch_polylap.sparse.autograd` or to arithmetic on
the value array, so gradients reach the vertices (and a learnable ``lam``) at O(nnz) memory.
An operation that has no O(nnz) gradient raises :class:`UnsupportedOperation` naming it and the
alternative,
instead of silently building a dense ``V x V`` matrix.

Why a wrapper subclass and not a torch sparse tensor: torch's sparse tensors cannot be subclassed
(``as_subclass`` fails on CSR and COO), their autograd materializes dense gradients, and any torch
op on them drops whatever link a library keeps to the differentiable values.  The wrapper reports
the sparse layout it stores (``torch.sparse_csr``: sorted CSR indices) while its storage is the
pattern and value array; nothing reaches torch's dispatcher with it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any, SupportsIndex

import torch

from .._torch_compat import (
    disable_current_modes,
    disable_torch_function_subclass,
    make_wrapper_subclass,
)
from ..tracing import run_eagerly, tracing
from .pattern import SparsityPattern

__all__ = [
    "HANDLERS",
    "PASSTHROUGH",
    "SparseOperator",
    "UnsupportedOperation",
    "is_operator",
    "operator_on",
]

# What __torch_function__ routes: torch function -> handler, and the functions that run on the
# wrapper as on any tensor (metadata). Filled by :mod:`.dispatch`, whose handlers need this
# type; the package imports it, so the table is complete before any operator exists.
HANDLERS: dict[Callable[..., Any], Callable[..., Any]] = {}
PASSTHROUGH: set[Callable[..., Any]] = set()


class UnsupportedOperation(RuntimeError):
    """A torch operation that a :class:`SparseOperator` cannot do with O(nnz) gradients.

    A ``RuntimeError`` (as torch's own operator errors are) rather than a ``TypeError``: torch
    turns a ``TypeError`` raised inside ``A + B`` or ``A @ B`` into Python's generic
    "unsupported operand type(s)" message, which would hide what to do instead.
    """


class SparseOperator(torch.Tensor):
    """An ``(n, m)`` sparse matrix: a :class:`SparsityPattern` and a differentiable value array.

    Construct with :func:`torch_polylap.sparse.operator_from_parts` or get one from
    :func:`torch_polylap.laplacian`.  Attributes (read-only): ``pattern``, ``symmetric``
    (``A = A^T`` is known, so products' backward reuse ``A``).

    Torch algebra on it (products with dense tensors, sums, scaling, transposes, ``.to``,
    ``values()``, ``diagonal()``, ...) keeps O(nnz) gradients; the documentation's page
    "Operator algebra" lists every supported operation, generated from this class's dispatch
    table.  Everything else raises :class:`UnsupportedOperation`, which says what to use instead.
    """

    symmetric: bool
    _vals: torch.Tensor
    _crow: torch.Tensor
    _col: torch.Tensor
    _row: torch.Tensor
    _pattern_key: int
    _diag_class: int
    _pattern_obj: SparsityPattern | None
    _solver_cache: dict[str, Any]

    # Built from tensors and constants only (not from a SparsityPattern object): code that
    # torch.compile traces constructs operators by calling this class, and its tracer accepts
    # only such arguments. operator_on(pattern, values) is the constructor for library code.
    @staticmethod
    def __new__(
        cls,
        values: torch.Tensor,
        crow: torch.Tensor,
        col: torch.Tensor,
        row: torch.Tensor,
        shape: tuple[int, int],
        symmetric: bool = False,
        pattern_key: int = -1,
        diag_class: int = -1,
    ) -> SparseOperator:
        if values.dim() not in (1, 2) or values.shape[-1] != col.shape[0]:
            raise ValueError(
                f"a sparse operator needs one value per stored entry (or a batch (B, nnz) of "
                f"them): the pattern has {col.shape[0]}, the values have shape "
                f"{tuple(values.shape)}."
            )
        # a batch of value arrays on one pattern is a (B, n, m) batch of operators
        A: SparseOperator = make_wrapper_subclass(
            cls, (*values.shape[:-1], *shape), values.dtype, values.device
        )
        A._vals = values
        A._crow, A._col, A._row = crow, col, row
        A.symmetric = bool(symmetric and shape[0] == shape[1])
        A._pattern_key = pattern_key
        # how the pattern holds the diagonal (SparsityPattern.diagonal_class), -1 where unknown:
        # an argument, not set afterwards, so that torch.compile's tracer sees it too
        A._diag_class = diag_class
        # the pattern object itself where known (eagerly): it keeps its caches, and its entry in
        # the registry that traced code looks it up in, alive as long as the operator
        A._pattern_obj = None
        A._solver_cache = {}
        return A

    @property
    def pattern(self) -> SparsityPattern:
        """The :class:`SparsityPattern` (the index structure and its cached derived indices)."""
        if self._pattern_obj is not None and not tracing():
            return self._pattern_obj
        return pattern_of_indices(
            self._pattern_key, self._crow, self._col, self._row, _shape2(self)
        )

    def with_values(
        self, values: torch.Tensor, symmetric: bool | None = None, *, share_cache: bool = False
    ) -> SparseOperator:
        """The operator on the same pattern with other values.

        ``share_cache``: share the solver cache (factorizations) with this operator, for values
        that are this operator's values (a detached view, or a solve's saved input in its
        backward).  Entries are checked against the values' storage and version counter, which
        a write through ``.data`` does not change: keep it off for values that may be such.
        """
        A = SparseOperator(
            values,
            self._crow,
            self._col,
            self._row,
            _shape2(self),
            self.symmetric if symmetric is None else symmetric,
            self._pattern_key,
            self._diag_class,
        )
        A._pattern_obj = self._pattern_obj
        if share_cache:
            A._solver_cache = self._solver_cache
        return A

    @classmethod
    def __torch_function__(
        cls,
        func: Callable[..., Any],
        types: Iterable[type],
        args: Sequence[Any] = (),
        kwargs: dict[str, Any] | None = None,
    ) -> Any:
        kwargs = kwargs or {}
        handler = HANDLERS.get(func)
        if handler is not None:
            return handler(*args, **kwargs)
        # torch.compile's tracer inspects the operator like any tensor (strides, storage
        # offset); what reaches torch's dispatcher from there is refused by __torch_dispatch__
        if func in PASSTHROUGH or tracing():
            with disable_torch_function_subclass():
                return func(*args, **kwargs)
        raise UnsupportedOperation(_unsupported_message(func))

    # torch types Tensor.__torch_dispatch__ as its disabled default, a plain function, though
    # subclasses are to define it as a classmethod (as torch's own subclasses do)
    @classmethod
    def __torch_dispatch__(  # type: ignore[override]
        cls,
        func: Callable[..., Any],
        types: Iterable[type],
        args: Sequence[Any] = (),
        kwargs: dict[str, Any] | None = None,
    ) -> Any:
        # Only reached by code that bypasses __torch_function__: torch internals in C++, and
        # torch.compile's AOTAutograd handling an operator that crosses a compiled function's
        # boundary with a gradient (it models gradients on the wrapper, ours are on the values)
        raise UnsupportedOperation(
            _unsupported_message(func)
            + " Inside torch.compile: an operator whose values require grad cannot be an input"
            " or output of a compiled function; build it inside the compiled function (from "
            "the vertices), or pass it detached."
        )

    # mypy rejects any annotated override of the unannotated Tensor.__repr__(self, *,
    # tensor_contents=None), even one with the same parameters
    def __repr__(self, *, tensor_contents: Any = None) -> str:  # type: ignore[override]
        values = self._vals
        grad = f", grad_fn=<{type(values.grad_fn).__name__}>" if values.grad_fn is not None else ""
        if values.grad_fn is None and values.requires_grad:
            grad = ", requires_grad=True"
        with disable_torch_function_subclass():
            body = repr(values.detach()).replace("\n", "\n" + " " * 7)
        return (
            f"SparseOperator(shape={_shape2(self)}, nnz={self._col.shape[0]}, "
            f"dtype={values.dtype}, device={values.device}, symmetric={self.symmetric}, "
            f"layout={torch.sparse_csr}{grad},\n       values={body})"
        )

    def __reduce_ex__(self, protocol: SupportsIndex) -> tuple[Any, ...]:
        return (
            _rebuild,
            (
                self._crow,
                self._col,
                _shape2(self),
                self._vals,
                self.symmetric,
            ),
        )

    def __deepcopy__(self, memo: dict[int, Any]) -> SparseOperator:
        return self.with_values(self._vals.clone())

    # torch.compile traces code that builds and uses operators through __torch_function__; the
    # flatten protocol tells its tracer what an operator holds: the value array and the index
    # tensors, with constant metadata that it guards on: the symmetry flag and how the pattern
    # holds the diagonal, which every mesh's L (or M0) shares, not the pattern's registry
    # number, which differs from mesh to mesh and would compile a graph for each. Traced code
    # finds what it needs from the index tensors themselves (the operators of .index_ops).
    def __tensor_flatten__(self) -> tuple[list[str], tuple[Any, ...]]:
        meta = (self.symmetric, self._diagonal_class())
        return ["_vals", "_crow", "_col", "_row"], meta

    @staticmethod
    def __tensor_unflatten__(
        inner: dict[str, torch.Tensor], meta: tuple[Any, ...], outer_size: Any, outer_stride: Any
    ) -> SparseOperator:
        symmetric, diag_class = meta
        shape = (outer_size[-2], outer_size[-1])
        parts = (inner["_crow"], inner["_col"], inner["_row"])
        return SparseOperator(inner["_vals"], *parts, shape, symmetric, -1, diag_class)

    def _diagonal_class(self) -> int:
        """How the pattern holds the diagonal: 2 exactly the diagonal (a mass matrix), 1 every
        diagonal entry and others (a mesh's ``L``), 0 otherwise or unknown
        (:meth:`SparsityPattern.diagonal_class`)."""
        if self._diag_class < 0:
            pattern = self._pattern_obj
            if pattern is None and self._pattern_key >= 0:
                pattern = SparsityPattern.registered(self._pattern_key)
            if pattern is None:
                return 0
            with disable_current_modes():
                self._diag_class = pattern.diagonal_class()
        return self._diag_class


def _rebuild(
    crow: torch.Tensor,
    col: torch.Tensor,
    shape: tuple[int, int],
    values: torch.Tensor,
    symmetric: bool,
) -> SparseOperator:
    return operator_on(SparsityPattern(crow, col, shape), values, symmetric=symmetric)


# torch.load(weights_only=True), torch's default, unpickles only allow-listed globals: an
# operator (a state dict's buffer, a module's attribute) is rebuilt by _rebuild from tensors,
# a tuple and a bool, all of which that unpickler accepts.
torch.serialization.add_safe_globals([_rebuild])


def _shape2(A: torch.Tensor) -> tuple[int, int]:
    """``(n, m)`` of an operator (of each operator of a batch)."""
    # symbolic under torch.compile with dynamic shapes (int() would specialize the graph)
    with disable_torch_function_subclass():
        n, m = A.shape[-2:]
    return n, m


def _batch(A: SparseOperator) -> tuple[int, ...]:
    """``()`` for one operator, ``(B,)`` for a batch of operators on one pattern."""
    return tuple(A._vals.shape[:-1])


def operator_on(
    pattern: SparsityPattern,
    values: torch.Tensor,
    *,
    symmetric: bool = False,
) -> SparseOperator:
    """The operator with ``values`` ``(nnz,)`` on ``pattern`` (moved to the values' device)."""
    if values.device != pattern.device:
        pattern = pattern.to(values.device)
    parts = (pattern.crow, pattern.col, pattern.row)
    A = SparseOperator(values, *parts, pattern.shape, symmetric, pattern.key)
    if not tracing():
        A._pattern_obj = pattern
    return A


def pattern_of_indices(
    key: int, crow: torch.Tensor, col: torch.Tensor, row: torch.Tensor, shape: tuple[int, int]
) -> SparsityPattern:
    """The pattern numbered ``key`` (with its caches) while it lives, else one built anew on
    the index tensors."""
    if key >= 0:
        if tracing():
            return run_eagerly(_live_pattern, key)
        pattern = SparsityPattern.registered(key)
        if pattern is not None:
            return pattern
    pattern = SparsityPattern(crow, col, shape)
    pattern._row = row
    return pattern


def _live_pattern(key: int) -> SparsityPattern:
    pattern = SparsityPattern.registered(key)
    if pattern is None:
        raise RuntimeError(
            "torch_polylap: an operator's sparsity pattern was freed while torch.compile traced "
            "code using it; keep the mesh's topology alive (e.g. in the module) while compiling."
        )
    return pattern


def is_operator(x: object) -> bool:
    return isinstance(x, SparseOperator)


def _name(func: Callable) -> str:
    name = getattr(func, "__qualname__", None) or getattr(func, "__name__", None) or repr(func)
    if name == "__get__":
        name = repr(func)
    for internal, public in (("_VariableFunctionsClass.", "torch."), ("TensorBase.", "Tensor.")):
        name = name.replace(internal, public)
    return name


def _unsupported_message(func: Callable) -> str:
    return (
        f"torch_polylap: {_name(func)} is not supported on a SparseOperator (L, M0 and what is "
        "built from them): it has no O(nnz) gradient here, or would build a dense V x V matrix. "
        "Supported: products with dense tensors (A @ X, torch.mm, torch.sparse.mm), sums and "
        "differences of operators, scalar multiples, row/column scaling, transposes, .to(), "
        "A.values(), A.diagonal(), A.sum(dim). To hand A to another library (code that calls "
        ".unsqueeze or indexes it) convert it to a torch sparse tensor: "
        "torch_polylap.sparse.to_torch_sparse(A, layout=torch.sparse_coo) (values detached: no "
        "gradient reaches the vertices through it; COO, since torch's CSR tensors have no "
        "strides); for DiffusionNet, torch_polylap.interop.to_diffusionnet(verts, faces) gives "
        "all its operators. Otherwise A.to_dense() (small meshes) or "
        "torch_polylap.sparse.to_scipy(A)."
    )
