"""Interop with pytorch3d, torch_geometric and trimesh conventions; pytorch3d's chamfer_distance.

pytorch3d is compiled and not installable here, so its adapter is checked on the data it hands
to ``Meshes`` (through a stand-in ``pytorch3d.structures`` module) and on its ImportError; a
test against the real class runs where pytorch3d is installed. torch_geometric is pure Python
and is tested against its real ``Data``/``Batch``.
"""

from __future__ import annotations

import sys
import types
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh
from meshes import read_mesh

import torch_polylap as tp
from torch_polylap.batch import PolygonMeshes
from torch_polylap.fitting import ChamferOptions, chamfer_distance
from torch_polylap.interop import (
    from_pyg,
    from_pytorch3d,
    to_pyg,
    to_pytorch3d,
    triangle_faces,
)
from torch_polylap.shapes import quad_grid


def three_meshes():
    v1, f1 = mixed_mesh()
    v2, f2 = quad_grid(3, bump=0.2, seed=1)
    v3, f3 = hex_pent_mesh()
    return [v1, v2, v3], [f1, f2, f3]


def _read(name: str):
    return read_mesh(DATA / name)


def _triangle_areas(verts: torch.Tensor, tris: torch.Tensor) -> torch.Tensor:
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    return 0.5 * torch.linalg.cross(b - a, c - a).norm(dim=1)


# --------------------------------------------------------------------------- padded accessors


def test_padded_accessors_match_the_lists(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    nv = [v.shape[0] for v in verts]
    padded = m.verts_padded()
    assert padded.shape == (3, max(nv), 3) and padded.device.type == device.type
    for i, v in enumerate(verts):
        assert torch.equal(padded[i, : nv[i]], v)
        assert bool((padded[i, nv[i] :] == 0).all())
    flat = padded.reshape(-1, 3)
    assert torch.equal(flat[m.verts_padded_to_packed_idx()], m.verts_packed())
    assert m.num_verts_per_mesh().tolist() == nv
    assert m.mesh_to_verts_packed_first_idx().tolist() == [0, nv[0], nv[0] + nv[1]]
    owner = torch.repeat_interleave(torch.arange(3), torch.tensor(nv))
    assert torch.equal(m.verts_packed_to_mesh_idx().cpu(), owner)
    fp = m.faces_padded()
    k_max = max(max(len(f) for f in fs) for fs in faces)
    assert fp.shape == (3, max(len(f) for f in faces), k_max) and fp.dtype == torch.int64
    for i, fs in enumerate(faces):
        got = [[j for j in row if j >= 0] for row in fp[i].tolist()]
        assert got[: len(fs)] == [list(map(int, f)) for f in fs]
        assert all(not row for row in got[len(fs) :])  # padding faces are all -1


def test_verts_padded_is_differentiable(device):
    verts, faces = three_meshes()
    leaves = [v.to(device, copy=True).requires_grad_(True) for v in verts]
    m = PolygonMeshes(leaves, faces)
    weights = torch.randn(m.verts_padded().shape, dtype=torch.float64, device=device)
    (m.verts_padded() * weights).sum().backward()
    for i, v in enumerate(leaves):
        assert torch.equal(v.grad, weights[i, : v.shape[0]])


# --------------------------------------------------------------------------- index offsets


def _block_diag_dense(mats: list[torch.Tensor]) -> torch.Tensor:
    return torch.block_diag(*[A.to_dense() for A in mats])


def test_packed_faces_follow_the_pyg_increment_and_give_the_block_diagonal_laplacian():
    tg = pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    verts, faces = three_meshes()
    m = PolygonMeshes(verts, faces)
    # torch_geometric's own batching of the same meshes (its increment rule, not ours)
    batch = tg.data.Batch.from_data_list(
        [
            tg.data.Data(pos=v, polygon_index=f.indices, polygon_sizes=f.sizes)
            for v, f in zip(verts, m.faces_list(), strict=True)
        ]
    )
    assert torch.equal(batch.polygon_index, m.faces_packed().indices)
    assert torch.equal(batch.batch, m.verts_packed_to_mesh_idx())
    # per-mesh operators, assembled one by one, are the blocks of the batch's
    L, M0 = m.laplacian()
    blocks = [tp.laplacian(v, f) for v, f in zip(verts, faces, strict=True)]
    torch.testing.assert_close(L.to_dense(), _block_diag_dense([b[0] for b in blocks]))
    torch.testing.assert_close(M0.to_dense(), _block_diag_dense([b[1] for b in blocks]))


def test_collate_offsets_polygon_faces_like_pyg(tmp_path):
    from torch_polylap.datasets import PolygonMeshDataset, collate_meshes

    verts, faces = three_meshes()
    data = PolygonMeshDataset(list(zip(verts, faces, strict=True)), k=4, cache_dir=tmp_path)
    batch = collate_meshes([data[2], data[0], data[1]])
    order = [2, 0, 1]
    first = 0
    packed = batch.meshes.faces_packed().tolist()
    expected = []
    for i in order:
        expected += [[first + int(j) for j in f] for f in faces[i]]
        first += verts[i].shape[0]
    assert packed == expected
    blocks = [tp.laplacian(data.mesh(i)[0], faces[i])[0] for i in order]
    torch.testing.assert_close(
        batch.L.to_dense(), _block_diag_dense(blocks).to(batch.L.dtype), rtol=1e-5, atol=1e-6
    )


# --------------------------------------------------------------------------- torch_geometric


def _mesh_edge_set(faces) -> set[tuple[int, int]]:
    """The undirected edges of a polygon mesh, from its faces' cycles (independent of the
    package's topology)."""
    edges = set()
    for f in tp.as_faces(faces).tolist():
        for a, b in zip(f, f[1:] + f[:1], strict=True):
            edges.add((min(a, b), max(a, b)))
    return edges


def _directed(edges: set[tuple[int, int]]) -> torch.Tensor:
    both = sorted(edges | {(b, a) for a, b in edges})
    return torch.tensor(both, dtype=torch.int64).t()


def test_to_pyg_quad_grid_has_the_mesh_edges_and_no_tetrahedra():
    tg = pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    from torch_geometric.transforms import FaceToEdge
    from torch_geometric.utils import coalesce, is_undirected, to_undirected

    v, f = quad_grid(2)
    data = to_pyg(v, f)
    assert isinstance(data, tg.data.Data) and data.pos is v
    # 2 x 2 quads: 2 * 3 * 3 = 12 edges; a (4, F) `face` is read as tetrahedra (20 edges)
    assert "face" not in data and data.edge_index.shape == (2, 24)
    assert torch.equal(data.edge_index, _directed(_mesh_edge_set(f)))
    assert is_undirected(data.edge_index)
    assert torch.equal(to_undirected(data.edge_index, num_nodes=9), data.edge_index)
    assert torch.equal(coalesce(data.edge_index, num_nodes=9), data.edge_index)
    assert torch.equal(data.polygon_index, f.reshape(-1))
    assert data.polygon_sizes.tolist() == [4] * 4
    # what the old layout handed FaceToEdge: the tetrahedra's 6 edges per quad, 20 in all
    tets = FaceToEdge()(tg.data.Data(pos=v, face=f.t().contiguous()))
    assert tets.edge_index.shape[1] // 2 == 20
    # torch_geometric's FaceToEdge reads triangles and tetrahedra only; on a graph without
    # `face` it asserts (2.8) or, in a version that skips such graphs, must keep our edges
    try:
        kept = FaceToEdge()(data.clone())
    except AssertionError:
        pass
    else:
        assert torch.equal(kept.edge_index, data.edge_index)


def test_to_pyg_triangles_match_face_to_edge():
    tg = pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    from torch_geometric.transforms import FaceToEdge

    v, q = quad_grid(3, bump=0.2, seed=1)
    tris = torch.cat([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    data = to_pyg(v, tris)
    assert torch.equal(data.face, tris.t()) and "polygon_index" not in data
    # torch_geometric's own FaceToEdge, from `face`, rebuilds exactly our edge_index
    rebuilt = FaceToEdge(remove_faces=False)(tg.data.Data(pos=v, face=data.face))
    assert torch.equal(rebuilt.edge_index, data.edge_index)
    assert torch.equal(data.edge_index, _directed(_mesh_edge_set(tris)))


def test_to_pyg_mixed_degrees_and_triangulate():
    pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    vm, fm = mixed_mesh()
    mixed = to_pyg(vm, fm)
    pf = tp.as_faces(fm)
    assert "face" not in mixed
    assert torch.equal(mixed.polygon_index, pf.indices)
    assert torch.equal(mixed.polygon_sizes, pf.sizes)
    assert torch.equal(mixed.edge_index, _directed(_mesh_edge_set(fm)))
    both = to_pyg(vm, fm, triangulate=True)
    assert both.face.shape == (3, int((pf.sizes - 2).sum()))
    assert torch.equal(both.face.t(), triangle_faces(vm, fm))
    assert torch.equal(both.polygon_index, pf.indices)
    assert torch.equal(both.edge_index, mixed.edge_index)  # the mesh's, not the triangulation's
    tri = torch.tensor([[0, 1, 2], [0, 2, 3]])
    assert "polygon_index" not in to_pyg(vm[:4], tri, triangulate=True)


@pytest.mark.parametrize("mesh", ["mixed", "hexpent", "triangles"])
def test_to_pyg_laplacian_is_what_get_laplacian_rebuilds(mesh):
    pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    from torch_geometric.utils import get_laplacian, is_undirected, to_scipy_sparse_matrix

    if mesh == "triangles":
        v, q = quad_grid(3, bump=0.3, seed=2)
        f = torch.cat([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    else:
        v, f = mixed_mesh() if mesh == "mixed" else hex_pent_mesh()
    v = v.clone().requires_grad_(True)
    data = to_pyg(v, f, laplacian=True)
    n = v.shape[0]
    assert is_undirected(data.edge_index, data.edge_weight)
    assert bool((data.edge_index[0] != data.edge_index[1]).all())  # off-diagonal only
    index, weight = get_laplacian(data.edge_index, data.edge_weight, num_nodes=n)
    rebuilt = to_scipy_sparse_matrix(index, weight.detach(), num_nodes=n).toarray()
    L, _ = tp.laplacian(v.detach(), f)
    np.testing.assert_allclose(rebuilt, L.to_dense().numpy(), rtol=1e-12, atol=1e-12)
    # every mesh edge is in the pattern; polygons add the pairs of corners across a face
    pairs = {tuple(e) for e in data.edge_index.t().tolist() if e[0] < e[1]}
    assert _mesh_edge_set(f) <= pairs
    if mesh == "triangles":  # the cotangent weights: libigl's cotmatrix off the diagonal
        assert pairs == _mesh_edge_set(f)
        igl = pytest.importorskip("igl", reason="libigl not installed: pip install libigl")
        C = igl.cotmatrix(v.detach().numpy(), f.numpy())
        rows, cols = data.edge_index.numpy()
        np.testing.assert_allclose(
            data.edge_weight.detach().numpy(), np.asarray(C[rows, cols]).ravel(), rtol=1e-10
        )
    # the weights are differentiable in the vertices
    data.edge_weight.square().sum().backward()
    assert v.grad is not None and bool(v.grad.abs().sum() > 0)


@pytest.mark.parametrize("triangulate", [False, True])
@pytest.mark.parametrize("laplacian", [False, True])
def test_pyg_round_trips(triangulate, laplacian):
    tg = pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    verts, faces = three_meshes()
    for v, f in zip(verts, faces, strict=True):
        back_v, back_f = from_pyg(to_pyg(v, f, triangulate=triangulate, laplacian=laplacian))
        assert back_v is v and back_f.tolist() == tp.as_faces(f).tolist()
    m = PolygonMeshes(verts, faces)
    batch = to_pyg(m, triangulate=triangulate, laplacian=laplacian)
    assert isinstance(batch, tg.data.Batch) and batch.num_graphs == 3
    assert torch.equal(batch.pos, m.verts_packed())
    back = from_pyg(batch)
    assert isinstance(back, PolygonMeshes)
    assert back.faces_packed().tolist() == m.faces_packed().tolist()
    assert torch.equal(back.verts_packed(), m.verts_packed())
    if not laplacian:  # the batch's edges are the packed mesh's, offset by torch_geometric
        assert torch.equal(batch.edge_index, _directed(_mesh_edge_set(m.faces_packed())))
    # a quad batch holds polygons, a triangle batch `face` with global indices
    grids = PolygonMeshes([quad_grid(2)[0], quad_grid(3)[0]], [quad_grid(2)[1], quad_grid(3)[1]])
    gb = to_pyg(grids, triangulate=triangulate, laplacian=laplacian)
    assert torch.equal(gb.polygon_index, grids.faces_packed().indices)
    v, q = quad_grid(2)
    tris = torch.cat([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    pair = PolygonMeshes([v, v * 2], [tris, tris])
    tb = to_pyg(pair, triangulate=triangulate, laplacian=laplacian)
    assert torch.equal(tb.face.t(), pair.faces_packed().as_uniform()) and "polygon_index" not in tb


def test_from_pyg_reads_triangles_and_polygons_and_refuses_tetrahedra():
    tg = pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    v, f = quad_grid(2)
    tris = torch.cat([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
    got_v, got_t = from_pyg(tg.data.Data(pos=v, face=tris.t()))
    assert got_v is v and torch.equal(got_t.as_uniform(), tris)
    polys = tg.data.Data(pos=v, polygon_index=f.reshape(-1), polygon_sizes=torch.full((4,), 4))
    assert torch.equal(from_pyg(polys)[1].as_uniform(), f)
    batch = tg.data.Batch.from_data_list([polys, polys])
    m = from_pyg(batch)
    assert len(m) == 2 and torch.equal(m[1][1].as_uniform(), f)
    # torch_geometric reads a (4, F) `face` as tetrahedra: no guess, the message says what to do
    with pytest.raises(ValueError, match="tetrahedra") as info:
        from_pyg(tg.data.Data(pos=v, face=f.t().contiguous()))
    assert "polygon_index" in str(info.value)
    with pytest.raises(ValueError, match=r"must have shape \(3, F\)"):
        from_pyg(tg.data.Data(pos=v, face=f[:2]))
    with pytest.raises(ValueError, match="polygon_sizes"):
        from_pyg(SimpleNamespace(pos=v, polygon_index=f.reshape(-1)))
    with pytest.raises(ValueError, match="no faces"):
        from_pyg(SimpleNamespace(pos=v))


def test_pyg_gradients_reach_the_vertices():
    pytest.importorskip(
        "torch_geometric", reason="torch_geometric not installed: pip install torch_geometric"
    )
    verts, faces = three_meshes()
    leaves = [v.clone().requires_grad_(True) for v in verts]
    batch = to_pyg(PolygonMeshes(leaves, faces))
    batch.pos.square().sum().backward()
    for v in leaves:
        torch.testing.assert_close(v.grad, 2 * v.detach())


def test_to_pyg_without_torch_geometric(monkeypatch):
    monkeypatch.setitem(sys.modules, "torch_geometric", None)
    monkeypatch.setitem(sys.modules, "torch_geometric.data", None)
    v, f = quad_grid(1)
    with pytest.raises(ImportError, match="pip install torch_geometric"):
        to_pyg(v, f)


# --------------------------------------------------------------------------- pytorch3d


class _FakeMeshes:
    """Records what a ``pytorch3d.structures.Meshes`` would be built from."""

    def __init__(self, verts, faces):
        self.verts, self.faces = verts, faces

    def verts_list(self):
        return self.verts

    def faces_list(self):
        return self.faces


@pytest.fixture
def fake_pytorch3d(monkeypatch):
    root = types.ModuleType("pytorch3d")
    structures = types.ModuleType("pytorch3d.structures")
    structures.Meshes = _FakeMeshes
    root.structures = structures
    monkeypatch.setitem(sys.modules, "pytorch3d", root)
    monkeypatch.setitem(sys.modules, "pytorch3d.structures", structures)


@pytest.mark.parametrize("name", ["grid/concave_3.obj", "tetris.obj", "grid/irr_poly_2.obj"])
def test_triangulation_preserves_face_areas(name, device):
    verts, faces = _read(name)  # planar meshes with non-convex faces of up to 10 corners
    tris = triangle_faces(verts.to(device), faces)
    assert tris.shape == (int((faces.sizes - 2).sum()), 3)
    tris = tris.cpu()
    owner = torch.repeat_interleave(torch.arange(len(faces)), faces.sizes - 2)
    per_face = torch.zeros(len(faces), dtype=verts.dtype).index_add_(
        0, owner, _triangle_areas(verts, tris)
    )
    torch.testing.assert_close(per_face, tp.face_areas(verts, faces), rtol=1e-10, atol=1e-12)
    # each triangle uses its own face's corners, and keeps its orientation
    for t, f in zip(tris.tolist()[:50], owner.tolist()[:50], strict=True):
        assert set(t) <= set(faces[f].tolist())
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    tri_normal = torch.linalg.cross(b - a, c - a)
    assert bool(((tri_normal * tp.face_normals(verts, faces)[owner]).sum(1) > 0).all())


def test_to_pytorch3d_hands_over_triangles_and_the_vertices(fake_pytorch3d, device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    leaves = [v.clone().requires_grad_(True) for v in verts]
    m = PolygonMeshes(leaves, faces)
    meshes = to_pytorch3d(m)
    assert isinstance(meshes, _FakeMeshes)
    assert all(a is b for a, b in zip(meshes.verts, leaves, strict=True))
    for v, f, t in zip(verts, faces, meshes.faces, strict=True):
        assert t.dtype == torch.int64 and torch.equal(t, triangle_faces(v, f))
        assert int(t.min()) >= 0 and int(t.max()) < v.shape[0]  # local indices
    # a single mesh
    one = to_pytorch3d(verts[1], faces[1])
    assert len(one.verts) == 1 and torch.equal(one.faces[0], meshes.faces[1])
    # a loss on the triangles' areas back-propagates to the polygon mesh's vertices
    area = sum(_triangle_areas(v, t).sum() for v, t in zip(meshes.verts, meshes.faces, strict=True))
    area.backward()
    assert all(v.grad is not None and bool(v.grad.abs().sum() > 0) for v in leaves)
    # and back: a Meshes becomes a triangle PolygonMeshes with the same vertices
    back = from_pytorch3d(meshes)
    assert torch.equal(back.verts_packed(), m.verts_packed())
    assert back.faces_list()[0].tolist() == meshes.faces[0].tolist()


def test_to_pytorch3d_without_pytorch3d_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pytorch3d", None)
    monkeypatch.setitem(sys.modules, "pytorch3d.structures", None)
    v, f = quad_grid(1)
    with pytest.raises(ImportError, match="pytorch3d.git") as info:
        to_pytorch3d(v, f)
    assert "triangle_faces" in str(info.value)


def test_to_pytorch3d_real_meshes():
    structures = pytest.importorskip(
        "pytorch3d.structures", reason="pytorch3d not installed (compiled; optional)"
    )
    verts, faces = three_meshes()
    meshes = to_pytorch3d(PolygonMeshes([v.float() for v in verts], faces))
    assert isinstance(meshes, structures.Meshes)
    expected = torch.cat(
        [
            t + int(o)
            for t, o in zip(
                triangle_faces(PolygonMeshes(verts, faces)),
                PolygonMeshes(verts, faces).mesh_to_verts_packed_first_idx(),
                strict=True,
            )
        ]
    )
    assert torch.equal(meshes.faces_packed(), expected)


def test_adapter_argument_errors(device):
    v, f = quad_grid(1, device=device)
    with pytest.raises(TypeError, match="without faces"):
        triangle_faces(v)
    with pytest.raises(TypeError, match="alone"):
        triangle_faces(PolygonMeshes([v], [f]), f)
    with pytest.raises(ValueError, match="vertex"):
        triangle_faces(v[:2], f)


# --------------------------------------------------------------------------- chamfer_distance


def _brute_force_chamfer(
    x,
    y,
    x_lengths,
    y_lengths,
    x_normals=None,
    y_normals=None,
    weights=None,
    batch_reduction="mean",
    point_reduction="mean",
    norm=2,
    single_directional=False,
    abs_cosine=True,
):
    """pytorch3d's documented semantics, spelled out with full distance matrices."""

    def direction(a, b, la, lb, na, nb):
        rows, cos_rows = [], []
        for i in range(a.shape[0]):
            d = torch.cdist(a[i, : la[i]], b[i, : lb[i]], p=norm)
            d = d.square() if norm == 2 else d
            best, j = d.min(dim=1)
            row = a.new_zeros(a.shape[1])
            row[: la[i]] = best
            rows.append(row * (1.0 if weights is None else weights[i]))
            if na is not None:
                c = torch.nn.functional.cosine_similarity(na[i, : la[i]], nb[i][j], dim=1)
                c = 1 - (c.abs() if abs_cosine else c)
                crow = a.new_zeros(a.shape[1])
                crow[: la[i]] = c
                cos_rows.append(crow * (1.0 if weights is None else weights[i]))
        return torch.stack(rows), (torch.stack(cos_rows) if na is not None else None)

    def reduce(t, lengths):
        if point_reduction is None:
            return t
        if point_reduction == "max":
            per = t.max(dim=1).values
        else:
            per = t.sum(1)
            if point_reduction == "mean":
                per = per / torch.tensor(lengths, dtype=t.dtype, device=t.device).clamp(min=1)
        if batch_reduction is None:
            return per
        if batch_reduction == "sum":
            return per.sum()
        return per.sum() / (weights.sum() if weights is not None else t.shape[0])

    fx = direction(x, y, x_lengths, y_lengths, x_normals, y_normals)
    if single_directional:
        return reduce(fx[0], x_lengths), None if fx[1] is None else reduce(fx[1], x_lengths)
    fy = direction(y, x, y_lengths, x_lengths, y_normals, x_normals)
    loss = (reduce(fx[0], x_lengths), reduce(fy[0], y_lengths))
    normals = None
    if fx[1] is not None:
        normals = (reduce(fx[1], x_lengths), reduce(fy[1], y_lengths))
    if point_reduction is None:
        return loss, normals
    return loss[0] + loss[1], None if normals is None else normals[0] + normals[1]


def _clouds(seed=0, n=3, p1=40, p2=30):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, p1, 3, generator=gen, dtype=torch.float64)
    y = torch.rand(n, p2, 3, generator=gen, dtype=torch.float64) * 1.2
    xn = torch.randn(n, p1, 3, generator=gen, dtype=torch.float64)
    yn = torch.randn(n, p2, 3, generator=gen, dtype=torch.float64)
    return x, y, xn, yn, torch.tensor([40, 17, 25]), torch.tensor([30, 30, 9])


def _assert_same(got, expected):
    if isinstance(expected, tuple):
        assert isinstance(got, tuple) and len(got) == len(expected)
        for g, e in zip(got, expected, strict=True):
            _assert_same(g, e)
    elif expected is None:
        assert got is None
    else:
        torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("batch_reduction", ["mean", "sum", None])
@pytest.mark.parametrize("point_reduction", ["mean", "sum", "max", None])
@pytest.mark.parametrize("norm", [1, 2])
@pytest.mark.parametrize("backend", ["kdtree", "cdist"])
def test_chamfer_matches_brute_force_reference(
    batch_reduction, point_reduction, norm, backend, device
):
    x, y, xn, yn, lx, ly = (t.to(device) for t in _clouds())
    normals = point_reduction != "max"
    for single in (False, True):
        for weights in (None, torch.tensor([0.5, 2.0, 0.0], dtype=torch.float64, device=device)):
            data = dict(
                x_normals=xn if normals else None,
                y_normals=yn if normals else None,
                weights=weights,
            )
            knobs = dict(
                batch_reduction=batch_reduction,
                point_reduction=point_reduction,
                norm=norm,
                single_directional=single,
            )
            options = ChamferOptions(**knobs, backend=backend, chunk_size=7)
            got = chamfer_distance(x, y, lx, ly, **data, options=options)
            expected = _brute_force_chamfer(x, y, lx.tolist(), ly.tolist(), **data, **knobs)
            _assert_same(got, expected)


def test_chamfer_defaults_and_the_single_cloud_extension(device):
    x, y, xn, yn, _, _ = (t.to(device) for t in _clouds(seed=1))
    loss, normals = chamfer_distance(x[:1], y[:1])
    assert normals is None and loss.shape == ()
    d = torch.cdist(x[0], y[0]).square()
    expected = d.min(1).values.mean() + d.min(0).values.mean()  # squared, mean, mean
    torch.testing.assert_close(loss, expected, rtol=1e-12, atol=0)
    two_d, _ = chamfer_distance(x[0], y[0])  # (P, D) is one cloud
    torch.testing.assert_close(two_d, loss, rtol=0, atol=0)
    # abs_cosine: flipped normals cost nothing with it, 2 per point without
    same, n_same = chamfer_distance(x[:1], x[:1], x_normals=xn[:1], y_normals=-xn[:1])
    assert float(same) == 0.0 and float(n_same) < 1e-12
    signed = ChamferOptions(abs_cosine=False)
    _, n_flip = chamfer_distance(x[:1], x[:1], x_normals=xn[:1], y_normals=-xn[:1], options=signed)
    torch.testing.assert_close(n_flip, torch.tensor(4.0, dtype=torch.float64, device=device))


def test_chamfer_reads_pointclouds_duck_typed(device):
    x, y, xn, yn, lx, ly = (t.to(device) for t in _clouds(seed=2))
    cloud = SimpleNamespace(
        points_padded=lambda: x, num_points_per_cloud=lambda: lx, normals_padded=lambda: xn
    )
    target = SimpleNamespace(
        points_padded=lambda: y, num_points_per_cloud=lambda: ly, normals_padded=lambda: yn
    )
    _assert_same(chamfer_distance(cloud, target), chamfer_distance(x, y, lx, ly, xn, yn))


def test_chamfer_gradients_with_padding(device):
    x, y, xn, yn, lx, ly = (t.to(device) for t in _clouds(seed=3, n=3, p1=40, p2=30))
    x = x[:, :12].clone().requires_grad_(True)
    y = y[:, :10].clone().requires_grad_(True)
    lx, ly = torch.tensor([12, 5, 9], device=device), torch.tensor([10, 10, 4], device=device)

    def f(a, b):
        options = ChamferOptions(batch_reduction="sum", point_reduction="mean")
        loss, _ = chamfer_distance(a, b, lx, ly, options=options)
        return loss

    assert torch.autograd.gradcheck(f, (x, y), eps=1e-7)
    f(x, y).backward()
    assert bool((x.grad[1, 5:] == 0).all()) and bool((y.grad[2, 4:] == 0).all())


def test_chamfer_edge_cases(device):
    x, y, _, _, _, _ = (t.to(device) for t in _clouds(seed=4))
    zero, normals = chamfer_distance(
        x, y, weights=torch.zeros(3, dtype=torch.float64, device=device)
    )
    assert float(zero) == 0.0 and normals is None
    per_cloud = ChamferOptions(batch_reduction=None)
    empty, _ = chamfer_distance(
        x,
        y,
        torch.tensor([0, 40, 40], device=device),
        torch.tensor([0, 30, 30], device=device),
        options=per_cloud,
    )
    assert float(empty[0]) == 0.0 and bool((empty[1:] > 0).all())
    with pytest.raises(ValueError, match="none on the other"):
        chamfer_distance(
            x, y, torch.tensor([3, 40, 40], device=device), torch.tensor([0, 30, 30], device=device)
        )
    with pytest.raises(ValueError, match="takes no normals"):
        chamfer_distance(
            x, y, x_normals=x, y_normals=y, options=ChamferOptions(point_reduction="max")
        )
    with pytest.raises(ValueError, match="norm"):
        chamfer_distance(x, y, options=ChamferOptions(norm=3))
    with pytest.raises(ValueError, match="non-negative"):
        weights = torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64, device=device)
        chamfer_distance(x, y, weights=weights)
    with pytest.raises(ValueError, match="x_lengths"):
        chamfer_distance(x, y, x_lengths=torch.tensor([1, 2], device=device))
    with pytest.raises(ValueError, match="same number of clouds"):
        chamfer_distance(x, y[:2])
