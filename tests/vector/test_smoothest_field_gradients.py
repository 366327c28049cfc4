"""Gradients of ``tp.vector.smoothest_field``: the field is an eigenvector of the connection
Laplacian unique only up to its phase, so phase-invariant losses have gradients (checked
against central differences at several steps) and the others raise a clear error."""

from __future__ import annotations

import pytest
import torch
from conftest import assert_second_order_derivative
from meshes import bent_grid

import torch_polylap.vector as tv
from torch_polylap.shapes import quad_sphere

D64 = {"dtype": torch.float64}


MESHES = {
    "bent_grid": bent_grid,
    "noisy_sphere": lambda: quad_sphere(3, noise=0.15, seed=4),
}


def _weights(n: int, seed: int) -> torch.Tensor:
    return torch.randn(n, **D64, generator=torch.Generator().manual_seed(seed))


def _angles(X: torch.Tensor, F: torch.Tensor, n: int) -> torch.Tensor:
    """Each vertex's direction as the angle ``n theta`` in its own frame."""
    directions, _, _ = tv.smoothest_field(X, F, n)
    _, _, frames = tv.connection_laplacian(X, F, symmetry=n)
    e_x = (directions * frames.e_x).sum(1)
    e_y = (directions * frames.e_y).sum(1)
    return n * torch.atan2(e_y, e_x)


@pytest.mark.parametrize("mesh", sorted(MESHES))
@pytest.mark.parametrize("n", [1, 2, 4])
def test_directions_depend_on_the_phase_and_refuse(one_thread, mesh, n):
    """A loss on the directions themselves turns with the arbitrary phase: it raises (on the
    developable grid it used to return a gradient that central differences contradicted by
    10^2 to 10^5, diverging as the step shrank)."""
    V, F = MESHES[mesh]()
    X = V.clone().requires_grad_(True)
    directions, _, _ = tv.smoothest_field(X, F, n)
    w = torch.randn(directions.shape, **D64, generator=torch.Generator().manual_seed(1))
    with pytest.raises(RuntimeError, match=r"smoothest_field: no gradient.*unique only up to"):
        (directions * w).sum().backward()


@pytest.mark.parametrize("mesh", sorted(MESHES))
@pytest.mark.parametrize("n", [1, 2, 4])
def test_phase_invariant_losses_match_central_differences(one_thread, mesh, n):
    """The magnitude, the energy and angles between directions (cos of differences of the
    frame angles) do not see the phase: their gradients match central differences."""
    V, F = MESHES[mesh]()
    w = _weights(V.shape[0], seed=2)

    def magnitude(X):
        return tv.smoothest_field(X, F, n)[1] @ w

    def relative_angles(X):
        angles = _angles(X, F, n)
        return torch.cos(angles - angles[0]) @ w

    assert_second_order_derivative(magnitude, V)
    assert_second_order_derivative(relative_angles, V)
    assert_second_order_derivative(lambda X: tv.smoothest_field(X, F, n)[2], V)


def test_energy_of_a_developable_surface_is_stationary(one_thread):
    """On the developable grid the energy is 0, its minimum: the gradient vanishes."""
    V, F = bent_grid()
    X = V.clone().requires_grad_(True)
    _, _, energy = tv.smoothest_field(X, F, 4)
    (grad,) = torch.autograd.grad(energy, X)
    assert abs(float(energy.detach())) < 1e-10
    assert float(grad.abs().max()) < 1e-10


def test_repeated_complex_eigenvalue_refuses_the_magnitude(one_thread):
    """The cube sphere's smallest cross-field eigenvalue is repeated as a complex eigenvalue
    (three times): the field is not unique even up to phase, and its magnitude has no
    gradient (the energy's, one branch of the eigenvalue's, is still returned)."""
    V, F = quad_sphere(3)
    X = V.clone().requires_grad_(True)
    _, magnitude, energy = tv.smoothest_field(X, F, 4)
    with pytest.raises(RuntimeError, match=r"evecs\[:, 0\].*not computed"):
        magnitude.sum().backward(retain_graph=True)
    (grad,) = torch.autograd.grad(energy, X)
    assert torch.isfinite(grad).all()


def test_forward_without_gradients_is_unchanged(one_thread):
    """With and without gradients the outputs are the same numbers."""
    V, F = MESHES["noisy_sphere"]()
    with torch.no_grad():
        plain = tv.smoothest_field(V, F, 2)
    tracked = tv.smoothest_field(V.clone().requires_grad_(True), F, 2)
    for a, b in zip(plain, tracked, strict=True):
        assert torch.equal(a, b.detach())
