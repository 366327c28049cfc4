"""``polylap info [MESH]``: mesh statistics, topology defects, properties of ``L`` and ``M0``
(smallest eigenvalues by :func:`torch_polylap.eigs`), assembly timings; with ``-o DIR`` or
``--json`` also the report as ``<mesh>_info.json``."""

from __future__ import annotations

import argparse
from collections import Counter
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph
import torch

from .. import __version__
from ..faces import PolygonFaces
from ..kernels import LAM_FREE_METHODS
from ..linalg import eigs
from ..measures import face_areas, face_nonplanarity
from ..operators import laplacian
from ..sparse import to_scipy
from ..timing import pinned_threads, synchronizer, timed
from ..topology import Topology
from .common import (
    Result,
    Rows,
    add_laplacian_arguments,
    execute,
    finish_command,
    json_output,
    load_mesh,
    method_label,
    result_name,
)
from .timing import FIRST_ASSEMBLY, first_assembly

DTYPES = {"float32": torch.float32, "float64": torch.float64}


SUMMARY = "mesh statistics, operator properties and timings"
DESCRIPTION = (
    "Print mesh statistics, properties of L and M0 (with the smallest "
    "eigenvalues of L phi = mu M0 phi from torch_polylap.eigs), and assembly timings "
    "(torch pinned to --threads N, default 1). With -o DIR or --json also write the report "
    "as <mesh>_info.json."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_laplacian_arguments(p, float, "stabilizer weight lambda (default 1)")
    p.add_argument("--dtype", choices=tuple(DTYPES), default="float64")
    p.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    p.add_argument("--eigs", type=int, default=6, help="how many smallest eigenvalues to show")
    finish_command(p, run, compute, plot=False, progress=False, report="info")


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


@dataclass
class _Timings:
    """Seconds of the first assembly, a re-assembly and a forward + backward; torch threads."""

    first: float
    values: float
    grad: float
    threads: int


@dataclass
class _Stats:
    """What the report says about a mesh and its operators ``L``, ``M0``."""

    n: int
    n_boundary: int
    n_comp: int  # connected components, isolated vertices not counted
    chi: int
    polys: torch.Tensor  # non-planarity of the faces of degree > 3
    areas: torch.Tensor  # (F,)
    Ls: sp.sparray | sp.spmatrix  # L in scipy form
    mass: np.ndarray  # M0's diagonal
    evals: np.ndarray | None  # the smallest eigenvalues, or None ...
    no_evals: str | None  # ... and why


def compute(args: argparse.Namespace) -> Result:
    verts, faces, path, label = load_mesh(args, dtype=DTYPES[args.dtype], device=args.device)
    method, lam = args.method, args.lam
    timings, topo, L, M0 = _timed_assembly(
        verts, faces, lam, method, getattr(args, "threads", None)
    )
    stats = _statistics(verts, faces, topo, (L, M0), args.eigs)
    mesh_rows, genus, defects = _mesh_rows(stats, faces, topo)
    operator_rows, zero = _operator_rows(stats, L)
    timing_rows: Rows = [
        (FIRST_ASSEMBLY, f"{timings.first * 1e3:.2f} ms"),
        ("re-assembly, cached topology", f"{timings.values * 1e3:.2f} ms"),
        ("forward + backward of |L X|^2", f"{timings.grad * 1e3:.2f} ms"),
    ]
    threads = timings.threads
    operators = (
        f"operators ({'' if method == 'aw11' else method + ', '}"
        f"{'lambda unused' if method in LAM_FREE_METHODS else f'lambda = {lam}'}, "
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
        "vertices": stats.n,
        "faces": faces.num_faces,
        "edges": topo.num_edges,
        "boundary_edges": stats.n_boundary,
        "components": stats.n_comp,
        "euler_characteristic": stats.chi,
        "genus": genus,
        "topology_defects": defects,
        "laplacian": method_label(args),
        "method": method,
        "lam": lam,
        "dtype": args.dtype,
        "device": str(verts.device),
        "eigenvalues": None if stats.evals is None else stats.evals.tolist(),
        "zero_eigenvalues": zero,
        "threads": threads,
        "timings_s": {
            "first_assembly": timings.first,
            "reassembly": timings.values,
            "forward_backward": timings.grad,
        },
        "tables": {heading: [list(r) for r in rows] for heading, rows in sections},
    }
    result = Result(f"polylap {__version__}: {label}", sections=sections, data=data)
    if args.output is not None or args.json:
        result.outputs.append(json_output(result_name(path, "info", ".json"), data))
    return result


def _timed_assembly(
    verts: torch.Tensor, faces: PolygonFaces, lam: float, method: str, threads: int | None
) -> tuple[_Timings, Topology, torch.Tensor, torch.Tensor]:
    """Time the first assembly, a re-assembly and a forward + backward with torch pinned to
    ``threads``; the timings, the topology and ``L``, ``M0``."""
    sync = synchronizer(verts.device)
    with pinned_threads(threads) as used:
        # no warning: the table lists what the topology found (Topology.report)
        t_first, topo, _ = first_assembly(verts, faces, lam, method, warn=False, sync=sync)
        t_values, (L, M0) = timed(lambda: laplacian(verts, topo, lam, method=method), sync=sync)

        def forward_backward() -> None:
            X = verts.detach().clone().requires_grad_(True)
            Lx, _ = laplacian(X, topo, lam, method=method)
            ((Lx @ X) ** 2).sum().backward()

        t_grad, _ = timed(forward_backward, sync=sync)
    return _Timings(t_first, t_values, t_grad, used), topo, L, M0


def _statistics(
    verts: torch.Tensor,
    faces: PolygonFaces,
    topo: Topology,
    operators: tuple[torch.Tensor, torch.Tensor],
    k: int,
) -> _Stats:
    """The mesh's and the operators' statistics, with the ``k`` smallest eigenvalues."""
    L, M0 = operators
    Ls, Ms = to_scipy(L), to_scipy(M0)
    n_comp, _ = scipy.sparse.csgraph.connected_components(Ls, directed=False)
    n_comp -= int(topo.isolated.sum())  # isolated vertices count as components of their own
    nonplanar = face_nonplanarity(verts, topo)
    evals, no_evals = smallest_eigenvalues(L, M0, k)
    return _Stats(
        n=verts.shape[0],
        n_boundary=int((topo.edge_faces == 1).sum()),
        n_comp=n_comp,
        chi=topo.euler_characteristic(),
        polys=nonplanar[faces.sizes.to(nonplanar.device) > 3],
        areas=face_areas(verts, topo),
        Ls=Ls,
        mass=Ms.diagonal(),
        evals=evals,
        no_evals=no_evals,
    )


def _mesh_rows(
    stats: _Stats, faces: PolygonFaces, topo: Topology
) -> tuple[Rows, int | None, list[str]]:
    """The mesh section's rows, the genus (None unless closed, connected, orientable manifold)
    and the topology defects."""
    sizes = faces.sizes.tolist()
    degrees = " ".join(f"{k}:{count}" for k, count in sorted(Counter(sizes).items()))
    report = topo.report
    orientable = report.non_orientable_components == 0
    flags = (report.is_manifold, report.is_oriented, orientable)
    rows: Rows = [
        ("vertices / faces / edges", f"{stats.n} / {faces.num_faces} / {topo.num_edges}"),
        ("face degrees (k:count)", degrees),
        ("boundary edges", str(stats.n_boundary)),
        ("connected components", str(stats.n_comp)),
        ("Euler characteristic", str(stats.chi)),
        ("manifold / oriented / orientable", " / ".join("yes" if ok else "no" for ok in flags)),
    ]
    genus = None
    if stats.n_boundary == 0 and stats.n_comp == 1 and report.is_manifold and orientable:
        genus = (2 - stats.chi) // 2
        rows.append(("genus (closed, orientable)", str(genus)))
    defects = report.lines(stats.n)
    rows += [("topology defect", line) for line in defects]
    if defects:
        rows.append(
            (
                "repairs (L and M0 need none)",
                "torch_polylap.repair: orient_faces, remove_duplicate_faces, ...",
            )
        )
    polys = stats.polys
    if polys.numel():
        rows.append(
            (
                "non-planarity max / median",
                f"{float(polys.max()):.2e} / {float(polys.median()):.2e}  (height / diameter)",
            )
        )
    rows.append(("total area", f"{float(stats.areas.sum()):.6g}"))
    return rows, genus, defects


def _operator_rows(stats: _Stats, L: torch.Tensor) -> tuple[Rows, int | None]:
    """The operator section's rows and the number of zero eigenvalues (None without them)."""
    Ls, mass, areas, evals = stats.Ls, stats.mass, stats.areas, stats.evals
    scale = abs(Ls).max()
    asym = abs(Ls - Ls.T).max() / scale
    rowsum = np.abs(np.asarray(Ls.sum(1))).max() / scale
    rows: Rows = [
        ("L: size / nonzeros", f"{L.shape[0]} x {L.shape[1]} / {Ls.nnz}"),
        ("L symmetry |L - L^T| / max|L|", f"{asym:.1e}"),
        ("L row sums / max|L|", f"{rowsum:.1e}"),
        ("M0: sum - total area", f"{float(mass.sum() - areas.sum()):.1e}"),
        ("M0: min mass", f"{float(mass.min()):.3e}"),
    ]
    zero = None
    if evals is not None:
        zero = int((np.abs(evals) < 1e-8 * max(1.0, abs(evals).max())).sum())
        rows += [
            (
                f"smallest {len(evals)} eigenvalues of L = mu M0",
                np.array2string(evals, precision=4, max_line_width=1 << 16),
            ),
            ("zero eigenvalues / components", f"{zero} / {stats.n_comp}"),
        ]
    else:
        rows.append(("eigenvalues of L = mu M0", f"not computed: {stats.no_evals}"))
    return rows, zero


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
