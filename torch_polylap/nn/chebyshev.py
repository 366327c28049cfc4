"""Chebyshev polynomial filters of the polygon Laplacian (ChebConv, Defferrard et al. 2016).

The operator is the Alexa-Wardetzky Laplacian (AW11 eq. 3, 9) normalized by the lumped mass
(AW11 eq. 10) and rescaled so that its spectrum lies in ``[-1, 1]``:

* ``"sym"``: ``S = M0^{-1/2} L M0^{-1/2}`` (symmetric);
* ``"rw"``:  ``S = M0^{-1} L`` (the strong Laplacian; same eigenvalues, not symmetric);

``S_hat = 2 S / lambda_max - I``, where ``lambda_max`` is the Gershgorin bound
``max_i sum_j |S_ij|`` of each mesh of a batch (a guaranteed upper bound on the spectrum,
unlike a few power iterations, which approach it from below; pass ``lambda_max`` from
:func:`torch_polylap.eigs` for a tight one).  A filter of ``K`` terms computes
``y = sum_{k<K} T_k(S_hat) x W_k`` with the recursion ``T_0 x = x``, ``T_1 x = S_hat x``,
``T_k x = 2 S_hat T_{k-1} x - T_{k-2} x``: ``K - 1`` sparse products ``S_hat @ x`` (O(nnz)
backward, gradients to ``L``'s and ``M0``'s values).

torch.compile: Dynamo does not trace frames that take sparse CSR tensors; a compiled
``ChebyshevFilter`` runs eagerly (correct results, no graph: checked with
``torch._dynamo.explain`` on torch 2.13, CPU). Compile the dense parts of a model around it.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..sparse import as_operator, identity
from ..sparse.construct import mark_symmetric
from ..tracing import require
from .spectrum import masses_of

__all__ = ["chebyshev_operator", "chebyshev_filter", "ChebyshevFilter"]


def chebyshev_operator(
    L: torch.Tensor,
    M0: torch.Tensor,
    normalization: str = "sym",
    *,
    vert_to_mesh: torch.Tensor | None = None,
    num_meshes: int | None = None,
    lambda_max: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """``S_hat = 2 S / lambda_max - I`` on ``L``'s sparsity pattern (see the module docstring).

    Args:
        L: ``(V, V)`` sparse Laplacian (block-diagonal for a batch).
        M0: ``(V, V)`` sparse diagonal mass matrix, or its ``(V,)`` diagonal.
        normalization: ``"sym"`` or ``"rw"``.
        vert_to_mesh: ``(V,)`` mesh index of each vertex of a packed batch; each mesh gets its
            own ``lambda_max``, so a batch gives the same result as its meshes one by one.
        num_meshes: number of meshes (default ``vert_to_mesh.max() + 1``).
        lambda_max: upper bound(s) on the spectrum, a scalar or ``(B,)``; default Gershgorin.

    Returns:
        ``(V, V)`` sparse operator, differentiable in ``L``'s and ``M0``'s values.
    """
    if normalization not in ("sym", "rw"):
        raise ValueError(f"normalization must be 'sym' or 'rw', got {normalization!r}.")
    L = as_operator(L)
    m = masses_of(M0).to(L.dtype)
    n = L.shape[0]
    if not require(
        m > 0, "chebyshev_operator: M0 has a mass <= 0; see remove_unreferenced_vertices"
    ):
        # the normalization divides by the masses: a zero one (a vertex no face references)
        # would fill the whole operator with NaN through lambda_max
        bad = torch.nonzero(~(m > 0))[:, 0]
        raise ValueError(
            f"chebyshev_operator: vertex {int(bad[0])} has mass {float(m[bad[0]]):g} "
            f"({bad.numel()} such vertices), and the normalization divides by the masses. A "
            "vertex that no face references has none: remove such vertices first with "
            "torch_polylap.repair.remove_unreferenced_vertices(verts, faces)."
        )
    if normalization == "sym":
        r = torch.rsqrt(m)
        S = L * r[:, None] * r[None, :]
    else:
        S = L / m[:, None]
    if vert_to_mesh is None:
        vert_to_mesh = torch.zeros(n, dtype=torch.int64, device=L.device)
        num_meshes = 1
    elif num_meshes is None:
        num_meshes = int(vert_to_mesh.max()) + 1
    if lambda_max is None:
        lambda_max = m.new_zeros(num_meshes).scatter_reduce(
            0, vert_to_mesh, S.abs().sum(1), "amax", include_self=False
        )
    lam = torch.as_tensor(lambda_max, dtype=L.dtype, device=L.device)
    lam_v = lam.expand(num_meshes)[vert_to_mesh]
    S_hat = S * (2.0 / lam_v)[:, None] - identity(n, dtype=L.dtype, device=L.device)
    # the per-vertex factors are constant on each mesh's block: D^-1/2 L D^-1/2 stays symmetric
    return mark_symmetric(S_hat) if normalization == "sym" else S_hat


def chebyshev_filter(x: torch.Tensor, S_hat: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``sum_k T_k(S_hat) x weight[k]``.

    Args:
        x: ``(V, C_in)``; S_hat: ``(V, V)`` sparse from :func:`chebyshev_operator`;
        weight: ``(K, C_in, C_out)``.

    Returns:
        ``(V, C_out)``.
    """
    K = weight.shape[0]
    t_prev, t_cur = x, x  # T_0 x; t_cur is T_k x from k = 1 on
    out = x @ weight[0]
    for k in range(1, K):
        if k == 1:
            t_cur = S_hat @ x
        else:
            t_prev, t_cur = t_cur, 2.0 * (S_hat @ t_cur) - t_prev
        out = out + t_cur @ weight[k]
    return out


class ChebyshevFilter(nn.Module):
    """Learnable ``K``-term Chebyshev filter ``(sumV, C_in) -> (sumV, C_out)``.

    Args:
        in_channels: ``C_in``, the channels of the input.
        out_channels: ``C_out``, the channels of the output.
        K: number of polynomial terms (degree ``K - 1``, support ``K - 1`` rings).
        normalization: ``"sym"`` or ``"rw"`` (see :func:`chebyshev_operator`).
        bias: add a learnable ``(C_out,)`` bias.

    ``forward(x, L=None, M0=None, *, operator=None, vert_to_mesh=None)``: pass the batch's
    block-diagonal ``L, M0`` (and ``vert_to_mesh`` for per-mesh scaling), or a precomputed
    ``operator`` from :func:`chebyshev_operator` to reuse it across layers and steps.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        K: int = 3,
        normalization: str = "sym",
        *,
        bias: bool = True,
    ) -> None:
        super().__init__()
        if K < 1:
            raise ValueError(f"K must be at least 1, got {K}.")
        self.in_channels, self.out_channels, self.K = in_channels, out_channels, K
        self.normalization = normalization
        bound = math.sqrt(6.0 / (K * in_channels + out_channels))  # Glorot over the K terms
        self.weight = nn.Parameter(
            torch.empty(K, in_channels, out_channels).uniform_(-bound, bound)
        )
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None

    def forward(
        self,
        x: torch.Tensor,
        L: torch.Tensor | None = None,
        M0: torch.Tensor | None = None,
        *,
        operator: torch.Tensor | None = None,
        vert_to_mesh: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if operator is None:
            if L is None or M0 is None:
                raise ValueError("ChebyshevFilter needs L and M0, or a precomputed `operator`.")
            operator = chebyshev_operator(L, M0, self.normalization, vert_to_mesh=vert_to_mesh)
        out = chebyshev_filter(x, operator, self.weight.to(x.dtype))
        return out if self.bias is None else out + self.bias.to(x.dtype)

    def extra_repr(self) -> str:
        return (
            f"{self.in_channels}, {self.out_channels}, K={self.K}, "
            f"normalization={self.normalization!r}"
        )
