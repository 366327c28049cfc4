"""A dataset of polygon meshes with precomputed operators and eigenpairs, and its collate.

Each item carries what the layers of :mod:`torch_polylap.nn` need: the mesh, its Laplacian
``L`` and lumped mass ``M0`` (AW11 eq. 3, 9, 10) and ``k`` eigenpairs of ``L phi = mu M0 phi``.
Eigenpairs are the expensive part; they go through :func:`torch_polylap.cached_eigs`, an
on-disk cache keyed by the (normalized) geometry, so they are computed once per mesh across
epochs, runs and processes.  Fill the cache up front in parallel with
:meth:`PolygonMeshDataset.precompute`, on any :class:`concurrent.futures.Executor` (a Dask
cluster's, say) with :func:`precompute`, or let ``DataLoader(num_workers=n)`` workers fill it
on first access (writes are atomic, so concurrent workers never read half a file).

:func:`collate_meshes` packs a list of items into a :class:`MeshBatch`: a
:class:`~torch_polylap.batch.PolygonMeshes`, the packed :class:`~torch_polylap.nn.Spectrum`,
block-diagonal ``L`` and ``M0`` (concatenated, not re-assembled) and the labels.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import torch
from torch.utils.data import Dataset

from ..batch import PolygonMeshes, to_arguments
from ..faces import PolygonFaces
from ..kernels import check_method
from ..nn.spectrum import Spectrum
from ..operators import laplacian
from ..sparse import SparseOperator, block_diag, diag
from ..spectral import CacheWriteWarning, cached_eigs, check_cache_dir
from ..tangent import vertex_gradient_operators
from .jobs import (
    InlineExecutor,
    MeshItem,
    PrecomputeFailure,
    PrecomputeReport,
    local_executor,
    normalize_mesh,
    precompute,
    read_item,
)

__all__ = [
    "PolygonMeshDataset",
    "MeshBatch",
    "collate_meshes",
    "precompute",
    "PrecomputeReport",
    "PrecomputeFailure",
    "normalize_mesh",
]


class PolygonMeshDataset(Dataset):
    """Polygon meshes (files or ``(verts, faces)`` pairs) with labels, ``L``, ``M0`` and eigenpairs.

    Args:
        items: mesh file paths (OBJ/OFF/PLY, read with :func:`torch_polylap.read_mesh`) or
            ``(verts (V, 3), faces)`` pairs.
        labels: one integer label per item (classification), or ``None``.
        k: eigenpairs per mesh (every mesh needs more than ``k`` vertices).
        cache_dir: directory of the eigenpair cache (created when missing; a path naming an
            existing file is a ``ValueError`` at construction).  Unusable cache files are
            recomputed and replaced, see :func:`torch_polylap.cached_eigs`.
        lam: stabilization weight of the Laplacian (AW11 eq. 9; unused by ``"plms"``).
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` or ``"degoes"`` (see
            :func:`torch_polylap.laplacian`); part of the eigenpair cache key. The
            normalization uses the AW11 lumped mass whatever the method.
        normalize: center and scale each mesh to unit area (:func:`normalize_mesh`).
        dtype: dtype of the returned tensors (eigenpairs are computed in float64).
        gradient_operators: also give every item the per-vertex tangent gradient operators
            ``grad_x, grad_y`` (:func:`torch_polylap.tangent.vertex_gradient_operators`, computed in
            float64 on the normalized mesh) that
            ``DiffusionNetLike(gradient_features=True)`` needs.

    ``dataset[i]`` is a dict with ``verts (V, 3)``, ``faces`` (:class:`PolygonFaces`),
    ``label`` (int or None), ``evals (k,)``, ``evecs (V, k)``, ``mass (V,)`` and ``L`` as CSR
    arrays ``(crow, col, values)`` (plain tensors, so items cross DataLoader worker processes).
    With ``gradient_operators=True`` also ``grad_x`` and ``grad_y`` ``(V, V)``, sparse operators
    (they pickle as their index and value arrays, like ``L``).
    """

    def __init__(
        self,
        items: Sequence[MeshItem],
        labels: Sequence[int] | None = None,
        *,
        k: int = 32,
        cache_dir: str | os.PathLike,
        lam: float = 1.0,
        normalize: bool = True,
        dtype: torch.dtype = torch.float32,
        method: str = "aw11",
        gradient_operators: bool = False,
    ) -> None:
        if labels is not None and len(labels) != len(items):
            raise ValueError(f"got {len(items)} meshes but {len(labels)} labels.")
        self.items, self.labels = list(items), None if labels is None else list(labels)
        self.k, self.cache_dir, self.lam = k, Path(cache_dir), lam
        self.method = check_method(method, diagonal_mass="PolygonMeshDataset")
        check_cache_dir(self.cache_dir)  # before any mesh is read or eigenpair computed
        self.normalize, self.dtype = normalize, dtype
        self.gradient_operators = gradient_operators

    def __len__(self) -> int:
        return len(self.items)

    def mesh(self, i: int) -> tuple[torch.Tensor, PolygonFaces]:
        """``(verts, faces)`` of item ``i`` in float64, normalized if requested."""
        return read_item(self.items[i], self.k, self.normalize, f"mesh {i}")

    def __getitem__(self, i: int) -> dict[str, Any]:
        verts, faces = self.mesh(i)
        evals, evecs = cached_eigs(
            verts, faces, self.k, self.cache_dir, lam=self.lam, method=self.method
        )
        L, M0 = laplacian(verts, faces, self.lam, method=self.method)
        item = {
            "verts": verts.to(self.dtype),
            "faces": faces,
            "label": None if self.labels is None else int(self.labels[i]),
            "evals": evals.to(self.dtype),
            "evecs": evecs.to(self.dtype),
            "mass": M0.diagonal().to(self.dtype),
            "L": L.to(self.dtype),
        }
        if self.gradient_operators:
            grad_x, grad_y = vertex_gradient_operators(verts, faces)
            item["grad_x"], item["grad_y"] = grad_x.to(self.dtype), grad_y.to(self.dtype)
        return item

    def precompute(self, num_workers: int = 0) -> PrecomputeReport:
        """Fill the eigenpair cache for every item, in ``num_workers`` processes (0: here).

        A call of :func:`precompute` with this dataset's ``k``, ``method``, ``lam`` and
        ``normalize``, on a local process pool (:func:`~torch_polylap.datasets.jobs.
        local_executor`: ``fork`` where available, one torch thread per worker), without a
        progress bar. For a cluster, call :func:`precompute` with its executor.

        Returns:
            The :class:`PrecomputeReport`.

        Raises:
            ValueError: some meshes could not be read or solved (after all the others were
                cached); the message names each one and its reason. A cache folder that cannot
                be written is a :class:`~torch_polylap.spectral.CacheWriteWarning` instead, as
                with :func:`~torch_polylap.cached_eigs`: the items are computed on access.
        """
        executor = local_executor(num_workers) if num_workers > 0 else InlineExecutor()
        with executor:
            report = precompute(
                self.items,
                self.cache_dir,
                k=self.k,
                method=self.method,
                lam=self.lam,
                executor=executor,
                progress=False,
                normalize=self.normalize,
            )
        bad = [f for f in report.failures if not f.unwritable]
        if bad:
            listed = "; ".join(f"{f.item}: {f.reason}" for f in bad)
            raise ValueError(f"{len(bad)} of {len(self)} meshes were not cached: {listed}")
        if report.failures:
            # as cached_eigs: an unwritable cache loses no data (items recompute), so it warns
            warnings.warn(report.failures[0].reason, CacheWriteWarning, stacklevel=2)
        return report


@dataclass
class MeshBatch:
    """A collated batch: meshes, packed eigenpairs, block-diagonal operators, labels.

    Attributes:
        meshes: :class:`PolygonMeshes` of the ``B`` meshes (packed vertices and faces).
        spectrum: :class:`Spectrum` (``evals (B, k)``, ``evecs (sumV, k)``, masses, index maps).
        L: ``(sumV, sumV)`` block-diagonal Laplacian, a
            :class:`~torch_polylap.sparse.SparseOperator` (it pickles as its index and value
            arrays, so a batch collated in a DataLoader worker crosses processes).
        labels: ``(B,)`` int64, or ``None`` when the items have none.
        grad_x, grad_y: ``(sumV, sumV)`` block-diagonal tangent gradient operators, when the
            items carry them (``PolygonMeshDataset(gradient_operators=True)``), else ``None``.
    Property ``M0``: the ``(sumV, sumV)`` diagonal mass operator.
    """

    meshes: PolygonMeshes
    spectrum: Spectrum
    L: SparseOperator
    labels: torch.Tensor | None
    grad_x: SparseOperator | None = None
    grad_y: SparseOperator | None = None

    @property
    def M0(self) -> SparseOperator:
        return diag(self.spectrum.mass)

    def to(self, *args: Any, **kwargs: Any) -> MeshBatch:
        """The batch moved as :meth:`torch.Tensor.to` moves a tensor: ``to(dtype)``,
        ``to(device)``, ``to(device, dtype)``, ``to(tensor)``, keywords ``device``, ``dtype``,
        ``non_blocking``, ``copy`` (:func:`torch_polylap.batch.to_arguments`). Positions,
        eigenpairs and operator values take the dtype; labels stay int64.
        """
        move = to_arguments(*args, **kwargs)

        def moved(A: SparseOperator) -> SparseOperator:
            # an operator's .to() is an operator; torch's stubs type Tensor.to as a Tensor
            return cast(
                SparseOperator,
                A.to(
                    device=move.device,
                    dtype=move.dtype,
                    non_blocking=move.non_blocking,
                    copy=move.copy,
                ),
            )

        return MeshBatch(
            self.meshes.to(move.device, move.dtype, move.non_blocking, move.copy),
            self.spectrum.to(move.device, move.dtype, move.non_blocking, move.copy),
            moved(self.L),
            None if self.labels is None else move.apply(self.labels),
            *(None if g is None else moved(g) for g in (self.grad_x, self.grad_y)),
        )


def collate_meshes(items: Sequence[dict[str, Any]]) -> MeshBatch:
    """Pack dataset items into a :class:`MeshBatch` (use as ``DataLoader(collate_fn=...)``).

    ``L`` is concatenated block by block from the items' operators (no re-assembly). Faces of
    any degree are packed with torch_geometric's increment: ``batch.meshes.faces_packed()``
    holds mesh ``i``'s corners offset by the number of vertices of the meshes before it
    (``mesh_to_verts_packed_first_idx()[i]``); ``faces_padded()`` keeps local indices.
    """
    meshes = PolygonMeshes([it["verts"] for it in items], [it["faces"] for it in items])
    spectrum = Spectrum(
        torch.stack([it["evals"] for it in items]),
        torch.cat([it["evecs"] for it in items]),
        torch.cat([it["mass"] for it in items]),
        meshes.num_verts_per_mesh(),
    )
    L = block_diag([it["L"] for it in items])
    grads: list[SparseOperator | None] = [None, None]
    if all("grad_x" in it and "grad_y" in it for it in items):
        grads = [block_diag([it[key] for it in items]) for key in ("grad_x", "grad_y")]
    labels = [it["label"] for it in items]
    return MeshBatch(
        meshes,
        spectrum,
        L,
        None if any(lb is None for lb in labels) else torch.tensor(labels, dtype=torch.int64),
        *grads,
    )
