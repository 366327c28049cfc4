"""``polylap bench [MESH]``: quick side-by-side timings of the operators on one mesh.

Each time is the median of ``--repeat`` samples after a warm-up, with torch pinned to one
thread unless ``polylap bench --threads N`` asks for more (:mod:`torch_polylap.timing`). The
operations run through the library (``laplacian``, ``M0 + h * L``, :func:`torch_polylap.solve`,
:func:`torch_polylap.eigs`); the references are libigl's triangle ``cotmatrix`` and
``massmatrix`` on the library's triangulation of the same mesh
(:func:`torch_polylap.triangulate.triangulate_faces`, when libigl is installed), scipy's CSR
product, scipy's SuperLU with the settings of :func:`torch_polylap.linalg.spd_splu` on the same
``M0 + h L``, and scipy's generalized shift-invert ``eigsh`` just below zero. Measured numbers
and the full benchmarks (large grids, peak memory) are in ``benchmarks/``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..faces import PolygonFaces
from ..linalg import eigs, solve, spd_splu
from ..operators import laplacian
from ..sparse import to_scipy
from ..timing import fmt_time, markdown_table, median_time, pinned_threads
from ..topology import build_topology
from ..triangulate import triangulate_faces
from .common import (
    Result,
    add_laplacian_arguments,
    execute,
    finish_command,
    json_output,
    load_mesh,
    method_label,
    positive_float,
    positive_int,
    result_name,
)

# shift of the scipy eigsh reference, relative to max|L| / max M0: L is singular, so the
# shift-invert needs one just below zero
REFERENCE_SHIFT = -1e-6


SUMMARY = "quick timings against scipy (and libigl when installed)"
DESCRIPTION = (
    "Time topology, assembly, re-assembly, forward+backward, spmm, solve and "
    "eigs on one mesh, side by side with scipy (and libigl's cotmatrix on the triangulated "
    "mesh when libigl is installed); ratio = torch_polylap / reference. torch runs on one "
    "thread unless --threads N says otherwise: on a busy machine tiny multi-threaded "
    "kernels wait for descheduled threads."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_laplacian_arguments(p)
    p.add_argument("--repeat", type=positive_int, default=5, help="samples per timing (default 5)")
    p.add_argument("-k", type=positive_int, default=16, help="eigenpairs for eigs (default 16)")
    p.add_argument(
        "--h", type=positive_float, default=1e-2, help="time step in M0 + h L (default 0.01)"
    )
    finish_command(p, run, compute, plot=False, report="bench")


Case = tuple[str, Callable[[], object], str | None, Callable[[], object] | None]


def cases(verts: torch.Tensor, faces: PolygonFaces, args: argparse.Namespace, k: int) -> list[Case]:
    """``(operation, ours, reference name, reference)`` for every timed row."""
    n = verts.shape[0]
    lam, method, h = args.lam, args.method, args.h
    topo = build_topology(faces, n)
    L, M0 = laplacian(verts, topo, lam, method=method)
    A = M0 + h * L  # the implicit-step matrix, by the operators' own algebra
    Ls, Ms, As = to_scipy(L), to_scipy(M0), sp.csc_matrix(to_scipy(A))
    X = torch.randn(n, 3, dtype=verts.dtype, generator=torch.Generator().manual_seed(0))
    Xs = X.numpy()
    shift = REFERENCE_SHIFT * float(abs(Ls).max()) / float(Ms.diagonal().max())

    def forward_backward() -> None:
        V = verts.clone().requires_grad_(True)
        Lv, _ = laplacian(V, topo, lam, method=method)
        ((Lv @ X) ** 2).sum().backward()

    def scipy_eigsh() -> object:
        ncv = min(n, max(2 * k + 1, 20))
        return spla.eigsh(Ls, k=k, M=Ms, sigma=shift, which="LM", ncv=ncv)

    igl_name = "igl.cotmatrix + massmatrix (triangulated)"
    igl_ref = _igl_reference(verts.numpy(), triangulate_faces(verts, faces))
    return [
        ("topology (build_topology)", lambda: build_topology(faces, n), None, None),
        (
            "first assembly (topology + L, M0)",
            lambda: laplacian(verts, build_topology(faces, n), lam, method=method),
            igl_name,
            igl_ref,
        ),
        (
            "re-assembly (cached topology)",
            lambda: laplacian(verts, topo, lam, method=method),
            igl_name,
            igl_ref,
        ),
        ("forward + backward of sum((L X)^2)", forward_backward, None, None),
        ("spmm(L, X), X (V, 3)", lambda: L @ X, "scipy CSR @ X", lambda: Ls @ Xs),
        (
            f"solve(M0 + {h:g} L, X)",
            lambda: solve(M0 + h * L, X),
            "scipy splu + solve",
            lambda: spd_splu(As).solve(Xs),
        ),
        (f"eigs(L, M0, k={k})", lambda: eigs(L, M0, k), "scipy eigsh", scipy_eigsh),
    ]


def compute(args: argparse.Namespace) -> Result:
    from tqdm import tqdm

    verts, faces, path, label = load_mesh(args)
    n = verts.shape[0]
    k = min(args.k, n - 1)
    results = []
    with pinned_threads(getattr(args, "threads", None)) as threads:
        todo = cases(verts, faces, args, k)
        for name, ours, ref_name, ref in tqdm(todo, desc="bench", disable=args.no_progress):
            t_ours = median_time(ours, args.repeat)
            t_ref = median_time(ref, args.repeat) if ref is not None else None
            results.append(
                {
                    "operation": name,
                    "torch_polylap_s": t_ours,
                    "reference": ref_name if ref is not None else None,
                    "reference_s": t_ref,
                    "ratio": t_ours / t_ref if t_ref else None,
                }
            )
    plural = "s" if threads > 1 else ""
    pinned = (
        " (pinned; polylap bench --threads N to change)"
        if getattr(args, "threads", None) is None
        else ""
    )
    title = (
        f"polylap bench: {label}, {n} vertices, {faces.num_faces} faces, {method_label(args)}, "
        f"float64, median of {args.repeat}, {threads} torch thread{plural}{pinned}"
    )
    text = markdown_table(
        ["operation", "torch_polylap", "reference", "time", "ratio"],
        [
            [
                r["operation"],
                fmt_time(r["torch_polylap_s"]),
                r["reference"] or "-",
                fmt_time(r["reference_s"]) if r["reference_s"] is not None else "-",
                f"{r['ratio']:.2f}x" if r["ratio"] is not None else "-",
            ]
            for r in results
        ],
    )
    data = {
        "mesh": str(path),
        "verts": n,
        "faces": faces.num_faces,
        "lam": args.lam,
        "method": args.method,
        "repeat": args.repeat,
        "k": k,
        "h": args.h,
        "threads": threads,
        "torch": torch.__version__,
        "results": results,
    }
    result = Result(title, text=text, data=data)
    if args.output is not None or args.json:
        result.outputs.append(json_output(result_name(path, "bench", ".json"), data))
    return result


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)


def _igl_reference(V: np.ndarray, F: np.ndarray) -> Callable[[], object] | None:
    """libigl's cotan Laplacian and Voronoi mass on the triangles, if libigl is installed."""
    try:
        import igl
    except ImportError:
        return None
    F = np.ascontiguousarray(F.astype(np.int64))
    V = np.ascontiguousarray(V)
    return lambda: (igl.cotmatrix(V, F), igl.massmatrix(V, F, igl.MASSMATRIX_TYPE_VORONOI))
