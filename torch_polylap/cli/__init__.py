"""The ``polylap`` command: one subcommand per module of this package.

``info`` (mesh and operator statistics), ``smooth`` (mean-curvature flow), ``param`` (conformal
parameterization), ``planarize`` (face planarization), ``spectrum`` (Laplace eigenpairs),
``precompute`` (a dataset's eigenpair cache, from folders of meshes, locally or on a Dask
cluster), ``bench`` (timings against scipy) and ``demo`` (all applications, with a Markdown
report). Every command but ``precompute`` takes an optional mesh path (OBJ, OFF or PLY) and
falls back to an embedded mesh, and takes ``-o DIR``: ``smooth``, ``param``, ``planarize``,
``spectrum`` and ``demo`` write there (default ``./polylap_out``), ``info`` and ``bench`` write
their report as JSON there when given ``-o DIR`` (or ``--json``, to ``./polylap_out``). Bad
files and arguments end the command with one ``polylap: error: ...`` line on stderr and exit
status 2; set ``POLYLAP_DEBUG=1`` to see the traceback of an unexpected error instead. Ctrl-C
ends it with ``polylap: interrupted`` and status 130, SIGTERM and SIGHUP with ``polylap:
terminated (SIGTERM)`` and ``128 + signal`` (:mod:`.interrupts`); every file is written
atomically (:class:`.common.Output`), so an interrupted command leaves the previous file and no
temporary.

Every command runs with torch pinned to ``--threads N`` intra-op threads, 1 by default (``0``:
torch's own default, see :func:`torch_polylap.timing.pinned_threads`).

The command protocol: every command module has

- ``SUMMARY``, ``DESCRIPTION`` and optionally ``MESH`` (the fallback mesh; ``None`` for no mesh
  argument): how :func:`.common.add_command` registers it under the module's name;
- ``add_arguments(parser)``: its options, with ``func=run`` and ``compute=compute`` as
  defaults;
- ``compute(args) -> Result``: the work; reads the mesh, writes no file and prints no result
  (a progress bar at most), returning the summary table, the machine-readable values and the
  files to write (:class:`.common.Result`, :class:`.common.Output`);
- ``run(args) -> int``: ``execute(compute, args)`` (:func:`.common.execute`), which checks the
  output directory first, then computes, writes the files and prints the summary.

``demo`` composes the other commands through their ``compute``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from .. import __version__
from ..timing import DEFAULT_THREADS, pinned_threads
from . import bench, demo, info, param, planarize, precompute, smooth, spectrum
from .common import DEFAULT_MESH, add_command
from .interrupts import Terminated, ignore_signals, signals_as_exceptions

__all__ = ["main", "build_parser", "DEFAULT_MESH"]

COMMANDS = (info, smooth, param, planarize, spectrum, precompute, bench, demo)


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (its default prints the whole usage block first)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


THREADS_HELP = (
    "torch CPU threads for the whole command (default {default}; 0: torch's own default, "
    "OMP_NUM_THREADS or the number of cores). The sparse kernels of these commands gain little "
    "from more threads, and on a busy machine every parallel kernel waits for its descheduled "
    "threads"
)


def thread_count(text: str) -> int:
    """``--threads N``: a whole number, 0 or more."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of threads (0 for torch's default), got {text!r}"
        )
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="polylap",
        description="Alexa-Wardetzky polygon Laplacians in PyTorch: inspect meshes and operators, "
        "run the applications of the paper on your own meshes.",
        epilog="Run 'polylap COMMAND --help' for the options of a command. Without a command, "
        "'polylap' runs 'info' on the embedded mesh. Files go to ./polylap_out unless -o DIR "
        "(info and bench write a JSON report only with -o DIR or --json); each is written "
        "whole or not at all. Ctrl-C ends a command with exit status 130 and leaves every "
        "file as it was.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    threads_help = THREADS_HELP.format(default=DEFAULT_THREADS)
    parser.add_argument("--threads", type=thread_count, metavar="N", help=threads_help)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in COMMANDS:
        add_command(sub, module)
    for _name, command in sub.choices.items():
        # SUPPRESS: given after the command it overrides the one before; absent it leaves it
        command.add_argument(
            "--threads",
            type=thread_count,
            metavar="N",
            default=argparse.SUPPRESS,
            help=threads_help,
        )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``polylap`` with ``argv`` (default ``sys.argv[1:]``); the exit status."""
    with signals_as_exceptions():
        try:
            return _run(list(sys.argv[1:] if argv is None else argv))
        except KeyboardInterrupt:
            return _end("interrupted", 130)
        except Terminated as ended:
            return _end(f"terminated ({ended.name})", 128 + ended.signum)


# module -> the extra of setup.py that installs it
OPTIONAL_EXTRAS = {
    "matplotlib": "plot",
    "mpl_toolkits": "plot",
    "cholespy": "cholmod",
    "igl": "bench",
    "distributed": "distributed",
    "dask": "distributed",
}


def _run(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args([*argv, "info"])
    try:
        with pinned_threads(args.threads):
            return int(args.func(args))
    except (ValueError, OSError) as err:
        # bad input: a file that is missing or malformed, a mesh the operators reject, an output
        # folder that cannot be written
        print(f"polylap: error: {_one_line(err)}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as err:
        extra = OPTIONAL_EXTRAS.get((err.name or "").split(".")[0])
        if extra is None:
            raise
        # an optional dependency of this command (a plain `pip install` has none of them)
        print(
            f"polylap: error: `polylap {args.command}` needs the optional package "
            f"{err.name!r}: pip install 'torch_polylap[{extra}]'",
            file=sys.stderr,
        )
        return 2
    except Exception as err:
        if os.environ.get("POLYLAP_DEBUG"):
            raise
        print(
            f"polylap: internal error: {type(err).__name__}: {_one_line(err)} "
            "(set POLYLAP_DEBUG=1 for the traceback)",
            file=sys.stderr,
        )
        return 1


def _end(message: str, status: int) -> int:
    """One line for a command ended by a signal (its files were left as they were)."""
    ignore_signals()
    _close_progress_bars()
    try:
        print(f"polylap: {message}", file=sys.stderr)
    except OSError:  # SIGHUP: the terminal may be gone
        pass
    return status


def _close_progress_bars() -> None:
    """Close the progress bars an interruption left open (they close on their own only when
    garbage collected, after the message, which would land at the end of the bar's line)."""
    tqdm = sys.modules.get("tqdm")
    if tqdm is None:
        return
    for bar in list(getattr(tqdm.tqdm, "_instances", ())):
        try:
            bar.close()
        except Exception:  # a bar half torn down by the interruption: the message matters more
            pass


def _one_line(err: BaseException) -> str:
    return " ".join(str(err).split())
