"""``polylap spectrum [MESH]``: the first ``k`` eigenpairs of ``L phi = mu M0 phi``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from ..faces import PolygonFaces
from ..linalg import eigs
from ..operators import laplacian
from ..sparse import to_scipy
from .common import (
    Output,
    Result,
    add_mesh_argument,
    add_method_argument,
    add_output_arguments,
    execute,
    load_mesh,
    method_label,
    positive_float,
    positive_int,
    result_name,
    up_axis,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "spectrum",
        help="the smallest Laplace eigenvalues and eigenfunctions",
        description="Compute the k smallest eigenpairs of the generalized problem "
        "L phi = mu M0 phi (AW11 Laplacian and lumped mass, or those of --method), print the "
        "eigenvalues with their residuals, and draw a few eigenfunctions and the eigenvalue curve.",
    )
    add_mesh_argument(p)
    p.add_argument("-k", type=positive_int, default=20, help="number of eigenpairs (default 20)")
    p.add_argument("--lam", type=positive_float, default=1.0, help="stabilizer weight (default 1)")
    add_method_argument(p)
    p.add_argument(
        "--show", type=positive_int, default=4, help="eigenfunctions in the figure (default 4)"
    )
    p.add_argument(
        "--npz",
        action="store_true",
        help="also write eigenvalues, eigenvectors (columns) and masses to <mesh>_spectrum.npz",
    )
    add_output_arguments(p, progress=False)
    p.set_defaults(func=run, compute=compute)


def compute(args: argparse.Namespace) -> Result:
    verts, faces, path, label = load_mesh(args)
    n = verts.shape[0]
    if args.k >= n:
        raise ValueError(f"-k {args.k} is too large for a mesh with {n} vertices (k < {n}).")
    start = time.perf_counter()
    L, M0 = laplacian(verts, faces, args.lam, method=args.method)
    t_assembly = time.perf_counter() - start
    start = time.perf_counter()
    evals, evecs = eigs(L, M0, args.k)
    t_eigs = time.perf_counter() - start

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
        ("assembly / eigs", f"{t_assembly * 1e3:.1f} ms / {t_eigs * 1e3:.1f} ms"),
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
        data={"eigenvalues": values, "residual": rel_residual, "orthonormality": ortho},
    )
    if args.npz:

        def write_npz(npz: Path) -> None:
            np.savez(
                npz,
                eigenvalues=evals.numpy(),
                eigenvectors=evecs.numpy(),
                mass=mass,
                lam=args.lam,
                method=args.method,
            )

        result.outputs.append(Output(result_name(path, "spectrum", ".npz"), write_npz))
    if not args.no_plot:
        up = up_axis(args, verts)
        result.outputs.append(
            Output(
                result_name(path, "spectrum", ".png"),
                lambda png: _figure(verts, faces, evals, evecs, args.show, up, png),
            )
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
    png: Path,
) -> None:
    from ..plot import new_figure, plot_lines, plot_mesh, save_figure

    # skip the constant eigenfunction (mu_0 = 0) when there is more than one pair
    first = 1 if evals.numel() > 1 else 0
    picks = list(range(first, min(first + show, evals.numel())))
    fig, axes = new_figure(1, len(picks) + 1, [True] * len(picks) + [False], panel_size=3.2)
    for ax, i in zip(axes, picks, strict=False):
        phi = evecs[:, i]
        bound = float(phi.abs().max())
        plot_mesh(
            verts,
            faces,
            phi,
            ax=ax,
            title=f"phi_{i}, mu = {float(evals[i]):.4g}",
            cmap="RdBu_r",
            clim=(-bound, bound),
            colorbar=False,
            up=up,
        )
    idx = np.arange(evals.numel())
    plot_lines(
        {"mu_i": (idx, evals)},
        ax=axes[-1],
        title="eigenvalues of L phi = mu M0 phi",
        xlabel="i",
        ylabel="mu_i",
    )
    save_figure(fig, png)
