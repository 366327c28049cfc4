"""PolygonMeshDataset: eigenpair cache, parallel precomputation, collate, DataLoader workers."""

from __future__ import annotations

import pytest
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh
from torch.utils.data import DataLoader

import torch_polylap as tp
import torch_polylap.nn as tnn
from torch_polylap.datasets import PolygonMeshDataset, collate_meshes, normalize_mesh
from torch_polylap.shapes import quad_grid

# the dataset reads the test meshes, whose object names the reader reports as skipped:
# expected here (tests/io asserts that warning)
pytestmark = pytest.mark.filterwarnings("ignore::torch_polylap.io.SkippedContentWarning")

K = 4


def items():
    return [
        quad_grid(3, bump=0.2),
        mixed_mesh(),
        hex_pent_mesh(),
        DATA / "dodecahedron_poly.obj",
    ]


@pytest.fixture
def dataset(tmp_path):
    return PolygonMeshDataset(items(), [0, 1, 2, 1], k=K, cache_dir=tmp_path, dtype=torch.float64)


def cache_state(path):
    return {p.name: p.stat().st_mtime_ns for p in path.glob("eigs-*.npz")}


def test_items_hold_the_operators_and_eigenpairs_of_the_normalized_mesh(dataset):
    for i in range(len(dataset)):
        item = dataset[i]
        V, F = dataset.mesh(i)
        assert torch.isclose(tp.mass(V, F).sum(), torch.tensor(1.0, dtype=V.dtype))  # unit area
        L, M0 = tp.laplacian(V, F)
        assert torch.equal(item["verts"], V)
        L_item = torch.from_numpy(tp.sparse.to_scipy(item["L"]).toarray())
        assert torch.allclose(L_item, L.to_dense())
        assert torch.allclose(item["mass"], M0.diagonal())
        # L phi = mu M0 phi, M0-orthonormal
        phi, mu = item["evecs"], item["evals"]
        assert torch.allclose(L @ phi, (item["mass"][:, None] * phi) * mu, atol=1e-9)
        assert torch.allclose(
            phi.t() @ (item["mass"][:, None] * phi), torch.eye(K, **{"dtype": phi.dtype}), atol=1e-9
        )
    with pytest.raises(ValueError, match="too few for k"):
        PolygonMeshDataset(items(), k=15, cache_dir=dataset.cache_dir)[1]


def test_second_access_hits_the_cache(dataset, tmp_path):
    first = [dataset[i] for i in range(len(dataset))]
    state = cache_state(tmp_path)
    assert len(state) == len(dataset)
    again = [dataset[i] for i in range(len(dataset))]
    assert cache_state(tmp_path) == state  # no file written or rewritten
    for a, b in zip(first, again, strict=True):
        assert torch.equal(a["evals"], b["evals"]) and torch.equal(a["evecs"], b["evecs"])


def test_parallel_precompute_fills_the_cache(dataset, tmp_path):
    dataset.precompute(num_workers=2)
    state = cache_state(tmp_path)
    assert len(state) == len(dataset)
    item = dataset[2]
    assert cache_state(tmp_path) == state
    V, F = dataset.mesh(2)
    evals, _ = tp.eigs(*tp.laplacian(V, F), K)
    assert torch.allclose(item["evals"], evals, atol=1e-10)


def test_collate_builds_the_index_maps(dataset, device):
    batch = collate_meshes([dataset[i] for i in (2, 0, 3)]).to(device)
    sizes = [13, 16, 20]
    assert batch.spectrum.num_verts.tolist() == sizes
    assert batch.spectrum.first_idx.tolist() == [0, 13, 29]
    expected = torch.repeat_interleave(torch.arange(3), torch.tensor(sizes)).to(device)
    assert torch.equal(batch.spectrum.vert_to_mesh, expected)
    assert torch.equal(batch.meshes.verts_packed_to_mesh_idx(), expected)
    assert torch.equal(batch.labels, torch.tensor([2, 0, 1], device=device))
    # packed faces use global indices: each mesh's faces shifted by its first vertex
    faces = batch.meshes.faces_packed()
    face_mesh = batch.meshes.faces_packed_to_mesh_idx()
    corner_mesh = torch.repeat_interleave(face_mesh.cpu(), faces.sizes.cpu())
    assert torch.equal(expected.cpu()[faces.indices.cpu()], corner_mesh)
    # block-diagonal operators equal the block-diagonal assembly of the packed batch
    L, M0 = batch.meshes.laplacian()
    assert torch.allclose(batch.L.to_dense(), L.to_dense())
    assert torch.allclose(batch.M0.to_dense(), M0.to_dense())
    for b, i in enumerate((2, 0, 3)):
        rows = batch.spectrum.vert_to_mesh == b
        assert torch.equal(batch.spectrum.evecs[rows].cpu(), dataset[i]["evecs"])


def test_dataloader_with_two_workers(tmp_path):
    data = PolygonMeshDataset(items(), [0, 1, 2, 1], k=K, cache_dir=tmp_path)
    loader = DataLoader(data, batch_size=2, num_workers=2, collate_fn=collate_meshes)
    batches = list(loader)
    assert [b.labels.tolist() for b in batches] == [[0, 1], [2, 1]]
    assert len(cache_state(tmp_path)) == len(data)  # the workers filled the cache
    torch.manual_seed(0)
    model = tnn.DiffusionNetLike(0, 3, width=8, num_blocks=1, hks_features=3)
    for b in batches:
        assert b.spectrum.evecs.dtype == torch.float32
        logits = model(spectrum=b.spectrum)
        assert logits.shape == (2, 3) and torch.isfinite(logits).all()
    reference = collate_meshes([data[0], data[1]])  # the same items, collated here
    assert torch.equal(batches[0].spectrum.evecs, reference.spectrum.evecs)
    assert torch.equal(batches[0].L.to_dense(), reference.L.to_dense())


def test_normalize_mesh_is_scale_and_translation_invariant(device):
    V, F = mixed_mesh()
    V, F = V.to(device), tp.as_faces(F)
    moved = 3.0 * V + torch.tensor([1.0, -2.0, 0.5], dtype=V.dtype, device=device)
    assert normalize_mesh(moved, F).device.type == device.type
    assert torch.allclose(normalize_mesh(moved, F), normalize_mesh(V, F), atol=1e-12)
