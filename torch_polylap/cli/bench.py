"""``polylap bench [MESH]``: quick side-by-side timings of the operators on one mesh.

Each time is the median of ``--repeat`` calls after a warm-up call. References: libigl's
triangle ``cotmatrix`` on the fan triangulation of the same mesh (when libigl is installed),
scipy's CSR product, scipy ``splu`` with the same SPD settings as :func:`torch_polylap.solve`
(COLAMD, symmetric mode), and scipy's shift-invert ``eigsh`` with the first shift
:func:`torch_polylap.eigs` tries (``-1e-8 max|L| / max M0``) and ``ncv = max(2k + 1, 20)``.
For the full benchmarks (large grids, peak memory) see ``benchmarks/``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from ..faces import PolygonFaces
from ..linalg import eigs, solve
from ..operators import laplacian
from ..sparse import to_scipy
from ..topology import build_topology
from .common import (
    add_mesh_argument,
    add_method_argument,
    fmt_time,
    load_mesh,
    method_label,
    output_dir,
    positive_float,
    positive_int,
    result_path,
    table,
    timed,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="quick timings against scipy (and libigl when installed)",
        description="Time topology, assembly, re-assembly, forward+backward, spmm, solve and "
        "eigs on one mesh, side by side with scipy (and libigl's cotmatrix on the fan "
        "triangulation when libigl is installed); ratio = torch_polylap / reference.",
    )
    add_mesh_argument(p)
    p.add_argument("--lam", type=positive_float, default=1.0, help="stabilizer weight (default 1)")
    add_method_argument(p)
    p.add_argument("--repeat", type=positive_int, default=5, help="samples per timing (default 5)")
    p.add_argument("-k", type=positive_int, default=16, help="eigenpairs for eigs (default 16)")
    p.add_argument(
        "--h", type=positive_float, default=1e-2, help="time step in M0 + h L (default 0.01)"
    )
    p.add_argument(
        "-o",
        "--output",
        default="polylap_out",
        metavar="DIR",
        help="directory for --json (default: ./polylap_out)",
    )
    p.add_argument("--json", action="store_true", help="also write <mesh>_bench.json to -o DIR")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def fan_triangles(faces: PolygonFaces) -> np.ndarray:
    """``(sum(k_f - 2), 3)`` fan triangulation ``(c0, ci, ci+1)`` of every polygon."""
    idx = faces.indices.numpy()
    sizes = faces.sizes.numpy()
    ntri = sizes - 2
    first = np.repeat(faces.offsets.numpy()[:-1], ntri)
    local = np.arange(ntri.sum()) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    return np.stack([idx[first], idx[first + local], idx[first + local + 1]], 1)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    verts, faces, path, label = load_mesh(args)
    n = verts.shape[0]
    k = min(args.k, n - 1)
    topo = build_topology(faces, n)
    method = args.method
    L, M0 = laplacian(verts, topo, args.lam, method=method)
    Ls, Ms = to_scipy(L), to_scipy(M0)
    X = torch.randn(n, 3, dtype=verts.dtype, generator=torch.Generator().manual_seed(0))
    Xs = X.numpy()
    A_csc = sp.csc_matrix(to_scipy(M0 + args.h * L))
    shift = -1e-8 * float(abs(Ls).max()) / float(Ms.diagonal().max())

    def forward_backward() -> None:
        V = verts.clone().requires_grad_(True)
        Lv, _ = laplacian(V, topo, args.lam, method=method)
        ((Lv @ X) ** 2).sum().backward()

    def scipy_splu() -> np.ndarray:
        lu = spla.splu(
            A_csc, permc_spec="COLAMD", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
        return lu.solve(Xs)

    def scipy_eigsh() -> object:
        ncv = min(n, max(2 * k + 1, 20))
        return spla.eigsh(Ls, k=k, M=Ms, sigma=shift, which="LM", ncv=ncv)

    igl_cot = _igl_reference(verts.numpy(), fan_triangles(faces))
    cases: list[tuple[str, Callable[[], object], str, Callable[[], object] | None]] = [
        ("topology (build_topology)", lambda: build_topology(faces, n), "-", None),
        (
            "first assembly (topology + L, M0)",
            lambda: laplacian(verts, build_topology(faces, n), args.lam, method=method),
            "igl.cotmatrix + massmatrix (fan)",
            igl_cot,
        ),
        (
            "re-assembly (cached topology)",
            lambda: laplacian(verts, topo, args.lam, method=method),
            "igl.cotmatrix + massmatrix (fan)",
            igl_cot,
        ),
        ("forward + backward of sum((L X)^2)", forward_backward, "-", None),
        ("spmm(L, X), X (V, 3)", lambda: L @ X, "scipy CSR @ X", lambda: Ls @ Xs),
        (
            f"solve(M0 + {args.h:g} L, X)",
            lambda: solve(M0 + args.h * L, X),
            "scipy splu + solve",
            scipy_splu,
        ),
        (f"eigs(L, M0, k={k})", lambda: eigs(L, M0, k), "scipy eigsh", scipy_eigsh),
    ]
    results = []
    for name, ours, ref_name, ref in tqdm(cases, desc="bench", disable=args.no_progress):
        t_ours = timed(ours, args.repeat, warmup=True)[0]
        t_ref = timed(ref, args.repeat, warmup=True)[0] if ref is not None else None
        results.append(
            {
                "operation": name,
                "torch_polylap_s": t_ours,
                "reference": ref_name if ref is not None else None,
                "reference_s": t_ref,
                "ratio": t_ours / t_ref if t_ref else None,
            }
        )
    print(
        f"polylap bench: {label}, {n} vertices, {faces.num_faces} faces, "
        f"{method_label(args)}, "
        f"float64, median of {args.repeat}"
    )
    print(
        table(
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
    )
    if args.json:
        out = result_path(output_dir(args), path, "bench", ".json")
        meta = {"mesh": str(path), "verts": n, "faces": faces.num_faces, "lam": args.lam}
        meta |= {"method": method}
        meta |= {"repeat": args.repeat, "k": k, "h": args.h, "torch": torch.__version__}
        out.write_text(json.dumps({**meta, "results": results}, indent=2))
        print(f"wrote {out}")
    return 0


def _igl_reference(V: np.ndarray, F: np.ndarray) -> Callable[[], object] | None:
    """libigl's cotan Laplacian and Voronoi mass on the fan triangles, if libigl is installed."""
    try:
        import igl
    except ImportError:
        return None
    F = np.ascontiguousarray(F.astype(np.int64))
    V = np.ascontiguousarray(V)
    return lambda: (igl.cotmatrix(V, F), igl.massmatrix(V, F, igl.MASSMATRIX_TYPE_VORONOI))
