"""Sparse products with an O(nnz) backward, and conversion to and from scipy.sparse.

Why this module exists: torch's own autograd for ``sparse @ dense`` materializes a *dense*
``n x m`` gradient for the sparse operand (MATH.md measured +1.5 GB at 20k vertices; at 1M
vertices it asks for terabytes).  :func:`spmm` computes the same product with torch's CSR
kernel, and its backward returns the gradient of the sparse operand's values on its sparsity
pattern only (a sampled dense-dense product) and the gradient of the dense operand as
``A^T G``.  Every loss, solver and layer in torch_polylap goes through it; use it in your own
code whenever gradients must reach the values of ``L`` or ``M0``.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch

__all__ = [
    "spmm",
    "to_scipy",
    "from_scipy",
    "csr_parts",
    "mark_symmetric",
    "csr_tensor",
    "coo_tensor",
    "sparse_values",
]

_SYMMETRIC_FLAG = "_polylap_symmetric"
_VALUES_LINK = "_polylap_values"


def csr_tensor(
    crow: torch.Tensor, col: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]
) -> torch.Tensor:
    """A torch sparse CSR tensor from arrays this package built (and so already knows valid).

    Skips torch's invariant checks and its one-time "CSR support is in beta" warning, which
    would otherwise be shown to every user of the package for matrices it constructs itself.
    The tensor remembers ``values`` (see :func:`sparse_values`), so that products through
    :func:`spmm` send gradients straight to it instead of through torch's sparse-tensor autograd.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse.*")
        A = torch.sparse_csr_tensor(crow, col, values, shape, check_invariants=False)
    setattr(A, _VALUES_LINK, values)
    return A


def coo_tensor(indices: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """A coalesced COO tensor from sorted, duplicate-free ``indices`` (see :func:`csr_tensor`)."""
    A = torch.sparse_coo_tensor(indices, values, shape, is_coalesced=True, check_invariants=False)
    setattr(A, _VALUES_LINK, values)
    return A


def sparse_values(A: torch.Tensor) -> torch.Tensor:
    """The value array of a sparse CSR/COO tensor, differentiable without densifying.

    torch's backward of ``A.values()`` for a CSR tensor materializes a dense ``n x m`` gradient.
    Tensors made by this package keep a link to the tensor their values were built from, and
    that tensor is returned here, so gradients flow in O(nnz).
    """
    linked = getattr(A, _VALUES_LINK, None)
    if linked is not None:
        return linked
    if A.layout == torch.sparse_coo and not A.is_coalesced():
        raise ValueError(
            "expected a coalesced COO tensor (call A.coalesce() once) or a CSR tensor."
        )
    return A.values()


def mark_symmetric(A: torch.Tensor) -> torch.Tensor:
    """Record that ``A`` is symmetric, so :func:`spmm`'s backward can use ``A`` for ``A^T``.

    ``laplacian`` marks the ``L`` and ``M0`` it returns.  A tensor derived from them (``2 * L``,
    ``L + M0``) loses the mark and takes the general path, which is correct but has to sort the
    pattern once per backward to transpose it.
    """
    setattr(A, _SYMMETRIC_FLAG, True)
    return A


def csr_parts(A: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(crow, col, values)`` of a 2-D sparse CSR or COO tensor; ``values`` stays differentiable.

    A COO tensor must be coalesced (sorted by row, then column), which makes its value array
    the CSR value array of the same matrix.
    """
    if A.layout == torch.sparse_csr:
        return A.crow_indices(), A.col_indices(), sparse_values(A)
    if A.layout == torch.sparse_coo:
        values = sparse_values(A)
        row, col = A.indices()
        crow = torch.zeros(A.shape[0] + 1, dtype=torch.int64, device=A.device)
        torch.cumsum(torch.bincount(row, minlength=A.shape[0]), 0, out=crow[1:])
        return crow, col, values
    raise ValueError(f"expected a sparse CSR or COO matrix, got layout {A.layout}.")


def _transpose_csr(
    crow: torch.Tensor, col: torch.Tensor, n_rows: int, n_cols: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """CSR pattern of ``A^T`` and the permutation taking ``A``'s values to ``A^T``'s."""
    row = torch.repeat_interleave(torch.arange(n_rows, device=crow.device), crow.diff())
    key = col * n_rows + row
    if key.device.type == "cpu":
        perm = torch.from_numpy(np.argsort(key.numpy(), kind="stable"))
    else:
        perm = torch.argsort(key, stable=True)
    crow_t = torch.zeros(n_cols + 1, dtype=torch.int64, device=crow.device)
    torch.cumsum(torch.bincount(col, minlength=n_cols), 0, out=crow_t[1:])
    return crow_t, row[perm], perm


class _CSRMatmul(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values, X, crow, col, shape, symmetric):
        A = csr_tensor(crow, col, values.detach(), shape)
        ctx.save_for_backward(values, X, crow, col)
        ctx.shape, ctx.symmetric = shape, symmetric
        return A @ X

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, G):
        values, X, crow, col = ctx.saved_tensors
        n, m = ctx.shape
        grad_values = grad_X = None
        G = G.contiguous()
        if ctx.needs_input_grad[0]:
            # dLoss/dA_ij = (G X^T)_ij, needed on the pattern only: a sampled product, O(nnz * c).
            pattern = csr_tensor(crow, col, torch.zeros_like(values), (n, m))
            grad_values = torch.sparse.sampled_addmm(pattern, G, X.t(), beta=0.0).values()
        if ctx.needs_input_grad[1]:
            if ctx.symmetric:
                grad_X = csr_tensor(crow, col, values, (n, m)) @ G
            else:
                crow_t, col_t, perm = _transpose_csr(crow, col, n, m)
                grad_X = csr_tensor(crow_t, col_t, values[perm], (m, n)) @ G
        return grad_values, grad_X, None, None, None, None


def spmm(A: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """``A @ X`` for a sparse ``A`` and dense ``X``, differentiable in ``A``'s values and ``X``.

    Args:
        A: ``(n, m)`` sparse CSR tensor, or coalesced COO tensor.
        X: ``(m,)`` or ``(m, c)`` dense tensor of ``A``'s dtype and device.

    Returns:
        ``(n,)`` or ``(n, c)``.

    Backward costs ``O(nnz * c)`` time and memory: ``grad(values) = (G X^T)`` sampled on ``A``'s
    pattern, ``grad(X) = A^T G`` (``A`` itself when ``A`` is marked symmetric, as the operators of
    :func:`torch_polylap.laplacian` are).  Never call ``torch.sparse.mm`` / ``A @ X`` directly on
    operators whose values require grad: torch's backward builds a dense ``n x m`` matrix.
    Double backward is not supported.
    """
    if X.dtype != A.dtype:
        raise ValueError(f"spmm: A has dtype {A.dtype} but X has {X.dtype}; convert one of them.")
    if A.dim() != 2 or X.dim() not in (1, 2) or X.shape[0] != A.shape[1]:
        raise ValueError(
            f"spmm: cannot multiply A of shape {tuple(A.shape)} with X of shape {tuple(X.shape)}."
        )
    crow, col, values = csr_parts(A)
    vec = X.dim() == 1
    if not (torch.is_grad_enabled() and (values.requires_grad or X.requires_grad)):
        # nothing to differentiate: skip the autograd.Function (its fixed cost dominates on
        # small meshes) and use the CSR product directly
        A_csr = A if A.layout == torch.sparse_csr else csr_tensor(crow, col, values, A.shape)
        return A_csr.detach() @ X
    Y = _CSRMatmul.apply(
        values,
        X.unsqueeze(1) if vec else X,
        crow,
        col,
        (A.shape[0], A.shape[1]),
        bool(getattr(A, _SYMMETRIC_FLAG, False)),
    )
    return Y.squeeze(1) if vec else Y


def to_scipy(A: torch.Tensor) -> sp.csr_matrix:
    """A sparse (CSR/COO) or dense 2-D tensor as a ``scipy.sparse.csr_matrix`` (detached, CPU)."""
    if A.layout == torch.strided:
        return sp.csr_matrix(A.detach().cpu().numpy())
    crow, col, values = csr_parts(A)
    return sp.csr_matrix(
        (values.detach().cpu().numpy(), col.cpu().numpy(), crow.cpu().numpy()), shape=tuple(A.shape)
    )


def from_scipy(
    S: sp.spmatrix | sp.sparray,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """A scipy sparse matrix as a torch sparse CSR tensor (indices sorted, duplicates summed)."""
    S = sp.csr_matrix(S)
    S.sum_duplicates()
    S.sort_indices()
    values = torch.from_numpy(S.data).to(device=device, dtype=dtype)
    return csr_tensor(
        torch.from_numpy(S.indptr.astype(np.int64)).to(values.device),
        torch.from_numpy(S.indices.astype(np.int64)).to(values.device),
        values,
        S.shape,
    )
