"""Conformal parameterization of polygon meshes (AW11 sec. 5.2)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import (
    assert_directional_derivative,
    assert_second_order_derivative,
    hex_pent_mesh,
    mixed_mesh,
)

import torch_polylap as tp
from torch_polylap.apps.conformal import (
    angle_distortion,
    conformal_energy,
    conformal_matrix,
    conformal_parameterization,
)
from torch_polylap.shapes import quad_grid
from torch_polylap.sparse import to_scipy


def _rotation(seed: int) -> torch.Tensor:
    """A proper rotation of R^3 (QR of a Gaussian matrix, sign-fixed)."""
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def _similarity_residual(uv: torch.Tensor, target: torch.Tensor) -> float:
    """Relative residual of the best orientation-preserving similarity ``uv ~ a target + b``
    (complex least squares: rotation and scale ``a``, translation ``b``)."""
    w = torch.complex(uv[:, 0], uv[:, 1])
    z = torch.complex(target[:, 0], target[:, 1])
    A = torch.stack((z, torch.ones_like(z)), 1)
    coef = torch.linalg.lstsq(A, w[:, None]).solution
    resid = torch.linalg.vector_norm(A @ coef - w[:, None])
    return float(resid / torch.linalg.vector_norm(w - w.mean()))


def _flat_mesh(name: str):
    """A planar mesh: its 2D coordinates and the same mesh rotated into a generic 3D plane."""
    if name == "jittered_grid":
        V, F = quad_grid(4, 3, seed=2)
    elif name == "mixed":
        V, F = mixed_mesh()
    else:
        V, F = hex_pent_mesh()
    xy = V[:, :2].clone()
    V3 = torch.cat((xy, torch.zeros_like(xy[:, :1])), 1) @ _rotation(7).T + torch.tensor(
        [0.3, -1.0, 2.0], dtype=torch.float64
    )
    return xy, V3, F


def _annulus(n_ring: int = 12, n_layers: int = 3):
    """Planar quad annulus (two boundary loops), counter-clockwise quads seen from +z."""
    r = torch.linspace(1.0, 2.0, n_layers + 1, dtype=torch.float64)
    t = torch.arange(n_ring, dtype=torch.float64) * (2 * math.pi / n_ring)
    xy = torch.stack(
        (torch.outer(r, torch.cos(t)).reshape(-1), torch.outer(r, torch.sin(t)).reshape(-1)), 1
    )
    idx = torch.arange((n_layers + 1) * n_ring).reshape(n_layers + 1, n_ring)
    nxt = torch.roll(idx, -1, 1)
    F = torch.stack((idx[:-1], idx[1:], nxt[1:], nxt[:-1]), -1).reshape(-1, 4)
    return xy, F


def _single_polygon():
    """A non-planar hexagon (heights alternating in a non-symmetric pattern) with a reflex-free
    but irregular outline."""
    ang = torch.tensor([0.0, 0.9, 2.1, 3.0, 4.0, 5.3], dtype=torch.float64)
    rad = torch.tensor([1.0, 1.3, 0.9, 1.2, 1.0, 1.1], dtype=torch.float64)
    h = torch.tensor([0.3, -0.2, 0.5, 0.1, -0.4, 0.2], dtype=torch.float64)
    V = torch.stack((rad * torch.cos(ang), rad * torch.sin(ang), h), 1) @ _rotation(3).T
    return V, [[0, 1, 2, 3, 4, 5]]


def _maximal_projection(V: torch.Tensor) -> torch.Tensor:
    """2D coordinates of the projection of a polygon onto the plane orthogonal to its vector
    area ``1/2 sum x_i x x_{i+1}`` (independent of the library), in a right-handed frame."""
    a = 0.5 * torch.linalg.cross(V, torch.roll(V, -1, 0), dim=1).sum(0)
    n = a / torch.linalg.vector_norm(a)
    t1 = torch.linalg.cross(n, torch.tensor([0.3, 0.5, 0.8], dtype=V.dtype), dim=0)
    t1 = t1 / torch.linalg.vector_norm(t1)
    t2 = torch.linalg.cross(n, t1, dim=0)
    return torch.stack((V @ t1, V @ t2), 1)


@pytest.mark.parametrize("name", ["jittered_grid", "mixed", "hexpent"])
@pytest.mark.parametrize("free", [False, True])
def test_planar_mesh_maps_to_itself_up_to_similarity(name, free, device):
    xy, V3, F = _flat_mesh(name)
    V3 = V3.to(device)
    uv = conformal_parameterization(V3, F, free_boundary=free)
    assert uv.device == V3.device
    assert abs(float(conformal_energy(uv, V3, F))) < 1e-10 * float((uv * uv).sum())
    assert _similarity_residual(uv.cpu(), xy) < 1e-9


def test_pinned_at_true_positions_reproduces_planar_mesh_exactly(device):
    xy, V3, F = _flat_mesh("mixed")
    pins = [0, 11]
    uv = conformal_parameterization(V3.to(device), F, pins=pins, pin_uv=xy[pins].to(device))
    assert uv.device.type == device.type
    torch.testing.assert_close(uv.cpu(), xy, rtol=0, atol=1e-10)


def test_planar_annulus_with_two_boundary_loops(device):
    """The pinned map takes holes; the free-boundary map refuses them (not a disk: its area
    form over several loops folds curved meshes over, see tests/cli/test_reliability_cli.py)."""
    xy, F = _annulus()
    V3 = (torch.cat((xy, torch.zeros_like(xy[:, :1])), 1) @ _rotation(11).T).to(device)
    uv = conformal_parameterization(V3, F)
    assert uv.device.type == device.type
    assert _similarity_residual(uv.cpu(), xy) < 1e-9
    with pytest.raises(ValueError, match="2 boundary loops and Euler characteristic 0"):
        conformal_parameterization(V3, F, free_boundary=True)


@pytest.mark.parametrize("pins", [None, [0, 1], [2, 5], [4, 1]])
def test_single_nonplanar_polygon_maps_to_its_maximal_projection(pins, device):
    V, F = _single_polygon()
    target = _maximal_projection(V)
    # the polygon really is non-planar: its corners are not a similarity of any projection
    assert _similarity_residual(V[:, :2], target) > 1e-2
    V = V.to(device)
    uv = conformal_parameterization(V, F, pins=pins)
    assert _similarity_residual(uv.cpu(), target) < 1e-10
    assert angle_distortion(uv, V, F).max < 1e-9


def test_single_nonplanar_polygon_free_boundary(device):
    V, F = _single_polygon()
    uv = conformal_parameterization(V.to(device), F, free_boundary=True)
    assert uv.device.type == device.type
    uv = uv.cpu()
    assert _similarity_residual(uv, _maximal_projection(V)) < 1e-10
    # scaled to the area of the maximal projection
    area = 0.5 * (uv[:, 0] * torch.roll(uv[:, 1], -1) - torch.roll(uv[:, 0], -1) * uv[:, 1]).sum()
    a = 0.5 * torch.linalg.cross(V, torch.roll(V, -1, 0), dim=1).sum(0)
    torch.testing.assert_close(area, torch.linalg.vector_norm(a))


def _shoelace_total(uv: torch.Tensor, faces) -> torch.Tensor:
    total = uv.new_zeros(())
    for f in faces:
        p = uv[torch.as_tensor(f)]
        q = torch.roll(p, -1, 0)
        total = total + 0.5 * (p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]).sum()
    return total


def test_energy_is_dirichlet_minus_sum_of_face_areas_and_matches_matrix(device):
    V, F = hex_pent_mesh()
    uv = torch.randn(V.shape[0], 2, generator=torch.Generator().manual_seed(0), dtype=V.dtype)
    V, uv = V.to(device), uv.to(device)
    L, _ = tp.laplacian(V, F, 1.5)
    expected = 0.5 * (uv * (L.to_dense() @ uv)).sum() - _shoelace_total(uv, F)
    torch.testing.assert_close(conformal_energy(uv, V, F, lam=1.5), expected)
    z = torch.cat((uv[:, 0], uv[:, 1]))
    LC = conformal_matrix(V, F, 1.5).to_dense()
    torch.testing.assert_close(LC, LC.T, rtol=0, atol=0)
    torch.testing.assert_close(0.5 * z @ LC @ z, expected)


@pytest.mark.parametrize("lam", [0.25, 1.0, 3.0])
def test_conformal_matrix_is_psd_with_similarity_kernel_on_planar_mesh(lam, device):
    xy, V3, F = _flat_mesh("hexpent")
    LC = conformal_matrix(V3.to(device), F, lam)
    assert LC.device.type == device.type
    ev = np.linalg.eigvalsh(to_scipy(LC).toarray())
    assert ev[0] > -1e-12
    # translations (2) and the rotation-scale pair (2) have zero energy on a planar mesh
    assert np.all(np.abs(ev[:4]) < 1e-12) and ev[4] > 1e-4


def test_pinned_solution_is_a_constrained_minimizer(device):
    V, F = quad_grid(5, 4, bump=0.4, seed=1, device=device)
    pins = [0, 29]
    uv = conformal_parameterization(V, F, pins=pins)
    e0 = float(conformal_energy(uv, V, F))
    assert e0 > 0  # a curved patch is not flattened conformally
    g = torch.Generator().manual_seed(5)
    for _ in range(5):
        d = torch.randn(uv.shape, generator=g, dtype=uv.dtype).to(device)
        d[pins] = 0
        for h in (1e-4, 1e-2):
            assert float(conformal_energy(uv + h * d, V, F)) > e0


def test_free_boundary_minimizes_energy_per_area(device):
    V, F = quad_grid(5, 4, bump=0.4, seed=1, device=device)
    uv = conformal_parameterization(V, F, free_boundary=True)

    def ratio(y):  # E_C / A is the constrained objective of AW11 eq. 13 (E_C is 2-homogeneous)
        return float(conformal_energy(y, V, F) / _shoelace_total(y, F.tolist()))

    r0 = ratio(uv)
    # above zero (the bumped grid has no exactly conformal flat map) and below the ratio of
    # the obvious flat map, the projection onto the xy plane
    assert 0 < r0 < ratio(V[:, :2])
    g = torch.Generator().manual_seed(6)
    for _ in range(5):
        d = torch.randn(uv.shape, generator=g, dtype=uv.dtype).to(device)
        assert ratio(uv + 1e-3 * d) > r0
    # the pinned solution with the same two boundary points is no better
    pins = [0, 29]
    uv_p = conformal_parameterization(V, F, pins=pins, pin_uv=uv[pins])
    assert ratio(uv_p) >= r0 - 1e-12


def test_triangle_mesh_matches_libigl_lscm(device):
    igl = pytest.importorskip(
        "igl", reason="libigl (the independent LSCM) not installed: pip install libigl"
    )
    V, Fq = quad_grid(5, 4, bump=0.5, seed=4)
    F = torch.cat((Fq[:, [0, 1, 2]], Fq[:, [0, 2, 3]]))
    pins = torch.tensor([0, 29])
    pin_uv = torch.tensor([[0.0, 0.0], [1.0, 0.2]], dtype=torch.float64)
    uv = conformal_parameterization(V.to(device), F, pins=pins, pin_uv=pin_uv.to(device)).cpu()
    out = igl.lscm(V.numpy(), F.numpy(), pins.numpy(), pin_uv.numpy())
    uv_igl = out[0] if isinstance(out, tuple) else out
    np.testing.assert_allclose(uv.numpy(), uv_igl, atol=1e-9)


def test_pinned_is_differentiable_in_verts(device):
    V, F = quad_grid(3, bump=0.3, seed=0, device=device)
    pins = [0, 15]

    def f(X):
        uv = conformal_parameterization(X, F, pins=pins)
        return (
            uv * torch.tensor([0.3, -0.7], dtype=X.dtype, device=X.device)
        ).sum() + uv.square().sum()

    assert_directional_derivative(f, V, rtol=1e-5)


def test_free_boundary_is_differentiable_in_verts(device):
    V, F = quad_grid(3, bump=0.3, seed=0, device=device)

    def f(X):
        uv = conformal_parameterization(X, F, free_boundary=True)
        weights = torch.tensor([0.3, -0.7], dtype=X.dtype, device=X.device)
        return (uv * weights).sum() + uv[:, 0].pow(3).sum()

    assert_directional_derivative(f, V, rtol=1e-5)
    assert torch.autograd.gradcheck(
        lambda X: conformal_parameterization(X, F, free_boundary=True), V.clone().requires_grad_()
    )


def test_fixed_pins_are_differentiable_where_the_default_pins_tie():
    """A heptagon fan symmetric about vertex 1: vertices 4 and 5 are equally far from it, so
    the default pins switch under any perturbation (central differences of a loss on ``uv``
    grow as 1 / h). With the pins passed, the map is smooth: autograd equals central
    differences at second order."""
    n = 7
    angle = torch.arange(n, dtype=torch.float64) * 2 * math.pi / n
    ring = torch.stack([angle.cos(), angle.sin(), 0.1 * (2 * angle).cos()], 1)
    V = torch.cat([torch.zeros(1, 3, dtype=torch.float64), ring])
    F = [[0, 1 + i, 1 + (i + 1) % n] for i in range(n)]
    far = torch.linalg.vector_norm(ring - ring[0], dim=1)
    assert float(far[3]) == pytest.approx(float(far[4]), rel=1e-15)  # the tie
    weights = torch.arange(1.0, n + 2, dtype=torch.float64)

    def f(X):
        return (conformal_parameterization(X, F, pins=[1, 4])[:, 0] * weights).sum()

    assert_second_order_derivative(f, V)


def test_top_eigenpair_gradient_with_a_repeated_lower_eigenvalue(device):
    """Symmetric meshes have exactly repeated eigenvalues below the top one, where
    torch.linalg.eigh's backward divides zero by zero; the top gap is all that is needed."""
    from torch_polylap.linalg.derivatives import top_eigenpair

    M = torch.diag(torch.tensor([1.0, 1.0, 3.0], dtype=torch.float64, device=device))
    M.requires_grad_(True)
    evals, V = torch.linalg.eigh(M)
    (nan_grad,) = torch.autograd.grad(evals[-1] + V[2, -1] ** 2, M)
    assert torch.isnan(nan_grad).all()  # what this function avoids
    nu, x = top_eigenpair(M)
    (grad,) = torch.autograd.grad(nu + x[2] ** 2, M)
    expected = torch.zeros(3, 3, dtype=torch.float64, device=device)
    expected[2, 2] = 1.0  # d nu / d M = x x^T; |x_2| = 1 stays 1 to first order
    torch.testing.assert_close(grad, expected)


def test_top_eigenpair_matches_eigh_gradient(device):
    from torch_polylap.linalg.derivatives import top_eigenpair

    g = torch.Generator().manual_seed(0)
    A = torch.randn(6, 6, dtype=torch.complex128, generator=g)
    A = ((A + A.mH) / 2).to(device)
    w = torch.randn(6, dtype=torch.float64, generator=g).to(device)

    def loss(nu, x):  # invariant under the eigenvector's phase
        return nu + (x.abs().square() * w).sum()

    grads = []
    for top in (lambda M: top_eigenpair(M), lambda M: _eigh_top(M)):
        M = A.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(loss(*top((M + M.mH) / 2)), M)
        grads.append(grad)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-12, rtol=1e-10)
    R = torch.diag(torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64, device=device))
    R.requires_grad_(True)
    nu, x = top_eigenpair(R)
    with pytest.raises(ValueError, match="repeated"):
        torch.autograd.grad((x[0] ** 2) + nu, R)


def _eigh_top(M):
    evals, V = torch.linalg.eigh(M)
    return evals[-1], V[:, -1]


def test_float32_matches_float64(device, dtype):
    V, F = quad_grid(4, bump=0.3, seed=3)
    uv64 = conformal_parameterization(V, F)
    uv = conformal_parameterization(V.to(device, dtype), F)
    assert uv.dtype == dtype and uv.device.type == device.type
    tol = 1e-5 if dtype == torch.float32 else 1e-10
    torch.testing.assert_close(uv.cpu().double(), uv64, atol=tol, rtol=tol)
    uvf = conformal_parameterization(V.to(device, dtype), F, free_boundary=True)
    assert uvf.dtype == dtype and uvf.device.type == device.type


def test_angle_distortion_of_known_maps(device):
    # an L-shaped hexagon (one reflex corner): the identity has zero error
    xy = torch.tensor(
        [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=torch.float64, device=device
    )
    V = torch.cat((xy, torch.zeros(6, 1, dtype=torch.float64, device=device)), 1)
    F = [[0, 1, 2, 3, 4, 5]]
    assert angle_distortion(xy, V, F).max < 1e-14
    # a stretch keeps the right angles of an axis-aligned L
    stretch = xy * torch.tensor([3.0, 0.5], dtype=torch.float64, device=device)
    assert angle_distortion(stretch, V, F).max < 1e-14
    # a shear of the unit square: corner 0 becomes atan2(1, s), corner 1 its supplement
    sq = torch.tensor([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=torch.float64, device=device)
    Vs = torch.cat((sq, torch.zeros(4, 1, dtype=torch.float64, device=device)), 1)
    s = 0.4
    sheared = sq + s * sq[:, 1:] * torch.tensor([1.0, 0.0], dtype=torch.float64, device=device)
    err = angle_distortion(sheared, Vs, [[0, 1, 2, 3]]).per_corner
    assert err.device.type == device.type
    err = err.cpu()
    beta = math.atan2(1.0, s) - math.pi / 2
    torch.testing.assert_close(err, torch.tensor([beta, -beta, beta, -beta], dtype=torch.float64))


def test_errors(device):
    V, F = quad_grid(2, device=device)
    with pytest.raises(ValueError, match="not a boundary vertex"):
        conformal_parameterization(V, F, pins=[4, 0])
    with pytest.raises(ValueError, match="out of range"):
        conformal_parameterization(V, F, pins=[0, 9])
    with pytest.raises(ValueError, match="same vertex"):
        conformal_parameterization(V, F, pins=[0, 0])
    with pytest.raises(ValueError, match="exactly two"):
        conformal_parameterization(V, F, pins=[0, 1, 2])
    with pytest.raises(ValueError, match="do not pass pins"):
        conformal_parameterization(V, F, pins=[0, 8], free_boundary=True)
    with pytest.raises(ValueError, match="without pins"):
        conformal_parameterization(V, F, pin_uv=torch.zeros(2, 2, dtype=V.dtype, device=device))
    # a closed mesh: the surface of a cube
    cube = torch.tensor(
        [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)],
        dtype=torch.float64,
        device=device,
    )
    cube_faces = [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ]
    with pytest.raises(ValueError, match="no boundary"):
        conformal_parameterization(cube, cube_faces)
    # two separate quads
    V2 = torch.cat((V[:4], V[:4] + 5.0))
    with pytest.raises(ValueError, match="2 connected components"):
        conformal_parameterization(V2, [[0, 1, 2, 3], [4, 5, 6, 7]])
