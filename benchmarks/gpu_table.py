"""The GPU table: assembly, re-assembly, forward+backward, products, solves and eigenpairs on CUDA,
each beside the same step on this machine's CPU, as ratios.

Run by ``benchmarks/gpu_check.sh`` on a CUDA machine (about 2-4 minutes)::

    python3 benchmarks/gpu_table.py --json gpu_table.json

Markdown to stdout; writes ``benchmarks/results/gpu_table.json`` (or ``--json PATH``). Times
are medians of ``--repeat`` runs after one warm-up, with ``torch.cuda.synchronize()``
around every timed CUDA step.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import torch
from common import (
    bench_grid,
    markdown_table,
    median_time,
    run_meta,
    script_parser,
    synchronizer,
    table_data,
    write_results,
)

import torch_polylap as tp


def steps(verts: torch.Tensor, faces: torch.Tensor, k: int) -> dict[str, Callable[[], object]]:
    topo = tp.build_topology(faces, verts.shape[0])
    L, M0 = tp.laplacian(verts, topo)
    X = verts.clone()
    B = torch.randn_like(verts)

    def forward_backward() -> None:
        Xg = verts.clone().requires_grad_(True)
        Lg, M0g = tp.laplacian(Xg, topo)
        ((Lg @ Xg).square().sum() + tp.solve(M0g + 1e-2 * Lg, Xg, backend="cg").sum()).backward()

    table = {
        "first assembly (topology + L, M0)": lambda: tp.laplacian(verts, faces.clone()),
        "re-assembly (cached topology)": lambda: tp.laplacian(verts, topo),
        "fwd+bwd of sum (L X)^2 + CG solve": forward_backward,
        "L @ X, X (V, 3)": lambda: L @ X,
        "CG solve (M0 + 1e-2 L) X = B": lambda: tp.solve(M0 + 1e-2 * L, B, backend="cg"),
    }
    if verts.dtype == torch.float64:
        try:
            import cholespy  # noqa: F401

            table["Cholesky solve, factor + 3 columns"] = lambda: tp.solve(
                M0 + 1e-2 * L, B, backend="cholesky"
            )
        except ImportError:
            pass
        table[f"eigs k={k}"] = lambda: tp.eigs(L, M0, k)
    return table


def main() -> None:
    parser = script_parser(__doc__, "gpu_table", repeat=3)
    parser.add_argument("--grid", type=int, default=1000, help="n x n quads (default 1M)")
    parser.add_argument("--eigs-grid", type=int, default=300, help="grid for eigs (90k quads)")
    parser.add_argument("--k", type=int, default=16)
    parser.add_argument(
        "--device", default="cuda", help="the accelerator (cpu only to try the script itself)"
    )
    args = parser.parse_args()
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        sys.exit("gpu_table: no CUDA device")
    cuda, cpu = torch.device(args.device), torch.device("cpu")
    meta = run_meta()
    rows = []
    for dtype in (torch.float32, torch.float64):
        for n in sorted({args.grid, args.eigs_grid}):
            verts, faces = bench_grid(n, dtype=dtype)
            per_device = {dev: steps(verts.to(dev), faces, args.k) for dev in (cpu, cuda)}
            for name in per_device[cuda]:
                if name.startswith("eigs") != (n == args.eigs_grid):
                    continue
                t_gpu = median_time(per_device[cuda][name], args.repeat, sync=synchronizer(cuda))
                t_cpu = median_time(per_device[cpu][name], args.repeat)
                rows.append(
                    {
                        "step": name,
                        "dtype": str(dtype).replace("torch.", ""),
                        "quads": n * n,
                        "cuda_ms": t_gpu * 1e3,
                        "cpu_ms": t_cpu * 1e3,
                        "speedup": t_cpu / t_gpu,
                    }
                )
                print(f"{rows[-1]}", file=sys.stderr)
    name = torch.cuda.get_device_name() if cuda.type == "cuda" else str(cuda)
    print(
        f"GPU table: {name} vs {torch.get_num_threads()} CPU threads, "
        f"torch {torch.__version__}, median of {args.repeat}\n"
    )
    header = ["step", "dtype", "quads", "CUDA ms", "CPU ms", "CPU / CUDA"]
    body = [
        [
            r["step"],
            r["dtype"],
            f"{r['quads']:,}",
            f"{r['cuda_ms']:.2f}",
            f"{r['cpu_ms']:.2f}",
            f"{r['speedup']:.1f}",
        ]
        for r in rows
    ]
    print(markdown_table(header, body))
    meta["device"] = name
    sections = {"repeat": args.repeat, "rows": rows, "tables": {"gpu": table_data(header, body)}}
    write_results("gpu_table", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
