"""Implicit mean-curvature flow (AW11 sec. 5.1): rates, invariants, gradients, the lantern."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.spatial
import torch
from conftest import DATA, assert_directional_derivative, hex_pent_mesh

import torch_polylap as tp
from torch_polylap.apps import enclosed_volume, mean_curvature_flow
from torch_polylap.shapes import quad_grid, schwarz_lantern


def unit_sphere(name: str):
    verts, faces = tp.read_mesh(DATA / "sphere" / name, dtype=torch.float64)
    return verts / verts.norm(dim=1, keepdim=True), faces


def semi_implicit_sphere(r2: float, dt: float, steps: int) -> float:
    """Squared radius after ``steps`` of the scheme on an exact sphere.

    With this package's L, M0^{-1} L X = 2 H n = 2 X / r^2 on a round sphere (H = 1/r), and the
    operator is taken at the current radius, so each step scales X by 1 / (1 + 2 dt / r^2).
    Its continuum limit is dr/dt = -2/r, i.e. r(t)^2 = r(0)^2 - 4 t.
    """
    r = math.sqrt(r2)
    for _ in range(steps):
        r = r / (1 + 2 * dt / r**2)
    return r * r


def test_round_sphere_shrinks_at_the_mean_curvature_rate(device):
    dt, steps = 0.02, 5
    expected = semi_implicit_sphere(1.0, dt, steps)
    # the scheme tends to r^2 = 1 - 4 t at first order in dt
    T = dt * steps
    time_errors = [abs(semi_implicit_sphere(1.0, T / n, n) - (1 - 4 * T)) for n in (100, 200)]
    assert time_errors[1] == pytest.approx(time_errors[0] / 2, rel=0.02)
    errors = []
    for name in ("quad_2.obj", "quad_3.obj"):
        verts, faces = unit_sphere(name)
        verts = verts.to(device)
        X = mean_curvature_flow(verts, faces, dt, steps, lam=1.0)
        assert X.device == verts.device
        # the shape stays round, so the squared radius is the area ratio
        r2 = float(tp.face_areas(X, faces).sum() / tp.face_areas(verts, faces).sum())
        radii = (X - X.mean(0)).norm(dim=1)
        assert float(radii.max() - radii.min()) < 5e-3
        errors.append(abs(r2 - expected))
    # the spatial error falls under refinement (measured 3.5e-5 -> 7e-6)
    assert errors[1] < errors[0] / 2 and errors[0] < 1e-4, errors


def test_frozen_and_rebuilt_flows_agree_to_second_order_in_dt():
    verts, faces = unit_sphere("quad_2.obj")
    verts = verts * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)  # an ellipsoid
    gaps = []
    for dt in (2e-3, 1e-3):
        frozen = mean_curvature_flow(verts, faces, dt, 3, frozen=True)
        rebuilt = mean_curvature_flow(verts, faces, dt, 3)
        moved = float((rebuilt - verts).norm(dim=1).max())
        assert moved > 1e-3  # the flow moved by O(dt)
        gaps.append(float((frozen - rebuilt).norm(dim=1).max()))
    # dt is a fifth of the squared edge length: the fastest modes relax within one step
    assert gaps[1] < 0.35 * gaps[0] and gaps[0] < 0.1 * moved, gaps
    one_frozen = mean_curvature_flow(verts, faces, 1e-3, 1, frozen=True)
    torch.testing.assert_close(one_frozen, mean_curvature_flow(verts, faces, 1e-3, 1))


def test_area_and_volume_normalization_keep_their_measure():
    verts, faces = unit_sphere("hex_2.obj")
    verts = verts * torch.tensor([1.0, 0.7, 0.5], dtype=torch.float64)
    area0 = tp.face_areas(verts, faces).sum()
    X = mean_curvature_flow(verts, faces, 0.01, 4, normalize="area")
    torch.testing.assert_close(tp.face_areas(X, faces).sum(), area0, rtol=1e-12, atol=0)
    assert float((X - verts).norm(dim=1).max()) > 1e-2  # the shape did change
    vol0 = enclosed_volume(verts, faces)
    Y = mean_curvature_flow(verts, faces, 0.01, 4, normalize="volume")
    torch.testing.assert_close(enclosed_volume(Y, faces), vol0, rtol=1e-12, atol=0)


def test_enclosed_volume_matches_independent_volumes():
    # a unit cube of quads under a linear map and a shift: volume |det A|
    corners = torch.tensor(
        [[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)], dtype=torch.float64
    )
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    A = torch.tensor([[1.2, 0.3, -0.1], [0.2, 0.9, 0.4], [-0.3, 0.1, 1.5]], dtype=torch.float64)
    box = corners @ A.T + torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)
    assert float(enclosed_volume(box, quads)) == pytest.approx(float(torch.det(A)), rel=1e-13)
    # the dodecahedron's pentagons are planar to the file's printed digits only
    verts, faces = tp.read_mesh(DATA / "dodecahedron_poly.obj", dtype=torch.float64)
    hull = scipy.spatial.ConvexHull(verts.numpy())
    assert float(enclosed_volume(verts, faces)) == pytest.approx(hull.volume, rel=1e-6)


def test_flat_mesh_with_fixed_boundary_is_a_fixed_point_and_stays_in_its_plane():
    verts, faces = quad_grid(6, 5, seed=2)  # irregular convex quads in z = 0
    rotvec = scipy.spatial.transform.Rotation.from_rotvec([0.3, -0.5, 0.2])
    rot = torch.from_numpy(rotvec.as_matrix())
    verts = verts @ rot.T + torch.tensor([0.2, 0.1, -0.4], dtype=torch.float64)
    normal = rot[:, 2]
    boundary = tp.build_topology(faces, verts.shape[0]).boundary_vertices
    # linear precision: (L X)_p = 0 at interior vertices of a planar mesh
    X = mean_curvature_flow(verts, faces, 0.05, 3, fixed=boundary)
    torch.testing.assert_close(X, verts, rtol=0, atol=1e-12)
    # with a free boundary the rim shrinks, but every vertex stays in the plane
    Y = mean_curvature_flow(verts, faces, 0.05, 3)
    assert float((Y - verts).norm(dim=1).max()) > 1e-3
    offsets = (Y - verts[0]) @ normal
    assert float(offsets.abs().max()) < 1e-12


def test_flow_is_differentiable_in_the_initial_positions(device):
    verts, faces = hex_pent_mesh()
    verts = verts.to(device)
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(verts.shape, generator=gen, dtype=torch.float64).to(device)

    def loss(X):
        return (mean_curvature_flow(X, faces, 0.05, 3, lam=2.0) * weights).sum()

    def loss_fixed_frozen(X):
        flowed = mean_curvature_flow(X, faces, 0.05, 3, frozen=True, fixed=torch.tensor([6, 7]))
        return (flowed * weights).sum()

    assert_directional_derivative(loss, verts, rtol=1e-6)
    assert_directional_derivative(loss_fixed_frozen, verts, rtol=1e-6)


def test_trajectory_progress_and_argument_checks():
    verts, faces = unit_sphere("quad_2.obj")
    traj = mean_curvature_flow(verts, faces, 0.01, 2, return_trajectory=True, progress=True)
    assert traj.shape == (3, *verts.shape)
    assert torch.equal(traj[0], verts)
    torch.testing.assert_close(traj[-1], mean_curvature_flow(verts, faces, 0.01, 2))
    assert torch.equal(mean_curvature_flow(verts, faces, 0.01, 0), verts)
    with pytest.raises(ValueError, match="dt"):
        mean_curvature_flow(verts, faces, 0.0, 2)
    with pytest.raises(ValueError, match="dt"):
        mean_curvature_flow(verts, faces, -1e-3, 2)
    with pytest.raises(ValueError, match="steps"):
        mean_curvature_flow(verts, faces, 0.01, -1)
    with pytest.raises(ValueError, match="normalize"):
        mean_curvature_flow(verts, faces, 0.01, 1, normalize="length")
    flat, quads = quad_grid(3)
    with pytest.raises(ValueError, match="closed mesh"):
        mean_curvature_flow(flat, quads, 0.01, 1, normalize="volume")
    with pytest.raises(ValueError, match="fixed"):
        mean_curvature_flow(verts, faces, 0.01, 1, normalize="area", fixed=torch.tensor([0]))


def lantern_symmetry_defects(X: torch.Tensor, sides: int, rings: int) -> tuple[float, float]:
    """Largest vertex mismatch under rotation by 2 pi / sides and under the mirror y -> -y."""
    c, s = math.cos(2 * math.pi / sides), math.sin(2 * math.pi / sides)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=X.dtype)
    i, j = torch.meshgrid(torch.arange(rings), torch.arange(sides), indexing="ij")
    turned = (i * sides + (j + 1) % sides).reshape(-1)  # (i, j) -> (i, j + 1)
    mirrored = (i * sides + (-j - i) % sides).reshape(-1)  # angle (2j + i) pi/n -> its negative
    flip = torch.tensor([1.0, -1.0, 1.0], dtype=X.dtype)
    rotation_defect = float((X @ rot.T - X[turned]).norm(dim=1).max())
    mirror_defect = float((X * flip - X[mirrored]).norm(dim=1).max())
    return rotation_defect, mirror_defect


def test_lantern_quad_flow_keeps_the_symmetry_that_triangulations_break():
    """AW11 Fig. 2: the result depends on the triangulation, the quad mesh has no such choice."""
    sides, rings = 6, 5
    results = {}
    for kind in ("quad", "horizontal", "vertical", "alternating"):
        verts, faces = schwarz_lantern(sides, rings, triangulation=kind)
        fixed = tp.build_topology(faces, verts.shape[0]).boundary_vertices
        results[kind] = mean_curvature_flow(verts, faces, 0.02, 10, lam=2.0, fixed=fixed)
        if kind == "quad":
            # relabeling each quad cyclically (another "choice" a quad mesh does not have)
            shifted = [f[1:] + f[:1] for f in faces]
            again = mean_curvature_flow(verts, shifted, 0.02, 10, lam=2.0, fixed=fixed)
            torch.testing.assert_close(again, results[kind], rtol=0, atol=1e-12)
    rotation, mirror = lantern_symmetry_defects(results["quad"], sides, rings)
    assert rotation < 1e-10 and mirror < 1e-10
    rotation, mirror = lantern_symmetry_defects(results["alternating"], sides, rings)
    assert rotation > 1e-2 and mirror > 1e-2
    diff = {
        (a, b): float((results[a] - results[b]).norm(dim=1).max())
        for a in results
        for b in results
        if a < b
    }
    assert min(diff.values()) > 1e-2, diff
    assert np.isfinite(list(diff.values())).all()
