"""Eigenvector gradients through ``tp.eigs`` where an eigenvalue is repeated at or near 0 (a mesh
of two components, the parallel fields of a developable surface) and at a symmetric mesh's
nonzero eigenvalues: the backward refuses exactly where the eigenvectors are not functions of
the mesh, and elsewhere agrees with independent references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
from conftest import assert_second_order_derivative
from meshes import bent_grid

import torch_polylap as tp
import torch_polylap.vector as tv
from torch_polylap.linalg.derivatives import spectral_scale
from torch_polylap.shapes import quad_grid, quad_sphere

D64 = {"dtype": torch.float64}


def two_grids() -> tuple[torch.Tensor, torch.Tensor, int]:
    """Two disjoint non-planar grids, different enough that only the eigenvalue 0 is repeated;
    returns the vertices, the faces and the first vertex of the second grid."""
    V1, F1 = quad_grid(3, bump=0.3, seed=2)
    V2, F2 = quad_grid(4, bump=0.2, seed=5)
    V2 = V2 + torch.tensor([3.0, 0.0, 0.0], **D64)
    return torch.cat([V1, V2]), torch.cat([F1, F2 + V1.shape[0]]), V1.shape[0]


def _direction(shape: torch.Size, seed: int = 3) -> torch.Tensor:
    return torch.randn(shape, **D64, generator=torch.Generator().manual_seed(seed))


def test_spectral_scale_is_below_the_spectral_radius(one_thread):
    """max |L_ii| / M_ii is a Rayleigh quotient: at most the largest eigenvalue (dense
    reference), and not far below it for a Laplacian."""
    V, F = quad_grid(5, bump=0.3, seed=1)
    L, M0 = tp.laplacian(V, F)
    Ls, Ms = L.to_dense().numpy(), M0.to_dense().numpy()
    top = float(scipy.linalg.eigh(Ls, Ms, eigvals_only=True).max())
    scale = spectral_scale(np.zeros(1), tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0))
    assert top / 4 < scale <= top * (1 + 1e-12)


def test_zero_eigenvalue_of_two_components_with_k_1_refuses(one_thread):
    """k = 1 on two components: the kernel is two-dimensional, evecs[:, 0] is any unit vector
    of it, and its twin was not computed (it passed as simple when gaps were measured against
    the computed eigenvalue, ~1e-14)."""
    V, F, _ = two_grids()
    X = V.clone().requires_grad_(True)
    evals, evecs = tp.eigs(*tp.laplacian(X, F), 1)
    assert abs(float(evals[0].detach())) < 1e-10
    w = _direction(V.shape[:1], seed=1)
    with pytest.raises(RuntimeError, match=r"evecs\[:, 0\].*mu_0 = .*not computed"):
        (evecs[:, 0] ** 2 @ w).backward()


def test_zero_eigenvalue_of_two_components_cluster(one_thread):
    """k = 3: the kernel (mu_0 = mu_1 = 0) is one cluster. A loss not invariant to its
    rotations raises; its projector (the mass-weighted means over each component, computed
    here directly) has the right gradient, and so has the simple mu_2's eigenvector."""
    V, F, split = two_grids()
    u = torch.cos(2 * V[:, 0]) + V[:, 1]
    X = V.clone().requires_grad_(True)
    evals, evecs = tp.eigs(*tp.laplacian(X, F), 3)
    assert float(evals[1].detach()) < 1e-10 < 1e-3 < float(evals[2].detach())
    with pytest.raises(RuntimeError, match=r"eigenvalues 0\.\.1 mu_0 = .*mu_1 = .*not invariant"):
        (evecs[:, 0] @ u).backward()

    def through_eigs(X):
        L, M0 = tp.laplacian(X, F)
        _, evecs = tp.eigs(L, M0, 3)
        return (evecs[:, :2].T @ (M0 @ u)).square().sum()

    def direct(X):
        # the kernel is spanned by the components' indicators: sum_c (1_c^T M u)^2 / 1_c^T M 1_c
        mass = tp.laplacian(X, F)[1].diagonal()
        parts = (slice(None, split), slice(split, None))
        return sum((mass[c] @ u[c]) ** 2 / mass[c].sum() for c in parts)

    X = V.clone().requires_grad_(True)
    (got,) = torch.autograd.grad(through_eigs(X), X)
    (want,) = torch.autograd.grad(direct(X), X)
    torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-10)
    assert_second_order_derivative(lambda X: tp.eigs(*tp.laplacian(X, F), 3)[1][:, 2] @ u, V)


def test_constant_eigenvector_of_a_connected_mesh_keeps_its_gradient(one_thread):
    """The eigenvalue 0 of a connected mesh is simple: phi_0 = 1 / sqrt(sum of masses), whose
    gradient comes out of eigs as from that closed form."""
    V, F = quad_grid(4, bump=0.3, seed=2)
    w = _direction(V.shape[:1], seed=2)
    X = V.clone().requires_grad_(True)
    (got,) = torch.autograd.grad(tp.eigs(*tp.laplacian(X, F), 1)[1][:, 0] @ w, X)
    (want,) = torch.autograd.grad(w.sum() / tp.laplacian(X, F)[1].diagonal().sum().sqrt(), X)
    torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-12)


def test_parallel_field_of_a_developable_surface(one_thread):
    """The connection Laplacian's real form has every eigenvalue twice (X and i X); on a
    developable grid the smallest is ~1e-14. With k = 1 the twin was not computed, and a
    gradient used to come out regardless (central differences off by 10^2 to 10^5): it now
    raises. With k = 2 a loss seeing the pair through |X_v|^2 (unchanged by X -> e^{it} X)
    matches central differences."""
    V, F = bent_grid()
    A, M, _ = tv.connection_laplacian(V, F)
    evals, _ = tp.eigs(A, M, 3)
    assert abs(float(evals[1])) < 1e-10 < 1.0 < float(evals[2])
    w = _direction(V.shape[:1], seed=4)

    def magnitude(X, k):
        evecs = tp.eigs(*tv.connection_laplacian(X, F)[:2], k)[1]
        return (evecs[0::2, 0] ** 2 + evecs[1::2, 0] ** 2) @ w

    with pytest.raises(RuntimeError, match=r"evecs\[:, 0\].*not computed"):
        magnitude(V.clone().requires_grad_(True), 1).backward()
    assert_second_order_derivative(lambda X: magnitude(X, 2), V)


@pytest.mark.parametrize("k", [2, 3])
def test_exactly_repeated_eigenvalue_of_a_cube_sphere(one_thread, k):
    """The cube sphere's mu_1 = mu_2 = mu_3 (three linear functions, a symmetry of the cube):
    a partial cluster refuses; the whole cluster's projector has a gradient."""
    V, F = quad_sphere(4)
    u = V[:, 0] + 0.5 * V[:, 1] ** 2 - V[:, 2]
    X = V.clone().requires_grad_(True)
    L, M0 = tp.laplacian(X, F)
    evals, evecs = tp.eigs(L, M0, 5)
    evals = evals.detach()
    assert float(evals[3] - evals[1]) < 1e-10 < float(evals[4] - evals[3])
    evals, evecs = tp.eigs(L, M0, k)
    with pytest.raises(RuntimeError, match=r"evecs\[:, 1\].*not computed"):
        (evecs[:, 1:].T @ (M0 @ u)).square().sum().backward()

    def projector(X):
        L, M0 = tp.laplacian(X, F)
        C = tp.eigs(L, M0, 4)[1][:, 1:]
        return (C.T @ (M0 @ u)).square().sum()

    assert_second_order_derivative(projector, V)
