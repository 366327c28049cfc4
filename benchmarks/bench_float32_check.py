"""What the float32 precision check costs: validated float32 re-assembly, this tree against another.

The check (the largest ``s^2 / |f|`` of the faces, read in the validation's one sync, see
``docs/math/properties.md``, "Finite precision") lives inside the assembly, so it cannot be
switched off in one process: the peer is a checkout of the code without it (``--baseline``,
e.g. ``git worktree add /tmp/base <commit>``). Each round runs one worker process per tree, in
turn (A B A B ...; the order flips every round), so that load from other jobs hits both alike;
each worker times ``tp.laplacian(V, topo)`` (float32, ``validate=True``, cached topology) as the
median of ``--repeat`` calls after a warm-up (a third of them at 1000 x 1000). The ratio is
taken round by round and its median reported. Whole
processes in turn still see the load change between them, so this tree's worker also times
the check's own work against a validated assembly, alternating within its process (``share``).

Run from the repository root::

    python benchmarks/bench_float32_check.py --baseline /tmp/base --rounds 7

The numbers go to ``benchmarks/results/float32_check.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

import torch_polylap as tp

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SIZES = (100, 316, 1000)


def worker(sizes: list[int], repeat: int) -> dict[str, float]:
    """Median seconds per case, in this process (whatever torch_polylap is on the path)."""
    from common import bench_grid

    torch.set_num_threads(1)
    out: dict[str, float] = {}
    for n in sizes:
        V, F = bench_grid(n, dtype=torch.float32)
        topo = tp.build_topology(F, V.shape[0])
        tp.laplacian(V, topo)  # warm-up
        times = []
        for _ in range(max(3, repeat if n < 1000 else repeat // 3)):
            start = time.perf_counter()
            tp.laplacian(V, topo)
            times.append(time.perf_counter() - start)
        out[f"assemble {n}x{n}"] = statistics.median(times)
        if hasattr(tp.kernels.BlockKernel, "stretch"):
            out[f"share {n}x{n}"] = check_share(V, topo, repeat)
    return out


def check_share(V: torch.Tensor, topo: tp.Topology, repeat: int) -> float:
    """The check's own work (``s^2 / |f|`` of every chunk's faces, each chunk's maximum and
    the maximum of those, read) over a validated assembly, timed in turn in this process."""
    kernel = tp.kernels.block_kernel("aw11", 1.0)
    view = topo.on(V.device)
    verts_t = V.t().contiguous()
    entries = [
        (grp, kernel(verts_t, grp, chunk.corners_t)) for grp in view.groups for chunk in grp.chunks
    ]

    def check() -> float:
        return float(
            torch.stack([kernel.stretch(e.area, e.size2, g).amax() for g, e in entries]).amax()
        )

    shares = []
    for _ in range(repeat):
        start = time.perf_counter()
        check()
        middle = time.perf_counter()
        tp.laplacian(V, topo)
        shares.append((middle - start) / (time.perf_counter() - middle))
    return statistics.median(shares)


def run_tree(tree: Path, args: argparse.Namespace) -> dict[str, float]:
    """One worker process with ``tree`` first on the path."""
    env = dict(os.environ, PYTHONPATH=f"{tree}{os.pathsep}{HERE}", OMP_NUM_THREADS="1")
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", "--repeat"]
    command += [str(args.repeat), "--sizes", *map(str, args.sizes)]
    done = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    package = Path(result.pop("package"))
    if not package.is_relative_to(tree):  # the tree's own package, not another on the path
        raise RuntimeError(f"the worker for {tree} imported {package}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, help="a checkout of the code without the check")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--repeat", type=int, default=9)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps({**worker(args.sizes, args.repeat), "package": tp.__file__}))
        return
    if args.baseline is None:
        parser.error("--baseline is required")
    sys.path.insert(0, str(HERE))
    from common import markdown_table, run_meta, table_data, write_results

    meta = run_meta()
    trees = {"ours": ROOT, "baseline": args.baseline.resolve()}
    rounds: list[dict[str, dict[str, float]]] = []
    for r in range(args.rounds):
        order = list(trees) if r % 2 == 0 else list(reversed(trees))
        rounds.append({who: run_tree(trees[who], args) for who in order})
        print(f"round {r + 1}/{args.rounds}: {rounds[-1]}", file=sys.stderr)
    rows = []
    for case in [c for c in rounds[0]["ours"] if not c.startswith("share")]:
        ratios = [rd["ours"][case] / rd["baseline"][case] for rd in rounds]
        rows.append(
            [
                case,
                f"{statistics.median(rd['ours'][case] for rd in rounds) * 1e3:.2f}",
                f"{statistics.median(rd['baseline'][case] for rd in rounds) * 1e3:.2f}",
                f"{statistics.median(ratios):.3f}",
                f"{min(ratios):.3f} .. {max(ratios):.3f}",
            ]
        )
    columns = ["case (float32)", "ours ms", "baseline ms", "ratio (median)", "ratio range"]
    print(markdown_table(columns, rows))
    shares = [
        [case, f"{100 * statistics.median(rd['ours'][case] for rd in rounds):.2f} %"]
        for case in rounds[0]["ours"]
        if case.startswith("share")
    ]
    share_columns = ["grid", "the check's own work / validated assembly (median)"]
    print(markdown_table(share_columns, shares))
    sections = {
        "baseline": str(args.baseline),
        "rounds": rounds,
        "tables": {
            "float32_check": table_data(columns, rows),
            "float32_check_share": table_data(share_columns, shares),
        },
    }
    write_results("float32_check", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
