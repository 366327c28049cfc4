"""DistributedDataParallel training of DiffusionNetLike: two CPU processes, gloo backend."""

from __future__ import annotations

import datetime
import os
import socket
import time

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from conftest import hex_pent_mesh, mixed_mesh

import torch_polylap.nn as tnn
from torch_polylap.batch import PolygonMeshes
from torch_polylap.shapes import quad_grid

WORLD = 2
STEPS = 3
LR = 0.2
DEADLINE_S = 90.0  # a hung rendezvous or collective fails the test instead of blocking it

pytestmark = [
    pytest.mark.slow,  # two spawned processes: 6-12 s, most of it their start-up
    pytest.mark.skipif(
        not (dist.is_available() and dist.is_gloo_available()),
        reason="torch.distributed with the gloo backend is not available in this torch build",
    ),
]


def shard(rank: int):
    """Rank ``rank``'s disjoint part of a tiny labelled dataset, as a batch and a Spectrum."""
    meshes = [quad_grid(3, bump=0.3), mixed_mesh(), hex_pent_mesh(), quad_grid(4, bump=0.1, seed=2)]
    labels = [0, 1, 2, 1]
    mine = list(range(rank, len(meshes), WORLD))
    batch = PolygonMeshes([meshes[i][0] for i in mine], [meshes[i][1] for i in mine])
    spectrum = tnn.Spectrum.from_polygon_meshes(batch, 5)
    return spectrum, torch.tensor([labels[i] for i in mine])


def make_model() -> torch.nn.Module:
    torch.manual_seed(0)
    return tnn.DiffusionNetLike(0, 3, width=8, num_blocks=2, hks_features=4).double()


def loss_of(model, spectrum, labels):
    return torch.nn.functional.cross_entropy(model(spectrum=spectrum), labels)


def _worker(rank: int, port: int, out_dir: str) -> None:
    torch.set_num_threads(1)
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    dist.init_process_group(
        "gloo", rank=rank, world_size=WORLD, timeout=datetime.timedelta(seconds=30)
    )
    try:
        model = make_model()
        if rank == 1:  # DDP must broadcast rank 0's initial parameters
            with torch.no_grad():
                for p in model.parameters():
                    p.add_(1.0)
        ddp = torch.nn.parallel.DistributedDataParallel(model)
        optimizer = torch.optim.SGD(ddp.parameters(), lr=LR)
        spectrum, labels = shard(rank)
        for _ in range(STEPS):
            optimizer.zero_grad()
            loss_of(ddp, spectrum, labels).backward()  # gradients all-reduced (averaged)
            optimizer.step()
        torch.save(
            [p.detach() for p in model.parameters()], os.path.join(out_dir, f"rank{rank}.pt")
        )
    finally:
        dist.destroy_process_group()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ddp_keeps_replicas_identical_and_averages_gradients(tmp_path, monkeypatch):
    # spawned workers read these at import: one BLAS thread each (two ranks share two cores,
    # and threaded BLAS on tiny eigenproblems only spins)
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")
    context = mp.start_processes(
        _worker, args=(free_port(), str(tmp_path)), nprocs=WORLD, join=False, start_method="spawn"
    )
    deadline = time.monotonic() + DEADLINE_S
    try:
        while not context.join(timeout=1.0):
            if time.monotonic() > deadline:
                pytest.fail(f"the DDP workers did not finish within {DEADLINE_S} s")
    finally:
        for process in context.processes:
            if process.is_alive():
                process.terminate()
    params = [torch.load(tmp_path / f"rank{r}.pt") for r in range(WORLD)]
    for a, b in zip(*params, strict=True):
        assert torch.equal(a, b)  # replicas identical after every step
    # reference: one process, SGD on the average of the two shards' gradients (what DDP's
    # all-reduce computes), from the same initial parameters
    model = make_model()
    initial = [p.detach().clone() for p in model.parameters()]
    shards = [shard(r) for r in range(WORLD)]
    for _ in range(STEPS):
        grads = [torch.autograd.grad(loss_of(model, *s), list(model.parameters())) for s in shards]
        with torch.no_grad():
            for p, *g in zip(model.parameters(), *grads, strict=True):
                p.sub_(LR * sum(g) / WORLD)
    for trained, ref in zip(params[0], model.parameters(), strict=True):
        assert torch.allclose(trained, ref, atol=1e-10, rtol=1e-8)
    assert any(not torch.allclose(t, i) for t, i in zip(params[0], initial, strict=True))
