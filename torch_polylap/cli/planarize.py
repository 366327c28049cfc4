"""``polylap planarize [MESH]``: make every face planar (AW11 sec. 5.3)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..faces import PolygonFaces
from ..measures import face_nonplanarity
from ..topology import Topology
from .common import (
    Result,
    execute,
    finish_command,
    load_mesh_topology,
    mesh_output,
    plot_outputs,
    positive_float,
    positive_int,
    result_name,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

if TYPE_CHECKING:
    from ..apps.planarize import PlanarizeResult


SUMMARY = "planarize the faces (Gauss-Newton on the face-plane residuals, or L-BFGS on E_plan)"
DESCRIPTION = (
    "Make every face planar (AW11 sec. 5.3) until the largest face "
    "non-planarity (corner distance from the face plane over the face diameter) is below "
    "--tol: Gauss-Newton on the per-face plane residuals (default), or the paper's L-BFGS "
    "descent of E_plan = 1/2 sum_c X_c^T Lplan X_c (--method lbfgs). Stops at --max-iter or "
    "--time-limit and says so. Writes <mesh>_planar.<ext> and a before/after figure colored "
    "by non-planarity."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--lam", type=positive_float, default=2.0, help="lambda (default 2, as AW11)")
    p.add_argument(
        "--tol", type=positive_float, default=1e-4, help="target largest non-planarity (1e-4)"
    )
    p.add_argument(
        "--method",
        choices=("gauss-newton", "lbfgs"),
        default="gauss-newton",
        help="optimizer (default gauss-newton; lbfgs: the paper's quasi-Newton descent)",
    )
    p.add_argument(
        "--max-iter",
        type=positive_int,
        default=None,
        help="iteration limit (default 100 Gauss-Newton solves or 500 L-BFGS iterations)",
    )
    p.add_argument(
        "--time-limit",
        type=positive_float,
        default=60.0,
        help="wall-clock budget of the optimization in seconds (default 60)",
    )
    p.add_argument(
        "--closeness",
        type=float,
        default=0.0,
        help="weight pulling vertices towards the input, in units of the mean edge length "
        "(default 0: only the step damping keeps the result close)",
    )
    finish_command(p, run, compute)


def compute(args: argparse.Namespace) -> Result:
    from ..apps.planarize import PlanarizeOptions, planarize

    verts, faces, topo, path, label = load_mesh_topology(args)
    options = PlanarizeOptions(
        closeness=args.closeness,
        time_limit=args.time_limit,
        progress=not args.no_progress,
        warn=False,
    )
    res = planarize(
        verts,
        topo,
        lam=args.lam,
        tol=args.tol,
        max_iter=args.max_iter,
        method=args.method,
        options=options,
    )
    rows = [
        ("vertices / faces", f"{verts.shape[0]} / {faces.num_faces}"),
        ("method / lambda / tol", f"{res.method} / {args.lam} / {args.tol:g}"),
        (
            "non-planarity max / mean before",
            f"{res.nonplanarity_before[0]:.3e} / {res.nonplanarity_before[1]:.3e}",
        ),
        (
            "non-planarity max / mean after",
            f"{res.nonplanarity_after[0]:.3e} / {res.nonplanarity_after[1]:.3e}",
        ),
        (
            "displacement max / mean (bbox diag)",
            f"{res.displacement[0]:.3e} / {res.displacement[1]:.3e}",
        ),
        ("iterations / time", f"{res.iterations} / {res.seconds:.2f} s"),
        ("converged", "yes" if res.converged else f"no: {res.message}"),
    ]
    outputs = [mesh_output(result_name(path, "planar"), res.verts, faces)]
    outputs += plot_outputs(
        args, verts, path, "planar", lambda up: _figure(verts, faces, topo, res, up)
    )
    return Result(
        f"polylap planarize: {label}",
        rows,
        warnings=[] if res.converged else [res.message],
        outputs=outputs,
    )


def _figure(
    verts: torch.Tensor,
    faces: PolygonFaces,
    topo: Topology,
    res: PlanarizeResult,
    up: str,
) -> Figure:
    """Input and result colored by face non-planarity, and the energy per iteration."""
    from ..plot import PlotOptions, new_figure, plot_lines, plot_mesh

    before = face_nonplanarity(verts, topo)
    after = face_nonplanarity(res.verts, topo)
    fig, axes = new_figure(1, 3, three_d=[True, True, False], panel_size=4.0)
    clim = (0.0, float(before.max()) or 1.0)
    style = PlotOptions(cmap="inferno", clim=clim, up=up, label="non-planarity")
    for ax, x, values, title in (
        (axes[0], verts, before, f"input, max {res.nonplanarity_before[0]:.2e}"),
        (axes[1], res.verts, after, f"planarized, max {res.nonplanarity_after[0]:.2e}"),
    ):
        plot_mesh(x, faces, values, ax=ax, title=title, options=style)
    if res.energies:
        energies = np.maximum(np.asarray(res.energies), np.finfo(float).tiny)
        plot_lines(
            {"E_plan": (np.arange(len(energies)), energies)},
            ax=axes[2],
            title="planarity energy",
            xlabel="iteration",
            logy=True,
            marker="",
        )
    return fig


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
