"""Derivatives of generalized eigenpairs ``L phi = mu M phi``: eigenvalues by first-order
perturbation (``d mu = phi^T (dL - mu dM) phi``), eigenvectors by Nelson's method (one sparse
solve with ``L - mu M`` per eigenpair, with a rule for clusters of near-repeated eigenvalues).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..sparse import SparseOperator, to_scipy
from ..sparse.construct import sampled_gradient

_SECOND_ORDER_MESSAGE = (
    "torch_polylap.eigs: second derivatives of eigenvalues and eigenvectors (create_graph=True "
    "through eigs, Hessian-vector products) are not implemented: their backward factorizes with "
    "scipy outside autograd. Take first-order gradients only, or detach the eigenpairs in the "
    "second-order term."
)


class _EigenpairFunction(torch.autograd.Function):
    """What the eigenpair Functions share: the forward saves the eigenpairs ``evals`` ``(k,)``,
    ``evecs`` ``(n, k)`` and the operators ``L``, ``M`` for the backward, which refuses second
    derivatives. Inputs ``(l_values, m_values, evals, evecs, opaque_l, opaque_m)``, the last two
    ``OpaqueOperator`` wrappers of ``L`` and ``M``: autograd differentiates only the value
    arrays."""

    @staticmethod
    def _save(ctx: Any, inputs: tuple[Any, ...]) -> tuple[torch.Tensor, torch.Tensor]:
        """Save what the backward needs from the forward's ``inputs``; ``(evals, evecs)``."""
        _, _, evals, evecs, opaque_l, opaque_m = inputs
        ctx.save_for_backward(evals, evecs)
        ctx.operators = (opaque_l.A, opaque_m.A)
        return evals, evecs

    @staticmethod
    def _saved(ctx: Any) -> tuple[torch.Tensor, torch.Tensor, SparseOperator, SparseOperator]:
        """``(evals, evecs, L, M)`` as the forward saved them."""
        if torch.is_grad_enabled():
            raise RuntimeError(_SECOND_ORDER_MESSAGE)
        evals, evecs = ctx.saved_tensors
        return evals, evecs, *ctx.operators


class Eigenvalues(_EigenpairFunction):
    """Eigenvalues ``mu`` of ``L phi = mu M phi`` with the first-order perturbation gradient."""

    @staticmethod
    def forward(ctx: Any, *inputs: Any) -> torch.Tensor:
        evals, _ = _EigenpairFunction._save(ctx, inputs)
        return evals.clone()

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        evals, evecs, L, M = _EigenpairFunction._saved(ctx)
        grads = []
        for A, weights, needed in (
            (L, g, ctx.needs_input_grad[0]),
            (M, -g * evals, ctx.needs_input_grad[1]),
        ):
            # sum_i w_i phi_i phi_i^T, sampled on the pattern: O(nnz * k)
            grads.append(sampled_gradient(A, evecs * weights, evecs) if needed else None)
        return grads[0], grads[1], None, None, None, None


# A requested eigenvector has no derivative when another eigenvalue lies within this distance of
# its own, relative to the spectral scale (:func:`spectral_scale`): the computed eigenvectors,
# and the adjoint solve with L - mu M, lose about eps * scale / gap of their accuracy, so below
# it fewer than half the digits are left, and round-off alone splits an exactly repeated
# eigenvalue by far less.
EIGENVECTOR_GAP_RTOL = 1e-8
# Inverse-iteration steps that estimate the gap to the first eigenvalue that was not computed.
_GAP_ITERATIONS = 4


def spectral_scale(evals: np.ndarray, Ls: sp.spmatrix, Ms: sp.spmatrix) -> float:
    """The scale against which :data:`EIGENVECTOR_GAP_RTOL` measures eigenvalue gaps: the
    largest of ``|mu_i|`` over the computed ``evals`` ``(k,)`` and ``max_i |L_ii| / M_ii``
    (the Rayleigh quotient of a unit vector: a lower bound of the spectral radius of
    ``M^{-1} L``, within a small factor of it for a Laplacian). The computed eigenvalues alone
    would not do: the smallest ones of a Laplacian are about 0 (one per connected component,
    and a parallel field on a flat or developable surface), so a gap relative to them is
    relative to round-off, and a repeated eigenvalue at 0 passed as simple. O(n)."""
    diagonal = np.abs(Ls.diagonal()) / Ms.diagonal()
    operator = float(diagonal.max()) if diagonal.size else 0.0
    return max(float(np.abs(evals).max()), operator, np.finfo(float).tiny)


def _cluster_message(
    index: int, members: list[int], evals: np.ndarray, scale: float, reason: str
) -> str:
    values = ", ".join(f"mu_{j} = {evals[j]:.12g}" for j in members)
    which = f"eigenvalues {members[0]}..{members[-1]}" if len(members) > 1 else "eigenvalue"
    return (
        f"torch_polylap.eigs: no gradient through evecs[:, {index}]: its eigenvalue is repeated "
        f"({which} {values}{reason}; gap below {EIGENVECTOR_GAP_RTOL:g} times the spectral "
        f"scale {scale:.6g}, the largest of |mu| and max |L_ii| / M_ii), so each eigenvector "
        "of the cluster is any M-orthonormal basis vector of the eigenspace and not a "
        "differentiable function of L and M (a symmetric mesh, e.g. a regular grid, has exact "
        "multiplicities; so has the eigenvalue 0 of a mesh of several connected components, "
        "one per component). Use a loss that depends on the "
        "cluster's eigenvectors only through their span, with every eigenpair of the cluster "
        "computed: the projector Phi_C Phi_C^T M (e.g. sum_i (phi_i^T M u)^2 over the cluster) "
        "or symmetric functions of its eigenvalues (evals are differentiable); or use "
        "evecs.detach(), or only columns outside the cluster."
    )


def _clusters(evals: np.ndarray, scale: float) -> list[list[int]]:
    """Runs of consecutive eigenvalues whose neighbours lie within the gap."""
    close = np.abs(np.diff(evals)) <= EIGENVECTOR_GAP_RTOL * scale  # mu_j ~ mu_{j+1}
    runs = [[0]]
    for j in range(1, evals.size):
        if close[j - 1]:
            runs[-1].append(j)
        else:
            runs.append([j])
    return runs


def _eigenvector_adjoint(
    Ls: sp.csr_matrix,
    Ms: sp.csr_matrix,
    mu: float,
    Phi: np.ndarray,
    g: np.ndarray,
    check_next: float | None,
) -> tuple[np.ndarray, float]:
    """The adjoint ``w`` of one eigenvector whose eigenvalue ``mu`` has the cluster ``Phi``
    ``(n, m)`` (itself and the eigenvectors of eigenvalues within the gap; ``m = 1`` for a
    simple one): ``(L - mu M) w = (I - M Phi Phi^T) g`` with ``Phi^T M w = 0``, by Nelson's
    method.

    ``K = L - mu M`` is singular on ``span(Phi)``. Deleting the rows and columns ``P`` of ``m``
    well-conditioned rows of ``Phi`` (pivoted QR; for ``m = 1`` the largest entry) leaves a
    nonsingular matrix (an ``x`` with ``x_P = 0`` and ``K x = e_P c`` has
    ``0 = Phi^T K x = Phi_P^T c``, so ``x`` is in the kernel and ``0``). Its solution with
    ``x_P = 0`` satisfies rows ``P`` as well, because the right-hand side is orthogonal to
    ``Phi``; projecting out ``Phi`` gives ``w``. One sparse LU (SuperLU, partial pivoting: ``K``
    is indefinite) of the ``(n-m) x (n-m)`` matrix, then freed.

    ``check_next``: the spectral scale, when the cluster holds the last computed eigenpair,
    whose upper neighbour is unknown: inverse iteration with the same factorization on
    ``T = (I - Phi Phi^T M) K^+ M``
    (eigenvalues ``1 / (mu_j - mu)`` for the eigenvalues outside the cluster) bounds the
    distance to the nearest one from above, ``|mu_j - mu| <= 1 / |T x|_M``. Returns ``w`` and
    the estimated nearest outside eigenvalue (``nan`` without ``check_next``, or when it is
    farther than the gap).
    """
    n, m = Phi.shape
    if m == 1:
        P = np.array([int(np.abs(Phi[:, 0]).argmax())])
    else:
        P = scipy.linalg.qr(Phi.T, mode="r", pivoting=True)[1][:m]
    keep = np.setdiff1d(np.arange(n), P)
    K = (Ls - mu * Ms).tocsr()
    lu = spla.splu(sp.csc_matrix(K[keep][:, keep]))
    MPhi = Ms @ Phi

    def project_solve(r: np.ndarray) -> np.ndarray:
        x = np.zeros(n)
        x[keep] = lu.solve(np.ascontiguousarray(r[keep]))
        # one step of iterative refinement (the shifted matrix is nearly singular)
        residual = r - K @ x
        x[keep] += lu.solve(np.ascontiguousarray(residual[keep]))
        return x - Phi @ (MPhi.T @ x)

    nearest = float("nan")
    if check_next is not None:
        x = np.random.default_rng(0).standard_normal((n,))
        x -= Phi @ (MPhi.T @ x)
        t = norm = 0.0
        for _ in range(_GAP_ITERATIONS):
            x /= np.sqrt(x @ (Ms @ x))
            y = project_solve(Ms @ x)
            t = float(x @ (Ms @ y))  # Rayleigh quotient of T: about 1 / (mu_j - mu)
            norm = float(np.sqrt(y @ (Ms @ y)))
            x = y
        if 1.0 <= EIGENVECTOR_GAP_RTOL * check_next * norm:
            nearest = mu + 1.0 / t if t != 0 else mu
    return project_solve(g - MPhi @ (Phi.T @ g)), nearest


class Eigenvectors(_EigenpairFunction):
    """Eigenvectors of ``L phi = mu M phi`` (``M``-orthonormal, sign fixed) with the adjoint
    gradient (see :func:`eigs`)."""

    @staticmethod
    def forward(ctx: Any, *inputs: Any) -> torch.Tensor:
        _, evecs = _EigenpairFunction._save(ctx, inputs)
        return evecs.clone()

    @staticmethod
    def backward(ctx: Any, G: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        evals_t, evecs_t, L, M = _EigenpairFunction._saved(ctx)
        need_l, need_m = ctx.needs_input_grad[:2]
        if not (need_l or need_m):
            return None, None, None, None, None, None
        evals = evals_t.detach().cpu().double().numpy()
        Phi = evecs_t.detach().cpu().double().numpy()
        Gn = G.detach().cpu().double().numpy()
        k = evals.size
        active = np.any(Gn != 0, axis=0)
        Ls = to_scipy(L).astype(np.float64)
        Ms = to_scipy(M).astype(np.float64)
        scale = spectral_scale(evals, Ls, Ms)
        # A_ij = phi_i^T g_j on each cluster's diagonal block: the in-cluster coupling
        A = np.zeros((k, k))
        runs = [c for c in _clusters(evals, scale) if active[c].any()]
        for c in runs:
            block = Phi[:, c].T @ Gn[:, c]
            if len(c) > 1:
                # the loss must not change under rotations within the cluster: A symmetric
                tol = np.sqrt(np.finfo(evecs_t.detach().cpu().numpy().dtype).eps)
                size = np.linalg.norm(Phi[:, c]) * np.linalg.norm(Gn[:, c])
                if np.abs(block - block.T).max() > tol * size:
                    index = c[int(np.flatnonzero(active[c])[0])]
                    raise RuntimeError(
                        _cluster_message(
                            index,
                            c,
                            evals,
                            scale,
                            "; the loss is not invariant to rotations "
                            "of the cluster's eigenvectors",
                        )
                    )
                block = 0.5 * (block + block.T)
            A[np.ix_(c, c)] = block
        W = np.zeros_like(Phi)
        for c in runs:
            for i in (j for j in c if active[j]):
                try:
                    W[:, i], nearest = _eigenvector_adjoint(
                        Ls,
                        Ms,
                        evals[i],
                        Phi[:, c],
                        Gn[:, i],
                        check_next=scale if c[-1] == k - 1 else None,
                    )
                except RuntimeError as error:  # SuperLU: exactly singular
                    raise RuntimeError(
                        _cluster_message(i, c, evals, scale, f" (SuperLU: {error})")
                    ) from error
                if not np.isnan(nearest):
                    raise RuntimeError(
                        _cluster_message(
                            i,
                            c,
                            evals,
                            scale,
                            f", and the next eigenvalue, which was not "
                            f"computed, near {nearest:.12g}; compute more eigenpairs",
                        )
                    )
        Wt = torch.from_numpy(W).to(evecs_t)
        mu = evals_t.detach()
        Phi_t = evecs_t.detach()
        grad_l = grad_m = None
        # symmetrized (the gradient among symmetric matrices): (w phi^T + phi w^T) / 2
        if need_l:
            grad_l = -0.5 * sampled_gradient(
                L, torch.cat([Wt, Phi_t], 1), torch.cat([Phi_t, Wt], 1)
            )
        if need_m:
            # the M-orthonormality of each cluster: -(1/2) sum_ij A_ij phi_i phi_j^T (for a
            # simple eigenvalue, the normalization term -(phi^T g / 2) phi phi^T)
            At = torch.from_numpy(A).to(evecs_t)
            grad_m = 0.5 * sampled_gradient(
                M,
                torch.cat([Wt * mu, Phi_t * mu, -(Phi_t @ At)], 1),
                torch.cat([Phi_t, Wt, Phi_t], 1),
            )
        return grad_l, grad_m, None, None, None, None


# The top eigenvalue of top_eigenpair has a derivative only when it is simple to this relative
# gap (of the largest eigenvalue magnitude).
TOP_GAP_RTOL = 1e-10


class _TopEigenpair(torch.autograd.Function):
    """Largest eigenvalue and a unit eigenvector of a dense Hermitian matrix.

    The backward is the top column of ``torch.linalg.eigh``'s:
    ``gM = g_nu x x^H + sum_{j != top} v_j (v_j^H g_x) / (nu - mu_j) x^H``, which divides only by
    the gaps to the top eigenvalue. ``eigh``'s own backward divides by every gap and turns a
    repeated eigenvalue elsewhere in the spectrum (symmetric meshes have them) into NaN.
    """

    @staticmethod
    def forward(ctx: Any, M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        evals, V = torch.linalg.eigh(M)
        ctx.save_for_backward(evals, V)
        return evals[-1].clone(), V[:, -1].clone()

    @staticmethod
    def backward(ctx: Any, g_nu: torch.Tensor, g_x: torch.Tensor) -> torch.Tensor:
        evals, V = ctx.saved_tensors
        x, rest = V[:, -1], V[:, :-1]
        gap = evals[-1] - evals[:-1]
        scale = float(evals.abs().max()) if evals.numel() else 0.0
        if gap.numel() and float(gap.min()) <= TOP_GAP_RTOL * scale:
            raise ValueError(
                "top_eigenpair: the largest eigenvalue is repeated (gap "
                f"{float(gap.min()):.3g} of {scale:.3g}), so its eigenvector is any vector of "
                "the eigenspace and has no derivative."
            )
        w = rest @ ((rest.mH @ g_x) / gap.to(V.dtype)) if g_x is not None else torch.zeros_like(x)
        gM = torch.outer(w, x.conj())
        if g_nu is not None:
            gM = gM + g_nu.to(V.dtype) * torch.outer(x, x.conj())
        return gM


def top_eigenpair(M: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Largest eigenvalue ``nu`` and a unit eigenvector ``x`` of a dense Hermitian ``(n, n)``
    ``M`` (real symmetric or complex), differentiable when ``nu`` is simple and the loss does
    not depend on the eigenvector's sign or phase. Returns ``nu`` (real, ``()``) and ``x``
    (``(n,)``)."""
    nu, x = _TopEigenpair.apply(M)
    return nu, x
