"""Thin plate bending on polygon meshes: the lambda sweep (AW11 Fig. 6) and refinement (Fig. 7).

    python examples/plate_bending_study.py [--levels 1 2 3 4 5] [--sweep-level 3] [--out DIR]

A simply supported unit square plate under a uniform load (q = 1, flexural rigidity 1) is solved
with :func:`torch_polylap.apps.plate_bending` on the grid families ``quad``, ``str_hex``
(stretched hexagons), ``triangle`` and ``irr_poly`` (irregular 3- to 9-gons) of the
refinement families in ``--shared DIR`` (its ``grid`` folder) and compared with the Navier series
(:func:`torch_polylap.apps.navier_deflection`) in the relative L2 norm of ``M0``.  ``quad`` and
``triangle`` cover ``[-1/2, 1/2]^2`` and are shifted onto ``[0, 1]^2``; the others already cover
it.  Observed orders are ``log(e_prev / e) / log(h_prev / h)`` with ``h = |V|^-1/2``.

The support is imposed in mixed form (``L_II w = M0 q``, ``L_II u = M0 w``; see
``torch_polylap/apps/plate.py``).  For comparison the study also minimizes the paper's energy
with *all* rows of ``L`` (``u^T L^T M0^-1 L u`` with only ``u_B = 0``): that is a clamped plate
(center deflection 0.00126 q), so it does not converge to the Navier plate.

Writes ``plate_bending.md``, ``plate_lambda_sweep.png``, ``plate_refinement.png`` and
``plate_pointwise_error.png`` to ``examples/output/``.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

import torch_polylap as tp
from torch_polylap.apps import navier_deflection, plate_bending, plate_error

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SHARED = ROOT.parent / "shared" / "data" / "meshes"
FAMILIES = ("quad", "str_hex", "triangle", "irr_poly")
LAMS = (0.0, 0.01, 0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)


def unit_square_mesh(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    verts, faces = tp.read_mesh(path, dtype=torch.float64)
    shift = torch.cat([verts[:, :2].min(0).values, verts.new_zeros(1)])
    return verts - shift, faces


def full_energy_error(verts, faces, reference) -> float:
    """Minimize 1/2 u^T L^T M0^-1 L u - u^T M0 q over u with u_B = 0, keeping every row of L."""
    L, M0 = tp.laplacian(verts, faces, 1.0)
    Ls, m = tp.sparse.to_scipy(L).tocsc(), tp.sparse.to_scipy(M0).diagonal()
    boundary = tp.get_topology(faces, verts.shape[0]).boundary_vertices.numpy()
    inner = np.setdiff1d(np.arange(verts.shape[0]), boundary)
    L_in = Ls[:, inner]
    u = np.zeros(verts.shape[0])
    u[inner] = spla.spsolve((L_in.T @ sp.diags(1 / m) @ L_in).tocsc(), m[inner])
    return float(plate_error(verts, faces, torch.from_numpy(u), reference))


def orders(sizes: list[int], errors: list[float]) -> list[float]:
    return [
        math.log(errors[i - 1] / errors[i]) / math.log(math.sqrt(sizes[i] / sizes[i - 1]))
        for i in range(1, len(errors))
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED)
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--sweep-level", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "examples" / "output")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()

    refinement: dict[str, tuple[list[int], list[float]]] = {}
    clamped: dict[str, list[float]] = {}
    for family in FAMILIES:
        sizes, errors = [], []
        clamped[family] = []
        for level in args.levels:
            verts, faces = unit_square_mesh(args.shared / "grid" / f"{family}_{level}.obj")
            reference = navier_deflection(verts[:, 0], verts[:, 1])
            u = plate_bending(verts, faces, lam=1.0)
            sizes.append(verts.shape[0])
            errors.append(float(plate_error(verts, faces, u, reference)))
            if level <= 3:
                clamped[family].append(full_energy_error(verts, faces, reference))
        refinement[family] = (sizes, errors)

    sweep: dict[str, list[float]] = {}
    pointwise: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # (x, y), |u - u*| at lambda = 1
    for family in FAMILIES:
        verts, faces = unit_square_mesh(args.shared / "grid" / f"{family}_{args.sweep_level}.obj")
        reference = navier_deflection(verts[:, 0], verts[:, 1])
        sweep[family] = []
        for lam in LAMS:
            try:
                u = plate_bending(verts, faces, lam=lam)
                sweep[family].append(float(plate_error(verts, faces, u, reference)))
                if lam == 1.0:
                    pointwise[family] = (verts[:, :2].numpy(), (u - reference).abs().numpy())
            except ValueError:  # a singular system (spurious modes at lambda = 0)
                sweep[family].append(float("nan"))

    lines = [
        "# Thin plate bending: simply supported unit square, uniform load (AW11 sec. 5.4)",
        "",
        "Relative L2 error `sqrt(e^T M0 e / u*^T M0 u*)` against the Navier series; "
        "`examples/plate_bending_study.py` wrote this file. Support in mixed form "
        "(`L_II w = M0 q`, `L_II u = M0 w`); the last column keeps every row of `L` in "
        "`u^T L^T M0^-1 L u` (levels 1-3), which clamps the edge. Observed order: "
        "`log(e_prev / e) / log(h_prev / h)`, `h = |V|^-1/2`; the `irr_poly` levels are "
        "separate meshes of 400-2500 vertices, not nested refinements, so their orders are noisy.",
        "",
        "## Refinement at lambda = 1 (AW11 Fig. 7)",
        "",
        "| family | level | V | L2 error | observed order | all rows of L (a clamped plate) |",
        "|---|---|---|---|---|---|",
    ]
    for family, (sizes, errors) in refinement.items():
        rates = [float("nan"), *orders(sizes, errors)]
        for k, level in enumerate(args.levels):
            full = f"{clamped[family][k]:.3e}" if k < len(clamped[family]) else ""
            lines.append(
                f"| {family} | {level} | {sizes[k]} | {errors[k]:.3e} | {rates[k]:.2f} | {full} |"
            )
    lines += [
        "",
        f"## Lambda sweep at level {args.sweep_level} (AW11 Fig. 6)",
        "",
        "| lambda | " + " | ".join(FAMILIES) + " |",
        "|---|" + "---|" * len(FAMILIES),
    ]
    for k, lam in enumerate(LAMS):
        lines.append(f"| {lam:g} | " + " | ".join(f"{sweep[f][k]:.3e}" for f in FAMILIES) + " |")
    best = {f: LAMS[int(np.nanargmin(sweep[f]))] for f in FAMILIES if f != "triangle"}
    lines += ["", "Best lambda per family: " + ", ".join(f"{f} {b:g}" for f, b in best.items())]
    report = "\n".join(lines) + "\n"
    (args.out / "plate_bending.md").write_text(report)
    print(report)
    plot(refinement, sweep, pointwise, args)
    elapsed = time.perf_counter() - start
    print(f"wrote {args.out / 'plate_bending.md'} and three PNGs in {elapsed:.1f} s")


def plot(refinement, sweep, pointwise, args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for family in FAMILIES:
        ax.semilogy(LAMS[1:], sweep[family][1:], "o-", label=family)
    ax.set_xlabel("lambda")
    ax.set_ylabel("relative L2 error")
    ax.set_title(f"Plate error vs lambda (level {args.sweep_level})")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "plate_lambda_sweep.png", dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for family, (sizes, errors) in refinement.items():
        ax.loglog(np.power(sizes, -0.5), errors, "o-", label=family)
    h = np.array([0.006, 0.06])
    ax.loglog(h, 0.5 * h, "k--", lw=1, label="order 1")
    ax.loglog(h, 5 * h**2, "k:", lw=1, label="order 2")
    ax.set_xlabel("h = |V|^-1/2")
    ax.set_ylabel("relative L2 error")
    ax.set_title("Plate error under refinement (lambda = 1)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "plate_refinement.png", dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(FAMILIES), figsize=(3.2 * len(FAMILIES), 3.4))
    for ax, family in zip(axes, FAMILIES, strict=True):
        xy, err = pointwise[family]
        ax.scatter(xy[:, 0], xy[:, 1], c=err, s=3, cmap="jet", vmin=0.0, linewidths=0)
        ax.set_title(f"{family}: max |u - u*| = {err.max():.1e}", fontsize=8)
        ax.set_aspect("equal")
        ax.set_axis_off()
    fig.suptitle(f"Pointwise error, lambda = 1, level {args.sweep_level} (red: largest)")
    fig.tight_layout()
    fig.savefig(args.out / "plate_pointwise_error.png", dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    main()
