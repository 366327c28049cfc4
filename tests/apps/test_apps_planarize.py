"""Planarizing flow (AW11 sec. 5.3)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from conftest import DATA
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.apps.planarize import PlanarizeOptions, planarize
from torch_polylap.data import DEFAULT_MESH
from torch_polylap.shapes import quad_grid

QUIET = PlanarizeOptions(warn=False)


def _perturbed_grid(n: int = 8, noise: float = 0.02, seed: int = 0):
    V, F = quad_grid(n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    return V + noise * torch.randn(V.shape, generator=g, dtype=V.dtype), F


def test_planar_faces_have_zero_energy_and_are_a_fixed_point(device):
    # planar, strongly non-convex 4- to 10-gons
    V, F = read_mesh(DATA / "tetris.obj", device=device)
    X = V.clone().requires_grad_(True)
    energy = tp.planarity_energy(X, F, 2.0)
    (grad,) = torch.autograd.grad(energy, X)
    scale = float((V.amax(0) - V.amin(0)).norm())
    assert float(energy.detach()) < 1e-24 * scale**2
    assert float(grad.abs().max()) < 1e-12 * scale
    res = planarize(V, F)
    assert res.iterations == 0 and res.converged
    assert res.verts.device.type == device.type and torch.equal(res.verts, V)
    assert res.nonplanarity_before[0] < 1e-12


def test_random_perturbation_of_planar_grid_is_planarized(device):
    V, F = _perturbed_grid()
    V = V.to(device)
    res = planarize(V, F, tol=1e-6, max_iter=1000, method="lbfgs")
    assert res.verts.device.type == device.type
    assert res.nonplanarity_before[0] > 0.05
    assert res.converged
    after = tp.face_nonplanarity(res.verts, F)
    assert float(after.max()) < 1e-6
    assert res.nonplanarity_after[0] == pytest.approx(float(after.max()))
    # no collapse: the mesh keeps its size and moves by about the size of the perturbation
    size = lambda X: float((X.amax(0) - X.amin(0)).norm())  # noqa: E731
    assert size(res.verts) == pytest.approx(size(V), rel=0.05)
    assert float(tp.face_areas(res.verts, F).sum()) == pytest.approx(
        float(tp.face_areas(V, F).sum()), rel=0.05
    )
    disp = (res.verts - V).norm(dim=1) / size(V)
    assert res.displacement == pytest.approx((float(disp.max()), float(disp.mean())))
    assert res.displacement[1] < 0.02


def test_energy_decreases_monotonically(device):
    V, F = quad_grid(6, bump=0.3, seed=1, device=device)
    options = PlanarizeOptions(check_every=1)
    res = planarize(V, F, tol=1e-7, max_iter=200, method="lbfgs", options=options)
    e = np.asarray(res.energies)
    assert len(e) == res.iterations + 1 and len(e) > 5
    assert np.all(np.diff(e) <= 0)
    assert e[-1] < 1e-6 * e[0]


def test_fixed_vertices_do_not_move(device):
    V, F = _perturbed_grid(6, seed=3)
    V = V.to(device)
    fixed = torch.tensor([0, 6, 42, 48, 24], device=device)
    res = planarize(V, F, tol=1e-6, fixed=fixed)
    assert res.converged
    assert torch.equal(res.verts[fixed], V[fixed])
    mask = torch.zeros(V.shape[0], dtype=torch.bool, device=device)
    mask[fixed] = True
    res_mask = planarize(V, F, tol=1e-6, fixed=mask)
    torch.testing.assert_close(res_mask.verts, res.verts)


def test_float32(device):
    V, F = _perturbed_grid(6, seed=2)
    res = planarize(V.to(device, torch.float32), F, tol=1e-4)
    assert res.verts.dtype == torch.float32 and res.verts.device.type == device.type
    assert res.converged
    assert float(tp.face_nonplanarity(res.verts, F).max()) < 1e-4


def test_progress_bar_and_errors(capsys, device):
    V, F = _perturbed_grid(3)
    V = V.to(device)
    res = planarize(V, F, tol=1e-5, options=PlanarizeOptions(progress=True))
    assert res.converged
    assert "planarize" in capsys.readouterr().err
    with pytest.raises(ValueError, match="shape"):
        planarize(V[:, :2], F)
    with pytest.raises(ValueError, match=r"fixed\[0\] = 100 is out of range for 16 elements"):
        planarize(V, F, fixed=[100])
    with pytest.raises(ValueError, match=r"boolean mask of shape \(3,\).*\(16,\)"):
        planarize(V, F, fixed=torch.ones(3, dtype=torch.bool, device=device))
    with pytest.raises(ValueError, match="tol"):
        planarize(V, F, tol=0.0)


@pytest.mark.parametrize("method", ["gauss-newton", "lbfgs"])
def test_both_methods_planarize_a_perturbed_grid(method, device):
    V, F = _perturbed_grid()
    V, F = V.to(device), F.to(device)
    res = planarize(V, F, tol=1e-6, method=method, max_iter=1000)
    assert res.verts.device == V.device
    assert res.method == method and res.converged and res.message == "converged"
    assert float(tp.face_nonplanarity(res.verts, F).max()) < 1e-6
    assert res.displacement[1] < 0.02


# measured Gauss-Newton iterations with defaults (tol 1e-4): quad grid 3-4, spot_control_mesh 4,
# bunny_poly 3, mixedFaring 6, moebius 9; the bounds leave about 3x margin
@pytest.mark.parametrize(
    "name, bound",
    [
        ("spot_control_mesh.obj", 12),
        ("bunny_poly.ply", 12),
        ("mixedFaring.off", 20),
        ("moebius.obj", 25),
    ],
)
def test_defaults_converge_on_the_test_meshes(name, bound, device):
    V, F = read_mesh(DATA / name, device=device)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no "did not converge" warning
        warnings.filterwarnings("ignore", message=".*(read vertex|consistently oriented).*")
        res = planarize(V.double(), F)
    assert res.verts.device.type == device.type
    assert res.converged and res.iterations <= bound
    assert float(tp.face_nonplanarity(res.verts, F).max()) < 1e-4
    assert res.displacement[0] < 0.15


def test_defaults_converge_on_bumped_grid_and_embedded_mesh(device):
    V, F = quad_grid(12, bump=0.4, seed=4, device=device)
    res = planarize(V, F)
    assert res.converged and res.iterations <= 12
    V, F = read_mesh(DEFAULT_MESH, device=device)
    res = planarize(V, F)
    assert res.converged and res.iterations <= 12 and res.verts.device.type == device.type


def test_warns_when_it_cannot_converge(device):
    V, F = _perturbed_grid()
    V = V.to(device)
    for method in ("gauss-newton", "lbfgs"):
        with pytest.warns(UserWarning, match=r"max non-planarity .* >= tol 1e-09 after 1 "):
            res = planarize(V, F, tol=1e-9, max_iter=1, method=method)
        assert not res.converged and "raise max_iter" in res.message
    with pytest.warns(UserWarning, match="raise time_limit"):
        res = planarize(V, F, tol=1e-12, options=PlanarizeOptions(time_limit=0.0))
    assert not res.converged
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        planarize(V, F, tol=1e-9, max_iter=1, options=QUIET)


@pytest.mark.parametrize("method", ["gauss-newton", "lbfgs"])
def test_fixed_boundary_stays_put_exactly(method, device):
    V, F = quad_grid(8, bump=0.3, seed=5)
    boundary = tp.get_topology(F, V.shape[0]).boundary_vertices
    V = V.to(device)
    res = planarize(V, F, fixed=boundary, method=method, max_iter=2000)
    assert res.converged and res.verts.device == V.device
    assert torch.equal(res.verts[boundary], V[boundary])


def test_closeness_reduces_displacement(device):
    V, F = _perturbed_grid(8, noise=0.03, seed=6)
    V = V.to(device)
    free = planarize(V, F, tol=1e-3)
    close = planarize(V, F, tol=1e-3, options=PlanarizeOptions(closeness=1e-3, warn=False))
    assert free.converged
    assert close.displacement[1] < free.displacement[1]
    with pytest.raises(ValueError, match="closeness"):
        planarize(V, F, options=PlanarizeOptions(closeness=-1.0))
    with pytest.raises(ValueError, match="method"):
        planarize(V, F, method="newton")


def test_gauss_newton_objective_never_increases(device):
    V, F = _perturbed_grid(8, noise=0.05, seed=7)
    V = V.to(device)
    res = planarize(V, F, tol=1e-10, options=PlanarizeOptions(closeness=1e-6, warn=False))
    o = np.asarray(res.objectives)
    assert len(o) >= 3 and np.all(np.diff(o) <= 0)


def test_a_face_a_million_times_smaller_than_its_neighbours(capfd, device):
    """The damping is per vertex: a global one would not reach the ``1 / diam^2`` entries of a
    tiny face and CHOLMOD would report the matrix as not positive definite."""
    V, F = quad_grid(10, bump=0.3, device=device)
    f = F[55]
    center = V[f].mean(0)
    V[f] = center + (V[f] - center) * 1e-6  # same shape, so just as non-planar
    assert float(tp.face_nonplanarity(V, F)[55]) > 1e-3
    res = planarize(V, F)
    assert res.converged
    assert torch.isfinite(res.verts).all()
    assert "not positive definite" not in capfd.readouterr().err
