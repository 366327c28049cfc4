"""Benchmark differentiable solves and eigenpairs against plain scipy, in one run.

    python benchmarks/bench_solve.py [--sizes 100 316 1000] [--eig-sizes 100 316] [--k 64]

Measured on non-planar quad grids (n x n quads) with ``A = M0 + h L``:

* ``solve``: ``torch_polylap.solve(A, B)`` for ``B`` of shape ``(V, 3)``, factorization included,
  against ``scipy.sparse.linalg.splu(A) .solve(B)`` and ``spsolve``; the cached re-solve; and the
  backward pass (one transposed solve plus the sampled product for ``A``'s values) relative to
  the forward;
* ``eigs``: ``torch_polylap.eigs(L, M0, k)`` against ``scipy.sparse.linalg.eigsh`` with the same
  shift;
* the spectral-network precompute on ``sword-quad-dominant.obj`` (22k vertices): polygon
  ``L, M0`` and ``k = 128`` eigenpairs, against the triangle pipeline DiffusionNet uses
  (robust-laplacian's ``mesh_laplacian`` on the fan-triangulated mesh, then scipy shift-invert
  ``eigsh``), when ``robust_laplacian`` is installed.

Prints a Markdown report and writes ``benchmarks/results/solve.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from common import (
    bench_grid,
    markdown_table,
    median_time,
    run_meta,
    script_parser,
    table_data,
    write_results,
)

import torch_polylap as tp
from torch_polylap.sparse import operator_from_parts, sparse_values

SWORD = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "real"
SWORD = SWORD / "sword-quad-dominant.obj"


def timed(fn: Callable[[], object], repeat: int) -> float:
    """Median seconds over ``repeat`` calls after one warm-up call (``common.median_time``).
    Callers that time a factorization build a fresh matrix inside ``fn``, so no factorization
    is reused."""
    return median_time(fn, repeat)


def implicit_matrix(L: torch.Tensor, M0: torch.Tensor, h: float) -> torch.Tensor:
    crow, col = L.crow_indices(), L.col_indices()
    row = torch.repeat_interleave(torch.arange(L.shape[0]), crow.diff())
    mass = torch.zeros_like(sparse_values(L)).masked_scatter(row == col, sparse_values(M0))
    return operator_from_parts(
        crow, col, mass + h * sparse_values(L), tuple(L.shape), symmetric=True
    )


def bench_solve(n: int, repeat: int) -> dict:
    verts, faces = bench_grid(n)
    L, M0 = tp.laplacian(verts, faces)
    B = torch.randn(
        verts.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)
    )
    A_csc = sp.csc_matrix(tp.sparse.to_scipy(implicit_matrix(L, M0, 1e-2)))
    out = {"faces": faces.shape[0], "verts": verts.shape[0]}
    # a fresh A each call, so the factorization is part of every timing
    out["ours_factor_solve"] = timed(lambda: tp.solve(implicit_matrix(L, M0, 1e-2), B), repeat)
    A = implicit_matrix(L, M0, 1e-2)
    tp.solve(A, B)
    out["ours_resolve"] = timed(lambda: tp.solve(A, B), repeat)

    def splu_solve() -> np.ndarray:
        # the same SuperLU settings as torch_polylap.solve, called directly
        return tp.linalg.spd_splu(A_csc).solve(B.numpy())

    out["scipy_splu_solve"] = timed(splu_solve, repeat)
    out["scipy_splu_default"] = timed(lambda: spla.splu(A_csc).solve(B.numpy()), repeat)

    def forward_backward() -> None:
        values = sparse_values(A).detach().clone().requires_grad_(True)
        Ag = operator_from_parts(
            A.crow_indices(), A.col_indices(), values, tuple(A.shape), symmetric=True
        )
        X = tp.solve(Ag, B)
        start = time.perf_counter()
        X.square().sum().backward()
        forward_backward.backward_seconds.append(time.perf_counter() - start)

    forward_backward.backward_seconds = []
    out["ours_factor_solve_backward"] = timed(forward_backward, repeat)
    out["ours_backward_only"] = statistics.median(forward_backward.backward_seconds)
    return out


def bench_eigs(n: int, k: int, repeat: int) -> dict:
    verts, faces = bench_grid(n)
    L, M0 = tp.laplacian(verts, faces)
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0)
    shift = -1e-8 * abs(Ls).max() / Ms.diagonal().max()
    return {
        "faces": faces.shape[0],
        "k": k,
        "ours": timed(lambda: tp.eigs(L, M0, k), repeat),
        "scipy_eigsh": timed(lambda: spla.eigsh(Ls, k=k, M=Ms, sigma=shift, which="LM"), repeat),
    }


def bench_precompute(k: int, repeat: int) -> dict | None:
    if not SWORD.is_file():
        return None
    try:
        import robust_laplacian
    except ImportError:
        robust_laplacian = None
    verts, faces = tp.read_mesh(SWORD)
    out = {"verts": verts.shape[0], "faces": faces.num_faces, "k": k}

    def ours() -> None:
        # fresh faces every call, so the topology is built (not taken from the cache)
        fresh = tp.PolygonFaces(faces.indices.clone(), offsets=faces.offsets.clone())
        L, M0 = tp.laplacian(verts, fresh)
        tp.eigs(L, M0, k)

    out["ours_polygon"] = timed(ours, repeat)
    L, M0 = tp.laplacian(verts, faces)
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0)
    out["scipy_eigsh_polygon_L"] = timed(
        lambda: spla.eigsh(Ls, k=k, M=Ms, sigma=-1e-8, which="LM"), repeat
    )
    if robust_laplacian is not None:
        tris = np.concatenate(
            [
                np.stack([f[0].repeat(len(f) - 2), f[1:-1], f[2:]], 1)
                for f in map(np.array, faces.tolist())
            ]
        )
        V = verts.numpy()

        def triangle_pipeline() -> None:
            Lt, Mt = robust_laplacian.mesh_laplacian(V, tris)
            spla.eigsh(Lt, k=k, M=Mt, sigma=1e-8, which="LM")

        out["robust_laplacian_pipeline"] = timed(triangle_pipeline, repeat)
    return out


def main() -> None:
    parser = script_parser(__doc__, "solve", repeat=3)
    parser.add_argument("--sizes", type=int, nargs="*", default=[100, 316, 1000])
    parser.add_argument("--eig-sizes", type=int, nargs="*", default=[100, 316])
    parser.add_argument("--k", type=int, default=64)
    parser.add_argument(
        "--precompute-k", type=int, default=128, help="0 skips the sword precompute"
    )
    args = parser.parse_args()
    meta = run_meta()

    report: dict = {"repeat": args.repeat, "solve": [], "eigs": [], "precompute": None}
    tables = report["tables"] = {}
    lines = [
        f"torch {torch.__version__}, {torch.get_num_threads()} threads, float64; "
        f"median of {args.repeat}.",
        "",
    ]
    rows = []
    for n in args.sizes:
        r = bench_solve(n, args.repeat)
        report["solve"].append(r)
        rows.append(
            [
                f"{r['faces']:,}",
                f"{r['ours_factor_solve'] * 1e3:.1f} ms",
                f"{r['scipy_splu_solve'] * 1e3:.1f} ms",
                f"{r['ours_factor_solve'] / r['scipy_splu_solve']:.2f}",
                f"{r['scipy_splu_default'] * 1e3:.1f} ms",
                f"{r['ours_resolve'] * 1e3:.1f} ms",
                f"{r['ours_backward_only'] / r['ours_factor_solve']:.2f}",
            ]
        )
    header = [
        "F",
        "ours: factor + solve",
        "scipy splu (same options)",
        "ratio",
        "scipy splu (default)",
        "re-solve (cached)",
        "backward / forward",
    ]
    lines += ["### solve, A = M0 + 0.01 L, B (V, 3)", "", markdown_table(header, rows)]
    tables["solve"] = table_data(header, rows)
    rows = []
    for n in args.eig_sizes:
        r = bench_eigs(n, args.k, args.repeat)
        report["eigs"].append(r)
        rows.append(
            [
                f"{r['faces']:,}",
                f"{r['ours']:.2f} s",
                f"{r['scipy_eigsh']:.2f} s",
                f"{r['ours'] / r['scipy_eigsh']:.2f}",
            ]
        )
    header = ["F", "ours", "scipy eigsh", "ratio"]
    lines += ["", f"### eigs, k = {args.k}", "", markdown_table(header, rows)]
    tables["eigs"] = table_data(header, rows)
    pre = bench_precompute(args.precompute_k, args.repeat) if args.precompute_k > 0 else None
    report["precompute"] = pre
    if pre is not None:
        header = ["mesh", "V", "k", "ours (L, M0, eigs)", "scipy eigsh on our L"]
        row = [SWORD.name, f"{pre['verts']:,}", str(pre["k"]), f"{pre['ours_polygon']:.2f} s"]
        row.append(f"{pre['scipy_eigsh_polygon_L']:.2f} s")
        if "robust_laplacian_pipeline" in pre:
            header += ["robust-laplacian + eigsh", "ours / robust-laplacian"]
            row.append(f"{pre['robust_laplacian_pipeline']:.2f} s")
            row.append(f"{pre['ours_polygon'] / pre['robust_laplacian_pipeline']:.2f}")
        lines += ["", "### spectral precompute", "", markdown_table(header, [row])]
        tables["precompute"] = table_data(header, [row])
    print("\n".join(lines))
    write_results("solve", report, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
