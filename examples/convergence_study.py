"""Convergence of the polygon Laplacians under refinement: AW11, dGBD20 and PLMS side by side.

    python examples/convergence_study.py [--levels 1 2 3 4 5] [--methods aw11 degoes plms]
        [--lam 1] [--lams 0.5 1 2] [--shared DIR] [--out FILE]

On the sphere and grid refinement families in ``--shared DIR`` (levels 1..5), for the
Laplacians of ``tp.laplacian(..., method=...)``: ``"aw11"`` (Alexa and Wardetzky 2011),
``"degoes"`` (dGBD20, de Goes, Butts and Desbrun 2020), both at ``lambda = --lam``, and
``"plms"`` (Bunge et al. 2020, no lambda), each with its own lumped mass ``M0``:

(a) spherical harmonic: ``M0^-1 L Y`` against ``l (l + 1) Y = 12 Y`` for ``Y = Y_3^2`` on the
    normalized spheres, error ``sqrt(e^T M0 e / |V|)``;
(b) mean curvature: ``|M0^-1 L X| / 2`` against 1 on the normalized spheres, RMS over vertices;
(c) Poisson problem on the planar grids: ``L u = -M0 lap(f)`` for Franke's function ``f``,
    Dirichlet boundary ``u = f``, RMS error over vertices (``torch_polylap.dirichlet_solve``);
(d) spectrum: the first 16 eigenvalues of ``L phi = mu M0 phi`` on the normalized spheres
    against ``l (l + 1)`` with multiplicities 1, 3, 5, 7; error = largest relative error of
    eigenvalues 1..15 (``torch_polylap.eigs``).

Each experiment gets one table with the methods as columns, then one with AW11 for every lambda
of ``--lams`` (the lambda study of AW11 sec. 5), and the report ends with the observed orders
between the last two levels. The definitions follow the reference values of the polyLaplace
implementation (reproduced in ``tests/assembly/test_reference_values.py``). Observed orders are
``log(e_prev / e) / log(h_prev / h)`` with ``h = |V|^-1/2``. Writes a Markdown report (default
``examples/output/convergence.md``) and ``convergence.png`` beside it (AW11's errors against
``h``, one panel per experiment).

The experiments are the ones ``tests/assembly/test_reference_values.py`` checks against the
numbers printed by the polyLaplace research code (that test imports them from here; it keeps
its own copy of the published numbers and its own definition of ``Y_3^2``). PLMS's ``M0`` is
this package's, which lumps the fan's Galerkin mass as polyLaplace does.
"""

from __future__ import annotations

import argparse
import functools
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

import torch_polylap as tp

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SHARED = ROOT.parent / "shared" / "data" / "meshes"
SPHERES = ("hex", "quad", "voronoi", "concave", "hex_cos", "hex_noise", "triangle")
METHODS = ("aw11", "degoes", "plms")
TITLES = {"aw11": "AW11", "degoes": "dGBD20", "plms": "PLMS"}
GRIDS = ("quad", "voronoi", "concave", "str_hex", "comp_hex", "irr_poly", "dia_quad", "triangle")


Mass = Callable[[torch.Tensor, tp.PolygonFaces], torch.Tensor]  # (V,) lumped masses


def unit_sphere(verts: torch.Tensor) -> torch.Tensor:
    """The vertices pushed onto the unit sphere (the sphere experiments' first step)."""
    return verts / verts.norm(dim=1, keepdim=True)


def operators(
    verts: torch.Tensor, faces, lam: float, method: str, mass: Mass | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``L`` and the lumped masses ``m`` (``M0``'s diagonal, or ``mass(verts, faces)``)."""
    L, M0 = tp.laplacian(verts, faces, lam, method=method)
    return L, (M0.diagonal() if mass is None else mass(verts, faces))


def y32(p: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonic Y_3^2 with the reference's axes: sqrt(2) K 15 y (z^2 - x^2) / r^3."""
    x, y, z = p.unbind(1)
    k = math.sqrt(7.0 / (4 * math.pi * 120.0))
    return math.sqrt(2.0) * k * 15.0 * y * (z * z - x * x) / p.norm(dim=1) ** 3


def franke_and_laplacian(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Franke's function at raw coordinates and its exact Laplacian.

    Each term is ``c exp(q)`` with ``q`` at most quadratic, so its Laplacian is
    ``c exp(q) (|grad q|^2 + lap q)``.
    """
    terms = (  # c, q, dq/dx, dq/dy, lap q
        (
            0.75,
            -((9 * x - 2) ** 2 + (9 * y - 2) ** 2) / 4,
            -4.5 * (9 * x - 2),
            -4.5 * (9 * y - 2),
            -81.0,
        ),
        (
            0.75,
            -((9 * x + 1) ** 2) / 49 - (9 * y + 1) / 10,
            -18 * (9 * x + 1) / 49,
            -0.9 + 0 * y,
            -162 / 49,
        ),
        (
            0.5,
            -((9 * x - 7) ** 2 + (9 * y - 3) ** 2) / 4,
            -4.5 * (9 * x - 7),
            -4.5 * (9 * y - 3),
            -81.0,
        ),
        (
            -0.2,
            -((9 * x - 4) ** 2) - (9 * y - 7) ** 2,
            -18 * (9 * x - 4),
            -18 * (9 * y - 7),
            -324.0,
        ),
    )
    f = sum(c * torch.exp(q) for c, q, *_ in terms)
    lap = sum(c * torch.exp(q) * (qx * qx + qy * qy + lq) for c, q, qx, qy, lq in terms)
    return f, lap


# The experiments. Each takes the mesh as read (spheres are normalized here), lambda, the
# method of tp.laplacian and optionally a replacement for the lumped masses (tests pass
# polyLaplace's own PLMS mass), and returns the error.


def sh_error(
    verts: torch.Tensor, faces, lam: float = 1.0, method: str = "aw11", mass: Mass | None = None
) -> float:
    """(a) ``e = Y - M0^-1 L Y / 12`` for ``Y = Y_3^2``; ``sqrt(e^T M0 e / |V|)``."""
    verts = unit_sphere(verts)
    L, m = operators(verts, faces, lam, method, mass)
    y = y32(verts)
    e = y - (L @ y) / m / 12.0  # M0^-1 L approximates -lap, and -lap_S Y = 12 Y
    return float((e * m * e).sum() / y.numel()) ** 0.5


def mean_curvature_error(
    verts: torch.Tensor, faces, lam: float = 1.0, method: str = "aw11", mass: Mass | None = None
) -> float:
    """(b) ``c = |M0^-1 L X| / 2`` per vertex against 1: ``sqrt(mean (c - 1)^2)``."""
    verts = unit_sphere(verts)
    L, m = operators(verts, faces, lam, method, mass)
    c = ((L @ verts) / m[:, None]).norm(dim=1) / 2
    return float(((c - 1) ** 2).mean()) ** 0.5


def franke_error(
    verts: torch.Tensor, faces, lam: float = 1.0, method: str = "aw11", mass: Mass | None = None
) -> float:
    """(c) ``L u = -M0 lap(f)`` inside, ``u = f`` on the boundary vertices: RMS of ``u - f``."""
    L, m = operators(verts, faces, lam, method, mass)
    topo = tp.get_topology(faces, verts.shape[0])  # cached with the faces by tp.laplacian
    f, lap = franke_and_laplacian(verts[:, 0], verts[:, 1])
    boundary = topo.boundary_vertices
    u = tp.dirichlet_solve(L, -(m * lap), boundary, f[boundary])
    return float(((u - f) ** 2).mean()) ** 0.5


EXACT_SPECTRUM = torch.tensor([ell * (ell + 1) for ell in range(4) for _ in range(2 * ell + 1)])


def spectrum_error(
    verts: torch.Tensor, faces, lam: float = 1.0, method: str = "aw11", mass: Mass | None = None
) -> float:
    """(d) the first 16 eigenvalues of ``L phi = mu M0 phi`` against ``l (l + 1)``: the largest
    relative error of eigenvalues 1..15."""
    verts = unit_sphere(verts)
    L, m = operators(verts, faces, lam, method, mass)
    evals, _ = tp.eigs(L, tp.sparse.diag(m), 16)
    exact = EXACT_SPECTRUM.to(evals)
    return float(((evals[1:] - exact[1:]).abs() / exact[1:]).max())


Experiment = Callable[..., float]

EXPERIMENTS: dict[str, tuple[str, tuple[str, ...], Experiment]] = {
    "(a) spherical harmonic Y_3^2": ("sphere", SPHERES, sh_error),
    "(b) mean curvature |H|/2 - 1": ("sphere", SPHERES, mean_curvature_error),
    "(c) Franke Poisson problem": ("grid", GRIDS, franke_error),
    "(d) first 16 eigenvalues vs l(l+1)": ("sphere", SPHERES, spectrum_error),
}


def orders(errors: list[float], sizes: list[int]) -> list[float | None]:
    out: list[float | None] = [None]
    for i in range(1, len(errors)):
        ratio_h = math.sqrt(sizes[i] / sizes[i - 1])  # h_prev / h with h = |V|^-1/2
        out.append(math.log(errors[i - 1] / errors[i]) / math.log(ratio_h))
    return out


Column = tuple[str, str, float]  # (header, method, lambda)


@functools.cache
def read(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """``tp.read_mesh``, once per file (the faces object then carries its cached topology)."""
    return tp.read_mesh(path)


def method_columns(methods: list[str], lam: float) -> list[Column]:
    """One column per method, AW11 and dGBD20 at ``lam``; PLMS has no lambda."""
    return [(TITLES[m] if m == "plms" else f"{TITLES[m]} lam = {lam:g}", m, lam) for m in methods]


def lambda_columns(lams: list[float]) -> list[Column]:
    return [(f"lam = {lam:g}", "aw11", lam) for lam in lams]


def _table(
    folder: str,
    families: tuple[str, ...],
    shared: Path,
    levels: list[int],
    columns: list[Column],
    measure: Callable[[Path, Column], float],
    last_orders: dict[tuple[str, str], float | None] | None = None,
) -> list[str]:
    """Markdown rows ``| mesh | level | V | error (order) ... |``; with ``last_orders``, also
    record each column's order between the last two levels under ``(family, header)``."""
    lines = ["| mesh | level | V | " + " | ".join(c[0] for c in columns) + " |"]
    lines.append("|" + " --- |" * (3 + len(columns)))
    for family in families:
        paths = [shared / folder / f"{family}_{level}.obj" for level in levels]
        if not all(p.is_file() for p in paths):
            continue
        sizes = [read(p)[0].shape[0] for p in paths]
        table = []
        for column in columns:
            errors = [measure(p, column) for p in paths]
            table.append(list(zip(errors, orders(errors, sizes), strict=True)))
            if last_orders is not None:
                last_orders[(family, column[0])] = table[-1][-1][1]
        for row, (level, size) in enumerate(zip(levels, sizes, strict=True)):
            cells = [
                f"{e:.3e}" + (f" ({o:.2f})" if o is not None else "")
                for e, o in (column[row] for column in table)
            ]
            lines.append(f"| {folder}/{family} | {level} | {size} | " + " | ".join(cells) + " |")
    return lines


def run(
    shared: Path,
    levels: list[int],
    lams: list[float],
    methods: list[str] | None = None,
    lam: float = 1.0,
    curves: dict[str, dict[str, tuple[list[int], list[float]]]] | None = None,
) -> str:
    """The Markdown report; with ``curves``, also fill ``{experiment: {mesh: (sizes, errors)}}``
    with AW11's errors at ``lam`` over the levels (for :func:`figure`)."""
    methods = list(METHODS if methods is None else methods)
    results: dict[tuple[str, Path, str, float], float] = {}
    by_method = method_columns(methods, lam)
    lines = [
        "# Convergence study",
        "",
        f"Levels {levels}. Error (observed order against h = |V|^-1/2). Per experiment: the "
        f"Laplacians side by side ({', '.join(c[0] for c in by_method)}; each with its own "
        f"lumped mass), then AW11 for lambda in {lams}.",
    ]
    summary: list[str] = []
    for title, (folder, families, fn) in EXPERIMENTS.items():

        def measure(path: Path, column: Column, fn=fn, title=title) -> float:
            key = (title, path, column[1], 0.0 if column[1] == "plms" else column[2])
            if key not in results:
                results[key] = fn(*read(path), column[2], column[1])
            return results[key]

        last: dict[tuple[str, str], float | None] = {}
        lines += ["", f"## {title}", "", f"### Laplacians side by side (lambda = {lam:g})", ""]
        lines += _table(folder, families, shared, levels, by_method, measure, last)
        if curves is not None and "aw11" in methods:
            curves[title] = {}
            for family in families:
                paths = [shared / folder / f"{family}_{level}.obj" for level in levels]
                if all(p.is_file() for p in paths):
                    sizes = [read(p)[0].shape[0] for p in paths]
                    errors = [measure(p, ("", "aw11", lam)) for p in paths]
                    curves[title][f"{family} {folder}"] = (sizes, errors)
        if lams:
            lines += ["", f"### AW11, lambda in {lams}", ""]
            lines += _table(folder, families, shared, levels, lambda_columns(lams), measure)
        if len(levels) > 1:
            summary += ["", f"{title}:", ""]
            summary.append("| mesh | " + " | ".join(c[0] for c in by_method) + " |")
            summary.append("|" + " --- |" * (1 + len(by_method)))
            for family in dict.fromkeys(f for f, _ in last):
                cells = [last[(family, c[0])] for c in by_method]
                summary.append(
                    f"| {family} {folder} | "
                    + " | ".join("-" if o is None else f"{o:.2f}" for o in cells)
                    + " |"
                )
    if summary:
        lines += ["", f"## Observed orders, levels {levels[-2]} to {levels[-1]}"] + summary
    return "\n".join(lines) + "\n"


def figure(curves: dict[str, dict[str, tuple[list[int], list[float]]]], path: Path) -> None:
    """One log-log panel per experiment: AW11's error against h = |V|^-1/2 for every mesh
    family, with first- and second-order slopes for reference (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 4), squeeze=False)
    for ax, (title, families) in zip(axes[0], curves.items(), strict=True):
        h_all = []
        for family, (sizes, errors) in families.items():
            h = [v**-0.5 for v in sizes]
            h_all += h
            ax.loglog(h, errors, marker="o", ms=3, label=family)
        if h_all:
            h0, h1 = min(h_all), max(h_all)
            ref = min(e for _, errs in families.values() for e in errs)
            for order, style in ((1, ":"), (2, "--")):
                ax.loglog([h0, h1], [ref, ref * (h1 / h0) ** order], "k" + style, lw=0.8)
                ax.annotate(f"order {order}", (h1, ref * (h1 / h0) ** order), fontsize=7)
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("h = |V|^-1/2")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, loc="lower right")
    axes[0][0].set_ylabel("error (AW11)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED, help="mesh families folder")
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument(
        "--methods", nargs="+", choices=METHODS, default=list(METHODS), help="Laplacians compared"
    )
    parser.add_argument(
        "--lam", type=float, default=1.0, help="lambda of AW11 and dGBD20 in the comparison"
    )
    parser.add_argument(
        "--lams", type=float, nargs="*", default=[0.5, 1.0, 2.0], help="AW11's lambda study"
    )
    parser.add_argument("--out", type=Path, default=ROOT / "examples" / "output" / "convergence.md")
    args = parser.parse_args()
    if not args.shared.is_dir():
        raise SystemExit(f"mesh families not found at {args.shared}; pass --shared DIR")
    # the shared meshes carry objects and materials the study has no use for
    warnings.simplefilter("ignore", tp.io.SkippedContentWarning)
    start = time.perf_counter()
    curves: dict[str, dict[str, tuple[list[int], list[float]]]] = {}
    report = run(args.shared, args.levels, args.lams, args.methods, args.lam, curves)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    png = args.out.with_suffix(".png")
    if curves:
        figure(curves, png)
        report += f"\n![AW11's errors under refinement]({png.name})\n"
    args.out.write_text(report)
    print(report)
    print(f"wrote {args.out} and {png} in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    main()
