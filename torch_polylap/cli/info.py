"""``polylap info [MESH]``: mesh statistics, topology defects, properties of ``L`` and ``M0``
(smallest eigenvalues by :func:`torch_polylap.eigs`), assembly timings; with ``-o DIR`` or
``--json`` also the report as ``<mesh>_info.json``."""

from __future__ import annotations

import argparse
from collections import Counter

import numpy as np
import scipy.sparse.csgraph
import torch

from .. import __version__
from ..linalg import eigs
from ..measures import face_areas, face_nonplanarity
from ..operators import laplacian
from ..sparse import to_scipy
from ..timing import pinned_threads, synchronizer, timed
from .common import (
    Result,
    Rows,
    add_mesh_argument,
    add_method_argument,
    add_output_arguments,
    execute,
    json_output,
    load_mesh,
    method_label,
    result_name,
)
from .timing import FIRST_ASSEMBLY, first_assembly

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="mesh statistics, operator properties and timings",
        description="Print mesh statistics, properties of L and M0 (with the smallest "
        "eigenvalues of L phi = mu M0 phi from torch_polylap.eigs), and assembly timings "
        "(torch pinned to --threads N, default 1). With -o DIR or --json also write the report "
        "as <mesh>_info.json.",
    )
    add_mesh_argument(p)
    p.add_argument("--lam", type=float, default=1.0, help="stabilizer weight lambda (default 1)")
    add_method_argument(p)
    p.add_argument("--dtype", choices=tuple(DTYPES), default="float64")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--eigs", type=int, default=6, help="how many smallest eigenvalues to show")
    add_output_arguments(p, plot=False, progress=False, report="info")
    p.set_defaults(func=run, compute=compute)


def smallest_eigenvalues(
    L: torch.Tensor, M0: torch.Tensor, k: int
) -> tuple[np.ndarray | None, str | None]:
    """The ``k`` smallest eigenvalues of ``L phi = mu M0 phi`` by :func:`torch_polylap.eigs`
    (``k`` capped at ``n - 1``), or ``None`` and the reason where there are none."""
    k = min(k, L.shape[0] - 1)
    if k < 1:
        return None, "needs --eigs >= 1 and at least 2 vertices"
    try:
        evals, _ = eigs(L, M0, k)
    except ValueError as err:  # e.g. a vertex no face references has zero mass
        return None, " ".join(str(err).split())
    return evals.detach().cpu().double().numpy(), None


def compute(args: argparse.Namespace) -> Result:
    verts, faces, path, label = load_mesh(args, dtype=DTYPES[args.dtype], device=args.device)
    method, lam = args.method, args.lam
    sync = synchronizer(verts.device)
    with pinned_threads(getattr(args, "threads", None)) as threads:
        # no warning: the table lists what the topology found (Topology.report)
        t_first, topo, _ = first_assembly(verts, faces, lam, method, warn=False, sync=sync)
        t_values, (L, M0) = timed(lambda: laplacian(verts, topo, lam, method=method), sync=sync)

        def forward_backward() -> None:
            X = verts.detach().clone().requires_grad_(True)
            Lx, _ = laplacian(X, topo, lam, method=method)
            ((Lx @ X) ** 2).sum().backward()

        t_grad, _ = timed(forward_backward, sync=sync)

    n = verts.shape[0]
    sizes = faces.sizes.tolist()
    degrees = " ".join(f"{k}:{count}" for k, count in sorted(Counter(sizes).items()))
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
    evals, no_evals = smallest_eigenvalues(L, M0, args.eigs)

    report = topo.report
    orientable = report.non_orientable_components == 0
    flags = (report.is_manifold, report.is_oriented, orientable)
    mesh_rows: Rows = [
        ("vertices / faces / edges", f"{n} / {faces.num_faces} / {topo.num_edges}"),
        ("face degrees (k:count)", degrees),
        ("boundary edges", str(n_boundary)),
        ("connected components", str(n_comp)),
        ("Euler characteristic", str(chi)),
        ("manifold / oriented / orientable", " / ".join("yes" if ok else "no" for ok in flags)),
    ]
    genus = None
    if n_boundary == 0 and n_comp == 1 and report.is_manifold and orientable:
        genus = (2 - chi) // 2
        mesh_rows.append(("genus (closed, orientable)", str(genus)))
    defects = report.lines(n)
    mesh_rows += [("topology defect", line) for line in defects]
    if defects:
        mesh_rows.append(
            (
                "repairs (L and M0 need none)",
                "torch_polylap.repair: orient_faces, remove_duplicate_faces, ...",
            )
        )
    if polys.numel():
        mesh_rows.append(
            (
                "non-planarity max / median",
                f"{float(polys.max()):.2e} / {float(polys.median()):.2e}  (height / diameter)",
            )
        )
    mesh_rows.append(("total area", f"{float(areas.sum()):.6g}"))

    operator_rows: Rows = [
        ("L: size / nonzeros", f"{L.shape[0]} x {L.shape[1]} / {Ls.nnz}"),
        ("L symmetry |L - L^T| / max|L|", f"{asym:.1e}"),
        ("L row sums / max|L|", f"{rowsum:.1e}"),
        ("M0: sum - total area", f"{float(mass.sum() - areas.sum()):.1e}"),
        ("M0: min mass", f"{float(mass.min()):.3e}"),
    ]
    zero = None
    if evals is not None:
        zero = int((np.abs(evals) < 1e-8 * max(1.0, abs(evals).max())).sum())
        operator_rows += [
            (
                f"smallest {len(evals)} eigenvalues of L = mu M0",
                np.array2string(evals, precision=4, max_line_width=1 << 16),
            ),
            ("zero eigenvalues / components", f"{zero} / {n_comp}"),
        ]
    else:
        operator_rows.append(("eigenvalues of L = mu M0", f"not computed: {no_evals}"))

    timing_rows: Rows = [
        (FIRST_ASSEMBLY, f"{t_first * 1e3:.2f} ms"),
        ("re-assembly, cached topology", f"{t_values * 1e3:.2f} ms"),
        ("forward + backward of |L X|^2", f"{t_grad * 1e3:.2f} ms"),
    ]
    operators = (
        f"operators ({'' if method == 'aw11' else method + ', '}"
        f"{'lambda unused' if method == 'plms' else f'lambda = {lam}'}, "
        f"{args.dtype}, {verts.device})"
    )
    sections = [
        ("mesh", mesh_rows),
        (operators, operator_rows),
        (
            f"timings ({threads} torch thread{'s' if threads > 1 else ''}; first assembly once, "
            "the others median of 3)",
            timing_rows,
        ),
    ]
    data = {
        "polylap": __version__,
        "mesh": str(path),
        "embedded": not args.mesh,
        "vertices": n,
        "faces": faces.num_faces,
        "edges": topo.num_edges,
        "boundary_edges": n_boundary,
        "components": n_comp,
        "euler_characteristic": chi,
        "genus": genus,
        "topology_defects": defects,
        "laplacian": method_label(args),
        "method": method,
        "lam": lam,
        "dtype": args.dtype,
        "device": str(verts.device),
        "eigenvalues": None if evals is None else evals.tolist(),
        "zero_eigenvalues": zero,
        "threads": threads,
        "timings_s": {
            "first_assembly": t_first,
            "reassembly": t_values,
            "forward_backward": t_grad,
        },
        "tables": {heading: [list(r) for r in rows] for heading, rows in sections},
    }
    result = Result(f"polylap {__version__}: {label}", sections=sections, data=data)
    if args.output is not None or args.json:
        result.outputs.append(json_output(result_name(path, "info", ".json"), data))
    return result


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
