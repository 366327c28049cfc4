"""PolygonMeshes: packed accessors, block-diagonal operators, shared caches, adapters, errors."""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import hex_pent_mesh, mixed_mesh, tolerances

import torch_polylap as tp
from torch_polylap.batch import PolygonMeshes, per_mesh_mean, per_mesh_sum
from torch_polylap.shapes import quad_grid

pytestmark = pytest.mark.usefixtures("one_thread")


def three_meshes():
    v1, f1 = mixed_mesh()
    v2, f2 = quad_grid(3, bump=0.2, seed=1)
    v3, f3 = hex_pent_mesh()
    return [v1, v2, v3], [f1, f2, f3]


def dense(A: torch.Tensor) -> torch.Tensor:
    return A.to_dense()


def test_packed_accessors_match_concatenation(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    nv = [v.shape[0] for v in verts]
    nf = [len(f) for f in faces]
    assert len(m) == 3
    assert torch.equal(m.verts_packed(), torch.cat(verts))
    assert m.num_verts_per_mesh().tolist() == nv
    assert m.num_faces_per_mesh().tolist() == nf
    assert m.mesh_to_verts_packed_first_idx().tolist() == [0, nv[0], nv[0] + nv[1]]
    assert m.verts_packed_to_mesh_idx().tolist() == sum(([i] * n for i, n in enumerate(nv)), [])
    assert m.faces_packed_to_mesh_idx().tolist() == sum(([i] * n for i, n in enumerate(nf)), [])
    # packed faces: each mesh's faces shifted by its first vertex, in order
    expected = []
    for i, f in enumerate(faces):
        shift = sum(nv[:i])
        expected += [[j + shift for j in face] for face in tp.as_faces(f).tolist()]
    assert m.faces_packed().tolist() == expected
    for i in range(3):
        v_i, f_i = m[i]
        assert torch.equal(v_i, verts[i])
        assert f_i.tolist() == tp.as_faces(faces[i]).tolist()
    assert m[-1][0] is m.verts_list()[2]
    with pytest.raises(IndexError, match="out of range"):
        m[3]
    assert m.dtype == torch.float64 and m.device.type == device.type
    assert m.faces_packed_to_mesh_idx().device.type == device.type


def test_packed_laplacian_is_block_diagonal_of_per_mesh_ones(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    L, M0 = m.laplacian(lam=1.7)
    expected_L = torch.block_diag(
        *[dense(tp.laplacian(v, f, 1.7)[0]) for v, f in zip(verts, faces, strict=True)]
    )
    expected_M = torch.block_diag(
        *[dense(tp.laplacian(v, f, 1.7)[1]) for v, f in zip(verts, faces, strict=True)]
    )
    torch.testing.assert_close(dense(L), expected_L, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(dense(M0), expected_M, rtol=1e-13, atol=1e-13)
    # the operator's diagonal is exactly L's diagonal
    torch.testing.assert_close(L.diagonal(), torch.diagonal(expected_L))


def test_gradient_through_packed_batch_matches_single_meshes(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    leaves = [v.clone().requires_grad_(True) for v in verts]
    m = PolygonMeshes(leaves, faces)
    L, _ = m.laplacian()
    LX = tp.sparse.spmm(L, m.verts_packed())
    (LX * LX).sum().backward()
    for v, f, leaf in zip(verts, faces, leaves, strict=True):
        x = v.clone().requires_grad_(True)
        Li, _ = tp.laplacian(x, f)
        LXi = tp.sparse.spmm(Li, x)
        (g,) = torch.autograd.grad((LXi * LXi).sum(), x)
        torch.testing.assert_close(leaf.grad, g, rtol=1e-12, atol=1e-12)


def test_update_packed_shares_topology_and_uses_new_vertices(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    topo = m.topology()
    assert m.topology() is topo
    new = m.verts_packed() * 2.0 + 0.1
    m2 = m.update_packed(new)
    assert m2.topology() is topo
    assert torch.equal(m2.verts_list()[1], new[verts[0].shape[0] : verts[0].shape[0] + 16])
    L2, M2 = m2.laplacian()
    L_ref, M_ref = tp.laplacian(new, m.faces_packed())
    torch.testing.assert_close(dense(L2), dense(L_ref))
    torch.testing.assert_close(dense(M2), dense(M_ref))
    # L scales like length^0 and M0 like length^2 under X -> 2X + c
    torch.testing.assert_close(dense(L2), dense(m.laplacian()[0]))
    torch.testing.assert_close(dense(M2), 4 * dense(m.laplacian()[1]))
    with pytest.raises(ValueError, match=r"\(41, 3\)"):
        m.update_packed(new[:-1])
    m32 = m.to(dtype=torch.float32)
    assert m32.dtype == torch.float32 and m32.topology() is topo
    L32 = m32.laplacian()[0]
    assert L32.dtype == torch.float32 and L32.device.type == device.type


def test_single_mesh_reuses_topology_cached_on_the_faces_tensor(device):
    v, f = quad_grid(4, device=device)
    a = PolygonMeshes([v], [f]).topology()
    b = PolygonMeshes([v * 3], [f]).topology()
    assert a is b is tp.get_topology(f, v.shape[0])


def test_per_mesh_reductions_against_a_loop(device):
    gen = torch.Generator().manual_seed(0)
    index = torch.tensor([0, 0, 2, 2, 2, 0, 3], device=device)
    values = torch.randn(7, 2, generator=gen, dtype=torch.float64).to(device)
    s = per_mesh_sum(values, index, 5)
    mean = per_mesh_mean(values, index, 5)
    assert s.device.type == mean.device.type == device.type
    for b in range(5):
        rows = values[index == b]
        torch.testing.assert_close(s[b], rows.sum(0))
        torch.testing.assert_close(
            mean[b],
            rows.mean(0) if len(rows) else torch.zeros(2, dtype=torch.float64, device=device),
        )
    with pytest.raises(ValueError, match="one mesh per row"):
        per_mesh_sum(values, index[:-1], 5)


def test_interior_edge_faces_share_an_edge(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    m = PolygonMeshes(verts, faces)
    f0, f1 = m.interior_edge_faces()
    assert f0.device.type == f1.device.type == device.type
    topo = m.topology()
    assert f0.numel() == int((topo.edge_faces == 2).sum())
    packed = m.faces_packed().tolist()

    def edges(face):
        return {frozenset((face[i], face[(i + 1) % len(face)])) for i in range(len(face))}

    for a, b in zip(f0.tolist(), f1.tolist(), strict=True):
        assert a != b and len(edges(packed[a]) & edges(packed[b])) == 1


def test_errors_name_the_mesh_and_vertex(device):
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    bad = list(faces)
    bad[1] = faces[1].clone()
    bad[1][5, 2] = 16  # mesh 1 has 16 vertices
    with pytest.raises(ValueError, match="mesh 1: face 5 refers to vertex 16"):
        PolygonMeshes(verts, bad)
    with pytest.raises(ValueError, match="3 vertex tensors but 2"):
        PolygonMeshes(verts, faces[:2])
    with pytest.raises(ValueError, match="mesh 2 has verts of dtype torch.float32"):
        PolygonMeshes(verts[:2] + [verts[2].float()], faces)
    with pytest.raises(ValueError, match=r"verts of mesh 0 must have shape \(V, 3\)"):
        PolygonMeshes([verts[0][:, :2]], [faces[0]])
    with pytest.raises(ValueError, match="mesh 0: face 0 has 2 vertices"):
        PolygonMeshes([verts[0]], [[[0, 1], [1, 2, 3]]])
    with pytest.raises(ValueError, match=r"mesh 1: face 0 .* visits vertex 5 twice"):
        PolygonMeshes(verts, [faces[0], [[0, 1, 5, 4, 5]], faces[2]]).topology()
    with pytest.raises(TypeError, match="list of"):
        PolygonMeshes(verts[0], faces[0])


def test_irregular_meshes_warn_with_the_mesh_and_local_indices(device):
    """A flipped face (mesh 2) and a fin (mesh 1) are not errors: one warning names each mesh
    with its own indices, the operators are the per-mesh ones, and what needs an orientation
    or a manifold refuses naming the mesh."""
    verts, faces = three_meshes()
    verts = [v.to(device) for v in verts]
    flipped = [list(reversed(f)) if i == 4 else f for i, f in enumerate(faces[2])]
    p, q = int(faces[1][0, 2]), int(faces[1][0, 3])  # an interior edge of the grid
    nv = verts[1].shape[0]
    lift = torch.tensor([0.0, 0.1, 1.0], dtype=torch.float64, device=device)
    fin_verts = torch.cat([verts[1], verts[1][[p, q]] + lift])
    fin = faces[1].tolist() + [[p, q, nv + 1, nv]]
    local = [
        tp.build_topology(f, v.shape[0], warn=False).report
        for v, f in [(fin_verts, fin), (verts[2], flipped)]
    ]
    assert local[0].non_manifold_edges.tolist() == [[min(p, q), max(p, q)]]
    misoriented = local[1].misoriented_edges.tolist()
    assert misoriented  # edges of the flipped face 4, in mesh 2's own numbering

    m = PolygonMeshes([verts[0], fin_verts, verts[2]], [faces[0], fin, flipped])
    with pytest.warns(UserWarning) as record:
        topo = m.topology()
    (warning,) = [str(w.message) for w in record]
    assert "2 of the 3 meshes" in warning and "mesh 0" not in warning
    assert f"mesh 1 ({nv + 2} vertices, {len(fin)} faces): 1 non-manifold edge(s)" in warning
    assert f"(first: {[[min(p, q), max(p, q)]]})" in warning
    assert f"mesh 2 ({verts[2].shape[0]} vertices, {len(flipped)} faces)" in warning
    assert f"inconsistent orientation (first: {misoriented[:5]})" in warning
    # the packed report keeps packed indices; topology_reports() has the local ones
    shift = verts[0].shape[0] + nv + 2
    assert topo.report.misoriented_edges.tolist() == (local[1].misoriented_edges + shift).tolist()
    reports = m.topology_reports()
    assert sorted(reports) == [1, 2]
    assert reports[2].misoriented_edges.tolist() == misoriented
    assert reports[1].non_manifold_edges.tolist() == local[0].non_manifold_edges.tolist()

    L, M0 = m.laplacian()
    assert L.device.type == device.type
    first = m.mesh_to_verts_packed_first_idx().tolist()
    for i, (v, f) in enumerate([(verts[0], faces[0]), (fin_verts, fin), (verts[2], flipped)]):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            Li, Mi = tp.laplacian(v, f)
        a, b = first[i], first[i] + v.shape[0]
        torch.testing.assert_close(dense(L)[a:b, a:b], dense(Li), rtol=0, atol=1e-12)
        torch.testing.assert_close(dense(M0)[a:b, a:b], dense(Mi), rtol=0, atol=1e-12)

    with pytest.raises(
        ValueError,
        match=r"mesh 2: normal_consistency needs consistently oriented faces.*"
        r"orient_faces",
    ):
        tp.losses.normal_consistency(m)
    with pytest.raises(ValueError, match=r"mesh 1: demo needs a manifold mesh.*non-manifold edge"):
        m.require_manifold("demo")
    # a batch of clean meshes: no warning, no report, nothing to refuse
    clean = PolygonMeshes(verts, faces)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        clean.topology()
    assert clean.topology_reports() == {}
    clean.require_oriented("demo")
    clean.require_manifold("demo")


def test_from_list_and_trimesh():
    trimesh = pytest.importorskip("trimesh", reason="trimesh not installed: pip install trimesh")
    box = trimesh.creation.box()
    ico = trimesh.creation.icosphere(1)
    m = PolygonMeshes.from_list([tp.from_trimesh(mesh) for mesh in (box, ico)])
    assert m.num_verts_per_mesh().tolist() == [len(box.vertices), len(ico.vertices)]
    np.testing.assert_allclose(m.verts_list()[1].numpy(), ico.vertices)
    assert m.faces_list()[0].tolist() == box.faces.tolist()
    verts, faces = three_meshes()
    m2 = PolygonMeshes.from_list(list(zip(verts, faces, strict=True)))
    assert torch.equal(m2.verts_packed(), torch.cat(verts))


def test_from_pyg_duck_typed_data():
    """The adapter only reads ``pos``/``face``/``polygons`` (and ``to_data_list`` of a Batch)."""
    v1, f1 = mixed_mesh()
    tri = torch.tensor([[0, 1, 2], [0, 2, 3]])
    v2 = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64)
    d1 = SimpleNamespace(pos=v1, polygons=f1)
    d2 = SimpleNamespace(pos=v2, face=tri.t())
    m = tp.from_pyg([d1, d2])
    assert m[1][1].tolist() == tri.tolist() and m[0][1].tolist() == f1
    batch = SimpleNamespace(to_data_list=lambda: [d2, d1])
    assert tp.from_pyg(batch).num_verts_per_mesh().tolist() == [4, 12]
    with pytest.raises(ValueError, match=r"`face` must have shape \(3, F\)"):
        tp.from_pyg(SimpleNamespace(pos=v2, face=tri))


def optional_adapter(module: str):
    """The optional package ``module`` that an adapter converts from; skips the test without it."""
    package = module.split(".")[0]
    return pytest.importorskip(
        module, reason=f"{package} not installed (optional adapter; not a dependency)"
    )


def triangulated_grid() -> tuple[torch.Tensor, torch.Tensor]:
    """The 2 x 2 quad grid's vertices and its ``(8, 3)`` triangles (each quad split at 0-2)."""
    v, f = quad_grid(2)
    return v, torch.cat([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])


def test_from_pyg_real_data():
    tg = optional_adapter("torch_geometric")
    v, tris = triangulated_grid()
    data = tg.data.Data(pos=v, face=tris.t().contiguous())
    m = tp.from_pyg(tg.data.Batch.from_data_list([data, data]))
    assert len(m) == 2 and m[1][1].tolist() == tris.tolist()


def test_from_pytorch3d():
    structures = optional_adapter("pytorch3d.structures")
    v, tris = triangulated_grid()
    meshes = structures.Meshes([v.float(), v.float() * 2], [tris, tris])
    m = tp.from_pytorch3d(meshes)
    assert torch.equal(m.verts_packed(), meshes.verts_packed())
    assert torch.equal(m.faces_packed().as_uniform(), meshes.faces_packed())


def test_batch_follows_device_and_dtype(device, dtype):
    verts, faces = three_meshes()
    reference = PolygonMeshes(verts, faces)  # float64 on the CPU
    m = reference.to(device, dtype)
    assert m.device.type == device.type and m.dtype == dtype
    L, M0 = m.laplacian()
    assert L.device.type == device.type and L.dtype == dtype and M0.dtype == dtype
    assert m.verts_packed_to_mesh_idx().device.type == device.type
    Ld, m0 = dense(L).cpu().double(), M0.diagonal().cpu().double()
    tol = tolerances(dtype)
    # per mesh: symmetric, constants in the kernel, masses summing to the mesh's area
    torch.testing.assert_close(Ld, Ld.T, **tol)
    torch.testing.assert_close(Ld.sum(1), torch.zeros_like(m0), rtol=0, atol=tol["atol"] * 10)
    owner = reference.verts_packed_to_mesh_idx()
    areas = [float(tp.face_areas(v, f).sum()) for v, f in zip(verts, faces, strict=True)]
    for i, area in enumerate(areas):
        assert float(m0[owner == i].sum()) == pytest.approx(area, rel=tol["rtol"])
    if (device.type, dtype) != ("cpu", torch.float64):
        ref_L, ref_M0 = reference.laplacian()
        torch.testing.assert_close(Ld, dense(ref_L), **tol)
        torch.testing.assert_close(m0, ref_M0.diagonal(), **tol)
