"""Durability: atomic mesh writes under SIGKILL, and an eigenpair cache that survives bad files
and concurrent writers."""

from __future__ import annotations

import io
import os
import random
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import torch_polylap as tp
from torch_polylap.datasets import PolygonMeshDataset
from torch_polylap.shapes import quad_grid

K = 5

# --------------------------------------------------------------------------------------------
# mesh writers killed mid-write
# --------------------------------------------------------------------------------------------

WRITER = """
import sys
import numpy as np
from torch_polylap.io import write_mesh

def grid(n, seed):
    xs, ys = np.meshgrid(np.arange(n + 1.0), np.arange(n + 1.0), indexing="ij")
    z = np.random.default_rng(seed).random(xs.shape)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)
    return np.stack([xs.ravel(), ys.ravel(), z.ravel()], 1), quads.reshape(-1, 4)

MESHES = [grid(120, 0), grid(150, 1)]
if __name__ == "__main__":
    path, binary = sys.argv[1], sys.argv[2] == "1"
    print("ready", flush=True)
    while True:  # alternate the versions, so every moment is some write in progress
        for v, f in MESHES:
            write_mesh(path, v, f, binary=binary)
"""


def _versions(tmp_path: Path, suffix: str, binary: bool) -> set[bytes]:
    """The bytes of the two versions the writer script alternates, written here."""
    namespace: dict = {}
    exec(WRITER, namespace)  # the script's own mesh generator, without running its loop
    out = set()
    for i, (v, f) in enumerate(namespace["MESHES"]):
        tp.write_mesh(tmp_path / f"v{i}{suffix}", v, f, binary=binary)
        out.add((tmp_path / f"v{i}{suffix}").read_bytes())
    return out


def _assert_old_or_new(folder: Path, target: Path, versions: set[bytes]) -> None:
    assert target.read_bytes() in versions, "the target holds a partial write"
    for other in folder.iterdir():
        if other != target:  # a temporary left by the kill: hidden, not a mesh extension
            assert other.name.startswith(f".{target.name}.") and other.suffix == ".tmp"
    assert list(folder.glob("*" + target.suffix)) == [target]


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs POSIX signals (SIGKILL)")
@pytest.mark.parametrize(("name", "binary", "kills"), [("mesh.obj", "0", 2), ("mesh.ply", "1", 1)])
def test_killed_writer_leaves_old_or_new_file(tmp_path, name, binary, kills):
    """A subprocess alternates writing two versions of a large mesh; it is frozen (SIGSTOP) at
    random moments and the file inspected, then killed (SIGKILL) at a random moment and the
    file inspected: the file is always one complete version and no temporary looks like a
    mesh."""
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    folder = tmp_path / "out"
    folder.mkdir()
    target = folder / name
    versions = _versions(tmp_path, target.suffix, binary == "1")
    target.write_bytes(min(versions))  # the old file
    rng = random.Random(int(binary))
    for _ in range(kills):
        proc = subprocess.Popen(
            [sys.executable, str(script), str(target), binary], stdout=subprocess.PIPE, text=True
        )
        try:
            assert proc.stdout.readline().strip() == "ready"
            for _ in range(5):
                time.sleep(rng.uniform(0.0, 0.1))
                proc.send_signal(signal.SIGSTOP)
                _assert_old_or_new(folder, target, versions)
                proc.send_signal(signal.SIGCONT)
            time.sleep(rng.uniform(0.0, 0.1))
        finally:
            proc.kill()  # SIGKILL: no cleanup runs
            proc.wait()
            proc.stdout.close()
        _assert_old_or_new(folder, target, versions)


# --------------------------------------------------------------------------------------------
# eigenpair cache
# --------------------------------------------------------------------------------------------


@pytest.fixture
def mesh():
    V, F = quad_grid(4, bump=0.2, seed=1)
    return V, tp.as_faces(F)


def _corruptions(good: bytes, V: torch.Tensor) -> dict[str, bytes]:
    """Cache file contents that must count as misses, by what is wrong with them."""

    def npz(**arrays) -> bytes:
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return buffer.getvalue()

    n = V.shape[0]
    flipped = bytearray(good)
    for i in range(40, len(flipped), 97):
        flipped[i] ^= 0x5A
    return {
        "truncated": good[: len(good) // 2],
        "empty": b"",
        "flipped bytes": bytes(flipped),
        "garbage": b"not an archive at all\n" * 10,
        "wrong k": npz(evals=np.ones(K - 1), evecs=np.ones((n, K - 1))),
        "wrong n": npz(evals=np.ones(K), evecs=np.ones((n + 1, K))),
        "missing key": npz(evals=np.ones(K)),
        "bare npy": _npy(np.ones(K)),
        "non-finite": npz(evals=np.full(K, np.nan), evecs=np.ones((n, K))),
    }


def _npy(a: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, a)
    return buffer.getvalue()


def test_bad_cache_files_are_misses_replaced_with_one_warning(tmp_path, mesh, device):
    V, F = mesh
    V = V.to(device)
    evals, evecs = tp.cached_eigs(V, F, K, tmp_path)
    assert evals.device.type == evecs.device.type == device.type
    (path,) = tmp_path.glob("eigs-*.npz")
    good = path.read_bytes()
    for what, data in _corruptions(good, V).items():
        path.write_bytes(data)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            again = tp.cached_eigs(V, F, K, tmp_path)
        assert len(caught) == 1, what
        assert str(path) in str(caught[0].message) and "recomputing" in str(caught[0].message)
        assert torch.allclose(again[0], evals, atol=1e-10), what
        assert torch.allclose(again[1].abs(), evecs.abs(), atol=1e-8), what
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the replaced file is a hit
            hit = tp.cached_eigs(V, F, K, tmp_path)
        assert torch.equal(hit[0], again[0])
        assert sorted(p.name for p in tmp_path.iterdir()) == [path.name], what


def test_cache_dir_that_is_a_file_fails_before_any_work(tmp_path, mesh, monkeypatch):
    V, F = mesh
    not_a_dir = tmp_path / "cache"
    not_a_dir.write_text("I am a file")

    def no_work(*args, **kwargs):
        raise AssertionError("work started before the cache_dir check")

    monkeypatch.setattr(tp.spectral, "laplacian", no_work)
    monkeypatch.setattr(tp.spectral, "eigs_cache_key", no_work)
    with pytest.raises(ValueError, match=r"cache_dir .*cache exists but is not a directory"):
        tp.cached_eigs(V, F, K, not_a_dir)
    with pytest.raises(ValueError, match=r"cache_dir .*cache exists but is not a directory"):
        PolygonMeshDataset([(V, F)], k=K, cache_dir=not_a_dir)


def test_concurrent_threads_writing_one_key(tmp_path, mesh, device):
    V, F = mesh
    V = V.to(device)
    results, errors = [], []

    def work():
        try:
            results.append(tp.cached_eigs(V, F, K, tmp_path))
        except Exception as e:  # collected: an exception in a thread would go unnoticed
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert all(torch.equal(r[0], results[0][0]) for r in results)
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"]  # no temporary left behind


@pytest.mark.skipif(os.name != "posix", reason="fork-based precompute workers need POSIX")
def test_dataset_with_duplicate_meshes_precomputed_in_processes(tmp_path, mesh):
    V, F = mesh
    dataset = PolygonMeshDataset([(V, F)] * 6, k=K, cache_dir=tmp_path, dtype=torch.float64)
    dataset.precompute(num_workers=3)  # the same key written by several processes at once
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        items = [dataset[i] for i in range(len(dataset))]
    assert all(torch.equal(it["evals"], items[0]["evals"]) for it in items)
