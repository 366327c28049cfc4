"""Benchmark users' own torch algebra on L and M0 against the same computation by hand.

For each expression a user writes with the operators (``L @ X``, ``M0 + t * L``, ``L.T``, a
solve with ``M0 + t L``, ...), one training step is timed -- assembly of ``L, M0`` from vertices
that require grad, the expression, ``loss = out.square().sum()``, backward to the vertices --
on regular quad grids (default 100k and 1M quads, gently bumped so the faces are non-planar):

* **ours**: the expression as written, on the operators ``laplacian`` returns;
* **by hand**: the same computation without operator algebra, on the unmodified ``L`` and ``M0``
  (``tp.sparse.spmm(L, X)`` products combined afterwards; for the solve, the system's values
  scattered onto ``L``'s pattern by hand), which is how it had to be written before the sparse seam;
* **torch native**: ``torch.sparse_csr_tensor(...) @ X`` with the differentiable values, whose
  backward asks for a dense ``V x V`` gradient; attempted once per grid and reported.

Times are medians of ``--repeat`` steps, ours and by-hand interleaved (A B A B), one thread by
default.  Peak memory is the rise of the resident set during one step (``VmHWM`` after
``/proc/self/clear_refs``, see ``common.py``).

Run from the repository root::

    python benchmarks/bench_operator_algebra.py                       # 100k and 1M quads
    python benchmarks/bench_operator_algebra.py --grids 100 --repeat 2  # a quick look

Markdown to stdout; writes ``benchmarks/results/operator_algebra.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import common
import torch

import torch_polylap as tp
from torch_polylap.sparse import operator_from_parts, sparse_values

Expr = Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]


def implicit_by_hand(L: torch.Tensor, M0: torch.Tensor, t: float) -> torch.Tensor:
    """``M0 + t L`` with the masses scattered onto ``L``'s diagonal by hand."""
    values = sparse_values(L)
    crow, col = L.crow_indices(), L.col_indices()
    row = torch.repeat_interleave(torch.arange(L.shape[0]), crow.diff())
    mass = torch.zeros_like(values).masked_scatter(row == col, M0.diagonal())
    return operator_from_parts(crow, col, mass + t * values, tuple(L.shape), symmetric=True)


# (name, ours, the same computation by hand on the unmodified L and M0)
EXPRESSIONS: list[tuple[str, Expr, Expr]] = [
    ("L @ X", lambda L, M0, X: L @ X, lambda L, M0, X: tp.sparse.spmm(L, X)),
    ("torch.mm(L, X)", lambda L, M0, X: torch.mm(L, X), lambda L, M0, X: tp.sparse.spmm(L, X)),
    (
        "torch.sparse.mm(L, X)",
        lambda L, M0, X: torch.sparse.mm(L, X),
        lambda L, M0, X: tp.sparse.spmm(L, X),
    ),
    ("(2 * L) @ X", lambda L, M0, X: (2 * L) @ X, lambda L, M0, X: 2 * tp.sparse.spmm(L, X)),
    (
        "(L + M0) @ X",
        lambda L, M0, X: (L + M0) @ X,
        lambda L, M0, X: tp.sparse.spmm(L, X) + tp.sparse.spmm(M0, X),
    ),
    (
        "(0.5 * L + M0) @ X",
        lambda L, M0, X: (0.5 * L + M0) @ X,
        lambda L, M0, X: 0.5 * tp.sparse.spmm(L, X) + tp.sparse.spmm(M0, X),
    ),
    (
        "(L - 0.25 * M0) @ X",
        lambda L, M0, X: (L - 0.25 * M0) @ X,
        lambda L, M0, X: tp.sparse.spmm(L, X) - 0.25 * tp.sparse.spmm(M0, X),
    ),
    (
        "L.to_sparse_coo().coalesce() @ X",
        lambda L, M0, X: L.to_sparse_coo().coalesce() @ X,
        lambda L, M0, X: tp.sparse.spmm(L, X),
    ),
    ("L.T @ X", lambda L, M0, X: L.T @ X, lambda L, M0, X: tp.sparse.spmm(L, X)),
    (
        "X * (L @ X) (Dirichlet)",
        lambda L, M0, X: X * (L @ X),
        lambda L, M0, X: X * tp.sparse.spmm(L, X),
    ),
    (
        "solve(M0 + 0.1 * L, X)",
        lambda L, M0, X: tp.solve(M0 + 0.1 * L, X),
        lambda L, M0, X: tp.solve(implicit_by_hand(L, M0, 0.1), X),
    ),
]


def make_step(verts: torch.Tensor, topo, expr: Expr) -> Callable[[], None]:
    def step() -> None:
        X = verts.clone().requires_grad_(True)
        L, M0 = tp.laplacian(X, topo)
        expr(L, M0, X).square().sum().backward()

    return step


def timed(step: Callable[[], None]) -> float:
    start = time.perf_counter()
    step()
    return time.perf_counter() - start


def native_attempt(verts: torch.Tensor, topo) -> str:
    """torch's own sparse autograd on the same L: its backward builds a dense V x V gradient."""
    X = verts.clone().requires_grad_(True)
    L, _ = tp.laplacian(X, topo)
    dense_gb = L.shape[0] ** 2 * 8 / 1e9
    native = torch.sparse_csr_tensor(
        L.crow_indices(), L.col_indices(), sparse_values(L), tuple(L.shape)
    )
    try:
        seconds = timed(lambda: (native @ X).square().sum().backward())
    except (RuntimeError, MemoryError) as err:
        first = str(err).splitlines()[0][:60]
        return f"fails: dense V x V gradient of {dense_gb:.0f} GB ({first}...)"
    return f"ran in {seconds * 1e3:.0f} ms with a {dense_gb:.1f} GB dense gradient"


def run_grid(n: int, repeat: int) -> dict:
    verts, faces = common.bench_grid(n)
    topo = tp.build_topology(faces, verts.shape[0])
    rows = []
    for name, ours, by_hand in EXPRESSIONS:
        steps = {"ours": make_step(verts, topo, ours), "by hand": make_step(verts, topo, by_hand)}
        for step in steps.values():  # warm-up: caches (union pattern, transposes), allocator
            step()
        times: dict[str, list[float]] = {key: [] for key in steps}
        for _ in range(repeat):
            for key, step in steps.items():
                times[key].append(timed(step))
        memory = {
            key: common.peak_rss_growth(step)["rss_delta_bytes"] for key, step in steps.items()
        }
        row = {
            "expression": name,
            "ours_ms": statistics.median(times["ours"]) * 1e3,
            "by_hand_ms": statistics.median(times["by hand"]) * 1e3,
            "ours_peak_mb": memory["ours"] / 1e6,
            "by_hand_peak_mb": memory["by hand"] / 1e6,
        }
        row["time_ratio"] = row["ours_ms"] / row["by_hand_ms"]
        row["memory_ratio"] = row["ours_peak_mb"] / max(row["by_hand_peak_mb"], 1e-9)
        print(f"  {n * n} quads  {name:34s} {row['time_ratio']:.2f}x", file=sys.stderr)
        rows.append(row)
    return {
        "n": n,
        "quads": n * n,
        "vertices": verts.shape[0],
        "nnz": topo.nnz,
        "native": native_attempt(verts, topo),
        "rows": rows,
    }


def tables(results: list[dict]) -> dict:
    """One table per grid (``n<grid n>``), and ``native``: what torch's own autograd did."""
    header = ["expression", "ours ms", "by hand ms", "time ratio", "ours peak MB"]
    header += ["by hand peak MB", "memory ratio"]
    out = {}
    for grid in results:
        body = [
            [
                f"`{r['expression']}`",
                f"{r['ours_ms']:.1f}",
                f"{r['by_hand_ms']:.1f}",
                f"{r['time_ratio']:.2f}",
                f"{r['ours_peak_mb']:.0f}",
                f"{r['by_hand_peak_mb']:.0f}",
                f"{r['memory_ratio']:.2f}",
            ]
            for r in grid["rows"]
        ]
        out[f"n{grid['n']}"] = common.table_data(header, body)
    native = [
        [f"{g['quads']:,}", f"{g['vertices']:,}", f"{g['nnz']:,}", g["native"]] for g in results
    ]
    out["native"] = common.table_data(
        ["quads", "vertices", "nnz(L)", "torch native backward"], native
    )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--grids", type=int, nargs="+", default=[316, 1000], help="grid sizes n (n x n quads)"
    )
    parser.add_argument("--repeat", type=int, default=3, help="timed steps per method")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument(
        "--json", type=Path, help="default benchmarks/results/operator_algebra.json"
    )
    args = parser.parse_args()
    meta = common.run_meta(threads=args.threads)
    with common.pinned_threads(args.threads):
        results = [run_grid(n, args.repeat) for n in args.grids]
    rendered = tables(results)
    print(f"{args.threads} thread(s), torch {torch.__version__}, float64, median of {args.repeat}")
    for key, t in rendered.items():
        print(f"\n### {key}\n\n{common.markdown_table(t['columns'], t['rows'])}")
    sections = {"repeat": args.repeat, "grids": results, "tables": rendered}
    common.write_results("operator_algebra", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
