"""tp.datasets.precompute: the eigenpair cache filled on an executor, with a report.

The cached eigenvalues are checked against ``tp.eigs`` of the normalized mesh computed here; the
dataset must then read every entry without writing any; bad meshes fail alone; a damaged entry
(its checksum no longer matches) is recomputed.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import torch

import torch_polylap as tp
from torch_polylap.datasets import PolygonMeshDataset, normalize_mesh, precompute
from torch_polylap.datasets.jobs import InlineExecutor, local_executor
from torch_polylap.shapes import quad_grid

K = 6


def entries(cache):
    return {p.name: p.stat().st_mtime_ns for p in cache.glob("eigs-*.npz")}


def reference_evals(verts, faces):
    """``tp.eigs`` of the normalized mesh, as the dataset sees it (float64)."""
    v = normalize_mesh(verts.detach().cpu().to(torch.float64), tp.as_faces(faces))
    return tp.eigs(*tp.laplacian(v, faces), K)[0]


def grids(device):
    return [quad_grid(n, bump=0.2, seed=n, device=device) for n in (4, 5, 6)]


def test_cached_eigenvalues_equal_eigs_and_the_dataset_reads_them(tmp_path, device):
    meshes = grids(device)
    report = precompute(meshes, tmp_path, k=K, executor=InlineExecutor(), progress=False)
    assert (report.computed, report.reused, report.failed) == (3, 0, 0)
    state = entries(tmp_path)
    assert len(state) == 3
    data = PolygonMeshDataset(meshes, k=K, cache_dir=tmp_path, dtype=torch.float64)
    for i, (verts, faces) in enumerate(meshes):
        evals = data[i]["evals"]
        assert torch.allclose(evals.cpu(), reference_evals(verts, faces), rtol=0, atol=1e-8)
    assert entries(tmp_path) == state  # every item was a hit: nothing written again

    again = precompute(meshes, tmp_path, k=K, executor=InlineExecutor(), progress=False)
    assert (again.computed, again.reused, again.failed) == (0, 3, 0)
    assert entries(tmp_path) == state


def test_bad_meshes_fail_alone_with_their_file_and_reason(tmp_path, device):
    good = tmp_path / "good.obj"
    tp.write_mesh(good, *quad_grid(5, bump=0.1, device=device))
    garbage = tmp_path / "garbage.obj"
    garbage.write_text("v 0 0 0\nf 1 2 3\n")  # a face through vertices that do not exist
    tiny = quad_grid(1, device=device)  # 4 vertices: too few for K eigenpairs
    cache = tmp_path / "cache"
    with local_executor(2) as pool:
        report = precompute([garbage, good, tiny], cache, k=K, executor=pool, progress=False)
    assert (report.computed, report.reused, report.failed) == (1, 0, 2)
    reasons = {f.item: f.reason for f in report.failures}
    assert set(reasons) == {str(garbage), "item 2"}
    assert "ValueError" in reasons[str(garbage)]
    assert "too few for k = 6" in reasons["item 2"]
    assert not any(f.unwritable for f in report.failures)
    assert report.to_dict()["failed"] == 2
    with pytest.raises(ValueError, match=r"1 of 2 meshes were not cached: .*garbage\.obj"):
        PolygonMeshDataset([good, garbage], k=K, cache_dir=cache).precompute(num_workers=0)


def test_an_altered_entry_is_recomputed(tmp_path, device):
    verts, faces = quad_grid(5, bump=0.3, device=device)
    precompute([(verts, faces)], tmp_path, k=K, executor=InlineExecutor(), progress=False)
    (path,) = tmp_path.glob("eigs-*.npz")
    with np.load(path) as data:
        evals, evecs, digest = data["evals"], data["evecs"], data["sha256"]
    # a well-formed archive whose numbers changed: only the checksum tells
    np.savez(path, evals=evals * 1.5, evecs=evecs, sha256=digest)
    with pytest.warns(UserWarning, match="sha256 member does not match"):
        tp.cached_eigs(normalize_mesh(verts.cpu(), tp.as_faces(faces)), faces, K, tmp_path)
    # an archive without the checksum (another tool's, or a format without it) is not trusted
    np.savez(path, evals=evals, evecs=evecs)
    with pytest.warns(UserWarning, match="no sha256 member"):
        tp.cached_eigs(normalize_mesh(verts.cpu(), tp.as_faces(faces)), faces, K, tmp_path)
    np.savez(path, evals=evals * 1.5, evecs=evecs, sha256=digest)
    with ThreadPoolExecutor(1) as pool:
        report = precompute([(verts, faces)], tmp_path, k=K, executor=pool, progress=False)
    assert (report.computed, report.replaced, report.failed) == (1, 1, 0)
    cached = PolygonMeshDataset([(verts, faces)], k=K, cache_dir=tmp_path, dtype=torch.float64)
    assert torch.allclose(cached[0]["evals"].cpu(), reference_evals(verts, faces), atol=1e-8)


def test_an_unwritable_cache_fails_every_mesh_it_concerns(tmp_path, monkeypatch, device):
    """The cache warns once per folder and process; every mesh still reports its failure."""
    from torch_polylap import spectral

    def refuse(path, write):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(spectral, "_UNWRITABLE_REPORTED", set())
    monkeypatch.setattr(spectral, "atomic_write", refuse)
    report = precompute(grids(device), tmp_path, k=K, executor=InlineExecutor(), progress=False)
    assert (report.computed, report.failed) == (0, 3)
    assert [f.item for f in report.failures] == ["item 0", "item 1", "item 2"]  # input order
    reasons = [f.reason for f in report.failures]
    assert sum("cannot be written (PermissionError" in r for r in reasons) == 1  # one warning
    assert all("cannot be written" in r for r in reasons)  # and the same verdict for all
    assert all(f.unwritable for f in report.failures)
    # the dataset keeps cached_eigs's rule: nothing is lost (items recompute), so it warns
    data = PolygonMeshDataset(grids(device), k=K, cache_dir=tmp_path)
    with pytest.warns(spectral.CacheWriteWarning, match="cannot be written"):
        assert data.precompute().failed == 3
