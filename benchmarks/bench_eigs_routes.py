"""Which eigensolver route is fastest where, and the spectral precompute against robust-laplacian.

    python benchmarks/bench_eigs_routes.py routes [--sizes 500 1000 3000 10000 30000 100000]
    python benchmarks/bench_eigs_routes.py precompute [--sizes 1000 3000 10000 30000 100000]

Both run single-threaded (torch, OpenMP and OpenBLAS threads set to 1 before numpy loads) on
non-planar quad grids of about the requested vertex count, for ``k`` in ``--ks`` (16 64 128),
and interleave the contenders (A B C A B C ...) so that load from other jobs hits them alike;
medians of ``--repeat`` rounds (fewer above 10k vertices, see ``rounds``).

* ``routes``: the routes of :func:`torch_polylap.eigs` on the same ``L, M0``: dense LAPACK
  (``scipy.linalg.eigh`` with ``subset_by_index``, only up to ``--dense-max`` vertices), ARPACK
  shift-invert with scipy's internal SuperLU, ARPACK with CHOLMOD (cholespy) as the
  shift-invert operator, and block Lanczos on CHOLMOD; plus the route
  :func:`torch_polylap.linalg.eigs_route` picks. These are the measurements behind that rule.
* ``precompute``: what a spectral network computes per mesh, topology + ``L, M0`` + ``k``
  eigenpairs by ``torch_polylap.eigs``, against robust-laplacian's ``mesh_laplacian`` on the
  fan-triangulated mesh + scipy ``eigsh(L, M=M, sigma=1e-8, which="LM")`` (``pip install
  robust-laplacian``).

Prints Markdown tables and writes ``benchmarks/results/eigs_routes.json`` (``routes``) or
``benchmarks/results/eigs_precompute.json`` (``precompute``), or ``--json PATH``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402
import torch  # noqa: E402
from common import (  # noqa: E402
    bench_grid,
    interleaved,
    markdown_table,
    pinned_threads,
    run_meta,
    table_data,
    write_results,
)

import torch_polylap as tp  # noqa: E402
import torch_polylap.linalg as linalg  # noqa: E402

ROUTES = ("dense", "arpack_superlu", "arpack_cholmod", "arpack", "lanczos")


def grid_mesh(verts: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The benchmark grid (``common.bench_grid``) with about ``verts`` vertices."""
    return bench_grid(max(2, round(verts**0.5) - 1))


def rounds(n: int, repeat: int) -> int:
    return repeat if n <= 10_000 else max(1, repeat - 1) if n <= 30_000 else 1


def arpack_cholmod(Ls: sp.csr_matrix, Ms: sp.csr_matrix, k: int, shift: float):
    """ARPACK shift-invert with a CHOLMOD factorization of ``L - shift M`` as the operator."""
    factor = linalg.CholeskyFactorization(sp.csr_matrix(Ls - shift * Ms), torch.device("cpu"))

    def matvec(x: np.ndarray) -> np.ndarray:
        b = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 1))
        return factor._solve64(b)[:, 0].numpy()

    op = spla.LinearOperator(Ls.shape, matvec=matvec, dtype=np.float64)
    return spla.eigsh(Ls, k=k, M=Ms, sigma=shift, which="LM", tol=0, OPinv=op)


def bench_routes(n_target: int, k: int, repeat: int, dense_max: int, generalized_max: int) -> dict:
    V, F = grid_mesh(n_target)
    L, M0 = tp.laplacian(V, F)
    Ls, Ms = tp.sparse.to_scipy(L).astype(np.float64), tp.sparse.to_scipy(M0).astype(np.float64)
    n = Ls.shape[0]
    scale = abs(Ls).max() / Ms.diagonal().max()
    shift = -1e-6 * scale
    contenders: dict[str, Callable[[], object]] = {}
    if n <= dense_max:
        Ld, Md = Ls.toarray(), Ms.toarray()
        contenders["dense"] = lambda: scipy.linalg.eigh(Ld, Md, subset_by_index=(0, k - 1))
    if n <= generalized_max:
        contenders["arpack_superlu"] = lambda: spla.eigsh(
            Ls, k=k, M=Ms, sigma=shift, which="LM", tol=0
        )
        contenders["arpack_cholmod"] = lambda: arpack_cholmod(Ls, Ms, k, shift)
    contenders["arpack"] = lambda: linalg.eigenpairs._eigs_arpack(
        Ls, Ms, k, None, scale, 0.0, diagonal_mass=True
    )
    contenders["lanczos"] = lambda: linalg.eigenpairs._eigs_block_lanczos(
        Ls, Ms.diagonal(), k, shift, 1e-10, torch.device("cpu")
    )
    out = {"verts": n, "k": k, "route": linalg.eigs_route(n, k, diagonal_mass=True, cholmod=True)}
    out.update(interleaved(contenders, rounds(n, repeat)))
    return out


def fan_triangles(faces: torch.Tensor) -> np.ndarray:
    f = faces.numpy()
    return np.concatenate([f[:, [0, i, i + 1]] for i in range(1, f.shape[1] - 1)])


def bench_precompute(n_target: int, k: int, repeat: int) -> dict:
    import robust_laplacian

    V, F = grid_mesh(n_target)
    Vn, tris = V.numpy(), fan_triangles(F)

    def ours() -> None:
        L, M0 = tp.laplacian(V, F.clone())  # a fresh face tensor: topology built every call
        tp.eigs(L, M0, k)

    def pipeline() -> None:
        Lt, Mt = robust_laplacian.mesh_laplacian(Vn, tris)
        spla.eigsh(Lt, k=k, M=Mt, sigma=1e-8, which="LM")

    out = {
        "verts": V.shape[0],
        "k": k,
        "route": linalg.eigs_route(len(V), k, diagonal_mass=True, cholmod=True),
    }
    out.update(interleaved({"ours": ours, "robust_laplacian": pipeline}, rounds(len(V), repeat)))
    out["ratio"] = out["ours"] / out["robust_laplacian"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=["routes", "precompute"])
    parser.add_argument("--sizes", type=int, nargs="*")
    parser.add_argument("--ks", type=int, nargs="*", default=[16, 64, 128])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--dense-max", type=int, default=1500)
    parser.add_argument(
        "--generalized-max",
        type=int,
        default=30000,
        help="largest size to time ARPACK's generalized mode at (it lost everywhere below)",
    )
    parser.add_argument("--json", type=Path, help="default benchmarks/results/eigs_<mode>.json")
    args = parser.parse_args()
    meta = run_meta(threads=1)
    with pinned_threads(1):
        run(args, meta)


def run(args: argparse.Namespace, meta: dict) -> None:
    sizes = args.sizes or (
        [500, 1000, 3000, 10000, 30000, 100000]
        if args.mode == "routes"
        else [1000, 3000, 10000, 30000, 100000]
    )
    # warm-up: imports, CHOLMOD and ARPACK first calls
    bench_routes(500, 16, 1, 0, 1000) if args.mode == "routes" else bench_precompute(500, 16, 1)
    results, rows = [], []
    for size in sizes:
        for k in args.ks:
            if args.mode == "routes":
                r = bench_routes(size, k, args.repeat, args.dense_max, args.generalized_max)
                best = min(ROUTES, key=lambda name: r.get(name, np.inf))
                cells = [
                    f"**{r[c]:.3f}**" if c == best else f"{r[c]:.3f}" if c in r else "-"
                    for c in ROUTES
                ]
                rows.append([f"{r['verts']:,}", k, *cells, r["route"]])
            else:
                r = bench_precompute(size, k, args.repeat)
                rows.append(
                    [
                        f"{r['verts']:,}",
                        k,
                        f"{r['ours']:.3f} s",
                        f"{r['robust_laplacian']:.3f} s",
                        f"{r['ratio']:.2f}",
                        r["route"],
                    ]
                )
            print(" ".join(str(c) for c in rows[-1]), file=sys.stderr, flush=True)  # progress
            results.append(r)
    if args.mode == "routes":
        header = [
            "V",
            "k",
            "dense",
            "ARPACK gen. + SuperLU",
            "ARPACK gen. + CHOLMOD",
            "ARPACK std. (ours)",
            "block Lanczos",
            "picked",
        ]
    else:
        header = ["V", "k", "ours", "robust-laplacian + eigsh", "ratio", "route"]
    print(
        f"torch {torch.__version__}, 1 thread; medians of {args.repeat} interleaved rounds "
        "(2 above 10k vertices, 1 above 30k)\n"
    )
    print(markdown_table(header, rows))
    name = "eigs_routes" if args.mode == "routes" else "eigs_precompute"
    sections = {"repeat": args.repeat, "results": results}
    sections["tables"] = {args.mode: table_data(header, rows)}
    write_results(name, sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
