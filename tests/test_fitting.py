"""torch_polylap.fitting: samples, Chamfer distance and mesh-quality measures."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import DATA, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.fitting import (
    ChamferOptions,
    chamfer_distance,
    mesh_quality,
    nearest_neighbors,
    sample_points,
)
from torch_polylap.shapes import quad_grid


def _planar_mixed():
    verts, faces = mixed_mesh()
    verts = verts.clone()
    verts[:, 2] = 0.0
    return verts, faces


@pytest.mark.parametrize("backend", ["kdtree", "cdist"])
def test_chamfer_matches_brute_force(backend, device):
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(120, 3, generator=gen, dtype=torch.float64).to(device)
    b = (torch.rand(90, 3, generator=gen, dtype=torch.float64) * 1.3).to(device)
    D = ((a[:, None] - b[None]) ** 2).sum(-1)  # full matrix, independent of the chunked search
    expected = D.min(1).values.mean() + D.min(0).values.mean()
    got, got_normals = chamfer_distance(
        a, b, options=ChamferOptions(backend=backend, chunk_size=50)
    )
    assert got_normals is None
    assert torch.allclose(got, expected, rtol=1e-12, atol=0)
    summed = ChamferOptions(backend=backend, point_reduction="sum")
    got_sum, _ = chamfer_distance(a, b, options=summed)
    assert torch.allclose(got_sum, D.min(1).values.sum() + D.min(0).values.sum(), rtol=1e-12)
    d, idx = nearest_neighbors(a, b, backend=backend, chunk_size=7)
    assert idx.device.type == d.device.type == device.type
    assert torch.equal(idx, D.argmin(1))
    assert torch.allclose(d, D.min(1).values, rtol=1e-12, atol=0)


def test_chamfer_gradient_matches_finite_differences(device):
    gen = torch.Generator().manual_seed(1)
    a = torch.rand(15, 3, generator=gen, dtype=torch.float64).to(device).requires_grad_(True)
    b = torch.rand(20, 3, generator=gen, dtype=torch.float64).to(device).requires_grad_(True)
    # generic points have unique nearest neighbours, so the Chamfer distance is smooth there
    assert torch.autograd.gradcheck(lambda x, y: chamfer_distance(x, y)[0], (a, b), eps=1e-7)


def test_chamfer_of_identical_sets_is_zero_and_symmetric(device):
    gen = torch.Generator().manual_seed(2)
    a = torch.randn(64, 3, generator=gen).to(device)
    b = torch.randn(80, 3, generator=gen).to(device)
    assert chamfer_distance(a, a)[0].item() == 0.0
    assert torch.allclose(chamfer_distance(a, b)[0], chamfer_distance(b, a)[0])


def test_bad_point_sets_raise(device):
    a = torch.rand(5, 3, device=device)
    with pytest.raises(ValueError, match="none on the other"):
        chamfer_distance(a, torch.rand(0, 3, device=device))
    with pytest.raises(ValueError, match="point dimension"):
        chamfer_distance(a, torch.rand(5, 2, device=device))
    with pytest.raises(ValueError, match="non-empty"):
        nearest_neighbors(a, torch.rand(0, 3, device=device))
    with pytest.raises(ValueError, match="backend"):
        nearest_neighbors(a, a, backend="faiss")
    with pytest.raises(ValueError, match="point_reduction"):
        chamfer_distance(a, a, options=ChamferOptions(point_reduction="median"))
    with pytest.raises(ValueError, match="batch_reduction"):
        chamfer_distance(a, a, options=ChamferOptions(batch_reduction="max"))


def test_sample_points_density_is_proportional_to_area(device):
    """On planar convex faces of different areas and degrees (3 to 6), the number of samples
    per face is binomial with p = area / total area."""
    verts, faces = _planar_mixed()
    verts = verts.to(device)
    assert mesh_quality(verts, faces)["nonconvex_faces"] == 0.0
    S = 50_000
    gen = torch.Generator(device).manual_seed(3)
    pts, fid = sample_points(verts, faces, S, generator=gen, return_face_ids=True)
    assert pts.device.type == fid.device.type == device.type
    p = tp.face_areas(verts, faces) / tp.face_areas(verts, faces).sum()
    counts = torch.bincount(fid, minlength=p.numel()).double()
    sigma = (S * p * (1 - p)).sqrt()
    assert ((counts - S * p).abs() / sigma).max() < 4.5
    assert torch.all(pts[:, 2] == 0)


@pytest.mark.parametrize("shape", ["triangle", "square", "hexagon"])
def test_sample_points_are_uniform_inside_a_face(shape, device):
    """Empirical distribution of the samples against exact CDFs. Triangle (0,0),(1,0),(0,1):
    P(x + y <= t) = t^2 and P(x <= t) = 1 - (1 - t)^2. Unit square: x, y uniform on [0, 1].
    Regular hexagon of circumradius 1: P(|p| <= t) = t^2 for t below the inradius."""
    if shape == "triangle":
        verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    elif shape == "square":
        verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    else:
        a = torch.arange(6, dtype=torch.float64) * math.pi / 3
        verts = torch.stack([a.cos(), a.sin(), torch.zeros(6, dtype=torch.float64)], 1)
    faces = [list(range(verts.shape[0]))]
    S = 40_000
    p = sample_points(verts.to(device), faces, S, generator=torch.Generator(device).manual_seed(6))
    assert p.device.type == device.type
    p = p.cpu()
    ts = torch.linspace(0.1, 0.8, 8, dtype=torch.float64)
    if shape == "triangle":
        checks = [(p[:, 0] + p[:, 1], ts.square()), (p[:, 0], 1 - (1 - ts).square())]
    elif shape == "square":
        checks = [(p[:, 0], ts), (p[:, 1], ts)]
    else:
        checks = [(p[:, :2].norm(dim=1), ts.square() * (math.pi / (1.5 * math.sqrt(3))))]
    for values, cdf in checks:
        empirical = (values[:, None] <= ts[None]).double().mean(0)
        assert (empirical - cdf).abs().max() < 4.5 * math.sqrt(0.25 / S)  # binomial 4.5 sigma


def test_sample_points_lie_inside_their_faces(device):
    verts, faces = _planar_mixed()
    gen = torch.Generator(device).manual_seed(4)
    pts, fid = sample_points(verts.to(device), faces, 5000, generator=gen, return_face_ids=True)
    assert pts.device.type == device.type
    pts, fid = pts.cpu(), fid.cpu()
    for f, face in enumerate(faces):  # convex faces: inside = left of every edge (ccw from +z)
        x = verts[face, :2]
        e = torch.roll(x, -1, 0) - x
        q = pts[fid == f, :2]
        r = q[:, None] - x[None]
        cross = e[None, :, 0] * r[..., 1] - e[None, :, 1] * r[..., 0]
        assert bool((cross >= -1e-12).all()), f"a sample of face {f} lies outside it"


def test_sample_points_on_a_sphere_mesh_and_gradient(device):
    verts, faces = read_mesh(DATA / "sphere" / "quad_2.obj", device=device)
    X = verts.clone().requires_grad_(True)
    S = 3000
    pts = sample_points(X, faces, S, generator=torch.Generator(device).manual_seed(5))
    r = pts.detach().norm(dim=1)
    assert r.max() <= 1 + 1e-12 and r.min() > 0.95  # on the chords of the unit sphere
    pts.sum().backward()
    # every sample is a convex combination of its face's corners: weights sum to one
    assert torch.isfinite(X.grad).all()
    assert torch.allclose(X.grad.sum(0), torch.full_like(X[0], float(S)))
    assert bool((X.grad >= -1e-12).all())


def test_sample_points_follows_dtype_and_rejects_bad_input(device, dtype):
    verts, faces = quad_grid(3, device=device)
    pts = sample_points(verts.to(dtype), faces, 10)
    assert pts.dtype == dtype and pts.shape == (10, 3) and pts.device.type == device.type
    with pytest.raises(ValueError, match="num_samples"):
        sample_points(verts, faces, 0)
    with pytest.raises(ValueError, match="verts"):
        sample_points(verts[:, :2], faces, 5)


def test_mesh_quality_of_a_regular_grid(device):
    verts, faces = quad_grid(4, device=device)
    q = mesh_quality(verts, faces)
    assert q["angle_error_deg"] == pytest.approx(0, abs=1e-9)
    assert q["min_angle_deg"] == pytest.approx(90)
    assert q["aspect"] == pytest.approx(1)
    assert q["edge_cv"] == pytest.approx(0, abs=1e-12)
    assert q["nonplanarity_max"] == pytest.approx(0, abs=1e-12)
    assert q["nonconvex_faces"] == 0 and q["folded_edges"] == 0


def test_mesh_quality_detects_reflex_corners_and_folds(device):
    verts, faces = quad_grid(2, device=device)  # 3 x 3 vertices, centre vertex 4
    moved = verts.clone()
    moved[4, :2] = torch.tensor([0.9, 0.9])  # inside the top-right quad: a reflex corner there
    q = mesh_quality(moved, faces)
    assert q["nonconvex_faces"] == pytest.approx(1 / 4)
    # two triangles folded onto each other across their shared edge: normals opposite
    v = torch.tensor(
        [[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0.9, 1e-3]], dtype=torch.float64, device=device
    )
    q = mesh_quality(v, [[0, 1, 2], [1, 0, 3]])
    assert q["folded_edges"] == 1.0


def test_mesh_quality_matches_per_face_loops(device):
    verts, faces = read_mesh(DATA / "spot_control_mesh.obj")
    q = mesh_quality(verts.to(device), faces)
    V = verts.numpy()
    normals = tp.face_normals(verts, faces).numpy()
    topo = tp.get_topology(faces, V.shape[0])
    idx, off = topo.faces.indices.numpy(), topo.faces.offsets.numpy()
    edge_faces: dict[tuple[int, int], list[int]] = {}
    angle_err, lengths = [], []
    for f in range(len(off) - 1):
        c = idx[off[f] : off[f + 1]]
        k = len(c)
        for i in range(k):
            a, b, prev = V[c[i]], V[c[(i + 1) % k]], V[c[i - 1]]
            u, w = b - a, prev - a
            ang = math.acos(np.clip(u @ w / np.linalg.norm(u) / np.linalg.norm(w), -1, 1))
            angle_err.append(abs(ang - math.pi * (k - 2) / k))
            edge_faces.setdefault((min(c[i], c[(i + 1) % k]), max(c[i], c[(i + 1) % k])), [])
            edge_faces[(min(c[i], c[(i + 1) % k]), max(c[i], c[(i + 1) % k]))].append(f)
    for a, b in edge_faces:
        lengths.append(np.linalg.norm(V[a] - V[b]))
    dots = [normals[fs[0]] @ normals[fs[1]] for fs in edge_faces.values() if len(fs) == 2]
    assert q["angle_error_deg"] == pytest.approx(math.degrees(np.mean(angle_err)), rel=1e-9)
    assert q["edge_cv"] == pytest.approx(np.std(lengths, ddof=1) / np.mean(lengths), rel=1e-9)
    assert q["folded_edges"] == pytest.approx(np.mean(np.array(dots) < 0), rel=1e-12)
