"""The dispatch table of :class:`~torch_polylap.sparse.operator.SparseOperator`: what each torch
function does with an operator.

``__torch_function__`` looks every call up in :data:`~torch_polylap.sparse.operator.HANDLERS`,
which this module fills: products with dense tensors go to the O(nnz) products of
:mod:`torch_polylap.sparse.autograd`, arithmetic (sums, scaling, negation, transposes, moves)
to the value array, and the few operations without an O(nnz) gradient are refused with
:class:`~torch_polylap.sparse.operator.UnsupportedOperation`, which says what to use instead.
``_SUPPORTED`` groups the handled functions into the rows of the documentation's list of
supported operations (``docs/gen_supported_ops.py``).
"""

from __future__ import annotations

import numbers
from collections.abc import Callable
from typing import Any

import torch

from .._torch_compat import (
    capture_dynamic_output_shape_ops,
    disable_current_modes,
    sparse_internal_accessors,
)
from ..tracing import require, tracing
from .autograd import spmm as csr_product_parts
from .index_ops import diagonal_indices, positions_in, transpose_indices, union_indices
from .operator import (
    HANDLERS,
    PASSTHROUGH,
    SparseOperator,
    UnsupportedOperation,
    _batch,
    _shape2,
    _unsupported_message,
    operator_on,
)
from .pattern import SparsityPattern, block_diagonal_indices

__all__ = ["apply"]


# --------------------------------------------------------------------------------------------
# products
# --------------------------------------------------------------------------------------------


def _check_dense(A: SparseOperator, X: object, what: str) -> torch.Tensor:
    if isinstance(X, SparseOperator):
        raise UnsupportedOperation(
            f"torch_polylap: {what} of two sparse operators (a sparse-sparse product) is not "
            "supported: its gradient has no O(nnz) form here. Multiply step by step with a dense "
            "tensor instead, e.g. L @ (L @ X) for L^2 X."
        )
    if not isinstance(X, torch.Tensor) or X.layout != torch.strided:
        raise UnsupportedOperation(
            f"torch_polylap: {what} needs a dense torch tensor, got {type(X).__name__}"
            f"{'' if not isinstance(X, torch.Tensor) else ' of layout ' + str(X.layout)}."
        )
    if X.dtype != A.dtype and _autocast_cast(X):
        # under autocast a product runs in the operator's precision (float32 or float64):
        # torch has no half-precision sparse kernels, and L's entries need float32
        X = X.to(A.dtype)
    if X.dtype != A.dtype:
        raise UnsupportedOperation(
            f"torch_polylap: {what} with an operator of dtype {A.dtype} and a tensor of dtype "
            f"{X.dtype} is not supported; convert one of them (X.to(A.dtype) or A.to(X.dtype))."
        )
    if X.device != A.device:
        raise UnsupportedOperation(
            f"torch_polylap: {what} with an operator on {A.device} and a tensor on {X.device} is "
            "not supported; move one of them."
        )
    return X


def _autocast_cast(X: torch.Tensor) -> bool:
    """Whether autocast is on for ``X``'s device and ``X`` is in its lower precision."""
    return X.dtype in (torch.float16, torch.bfloat16) and torch.is_autocast_enabled(X.device.type)


def apply(A: SparseOperator, X: object) -> torch.Tensor:
    """``A @ X`` with ``X`` of shape ``(m,)``, ``(m, c)`` or ``(..., m, c)`` (batched)."""
    X = _check_dense(A, X, "A @ X")
    if _batch(A):
        return _apply_batch(A, X)
    n, m = _shape2(A)
    if X.dim() == 0 or X.shape[-2 if X.dim() > 1 else 0] != m:
        raise ValueError(
            f"torch_polylap: cannot multiply an operator of shape {(n, m)} with a tensor of shape "
            f"{tuple(X.shape)}."
        )
    parts = (A._crow, A._col, A._row)
    if X.dim() == 1:
        return csr_product_parts(A._vals, *parts, X[:, None], A.symmetric)[:, 0]
    if X.dim() == 2:
        return csr_product_parts(A._vals, *parts, X, A.symmetric)
    # (..., m, c): one product with the batch folded into the columns
    batch, c = X.shape[:-2], X.shape[-1]
    flat = X.movedim(-2, 0).reshape(m, -1)
    Y = csr_product_parts(A._vals, *parts, flat, A.symmetric)
    return Y.reshape(n, *batch, c).movedim(0, -2)


def _apply_batch(A: SparseOperator, X: torch.Tensor) -> torch.Tensor:
    """``A[b] @ X[b]`` for a batch of ``B`` operators: ``X`` ``(B, m, c)``, ``(B, m)``, or one
    ``(m, c)`` / ``(m,)`` for every operator; one product with the block-diagonal operator."""
    (B,) = _batch(A)
    n, m = _shape2(A)
    # (B, m) is a batch of vectors; where B == m it is read as one (m, c) for all
    vec = X.dim() == 1 or (X.dim() == 2 and X.shape == (B, m) and B != m)
    Xb = X.unsqueeze(-1) if vec else X
    if Xb.dim() == 2:
        Xb = Xb.expand(B, *Xb.shape)
    if Xb.dim() != 3 or Xb.shape[0] != B or Xb.shape[1] != m:
        raise ValueError(
            f"torch_polylap: a batch of {B} operators of shape {(n, m)} multiplies tensors of "
            f"shape ({B}, {m}, c), ({B}, {m}), ({m}, c) or ({m},), got {tuple(X.shape)}."
        )
    crow, col, row = block_diagonal_indices(A._crow, A._col, A._row, B, n, m)
    Y = csr_product_parts(
        A._vals.reshape(-1), crow, col, row, Xb.reshape(B * m, -1), A.symmetric
    ).reshape(B, n, -1)
    return Y[..., 0] if vec else Y


def _matmul(a: object, b: object, **kwargs: Any) -> torch.Tensor:
    if kwargs.get("out") is not None:
        raise UnsupportedOperation("torch_polylap: out= is not supported with a sparse operator.")
    if isinstance(a, SparseOperator):
        return apply(a, b)
    assert isinstance(b, SparseOperator)
    return _rmatmul(b, a)


def _rmatmul(B: SparseOperator, X: object) -> torch.Tensor:
    """``X @ B`` = ``(B^T X^T)^T`` for ``X`` of shape ``(n,)`` or ``(..., k, n)``."""
    X = _check_dense(B, X, "X @ A")
    if X.dim() == 1:
        return apply(_transpose(B), X)
    return apply(_transpose(B), X.transpose(-1, -2)).transpose(-1, -2)


def _sparse_mm(a: object, b: object, reduce: str | None = None) -> torch.Tensor:
    if reduce not in (None, "sum"):
        raise UnsupportedOperation(
            f"torch_polylap: torch.sparse.mm with reduce={reduce!r} is not supported."
        )
    return _matmul(a, b)


def _addmm(
    input: torch.Tensor, mat1: object, mat2: object, *, beta: float = 1, alpha: float = 1, **kw: Any
) -> torch.Tensor:
    if isinstance(input, SparseOperator):
        raise UnsupportedOperation(_unsupported_message(torch.addmm) + " (a sparse `input`)")
    return beta * input + alpha * _matmul(mat1, mat2, **kw)


# --------------------------------------------------------------------------------------------
# linear combinations and scaling
# --------------------------------------------------------------------------------------------


def _is_scalar(s: object) -> bool:
    if isinstance(s, SparseOperator):
        return False
    if isinstance(s, torch.Tensor):
        return s.dim() == 0 or s.numel() == 1 and s.dim() <= 2 and max(s.shape, default=1) == 1
    return isinstance(s, numbers.Number) and not isinstance(s, bool | complex)


# The scalars of _scalar_tensor, _combine, _sub and _rsub are whatever the caller gave torch
# (a number, a one-element tensor, ...): Any, as float() and unary minus decide at run time.
def _scalar_tensor(A: SparseOperator, s: Any) -> torch.Tensor | float:
    if isinstance(s, torch.Tensor):
        if s.device != A.device and s.device.type != "cpu":
            raise UnsupportedOperation(
                f"torch_polylap: scalar on {s.device}, operator on {A.device}."
            )
        return s.reshape(()).to(dtype=A.dtype, device=A.device)
    return float(s)


def _scale(A: SparseOperator, w: object, op: str) -> SparseOperator:
    """``A * w`` or ``A / w``: a scalar, a row ``(n, 1)`` or a column ``(m,)``/``(1, m)`` vector."""
    if _is_scalar(w):
        s = _scalar_tensor(A, w)
        return A.with_values(A._vals * s if op == "mul" else A._vals / s)
    if (
        isinstance(w, torch.Tensor)
        and w.layout == torch.strided
        and not isinstance(w, SparseOperator)
    ):
        n, m = _shape2(A)
        w = _check_dense(A, w, f"A {'*' if op == 'mul' else '/'} w")
        batch = _batch(A)
        if w.shape[-2:] == (n, 1) and w.shape[:-2] in ((), batch):
            factor = w[..., :, 0][..., A._row]
        elif w.shape in ((m,), (1, m)) or w.shape == (*batch, 1, m) and batch:
            factor = (
                w.reshape(*w.shape[:-2], m)[..., A._col] if w.dim() > 2 else w.reshape(-1)[A._col]
            )
        else:
            factor = None
        if factor is not None:
            values = A._vals * factor if op == "mul" else A._vals / factor
            return A.with_values(values, symmetric=False)
    raise UnsupportedOperation(
        f"torch_polylap: A {'*' if op == 'mul' else '/'} {_describe(w)} is not supported on a "
        "sparse operator: only a number, a 0-dim tensor, a row vector (n, 1) or a column vector "
        "(m,) / "
        "(1, m) keeps the result sparse (an elementwise product of two operators is not supported)."
    )


def _describe(x: object) -> str:
    if isinstance(x, SparseOperator):
        return "a sparse operator"
    if isinstance(x, torch.Tensor):
        return f"a tensor of shape {tuple(x.shape)}"
    return type(x).__name__


def _mul(a: object, b: object, **kwargs: Any) -> SparseOperator:
    if kwargs.get("out") is not None:
        raise UnsupportedOperation("torch_polylap: out= is not supported with a sparse operator.")
    if isinstance(a, SparseOperator) and isinstance(b, SparseOperator):
        raise UnsupportedOperation(
            "torch_polylap: the elementwise product of two sparse operators is not supported; "
            "for the matrix product multiply with a dense tensor step by step (L @ (M @ X))."
        )
    if isinstance(a, SparseOperator):
        return _scale(a, b, "mul")
    assert isinstance(b, SparseOperator)
    return _scale(b, a, "mul")


def _div(
    a: object, b: object, *, rounding_mode: str | None = None, **kwargs: Any
) -> SparseOperator:
    if not isinstance(a, SparseOperator) or rounding_mode is not None:
        raise UnsupportedOperation(
            f"torch_polylap: {_describe(a)} / {_describe(b)} is not supported (dividing by a "
            "sparse operator would fill the zeros with infinities); divide the operator by a "
            "number."
        )
    return _scale(a, b, "div")


def _combine(A: SparseOperator, B: SparseOperator, alpha: Any) -> SparseOperator:
    """``A + alpha B`` on the union of the two patterns (cached per pattern pair)."""
    if B.dtype != A.dtype:
        raise UnsupportedOperation(
            f"torch_polylap: cannot add operators of dtypes {A.dtype} and {B.dtype}; "
            "convert one with .to(dtype)."
        )
    if B.device != A.device:
        raise UnsupportedOperation(
            f"torch_polylap: cannot add operators on {A.device} and {B.device}; "
            "move one with .to()."
        )
    b_vals = B._vals
    if not (isinstance(alpha, numbers.Number) and alpha == 1):
        b_vals = b_vals * _scalar_tensor(A, alpha)
    if _batch(A) != _batch(B):
        if _batch(A) and _batch(B):
            raise UnsupportedOperation(
                f"torch_polylap: cannot add batches of {_batch(A)[0]} and {_batch(B)[0]} operators."
            )
        # one operator and a batch: the one is added to each
        batch = _batch(A) or _batch(B)
        A = A.with_values(A._vals.expand(*batch, A._vals.shape[-1]))
        b_vals = b_vals.expand(*batch, b_vals.shape[-1])
    symmetric = A.symmetric and B.symmetric
    if tracing():
        return _combine_traced(A, B, b_vals, symmetric)
    pattern, at_a, at_b = A.pattern.union(B.pattern)
    if at_a is None:
        values = A._vals + b_vals if at_b is None else A._vals.index_add(-1, at_b, b_vals)
    elif at_b is None:
        values = b_vals.index_add(-1, at_a, A._vals)
    else:
        values = A._vals.new_zeros(*_batch(A), pattern.nnz).index_add(-1, at_a, A._vals)
        values = values.index_add(-1, at_b, b_vals)
    return operator_on(pattern, values, symmetric=symmetric)


def _nesting(A: SparseOperator, B: SparseOperator) -> int:
    """1 if ``B``'s pattern is contained in ``A``'s, -1 if the converse, 0 if neither or
    unknown: a question about the two patterns' index tensors, answered on the real ones (kept
    by the pattern registry) whatever tensors the tracer is propagating."""
    pa = SparsityPattern.registered(A._pattern_key) if A._pattern_key >= 0 else None
    pb = SparsityPattern.registered(B._pattern_key) if B._pattern_key >= 0 else None
    if pa is None or pb is None:
        return 0
    with disable_current_modes():
        return 1 if pa.contains(pb) else (-1 if pb.contains(pa) else 0)


def _combine_traced(
    A: SparseOperator, B: SparseOperator, b_vals: torch.Tensor, symmetric: bool
) -> SparseOperator:
    """``A + B`` in traced code: on ``A``'s or ``B``'s pattern when one contains the other
    (``M0 + t L``: the diagonal is in ``L``'s pattern), else on a union of data-dependent size."""
    if A._pattern_key >= 0 and A._pattern_key == B._pattern_key:
        return A.with_values(A._vals + b_vals, symmetric)
    n, m = _shape2(A)
    unregistered = A._pattern_key < 0 or B._pattern_key < 0
    if unregistered and {A._diagonal_class(), B._diagonal_class()} == {1, 2}:
        return _add_diagonal_traced(A, B, b_vals, symmetric)
    nesting = _nesting(A, B)
    if nesting == 1:
        at_b = positions_in(A._crow, A._col, B._crow, B._col, m)
        return A.with_values(A._vals.index_add(-1, at_b, b_vals), symmetric)
    if nesting == -1:
        at_a = positions_in(B._crow, B._col, A._crow, A._col, m)
        values = b_vals.index_add(-1, at_a, A._vals)
        parts = (B._crow, B._col, B._row)
        return SparseOperator(values, *parts, (n, m), symmetric, B._pattern_key)
    if not capture_dynamic_output_shape_ops():
        raise UnsupportedOperation(
            "torch_polylap: inside torch.compile, A + B of operators whose patterns do not "
            "contain one another (a mesh's M0 + t L does; a mesh with isolated vertices does "
            "not) has a size that depends on the data. Set "
            "torch._dynamo.config.capture_dynamic_output_shape_ops = True, remove the isolated "
            "vertices (torch_polylap.repair.remove_unreferenced_vertices), or add the operators "
            "outside the compiled code."
        )
    crow, col, row, at_a, at_b = union_indices(A._crow, A._col, B._crow, B._col, m)
    values = A._vals.new_zeros(*_batch(A), col.shape[0]).index_add(-1, at_a, A._vals)
    values = values.index_add(-1, at_b, b_vals)
    return SparseOperator(values, crow, col, row, (n, m), symmetric)


_MISSING_DIAGONAL = (
    "torch_polylap: in compiled code, a diagonal operator plus one whose pattern was taken to "
    "store every diagonal entry (as a mesh's L does) met an operator that does not store them "
    "all; add these operators outside the compiled code."
)


def _add_diagonal_traced(
    A: SparseOperator, B: SparseOperator, b_vals: torch.Tensor, symmetric: bool
) -> SparseOperator:
    """``A + B`` in traced code for a diagonal operator and one whose pattern stores every
    diagonal entry (``M0 + t L``), known from their metadata (operators passed into the
    compiled code, or built there for a mesh the graph does not fix): the sum keeps the
    larger pattern, the diagonal's values added at the diagonal positions, which the graph
    checks are all stored (a mesh's L stores them, also at isolated vertices)."""
    a_vals = A._vals
    if A._diagonal_class() == 2:
        A, B, a_vals, b_vals = B, A, b_vals, a_vals
    pos = diagonal_indices(A._crow, A._col, _shape2(A)[0])
    require((pos >= 0).all(), _MISSING_DIAGONAL)
    return A.with_values(a_vals.index_add(-1, pos, b_vals), symmetric)


def _is_zero(x: object) -> bool:
    return isinstance(x, numbers.Number) and not isinstance(x, bool) and x == 0


def _add(a: object, b: object, *, alpha: object = 1, **kwargs: Any) -> torch.Tensor:
    if kwargs.get("out") is not None:
        raise UnsupportedOperation("torch_polylap: out= is not supported with a sparse operator.")
    if isinstance(a, SparseOperator) and isinstance(b, SparseOperator):
        return _combine(a, b, alpha)
    # 0 + A (Python's sum() starts from 0) leaves A as it is
    if isinstance(a, SparseOperator) and _is_zero(b):
        return a
    if isinstance(b, SparseOperator) and _is_zero(a) and _is_zero_alpha_one(alpha):
        return b
    raise UnsupportedOperation(
        f"torch_polylap: {_describe(a)} + {_describe(b)} is not supported: adding a dense "
        "tensor or a non-zero number to a sparse operator gives a dense V x V matrix. Add sparse "
        "operators "
        "instead, e.g. torch_polylap.sparse.identity(n) or torch_polylap.sparse.diag(d)."
    )


def _is_zero_alpha_one(alpha: object) -> bool:
    return isinstance(alpha, numbers.Number) and alpha == 1


def _sub(a: object, b: object, *, alpha: Any = 1, **kwargs: Any) -> torch.Tensor:
    if isinstance(a, SparseOperator) and isinstance(b, SparseOperator):
        return _combine(a, b, -alpha)
    if isinstance(a, SparseOperator) and _is_zero(b):
        return a
    if isinstance(b, SparseOperator) and _is_zero(a):
        return _neg(b)
    raise UnsupportedOperation(
        f"torch_polylap: {_describe(a)} - {_describe(b)} is not supported: it would give a dense "
        "V x V matrix. Subtract sparse operators instead (e.g. torch_polylap.sparse.identity(n))."
    )


def _rsub(a: object, b: object, *, alpha: Any = 1, **kwargs: Any) -> torch.Tensor:
    # torch.rsub(a, b) = b - alpha * a
    if isinstance(a, SparseOperator) and isinstance(b, SparseOperator):
        return _sub(b, a, alpha=alpha)
    if isinstance(a, SparseOperator) and _is_zero(b):
        return _neg(a) if _is_zero_alpha_one(alpha) else _scale(a, -alpha, "mul")
    raise UnsupportedOperation(
        f"torch_polylap: {_describe(b)} - {_describe(a)} is not supported: it would give a dense "
        "V x V matrix. Subtract sparse operators instead (e.g. torch_polylap.sparse.identity(n))."
    )


def _neg(A: SparseOperator, **kwargs: Any) -> SparseOperator:
    return A.with_values(-A._vals)


# --------------------------------------------------------------------------------------------
# structure: transpose, conversions, accessors
# --------------------------------------------------------------------------------------------


def _transpose(A: SparseOperator, *args: Any) -> SparseOperator:
    nd = len(_batch(A)) + 2
    if args and sorted(d % nd for d in args) != [nd - 2, nd - 1]:
        raise UnsupportedOperation(
            f"torch_polylap: an operator transposes its last two dimensions only, got {args}."
        )
    if A.symmetric:
        return A
    if tracing():
        n, m = _shape2(A)
        crow, col, row, perm_t = transpose_indices(A._crow, A._col, m)
        return SparseOperator(A._vals[..., perm_t], crow, col, row, (m, n), False)
    transposed, perm = A.pattern.transpose()
    return operator_on(transposed, A._vals[..., perm])


def _to(A: SparseOperator, *args: Any, **kwargs: Any) -> SparseOperator:
    dtype, device = A.dtype, A.device
    for arg in (*args, kwargs.get("dtype"), kwargs.get("device")):
        if arg is None:
            continue
        if isinstance(arg, torch.dtype):
            dtype = arg
        elif isinstance(arg, str | torch.device):
            device = torch.device(arg)
        elif isinstance(arg, torch.Tensor):
            dtype, device = arg.dtype, arg.device
        elif isinstance(arg, bool):
            continue  # non_blocking / copy
        else:
            raise UnsupportedOperation(
                f"torch_polylap: .to({arg!r}) is not supported on a sparse operator."
            )
    if kwargs.get("memory_format") is not None:
        raise UnsupportedOperation(
            "torch_polylap: memory_format is not supported on a sparse operator."
        )
    if not (dtype.is_floating_point or dtype.is_complex):
        raise UnsupportedOperation(
            f"torch_polylap: a sparse operator holds floating values; .to({dtype}) is not "
            "supported."
        )
    values = A._vals.to(device=device, dtype=dtype, copy=bool(kwargs.get("copy", False)))
    if values is A._vals:
        return A
    if values.device == A._col.device:
        return A.with_values(values)
    return operator_on(A.pattern, values, symmetric=A.symmetric)


def _cast(dtype: torch.dtype) -> Callable[..., SparseOperator]:
    def cast(A: SparseOperator, *args: Any, **kwargs: Any) -> SparseOperator:
        return _to(A, dtype)

    return cast


def _cuda(
    A: SparseOperator, device: torch.device | str | int | None = None, **kwargs: Any
) -> SparseOperator:
    if isinstance(device, int):
        device = f"cuda:{device}"
    return _to(A, torch.device(device or "cuda"))


def _to_dense(A: SparseOperator, *args: Any, **kwargs: Any) -> torch.Tensor:
    dense = A._vals.new_zeros(*_batch(A), *_shape2(A))
    if not _batch(A):
        return dense.index_put((A._row, A._col), A._vals)
    b = torch.arange(_batch(A)[0], device=A._vals.device)[:, None]
    return dense.index_put((b, A._row[None], A._col[None]), A._vals)


def _diagonal(A: SparseOperator, offset: int = 0, dim1: int = 0, dim2: int = 1) -> torch.Tensor:
    nd = len(_batch(A)) + 2
    if (dim1, dim2) == (0, 1):
        # the default: the diagonal of each operator of a batch (torch's would mix the batch
        # dimension with the rows, which means nothing for operators)
        dim1, dim2 = nd - 2, nd - 1
    if offset != 0 or sorted((dim1 % nd, dim2 % nd)) != [nd - 2, nd - 1]:
        raise UnsupportedOperation(
            "torch_polylap: only the main diagonal of a sparse operator is supported."
        )
    if tracing():
        pos = diagonal_indices(A._crow, A._col, min(_shape2(A)))
    else:
        pos = A.pattern.diagonal_positions()
    stored = pos >= 0
    gathered = A._vals[..., pos.clamp_min(0)]
    return torch.where(stored, gathered, torch.zeros_like(gathered))


def _sum(
    A: SparseOperator, dim: int | None = None, keepdim: bool = False, **kw: Any
) -> torch.Tensor:
    if kw.get("dtype") is not None:
        raise UnsupportedOperation(
            "torch_polylap: sum(dtype=...) is not supported on a sparse operator."
        )
    if dim is None:
        return A._vals.sum()
    nd = len(_batch(A)) + 2
    dim = dim % nd
    if dim < nd - 2:
        raise UnsupportedOperation(
            "torch_polylap: sum over the batch dimension of operators is not supported; add "
            "them with + (or sum(list(A)))."
        )
    dim -= nd - 2
    index = A._row if dim == 1 else A._col
    out = A._vals.new_zeros(*_batch(A), _shape2(A)[1 - dim]).index_add(-1, index, A._vals)
    return out.unsqueeze(dim - 2) if keepdim else out


def _copy(A: SparseOperator, src: object, non_blocking: bool = False) -> SparseOperator:
    """``A.copy_(B)`` for an operator ``B`` on the same pattern: ``A``'s values become ``B``'s.

    What ``load_state_dict`` does with a buffer: a checkpoint of the same mesh loads in place.
    """
    same = (
        isinstance(src, SparseOperator)
        and _shape2(src) == _shape2(A)
        and src._col.shape == A._col.shape
        and (
            A._pattern_key >= 0
            and src._pattern_key == A._pattern_key
            or bool(torch.equal(src._crow.to(A._crow.device), A._crow))
            and bool(torch.equal(src._col.to(A._col.device), A._col))
        )
    )
    if not same:
        raise UnsupportedOperation(
            f"torch_polylap: copying {_describe(src)} into a sparse operator needs an operator "
            "with the same sparsity pattern (a checkpoint of the same mesh). To load a state "
            "dict whose operators belong to other meshes, call "
            "model.load_state_dict(state_dict, assign=True), which takes them as they are."
        )
    assert isinstance(src, SparseOperator)
    with torch.no_grad():
        A._vals.copy_(src._vals, non_blocking=non_blocking)
    return A


def _getitem(A: SparseOperator, index: Any) -> SparseOperator:
    """``A[b]``: operator ``b`` of a batch (an int), or a sub-batch (a slice or index tensor)."""
    if not _batch(A):
        raise UnsupportedOperation(
            "torch_polylap: indexing a sparse operator is not supported; take rows with "
            "torch_polylap.sparse.submatrix or entries with A.to_dense() on small meshes."
        )
    if not isinstance(index, int | slice | torch.Tensor):
        raise UnsupportedOperation(
            "torch_polylap: a batch of operators is indexed along the batch only (A[b], A[i:j])."
        )
    return A.with_values(A._vals[index])


def _unbind(A: SparseOperator, dim: int = 0) -> tuple[SparseOperator, ...]:
    if not _batch(A) or dim != 0:
        raise UnsupportedOperation("torch_polylap: only a batch of operators unbinds (dim 0).")
    return tuple(A.with_values(v) for v in A._vals.unbind(0))


def _refuse_grad(A: SparseOperator, requires_grad: bool = True) -> SparseOperator:
    if requires_grad:
        raise UnsupportedOperation(
            "torch_polylap: requires_grad_() is not supported on a sparse operator: its gradient "
            "lives on its values. Make the vertices "
            "(or lam) require grad before building it, or build your own operator with "
            "torch_polylap.sparse.operator_from_parts(crow, col, values, shape) from values that "
            "require grad."
        )
    return A


def _metadata(name: str) -> Callable[..., Any]:
    def get(A: SparseOperator, *args: Any) -> Any:
        if tracing() and name in ("layout", "is_sparse", "is_sparse_csr"):
            # torch.compile's tracer refuses tensors that report a sparse layout; it sees the
            # operator as what it is to torch, a strided wrapper around its tensors
            return {"layout": torch.strided, "is_sparse": False, "is_sparse_csr": False}[name]
        return {
            "layout": torch.sparse_csr,
            "is_sparse": False,
            "is_sparse_csr": True,
            "requires_grad": A._vals.requires_grad,
            "grad_fn": A._vals.grad_fn,
            "is_leaf": A._vals.grad_fn is None,
        }[name]

    return get


def _getter(prop: Any) -> Callable:
    return prop.__get__


# What each group of handled torch functions does with an operator ``A``, and what it returns:
# the rows of the documentation's list of supported operations, which
# docs/gen_supported_ops.py writes from _SUPPORTED (a test keeps the page in step with it).
_SUPPORTED: list[tuple[str, str, list[Callable]]] = []


def _true(A: SparseOperator) -> bool:
    return True


def _build_handlers() -> dict[Callable, Callable]:
    T = torch.Tensor
    internal = sparse_internal_accessors()
    handlers: dict[Callable, Callable] = {}

    def add(what: str, result: str, funcs: list, handler: Callable) -> None:
        funcs = [f for f in funcs if f is not None]
        for f in funcs:
            handlers[f] = handler
        for row_what, row_result, row_funcs in _SUPPORTED:
            if (row_what, row_result) == (what, result):
                row_funcs.extend(funcs)
                return
        _SUPPORTED.append((what, result, funcs))

    product = "product with a dense `X` of shape `(m,)`, `(m, c)` or `(..., m, c)`"
    add(product, "dense", [T.matmul, T.__matmul__, torch.matmul, T.mm, torch.mm], _matmul)
    add(product, "dense", [T.mv, torch.mv], _matmul)
    add(product, "dense", [T.__rmatmul__], lambda a, b: _matmul(b, a))
    add(product, "dense", [torch.sparse.mm], _sparse_mm)
    add(product, "dense", [torch.addmm, T.addmm, torch.sparse.addmm], _addmm)
    combination = (
        "sum or difference of two operators of one shape (any two patterns); `0 + A`, so "
        "Python's `sum` works"
    )
    add(combination, "operator", [T.add, T.__add__, T.__radd__, torch.add], _add)
    add(combination, "operator", [T.sub, T.__sub__, torch.sub, T.subtract, torch.subtract], _sub)
    add(combination, "operator", [T.__rsub__, torch.rsub], _rsub)
    scaling = (
        "multiple by a number or a 0-dim tensor (which may require grad); row scaling "
        "`A * w[:, None]`, `A / w[:, None]`; column scaling `A * w[None, :]`"
    )
    add(scaling, "operator", [T.mul, T.__mul__, T.__rmul__, torch.mul], _mul)
    add(scaling, "operator", [T.multiply, torch.multiply], _mul)
    add(scaling, "operator", [T.div, T.__truediv__, torch.div, T.divide], _div)
    add(scaling, "operator", [torch.divide, torch.true_divide], _div)
    sign = "negation (`-A`), absolute value of the entries"
    add(sign, "operator", [T.neg, T.__neg__, torch.neg, T.negative, torch.negative], _neg)
    add(
        sign,
        "operator",
        [T.abs, T.__abs__, torch.abs, T.absolute, torch.absolute],
        lambda A: A.with_values(A._vals.abs()),
    )
    add(sign, "operator", [T.__pos__, torch.positive, T.positive], lambda A: A)
    transpose = "transpose (`A` itself when symmetric); conjugation is a no-op on real values"
    add(transpose, "operator", [T.t, torch.t, T.transpose, torch.transpose], _transpose)
    add(transpose, "operator", [T.adjoint, torch.adjoint], _transpose)
    getters = [_getter(T.T), _getter(T.mT), _getter(T.H), _getter(T.mH)]
    add(transpose, "operator", getters, _transpose)
    add(
        transpose,
        "operator",
        [T.conj, torch.conj, T.resolve_conj, T.resolve_neg, T.contiguous],
        lambda A, *a, **k: A,
    )
    move = "dtype and device"
    add(move, "operator", [T.to], _to)
    add(move, "operator", [T.double], _cast(torch.float64))
    add(move, "operator", [T.float], _cast(torch.float32))
    add(move, "operator", [T.half], _cast(torch.float16))
    add(move, "operator", [T.bfloat16], _cast(torch.bfloat16))
    add(move, "operator", [T.cpu], lambda A, *a, **k: _to(A, torch.device("cpu")))
    add(move, "operator", [T.cuda], _cuda)
    values = "detached or cloned values; `copy_` loads the values of an operator of one pattern"
    add(values, "operator", [T.detach], lambda A: A.with_values(A._vals.detach(), share_cache=True))
    add(values, "operator", [T.clone], lambda A, **k: A.with_values(A._vals.clone()))
    add(values, "operator", [T.copy_], _copy)
    batch = "one operator or a sub-batch of a batch `(B, n, m)` (along the batch only)"
    add(batch, "operator", [T.__getitem__], _getitem)
    add(batch, "operator", [T.unbind, torch.unbind], _unbind)
    add(batch, "operator", [T.__iter__], lambda A: iter(_unbind(A)))
    layout = "the operator itself: it is sorted CSR, whose `indices()` are also COO's, coalesced"
    conversions = [T.to_sparse_csr, T.to_sparse_coo, T.to_sparse, T.coalesce]
    add(layout, "operator", conversions, lambda A, *a, **k: A)
    add("whether the entries are coalesced (they always are)", "`True`", [T.is_coalesced], _true)
    reductions = "the value array, the main diagonal, row or column sums, the dense matrix"
    add(reductions, "dense, differentiable", [T.values, internal["_values"]], lambda A: A._vals)
    add(reductions, "dense, differentiable", [T.diagonal, torch.diagonal], _diagonal)
    add(reductions, "dense, differentiable", [T.sum, torch.sum], _sum)
    add(reductions, "dense, differentiable", [T.to_dense], _to_dense)
    indices = "the stored indices (CSR, and COO's `(2, nnz)`), the number of stored entries"
    add(indices, "index tensors", [T.crow_indices], lambda A: A._crow)
    add(indices, "index tensors", [T.col_indices], lambda A: A._col)
    add(
        indices,
        "index tensors",
        [T.indices, internal["_indices"]],
        lambda A: torch.stack((A._row, A._col)),
    )
    add(indices, "index tensors", [internal["_nnz"]], lambda A: A._col.shape[0])
    for name in ("layout", "is_sparse", "is_sparse_csr", "requires_grad", "grad_fn", "is_leaf"):
        add(
            "metadata of a sparse tensor, `requires_grad` and `grad_fn` of the value array",
            "as for a torch sparse tensor",
            [_getter(getattr(T, name))],
            _metadata(name),
        )
    refused = "refused with the reason and what to do instead"
    add(refused, "`UnsupportedOperation`", [T.requires_grad_], _refuse_grad)
    add(refused, "`UnsupportedOperation`", [T.__rtruediv__, T.__rdiv__], lambda a, b: _div(b, a))
    return handlers


HANDLERS.update(_build_handlers())
# Newer torch.compile traces the transposing properties (``A.T``, ``A.mT``, ``A.mH``) as calls
# of the aten operators themselves rather than of the property getters: the same handler serves
# those spellings (not listed in the supported-operations table, which names the public ones).
for _op in (torch.ops.aten.numpy_T, torch.ops.aten.mT, torch.ops.aten.mH):
    HANDLERS[_op] = HANDLERS[_op.default] = _transpose

PASSTHROUGH.update(
    {
        _getter(torch.Tensor.shape),
        _getter(torch.Tensor.dtype),
        _getter(torch.Tensor.device),
        _getter(torch.Tensor.ndim),
        _getter(torch.Tensor.is_cuda),
        _getter(torch.Tensor.is_cpu),
        _getter(torch.Tensor.is_meta),
        _getter(torch.Tensor.is_quantized),
        _getter(torch.Tensor.is_nested),
        torch.Tensor.size,
        torch.Tensor.dim,
        torch.Tensor.ndimension,
        torch.Tensor.numel,
        torch.Tensor.__len__,
        torch.Tensor.is_floating_point,
        torch.Tensor.is_complex,
        torch.Tensor.element_size,
        torch.Tensor.get_device,
        torch.Tensor.__hash__,
        torch.Tensor.__format__,
        # read on every operator passed into a graph compiled with dynamic shapes, by torch's
        # own wrapper code (the wrapper's strides, those of a contiguous (n, m) tensor)
        torch.Tensor.stride,
    }
)
