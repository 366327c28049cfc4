"""Repairs keep polygons, say what they changed, and map per-vertex/per-face data along."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from conftest import DATA
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap import repair
from torch_polylap.shapes import quad_grid


def _topology(faces, n):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return tp.build_topology(faces, n)


def test_orient_faces_flips_the_minority_back(device):
    V, F = quad_grid(4, bump=0.2, seed=1, device=device)
    bad = F.clone()
    bad[[3, 7, 8]] = bad[[3, 7, 8]].flip(1)
    V2, fixed, rep = repair.orient_faces(V, bad)
    assert V2 is V and rep.flipped_faces.tolist() == [3, 7, 8]
    assert fixed.tolist() == F.tolist() and rep.non_orientable_components == 0
    assert "3 face(s) flipped" in rep.summary()


def test_orient_faces_on_a_closed_mesh_with_random_flips(device):
    V, F = read_mesh(DATA / "sphere" / "quad_2.obj", device=device)
    rng = np.random.default_rng(0)
    flip = rng.random(F.num_faces) < 0.3
    bad = tp.PolygonFaces(
        torch.where(
            torch.from_numpy(np.repeat(flip, F.sizes.numpy())), F.flipped().indices, F.indices
        ),
        sizes=F.sizes,
    )
    assert not _topology(bad, V.shape[0]).is_oriented
    _, fixed, rep = repair.orient_faces(V, bad)
    topo = tp.build_topology(fixed, V.shape[0])  # no warning: clean
    assert topo.report.is_clean
    assert torch.allclose(tp.laplacian(V, topo)[0].to_dense(), tp.laplacian(V, F)[0].to_dense())


def test_orient_faces_reports_a_moebius_band(device):
    V, F = read_mesh(DATA / "moebius.obj", device=device)
    _, fixed, rep = repair.orient_faces(V, F)
    assert rep.non_orientable_components == 1 and rep.non_orientable_faces.size == F.num_faces
    assert fixed.tolist() == F.tolist()
    assert "1 non-orientable component(s)" in rep.summary()


def test_weld_vertices_closes_a_seam(device):
    V, F = quad_grid(3, bump=0.2, seed=2, device=device)
    # split the grid along the column x = 1/3: faces right of it use copies of its vertices
    seam = [4, 5, 6, 7]
    copies = {v: V.shape[0] + i for i, v in enumerate(seam)}
    split = [[copies.get(v, v) if f >= 3 else v for v in face] for f, face in enumerate(F.tolist())]
    Vs = torch.cat([V, V[seam] + 1e-12])
    assert _topology(split, Vs.shape[0]).num_edges > tp.build_topology(F, 16).num_edges
    V2, welded, rep = repair.weld_vertices(Vs, split)
    assert rep.vertex_source.tolist() == list(range(16)) and rep.vertex_map[16:].tolist() == seam
    assert welded.tolist() == F.tolist() and V2.device.type == device.type
    assert torch.equal(V2, Vs[:16])
    assert rep.changed_faces.tolist() == [3, 4, 5]  # the faces that used a copy
    _, _, none = repair.weld_vertices(Vs, split, tol=1e-14)  # below the gap: nothing welds
    assert none.vertex_source.size == Vs.shape[0]


def test_weld_then_remove_degenerate_faces(device):
    V = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1e-13, 0], [2, 0, 0], [3, 0, 0]],
        dtype=torch.float64,
        device=device,
    )
    faces = [[0, 1, 4, 2, 3], [1, 5, 2], [0, 5, 6], [1, 2, 1, 3]]  # 4 ~ 1; face 2 is collinear
    V2, welded, rep = repair.weld_vertices(V, faces, tol=1e-10)
    assert "face(s) now visit a vertex twice" in rep.summary()
    assert welded.tolist()[0] == [0, 1, 1, 2, 3]
    V3, clean, rep2 = repair.remove_degenerate_faces(V2, welded)
    assert V3.device.type == device.type
    assert clean.tolist() == [[0, 1, 2, 3], [1, 4, 2]]
    assert rep2.face_map.tolist() == [0, 1, -1, -1] and rep2.face_source.tolist() == [0, 1]
    assert rep2.changed_faces.tolist() == [0]
    assert "1 repeating a vertex, 1 of zero area removed" in rep2.summary()
    labels = np.array([10, 11, 12, 13])
    assert labels[rep2.face_source].tolist() == [10, 11]


def test_tiny_faces_are_not_degenerate(device):
    V, F = quad_grid(2, bump=0.2, seed=3, device=device)
    _, out, rep = repair.remove_degenerate_faces(V * 1e-150, F)
    assert out.num_faces == F.shape[0] and rep.removed_faces.size == 0


def test_remove_duplicate_faces_keeps_the_first(device):
    V, F = quad_grid(3, bump=0.2, seed=4, device=device)
    faces = F.tolist() + [F[4].tolist(), F[2].flip(0).tolist(), F[2].roll(1).tolist()]
    _, out, rep = repair.remove_duplicate_faces(V, faces)
    assert out.tolist() == F.tolist() and rep.removed_faces.tolist() == [9, 10, 11]
    assert rep.face_map[9:].tolist() == [-1, -1, -1]
    assert tp.topology.duplicate_faces(faces)[1].tolist() == [4, 2, 2]
    _, same, _ = repair.remove_duplicate_faces(V, [[0, 1, 5, 4], [0, 5, 1, 4]])
    assert same.num_faces == 2  # the same vertex set in another cycle is another polygon


def test_remove_unreferenced_vertices_maps_vertex_data(device):
    V, F = quad_grid(2, device=device)
    V = torch.cat([torch.tensor([[7.0, 7, 7]], dtype=V.dtype, device=device), V])
    faces = (F + 1).tolist()
    V2, out, rep = repair.remove_unreferenced_vertices(V, faces)
    assert rep.removed_vertices.tolist() == [0] and V2.device.type == device.type
    assert torch.equal(V2, V[1:])
    assert out.tolist() == F.tolist() and rep.vertex_map.tolist() == [-1, *range(9)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tp.laplacian(V2, out)
    arr, _, _ = repair.remove_unreferenced_vertices(V.cpu().numpy(), faces)
    assert isinstance(arr, np.ndarray) and arr.shape == (9, 3)


def test_repairs_name_bad_input(device):
    with pytest.raises(ValueError, match="refers to vertex 9, but verts has 4 rows"):
        repair.orient_faces(torch.zeros(4, 3, device=device), [[0, 1, 9]])
