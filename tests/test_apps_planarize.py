"""Planarizing flow (AW11 sec. 5.3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import DATA, quad_grid

import torch_polylap as tp
from torch_polylap.apps.planarize import planarize


def _perturbed_grid(n: int = 8, noise: float = 0.02, seed: int = 0):
    V, F = quad_grid(n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    return V + noise * torch.randn(V.shape, generator=g, dtype=V.dtype), F


def test_planar_faces_have_zero_energy_and_are_a_fixed_point():
    V, F = tp.read_mesh(DATA / "tetris.obj")  # planar, strongly non-convex 4- to 10-gons
    X = V.clone().requires_grad_(True)
    energy = tp.planarity_energy(X, F, 2.0)
    (grad,) = torch.autograd.grad(energy, X)
    scale = float((V.amax(0) - V.amin(0)).norm())
    assert float(energy.detach()) < 1e-24 * scale**2
    assert float(grad.abs().max()) < 1e-12 * scale
    res = planarize(V, F)
    assert res.iterations == 0 and res.converged
    assert torch.equal(res.verts, V)
    assert res.nonplanarity_before[0] < 1e-12


def test_random_perturbation_of_planar_grid_is_planarized():
    V, F = _perturbed_grid()
    res = planarize(V, F, tol=1e-6, max_iter=1000)
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


def test_energy_decreases_monotonically():
    V, F = quad_grid(6, bump=0.3, seed=1)
    res = planarize(V, F, tol=1e-7, max_iter=200, check_every=1)
    e = np.asarray(res.energies)
    assert len(e) == res.iterations + 1 and len(e) > 5
    assert np.all(np.diff(e) <= 0)
    assert e[-1] < 1e-6 * e[0]


def test_fixed_vertices_do_not_move():
    V, F = _perturbed_grid(6, seed=3)
    fixed = torch.tensor([0, 6, 42, 48, 24])
    res = planarize(V, F, tol=1e-6, fixed=fixed)
    assert res.converged
    assert torch.equal(res.verts[fixed], V[fixed])
    mask = torch.zeros(V.shape[0], dtype=torch.bool)
    mask[fixed] = True
    res_mask = planarize(V, F, tol=1e-6, fixed=mask)
    torch.testing.assert_close(res_mask.verts, res.verts)


def test_float32():
    V, F = _perturbed_grid(6, seed=2)
    res = planarize(V.float(), F, tol=1e-4)
    assert res.verts.dtype == torch.float32
    assert res.converged
    assert float(tp.face_nonplanarity(res.verts, F).max()) < 1e-4


def test_progress_bar_and_errors(capsys):
    V, F = _perturbed_grid(3)
    res = planarize(V, F, tol=1e-5, progress=True)
    assert res.converged
    assert "planarize" in capsys.readouterr().err
    with pytest.raises(ValueError, match="shape"):
        planarize(V[:, :2], F)
    with pytest.raises(ValueError, match=r"fixed\[0\] = 100 is out of range for 16 elements"):
        planarize(V, F, fixed=[100])
    with pytest.raises(ValueError, match=r"boolean mask of shape \(3,\).*\(16,\)"):
        planarize(V, F, fixed=torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="tol"):
        planarize(V, F, tol=0.0)
