"""The ``polylap`` command: one subcommand per module of this package.

``info`` (mesh and operator statistics), ``smooth`` (mean-curvature flow), ``param`` (conformal
parameterization), ``planarize`` (face planarization), ``spectrum`` (Laplace eigenpairs),
``bench`` (timings against scipy) and ``demo`` (all applications, with a Markdown report).
Every command takes an optional mesh path (OBJ, OFF or PLY) and falls back to an embedded mesh,
and takes ``-o DIR``: ``smooth``, ``param``, ``planarize``, ``spectrum`` and ``demo`` write
there (default ``./polylap_out``), ``info`` and ``bench`` write their report as JSON there
when given ``-o DIR`` (or ``--json``, to ``./polylap_out``). Bad files and arguments end the
command with one ``polylap: error: ...`` line on stderr and exit status 2; set
``POLYLAP_DEBUG=1`` to see the traceback of an unexpected error instead.

The command protocol: every command module has

- ``add_parser(sub)``: its subparser, with ``func=run`` and ``compute=compute`` as defaults;
- ``compute(args) -> Result``: the work; reads the mesh, writes no file and prints no result
  (a progress bar at most), returning the summary table, the machine-readable values and the
  files to write (:class:`.common.Result`, :class:`.common.Output`);
- ``run(args) -> int``: ``execute(compute, args)`` (:func:`.common.execute`), which checks the
  output directory first, then computes, writes the files and prints the summary.

``demo`` composes the other commands through their ``compute``. Timings (``info``, ``bench``)
pin torch to ``--threads N`` threads, 1 by default (:mod:`.timing`).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

import torch

from .. import __version__
from . import bench, demo, info, param, planarize, smooth, spectrum
from .common import DEFAULT_MESH

__all__ = ["main", "build_parser", "DEFAULT_MESH"]

COMMANDS = (info, smooth, param, planarize, spectrum, bench, demo)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (its default prints the whole usage block first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="polylap",
        description="Alexa-Wardetzky polygon Laplacians in PyTorch: inspect meshes and operators, "
        "run the applications of the paper on your own meshes.",
        epilog="Run 'polylap COMMAND --help' for the options of a command. Without a command, "
        "'polylap' runs 'info' on the embedded mesh. Files go to ./polylap_out unless -o DIR "
        "(info and bench write a JSON report only with -o DIR or --json).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--threads",
        type=int,
        metavar="N",
        help="torch CPU threads (default: torch's choice, except for the timings of info and "
        "bench, which run on 1 unless N is given). On a busy machine small meshes run much "
        "faster with 1: every tiny parallel kernel otherwise waits for descheduled threads",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args([*argv, "info"])
    try:
        if args.threads is not None:
            if args.threads < 1:
                raise ValueError(f"--threads must be at least 1, got {args.threads}.")
            torch.set_num_threads(args.threads)
        return args.func(args)
    except (ValueError, OSError) as err:
        # bad input: a file that is missing or malformed, a mesh the operators reject
        print(f"polylap: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("polylap: interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        if os.environ.get("POLYLAP_DEBUG"):
            raise
        print(
            f"polylap: internal error: {type(err).__name__}: {_one_line(err)} "
            "(set POLYLAP_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 1


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())
