"""How each operation's time grows with the mesh: 10k, 100k and 1M faces, with fitted exponents.

    python benchmarks/bench_scaling.py [--sizes 100 316 1000] [--repeat 3] [--json PATH]

Writes ``benchmarks/results/scaling.json`` (or ``--json PATH``).

On ``n x n`` non-planar quad grids (``F = n^2`` quads, ``common.bench_grid``), one
torch thread, float64, CPU, every operation timed as the median of ``--repeat`` samples after a
warm-up call (one sample at 500k faces and above for the factorizations and the I/O):

* ``topology``: ``tp.build_topology`` (sorting corner pairs, manifold analysis, CSR pattern);
* ``first assembly``: ``tp.laplacian`` on a fresh topology (topology included);
* ``re-assembly``: ``tp.laplacian`` on the cached topology;
* ``forward+backward``: re-assembly, ``(L X)^2`` summed, and its gradient to the vertices;
* ``solve``: ``tp.solve(M0 + 0.01 L, B)`` for ``B`` of shape ``(V, 3)``, factorization included;
* ``eigs``: ``tp.eigs(L, M0, k=16)``, the shift-invert factorization included;
* ``geodesics build+query`` and ``geodesics query``: ``tp.HeatGeodesicSolver`` from vertex 0;
* ``write OBJ`` and ``read OBJ``: ``tp.write_mesh`` / ``tp.read_mesh`` of the grid, 17-digit
  coordinates.

The exponent of each row is the least-squares slope of ``log(time)`` against ``log(F)``. Each row
also names the exponent its algorithm needs: 1 for everything that visits each face a bounded
number of times; about 1.5 for a sparse Cholesky factorization of a planar grid's matrix under a
nested-dissection-like ordering (George 1973), which the solve, the shift-invert eigensolver and
the geodesic solver's build contain. A row is flagged when its fitted exponent exceeds the
algorithm's by more than 0.15.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from common import (
    bench_grid,
    markdown_table,
    pinned_threads,
    run_meta,
    script_parser,
    table_data,
    timed,
    write_results,
)

import torch_polylap as tp

# (label, exponent the algorithm needs)
ROWS: dict[str, tuple[str, float]] = {
    "topology": ("topology", 1.0),
    "first": ("first assembly", 1.0),
    "reassembly": ("re-assembly", 1.0),
    "fwd_bwd": ("forward+backward", 1.0),
    "solve": ("solve (factor + 3 RHS)", 1.5),
    "eigs": ("eigs k=16 (shift-invert)", 1.5),
    "geo_total": ("geodesics build+query", 1.5),
    "geo_query": ("geodesics query", 1.0),
    "write_obj": ("write OBJ", 1.0),
    "read_obj": ("read OBJ", 1.0),
}
# a fitted exponent this far above the algorithm's is flagged as superlinear beyond need
TOLERANCE = 0.15


def forward_backward(verts: torch.Tensor, topo: tp.Topology) -> None:
    """Re-assembly, ``sum((L X)^2)`` and its gradient to the vertices."""
    X = verts.detach().requires_grad_(True)
    L, _ = tp.laplacian(X, topo)
    (L @ X).square().sum().backward()


def solve_fresh(verts: torch.Tensor, topo: tp.Topology, B: torch.Tensor) -> torch.Tensor:
    """``(M0 + 0.01 L)^{-1} B`` on freshly assembled operators, so no factorization is reused."""
    L, M0 = tp.laplacian(verts, topo)
    return tp.solve(M0 + 0.01 * L, B)


def eigs_fresh(verts: torch.Tensor, topo: tp.Topology) -> torch.Tensor:
    """The 16 smallest eigenvalues of ``L phi = lambda M0 phi`` on fresh operators."""
    L, M0 = tp.laplacian(verts, topo)
    return tp.eigs(L, M0, 16)[0]


def measure(n: int, repeat: int, workdir: Path) -> dict:
    """Median seconds of every row on the ``n x n`` grid."""
    verts, faces = bench_grid(n)
    topo = tp.build_topology(faces, verts.shape[0])
    B = torch.randn(
        verts.shape[0], 3, dtype=verts.dtype, generator=torch.Generator().manual_seed(0)
    )
    solver = tp.HeatGeodesicSolver(verts, topo)
    # its first query factors, its second makes the copies of QDLDL's factors (timed()'s
    # discarded warm-up call): "geodesics query" is the cost of every later one
    solver.distance(0)
    path = workdir / f"grid_{n}.obj"
    tp.write_mesh(path, verts, faces)
    big = n * n >= 500_000
    # the factorizations take tens of seconds at 1M faces: fewer samples there
    slow_repeat = 1 if big else repeat
    steps: dict[str, tuple[Callable[[], object], int]] = {
        "topology": (lambda: tp.build_topology(faces, verts.shape[0]), repeat),
        "first": (lambda: tp.laplacian(verts, tp.build_topology(faces, verts.shape[0])), repeat),
        "reassembly": (lambda: tp.laplacian(verts, topo), repeat),
        "fwd_bwd": (lambda: forward_backward(verts, topo), repeat),
        "solve": (lambda: solve_fresh(verts, topo, B), slow_repeat),
        "eigs": (lambda: eigs_fresh(verts, topo), slow_repeat),
        "geo_total": (lambda: tp.HeatGeodesicSolver(verts, topo).distance(0), slow_repeat),
        "geo_query": (lambda: solver.distance(0), repeat),
        "write_obj": (lambda: tp.write_mesh(path, verts, faces), slow_repeat),
        "read_obj": (lambda: tp.read_mesh(path), slow_repeat),
    }
    seconds = {}
    for key, (fn, reps) in steps.items():
        print(f"  {n}x{n} {ROWS[key][0]} ...", file=sys.stderr, flush=True)
        # one discarded warm-up call; sub-millisecond work timed over several calls per sample
        seconds[key] = timed(fn, reps, warmup=True, min_sample_s=0 if big else 0.05)[0]
    path.unlink()
    return {
        "n": n,
        "faces": n * n,
        "verts": int(verts.shape[0]),
        "nnz": topo.nnz,
        "seconds": seconds,
    }


def exponent(faces: list[int], seconds: list[float]) -> float:
    """Least-squares slope of ``log(seconds)`` against ``log(faces)``."""
    return float(np.polyfit(np.log(faces), np.log(seconds), 1)[0])


def table(grids: list[dict]) -> tuple[list[str], list[list[str]]]:
    """One row per operation: milliseconds at each size, the fitted and the needed exponent."""
    faces = [g["faces"] for g in grids]
    header = ["operation", *[f"{f:,} faces (ms)" for f in faces], "exponent", "needs", ""]
    body = []
    for key, (label, needed) in ROWS.items():
        times = [g["seconds"][key] for g in grids]
        fitted = exponent(faces, times)
        flag = "superlinear beyond need" if fitted > needed + TOLERANCE else ""
        body.append(
            [label, *[f"{1e3 * t:,.1f}" for t in times], f"{fitted:.2f}", f"{needed:g}", flag]
        )
    return header, body


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = script_parser(__doc__, "scaling", repeat=3)
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[100, 316, 1000],
        help="grid sides n (n x n quads); at least two (default 100 316 1000)",
    )
    args = parser.parse_args(argv)
    if len(args.sizes) < 2:
        parser.error("an exponent needs at least two --sizes")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    meta = run_meta(threads=1)
    with pinned_threads(1), warnings.catch_warnings(), tempfile.TemporaryDirectory() as tmp:
        warnings.simplefilter("ignore")
        grids = [measure(n, args.repeat, Path(tmp)) for n in sorted(args.sizes)]
    header, body = table(grids)
    print(markdown_table(header, body))
    tables = {"scaling": table_data(header, body)}
    write_results("scaling", {"grids": grids, "tables": tables}, meta=meta, path=args.json)
    return 0 if all(math.isfinite(t) for g in grids for t in g["seconds"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
