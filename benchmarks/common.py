"""What the benchmark scripts share: the benchmark grid, the results file with its metadata
header (:func:`run_meta`, :func:`write_results`), the CPU's name, the peak resident memory of one
step (Linux ``/proc``; an upper bound from ``ru_maxrss`` elsewhere), interleaved timing of rival
callables (:func:`interleaved`), and the timing and table helpers of the ``polylap`` command
(median timing, thread pinning, Markdown tables), imported from the package rather than kept here
as a second copy.
Imported by the ``bench_*.py`` scripts (run from this folder, or with it on ``sys.path``).

A results file ``benchmarks/results/<name>.json`` is committed data: ``benchmarks/tables.py``
renders the tables of ``benchmarks/README.md`` from it. Its layout::

    {"benchmark": name, "meta": run_meta(...), "tables": {table: {"columns": [...],
     "rows": [[...], ...]}}, ...further sections of raw numbers}
"""

from __future__ import annotations

import argparse
import ctypes
import datetime
import gc
import importlib.metadata
import json
import os
import platform
import re
import resource
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

# the scripts import the package of the checkout they live in, installed or not
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torch_polylap.timing import (
    DEFAULT_THREADS,
    fmt_time,
    markdown_table,
    median_time,
    pinned_threads,
    synchronizer,
    timed,
)

__all__ = [
    "RESULTS",
    "add_switch",
    "script_parser",
    "bench_grid",
    "cpu_model",
    "run_meta",
    "table_data",
    "table_from_markdown",
    "write_results",
    "interleaved",
    "rss_bytes",
    "reset_peak_rss",
    "trim_heap",
    "peak_rss_growth",
    "DEFAULT_THREADS",
    "fmt_time",
    "markdown_table",
    "median_time",
    "pinned_threads",
    "synchronizer",
    "timed",
]


RESULTS = Path(__file__).resolve().parent / "results"

# distributions whose version a results file records when their module was imported by the run
PEERS = {
    "igl": "libigl",
    "potpourri3d": "potpourri3d",
    "robust_laplacian": "robust-laplacian",
    "lagrange": "adobe-lagrange",
    "cholespy": "cholespy",
    "qdldl": "qdldl",
    "trimesh": "trimesh",
    "plyfile": "plyfile",
    "meshio": "meshio",
    "openmesh": "openmesh",
    "pytorch3d": "pytorch3d",
    "sksparse": "scikit-sparse",
    "pyarrow": "pyarrow",  # the readers' number conversion, when installed (fast-text extra)
}


# environment variables that change what a run measures, recorded with it
ENVIRONMENT = (
    "POLYLAP_SHARED_MESHES",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "CUDA_VISIBLE_DEVICES",
)


def bench_grid(
    n: int,
    m: int | None = None,
    *,
    noise: float = 0.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The benchmarks' quad grid: ``n x m`` quads on the unit square lifted to
    ``z = 0.05 sin(7x) cos(5y)``, so that no quad is planar (the AW11 stabilizer works on every
    face). Built by ``torch_polylap.shapes.quad_grid``; every script takes its grid from here.

    Args:
        n: quads along ``x`` (``n^2`` quads for a square grid: 100, 316, 1000 give 10k, 100k, 1M).
        m: quads along ``y``; ``None`` means ``n``.
        noise: standard deviation of Gaussian noise added to every coordinate (0: none), for
            the scripts that need random variants of the grid.
        seed: seed of that noise.
        dtype: dtype of the vertices.
        device: device of both tensors.

    Returns:
        ``verts`` ``((n + 1) (m + 1), 3)`` and ``faces`` ``(n m, 4)`` int64.
    """
    from torch_polylap.shapes import quad_grid

    verts, faces = quad_grid(n, m, height=lambda x, y: 0.05 * torch.sin(7 * x) * torch.cos(5 * y))
    if noise:
        g = torch.Generator().manual_seed(seed)
        verts = verts + noise * torch.randn(verts.shape, generator=g, dtype=verts.dtype)
    return verts.to(device=device, dtype=dtype), faces.to(device)


def _load() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def _env(name: str) -> str:
    """An environment variable's value; a path relative to the repository (no machine's own
    directories in a committed file)."""
    value = os.environ[name]
    if name == "POLYLAP_SHARED_MESHES":
        return os.path.relpath(value, Path(__file__).resolve().parents[1])
    return value


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def run_meta(argv: Sequence[str] | None = None, threads: int | None = None) -> dict:
    """The metadata header of a results file, taken at the start of a run.

    Records the machine (CPU model from ``/proc/cpuinfo``, cores), OS, the versions of Python,
    torch, numpy, scipy and torch_polylap, torch's thread count, the variables of
    :data:`ENVIRONMENT` that are set, the 1/5/15-minute load average before the run, the UTC
    date and the command line (``argv``, default ``sys.argv``).
    ``threads`` is the thread count the timed code runs with, where the script pins one (default:
    torch's current count).
    :func:`write_results` adds the load average after the run and the peer libraries used.
    """
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        # quoted as a shell needs it ("roof 300x200" is one argument), so it reruns as is
        "command": shlex.join(["python", *(sys.argv if argv is None else argv)]),
        "machine": {"cpu": cpu_model(), "cores": os.cpu_count()},
        "os": platform.platform(),
        "versions": {
            "python": platform.python_version(),
            **{d: _version(d) for d in ("torch", "numpy", "scipy", "torch_polylap")},
        },
        "threads": torch.get_num_threads() if threads is None else threads,
        "environment": {k: _env(k) for k in ENVIRONMENT if k in os.environ},
        "load_before": _load(),
    }


def script_parser(
    doc: str | None, results: str, repeat: int | None = None
) -> argparse.ArgumentParser:
    """The argument parser of a benchmark script: described by the first paragraph of its module
    ``doc``, with ``--json PATH`` (where the results file goes; the script's default is
    ``benchmarks/results/<results>.json``) and, given ``repeat``, ``--repeat N`` (timed samples
    per measurement, default ``repeat``)."""
    parser = argparse.ArgumentParser(description=(doc or "").split("\n\n")[0])
    if repeat is not None:
        parser.add_argument(
            "--repeat", type=int, default=repeat, help=f"timed samples (default {repeat})"
        )
    parser.add_argument("--json", type=Path, help=f"default benchmarks/results/{results}.json")
    return parser


def add_switch(parser: argparse.ArgumentParser, flag: str, help: str) -> None:
    """``flag`` and ``--no-<flag>``, on by default: the parts of a run that can be skipped."""
    parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=True, help=help)


def table_data(columns: Sequence[object], rows: Sequence[Sequence[object]]) -> dict:
    """A table as a results file stores it (cells as printed), for ``benchmarks/tables.py``."""
    return {"columns": [str(c) for c in columns], "rows": [[str(c) for c in r] for r in rows]}


def table_from_markdown(text: str) -> dict:
    """:func:`table_data` of a Markdown table a script built by hand (header, rule, rows)."""
    lines = [line.strip() for line in text.strip().splitlines() if line.strip().startswith("|")]

    def cells(line: str) -> list[str]:
        return [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line[1:-1])]

    return table_data(cells(lines[0]), [cells(line) for line in lines[2:]])


def write_results(
    name: str,
    sections: dict,
    argv: Sequence[str] | None = None,
    *,
    meta: dict | None = None,
    path: Path | None = None,
) -> Path:
    """Write ``benchmarks/results/<name>.json`` (or ``path``) atomically and return its path.

    Args:
        name: the benchmark's name, e.g. ``"laplacian"`` for ``bench_laplacian.py``.
        sections: the results; a ``"tables"`` entry maps table names to :func:`table_data` dicts,
            which ``benchmarks/tables.py`` renders into the README.
        argv: the command line (default ``sys.argv``); used only when ``meta`` is None.
        meta: the header :func:`run_meta` returned at the start of the run (so that its load
            average is the one before the run); None takes it now.
        path: where to write instead of the default; the file's stem is then the name it is
            recorded under (the README shows a results file by its name, e.g. a 1M-only run
            of ``bench_laplacian.py`` written to ``laplacian_1m.json``).

    Values JSON cannot hold (paths, numpy scalars) are written as their ``str``.
    """
    meta = dict(run_meta(argv) if meta is None else meta)
    meta["load_after"] = _load()
    meta["peers"] = {
        dist: _version(dist) for module, dist in PEERS.items() if module in sys.modules
    }
    target = RESULTS / f"{name}.json" if path is None else Path(path)
    name = target.stem
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(target.name + ".tmp")
    text = json.dumps({"benchmark": name, "meta": meta, **sections}, indent=1, default=str)
    tmp.write_text(text + "\n")
    tmp.replace(target)
    print(f"wrote {target}", file=sys.stderr)
    return target


def interleaved(contenders: dict[str, Callable[[], object]], repeat: int) -> dict[str, float]:
    """Median seconds per contender over ``repeat`` rounds, each round calling every contender
    once in turn (A B C A B C ...), so that a load change on a shared machine falls on all of
    them alike."""
    times: dict[str, list[float]] = {name: [] for name in contenders}
    for _ in range(repeat):
        for name, fn in contenders.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (``platform``'s guess elsewhere)."""
    try:
        with open("/proc/cpuinfo") as info:
            return next(line.split(":", 1)[1].strip() for line in info if "model name" in line)
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def rss_bytes(field: str) -> int | None:
    """``VmRSS`` / ``VmHWM`` of this process from ``/proc/self/status`` (None off Linux)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (``VmHWM``) to the current RSS; False if unsupported."""
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def trim_heap() -> None:
    """Return freed heap memory to the OS (glibc), so that a step's peak is not hidden in it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def peak_rss_growth(step: Callable[[], object]) -> dict:
    """Run ``step`` once and report how far the resident memory rose above where it started.

    The heap is trimmed and the peak counter reset first, so the baseline is what the setup
    left resident. Where ``/proc/self/clear_refs`` cannot be written the peak is ``ru_maxrss``
    since process start (an upper bound).
    """
    gc.collect()
    trim_heap()
    exact = reset_peak_rss()
    baseline = rss_bytes("VmRSS")
    step()
    peak = (
        rss_bytes("VmHWM") if exact else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    )
    return {
        "method": "VmHWM after clear_refs" if exact else "ru_maxrss since start",
        "rss_baseline_bytes": baseline,
        "rss_peak_bytes": peak,
        "rss_delta_bytes": None if baseline is None or peak is None else peak - baseline,
    }
