"""Wall-clock timing and tables, shared by the timing commands (``polylap bench``, the timings of
``polylap info``) and the repository's ``benchmarks/`` scripts (through ``benchmarks/common.py``,
which imports them from here: the installed package cannot import ``benchmarks/``).

Timings are medians over several samples, taken with torch's intra-op thread count pinned
(:func:`pinned_threads`): on a busy machine, every small parallel kernel otherwise waits for
its descheduled threads, and a sub-millisecond operation can take hundreds of times longer.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

import torch

from .._typing import MeshFaces
from ..operators import laplacian
from ..topology import Topology, build_topology

__all__ = [
    "DEFAULT_THREADS",
    "TORCH_DEFAULT_THREADS",
    "FIRST_ASSEMBLY",
    "pinned_threads",
    "first_assembly",
    "synchronizer",
    "median_time",
    "timed",
    "fmt_time",
    "markdown_table",
]

T = TypeVar("T")

# torch threads of the polylap commands and of timings when none are asked for: small sparse
# kernels run (and time) reliably with one
DEFAULT_THREADS = 1
# torch's own thread count, as the process started (OMP_NUM_THREADS or the number of cores)
TORCH_DEFAULT_THREADS = torch.get_num_threads()


@contextmanager
def pinned_threads(threads: int | None = DEFAULT_THREADS) -> Iterator[int]:
    """Run the block with ``torch.set_num_threads(threads)`` and restore the previous count.

    ``None`` means :data:`DEFAULT_THREADS`, ``0`` torch's own default
    (:data:`TORCH_DEFAULT_THREADS`). Yields the thread count in effect.
    """
    threads = DEFAULT_THREADS if threads is None else int(threads)
    if threads == 0:
        threads = TORCH_DEFAULT_THREADS
    if threads < 1:
        raise ValueError(f"the thread count must be at least 0, got {threads}.")
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield threads
    finally:
        torch.set_num_threads(before)


def synchronizer(device: torch.device | str) -> Callable[[], None]:
    """A function that waits for the work queued on ``device`` (a no-op off CUDA)."""
    device = torch.device(device)
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def _sample(fn: Callable[[], T], number: int, sync: Callable[[], None]) -> tuple[float, T]:
    """Seconds taken by ``number`` back-to-back calls of ``fn`` (synced), and the last result."""
    sync()
    start = time.perf_counter()
    for _ in range(number):
        out = fn()
    sync()
    return time.perf_counter() - start, out


def timed(
    fn: Callable[[], T],
    repeat: int = 3,
    *,
    warmup: bool = False,
    sync: Callable[[], None] | None = None,
    min_sample_s: float = 0.0,
) -> tuple[float, T]:
    """Median seconds per call of ``fn`` over ``repeat`` samples, and the last call's result.

    Args:
        fn: the work, called without arguments.
        repeat: number of samples (at least 1).
        warmup: one discarded call first (first-call costs: imports, caches, allocations).
        sync: called before and after each sample, e.g. :func:`synchronizer` of a CUDA device.
        min_sample_s: when positive, calls per sample are doubled (those runs discarded) until
            a sample lasts this long, so that sub-millisecond work is timed over many calls.
    """
    if repeat < 1:
        raise ValueError(f"repeat must be at least 1, got {repeat}.")
    sync = sync or (lambda: None)
    if warmup:
        _sample(fn, 1, sync)
    number = 1
    if min_sample_s > 0:
        while _sample(fn, number, sync)[0] < min_sample_s and number < 2**20:
            number *= 2
    seconds, out = _sample(fn, number, sync)
    times = [seconds / number]
    for _ in range(repeat - 1):
        seconds, out = _sample(fn, number, sync)
        times.append(seconds / number)
    return statistics.median(times), out


def median_time(
    fn: Callable[[], object],
    repeat: int = 5,
    *,
    warmup: bool = True,
    sync: Callable[[], None] | None = None,
    min_sample_s: float = 0.0,
) -> float:
    """Median seconds per call of ``fn`` (:func:`timed` without the result; warm-up on)."""
    return timed(fn, repeat, warmup=warmup, sync=sync, min_sample_s=min_sample_s)[0]


# what first_assembly measures, as the commands label it
FIRST_ASSEMBLY = "first assembly (topology + values)"


def first_assembly(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: float,
    method: str,
    *,
    warn: bool = True,
    sync: Callable[[], None] | None = None,
) -> tuple[float, Topology, tuple[torch.Tensor, torch.Tensor]]:
    """Seconds of assembling ``(L, M0)`` from scratch, the topology and the operators.

    The quantity that ``polylap info`` and ``polylap spectrum`` both report as
    :data:`FIRST_ASSEMBLY`: :func:`~torch_polylap.topology.build_topology` of ``faces`` (never
    the topology cache) plus the first :func:`~torch_polylap.laplacian` on it, one sample each,
    at the thread count in effect. In a fresh process it includes first-call costs (lazy
    imports, allocator warm-up); the re-assembly on a cached topology is much cheaper (``info``
    reports both).

    Args:
        verts: ``(V, 3)`` positions.
        faces: the faces (a ``Topology`` is rebuilt from its faces).
        lam: stabilizer weight.
        method: the Laplacian.
        warn: let :func:`build_topology` warn about topology defects.
        sync: see :func:`timed` (CUDA).

    Returns:
        ``(seconds, topology, (L, M0))``.
    """
    if isinstance(faces, Topology):
        faces = faces.faces
    t_topo, topo = timed(lambda: build_topology(faces, verts.shape[0], warn=warn), 1, sync=sync)
    t_values, operators = timed(lambda: laplacian(verts, topo, lam, method=method), 1, sync=sync)
    return t_topo + t_values, topo, operators


def fmt_time(seconds: float) -> str:
    """``seconds`` in us, ms or s with three significant figures or so."""
    if seconds < 1e-3:
        return f"{seconds * 1e6:.0f} us"
    if seconds < 1.0:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def markdown_table(header: Sequence[object], body: Sequence[Sequence[object]]) -> str:
    """A Markdown table (readable as plain text too), columns padded to their widest cell."""
    # a "|" inside a cell (|H|) would end it in Markdown
    cells = [[str(c).replace("|", "\\|") for c in r] for r in [header, *body]]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = [
        "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in cells
    ]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)
