"""``polylap spectrum [MESH]``: the first ``k`` eigenpairs of ``L phi = mu M0 phi``."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, BinaryIO

import numpy as np
import torch

from ..faces import PolygonFaces
from ..linalg import eigs
from ..sparse import to_scipy
from ..timing import timed
from .common import (
    Output,
    Result,
    add_laplacian_arguments,
    execute,
    finish_command,
    load_mesh,
    method_label,
    plot_outputs,
    positive_int,
    result_name,
)
from .timing import FIRST_ASSEMBLY, first_assembly

if TYPE_CHECKING:
    from matplotlib.figure import Figure


SUMMARY = "the smallest Laplace eigenvalues and eigenfunctions"
DESCRIPTION = (
    "Compute the k smallest eigenpairs of the generalized problem "
    "L phi = mu M0 phi (AW11 Laplacian and lumped mass, or those of --method), print the "
    "eigenvalues with their residuals, and draw a few eigenfunctions and the eigenvalue curve."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-k", type=positive_int, default=20, help="number of eigenpairs (default 20)")
    add_laplacian_arguments(p)
    p.add_argument(
        "--show", type=positive_int, default=4, help="eigenfunctions in the figure (default 4)"
    )
    p.add_argument(
        "--npz",
        action="store_true",
        help="also write eigenvalues, eigenvectors (columns) and masses to <mesh>_spectrum.npz",
    )
    finish_command(p, run, compute, progress=False)


def compute(args: argparse.Namespace) -> Result:
    verts, faces, path, label = load_mesh(args)
    n = verts.shape[0]
    if args.k >= n:
        raise ValueError(f"-k {args.k} is too large for a mesh with {n} vertices (k < {n}).")
    t_assembly, _, (L, M0) = first_assembly(verts, faces, args.lam, args.method)
    t_eigs, (evals, evecs) = timed(lambda: eigs(L, M0, args.k), 1)

    # checks a reader can trust: residual of each pair and M0-orthonormality
    residual = L @ evecs - (M0 @ evecs) * evals
    mass = to_scipy(M0).diagonal()
    scale = float(to_scipy(L).diagonal().max())
    rel_residual = float(residual.abs().max()) / scale
    gram = evecs.T @ (M0 @ evecs)
    ortho = float((gram - torch.eye(args.k, dtype=gram.dtype)).abs().max())

    rows = [
        ("vertices / faces", f"{n} / {faces.num_faces}"),
        ("lambda / k", f"{args.lam} / {args.k}"),
        ("Laplacian", method_label(args)),
        (FIRST_ASSEMBLY, f"{t_assembly * 1e3:.2f} ms"),
        ("eigs", f"{t_eigs * 1e3:.1f} ms"),
        ("torch threads", str(torch.get_num_threads())),
        ("max |L phi - mu M0 phi| / max L_ii", f"{rel_residual:.1e}"),
        ("max |Phi^T M0 Phi - I|", f"{ortho:.1e}"),
    ]
    values = evals.tolist()
    lines = ["eigenvalues mu_i"] + [
        "  " + "  ".join(f"{j:>3}: {v:<12.6g}" for j, v in enumerate(values[i : i + 5], i))
        for i in range(0, len(values), 5)
    ]
    result = Result(
        f"polylap spectrum: {label}",
        rows,
        text="\n".join(lines),
        data={
            "eigenvalues": values,
            "residual": rel_residual,
            "orthonormality": ortho,
            "threads": torch.get_num_threads(),
            "timings_s": {"first_assembly": t_assembly, "eigs": t_eigs},
        },
    )
    if args.npz:

        def write_npz(npz: BinaryIO) -> None:
            np.savez(
                npz,
                eigenvalues=evals.numpy(),
                eigenvectors=evecs.numpy(),
                mass=mass,
                lam=args.lam,
                method=args.method,
            )

        result.outputs.append(Output(result_name(path, "spectrum", ".npz"), fill=write_npz))
    result.outputs += plot_outputs(
        args, verts, path, "spectrum", lambda up: _figure(verts, faces, evals, evecs, args.show, up)
    )
    return result


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)


def _figure(
    verts: torch.Tensor,
    faces: PolygonFaces,
    evals: torch.Tensor,
    evecs: torch.Tensor,
    show: int,
    up: str,
) -> Figure:
    from ..plot import PlotOptions, new_figure, plot_lines, plot_mesh

    # skip the constant eigenfunction (mu_0 = 0) when there is more than one pair
    first = 1 if evals.numel() > 1 else 0
    picks = list(range(first, min(first + show, evals.numel())))
    fig, axes = new_figure(1, len(picks) + 1, three_d=[True] * len(picks) + [False], panel_size=3.2)
    for ax, i in zip(axes, picks, strict=False):
        phi = evecs[:, i]
        bound = float(phi.abs().max())
        plot_mesh(
            verts,
            faces,
            phi,
            ax=ax,
            title=f"phi_{i}, mu = {float(evals[i]):.4g}",
            options=PlotOptions(cmap="RdBu_r", clim=(-bound, bound), colorbar=False, up=up),
        )
    idx = np.arange(evals.numel())
    plot_lines(
        {"mu_i": (idx, evals)},
        ax=axes[-1],
        title="eigenvalues of L phi = mu M0 phi",
        xlabel="i",
        ylabel="mu_i",
    )
    return fig
