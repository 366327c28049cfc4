"""Only what truly needs a manifold or an orientation refuses irregular meshes, at its own entry,
with a message that names the defect and the repair.

L, M0 and whatever is built only on them (the flow without volume normalization, the plate)
run on a misoriented grid, a Moebius band and a fin (a quad standing on an interior edge).
"""

from __future__ import annotations

import pytest
import torch
from conftest import DATA, on_device
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.apps import (
    FlowOptions,
    conformal_parameterization,
    enclosed_volume,
    mean_curvature_flow,
    plate_bending,
)
from torch_polylap.apps.conformal import conformal_energy, conformal_matrix
from torch_polylap.apps.planarize import planarize
from torch_polylap.fitting import mesh_quality
from torch_polylap.repair import orient_faces
from torch_polylap.shapes import quad_grid

VOLUME = FlowOptions(normalize="volume")

pytestmark = pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")


def flipped_grid():
    """A bumpy 3 x 3 quad grid with its centre face 4 reversed: 4 misoriented edges."""
    V, F = quad_grid(3, bump=0.2, seed=1)
    F = F.clone()
    F[4] = F[4].flip(0)
    return V, F


def moebius():
    return read_mesh(DATA / "moebius.obj")


def fin():
    """The grid with a quad standing on its interior edge (p, q): three faces on one edge."""
    V, F = quad_grid(3, bump=0.2, seed=1)
    p, q = int(F[0, 2]), int(F[0, 3])
    top = V[[p, q]] + torch.tensor([0.0, 0.1, 1.0], dtype=V.dtype)
    nv = V.shape[0]
    return torch.cat([V, top]), F.tolist() + [[p, q, nv + 1, nv]]


def bowtie():
    """Two flat quads sharing only vertex 2: manifold edges, one non-manifold vertex."""
    V = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 1, 0], [2, 2, 0], [1, 2, 0]],
        dtype=torch.float64,
    )
    return V, [[0, 1, 2, 3], [2, 4, 5, 6]]


def cubes(offsets: list[tuple[float, float, float]]):
    """Outward-oriented unit cubes at ``offsets``, sharing the vertices they have in common."""
    corner = [(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1)]  # index x + 2y + 4z
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    index: dict[tuple[float, float, float], int] = {}
    faces = []
    for o in offsets:
        ids = [
            index.setdefault(tuple(a + b for a, b in zip(c, o, strict=True)), len(index))
            for c in corner
        ]
        faces += [[ids[i] for i in q] for q in quads]
    return torch.tensor(list(index), dtype=torch.float64), faces


MISORIENTED = r"needs consistently oriented faces, but 4 edge\(s\) are traversed in the same "
ORIENT_FACES = r".*Run `verts, faces, rep = torch_polylap.repair.orient_faces\(verts, faces\)`"
NON_ORIENTABLE = r"needs an oriented mesh, but 1 of its components cannot be oriented"
FIN = r"needs a manifold mesh, but it has 1 non-manifold edge\(s\) used by 3\+ faces"


# -- conformal parameterization: manifold, oriented ------------------------------------------


def test_conformal_refuses_misoriented_non_orientable_and_non_manifold_meshes(device):
    V, F = on_device(flipped_grid(), device)
    for fn, name in (
        (lambda v, f: conformal_parameterization(v, f), "conformal_parameterization"),
        (
            lambda v, f: conformal_parameterization(v, f, free_boundary=True),
            "conformal_parameterization",
        ),
        (conformal_matrix, "conformal_matrix"),
        (lambda v, f: conformal_energy(v[:, :2], v, f), "conformal_energy"),
    ):
        with pytest.raises(ValueError, match=name + " " + MISORIENTED + ORIENT_FACES):
            fn(V, F)
        with pytest.raises(ValueError, match=name + " " + NON_ORIENTABLE):
            fn(*on_device(moebius(), device))
        with pytest.raises(ValueError, match=name + " " + FIN):
            fn(*on_device(fin(), device))
    # the suggested repair makes it work
    _, fixed, _ = orient_faces(V, F)
    uv = conformal_parameterization(V, fixed)
    assert uv.device.type == device.type and torch.isfinite(uv).all()


def test_conformal_parameterization_refuses_a_non_manifold_vertex_the_energy_does_not(device):
    V, F = on_device(bowtie(), device)
    with pytest.raises(
        ValueError, match=r"conformal_parameterization needs a manifold mesh.*non-manifold vertex"
    ):
        conformal_parameterization(V, F)
    # the energy needs manifold edges only: the identity map of a flat mesh costs nothing
    assert abs(float(conformal_energy(V[:, :2], V, F))) < 1e-12
    assert conformal_matrix(V, F).shape == (14, 14)


# -- normal consistency: oriented; edges of 3+ faces left out ---------------------------------


def test_normal_consistency_refuses_misoriented_meshes_and_skips_fin_edges(device):
    V, F = on_device(flipped_grid(), device)
    with pytest.raises(
        ValueError, match=r"mesh 0: normal_consistency " + MISORIENTED + ORIENT_FACES
    ):
        tp.losses.normal_consistency((V, F))
    with pytest.raises(ValueError, match="mesh 0: normal_consistency " + NON_ORIENTABLE):
        tp.losses.NormalConsistencyLoss()(on_device(moebius(), device))
    # a fin: its edge has no two sides and is left out of the mean, like a boundary edge
    Vf, Ff = on_device(fin(), device)
    n = tp.face_normals(Vf, Ff)
    owners: dict[frozenset, list[int]] = {}
    for fi, face in enumerate(Ff):
        for i in range(len(face)):
            owners.setdefault(frozenset((face[i], face[(i + 1) % len(face)])), []).append(fi)
    assert sorted(len(o) for o in owners.values())[-1] == 3
    pairs = [o for o in owners.values() if len(o) == 2]
    expected = torch.stack([1 - n[a] @ n[b] for a, b in pairs]).mean()
    torch.testing.assert_close(tp.losses.normal_consistency((Vf, Ff)), expected)


# -- mesh quality: folded_edges needs an orientation -------------------------------------------


def test_mesh_quality_refuses_misoriented_meshes(device):
    V, F = on_device(flipped_grid(), device)
    with pytest.raises(
        ValueError, match=r"mesh_quality \(its folded_edges measure\) " + MISORIENTED
    ):
        mesh_quality(V, F)
    with pytest.raises(ValueError, match="mesh_quality .*" + NON_ORIENTABLE):
        mesh_quality(*on_device(moebius(), device))
    _, fixed, _ = orient_faces(V, F)
    assert mesh_quality(V, fixed)["folded_edges"] == 0.0
    # a fin is oriented: its 3-face edge is left out of folded_edges (the fin stands upright,
    # 90 degrees from the grid, which would not count as folded anyway)
    q = mesh_quality(*on_device(fin(), device))
    assert q["folded_edges"] == 0.0 and q["nonconvex_faces"] == 0.0


# -- volume: closed oriented 2-cycle -----------------------------------------------------------


def test_enclosed_volume_needs_a_closed_oriented_surface(device):
    V, F = on_device(cubes([(0, 0, 0)]), device)
    assert float(enclosed_volume(V, F)) == pytest.approx(1.0, rel=1e-12)
    flipped = [f[::-1] if i == 2 else f for i, f in enumerate(F)]
    with pytest.raises(ValueError, match="enclosed_volume " + MISORIENTED + ORIENT_FACES):
        enclosed_volume(V, flipped)
    with pytest.raises(ValueError, match="enclosed_volume " + NON_ORIENTABLE):
        enclosed_volume(*on_device(moebius(), device))
    grid_v, grid_f = quad_grid(3, device=device)
    with pytest.raises(
        ValueError, match=r"enclosed_volume needs a closed mesh, but this one has 12 boundary edges"
    ):
        enclosed_volume(grid_v, grid_f)
    with pytest.raises(ValueError, match=r"enclosed_volume needs a closed mesh"):
        enclosed_volume(*on_device(fin(), device))  # the fin's free edges are boundary
    # a duplicated face: 4 edges used by 3 faces, unbalanced
    with pytest.raises(
        ValueError,
        match=r"enclosed_volume needs a manifold mesh, but it has 4 non-manifold edge\(s\).*"
        r"remove_duplicate_faces",
    ):
        enclosed_volume(V, [*F, F[0]])
    # two cubes sharing an edge: non-manifold, but a closed oriented 2-cycle (every edge is
    # traversed as often each way), so the volume is well defined
    V2, F2 = on_device(cubes([(0, 0, 0), (1, 1, 0)]), device)
    topo = tp.build_topology(F2, V2.shape[0], warn=False)
    assert not topo.is_manifold
    assert float(enclosed_volume(V2, topo)) == pytest.approx(2.0, rel=1e-12)


def test_flow_volume_normalization_checks_at_entry_and_the_flow_runs_on_any_mesh(device):
    V, F = on_device(cubes([(0, 0, 0)]), device)
    flipped = [f[::-1] if i == 2 else f for i, f in enumerate(F)]
    hint = r".*Use normalize='area' or None\."
    with pytest.raises(ValueError, match="normalize='volume' " + MISORIENTED + ORIENT_FACES + hint):
        mean_curvature_flow(V, flipped, 0.01, 1, options=VOLUME)
    with pytest.raises(ValueError, match="normalize='volume' " + NON_ORIENTABLE + hint):
        mean_curvature_flow(*on_device(moebius(), device), 0.01, 1, options=VOLUME)
    with pytest.raises(ValueError, match=r"normalize='volume' needs a closed mesh.*" + hint):
        mean_curvature_flow(*on_device(fin(), device), 0.01, 1, options=VOLUME)
    # the flow itself needs L and M0 only
    for verts, faces in (flipped_grid(), moebius(), fin(), (V, flipped)):
        X = mean_curvature_flow(verts.to(device), faces, 0.01, 2).verts
        assert X.shape == verts.shape and X.device.type == device.type
        assert torch.isfinite(X).all()
    area = FlowOptions(normalize="area")
    X = mean_curvature_flow(*on_device(moebius(), device), 0.01, 1, options=area).verts
    assert torch.isfinite(X).all()


# -- "vertex indices or a boolean mask": torch_polylap.checks.check_index_or_mask ---------------


def test_fixed_and_boundary_arguments_are_checked_alike(device):
    V, F = quad_grid(3, device=device)  # 16 vertices
    entries = {
        "fixed (flow)": lambda x: mean_curvature_flow(V, F, 0.01, 1, fixed=x),
        "fixed (planarize)": lambda x: planarize(V, F, max_iter=1, fixed=x),
        "boundary (plate)": lambda x: plate_bending(V, F, boundary=x),
    }
    for label, fn in entries.items():
        name = label.split()[0]
        with pytest.raises(ValueError, match=rf"{name}\[1\] = 16 is out of range for 16 "):
            fn([0, 16])
        with pytest.raises(ValueError, match=rf"{name}\[0\] = -1 is out of range"):
            fn(torch.tensor([-1]))
        with pytest.raises(ValueError, match=rf"{name}\[2\] = 3 repeats an earlier index"):
            fn([3, 5, 3])
        with pytest.raises(ValueError, match=rf"{name} is a boolean mask of shape \(15,\)"):
            fn(torch.zeros(15, dtype=torch.bool))
        with pytest.raises(TypeError, match=rf"{name} must hold integer indices"):
            fn(torch.tensor([1.0, 2.0]))
    # masks and indices still mean the same
    mask = torch.zeros(16, dtype=torch.bool)
    mask[[0, 3, 12, 15]] = True
    for fn in entries.values():
        a, b = fn(mask), fn(torch.tensor([0, 3, 12, 15]))
        a, b = (getattr(r, "verts", r) for r in (a, b))
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_plate_runs_on_any_mesh(device):
    for verts, faces in (flipped_grid(), moebius(), fin()):
        u = plate_bending(verts.to(device), faces)
        assert u.device.type == device.type
        assert torch.isfinite(u).all() and float(u.abs().max()) > 0
