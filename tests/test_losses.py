"""Losses on polygon mesh batches against independent formulas, finite differences and gradcheck."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from conftest import assert_directional_derivative, hex_pent_mesh, mixed_mesh, tolerances

import torch_polylap as tp
from torch_polylap import losses
from torch_polylap.batch import PolygonMeshes
from torch_polylap.shapes import quad_grid

pytestmark = pytest.mark.usefixtures("one_thread")


def cube():
    """Unit cube, 6 quads oriented outward: every edge is interior with perpendicular normals."""
    verts = torch.tensor(
        [[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=torch.float64
    )
    faces = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return verts, faces


def batch():
    v1, f1 = mixed_mesh()
    v2, f2 = quad_grid(3, bump=0.3, seed=2)
    v3, f3 = hex_pent_mesh()
    return [v1, v2, v3], [f1, f2, f3]


def neighbours(faces, num_verts):
    nbr = [set() for _ in range(num_verts)]
    for face in tp.as_faces(faces).tolist():
        for i, p in enumerate(face):
            q = face[(i + 1) % len(face)]
            nbr[p].add(q)
            nbr[q].add(p)
    return nbr


def test_uniform_smoothing_is_mean_distance_to_neighbour_mean(device):
    verts, faces = batch()
    per_mesh = []
    for v, f in zip(verts, faces, strict=True):
        nbr = neighbours(f, v.shape[0])
        dist = [torch.linalg.norm(v[sorted(n)].mean(0) - v[p]) for p, n in enumerate(nbr)]
        per_mesh.append(torch.stack(dist).mean())
    expected = torch.stack(per_mesh).to(device)
    m = PolygonMeshes([v.to(device) for v in verts], faces)
    out = losses.laplacian_smoothing(m, "uniform", reduction="none")
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(losses.laplacian_smoothing(m), expected.mean())
    torch.testing.assert_close(losses.laplacian_smoothing(m, reduction="sum"), expected.sum())


def cotan_smoothing(verts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Per-vertex ``|sum_q w_pq (X_q - X_p)| / sum_q w_pq`` with ``w = (cot a + cot b) / 2``."""
    n = verts.shape[0]
    w = np.zeros((n, n))
    for t in tris:
        for c in range(3):
            o, p, q = t[c], t[(c + 1) % 3], t[(c + 2) % 3]
            u, v = verts[p] - verts[o], verts[q] - verts[o]
            cot = u @ v / np.linalg.norm(np.cross(u, v))
            w[p, q] += cot / 2
            w[q, p] += cot / 2
    rows = w.sum(1)
    assert (rows > 0).all()
    return np.linalg.norm(w @ verts / rows[:, None] - verts, axis=1)


def triangle_grid():
    v, f = quad_grid(4, bump=0.4, seed=5)
    tris = torch.cat([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
    return v, tris


def test_polygon_smoothing_on_triangles_is_the_cotan_weighted_mean(device):
    v, tris = triangle_grid()
    expected = cotan_smoothing(v.numpy(), tris.numpy()).mean()
    v, tris = v.to(device), tris.to(device)
    for frozen in (False, True):
        out = losses.laplacian_smoothing((v, tris), "polygon", frozen_weights=frozen)
        assert abs(float(out) - expected) < 1e-12
    # on triangles the stabilizer weight plays no role (AW11 Theorem 2)
    out = losses.laplacian_smoothing((v, tris), "cot", lam=5.0)
    assert abs(float(out) - expected) < 1e-12


def test_frozen_weights_differentiate_only_the_coordinates(device):
    v, f = quad_grid(3, bump=0.3, seed=2, device=device)
    L0, _ = tp.laplacian(v, f)
    L0 = L0.to_dense()
    d0 = torch.diagonal(L0)

    def fixed_weights(x):
        return (torch.linalg.norm(L0 @ x, dim=1) / d0).mean()

    x = v.clone().requires_grad_(True)
    (g_frozen,) = torch.autograd.grad(
        losses.laplacian_smoothing((x, f), "polygon", frozen_weights=True), x
    )
    (g_ref,) = torch.autograd.grad(fixed_weights(x), x)
    torch.testing.assert_close(g_frozen, g_ref)
    # live weights: the exact derivative of the loss, which differs from the frozen one
    assert_directional_derivative(
        lambda y: losses.laplacian_smoothing((y, f), "polygon"), v, rtol=1e-6
    )
    (g_live,) = torch.autograd.grad(losses.laplacian_smoothing((x, f), "polygon"), x)
    assert (g_live - g_frozen).abs().max() > 1e-3


def test_mean_curvature_smoothing_and_bending_against_mean_curvature_normal(device):
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    mc, be = [], []
    for v, f in zip(verts, faces, strict=True):
        H = tp.mean_curvature_normal(v, f, 1.3)
        mass = tp.mass(v, f)
        mc.append(torch.linalg.norm(H, dim=1).mean())
        be.append(0.5 * (mass * (H * H).sum(1)).sum())
    torch.testing.assert_close(
        losses.mean_curvature_smoothing(m, 1.3, reduction="none"), torch.stack(mc)
    )
    torch.testing.assert_close(losses.bending_energy(m, lam=1.3, reduction="none"), torch.stack(be))


def test_bending_energy_of_a_signal_is_the_dense_quadratic_form(device):
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    u = torch.sin(3 * m.verts_packed()[:, :2])
    L, M0 = m.laplacian(0.7)
    Ld, m0 = L.to_dense(), torch.diagonal(M0.to_dense())
    first = m.mesh_to_verts_packed_first_idx().tolist() + [m.verts_packed().shape[0]]
    expected = []
    for i in range(3):
        s = slice(first[i], first[i + 1])
        Lu = Ld[s, s] @ u[s]
        expected.append(0.5 * torch.trace(Lu.t() @ torch.diag(1 / m0[s]) @ Lu))
    out = losses.bending_energy(m, u, lam=0.7, reduction="none")
    assert out.device.type == device.type
    torch.testing.assert_close(out, torch.stack(expected))


def test_dirichlet_energy_via_coboundary_and_one_form_inner_product(device):
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    signal = torch.cos(2 * m.verts_packed()) + m.verts_packed()[:, :1]
    first = m.mesh_to_verts_packed_first_idx().tolist() + [m.verts_packed().shape[0]]
    expected = []
    for i, (v, f) in enumerate(zip(verts, faces, strict=True)):
        d = tp.dec.coboundary(f, v.shape[0]).to_dense().to(device)
        M1 = tp.dec.one_form_inner_product(v, f, 2.0).to_dense()
        df = d @ signal[first[i] : first[i + 1]]
        expected.append(0.5 * torch.trace(df.t() @ M1 @ df))
    out = losses.dirichlet_energy(m, signal, lam=2.0, reduction="none")
    torch.testing.assert_close(out, torch.stack(expected))
    # a constant signal per mesh has zero energy (L 1 = 0)
    const = m.verts_packed_to_mesh_idx().to(torch.float64) * 3.0 + 1.0
    assert losses.dirichlet_energy(m, const, reduction="sum").abs() < 1e-12
    with pytest.raises(ValueError, match="one row per vertex"):
        losses.dirichlet_energy(m, signal[:-1])


def test_planarity_loss(device):
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    per_mesh = losses.planarity_loss(m, lam=2.0, reduction="none")
    for i, (v, f) in enumerate(zip(verts, faces, strict=True)):
        Lplan = tp.planarity_laplacian(v, f, 2.0).to_dense()
        expected = 0.5 * torch.trace(v.t() @ Lplan @ v)
        torch.testing.assert_close(per_mesh[i], expected)
        torch.testing.assert_close(per_mesh[i], tp.planarity_energy(v, f, 2.0))
    assert (per_mesh > 1e-4).all()
    # planar meshes: a flat irregular grid rotated out of the xy-plane, and the cube
    v, f = quad_grid(4, seed=3, device=device)
    rot = torch.linalg.matrix_exp(torch.tensor([[0, 0.3, -0.5], [-0.3, 0, 0.2], [0.5, -0.2, 0]]))
    flat = PolygonMeshes([v @ rot.double().t().to(device), cube()[0].to(device)], [f, cube()[1]])
    assert losses.planarity_loss(flat, reduction="sum") < 1e-25


def test_normal_consistency(device):
    v, f = cube()
    # every cube edge joins perpendicular faces: 1 - cos 90deg = 1
    one = torch.tensor(1.0, dtype=torch.float64, device=device)
    torch.testing.assert_close(losses.normal_consistency((v.to(device), f)), one)
    flat, ff = quad_grid(3, seed=1, device=device)
    assert losses.normal_consistency((flat, ff)) < 1e-15
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    expected = []
    for vv, f in zip(verts, faces, strict=True):
        n = tp.face_normals(vv, f)
        fl = tp.as_faces(f).tolist()
        owners = {}
        for fi, face in enumerate(fl):
            for i in range(len(face)):
                owners.setdefault(frozenset((face[i], face[(i + 1) % len(face)])), []).append(fi)
        terms = [1 - n[a] @ n[b] for a, b in (o for o in owners.values() if len(o) == 2)]
        expected.append(torch.stack(terms).mean())
    out = losses.normal_consistency(PolygonMeshes(verts, faces), reduction="none")
    torch.testing.assert_close(out, torch.stack(expected))


def packed_verts(m) -> torch.Tensor:
    return m.verts_packed() if isinstance(m, PolygonMeshes) else m[0]


ALL_LOSSES = {
    "uniform": lambda m: losses.laplacian_smoothing(m, "uniform"),
    "polygon": lambda m: losses.laplacian_smoothing(m, "polygon", lam=1.5),
    "polygon_frozen": lambda m: losses.laplacian_smoothing(m, "polygon", frozen_weights=True),
    "mean_curvature": lambda m: losses.mean_curvature_smoothing(m, 1.2),
    "dirichlet": lambda m: losses.dirichlet_energy(m, torch.sin(packed_verts(m)), 0.8),
    "planarity": lambda m: losses.planarity_loss(m),
    "bending": lambda m: losses.bending_energy(m),
    "normal_consistency": lambda m: losses.normal_consistency(m),
}


@pytest.mark.parametrize("name", sorted(ALL_LOSSES))
def test_batch_loss_is_mean_of_single_mesh_losses(name, device):
    fn = ALL_LOSSES[name]
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    singles = torch.stack([fn((v, f)) for v, f in zip(verts, faces, strict=True)])
    torch.testing.assert_close(fn(PolygonMeshes(verts, faces)), singles.mean())


def tiny_mesh():
    """A quad, a triangle and a non-convex, non-planar pentagon on 7 vertices."""
    verts = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.1],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.1],
            [2.0, 0.5, 0.2],
            [1.8, 1.8, -0.1],
            [0.5, 2.0, 0.1],
        ],
        dtype=torch.float64,
    )
    return verts, tp.as_faces([[0, 1, 2, 3], [2, 1, 4], [3, 2, 4, 5, 6]])


# frozen weights are deliberately not the derivative of the loss (tested against fixed weights)
@pytest.mark.parametrize("name", sorted(set(ALL_LOSSES) - {"polygon_frozen"}))
def test_gradcheck_on_a_mixed_polygon_mesh(name, device):
    fn = ALL_LOSSES[name]
    v, pf = tiny_mesh()
    v = v.to(device)
    assert torch.autograd.gradcheck(
        lambda x: fn((x, pf)), (v.clone().requires_grad_(True),), eps=1e-6, atol=1e-6
    )


def thin_mesh(dtype: torch.dtype, aspect: float):
    """Non-planar quads and triangles, each ``aspect`` times longer than wide."""
    v, f = quad_grid(3, bump=0.2, seed=4)
    v = v * torch.tensor([1.0, 1.0 / aspect, 1.0 / aspect], dtype=torch.float64)
    tris = [[0, 4, 5], [0, 5, 1]]  # replace the first quad [0, 4, 5, 1]
    return v.to(dtype), [*f[1:].tolist(), *tris]


# the losses built on the polygon Laplacian (the others use no per-face blocks)
ASSEMBLE_L = {"polygon", "polygon_frozen", "mean_curvature", "dirichlet", "bending"}


@pytest.mark.parametrize(("dtype", "aspect"), [(torch.float64, 1e6), (torch.float32, 1e3)])
@pytest.mark.parametrize("name", sorted(ALL_LOSSES))
def test_thin_faces_give_finite_values_and_gradients(name, dtype, aspect, device):
    """Finite, and in float32 (aspect 1e3: products with L lose about 1e-1) with the warning
    that says so wherever the loss assembles L."""
    v, f = thin_mesh(dtype, aspect)
    x = v.to(device, copy=True).requires_grad_(True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", tp.checks.Float32PrecisionWarning)
        out = ALL_LOSSES[name]((x, f))
    warns = dtype == torch.float32 and name in ASSEMBLE_L
    assert [w.category for w in caught] == ([tp.checks.Float32PrecisionWarning] if warns else [])
    (g,) = torch.autograd.grad(out, x)
    assert out.dtype == dtype and g.dtype == dtype
    assert torch.isfinite(out) and torch.isfinite(g).all()


def test_vertices_with_zero_residual_have_finite_gradients(device):
    """On a flat regular grid the Laplacian vanishes at interior vertices, where |.| has a kink."""
    v, f = quad_grid(4, device=device)
    x = v.clone().requires_grad_(True)
    for method in ("uniform", "polygon"):
        per_mesh = losses.laplacian_smoothing((x, f), method, reduction="none")
        (g,) = torch.autograd.grad(per_mesh.sum(), x)
        assert torch.isfinite(g).all()
        # only the 16 boundary vertices of the 25 contribute: the interior residual is zero
        L, _ = tp.laplacian(v, f)
        assert torch.linalg.norm((L @ v)[[6, 7, 8, 11, 12, 13, 16, 17, 18]]) < 1e-14


def test_float32_agrees_with_float64(device):
    verts, faces = batch()
    m64 = PolygonMeshes(verts, faces)
    m32 = m64.to(device, torch.float32)
    for name, fn in ALL_LOSSES.items():
        a, b = fn(m64), fn(m32)
        assert b.dtype == torch.float32 and b.device.type == device.type
        assert math.isclose(float(a), float(b), rel_tol=1e-4, abs_tol=1e-6), name


def test_modules_match_functionals_and_reject_bad_options(device):
    verts, faces = batch()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    u = torch.sin(m.verts_packed())
    pairs = [
        (losses.LaplacianSmoothingLoss("polygon", 1.5), ALL_LOSSES["polygon"](m)),
        (losses.MeanCurvatureSmoothingLoss(1.2), ALL_LOSSES["mean_curvature"](m)),
        (losses.PlanarityLoss(), ALL_LOSSES["planarity"](m)),
        (losses.BendingEnergy(), ALL_LOSSES["bending"](m)),
        (losses.NormalConsistencyLoss(), ALL_LOSSES["normal_consistency"](m)),
    ]
    for module, expected in pairs:
        torch.testing.assert_close(module(m), expected)
    torch.testing.assert_close(losses.DirichletEnergy(0.8)(m, u), ALL_LOSSES["dirichlet"](m))
    assert losses.LaplacianSmoothingLoss(reduction="none")(m).shape == (3,)
    with pytest.raises(ValueError, match="reduction must be one of"):
        losses.PlanarityLoss(reduction="average")
    with pytest.raises(ValueError, match="method must be"):
        losses.laplacian_smoothing(m, "cotcurv")
    with pytest.raises(TypeError, match="PolygonMeshes or a"):
        losses.normal_consistency(verts[0])


@pytest.mark.parametrize("name", sorted(ALL_LOSSES))
def test_losses_on_every_device_and_dtype(name, device, dtype):
    verts, faces = batch()
    m = PolygonMeshes(verts, faces)
    x = m.verts_packed().to(device, dtype).requires_grad_(True)
    out = ALL_LOSSES[name](m.update_packed(x))
    (g,) = torch.autograd.grad(out, x)
    assert out.device.type == device.type and g.device.type == device.type
    assert out.dtype == dtype and g.dtype == dtype
    xc = m.verts_packed().clone().requires_grad_(True)
    ref = ALL_LOSSES[name](m.update_packed(xc))
    (gc,) = torch.autograd.grad(ref, xc)
    if name != "dirichlet":  # the others are invariant under translation: zero net gradient
        assert float(g.double().sum(0).abs().max()) <= 1e-4 * float(gc.abs().sum())
    if (device.type, dtype) == ("cpu", torch.float64):
        if name == "polygon_frozen":  # its gradient leaves out the weights' derivative
            return
        assert_directional_derivative(
            lambda y: ALL_LOSSES[name](m.update_packed(y)), m.verts_packed(), rtol=1e-5
        )
    else:
        tol = tolerances(dtype)
        torch.testing.assert_close(out.cpu().double(), ref, **tol)
        scale = float(gc.abs().max())
        torch.testing.assert_close(g.cpu().double(), gc, rtol=tol["rtol"], atol=tol["rtol"] * scale)
