"""Filling the eigenpair cache of a dataset on any :class:`concurrent.futures.Executor`.

:func:`precompute` sends one task per mesh to an executor: a local process pool by default,
``distributed.Client(...).get_executor()`` for a Dask cluster, or any other executor whose
workers see the cache folder (a shared POSIX folder for several machines).  Each task reads its
mesh, normalizes it as :class:`~torch_polylap.datasets.PolygonMeshDataset` does, and reads or
writes the entry :func:`torch_polylap.cached_eigs` would: entries are keyed by content, written
atomically and checked on read (see the "Dataset cache" page of the documentation), so tasks
run twice, by several machines at once, or after a killed run, are harmless.
"""

from __future__ import annotations

import multiprocessing
import os
import secrets
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import Executor, Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

import torch
from threadpoolctl import threadpool_limits

from ..faces import FacesLike, PolygonFaces, as_faces
from ..io import read_mesh
from ..kernels import check_method
from ..measures import mass
from ..spectral import (
    CacheWriteWarning,
    check_cache_dir,
    eigs_cache_path,
    eigs_through_cache,
    load_cached_eigs,
)

__all__ = [
    "precompute",
    "PrecomputeReport",
    "PrecomputeFailure",
    "InlineExecutor",
    "local_executor",
    "normalize_mesh",
    "read_item",
]

MeshItem = str | os.PathLike | tuple[torch.Tensor, FacesLike]

_P = ParamSpec("_P")
_T = TypeVar("_T")


def normalize_mesh(verts: torch.Tensor, faces: PolygonFaces) -> torch.Tensor:
    """Translate the area-weighted centroid to the origin and scale to unit total area.

    Diffusion times and spectra then mean the same on meshes of any size (``mu`` scales as
    ``1 / area``).
    """
    m = mass(verts, faces)
    centered = verts - (m[:, None] * verts).sum(0) / m.sum()
    return centered / m.sum().sqrt()


def read_item(
    item: MeshItem, k: int, normalize: bool = True, label: str | None = None
) -> tuple[torch.Tensor, PolygonFaces]:
    """``(verts (V, 3) float64, faces)`` of a dataset item (a mesh file or a ``(verts, faces)``
    pair), normalized when asked (:func:`normalize_mesh`); ``label`` names the item in errors
    (default: its file).

    Raises:
        ValueError: the mesh has ``k`` vertices or fewer (too few for ``k`` eigenpairs), or the
            file is malformed (:func:`torch_polylap.read_mesh`).
    """
    if isinstance(item, str | os.PathLike):
        verts, faces = read_mesh(item, dtype=torch.float64)
    else:
        verts, faces = item[0].detach().to(torch.float64), as_faces(item[1])
    if verts.shape[0] <= k:
        raise ValueError(
            f"{label or _label(item, None)} has {verts.shape[0]} vertices, too few for k = {k} "
            "eigenpairs; use a smaller k or a finer mesh."
        )
    return (normalize_mesh(verts, faces) if normalize else verts), faces


@dataclass(frozen=True)
class PrecomputeFailure:
    """A mesh whose eigenpairs could not be cached: ``item`` (its file, or ``"item i"`` for a
    ``(verts, faces)`` pair), ``reason`` (the error, in one line) and ``unwritable``: the
    eigenpairs were computed but the cache folder could not take them (the mesh is fine)."""

    item: str
    reason: str
    unwritable: bool = False


@dataclass
class PrecomputeReport:
    """What :func:`precompute` did.

    Attributes:
        computed: meshes whose eigenpairs were computed and written.
        reused: meshes whose entry was already there and read back intact.
        failures: one :class:`PrecomputeFailure` per mesh that could not be cached.
        replaced: entries found damaged (unreadable, wrong shape, bad checksum) and rewritten;
            they count as computed too.
        seconds: wall time of the whole call.
        mesh_seconds: ``{item: seconds}`` spent in the task of each mesh, where it ran.
        mesh_sizes: ``{item: (vertices, faces)}`` of each mesh read.
    """

    computed: int = 0
    reused: int = 0
    failures: list[PrecomputeFailure] = field(default_factory=list)
    replaced: int = 0
    seconds: float = 0.0
    mesh_seconds: dict[str, float] = field(default_factory=dict)
    mesh_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)

    @property
    def failed(self) -> int:
        """The number of meshes that could not be cached."""
        return len(self.failures)

    @property
    def ok(self) -> bool:
        """Whether every mesh is in the cache now."""
        return not self.failures

    def to_dict(self) -> dict[str, Any]:
        """The counts, the failures and the seconds as JSON-ready values."""
        return {
            "computed": self.computed,
            "reused": self.reused,
            "failed": self.failed,
            "replaced": self.replaced,
            "seconds": self.seconds,
            "failures": [{"item": f.item, "reason": f.reason} for f in self.failures],
        }


@dataclass(frozen=True)
class _Outcome:
    """What one task sends back (small and picklable: strings and numbers only)."""

    item: str
    status: str  # "computed", "reused" or "failed"
    seconds: float = 0.0
    size: tuple[int, int] = (0, 0)
    reason: str = ""
    replaced: bool = False
    unwritable: bool = False


def _label(item: MeshItem, index: int | None) -> str:
    if isinstance(item, str | os.PathLike):
        return os.fspath(item)
    return "a (verts, faces) item" if index is None else f"item {index}"


def _fill_one(
    item: MeshItem,
    label: str,
    cache: str,
    k: int,
    method: str,
    lam: float,
    normalize: bool,
    run: str,
) -> _Outcome:
    """The task of one mesh, run where the executor runs it: read, then reuse or compute.

    ``run`` is unused here: a token unique to each :func:`precompute` call, so that executors
    that take a task's arguments for its identity (Dask's ``pure`` tasks) never answer a
    later call with the outcome of an earlier one (the outcome depends on the cache's state).

    Never raises for a bad mesh: the error comes back as a ``"failed"`` outcome, so it cannot
    stop the other tasks, and exceptions that do not pickle never cross processes. Warnings
    are recorded, not printed: a damaged entry counts as ``replaced``, an unwritable cache as
    a failure.
    """
    start = time.perf_counter()
    size = (0, 0)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            verts, faces = read_item(item, k, normalize)
            size = (int(verts.shape[0]), int(faces.num_faces))
            path = eigs_cache_path(Path(cache), verts, faces, k, lam, method)
            reused = path.is_file() and load_cached_eigs(path, k, size[0]) is not None
            if not reused:
                with torch.no_grad():
                    eigs_through_cache(verts, faces, k, Path(cache), lam, method)
    except Exception as err:  # any error of this mesh is its failure, not the run's
        reason = f"{type(err).__name__}: {' '.join(str(err).split())}"
        return _Outcome(label, "failed", time.perf_counter() - start, size, reason)
    seconds = time.perf_counter() - start
    if not reused and not path.is_file():
        # the cache warns once per folder and process: a later task here sees no warning
        unwritable = [w for w in caught if issubclass(w.category, CacheWriteWarning)]
        reason = f"the entry {path} was not written: the cache folder cannot be written"
        if unwritable:
            reason = " ".join(str(unwritable[0].message).split())
        return _Outcome(label, "failed", seconds, size, reason, unwritable=True)
    replaced = any("recomputing and replacing it" in str(w.message) for w in caught)
    return _Outcome(label, "reused" if reused else "computed", seconds, size, replaced=replaced)


class InlineExecutor(Executor):
    """An executor that runs each task in the calling thread as it is submitted (no workers)."""

    def submit(self, fn: Callable[_P, _T], /, *args: _P.args, **kwargs: _P.kwargs) -> Future[_T]:
        future: Future[_T] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as err:
            future.set_exception(err)
        return future


def _single_threaded() -> None:
    """Worker initializer: one torch thread, and one thread in every BLAS and OpenMP pool the
    process has loaded (numpy's and scipy's BLAS behind the eigensolver among them).

    A forked worker inherits the parent's pools, sized for every core: two workers on two
    cores then ran four BLAS threads that spin while they wait, doubling the CPU time, and
    were slower together than one worker alone."""
    torch.set_num_threads(1)
    threadpool_limits(1)


def local_executor(workers: int | None = None) -> Executor:
    """A local process pool of ``workers`` processes (default: one per core), each with one
    thread (:func:`_single_threaded`), so ``workers`` processes use about ``workers`` cores.

    Uses ``fork`` where available (no re-import of torch per worker), else ``spawn``."""
    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
    return ProcessPoolExecutor(
        workers or os.cpu_count() or 1, mp_context=context, initializer=_single_threaded
    )


def precompute(
    items: Sequence[MeshItem],
    cache_dir: str | os.PathLike,
    *,
    k: int = 32,
    method: str = "aw11",
    lam: float = 1.0,
    executor: Executor | None = None,
    progress: bool = True,
    normalize: bool = True,
) -> PrecomputeReport:
    """Fill the eigenpair cache of every mesh of ``items``, on ``executor``'s workers.

    Computes, for each mesh, the ``k`` eigenpairs of ``L phi = mu M0 phi`` that
    :class:`~torch_polylap.datasets.PolygonMeshDataset` with the same ``k``, ``method``,
    ``lam`` and ``normalize`` reads (``L`` and ``M0`` themselves are assembled per item when
    the dataset serves it, in milliseconds; the eigenpairs are the part worth caching).
    Meshes already cached are read back and verified, not recomputed, so a run that was
    killed resumes where it stopped.

    Args:
        items: mesh files (OBJ, OFF, PLY) or ``(verts (V, 3), faces)`` pairs.
        cache_dir: the cache folder (created when missing); every worker must see it.
        k: eigenpairs per mesh.
        method: ``"aw11"``, ``"plms"`` or ``"degoes"`` (:func:`torch_polylap.laplacian`).
        lam: stabilization weight of the Laplacian (unused by ``"plms"``).
        executor: where the tasks run: any :class:`concurrent.futures.Executor`, e.g. a
            ``ProcessPoolExecutor`` or Dask's ``Client.get_executor()``; it is not shut down.
            ``None``: a local process pool with one process per core (:func:`local_executor`),
            shut down at the end. A thread pool works but gains little (the eigensolver holds
            the GIL part of the time).
        progress: show a progress bar (meshes done, throughput, ETA) on stderr.
        normalize: center and scale each mesh to unit area first, as the dataset does.

    Returns:
        A :class:`PrecomputeReport`: computed, reused and failed counts, each failure with its
        file and reason. A bad mesh (unreadable file, too few vertices, an eigensolver error)
        is a failure of that mesh only; an unwritable cache fails every mesh it concerns.

    Raises:
        ValueError: ``cache_dir`` names a file, or ``method`` is unknown (before any work).
        KeyboardInterrupt: the run was interrupted; pending tasks are cancelled and every
            entry written so far is complete (writes are atomic).
    """
    method = check_method(method)
    cache = Path(cache_dir)
    check_cache_dir(cache)
    cache.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    own = executor is None
    pool = local_executor() if executor is None else executor
    report = PrecomputeReport()
    try:
        _collect(pool, list(items), cache, (k, method, lam, normalize), progress, report)
    finally:
        if own:
            # also on Ctrl-C: running tasks end their atomic writes (or remove their temporary)
            pool.shutdown(wait=True, cancel_futures=True)
    report.seconds = time.perf_counter() - start
    return report


def _collect(
    pool: Executor,
    items: list[MeshItem],
    cache: Path,
    options: tuple[int, str, float, bool],
    progress: bool,
    report: PrecomputeReport,
) -> None:
    """Submit one task per item and tally the outcomes as they complete."""
    from tqdm import tqdm

    labels = [_label(item, i) for i, item in enumerate(items)]
    run = secrets.token_hex(8)
    futures: dict[Future[_Outcome], str] = {}
    try:
        for item, label in zip(items, labels, strict=True):
            task = (_on_cpu(item), label, os.fspath(cache), *options, run)
            futures[pool.submit(_fill_one, *task)] = label
        with tqdm(total=len(items), unit="mesh", desc="precompute", disable=not progress) as bar:
            for future in as_completed(futures):
                _tally(report, future, futures[future])
                bar.update(1)
        position = {label: i for i, label in enumerate(labels)}
        report.failures.sort(key=lambda failure: position.get(failure.item, len(labels)))
    except BaseException:
        for future in futures:
            future.cancel()
        raise


def _on_cpu(item: MeshItem) -> MeshItem:
    """The item with its tensors on the CPU: CUDA tensors do not cross into forked workers or
    other machines, and the entry is the same (its key hashes float64 CPU copies)."""
    if isinstance(item, str | os.PathLike):
        return item
    verts, faces = item
    if isinstance(faces, torch.Tensor | PolygonFaces):
        faces = faces.to("cpu")
    return verts.detach().cpu(), faces


def _tally(report: PrecomputeReport, future: Future[_Outcome], label: str) -> None:
    try:
        outcome = future.result()
    except Exception as err:  # the worker itself died (a lost process, a broken pool)
        reason = f"{type(err).__name__}: {' '.join(str(err).split()) or 'the worker was lost'}"
        report.failures.append(PrecomputeFailure(label, reason))
        return
    if outcome.status == "failed":
        failure = PrecomputeFailure(outcome.item, outcome.reason, outcome.unwritable)
        report.failures.append(failure)
    elif outcome.status == "reused":
        report.reused += 1
    else:
        report.computed += 1
        report.replaced += outcome.replaced
    report.mesh_seconds[outcome.item] = outcome.seconds
    if outcome.size != (0, 0):
        report.mesh_sizes[outcome.item] = outcome.size
