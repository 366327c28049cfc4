"""Train a mesh classifier on several processes with ``torchrun`` (DistributedDataParallel).

    torchrun --standalone --nproc_per_node=2 examples/train_ddp.py --data DIR [--epochs 5]
        [--k 16] [--batch 4] [--cache DIR] [--out DIR] [--make-data]

``DIR`` holds one subfolder per class, each with mesh files (OBJ, OFF, PLY); ``--make-data``
first writes a small synthetic set there (bumpy grids, tori and cubes of several resolutions).
The eigenpairs come from the shared cache (``--cache``, default ``DIR/.polylap-cache``): each
rank fills its share with :func:`torch_polylap.datasets.precompute` (entries are atomic and
content-addressed, so ranks on several machines may share the folder, and a cache filled
beforehand with ``polylap precompute DIR --cache ...`` is simply read). The sampler gives every
rank about the same number of *vertices* per epoch, not the same number of meshes, so no rank
waits for a rank that drew the large meshes. Rank 0 writes a checkpoint after every epoch
(atomically); a run started again resumes after the last epoch saved.

Backend: gloo on the CPU, nccl with CUDA. Without ``torchrun`` it runs as a single process.
Writes ``--out`` (default ``examples/output/ddp``): ``checkpoint.pt``.
"""

from __future__ import annotations

import argparse
import io
import os
from collections.abc import Iterator
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DistributedSampler

import torch_polylap as tp
from torch_polylap.atomic import atomic_write
from torch_polylap.datasets import PolygonMeshDataset, collate_meshes, precompute
from torch_polylap.datasets.jobs import InlineExecutor
from torch_polylap.nn import DiffusionNetLike
from torch_polylap.shapes import quad_cube, quad_grid, torus

OUTPUT = Path(__file__).resolve().parent / "output" / "ddp"
SUFFIXES = (".obj", ".off", ".ply")


class SizeBalancedSampler(DistributedSampler):
    """A :class:`DistributedSampler` whose ranks get about equal total mesh size, not count.

    Each epoch (:meth:`set_epoch`) the items are shuffled, sorted by size (largest first, ties
    in shuffled order) and dealt greedily to the rank with the least total size so far among
    those still short of ``num_samples`` items; every rank gets the same number of items (DDP
    steps in lockstep), padding with repeats when the count does not divide. Each rank then
    visits its items in a shuffled order.

    Args:
        sizes: ``(N,)`` a cost per item (vertex counts).
        num_replicas, rank, seed: as :class:`DistributedSampler` (default: the process group's).
    """

    def __init__(
        self,
        sizes: list[int],
        num_replicas: int | None = None,
        rank: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(range(len(sizes)), num_replicas, rank, shuffle=True, seed=seed)
        self.sizes = sizes

    def shares(self) -> list[list[int]]:
        """The items of every rank this epoch."""
        g = torch.Generator().manual_seed(self.seed + self.epoch)
        order = torch.randperm(len(self.sizes), generator=g).tolist()
        order += order[: self.total_size - len(order)]  # pad: every rank the same count
        order.sort(key=lambda i: -self.sizes[i])  # stable: ties keep the shuffled order
        shares: list[list[int]] = [[] for _ in range(self.num_replicas)]
        loads = [0] * self.num_replicas
        for i in order:
            rank = min(
                (r for r in range(self.num_replicas) if len(shares[r]) < self.num_samples),
                key=lambda r: loads[r],
            )
            shares[rank].append(i)
            loads[rank] += self.sizes[i]
        return shares

    def __iter__(self) -> Iterator[int]:
        mine = self.shares()[self.rank]
        g = torch.Generator().manual_seed(self.seed + self.epoch + 1 + self.rank)
        return iter([mine[j] for j in torch.randperm(len(mine), generator=g).tolist()])


def make_data(root: Path) -> None:
    """A small labelled set: bumpy grids, tori and cubes at several resolutions."""
    shapes = {
        "grid": lambda n, s: quad_grid(n, bump=0.3, seed=s),
        "torus": lambda n, s: torus(2 * n, n, major=1.0, minor=0.3 + 0.02 * s),
        "cube": lambda n, s: quad_cube(n // 2 + 2),
    }
    for name, build in shapes.items():
        (root / name).mkdir(parents=True, exist_ok=True)
        for s, n in enumerate((6, 8, 10, 12, 14, 16)):
            tp.write_mesh(root / name / f"{name}{s}.obj", *build(n, s))


def labelled_files(root: Path) -> tuple[list[Path], list[int], list[str]]:
    """Mesh files under ``root``'s subfolders, their class indices and the class names."""
    classes = sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    files, labels = [], []
    for c, name in enumerate(classes):
        for path in sorted((root / name).rglob("*")):
            if path.suffix.lower() in SUFFIXES:
                files.append(path)
                labels.append(c)
    if not files:
        raise SystemExit(f"no mesh files in the class subfolders of {root} (try --make-data)")
    return files, labels, classes


def save_checkpoint(path: Path, epoch: int, model: torch.nn.Module, optimizer) -> None:
    """Rank 0's checkpoint, written whole or not at all."""
    buffer = io.BytesIO()
    state = {"epoch": epoch, "model": model.state_dict(), "optimizer": optimizer.state_dict()}
    torch.save(state, buffer)
    atomic_write(path, lambda f: f.write(buffer.getvalue()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="one subfolder per class")
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--k", type=int, default=16, help="eigenpairs per mesh")
    parser.add_argument("--batch", type=int, default=4, help="meshes per step and rank")
    parser.add_argument("--cache", type=Path, default=None, help="default: DATA/.polylap-cache")
    parser.add_argument("--out", type=Path, default=OUTPUT)
    parser.add_argument("--make-data", action="store_true", help="write a synthetic set first")
    args = parser.parse_args()
    torch.set_num_threads(1)  # one core per rank
    distributed = "WORLD_SIZE" in os.environ  # set by torchrun
    if distributed:
        dist.init_process_group("nccl" if torch.cuda.is_available() else "gloo")
    rank, world = (dist.get_rank(), dist.get_world_size()) if distributed else (0, 1)
    device = torch.device(
        f"cuda:{os.environ.get('LOCAL_RANK', 0)}" if torch.cuda.is_available() else "cpu"
    )
    cache = args.cache or args.data / ".polylap-cache"
    if args.make_data and rank == 0:
        make_data(args.data)
    if distributed:
        dist.barrier()  # the data exists before any rank lists it
    try:
        train(args, rank, world, distributed, device, cache)
    finally:
        if distributed:
            dist.destroy_process_group()


def train(
    args, rank: int, world: int, distributed: bool, device: torch.device, cache: Path
) -> None:
    files, labels, classes = labelled_files(args.data)
    # each rank caches its share (a cache filled beforehand is only read), then all wait
    report = precompute(
        files[rank::world], cache, k=args.k, executor=InlineExecutor(), progress=False
    )
    if report.failures:
        raise SystemExit(f"rank {rank}: {report.failed} meshes not cached: {report.failures}")
    if distributed:
        dist.barrier()
    data = PolygonMeshDataset(files, labels, k=args.k, cache_dir=cache)
    sizes = [data.mesh(i)[0].shape[0] for i in range(len(data))]
    sampler = SizeBalancedSampler(sizes, world, rank)

    torch.manual_seed(0)  # the same initial model everywhere (DDP also broadcasts rank 0's)
    model = DiffusionNetLike(0, len(classes), width=16, num_blocks=2, hks_features=8).to(device)
    ddp = DistributedDataParallel(model) if distributed else model
    optimizer = torch.optim.Adam(ddp.parameters(), lr=5e-3)
    checkpoint = args.out / "checkpoint.pt"
    start = 0
    if checkpoint.is_file():
        state = torch.load(checkpoint, map_location=device)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start = state["epoch"] + 1
    for epoch in range(start, args.epochs):
        sampler.set_epoch(epoch)
        mine = list(sampler)
        total = torch.zeros(2, dtype=torch.float64)
        for s in range(0, len(mine), args.batch):
            batch = collate_meshes([data[i] for i in mine[s : s + args.batch]]).to(device)
            loss = torch.nn.functional.cross_entropy(ddp(spectrum=batch.spectrum), batch.labels)
            optimizer.zero_grad()
            loss.backward()  # DDP averages the gradients over the ranks
            optimizer.step()
            total += torch.tensor([loss.item() * len(batch.labels), len(batch.labels)])
        load = torch.tensor([float(sum(sizes[i] for i in mine))], dtype=torch.float64)
        loads = [torch.zeros_like(load) for _ in range(world)]
        if distributed:
            dist.all_reduce(total)
            dist.all_gather(loads, load)
        else:
            loads = [load]
        if rank == 0:
            args.out.mkdir(parents=True, exist_ok=True)
            save_checkpoint(checkpoint, epoch, model, optimizer)
            per_rank = ", ".join(f"{int(x.item()):,}" for x in loads)
            print(f"epoch {epoch}: loss {total[0] / total[1]:.4f}; vertices per rank {per_rank}")


if __name__ == "__main__":
    main()
