"""``polylap demo``: the four applications of AW11 sec. 5 on small embedded meshes, one report.

Mean-curvature flow (sec. 5.1) and planarization (sec. 5.3) on the Spot cage, conformal
parameterization (sec. 5.2) on a hexagonal hemisphere, thin-plate bending (sec. 5.4) on a
Voronoi polygon grid of the unit square against Navier's series solution. Writes every result
mesh and figure plus ``report.md`` (Markdown, figures linked by relative path) into ``-o DIR``.
"""

from __future__ import annotations

import argparse
import datetime
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch

from .. import __version__
from ..data import PLATE_MESH
from ..faces import PolygonFaces
from ..io import read_mesh
from ..timing import markdown_table
from ..topology import get_topology
from . import param, planarize, smooth
from .common import (
    DEFAULT_OUTPUT,
    Result,
    add_command,
    add_method_argument,
    execute,
    figure_output,
    mesh_output,
    text_output,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# (title, AW11 section, command, result, seconds) of one part of the report
_Section = tuple[str, str, str, Result, float]

# (section, AW11 section, the equivalent command line, its arguments)
STEPS = (
    ("Mean-curvature flow", "5.1", ["smooth", "--steps", "10", "--normalize", "area"]),
    ("Conformal parameterization", "5.2", ["param"]),
    ("Planarization", "5.3", ["planarize"]),
)


# the commands with a progress bar of their own
PROGRESS = ("smooth", "planarize")
# the commands that build L and take --method
WITH_METHOD = ("smooth", "param")


SUMMARY = "run all applications on embedded meshes and write a Markdown report"
MESH = None  # no mesh argument
DESCRIPTION = (
    "Run mean-curvature flow, conformal parameterization, planarization and "
    "thin-plate bending (AW11 sec. 5.1-5.4) on small embedded meshes; write the result "
    "meshes, figures and report.md into -o DIR."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-o",
        "--output",
        default=DEFAULT_OUTPUT,
        metavar="DIR",
        help=f"directory for the report and its files (default: ./{DEFAULT_OUTPUT})",
    )
    p.add_argument("--no-plot", action="store_true", help="numbers only, no figures")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_method_argument(p)
    p.set_defaults(func=run, compute=compute)


def compute(args: argparse.Namespace) -> Result:
    from tqdm import tqdm

    parser = _steps_parser()
    common = ["--no-plot"] if args.no_plot else []
    tasks: list[tuple[str, str, str, Callable[[], Result]]] = []
    for title, section, argv in STEPS:
        # the demo's own bar counts the applications; theirs would interleave with it
        quiet = ["--no-progress"] if argv[0] in PROGRESS else []
        if argv[0] in WITH_METHOD and args.method != "aw11":
            argv = [*argv, "--method", args.method]
        sub_args = parser.parse_args([*argv, *common, *quiet])
        tasks.append((title, section, "polylap " + " ".join(argv), _bound(sub_args)))
    tasks.append(
        (
            "Thin-plate bending",
            "5.4",
            "(Python API: torch_polylap.apps.plate_bending)",
            lambda: plate(with_plot=not args.no_plot, method=args.method),
        )
    )
    sections: list[_Section] = []
    start = time.perf_counter()
    for title, section, command, task in tqdm(tasks, desc="demo", disable=args.no_progress):
        t0 = time.perf_counter()
        result = task()
        sections.append((title, section, command, result, time.perf_counter() - t0))

    def report() -> str:
        # written after the parts' meshes and figures: the total includes them
        return _markdown(sections, time.perf_counter() - start)

    return Result(
        "polylap demo: the applications of AW11 sec. 5.1-5.4 on embedded meshes",
        parts=[result for _, _, _, result, _ in sections],
        outputs=[text_output("report.md", report)],
    )


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)


def _steps_parser() -> argparse.ArgumentParser:
    """A parser of the commands that :data:`STEPS` runs, built from their own options
    (the options and defaults of ``polylap``'s, without the package's parser, which holds this
    command too)."""
    parser = argparse.ArgumentParser(prog="polylap")
    sub = parser.add_subparsers(dest="command")
    for module in (smooth, param, planarize):
        add_command(sub, module)
    return parser


def _bound(sub_args: argparse.Namespace) -> Callable[[], Result]:
    return lambda: sub_args.compute(sub_args)


def plate(*, with_plot: bool, method: str = "aw11") -> Result:
    """Simply supported unit-square plate under unit load on a Voronoi polygon mesh, against
    Navier's solution (AW11 sec. 5.4, Fig. 6-7), for three values of lambda, with the Laplacian
    of ``method`` (``"plms"`` ignores lambda: the three errors are equal)."""
    from ..apps.plate import navier_deflection, plate_bending, plate_error

    verts, faces = read_mesh(PLATE_MESH)
    # the polyLaplace grid covers [-1/2, 1/2]^2; Navier's solution is for [0, 1]^2
    verts = verts + torch.tensor([0.5, 0.5, 0.0], dtype=verts.dtype)
    topo = get_topology(faces, verts.shape[0])
    reference = navier_deflection(verts[:, 0], verts[:, 1], load=1.0)
    errors, u, seconds = {}, None, 0.0
    for lam in (0.5, 1.0, 2.0):
        t0 = time.perf_counter()
        u_lam = plate_bending(verts, topo, load=1.0, lam=lam, method=method)
        if lam == 1.0:
            u, seconds = u_lam, time.perf_counter() - t0
        errors[lam] = float(plate_error(verts, topo, u_lam, reference))
    assert u is not None  # set at lam = 1
    deflected = verts.clone()
    deflected[:, 2] = u
    rows = [
        ("mesh", f"{PLATE_MESH.name}: {verts.shape[0]} vertices, {faces.num_faces} polygons"),
        ("load / support", "1 per unit area / simply supported boundary"),
        ("Laplacian", method),
        ("max deflection: ours / Navier", f"{float(u.max()):.6f} / {float(reference.max()):.6f}"),
        (
            "relative L2 error, lambda = 0.5 / 1 / 2",
            " / ".join(f"{errors[lam]:.4f}" for lam in (0.5, 1.0, 2.0)),
        ),
        ("time (lambda = 1)", f"{seconds * 1e3:.1f} ms"),
    ]
    outputs = [mesh_output("plate_deflection.obj", deflected, faces)]
    if with_plot:
        outputs.append(
            figure_output("plate_deflection.png", lambda: _plate_figure(verts, faces, u, reference))
        )
    return Result("polylap demo: thin-plate bending", rows, outputs=outputs)


def _plate_figure(
    verts: torch.Tensor, faces: PolygonFaces, u: torch.Tensor, reference: torch.Tensor
) -> Figure:
    from ..plot import PlotOptions, new_figure, plot_mesh

    fig, (ax1, ax2) = new_figure(1, 2, three_d=True, panel_size=4.5)
    # exaggerate the deflection so that the shape is visible next to the unit square
    shown = verts.clone()
    shown[:, 2] = -u * (0.3 / float(u.max()))
    title = "deflection u (z exaggerated)"
    plot_mesh(shown, faces, u, ax=ax1, title=title, options=PlotOptions(up="z", label="u"))
    style = PlotOptions(
        cmap="RdBu_r", clim=_symmetric(u - reference), up="z", elev=90, azim=-90, label="error"
    )
    plot_mesh(verts, faces, u - reference, ax=ax2, title="u - Navier", options=style)
    return fig


def _symmetric(x: torch.Tensor) -> tuple[float, float]:
    bound = float(x.abs().max()) or 1.0
    return -bound, bound


def _markdown(sections: Sequence[_Section], total: float) -> str:
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# torch_polylap demo",
        "",
        f"torch_polylap {__version__}, torch {torch.__version__}, {now}; total {total:.1f} s. "
        "The applications of Alexa & Wardetzky, *Discrete Laplacians on General Polygonal "
        "Meshes* (SIGGRAPH 2011), section 5, on small meshes embedded in the package.",
        "",
    ]
    for title, section, command, result, seconds in sections:
        lines += [
            f"## {title} (AW11 sec. {section})",
            "",
            f"`{command}` ({seconds:.1f} s)",
            "",
            markdown_table(["quantity", "value"], result.rows),
            "",
        ]
        # the files are written into the report's directory: link them by name
        for output in result.outputs:
            if output.name.endswith(".png"):
                lines += [f"![{title}]({output.name})", ""]
            else:
                lines += [f"Result mesh: `{output.name}`", ""]
    return "\n".join(lines)
