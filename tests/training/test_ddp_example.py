"""examples/train_ddp.py: its size-balanced sampler, and one epoch under torchrun with 2 ranks."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import pytest
import torch
import torch.distributed as dist
from conftest import ROOT

SCRIPT = ROOT / "examples" / "train_ddp.py"


def load_example():
    spec = importlib.util.spec_from_file_location("train_ddp", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_ranks_get_equal_counts_and_near_equal_sizes():
    sampler_type = load_example().SizeBalancedSampler
    g = torch.Generator().manual_seed(1)
    sizes = (torch.rand(101, generator=g) ** 3 * 10_000 + 10).long().tolist()  # skewed sizes
    for epoch in range(3):
        shares = []
        for rank in range(3):
            sampler = sampler_type(sizes, num_replicas=3, rank=rank, seed=5)
            sampler.set_epoch(epoch)
            shares.append(list(sampler))
        assert [len(s) for s in shares] == [34, 34, 34]  # DDP steps in lockstep
        assert set().union(*shares) == set(range(len(sizes)))  # every item, padding repeats
        loads = [sum(sizes[i] for i in share) for share in shares]
        # greedy largest-first: the spread is at most the largest item
        assert max(loads) - min(loads) <= max(sizes)
        # what dealing by count alone (DistributedSampler) gives is far worse on skewed sizes
        by_count = [sum(sizes[i] for i in range(r, len(sizes), 3)) for r in range(3)]
        assert max(loads) - min(loads) < max(by_count) - min(by_count)


@pytest.mark.slow  # torchrun starts two ranks that import torch: 10-40 s
@pytest.mark.skipif(
    not (dist.is_available() and dist.is_gloo_available()),
    reason="torch.distributed with the gloo backend is not available in this torch build",
)
def test_one_epoch_under_torchrun_with_two_ranks(tmp_path):
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    command += ["--nproc_per_node=2", str(SCRIPT), "--data", str(tmp_path / "data")]
    command += ["--make-data", "--epochs", "1", "--out", str(tmp_path / "out")]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    (line,) = [x for x in result.stdout.splitlines() if x.startswith("epoch 0:")]  # rank 0 only
    loads = [int(x.replace(",", "")) for x in line.split("vertices per rank ")[1].split(", ")]
    assert len(loads) == 2 and max(loads) <= 1.2 * min(loads)
    state = torch.load(tmp_path / "out" / "checkpoint.pt")
    assert state["epoch"] == 0 and state["model"]
    assert len(list((tmp_path / "data" / ".polylap-cache").glob("eigs-*.npz"))) == 18
