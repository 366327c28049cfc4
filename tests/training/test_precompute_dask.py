"""tp.datasets.precompute and ``polylap precompute --scheduler`` on a Dask cluster.

A ``LocalCluster`` of two worker processes on localhost (no other network): the cached
eigenvalues equal ``tp.eigs`` computed here, the command reports through the scheduler's
address, and a worker killed mid-run costs a retry, not a failure.
"""

from __future__ import annotations

import json
import os
import signal
import threading

import pytest
import torch

import torch_polylap as tp
from torch_polylap.cli import main
from torch_polylap.datasets import PolygonMeshDataset, normalize_mesh, precompute
from torch_polylap.shapes import quad_grid

distributed = pytest.importorskip(
    "distributed", reason="dask's distributed is missing: pip install 'torch_polylap[distributed]'"
)

K = 8

pytestmark = [
    pytest.mark.slow,  # a cluster of two worker processes starts in 3-10 s
    # the cluster's own notices (a port in use, a worker restarting) are not this package's
    pytest.mark.filterwarnings("ignore::UserWarning:distributed"),
]


@pytest.fixture(scope="module")
def client():
    cluster = distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    )
    with cluster, distributed.Client(cluster) as c:
        yield c


def meshes(count: int, n: int, device) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [quad_grid(n, bump=0.2, seed=i, device=device) for i in range(count)]


def test_cached_eigenvalues_equal_eigs(client, tmp_path, device):
    items = [(v.cpu(), f.cpu()) for v, f in meshes(6, 8, device)]
    report = precompute(items, tmp_path, k=K, executor=client.get_executor(), progress=False)
    assert (report.computed, report.reused, report.failed) == (6, 0, 0)
    data = PolygonMeshDataset(items, k=K, cache_dir=tmp_path, dtype=torch.float64)
    for i, (verts, faces) in enumerate(items):
        v = normalize_mesh(verts, tp.as_faces(faces))
        expected = tp.eigs(*tp.laplacian(v, faces), K)[0]
        assert torch.allclose(data[i]["evals"], expected, rtol=0, atol=1e-8)
    again = precompute(items, tmp_path, k=K, executor=client.get_executor(), progress=False)
    assert (again.computed, again.reused, again.failed) == (0, 6, 0)


def test_the_command_runs_on_a_scheduler(client, tmp_path, capsys, device):
    (tmp_path / "meshes").mkdir()
    for i, (verts, faces) in enumerate(meshes(4, 6, device)):
        tp.write_mesh(tmp_path / "meshes" / f"m{i}.off", verts.cpu(), faces.cpu())
    address = client.scheduler.address
    argv = ["precompute", str(tmp_path / "meshes"), "--cache", str(tmp_path / "cache")]
    assert main([*argv, "-k", "5", "--scheduler", address, "--json", "--no-progress"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (report["computed"], report["reused"], report["failed"]) == (4, 0, 0)


def test_a_worker_killed_mid_run_does_not_fail_the_run(client, tmp_path, device):
    items = [(v.cpu(), f.cpu()) for v, f in meshes(24, 40, device)]
    victim = next(iter(client.run(os.getpid).values()))
    entries_at_kill: list[int] = []

    def kill_when_started() -> None:
        while not list(tmp_path.glob("eigs-*.npz")):
            threading.Event().wait(0.01)
        entries_at_kill.append(len(list(tmp_path.glob("eigs-*.npz"))))
        os.kill(victim, signal.SIGKILL)  # the nanny starts a new worker; Dask reruns its tasks

    killer = threading.Thread(target=kill_when_started, daemon=True)
    killer.start()
    report = precompute(items, tmp_path, k=K, executor=client.get_executor(), progress=False)
    killer.join(30)
    assert entries_at_kill and entries_at_kill[0] < len(items)  # the kill landed mid-run
    assert victim not in client.run(os.getpid).values()
    assert report.failed == 0, report.failures
    assert report.computed + report.reused == len(items)
    assert len(list(tmp_path.glob("eigs-*.npz"))) == len(items)
