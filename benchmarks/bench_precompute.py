"""The dataset precompute: 2 local workers against 1, and what a mesh costs.

``python benchmarks/bench_precompute.py [--meshes 40] [--pairs 3] [--k 32]`` writes
``benchmarks/results/precompute.json`` with three tables:

* ``workers``: :func:`torch_polylap.datasets.precompute` of ``--meshes`` OBJ files of 3.6k-4.5k
  quad faces (bumpy grids of 60-67 faces a side), into a fresh cache each time, on a local
  pool of 1 and of 2 processes. The two sides alternate (1, 2, then 2, 1, ...), so a change of
  the machine's load during the run hits both; each pair gives one ratio ``t(1) / t(2)``, and
  the table shows every pair and their median. Pool start-up and file reads are included.
  ``CPU s: 2 / 1``: the workers' CPU seconds with 2 against 1 (about 1: the second worker adds
  no work, so on free cores the wall time halves; on a loaded machine it cannot).
* ``workers_own_sessions``: the same with every worker in a session of its own. Linux
  (``sched_autogroup``) shares the CPU between sessions first, so on a machine other users'
  sessions keep busy, the workers of one session share that session's slice however many
  they are; separate sessions stand for what separate jobs or machines would get.
* ``cost``: per-mesh seconds of one task (read, normalize, assemble, ``eigs``, write) against
  the mesh size, one worker, median of the meshes of each size; the entry's bytes on disk;
  the assembly of ``L`` and ``M0`` alone (what the dataset redoes per item, uncached; median
  of 5).
* ``throughput``: meshes per second of each pool in the ``workers`` runs.

The machine may be shared: the load average before and after is in the header; the tables
hold ratios of interleaved runs, not absolute speed claims.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import resource
import statistics
import tempfile
import time
from concurrent.futures import Executor, ProcessPoolExecutor
from pathlib import Path

import torch
from common import run_meta, table_data, write_results
from threadpoolctl import threadpool_limits

import torch_polylap as tp
from torch_polylap.datasets import normalize_mesh, precompute
from torch_polylap.datasets.jobs import InlineExecutor, local_executor
from torch_polylap.shapes import quad_grid


def write_grids(folder: Path, sides: list[int]) -> list[Path]:
    """One bumpy ``n x n`` quad grid per entry of ``sides``, as OBJ files in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, n in enumerate(sides):
        path = folder / f"grid{i:03}_{n}.obj"
        tp.write_mesh(path, *quad_grid(n, bump=0.2, seed=i))
        paths.append(path)
    return paths


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _own_session() -> None:
    """Worker initializer: a session of its own (so its own scheduling group), one thread in
    torch and in every BLAS/OpenMP pool, as the library's pool has."""
    os.setsid()
    torch.set_num_threads(1)
    threadpool_limits(1)


def pool_of(workers: int, own_sessions: bool) -> Executor:
    """The pool a run uses: :func:`local_executor`, or the same whose workers each start a
    session of their own."""
    if not own_sessions:
        return local_executor(workers)
    context = multiprocessing.get_context("fork")
    return ProcessPoolExecutor(workers, mp_context=context, initializer=_own_session)


def timed_run(
    files: list[Path], workers: int, k: int, root: Path, tag: str, own_sessions: bool
) -> tuple[float, float]:
    """Wall seconds of one precompute of ``files`` into a new cache on ``workers`` processes,
    and the CPU seconds its workers used (reaped when the pool shuts down)."""
    cache = root / f"cache-{tag}"
    start, cpu = time.perf_counter(), _children_cpu()
    with pool_of(workers, own_sessions) as pool:
        report = precompute(files, cache, k=k, executor=pool, progress=False)
    seconds, cpu = time.perf_counter() - start, _children_cpu() - cpu
    if report.computed != len(files):
        raise RuntimeError(f"expected {len(files)} computed, got {report.to_dict()}")
    return seconds, cpu


def workers_table(
    files: list[Path], k: int, pairs: int, root: Path, own_sessions: bool
) -> tuple[dict, dict, list]:
    """The interleaved 1-against-2 runs: the table, the throughputs and the raw seconds."""
    raw = []
    for p in range(pairs):
        order = (1, 2) if p % 2 == 0 else (2, 1)
        tag = f"{p}-{own_sessions}"
        runs = {w: timed_run(files, w, k, root, f"{tag}-{w}", own_sessions) for w in order}
        seconds = {w: wall for w, (wall, _) in runs.items()}
        cpu = {w: used for w, (_, used) in runs.items()}
        raw.append({"order": list(order), "seconds": seconds, "cpu_s": cpu})
        raw[-1]["load"] = os.getloadavg()[0]
        print(f"pair {p}: 1 worker {seconds[1]:.2f} s, 2 workers {seconds[2]:.2f} s, cpu {cpu}")
    ratios = [r["seconds"][1] / r["seconds"][2] for r in raw]
    cpu_ratios = [r["cpu_s"][2] / r["cpu_s"][1] for r in raw]
    rows = [
        [i, "-".join(map(str, r["order"])), f"{r['seconds'][1]:.2f}", f"{r['seconds'][2]:.2f}"]
        + [f"{ratio:.2f}", f"{cpu_ratio:.2f}", f"{r['load']:.1f}"]
        for i, (r, ratio, cpu_ratio) in enumerate(zip(raw, ratios, cpu_ratios, strict=True))
    ]
    medians = [f"{statistics.median(ratios):.2f}", f"{statistics.median(cpu_ratios):.2f}"]
    rows.append(["median", "", "", "", *medians, ""])
    columns = ["pair", "order", "1 worker (s)", "2 workers (s)", "t(1) / t(2)"]
    columns += ["CPU s: 2 / 1", "load (1 min)"]
    n = len(files)
    throughput = {
        w: statistics.median(n / r["seconds"][w] for r in raw) for w in (1, 2)
    }  # meshes per second
    return table_data(columns, rows), throughput, raw


def _assembly_seconds(verts, faces) -> float:
    start = time.perf_counter()
    tp.laplacian(verts, faces)
    return time.perf_counter() - start


def cost_table(k: int, root: Path) -> tuple[dict, list]:
    """Per-mesh task seconds, entry bytes and assembly seconds against the mesh size."""
    rows, raw = [], []
    for n in (32, 64, 128, 256):
        files = write_grids(root / f"cost{n}", [n] * 3)
        cache = root / f"cost-cache-{n}"
        report = precompute(files, cache, k=k, executor=InlineExecutor(), progress=False)
        task_s = statistics.median(report.mesh_seconds.values())
        entry_bytes = statistics.median(p.stat().st_size for p in cache.glob("eigs-*.npz"))
        verts, faces = tp.read_mesh(files[0])
        v = normalize_mesh(verts, faces)
        assembly_s = statistics.median(_assembly_seconds(v, faces) for _ in range(5))
        rows.append(
            [f"{faces.num_faces:,}", f"{verts.shape[0]:,}", f"{task_s:.3f}", f"{entry_bytes:,.0f}"]
            + [f"{assembly_s * 1e3:.1f}"]
        )
        raw.append({"faces": faces.num_faces, "verts": verts.shape[0], "task_s": task_s})
        raw[-1].update({"entry_bytes": entry_bytes, "assembly_s": assembly_s})
        print(rows[-1])
    columns = ["faces", "vertices", "task (s)", "entry (bytes)", "assembly of L, M0 (ms)"]
    return table_data(columns, rows), raw


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", type=int, default=40)
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--k", type=int, default=32)
    args = parser.parse_args()
    meta = run_meta(threads=1)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        sides = [60 + (i % 8) for i in range(args.meshes)]  # 3,600 to 4,489 faces
        files = write_grids(root / "meshes", sides)
        workers, throughput, raw = workers_table(files, args.k, args.pairs, root, False)
        sessions, throughput_s, raw_s = workers_table(files, args.k, args.pairs, root, True)
        cost, cost_raw = cost_table(args.k, root)
    rows = [[w, f"{throughput[w]:.2f}", f"{throughput_s[w]:.2f}"] for w in (1, 2)]
    write_results(
        "precompute",
        {
            "tables": {
                "workers": workers,
                "workers_own_sessions": sessions,
                "cost": cost,
                "throughput": table_data(
                    ["workers", "meshes / s", "meshes / s (own sessions)"], rows
                ),
            },
            "workers_raw": raw,
            "workers_own_sessions_raw": raw_s,
            "cost_raw": cost_raw,
            "faces": [s * s for s in sides],
            "k": args.k,
        },
        meta={**meta, "note": "sides interleaved (1-2, 2-1, ...); load average per pair"},
    )


if __name__ == "__main__":
    main()
