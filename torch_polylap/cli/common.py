"""What every ``polylap`` command shares: the command protocol (:class:`Result`,
:func:`execute`), mesh and output arguments, output files, tables. Timing helpers are in
:mod:`torch_polylap.timing`."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np
import torch

from ..atomic import atomic_write
from ..data import DEFAULT_MESH
from ..faces import PolygonFaces
from ..io import read_mesh, write_mesh
from ..topology import Topology, get_topology

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DEFAULT_OUTPUT = "polylap_out"


Rows = list[tuple[str, str]]


# resolution of the figures (that of torch_polylap.plot.save_figure)
FIGURE_DPI = 110


@dataclass
class Output:
    """A file a command writes: its name in the output directory and its content, either
    ``fill`` or ``mesh``.

    Every output is written atomically (:func:`~torch_polylap.atomic.atomic_write`): into a
    temporary next to the target, fsynced, then moved onto it, so that an error, Ctrl-C or
    ``kill`` mid-write leaves the previous file and no temporary.

    Attributes:
        name: the file name in the output directory.
        fill: writes the content into an open binary file (the temporary).
        mesh: ``(verts, faces)`` for :func:`~torch_polylap.io.write_mesh`, which writes the
            format of the name's extension atomically itself.
    """

    name: str
    fill: Callable[[BinaryIO], object] | None = None
    mesh: tuple[torch.Tensor, PolygonFaces] | None = None

    def __post_init__(self) -> None:
        if (self.fill is None) == (self.mesh is None):
            raise TypeError(f"Output {self.name!r}: give exactly one of fill and mesh.")

    def write(self, path: Path) -> None:
        """Replace ``path`` by this output, all or nothing."""
        if self.mesh is not None:
            write_mesh(path, *self.mesh)
        else:
            assert self.fill is not None  # __post_init__
            atomic_write(path, self.fill)


def mesh_output(name: str, verts: torch.Tensor, faces: PolygonFaces) -> Output:
    """An :class:`Output` writing a mesh (format from the extension of ``name``)."""
    return Output(name, mesh=(verts, faces))


def figure_output(name: str, draw: Callable[[], Figure]) -> Output:
    """An :class:`Output` writing the figure ``draw()`` returns (format from the extension of
    ``name``, drawn only when the file is written)."""
    fmt = Path(name).suffix.lstrip(".") or "png"
    return Output(name, fill=lambda f: draw().savefig(f, format=fmt, dpi=FIGURE_DPI))


def text_output(name: str, text: Callable[[], str]) -> Output:
    """An :class:`Output` writing the UTF-8 text ``text()`` returns when the file is written."""
    return Output(name, fill=lambda f: f.write(text().encode("utf-8")))


@dataclass
class Result:
    """What a command computed, before anything is printed or written.

    ``title`` and ``rows`` (``(label, value)``) form the summary table; ``sections`` are
    further titled tables, ``text`` is printed after them and ``warnings`` go to stderr.
    ``outputs`` are the files to write (deferred until :meth:`write`, which records the paths
    in ``files``); ``data`` holds the machine-readable values (JSON reports, tests); ``parts``
    are the results of sub-commands (``polylap demo``), printed and written first.
    """

    title: str
    rows: Rows = field(default_factory=list)
    sections: list[tuple[str, Rows]] = field(default_factory=list)
    text: str = ""
    warnings: list[str] = field(default_factory=list)
    outputs: list[Output] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)
    parts: list[Result] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)

    def write(self, out: Path) -> list[Path]:
        """Write the parts' outputs, then this result's, into ``out``; the paths written."""
        written = [path for part in self.parts for path in part.write(out)]
        for output in self.outputs:
            path = out / output.name
            output.write(path)
            self.files.append(path)
        return written + self.files

    def print(self) -> None:
        """The parts, the title and tables, the text and the files written (stdout); the
        warnings (stderr)."""
        for part in self.parts:
            part.print()
        print_table(self.title, self.rows)
        for heading, rows in self.sections:
            print_table(heading, rows)
        if self.text:
            print(self.text)
        for message in self.warnings:
            print(f"warning: {message}", file=sys.stderr)
        for path in self.files:
            print(f"wrote {path}")


def execute(compute: Callable[[argparse.Namespace], Result], args: argparse.Namespace) -> int:
    """The ``run`` of every command: check (and create) the output directory before the work,
    ``compute``, write the outputs, print; exit status 0."""
    out = output_dir(args) if writes_files(args) else None
    result = compute(args)
    if result.outputs or result.parts:
        result.write(out if out is not None else output_dir(args))
    result.print()
    return 0


def json_output(name: str, data: dict[str, Any]) -> Output:
    """An :class:`Output` writing ``data`` as indented JSON."""
    return text_output(name, lambda: json.dumps(data, indent=2) + "\n")


def add_command(sub: argparse._SubParsersAction, module: ModuleType) -> argparse.ArgumentParser:
    """Register the command of ``module`` (one of this package, following the command protocol
    of :mod:`torch_polylap.cli`) under the module's name: ``SUMMARY`` is its line in ``polylap
    --help``, ``DESCRIPTION`` its help text, ``MESH`` (default :data:`DEFAULT_MESH`; ``None``:
    no mesh argument) the mesh it falls back to, and ``add_arguments(parser)`` adds its own
    options. Returns the subparser."""
    name = module.__name__.rpartition(".")[2]
    parser: argparse.ArgumentParser = sub.add_parser(
        name, help=module.SUMMARY, description=module.DESCRIPTION
    )
    mesh = getattr(module, "MESH", DEFAULT_MESH)
    if mesh is not None:
        add_mesh_argument(parser, default=mesh)
    module.add_arguments(parser)
    return parser


def finish_command(
    parser: argparse.ArgumentParser,
    run: Callable[[argparse.Namespace], int],
    compute: Callable[[argparse.Namespace], Result],
    **output: Any,
) -> None:
    """The options every command ends with (:func:`add_output_arguments`, given ``output``) and
    the protocol defaults ``func=run``, ``compute=compute``."""
    add_output_arguments(parser, **output)
    parser.set_defaults(func=run, compute=compute)


def add_laplacian_arguments(
    parser: argparse.ArgumentParser,
    lam_type: Callable[[str], float] | None = None,
    lam_help: str = "stabilizer weight (default 1)",
) -> None:
    """``--lam`` (default 1; ``lam_type`` checks it, positive by default) and ``--method``: the
    Laplacian the command builds."""
    parser.add_argument(
        "--lam",
        type=lam_type if lam_type is not None else positive_float,
        default=1.0,
        help=lam_help,
    )
    add_method_argument(parser)


def add_mesh_argument(parser: argparse.ArgumentParser, default: Path = DEFAULT_MESH) -> None:
    parser.add_argument(
        "mesh",
        nargs="?",
        help=f"OBJ, OFF or PLY polygon mesh (default: the embedded {default.name})",
    )
    parser.set_defaults(default_mesh=default)


def add_output_arguments(
    parser: argparse.ArgumentParser,
    *,
    plot: bool = True,
    progress: bool = True,
    report: str | None = None,
) -> None:
    """``-o/--output DIR`` (every command), ``--no-plot`` and ``--up`` (commands with a figure),
    ``--no-progress``. ``report``: the command only reports (``info``, ``bench``); it writes
    ``<mesh>_<report>.json`` when given ``-o DIR`` or ``--json``, and nothing otherwise."""
    if report is None:
        parser.add_argument(
            "-o",
            "--output",
            default=DEFAULT_OUTPUT,
            metavar="DIR",
            help=f"directory for the files written (default: ./{DEFAULT_OUTPUT}, created if "
            "needed)",
        )
    else:
        parser.add_argument(
            "-o",
            "--output",
            default=None,
            metavar="DIR",
            help=f"also write the report as <mesh>_{report}.json into DIR (created if needed)",
        )
        parser.add_argument(
            "--json",
            action="store_true",
            help=f"write <mesh>_{report}.json into -o DIR (default: ./{DEFAULT_OUTPUT})",
        )
    if plot:
        parser.add_argument(
            "--no-plot", action="store_true", help="skip the PNG figure (faster, no matplotlib)"
        )
        parser.add_argument(
            "--up",
            choices=("auto", "x", "y", "z"),
            default="auto",
            help="axis drawn vertically in figures (default auto: the thin axis of a flat mesh, "
            "else y as in most OBJ models)",
        )
    if progress:
        parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def writes_files(args: argparse.Namespace) -> bool:
    """Whether the command writes into the output directory: always, except for the reporting
    commands (``info``, ``bench``) without ``-o DIR`` or ``--json``."""
    if not hasattr(args, "json"):
        return True
    return args.output is not None or args.json


def add_method_argument(parser: argparse.ArgumentParser) -> None:
    """``--method {aw11,plms,degoes,diamond}``: which polygon Laplacian the command builds."""
    from ..kernels import METHODS

    parser.add_argument(
        "--method",
        choices=METHODS,
        default="aw11",
        help="polygon Laplacian: aw11 (Alexa & Wardetzky 2011, default), plms (Bunge et al. "
        "2020, ignores --lam), degoes (de Goes et al. 2020) or diamond (Bunge et al. 2021, "
        "ignores --lam; its mass is not diagonal, so commands that need lumped masses refuse it)",
    )


def method_label(args: argparse.Namespace) -> str:
    """The Laplacian of ``args.method`` with its ``lambda`` (none for PLMS), for result tables."""
    method = getattr(args, "method", "aw11")
    from ..kernels import LAM_FREE_METHODS

    if method in LAM_FREE_METHODS:
        return f"{method} (lambda unused)"
    return f"{method}, lambda = {args.lam}"


def positive_float(text: str) -> float:
    value = float(text)
    if not value > 0 or not np.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def load_mesh(
    args: argparse.Namespace,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str = "cpu",
) -> tuple[torch.Tensor, PolygonFaces, Path, str]:
    """``(verts, faces, path, label)`` of the mesh argument or the command's default mesh."""
    path = Path(args.mesh) if args.mesh else args.default_mesh
    verts, faces = read_mesh(path, dtype, device)
    label = path.name + ("" if args.mesh else " (embedded default mesh)")
    return verts, faces, path, label


def load_mesh_topology(
    args: argparse.Namespace,
) -> tuple[torch.Tensor, PolygonFaces, Topology, Path, str]:
    """``(verts, faces, topo, path, label)``: :func:`load_mesh` and the mesh's topology."""
    verts, faces, path, label = load_mesh(args)
    return verts, faces, get_topology(faces, verts.shape[0]), path, label


def plot_outputs(
    args: argparse.Namespace,
    verts: torch.Tensor,
    path: Path,
    suffix: str,
    draw: Callable[[str], Figure],
) -> list[Output]:
    """The figure ``<mesh>_<suffix>.png`` that ``draw(up)`` returns (``up``:
    :func:`up_axis` of ``verts``), or none under ``--no-plot``."""
    if args.no_plot:
        return []
    up = up_axis(args, verts)
    return [figure_output(result_name(path, suffix, ".png"), lambda: draw(up))]


def output_dir(args: argparse.Namespace) -> Path:
    """``-o DIR`` (``./polylap_out`` when not given), created if needed."""
    out = Path(args.output if args.output is not None else DEFAULT_OUTPUT)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output path {out} exists and is not a directory; pass -o DIR.")
    out.mkdir(parents=True, exist_ok=True)
    return out


def result_name(source: Path, suffix: str, ext: str | None = None) -> str:
    """``<source stem>_<suffix><ext>``; ``ext`` defaults to the source mesh's extension."""
    return f"{source.stem}_{suffix}{ext if ext is not None else source.suffix.lower()}"


def up_axis(args: argparse.Namespace, verts: torch.Tensor) -> str:
    """The axis figures draw vertically: ``--up``, or for ``auto`` the thinnest axis of a flat
    mesh (extent under a fifth of the largest), else ``y`` (the OBJ convention)."""
    if args.up != "auto":
        return args.up
    extent = (verts.amax(0) - verts.amin(0)).double()
    thin = int(extent.argmin())
    return "xyz"[thin] if float(extent[thin]) < 0.2 * float(extent.max()) else "y"


def row(label: str, value: object) -> str:
    return f"  {label:<40}{value}"


def print_table(title: str, rows: Iterable[tuple[str, object]]) -> None:
    print(title)
    for label, value in rows:
        print(row(label, value))
