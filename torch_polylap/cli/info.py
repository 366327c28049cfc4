"""``polylap info [MESH]``: mesh statistics, topology defects, properties of ``L`` and ``M0``,
assembly timings."""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph
import scipy.sparse.linalg
import torch

from .. import __version__
from ..operators import face_areas, face_nonplanarity, laplacian
from ..sparse import to_scipy
from ..topology import build_topology
from .common import DEFAULT_MESH, add_method_argument, read_mesh_quietly, row, timed


def add_parser(sub: argparse._SubParsersAction) -> None:
    info = sub.add_parser(
        "info",
        help="mesh statistics, operator properties and timings",
        description="Print mesh statistics, properties of L and M0, and assembly timings.",
    )
    info.add_argument(
        "mesh", nargs="?", help="OBJ, OFF or PLY polygon mesh (default: the embedded Spot cage)"
    )
    info.add_argument("--lam", type=float, default=1.0, help="stabilizer weight lambda (default 1)")
    add_method_argument(info)
    info.add_argument("--dtype", choices=("float32", "float64"), default="float64")
    info.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    info.add_argument("--eigs", type=int, default=6, help="how many smallest eigenvalues to show")
    info.set_defaults(func=run)


def _smallest_eigenvalues(L: sp.csr_matrix, M: sp.csr_matrix, k: int) -> np.ndarray | None:
    """The ``k`` smallest generalized eigenvalues of ``L phi = mu M0 phi`` (shift-invert)."""
    n = L.shape[0]
    k = min(k, n - 2)
    if k < 1:
        return None
    shift = -1e-8 * abs(L.diagonal()).max()
    try:
        vals = scipy.sparse.linalg.eigsh(
            L, k=k, M=M, sigma=shift, which="LM", return_eigenvectors=False
        )
    except (RuntimeError, scipy.sparse.linalg.ArpackNoConvergence):
        return None
    return np.sort(vals)


def run(args: argparse.Namespace) -> int:
    path = Path(args.mesh) if args.mesh else DEFAULT_MESH
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    verts, faces = read_mesh_quietly(path, not args.mesh, dtype=dtype, device=args.device)
    # no warning: the table lists what the topology found (Topology.report)
    t_topo, topo = timed(lambda: build_topology(faces, verts.shape[0], warn=False), repeat=1)
    method = args.method
    t_first = t_topo + timed(lambda: laplacian(verts, topo, args.lam, method=method), repeat=1)[0]
    t_values, (L, M0) = timed(lambda: laplacian(verts, topo, args.lam, method=method))

    def forward_backward() -> None:
        X = verts.detach().clone().requires_grad_(True)
        Lx, _ = laplacian(X, topo, args.lam, method=method)
        ((Lx @ X) ** 2).sum().backward()

    t_grad, _ = timed(forward_backward)

    sizes = faces.sizes.tolist()
    degrees = " ".join(f"{k}:{n}" for k, n in sorted(Counter(sizes).items()))
    n_boundary = int((topo.edge_faces == 1).sum())
    Ls, Ms = to_scipy(L), to_scipy(M0)
    n_comp, _ = scipy.sparse.csgraph.connected_components(Ls, directed=False)
    n_comp -= int(topo.isolated.sum())  # isolated vertices count as components of their own
    chi = topo.euler_characteristic()
    nonplanar = face_nonplanarity(verts, topo)
    polys = nonplanar[faces.sizes.to(nonplanar.device) > 3]
    areas = face_areas(verts, topo)
    scale = abs(Ls).max()
    asym = abs(Ls - Ls.T).max() / scale
    rowsum = np.abs(np.asarray(Ls.sum(1))).max() / scale
    mass = Ms.diagonal()
    evals = _smallest_eigenvalues(Ls.astype(np.float64), Ms.astype(np.float64), args.eigs)

    lines = [
        f"polylap {__version__}: {path.name}"
        + (" (embedded default mesh)" if not args.mesh else ""),
        "mesh",
        row("vertices / faces / edges", f"{verts.shape[0]} / {faces.num_faces} / {topo.num_edges}"),
        row("face degrees (k:count)", degrees),
        row("boundary edges", str(n_boundary)),
        row("connected components", str(n_comp)),
        row("Euler characteristic", str(chi)),
    ]
    report = topo.report
    orientable = report.non_orientable_components == 0
    lines.append(
        row(
            "manifold / oriented / orientable",
            " / ".join(
                "yes" if ok else "no" for ok in (report.is_manifold, report.is_oriented, orientable)
            ),
        )
    )
    if n_boundary == 0 and n_comp == 1 and report.is_manifold and orientable:
        lines.append(row("genus (closed, orientable)", str((2 - chi) // 2)))
    defects = report.lines(verts.shape[0])
    lines += [row("topology defect", line) for line in defects]
    if defects:
        lines.append(
            row(
                "repairs (L and M0 need none)",
                "torch_polylap.repair: orient_faces, remove_duplicate_faces, ...",
            )
        )
    if polys.numel():
        lines.append(
            row(
                "non-planarity max / median",
                f"{float(polys.max()):.2e} / {float(polys.median()):.2e}  (height / diameter)",
            )
        )
    lines += [
        row("total area", f"{float(areas.sum()):.6g}"),
        f"operators ({'' if method == 'aw11' else method + ', '}"
        f"{'lambda unused' if method == 'plms' else f'lambda = {args.lam}'}, "
        f"{args.dtype}, {verts.device})",
        row("L: size / nonzeros", f"{L.shape[0]} x {L.shape[1]} / {Ls.nnz}"),
        row("L symmetry |L - L^T| / max|L|", f"{asym:.1e}"),
        row("L row sums / max|L|", f"{rowsum:.1e}"),
        row("M0: sum - total area", f"{float(mass.sum() - areas.sum()):.1e}"),
        row("M0: min mass", f"{float(mass.min()):.3e}"),
    ]
    if evals is not None:
        zero = int((np.abs(evals) < 1e-8 * max(1.0, abs(evals).max())).sum())
        lines.append(
            row(
                f"smallest {len(evals)} eigenvalues of L = mu M0",
                np.array2string(evals, precision=4),
            )
        )
        lines.append(row("zero eigenvalues / components", f"{zero} / {n_comp}"))
    lines += [
        "timings (median of 3)",
        row("first assembly (topology + values)", f"{t_first * 1e3:.2f} ms"),
        row("re-assembly, cached topology", f"{t_values * 1e3:.2f} ms"),
        row("forward + backward of |L X|^2", f"{t_grad * 1e3:.2f} ms"),
    ]
    print("\n".join(lines))
    return 0
