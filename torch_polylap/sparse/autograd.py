"""Differentiable sparse products whose gradients stay on the sparsity pattern (O(nnz) memory).

torch's own autograd for ``sparse @ dense`` returns a *dense* ``n x m`` gradient for the sparse
operand: at 62k vertices that is 31 GB.  Here a matrix is its pattern plus a value array, and
three products are each other's derivatives:

    product     Y = A X          dvalues = sampled(G, X),   dX = A^T G
    transposed  Z = A^T G        dvalues = sampled(G, H),   dG = A H
    sampled     s = (G X^T)|_A   dG = A(w) X,               dX = A(w)^T G

(``A(w)`` is the matrix on the same pattern with values ``w``; ``(G X^T)|_A`` the entries of
``G X^T`` at the pattern's positions.)  Gradients of gradients (Hessian-vector products,
``create_graph=True``) are therefore exact to any order, each at O(nnz * columns).

The three products are ``torch.library`` custom operators (``torch_polylap::spmm``,
``torch_polylap::spmm_t``, ``torch_polylap::sampled``) with fake kernels, so torch.compile,
``torch.export`` and ``FakeTensorMode`` see them as single graph nodes of known output shape;
with vmap rules (a batch of value arrays is a block-diagonal operator; a batch of right-hand
sides is folded into the columns) and autocast rules (they run in float32 under mixed
precision: half precision cannot hold the Laplacian's entries, and torch has no half-precision
sparse kernels).  Their reverse-mode derivatives are registered on the operators.  Eagerly, the
products go through :class:`_Product`, an ``autograd.Function`` with the same backward and a
forward-mode rule as well, because custom operators have no forward-mode derivative and
``torch.func.jvp`` would silently return a zero tangent through them; torch.compile cannot trace
an ``autograd.Function`` with a forward-mode rule, so traced code calls the operators directly.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import torch

from .._torch_compat import forward_ad_active
from ..tracing import in_functorch, tracing
from .index_ops import int32_indices, transposed
from .pattern import SparsityPattern, block_diagonal_indices

__all__ = ["csr_product", "sampled_product", "spmm", "spmm_t", "sampled", "torch_csr"]


def _csr(crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, m: int) -> torch.Tensor:
    # the package builds its patterns itself and knows them valid: skip torch's invariant
    # checks and its one-time "CSR support is in beta" warning
    if crow.device.type == "cpu" and crow.dtype == torch.int64:
        crow, col = int32_indices(crow, col, m)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(
            crow, col, values, (crow.numel() - 1, m), check_invariants=False
        )


def torch_csr(pattern: SparsityPattern, values: torch.Tensor) -> torch.Tensor:
    """A plain torch sparse CSR tensor on ``pattern`` (for torch's kernels; no autograd meaning)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        return torch.sparse_csr_tensor(
            pattern.crow, pattern.col, values, pattern.shape, check_invariants=False
        )


# --------------------------------------------------------------------------------------------
# the kernels: torch's CSR products (A^T G with the transposed pattern, computed once per
# pattern: an argsort per product would cost more than the product)
# --------------------------------------------------------------------------------------------


@torch.library.custom_op("torch_polylap::spmm", mutates_args=())
def spmm_op(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    X: torch.Tensor,
    symmetric: bool,
) -> torch.Tensor:
    """``A X``: ``A`` ``(n, m)`` on CSR indices ``crow (n + 1,)``, ``col``/``row (nnz,)``,
    values ``(nnz,)``; ``X`` ``(m, c)``; returns ``(n, c)``.  ``symmetric`` (``A = A^T``) only
    informs the backward."""
    return _csr(crow, col, values, X.shape[0]) @ X


@spmm_op.register_fake
def _spmm_fake(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    X: torch.Tensor,
    symmetric: bool,
) -> torch.Tensor:
    return X.new_empty((crow.shape[0] - 1, X.shape[1]))


@torch.library.custom_op("torch_polylap::spmm_t", mutates_args=())
def spmm_t_op(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    G: torch.Tensor,
    m: int,
) -> torch.Tensor:
    """``A^T G`` for ``A`` ``(n, m)`` as in :func:`spmm_op` and ``G`` ``(n, c)``: ``(m, c)``."""
    crow_t, col_t, _, perm = transposed(crow, col, m, copy=False)
    return _csr(crow_t, col_t, values[perm], G.shape[0]) @ G


@spmm_t_op.register_fake
def _spmm_t_fake(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    G: torch.Tensor,
    m: int,
) -> torch.Tensor:
    return G.new_empty((m, G.shape[1]))


@torch.library.custom_op("torch_polylap::sampled", mutates_args=())
def sampled_op(
    G: torch.Tensor, X: torch.Tensor, crow: torch.Tensor, col: torch.Tensor, row: torch.Tensor
) -> torch.Tensor:
    """``(nnz,)`` entries ``s_k = sum_c G[row_k, c] X[col_k, c]`` of ``G X^T`` on the pattern."""
    if G.device.type == "cpu":
        return _sampled_cpu(G, X, row, col)
    zeros = G.new_zeros(col.shape[0])
    return torch.sparse.sampled_addmm(
        _csr(crow, col, zeros, X.shape[0]), G.contiguous(), X.t().contiguous(), beta=0.0
    ).values()


# entries per block of the CPU sampled product: its two (block, c) row gathers stay in cache
_SAMPLED_BLOCK = 1 << 16


def _sampled_cpu(
    G: torch.Tensor,
    X: torch.Tensor,
    row: torch.Tensor,
    col: torch.Tensor,
    block: int = _SAMPLED_BLOCK,
) -> torch.Tensor:
    """:func:`sampled_op` on the CPU, in blocks of entries: two row gathers, their product
    and its columns summed in order (the sums torch's ``sampled_addmm`` forms, at a third
    of its time: it is the largest cost of a Laplacian's backward)."""
    nnz, c = col.shape[0], G.shape[1]
    out = G.new_empty(nnz)
    if c == 0:
        return out.zero_()
    for start in range(0, nnz, block):
        stop = min(start + block, nnz)
        part = out[start:stop]
        prod = G.index_select(0, row[start:stop]).mul_(X.index_select(0, col[start:stop]))
        # a strided copy of the first column would cost as much as the gathers: add two
        if c == 1:
            part.copy_(prod[:, 0])
        else:
            torch.add(prod[:, 0], prod[:, 1], out=part)
        for j in range(2, c):
            part.add_(prod[:, j])
    return out


@sampled_op.register_fake
def _sampled_fake(
    G: torch.Tensor, X: torch.Tensor, crow: torch.Tensor, col: torch.Tensor, row: torch.Tensor
) -> torch.Tensor:
    return G.new_empty(col.shape)


# --------------------------------------------------------------------------------------------
# reverse mode: one set of formulas, written with whichever products the caller's mode needs
# --------------------------------------------------------------------------------------------


class _Products(NamedTuple):
    """The three products with the signatures of the operators above."""

    spmm: Callable[..., torch.Tensor]
    spmm_t: Callable[..., torch.Tensor]
    sampled: Callable[..., torch.Tensor]


# Each product is bilinear in two of its inputs (the rest are the pattern and constants), so
# its derivatives in either mode are sums of the three products: one rule per product gives the
# reverse-mode gradients and the forward-mode tangent, written with whichever products the
# caller's mode needs (the operators for their registered backward, the eager functions below
# for derivatives of any order).
Pair = tuple[torch.Tensor | None, torch.Tensor | None]


def _leibniz(
    tangent: Pair,
    first: Callable[[torch.Tensor], torch.Tensor],
    second: Callable[[torch.Tensor], torch.Tensor],
) -> list[torch.Tensor]:
    """The terms ``f(da, b) + f(a, db)`` of the tangent of a bilinear ``f(a, b)`` for
    ``tangent = (da, db)``, ``first(da) = f(da, b)`` and ``second(db) = f(a, db)``; an input
    without a tangent (``None``) adds no term."""
    da, db = tangent
    terms = [] if da is None else [first(da)]
    if db is not None:
        terms.append(second(db))
    return terms


def _spmm_setup(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
    values, crow, col, row, X, symmetric = inputs
    ctx.save_for_backward(values, crow, col, row, X)
    ctx.parts, ctx.symmetric = (crow, col, row), symmetric


def _spmm_grads(ops: _Products, ctx: Any, G: torch.Tensor, needs: Sequence[bool]) -> Pair:
    """``(dvalues, dX)`` of ``Y = A X`` for ``G = dY``."""
    values, crow, col, row, X = ctx.saved_tensors
    grad_values = ops.sampled(G, X, crow, col, row) if needs[0] else None
    grad_X = None
    if needs[1]:
        grad_X = (
            ops.spmm(values, crow, col, row, G, True)
            if ctx.symmetric
            else ops.spmm_t(values, crow, col, row, G, X.shape[0])
        )
    return grad_values, grad_X


def _spmm_tangents(
    ops: _Products, ctx: Any, primal: Sequence[torch.Tensor], tangent: Pair
) -> list[torch.Tensor]:
    """The terms of ``d(A X) = A(dvalues) X + A dX`` (``A(dvalues)`` need not be symmetric)."""
    (values, X), (crow, col, row) = primal, ctx.parts
    return _leibniz(
        tangent,
        lambda dv: ops.spmm(dv, crow, col, row, X, False),
        lambda dX: ops.spmm(values, crow, col, row, dX, ctx.symmetric),
    )


def _spmm_t_setup(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
    values, crow, col, row, G, m = inputs
    ctx.save_for_backward(values, crow, col, row, G)
    ctx.parts, ctx.m = (crow, col, row), m


def _spmm_t_grads(ops: _Products, ctx: Any, H: torch.Tensor, needs: Sequence[bool]) -> Pair:
    """``(dvalues, dG)`` of ``Z = A^T G`` for ``H = dZ``."""
    values, crow, col, row, G = ctx.saved_tensors
    grad_values = ops.sampled(G, H, crow, col, row) if needs[0] else None
    grad_G = ops.spmm(values, crow, col, row, H, False) if needs[1] else None
    return grad_values, grad_G


def _spmm_t_tangents(
    ops: _Products, ctx: Any, primal: Sequence[torch.Tensor], tangent: Pair
) -> list[torch.Tensor]:
    """The terms of ``d(A^T G) = A(dvalues)^T G + A^T dG``."""
    (values, G), (crow, col, row) = primal, ctx.parts
    return _leibniz(
        tangent,
        lambda dv: ops.spmm_t(dv, crow, col, row, G, ctx.m),
        lambda dG: ops.spmm_t(values, crow, col, row, dG, ctx.m),
    )


def _sampled_setup(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
    ctx.save_for_backward(*inputs)
    ctx.parts = inputs[2:5]


def _sampled_grads(ops: _Products, ctx: Any, w: torch.Tensor, needs: Sequence[bool]) -> Pair:
    """``(dG, dX)`` of ``s = (G X^T)|_A`` for ``w = ds``."""
    G, X, crow, col, row = ctx.saved_tensors
    grad_G = ops.spmm(w, crow, col, row, X, False) if needs[0] else None
    grad_X = ops.spmm_t(w, crow, col, row, G, X.shape[0]) if needs[1] else None
    return grad_G, grad_X


def _sampled_tangents(
    ops: _Products, ctx: Any, primal: Sequence[torch.Tensor], tangent: Pair
) -> list[torch.Tensor]:
    """The terms of ``d((G X^T)|_A) = (dG X^T)|_A + (G dX^T)|_A``."""
    G, X = primal
    return _leibniz(
        tangent,
        lambda dG: ops.sampled(dG, X, *ctx.parts),
        lambda dX: ops.sampled(G, dX, *ctx.parts),
    )


class _Rule(NamedTuple):
    """The derivatives of one product."""

    op: Callable[..., torch.Tensor]
    """The custom operator: the arithmetic."""
    setup: Callable[[Any, tuple[Any, ...], torch.Tensor], None]
    """Saves what the derivatives need (its ``setup_context``)."""
    grads: Callable[[_Products, Any, torch.Tensor, Sequence[bool]], Pair]
    """The reverse-mode gradients of the two inputs ``diff``."""
    tangents: Callable[[_Products, Any, Sequence[torch.Tensor], Pair], list[torch.Tensor]]
    """The terms of the forward-mode tangent, from the two inputs and their tangents."""
    diff: tuple[int, int]
    """The positions of the two inputs the product is bilinear in."""


_SPMM = _Rule(spmm_op, _spmm_setup, _spmm_grads, _spmm_tangents, (0, 4))
_SPMM_T = _Rule(spmm_t_op, _spmm_t_setup, _spmm_t_grads, _spmm_t_tangents, (0, 4))
_SAMPLED = _Rule(sampled_op, _sampled_setup, _sampled_grads, _sampled_tangents, (0, 1))


def _gradients(
    rule: _Rule, ops: _Products, ctx: Any, grad: torch.Tensor
) -> tuple[torch.Tensor | None, ...]:
    """The backward of ``rule``'s product, written with ``ops``: a gradient for each of its
    two differentiable inputs, ``None`` for the others."""
    needs = [ctx.needs_input_grad[i] for i in rule.diff]
    pair = rule.grads(ops, ctx, grad, needs)
    out: list[torch.Tensor | None] = [None] * len(ctx.needs_input_grad)
    out[rule.diff[0]], out[rule.diff[1]] = pair
    return tuple(out)


_OPS = _Products(spmm_op, spmm_t_op, sampled_op)

spmm_op.register_autograd(functools.partial(_gradients, _SPMM, _OPS), setup_context=_spmm_setup)
spmm_t_op.register_autograd(
    functools.partial(_gradients, _SPMM_T, _OPS), setup_context=_spmm_t_setup
)
sampled_op.register_autograd(
    functools.partial(_gradients, _SAMPLED, _OPS), setup_context=_sampled_setup
)


# --------------------------------------------------------------------------------------------
# vmap: a batch of value arrays on one pattern is one block-diagonal operator
# --------------------------------------------------------------------------------------------


def _batched(x: torch.Tensor, dim: int | None, batch: int) -> torch.Tensor:
    """``x`` with its batch dimension first, expanded to ``batch`` if it has none."""
    return x.movedim(dim, 0) if dim is not None else x.expand(batch, *x.shape)


def _refuse_batched_indices(in_dims: tuple[int | None, ...], what: str) -> None:
    if any(d is not None for d in in_dims):
        raise NotImplementedError(
            f"torch_polylap: vmap over the sparsity pattern of {what} is not supported; batch "
            "the values (one pattern, several value arrays) or the dense operand instead."
        )


def _product_vmap(
    info: Any,
    in_dims: tuple[int | None, ...],
    values: torch.Tensor,
    parts: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    D: torch.Tensor,
    m: int,
    transpose: bool,
    symmetric: bool,
) -> tuple[torch.Tensor, int]:
    """The vmap rule of ``A D`` (``transpose`` false) or ``A^T D`` for ``A`` ``(n, m)`` on the
    CSR ``parts`` ``(crow, col, row)`` and dense ``D``: one operator and a batch of ``D`` fold
    the batch into the columns; a batch of value arrays is one block-diagonal operator."""
    crow, col, row = parts
    _refuse_batched_indices(
        in_dims[1:4], "a transposed sparse product" if transpose else "a sparse product"
    )
    v_dim, d_dim = in_dims[0], in_dims[4]
    n, B = crow.shape[0] - 1, info.batch_size
    rows_in, rows_out = (n, m) if transpose else (m, n)
    if v_dim is None:
        assert d_dim is not None
        Db = D.movedim(d_dim, 1).reshape(rows_in, -1)  # (rows_in, B * c)
        if transpose:
            out = spmm_t_op(values, crow, col, row, Db, m)
        else:
            out = spmm_op(values, crow, col, row, Db, symmetric)
        return out.reshape(rows_out, B, -1), 1
    Db = _batched(D, d_dim, B).reshape(B * rows_in, -1)
    crow_b, col_b, row_b = block_diagonal_indices(crow, col, row, B, n, m)
    values_b = values.movedim(v_dim, 0).reshape(-1)
    if transpose:
        out = spmm_t_op(values_b, crow_b, col_b, row_b, Db, B * m)
    else:
        out = spmm_op(values_b, crow_b, col_b, row_b, Db, symmetric)
    return out.reshape(B, rows_out, -1), 0


def _spmm_vmap(
    info: Any,
    in_dims: tuple[int | None, ...],
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    X: torch.Tensor,
    symmetric: bool,
) -> tuple[torch.Tensor, int]:
    # A's column count is X's row count (the pattern's arrays do not hold it)
    m = _batched(X, in_dims[4], info.batch_size).shape[1]
    return _product_vmap(info, in_dims, values, (crow, col, row), X, m, False, symmetric)


def _spmm_t_vmap(
    info: Any,
    in_dims: tuple[int | None, ...],
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    G: torch.Tensor,
    m: int,
) -> tuple[torch.Tensor, int]:
    return _product_vmap(info, in_dims, values, (crow, col, row), G, m, True, False)


def _sampled_vmap(
    info: Any,
    in_dims: tuple[int | None, ...],
    G: torch.Tensor,
    X: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
) -> tuple[torch.Tensor, int]:
    _refuse_batched_indices(in_dims[2:], "a sampled product")
    B, n, m = info.batch_size, crow.shape[0] - 1, X.shape[-2]
    Gb = _batched(G, in_dims[0], B).reshape(B * n, -1)
    Xb = _batched(X, in_dims[1], B).reshape(B * m, -1)
    crow_b, col_b, row_b = block_diagonal_indices(crow, col, row, B, n, m)
    return sampled_op(Gb, Xb, crow_b, col_b, row_b).reshape(B, -1), 0


spmm_op.register_vmap(_spmm_vmap)
spmm_t_op.register_vmap(_spmm_t_vmap)
sampled_op.register_vmap(_sampled_vmap)

for _op in ("torch_polylap::spmm", "torch_polylap::spmm_t", "torch_polylap::sampled"):
    for _device in ("cpu", "cuda"):
        torch.library.register_autocast(_op, _device, torch.float32)


# --------------------------------------------------------------------------------------------
# eager entry: the same derivatives, plus forward mode, usable under torch.func transforms
# --------------------------------------------------------------------------------------------
# Custom operators' registered derivatives are not usable under torch.func (their generated
# autograd.Function has no setup_context) and have no forward mode (torch.func.jvp silently
# returns a zero tangent through them). Eagerly, the products therefore go through the
# autograd.Functions below, which call the operators for the arithmetic; traced code, which
# cannot hold an autograd.Function with a forward-mode rule, calls the operators directly.


def _eager_function(rule: _Rule, name: str, doc: str) -> type[torch.autograd.Function]:
    """The eager ``autograd.Function`` of ``rule``'s product: the operator's arithmetic, reverse
    mode as the operator's (written with the eager products, so differentiable again), forward
    mode, and vmap through its own rule."""

    def forward(*inputs: Any) -> torch.Tensor:
        return rule.op(*inputs)

    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
        rule.setup(ctx, inputs, output)
        ctx.save_for_forward(*(inputs[i] for i in rule.diff))

    # the eager products (_EAGER) are defined below, and looked up when a derivative is taken
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        return _gradients(rule, _EAGER, ctx, grad)

    def jvp(ctx: Any, *tangents: Any) -> torch.Tensor:
        pair = (tangents[rule.diff[0]], tangents[rule.diff[1]])
        return _sum(rule.tangents(_EAGER, ctx, ctx.saved_tensors, pair))

    namespace = {
        "__doc__": doc,
        "generate_vmap_rule": True,
        "forward": staticmethod(forward),
        "setup_context": staticmethod(setup_context),
        "backward": staticmethod(backward),
        "jvp": staticmethod(jvp),
    }
    return type(name, (torch.autograd.Function,), namespace)


_Product = _eager_function(_SPMM, "_Product", "``A X`` (eager).")
_TransposedProduct = _eager_function(_SPMM_T, "_TransposedProduct", "``A^T G`` (eager).")
_Sampled = _eager_function(_SAMPLED, "_Sampled", "``(G X^T)|_A`` (eager).")


def _sum(terms: list[torch.Tensor]) -> torch.Tensor:
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def _differentiated(*tensors: torch.Tensor) -> bool:
    """Whether an autograd graph, a forward-mode tangent or a torch.func transform may need
    the derivatives of a product of these tensors."""
    return any(t.requires_grad for t in tensors) or in_functorch() or forward_ad_active()


def _apply(rule: _Rule, function: type[torch.autograd.Function], *inputs: Any) -> torch.Tensor:
    """``rule``'s product of ``inputs``: the operator itself where traced or where nothing may
    need its derivatives (no autograd bookkeeping), else its eager ``function``."""
    if tracing() or not _differentiated(*(inputs[i] for i in rule.diff)):
        return rule.op(*inputs)
    out: torch.Tensor = function.apply(*inputs)
    return out


def spmm(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    X: torch.Tensor,
    symmetric: bool,
) -> torch.Tensor:
    """``A X`` from CSR parts (``X`` ``(m, c)``), differentiable to any order in every mode."""
    return _apply(_SPMM, _Product, values, crow, col, row, X, symmetric)


def spmm_t(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    row: torch.Tensor,
    G: torch.Tensor,
    m: int,
) -> torch.Tensor:
    """``A^T G`` from CSR parts (``G`` ``(n, c)``), differentiable to any order in every mode."""
    return _apply(_SPMM_T, _TransposedProduct, values, crow, col, row, G, m)


def sampled(
    G: torch.Tensor, X: torch.Tensor, crow: torch.Tensor, col: torch.Tensor, row: torch.Tensor
) -> torch.Tensor:
    """``(nnz,)`` entries of ``G X^T`` on the pattern, differentiable in every mode."""
    return _apply(_SAMPLED, _Sampled, G, X, crow, col, row)


_EAGER = _Products(spmm, spmm_t, sampled)


def csr_product(
    pattern: SparsityPattern, values: torch.Tensor, X: torch.Tensor, symmetric: bool
) -> torch.Tensor:
    """``A X`` for ``A`` = (``pattern``, ``values``) ``(n, m)`` and dense ``X`` ``(m, c)``.

    Differentiable in ``values`` and ``X`` to any order; ``symmetric`` (``A = A^T``) lets the
    backward multiply by ``A`` itself instead of its transpose.
    """
    return spmm(values, pattern.crow, pattern.col, pattern.row, X, symmetric)


def sampled_product(pattern: SparsityPattern, G: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``(nnz,)`` entries of ``G X^T`` on ``pattern``: ``s_k = sum_c G[row_k, c] X[col_k, c]``.

    The gradient of ``loss(A X)`` with respect to ``A``'s values, for ``G = dloss / d(A X)``.
    ``G`` ``(n, c)``, ``X`` ``(m, c)``.  Differentiable in both to any order.
    """
    return sampled(G, X, pattern.crow, pattern.col, pattern.row)
