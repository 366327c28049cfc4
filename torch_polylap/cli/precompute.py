"""``polylap precompute INPUT... --cache DIR``: fill a dataset's eigenpair cache.

The files and folders given (folders searched recursively for ``.obj``, ``.off`` and ``.ply``)
go through :func:`torch_polylap.datasets.precompute` on a local process pool (``--workers N``)
or on a running Dask cluster (``--scheduler ADDRESS``). The entries are those
:class:`~torch_polylap.datasets.PolygonMeshDataset` reads with the same ``k``, ``--method`` and
``--lam`` (meshes normalized to unit area). Meshes already cached are verified and skipped, so
running the command again after it was killed computes only what is missing.

Exit status: 0 when every mesh is cached, 1 when some failed (each named on stderr with its
reason), 2 for bad arguments; Ctrl-C: one line and 130, every entry whole (atomic writes).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from concurrent.futures import Executor
from contextlib import contextmanager
from pathlib import Path

from ..data import DEFAULT_MESH
from ..datasets import precompute
from ..datasets.jobs import local_executor
from .common import Result, add_laplacian_arguments, positive_int, print_table

SUMMARY = "fill a dataset's eigenpair cache from mesh files, here or on a Dask cluster"
MESH = None  # no mesh argument
DESCRIPTION = (
    "Compute the k smallest eigenpairs of every mesh file given (folders are searched "
    "recursively for .obj, .off and .ply) into the cache folder that PolygonMeshDataset "
    "(cache_dir=DIR) reads. Meshes already cached are checked and skipped, so a run that was "
    "interrupted or killed resumes. Runs on a local process pool (--workers) or on a running "
    "Dask scheduler (--scheduler, needs pip install 'torch_polylap[distributed]'). Exit status "
    "0 when every mesh is cached, 1 when some failed."
)

MESH_SUFFIXES = (".obj", ".off", ".ply")


def add_arguments(p: argparse.ArgumentParser) -> None:
    # no INPUT: the embedded default mesh, as every other command runs on it
    p.add_argument(
        "inputs",
        nargs="*",
        type=Path,
        metavar="INPUT",
        default=[DEFAULT_MESH],
        help="mesh files and folders of meshes (default: the embedded default mesh)",
    )
    # -o/--output: the option every command writes its files to; here the files are entries
    p.add_argument(
        "--cache",
        "-o",
        "--output",
        dest="output",
        metavar="DIR",
        help="the cache folder (required; created if needed)",
    )
    p.add_argument(
        "-k", "--k", type=positive_int, default=32, help="eigenpairs per mesh (default 32)"
    )
    add_laplacian_arguments(p)
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=positive_int,
        metavar="N",
        help="local worker processes, one torch thread each (default: one per core)",
    )
    where.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="address of a running Dask scheduler (tcp://host:8786); its workers must see the "
        "mesh files and the cache folder at the same paths",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object (computed, reused, failed, replaced, seconds, failures) as "
        "the last line of stdout instead of the summary table",
    )
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run, compute=compute)


def mesh_files(inputs: list[Path]) -> list[Path]:
    """The files of ``inputs``: files as given, folders searched recursively for mesh files
    (sorted); each path once.

    Raises:
        FileNotFoundError: an input does not exist.
        ValueError: no input, or no mesh file in them.
    """
    if not inputs:
        raise ValueError("give at least one mesh file or folder (INPUT...).")
    found: dict[Path, None] = {}
    for path in inputs:
        if path.is_dir():
            for file in sorted(path.rglob("*")):
                if file.suffix.lower() in MESH_SUFFIXES and file.is_file():
                    found[file] = None
        elif path.exists():
            found[path] = None
        else:
            raise FileNotFoundError(f"{path}: no such file or folder")
    if not found:
        listed = ", ".join(str(p) for p in inputs)
        raise ValueError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) in {listed}.")
    return list(found)


@contextmanager
def _executor(args: argparse.Namespace) -> Iterator[Executor]:
    """The local pool of ``--workers``, or the executor of a client of ``--scheduler``."""
    if args.scheduler is None:
        with local_executor(args.workers) as pool:
            yield pool
        return
    from distributed import Client  # the optional extra: a clear message when it is missing

    with Client(args.scheduler, timeout="30s") as client:
        yield client.get_executor()


def compute(args: argparse.Namespace) -> Result:
    if args.output is None:
        raise ValueError("give the cache folder with --cache DIR.")
    cache = Path(args.output)
    files = mesh_files(list(args.inputs))
    with _executor(args) as pool:
        report = precompute(
            files,
            cache,
            k=args.k,
            method=args.method,
            lam=args.lam,
            executor=pool,
            progress=not args.no_progress,
        )
    where = args.scheduler or f"{args.workers or 'one per core'} local workers"
    rows = [
        ("meshes", str(len(files))),
        ("computed / reused / failed", f"{report.computed} / {report.reused} / {report.failed}"),
        ("damaged entries replaced", str(report.replaced)),
        ("cache", str(cache)),
        ("k / Laplacian", f"{args.k} / {args.method}, lambda = {args.lam}"),
        ("workers", where),
        ("seconds", f"{report.seconds:.1f}"),
    ]
    warnings = [f"{f.item}: {f.reason}" for f in report.failures]
    return Result("polylap precompute", rows, warnings=warnings, data=report.to_dict())


def run(args: argparse.Namespace) -> int:
    result = compute(args)
    for message in result.warnings:
        print(f"failed: {message}", file=sys.stderr)
    if args.json:
        print(json.dumps(result.data))
    else:
        print_table(result.title, result.rows)
    return 0 if result.data["failed"] == 0 else 1
