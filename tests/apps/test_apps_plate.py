"""Thin plate bending (AW11 sec. 5.4) against the Navier plate, and the Navier series itself."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from conftest import DATA, assert_directional_derivative
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.apps import navier_deflection, plate_bending, plate_error
from torch_polylap.shapes import quad_grid


def unit_square_grid(name: str):
    """A mesh of ``tests/data/grid`` moved onto ``[0, 1]^2`` (some cover ``[-1/2, 1/2]^2``)."""
    verts, faces = read_mesh(DATA / "grid" / name, dtype=torch.float64)
    return verts - torch.cat([verts[:, :2].min(0).values, verts.new_zeros(1)]), faces


def navier_double_series(x: np.ndarray, y: np.ndarray, terms: int = 400) -> np.ndarray:
    """Navier's double series summed directly (no Lévy form), ``terms`` odd m and n."""
    m = np.arange(1, 2 * terms, 2)
    mm, nn = np.meshgrid(m, m, indexing="ij")
    c = 1.0 / (mm * nn * (mm**2 + nn**2) ** 2)
    sx, sy = np.sin(np.pi * np.outer(x, m)), np.sin(np.pi * np.outer(y, m))
    return 16 / np.pi**6 * np.einsum("pi,ij,pj->p", sx, c, sy)


def test_navier_center_value_and_double_series(device):
    # Timoshenko & Woinowsky-Krieger, Table 8 (b/a = 1): w_max = 0.00406 q a^4 / D
    assert float(navier_deflection(0.5, 0.5)) == pytest.approx(0.00406235, abs=5e-9)
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 1, 50), rng.uniform(0, 1, 50)
    # the double series' tail after 400 x 400 odd terms is below 1e-14
    direct = navier_double_series(x, y)
    levy = navier_deflection(torch.from_numpy(x).to(device), torch.from_numpy(y).to(device))
    assert levy.device.type == device.type
    levy = levy.cpu().numpy()
    np.testing.assert_allclose(levy, direct, rtol=0, atol=1e-14)
    assert float(navier_deflection(0.5, 0.5, load=3.0)) == pytest.approx(3 * 0.0040623527, rel=1e-8)


def test_navier_solves_the_biharmonic_problem_with_navier_boundary():
    rng = np.random.default_rng(2)
    x0, y0 = rng.uniform(0.2, 0.8, 6), rng.uniform(0.2, 0.8, 6)

    def biharmonic(h):
        def w(dx, dy):
            return navier_deflection(torch.from_numpy(x0 + dx * h), torch.from_numpy(y0 + dy * h))

        # 13-point stencil, error O(h^2)
        return (
            20 * w(0, 0)
            - 8 * (w(1, 0) + w(-1, 0) + w(0, 1) + w(0, -1))
            + 2 * (w(1, 1) + w(1, -1) + w(-1, 1) + w(-1, -1))
            + (w(2, 0) + w(-2, 0) + w(0, 2) + w(0, -2))
        ) / h**4

    coarse, fine = biharmonic(0.02), biharmonic(0.01)
    np.testing.assert_allclose(fine.numpy(), 1.0, atol=1e-3)
    np.testing.assert_allclose(((4 * fine - coarse) / 3).numpy(), 1.0, atol=1e-6)  # Richardson
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    edges = torch.cat([navier_deflection(t, 0.0), navier_deflection(1.0, t)])
    assert float(edges.abs().max()) < 1e-17
    # bending moment Laplacian(w) = 0 along the edge x = 0 (w is not odd-extended here: one-sided)
    yy = torch.linspace(0.1, 0.9, 5, dtype=torch.float64)
    xs = torch.tensor([0.0, 1.0, 2.0, 3.0], dtype=torch.float64)[:, None] * 1e-3
    col = navier_deflection(xs, yy)  # (4, 5)
    w_xx = (2 * col[0] - 5 * col[1] + 4 * col[2] - col[3]) / 1e-6  # one-sided, O(h^2)
    assert float(w_xx.abs().max()) < 1e-5
    with pytest.raises(ValueError, match="terms"):
        navier_deflection(0.5, 0.5, terms=0)
    assert navier_deflection(torch.tensor([0.5]), torch.tensor([0.5])).dtype == torch.float32


@pytest.mark.parametrize("family", ["quad", "str_hex", "triangle", "irr_poly"])
def test_plate_converges_to_the_navier_solution(family, device):
    """AW11 Fig. 7: the L2 error falls under refinement (at least linearly) at lambda = 1."""
    errors, sizes = [], []
    for level in (1, 2, 3):
        verts, faces = unit_square_grid(f"{family}_{level}.obj")
        verts = verts.to(device)
        u = plate_bending(verts, faces, lam=1.0)
        assert u.device.type == device.type
        errors.append(float(plate_error(verts, faces, u)))
        sizes.append(verts.shape[0])
    assert errors[0] > errors[1] > errors[2], errors
    order = math.log(errors[0] / errors[2]) / math.log(math.sqrt(sizes[2] / sizes[0]))
    assert order > 1.0 and errors[2] < 0.04, (errors, order)


def test_lambda_zero_has_spurious_zero_energy_modes(device):
    """AW11 sec. 5.4: with lambda = 0, L is rank deficient on polygons of degree > 3."""
    verts, faces = quad_grid(6, device=device)
    checker = torch.tensor([(-1.0) ** (i + j) for i in range(7) for j in range(7)])
    checker = checker.to(device, torch.float64)

    def bending_energy(lam):
        L, M0 = tp.laplacian(verts, faces, lam)
        Lu = tp.sparse.spmm(L, checker)
        return float(0.5 * (Lu * Lu / tp.mass(verts, faces)).sum())

    assert bending_energy(0.0) < 1e-24 and bending_energy(1.0) > 1.0
    verts, faces = unit_square_grid("str_hex_1.obj")
    verts = verts.to(device)
    for lam, nullity in ((0.0, 15), (1e-3, 1)):
        L = tp.sparse.to_scipy(tp.laplacian(verts, faces, lam)[0]).toarray()
        evals = np.linalg.eigvalsh(L)
        assert int((evals < 1e-10 * np.abs(L).max()).sum()) == nullity
    # the modes spoil the supported plate too: a meaningless deflection at lambda = 0
    errors, _ = lambda_sweep("str_hex")
    assert errors[SWEEP_LAMS.index(0.0)] > 1.0 and errors[SWEEP_LAMS.index(1.0)] < 0.06


SWEEP_LAMS = (0.0, 0.5, 1.0, 2.0, 5.0, 10.0)


@functools.cache
def lambda_sweep(family: str) -> tuple[list[float], list[float]]:
    """Relative L2 errors and peak deflections over SWEEP_LAMS on the level-2 mesh."""
    verts, faces = unit_square_grid(f"{family}_2.obj")
    reference = navier_deflection(verts[:, 0], verts[:, 1])
    errors, peaks = [], []
    for lam in SWEEP_LAMS:
        u = plate_bending(verts, faces, lam=lam)
        errors.append(float(plate_error(verts, faces, u, reference)))
        peaks.append(float(u.max()))
    return errors, peaks


@pytest.mark.parametrize("family", ["quad", "str_hex", "irr_poly"])
def test_large_lambda_inhibits_bending(family):
    """AW11 sec. 5.4 / Fig. 6: past the best lambda the plate stiffens and the error grows."""
    errors, peaks = lambda_sweep(family)
    past = SWEEP_LAMS.index(1.0)
    assert all(a > b for a, b in zip(peaks[past:], peaks[past + 1 :], strict=False)), peaks
    assert all(a < b for a, b in zip(errors[past:], errors[past + 1 :], strict=False)), errors


def test_best_lambda_depends_on_the_mesh():
    """AW11: 1 <= lambda <= 3 is best on irregular polygons, but no lambda is best for all."""
    best = {f: SWEEP_LAMS[int(np.argmin(lambda_sweep(f)[0]))] for f in ("quad", "irr_poly")}
    assert 1.0 <= best["irr_poly"] <= 3.0
    assert best["quad"] != best["irr_poly"], best


def test_all_rows_of_the_energy_give_the_clamped_plate(device):
    """Why plate_bending drops the boundary rows of L: keeping them clamps the edge.

    Minimizing 1/2 u^T L^T M0^-1 L u - u^T M0 q with only u_B = 0 converges to the clamped
    square plate, center deflection 0.00126 q a^4 / D (Timoshenko & Woinowsky-Krieger,
    Table 35), not to the simply supported 0.00406.
    """
    verts, faces = unit_square_grid("quad_3.obj")
    verts = verts.to(device)
    L, M0 = tp.laplacian(verts, faces, 1.0)
    Ls, m = tp.sparse.to_scipy(L).tocsc(), tp.sparse.to_scipy(M0).diagonal()
    boundary = tp.build_topology(faces, verts.shape[0]).boundary_vertices.numpy()
    inner = np.setdiff1d(np.arange(verts.shape[0]), boundary)
    L_in = Ls[:, inner]
    u = np.zeros(verts.shape[0])
    u[inner] = spla.spsolve((L_in.T @ sp.diags(1 / m) @ L_in).tocsc(), m[inner])
    assert u.max() == pytest.approx(0.00126, rel=0.02)
    assert float(plate_bending(verts, faces).max()) == pytest.approx(0.00406, rel=0.01)


def test_plate_minimizes_the_interior_bending_energy(device):
    """u = 0 on the support and the gradient of 1/2 sum_I (L u)_p^2 / m_p - u^T M0 q vanishes."""
    verts, faces = quad_grid(5, 4, seed=3, device=device)
    load = 1.0 + verts[:, 0]  # a non-uniform load
    u = plate_bending(verts, faces, load=load, lam=2.0)
    assert u.device.type == device.type
    L, M0 = tp.laplacian(verts, faces, 2.0)
    Ld = tp.sparse.to_scipy(L).toarray()
    m = tp.mass(verts, faces).cpu().numpy()
    boundary = tp.build_topology(faces, verts.shape[0]).boundary_vertices.numpy()
    inner = np.setdiff1d(np.arange(verts.shape[0]), boundary)
    assert np.abs(u.cpu().numpy()[boundary]).max() == 0.0
    un, force = u.cpu().numpy(), m * load.cpu().numpy()
    grad = Ld[np.ix_(inner, inner)].T @ ((Ld[inner] @ un) / m[inner]) - force[inner]
    assert np.abs(grad).max() < 1e-9 * np.abs(force).max()
    assert (un[inner] > 0).all()
    torch.testing.assert_close(plate_bending(verts, faces, load=2 * load, lam=2.0), 2 * u)


def test_plate_symmetry_gradient_and_errors(device):
    verts, faces = quad_grid(6, device=device)
    u = plate_bending(verts, faces).reshape(7, 7)  # vertex (i, j) at x = i/6, y = j/6
    torch.testing.assert_close(u, u.t(), rtol=0, atol=1e-15)
    torch.testing.assert_close(u, u.flip(0), rtol=0, atol=1e-15)

    bumpy, quads = quad_grid(4, bump=0.1, seed=1, device=device)
    assert_directional_derivative(
        lambda X: (plate_bending(X, quads, lam=1.5) ** 2).sum(), bumpy, rtol=1e-6
    )
    sphere, sphere_faces = read_mesh(
        DATA / "sphere" / "quad_2.obj", dtype=torch.float64, device=device
    )
    with pytest.raises(ValueError, match="no boundary"):
        plate_bending(sphere, sphere_faces)
    with pytest.raises(ValueError, match="boundary"):
        plate_bending(verts, faces, boundary=torch.tensor([0, 99], device=device))
