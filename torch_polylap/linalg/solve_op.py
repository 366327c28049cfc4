"""The sparse solve as a ``torch.library`` operator, for code that torch.compile traces.

A factorization (CHOLMOD, SuperLU) or a CG loop is not traceable, so traced code holds
``X = A^{-1} B`` as one node, ``torch_polylap::solve``, whose fake kernel gives ``B``'s shape.
Its derivative is registered on it and written with the operator itself and the sampled
product: ``dB = A^{-T} G`` and ``dvalues = -(A^{-T} G) X^T`` on the pattern, so second
derivatives through it work too.  Eagerly, :func:`torch_polylap.solve` keeps its
``autograd.Function``, which also shares factorizations between the forward and backward.
"""

from __future__ import annotations

from typing import Any

import torch

from ..sparse import SparseOperator, operator_from_parts
from ..sparse.autograd import sampled_op
from .cg import cg_solve
from .factor import cached_factorization

__all__ = ["solve_op", "solve_values"]


def solve_values(
    A: SparseOperator, B: torch.Tensor, backend: str, tol: float, max_iter: int
) -> torch.Tensor:
    """``A^{-1} B`` for ``(n, c)`` ``B``, no autograd."""
    if backend == "cg":
        return cg_solve(A, B.detach(), tol, max_iter)
    return cached_factorization(A, backend).solve(B)


@torch.library.custom_op("torch_polylap::solve", mutates_args=())
def solve_op(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    B: torch.Tensor,
    symmetric: bool,
    backend: str,
    tol: float,
    max_iter: int,
) -> torch.Tensor:
    """``A^{-1} B`` for ``A`` ``(n, n)`` on CSR indices ``crow``, ``col``; ``B`` ``(n, c)``."""
    n = crow.numel() - 1
    A = operator_from_parts(crow, col, values, (n, n), symmetric=symmetric)
    return solve_values(A, B, backend, tol, max_iter)


@solve_op.register_fake
def _solve_fake(
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    B: torch.Tensor,
    symmetric: bool,
    backend: str,
    tol: float,
    max_iter: int,
) -> torch.Tensor:
    return torch.empty_like(B)


def _setup(ctx: Any, inputs: tuple[Any, ...], output: torch.Tensor) -> None:
    values, crow, col, B, symmetric, backend, tol, max_iter = inputs
    ctx.save_for_backward(values, crow, col, output)
    ctx.options = (symmetric, backend, tol, max_iter)


def _backward(ctx: Any, G: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
    values, crow, col, X = ctx.saved_tensors
    symmetric = ctx.options[0]
    if not symmetric:
        raise NotImplementedError(
            "torch_polylap: inside torch.compile, the derivative of a solve is available for "
            "symmetric operators (M0 + t L, Dirichlet blocks of L); solve a non-symmetric one "
            "outside the compiled code."
        )
    gB = solve_op(values, crow, col, G, *ctx.options)
    grad_values = None
    if ctx.needs_input_grad[0]:
        n = crow.numel() - 1
        row = torch.repeat_interleave(
            torch.arange(n, device=crow.device), crow.diff(), output_size=col.shape[0]
        )
        grad_values = -sampled_op(gB, X, crow, col, row)
    return grad_values, None, None, gB, None, None, None, None


solve_op.register_autograd(_backward, setup_context=_setup)


def _solve_vmap(
    info: Any,
    in_dims: tuple[int | None, ...],
    values: torch.Tensor,
    crow: torch.Tensor,
    col: torch.Tensor,
    B: torch.Tensor,
    *options: Any,
) -> tuple[torch.Tensor, int]:
    if in_dims[0] is not None or in_dims[1] is not None or in_dims[2] is not None:
        raise NotImplementedError(
            "torch_polylap: vmap over the matrix of a solve is not supported; batch the "
            "right-hand sides, or stack the systems with torch_polylap.sparse.block_diag."
        )
    b_dim = in_dims[3]
    assert b_dim is not None
    Bb = B.movedim(b_dim, 1)  # (n, batch, c)
    X = solve_op(values, crow, col, Bb.reshape(Bb.shape[0], -1), *options)
    return X.reshape(Bb.shape), 1


solve_op.register_vmap(_solve_vmap)
for _device in ("cpu", "cuda"):
    torch.library.register_autocast("torch_polylap::solve", _device, torch.float32)
