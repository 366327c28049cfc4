"""Implicit mean-curvature flow (AW11 sec. 5.1): rates, invariants, gradients, the lantern."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.spatial
import torch
from conftest import DATA, assert_directional_derivative, hex_pent_mesh
from meshes import dumbbell, read_mesh

import torch_polylap as tp
from torch_polylap.apps import (
    FlowOptions,
    FlowResult,
    enclosed_volume,
    mean_curvature_flow,
    scale_free_mean_curvature,
)
from torch_polylap.apps.flow import SINGULARITY_FACTOR
from torch_polylap.shapes import quad_grid, schwarz_lantern, torus

FROZEN = FlowOptions(frozen=True)
GUARDED = FlowOptions(stop_at_singularity=True)


def unit_sphere(name: str):
    verts, faces = read_mesh(DATA / "sphere" / name, dtype=torch.float64)
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
        X = mean_curvature_flow(verts, faces, dt, steps, lam=1.0).verts
        assert X.device == verts.device
        # the shape stays round, so the squared radius is the area ratio
        r2 = float(tp.face_areas(X, faces).sum() / tp.face_areas(verts, faces).sum())
        radii = (X - X.mean(0)).norm(dim=1)
        assert float(radii.max() - radii.min()) < 5e-3
        errors.append(abs(r2 - expected))
    # the spatial error falls under refinement (measured 3.5e-5 -> 7e-6)
    assert errors[1] < errors[0] / 2 and errors[0] < 1e-4, errors


def test_frozen_and_rebuilt_flows_agree_to_second_order_in_dt(device):
    verts, faces = unit_sphere("quad_2.obj")
    verts = verts.to(device) * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64, device=device)
    gaps = []
    for dt in (2e-3, 1e-3):
        frozen = mean_curvature_flow(verts, faces, dt, 3, options=FROZEN).verts
        rebuilt = mean_curvature_flow(verts, faces, dt, 3).verts
        assert frozen.device.type == rebuilt.device.type == device.type
        moved = float((rebuilt - verts).norm(dim=1).max())
        assert moved > 1e-3  # the flow moved by O(dt)
        gaps.append(float((frozen - rebuilt).norm(dim=1).max()))
    # dt is a fifth of the squared edge length: the fastest modes relax within one step
    assert gaps[1] < 0.35 * gaps[0] and gaps[0] < 0.1 * moved, gaps
    one_frozen = mean_curvature_flow(verts, faces, 1e-3, 1, options=FROZEN).verts
    torch.testing.assert_close(one_frozen, mean_curvature_flow(verts, faces, 1e-3, 1).verts)


def test_area_and_volume_normalization_keep_their_measure(device):
    verts, faces = unit_sphere("hex_2.obj")
    verts = verts.to(device) * torch.tensor([1.0, 0.7, 0.5], dtype=torch.float64, device=device)
    area0 = tp.face_areas(verts, faces).sum()
    X = mean_curvature_flow(verts, faces, 0.01, 4, options=FlowOptions(normalize="area")).verts
    torch.testing.assert_close(tp.face_areas(X, faces).sum(), area0, rtol=1e-12, atol=0)
    assert float((X - verts).norm(dim=1).max()) > 1e-2  # the shape did change
    vol0 = enclosed_volume(verts, faces)
    Y = mean_curvature_flow(verts, faces, 0.01, 4, options=FlowOptions(normalize="volume"))
    Y = Y.verts
    torch.testing.assert_close(enclosed_volume(Y, faces), vol0, rtol=1e-12, atol=0)


def test_enclosed_volume_matches_independent_volumes(device):
    # a unit cube of quads under a linear map and a shift: volume |det A|
    corners = torch.tensor(
        [[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)], dtype=torch.float64
    )
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    A = torch.tensor([[1.2, 0.3, -0.1], [0.2, 0.9, 0.4], [-0.3, 0.1, 1.5]], dtype=torch.float64)
    box = (corners @ A.T + torch.tensor([3.0, -2.0, 1.0], dtype=torch.float64)).to(device)
    assert float(enclosed_volume(box, quads)) == pytest.approx(float(torch.det(A)), rel=1e-13)
    # the dodecahedron's pentagons are planar to the file's printed digits only
    verts, faces = read_mesh(DATA / "dodecahedron_poly.obj", dtype=torch.float64, device=device)
    hull = scipy.spatial.ConvexHull(verts.cpu().numpy())
    assert float(enclosed_volume(verts, faces)) == pytest.approx(hull.volume, rel=1e-6)


def test_flat_mesh_with_fixed_boundary_is_a_fixed_point_and_stays_in_its_plane(device):
    verts, faces = quad_grid(6, 5, seed=2, device=device)  # irregular convex quads in z = 0
    rotvec = scipy.spatial.transform.Rotation.from_rotvec([0.3, -0.5, 0.2])
    rot = torch.from_numpy(rotvec.as_matrix()).to(device)
    verts = verts @ rot.T + torch.tensor([0.2, 0.1, -0.4], dtype=torch.float64, device=device)
    normal = rot[:, 2]
    boundary = tp.build_topology(faces, verts.shape[0]).boundary_vertices
    # linear precision: (L X)_p = 0 at interior vertices of a planar mesh
    X = mean_curvature_flow(verts, faces, 0.05, 3, fixed=boundary).verts
    torch.testing.assert_close(X, verts, rtol=0, atol=1e-12)
    # with a free boundary the rim shrinks, but every vertex stays in the plane
    Y = mean_curvature_flow(verts, faces, 0.05, 3).verts
    assert float((Y - verts).norm(dim=1).max()) > 1e-3
    offsets = (Y - verts[0]) @ normal
    assert float(offsets.abs().max()) < 1e-12


def test_flow_is_differentiable_in_the_initial_positions(device):
    verts, faces = hex_pent_mesh()
    verts = verts.to(device)
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(verts.shape, generator=gen, dtype=torch.float64).to(device)

    def loss(X):
        return (mean_curvature_flow(X, faces, 0.05, 3, lam=2.0).verts * weights).sum()

    def loss_fixed_frozen(X):
        flowed = mean_curvature_flow(X, faces, 0.05, 3, fixed=torch.tensor([6, 7]), options=FROZEN)
        return (flowed.verts * weights).sum()

    assert_directional_derivative(loss, verts, rtol=1e-6)
    assert_directional_derivative(loss_fixed_frozen, verts, rtol=1e-6)


def test_trajectory_progress_and_argument_checks(device):
    verts, faces = unit_sphere("quad_2.obj")
    verts = verts.to(device)
    options = FlowOptions(trajectory=True, progress=True)
    result = mean_curvature_flow(verts, faces, 0.01, 2, options=options)
    traj = result.trajectory
    assert traj is not None and traj.shape == (3, *verts.shape)
    assert traj.device.type == device.type
    assert torch.equal(traj[0], verts) and torch.equal(traj[-1], result.verts)
    torch.testing.assert_close(traj[-1], mean_curvature_flow(verts, faces, 0.01, 2).verts)
    assert mean_curvature_flow(verts, faces, 0.01, 2).trajectory is None
    assert torch.equal(mean_curvature_flow(verts, faces, 0.01, 0).verts, verts)
    with pytest.raises(ValueError, match="dt"):
        mean_curvature_flow(verts, faces, 0.0, 2)
    with pytest.raises(ValueError, match="dt"):
        mean_curvature_flow(verts, faces, -1e-3, 2)
    with pytest.raises(ValueError, match="steps"):
        mean_curvature_flow(verts, faces, 0.01, -1)
    with pytest.raises(ValueError, match="normalize"):
        mean_curvature_flow(verts, faces, 0.01, 1, options=FlowOptions(normalize="length"))
    flat, quads = quad_grid(3, device=device)
    with pytest.raises(ValueError, match="closed mesh"):
        mean_curvature_flow(flat, quads, 0.01, 1, options=FlowOptions(normalize="volume"))
    with pytest.raises(ValueError, match="fixed"):
        mean_curvature_flow(
            verts, faces, 0.01, 1, fixed=torch.tensor([0]), options=FlowOptions(normalize="area")
        )


def test_trajectory_is_the_flow_restarted_from_each_state():
    """Each state of a rebuilt flow's trajectory is one step from the one before, bit for bit:
    the trajectory records the states the steps went through and nothing else."""
    verts, faces = unit_sphere("hex_2.obj")
    verts = verts * torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)
    result = mean_curvature_flow(
        verts, faces, 0.01, 3, lam=2.0, options=FlowOptions(trajectory=True)
    )
    assert result.trajectory is not None and result.steps == 3
    for before, after in zip(result.trajectory[:-1], result.trajectory[1:], strict=True):
        assert torch.equal(mean_curvature_flow(before, faces, 0.01, 1, lam=2.0).verts, after)
    assert torch.equal(result.trajectory[-1], result.verts)


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


def test_lantern_quad_flow_keeps_the_symmetry_that_triangulations_break(device):
    """AW11 Fig. 2: the result depends on the triangulation, the quad mesh has no such choice."""
    sides, rings = 6, 5
    results = {}
    for kind in ("quad", "horizontal", "vertical", "alternating"):
        verts, faces = schwarz_lantern(sides, rings, triangulation=kind, device=device)
        fixed = tp.build_topology(faces, verts.shape[0]).boundary_vertices
        flowed = mean_curvature_flow(verts, faces, 0.02, 10, lam=2.0, fixed=fixed).verts
        assert flowed.device.type == device.type
        results[kind] = flowed.cpu()
        if kind == "quad":
            # relabeling each quad cyclically (another "choice" a quad mesh does not have)
            shifted = [f[1:] + f[:1] for f in faces]
            again = mean_curvature_flow(verts, shifted, 0.02, 10, lam=2.0, fixed=fixed).verts
            torch.testing.assert_close(again.cpu(), results[kind], rtol=0, atol=1e-12)
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


# ---- the singularity guard ----------------------------------------------------------------


def largest_scale_free_curvature(verts: torch.Tensor, faces) -> float:
    """max_p |M0^{-1} L X|_p / 2 * sqrt(A / 4 pi), from the public operators (closed meshes)."""
    L, M0 = tp.laplacian(verts, faces)
    h = tp.strong_laplacian(L, M0, verts).norm(dim=1) / 2
    return float(h.max()) * math.sqrt(float(tp.face_areas(verts, faces).sum()) / (4 * math.pi))


def unguarded_flow_degenerates(verts, faces, dt: float, steps: int, bound: float) -> bool:
    """Whether the plain flow passes ``bound`` or breaks down (a singular system)."""
    try:
        raw = mean_curvature_flow(verts, faces, dt, steps).verts
    except ValueError:
        return True
    return not largest_scale_free_curvature(raw, faces) <= bound


@pytest.mark.parametrize(
    ("shape", "dt", "steps"),
    [("thin torus", 0.01, 20), ("dumbbell", 0.05, 20)],
)
def test_guard_stops_before_a_thin_part_pinches(shape, dt, steps, device):
    verts, faces = torus(24, 8, major=1.0, minor=0.15) if shape == "thin torus" else dumbbell()
    verts = verts.to(device)
    before = largest_scale_free_curvature(verts, faces)
    bound = SINGULARITY_FACTOR * max(before, 1.0)
    # the plain flow with this step does degenerate: without the guard this test would fail
    assert unguarded_flow_degenerates(verts, faces, dt, steps, bound)
    result = mean_curvature_flow(verts, faces, dt, steps, options=GUARDED)
    assert isinstance(result, FlowResult) and result.verts.device.type == device.type
    assert 0 < result.steps < steps and result.dt == dt  # a chosen step is kept
    assert result.stopped.startswith(f"at step {result.steps + 1} ")
    assert "pinching off" in result.stopped or "shrank to a point" in result.stopped
    # the state kept is within the bound (recomputed from the public operators) and is the
    # plain flow's state after as many steps: the guard only chooses where to stop
    assert largest_scale_free_curvature(result.verts, faces) <= bound
    plain = mean_curvature_flow(verts, faces, dt, result.steps)
    assert torch.equal(result.verts, plain.verts) and not plain.stopped


def test_guard_halves_the_step_before_giving_up(device):
    verts, faces = torus(24, 8, major=1.0, minor=0.15, device=device)
    dt, steps, halvings = 0.002, 10, 6
    kept = mean_curvature_flow(verts, faces, dt, steps, options=GUARDED)
    options = FlowOptions(stop_at_singularity=True, max_halvings=halvings)
    halved = mean_curvature_flow(verts, faces, dt, steps, options=options)
    # the smaller steps went further; a singularity in time still stops the flow, and only
    # once every halving is spent
    assert halved.steps > kept.steps
    assert halved.stopped and halved.dt == dt / 2**halvings
    bound = SINGULARITY_FACTOR * max(largest_scale_free_curvature(verts, faces), 1.0)
    assert largest_scale_free_curvature(halved.verts, faces) <= bound


def test_guard_that_never_fires_changes_nothing(device):
    """On a sphere the curvature stays put: every step is taken, bit for bit the plain flow's,
    trajectory and gradients included."""
    verts, faces = unit_sphere("quad_2.obj")
    verts = verts.to(device, copy=True).requires_grad_(True)
    plain = mean_curvature_flow(verts, faces, 0.01, 3, options=FlowOptions(trajectory=True))
    options = FlowOptions(trajectory=True, stop_at_singularity=True, max_halvings=2)
    guarded = mean_curvature_flow(verts, faces, 0.01, 3, options=options)
    assert (guarded.steps, guarded.dt, guarded.stopped) == (3, 0.01, "")
    assert (plain.steps, plain.dt, plain.stopped) == (3, 0.01, "")
    assert guarded.trajectory is not None and plain.trajectory is not None
    assert torch.equal(guarded.trajectory, plain.trajectory)
    weights = torch.linspace(-1, 1, verts.numel(), dtype=torch.float64, device=device)
    weights = weights.reshape(verts.shape)
    (g_plain,) = torch.autograd.grad((plain.verts * weights).sum(), verts)
    (g_guarded,) = torch.autograd.grad((guarded.verts * weights).sum(), verts)
    assert torch.equal(g_plain, g_guarded)


def test_scale_free_mean_curvature_is_one_on_round_spheres_of_any_size(device):
    verts, faces = unit_sphere("hex_3.obj")
    verts = verts.to(device)
    h = scale_free_mean_curvature(verts, faces)
    assert h.device.type == device.type
    torch.testing.assert_close(h, torch.ones_like(h), atol=0.05, rtol=0)  # H = 1/r, A = 4 pi r^2
    for radius in (0.1, 30.0):  # scale-free: the same at every size
        torch.testing.assert_close(scale_free_mean_curvature(radius * verts, faces), h)


def test_guard_argument_checks(device):
    verts, faces = unit_sphere("quad_2.obj")
    verts = verts.to(device)
    with pytest.raises(ValueError, match="stop_at_singularity"):
        mean_curvature_flow(verts, faces, 0.01, 1, options=FlowOptions(max_halvings=2))
    refused = {
        "frozen": FlowOptions(frozen=True, stop_at_singularity=True, max_halvings=2),
        "singularity_factor": FlowOptions(stop_at_singularity=True, singularity_factor=1),
        "max_halvings": FlowOptions(stop_at_singularity=True, max_halvings=-1),
    }
    for match, options in refused.items():
        with pytest.raises(ValueError, match=match):
            mean_curvature_flow(verts, faces, 0.01, 1, options=options)
