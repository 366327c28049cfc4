"""Helpers every ``polylap`` command shares: mesh arguments, output files, tables, timings."""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..faces import PolygonFaces
from ..io import SkippedContentWarning, read_mesh

DATA_DIR = Path(__file__).resolve().parents[1] / "data"
DEFAULT_MESH = DATA_DIR / "spot_control_mesh.obj"
# a disk (one boundary loop): the default of `polylap param`, which needs a boundary
DISK_MESH = DATA_DIR / "hex_hemisphere.obj"
DEFAULT_OUTPUT = "polylap_out"


@dataclass
class Result:
    """What a command computed: a titled table of ``(label, value)`` rows, free text printed
    after it, and the files written. ``polylap demo`` puts these into its report."""

    title: str
    rows: list[tuple[str, str]]
    files: list[Path] = field(default_factory=list)
    text: str = ""

    def print(self) -> None:
        print_table(self.title, self.rows)
        if self.text:
            print(self.text)
        for path in self.files:
            print(f"wrote {path}")


def mean_edge_length(verts: torch.Tensor, edges: torch.Tensor) -> float:
    """Mean length of the ``(E, 2)`` edges."""
    return float(torch.linalg.vector_norm(verts[edges[:, 0]] - verts[edges[:, 1]], dim=1).mean())


def add_mesh_argument(parser: argparse.ArgumentParser, default: Path = DEFAULT_MESH) -> None:
    parser.add_argument(
        "mesh",
        nargs="?",
        help=f"OBJ, OFF or PLY polygon mesh (default: the embedded {default.name})",
    )
    parser.set_defaults(default_mesh=default)


def add_output_arguments(parser: argparse.ArgumentParser, progress: bool = True) -> None:
    parser.add_argument(
        "-o",
        "--output",
        default=DEFAULT_OUTPUT,
        metavar="DIR",
        help=f"directory for the files written (default: ./{DEFAULT_OUTPUT}, created if needed)",
    )
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


def add_method_argument(parser: argparse.ArgumentParser) -> None:
    """``--method {aw11,plms,degoes}``: which polygon Laplacian the command builds."""
    from ..methods import METHODS

    parser.add_argument(
        "--method",
        choices=METHODS,
        default="aw11",
        help="polygon Laplacian: aw11 (Alexa & Wardetzky 2011, default), plms (Bunge et al. "
        "2020, ignores --lam) or degoes (de Goes et al. 2020)",
    )


def method_label(args: argparse.Namespace) -> str:
    """The Laplacian of ``args.method`` with its ``lambda`` (none for PLMS), for result tables."""
    method = getattr(args, "method", "aw11")
    return f"{method} (lambda unused)" if method == "plms" else f"{method}, lambda = {args.lam}"


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
    args: argparse.Namespace, dtype: torch.dtype = torch.float64
) -> tuple[torch.Tensor, PolygonFaces, Path, str]:
    """``(verts, faces, path, label)`` of the mesh argument or the command's default mesh."""
    path = Path(args.mesh) if args.mesh else args.default_mesh
    verts, faces = read_mesh_quietly(path, not args.mesh, dtype=dtype)
    label = path.name + ("" if args.mesh else " (embedded default mesh)")
    return verts, faces, path, label


def read_mesh_quietly(
    path: Path, embedded: bool, **options: object
) -> tuple[torch.Tensor, PolygonFaces]:
    """``read_mesh``; for the package's embedded meshes without the warning about the texture
    coordinates and materials they carry, which the commands have no use for."""
    with warnings.catch_warnings():
        if embedded:
            warnings.simplefilter("ignore", SkippedContentWarning)
        return read_mesh(path, **options)  # type: ignore[arg-type]


def output_dir(args: argparse.Namespace) -> Path:
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output path {out} exists and is not a directory; pass -o DIR.")
    out.mkdir(parents=True, exist_ok=True)
    return out


def result_path(out: Path, source: Path, suffix: str, ext: str | None = None) -> Path:
    """``out/<source stem>_<suffix><ext>``; ``ext`` defaults to the source mesh's extension."""
    return out / f"{source.stem}_{suffix}{ext if ext is not None else source.suffix.lower()}"


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


def table(header: Sequence[str], body: Sequence[Sequence[object]]) -> str:
    """A Markdown table (readable as plain text too), columns padded to their widest cell."""
    # a "|" inside a cell (|H|) would end it in Markdown
    cells = [[str(c).replace("|", "\\|") for c in r] for r in [header, *body]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = [
        "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in cells
    ]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def timed(fn: Callable[[], object], repeat: int = 3, warmup: bool = False) -> tuple[float, object]:
    """Median wall time of ``repeat`` calls (seconds) and the last result."""
    if warmup:
        fn()
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def fmt_time(seconds: float) -> str:
    if seconds < 1e-3:
        return f"{seconds * 1e6:.0f} us"
    if seconds < 1.0:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"
