"""Batches of heterogeneous polygon meshes in pytorch3d's packed convention.

A batch of ``B`` meshes with ``V_i`` vertices and ``F_i`` faces each is held as one
``(sum V_i, 3)`` vertex tensor (*packed* vertices) and one :class:`PolygonFaces` whose indices
are global, i.e. shifted by the first packed index of their mesh.  Because no face joins two
meshes, every operator assembled on the packed mesh is block diagonal: one call of
:func:`torch_polylap.laplacian` on the packed faces yields ``blockdiag(L_1, ..., L_B)`` (and
the same for ``M0``), and per-mesh quantities follow by scattering per-vertex or per-face values
with :func:`per_mesh_sum`.

The connectivity (the packed faces, their validated :class:`~torch_polylap.Topology` and the
index maps) lives in a cache shared by every batch derived with :meth:`PolygonMeshes.update_packed`
or :meth:`PolygonMeshes.to`, so a training loop with fixed connectivity builds it once.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .checks import Lam, check_verts, warn_outside_package
from .faces import FacesLike, PolygonFaces, as_faces
from .operators import laplacian
from .topology import (
    Topology,
    TopologyReport,
    build_topology,
    get_topology,
    half_edge_vertices,
)

__all__ = ["PolygonMeshes", "per_mesh_sum", "per_mesh_mean"]


def per_mesh_sum(values: torch.Tensor, index: torch.Tensor, num_meshes: int) -> torch.Tensor:
    """Sum packed per-element values into their meshes.

    Args:
        values: ``(N, ...)`` one row per packed vertex, face or edge.
        index: ``(N,)`` the mesh of each row, e.g. :meth:`PolygonMeshes.verts_packed_to_mesh_idx`.
        num_meshes: ``B``.

    Returns:
        ``(B, ...)`` per-mesh sums (zero for a mesh without rows); differentiable in ``values``.
    """
    if index.shape != values.shape[:1]:
        raise ValueError(
            f"index must have shape ({values.shape[0]},), one mesh per row of values, "
            f"got {tuple(index.shape)}."
        )
    out = values.new_zeros((num_meshes, *values.shape[1:]))
    return out.index_add(0, index.to(values.device), values)


def per_mesh_mean(
    values: torch.Tensor,
    index: torch.Tensor,
    num_meshes: int,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """``(B, ...)`` per-mesh means of packed values (see :func:`per_mesh_sum`).

    With ``weights`` ``(N,)`` the weighted mean ``sum_v w_v x_v / sum_v w_v``: with the lumped
    masses (``M0.diagonal()``) the area-weighted mean, a global pooling that does not depend on
    the tessellation density. A mesh without rows (or without weight) gets ``0``.
    """
    if weights is None:
        sums = per_mesh_sum(values, index, num_meshes)
        counts = torch.bincount(index.to(values.device), minlength=num_meshes).clamp_min(1)
        return sums / counts.to(values.dtype).reshape(-1, *([1] * (values.dim() - 1)))
    if weights.shape != values.shape[:1]:
        raise ValueError(
            f"weights must have shape ({values.shape[0]},), one per row of values, "
            f"got {tuple(weights.shape)}."
        )
    w = weights.to(values.dtype).reshape(-1, *([1] * (values.dim() - 1)))
    sums = per_mesh_sum(w * values, index, num_meshes)
    total = per_mesh_sum(weights.to(values.dtype), index, num_meshes)
    total = torch.where(total > 0, total, torch.ones_like(total))
    return sums / total.reshape(-1, *([1] * (values.dim() - 1)))


@dataclass(frozen=True)
class TensorMove:
    """Where and how :meth:`torch.Tensor.to` would move a tensor: the parsed arguments of a
    container's ``.to`` (:func:`to_arguments`)."""

    device: torch.device | None
    dtype: torch.dtype | None
    non_blocking: bool
    copy: bool

    def apply(self, t: torch.Tensor) -> torch.Tensor:
        """``t`` moved to :attr:`device`; cast to :attr:`dtype` only if ``t`` is floating point
        (index and label tensors keep their integer dtype)."""
        dtype = self.dtype if t.is_floating_point() else None
        return t.to(device=self.device, dtype=dtype, non_blocking=self.non_blocking, copy=self.copy)


_TO_SIGNATURES = (
    "to(dtype, non_blocking=False, copy=False), to(device=None, dtype=None, non_blocking=False, "
    "copy=False) or to(tensor, non_blocking=False, copy=False)"
)


def to_arguments(*args: Any, **kwargs: Any) -> TensorMove:
    """The arguments of a container's ``.to``, read with :meth:`torch.Tensor.to`'s three forms:

    - ``to(dtype, non_blocking=False, copy=False)``;
    - ``to(device=None, dtype=None, non_blocking=False, copy=False)``;
    - ``to(tensor, non_blocking=False, copy=False)``: ``tensor``'s device and dtype.

    ``memory_format`` is accepted as ``None`` or ``torch.preserve_format`` only (the containers
    hold no image tensors).

    Raises:
        TypeError: arguments that fit none of the forms (as torch raises), or a dtype that is
            not floating point (the containers' floating tensors are positions and operator
            values; integer tensors are never cast).
    """
    unknown = sorted(set(kwargs) - {"device", "dtype", "non_blocking", "copy", "memory_format"})
    if unknown:
        raise TypeError(
            f"to() got unexpected keyword arguments {unknown}; it takes {_TO_SIGNATURES}."
        )
    memory_format = kwargs.pop("memory_format", None)
    if memory_format not in (None, torch.preserve_format):
        raise TypeError(f"to(memory_format={memory_format}) is not supported on a mesh container.")
    rest = list(args)
    given: dict[str, Any] = {}
    names: tuple[str, ...] = ("device", "dtype", "non_blocking", "copy")
    if rest and isinstance(rest[0], torch.Tensor | torch.dtype):
        first = rest.pop(0)
        names = ("non_blocking", "copy")
        taken = {"device", "dtype"}  # torch's dtype and tensor forms take neither keyword
        if taken & kwargs.keys():
            what = "a dtype" if isinstance(first, torch.dtype) else "a tensor"
            raise TypeError(
                f"to() got {what} positionally and {sorted(taken & kwargs.keys())} as keywords; "
                f"it takes {_TO_SIGNATURES}."
            )
        if isinstance(first, torch.dtype):
            given["dtype"] = first
        else:
            given.update(device=first.device, dtype=first.dtype)
    if len(rest) > len(names):
        raise TypeError(f"to() got {len(args)} positional arguments; it takes {_TO_SIGNATURES}.")
    positional = dict(zip(names, rest, strict=False))
    twice = sorted(positional.keys() & kwargs.keys())
    if twice:
        raise TypeError(f"to() got multiple values for {twice}.")
    given.update(positional)
    given.update(kwargs)
    device, dtype = given.get("device"), given.get("dtype")
    if device is not None and (
        isinstance(device, bool) or not isinstance(device, str | int | torch.device)
    ):
        raise TypeError(
            f"to(): device must be a torch.device, a string or an index, got {device!r}; it "
            f"takes {_TO_SIGNATURES}."
        )
    if dtype is not None and not isinstance(dtype, torch.dtype):
        raise TypeError(f"to(): dtype must be a torch.dtype, got {dtype!r}.")
    flags = {key: given.get(key, False) for key in ("non_blocking", "copy")}
    for key, value in flags.items():
        if not isinstance(value, bool):
            raise TypeError(f"to(): {key} must be a bool, got {value!r}.")
    # as torch: arguments of the wrong type are a TypeError first, then a device string it
    # cannot read is a RuntimeError, whatever the dtype
    target = None if device is None else torch.device(device)
    if dtype is not None and not dtype.is_floating_point:
        raise TypeError(
            f"to(): a mesh container casts its positions and operator values, which must stay "
            f"floating point; got dtype {dtype} (use torch.float32 or torch.float64)."
        )
    return TensorMove(
        target,
        dtype,
        flags["non_blocking"],
        flags["copy"],
    )


class _Connectivity:
    """Everything about a batch that depends only on its faces; shared by derived batches."""

    def __init__(self, faces: list[PolygonFaces], num_verts: list[int], source: Any) -> None:
        self.faces = faces
        self.num_verts = num_verts
        self.num_faces = [f.num_faces for f in faces]
        # For a single mesh given as a tensor or PolygonFaces, get_topology caches the topology
        # on the user's object, so rebuilding a batch from the same faces does not re-validate.
        self.source = source
        self.topology: Topology | None = None
        # mesh -> its own Topology (local indices), for the meshes whose report is not clean
        self.local: dict[int, Topology] | None = None
        self.packed_cpu: PolygonFaces | None = None
        self.per_device: dict[tuple[str, torch.device], Any] = {}

    def packed(self) -> PolygonFaces:
        if self.packed_cpu is None:
            if len(self.faces) == 1:
                self.packed_cpu = self.faces[0]
            else:
                first = torch.tensor([0, *self.num_verts[:-1]], dtype=torch.int64).cumsum(0)
                corners = torch.tensor([f.num_corners for f in self.faces], dtype=torch.int64)
                shift = torch.repeat_interleave(first, corners)
                indices = torch.cat([f.indices for f in self.faces]) + shift
                sizes = torch.cat([f.sizes for f in self.faces])
                self.packed_cpu = PolygonFaces(indices, sizes=sizes)
        return self.packed_cpu

    def cached(self, name: str, device: torch.device, make: Callable[[], Any]) -> Any:
        key = (name, device)
        if key not in self.per_device:
            self.per_device[key] = make()
        return self.per_device[key]


def _check_mesh(i: int, verts: torch.Tensor, faces: PolygonFaces) -> None:
    check_verts(verts, f"verts of mesh {i}", finite=False)
    if faces.num_corners:
        hi, lo = int(faces.indices.max()), int(faces.indices.min())
        if hi >= verts.shape[0] or lo < 0:
            j = hi if hi >= verts.shape[0] else lo
            corner = int(torch.nonzero(faces.indices == j)[0, 0])
            f = int(torch.searchsorted(faces.offsets, torch.tensor(corner), right=True)) - 1
            raise ValueError(
                f"mesh {i}: face {f} refers to vertex {j}, but the mesh has {verts.shape[0]} "
                f"vertices (valid local indices are 0..{verts.shape[0] - 1}). Faces of each "
                "mesh must index its own verts, 0-based."
            )


class PolygonMeshes:
    """A batch of ``B`` polygon meshes of different sizes and face degrees (packed layout).

    Args:
        verts: ``B`` tensors ``(V_i, 3)``, same dtype and device; may require grad.
        faces: ``B`` faces in any form accepted by :func:`torch_polylap.as_faces`, with indices
            local to their mesh (``0 <= j < V_i``).

    The packed representation follows pytorch3d's ``Meshes``: ``verts_packed()`` is
    ``(sum V_i, 3)``, ``faces_packed()`` holds global indices and the ``*_idx`` maps tell which
    mesh a packed row belongs to.  :meth:`laplacian` assembles the block-diagonal ``(L, M0)``
    of the whole batch in one call (AW11 eq. 3, 9, 10 on the packed mesh).

    Conversions to and from trimesh, pytorch3d and PyTorch Geometric are functions of
    :mod:`torch_polylap.interop` (``tp.to_pytorch3d(meshes)``, ``tp.from_pyg(batch)``, ...).

    Raises:
        ValueError: lists of different lengths, a malformed verts tensor, or a face of mesh
            ``i`` that refers to a vertex ``j >= V_i`` (the message names ``i`` and ``j``).
    """

    def __init__(self, verts: Sequence[torch.Tensor], faces: Sequence[FacesLike]) -> None:
        if isinstance(verts, torch.Tensor):
            raise TypeError(
                "PolygonMeshes takes a list of (V_i, 3) tensors, one per mesh; for a single mesh "
                "pass [verts], [faces]."
            )
        verts = list(verts)
        faces_in = list(faces)
        if len(verts) != len(faces_in):
            raise ValueError(f"got {len(verts)} vertex tensors but {len(faces_in)} face sets.")
        if not verts:
            raise ValueError("PolygonMeshes needs at least one mesh.")
        pfaces = []
        for i, (v, f) in enumerate(zip(verts, faces_in, strict=True)):
            try:
                pf = as_faces(f)
            except ValueError as err:
                raise ValueError(f"mesh {i}: {err}") from None
            pf = pf if pf.device.type == "cpu" else pf.to("cpu")
            _check_mesh(i, v, pf)
            if v.dtype != verts[0].dtype or v.device != verts[0].device:
                raise ValueError(
                    f"mesh {i} has verts of dtype {v.dtype} on {v.device} but mesh 0 has "
                    f"{verts[0].dtype} on {verts[0].device}; convert them to one dtype and device."
                )
            pfaces.append(pf)
        source = faces_in[0] if len(verts) == 1 else None
        if not isinstance(source, (torch.Tensor, PolygonFaces)):
            source = None
        self._conn = _Connectivity(pfaces, [v.shape[0] for v in verts], source)
        self._verts_list: list[torch.Tensor] | None = verts
        self._verts_packed: torch.Tensor | None = None

    @classmethod
    def _from_packed(cls, conn: _Connectivity, verts_packed: torch.Tensor) -> PolygonMeshes:
        out = cls.__new__(cls)
        out._conn = conn
        out._verts_list = None
        out._verts_packed = verts_packed
        return out

    # ----------------------------------------------------------------- constructors

    @classmethod
    def from_list(cls, meshes: Sequence[tuple[torch.Tensor, FacesLike]]) -> PolygonMeshes:
        """From a sequence of ``(verts, faces)`` pairs."""
        meshes = list(meshes)
        return cls([m[0] for m in meshes], [m[1] for m in meshes])

    # ----------------------------------------------------------------- accessors

    def __len__(self) -> int:
        return len(self._conn.faces)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, PolygonFaces]:
        """``(verts_i (V_i, 3), faces_i)`` of mesh ``i`` with local indices."""
        b = len(self)
        try:
            i = operator.index(i)
        except TypeError:
            raise TypeError(f"mesh index must be an integer, got {type(i).__name__}.") from None
        if not -b <= i < b:
            raise IndexError(f"mesh index {i} is out of range for a batch of {b} meshes.")
        return self.verts_list()[i], self.faces_list()[i]

    def __repr__(self) -> str:
        return (
            f"PolygonMeshes(B={len(self)}, V={sum(self._conn.num_verts)}, "
            f"F={sum(self._conn.num_faces)}, dtype={self.dtype}, device={self.device})"
        )

    def _held_verts(self) -> torch.Tensor:
        """The packed vertices, or else the first mesh's (a batch always holds one of them)."""
        if self._verts_packed is not None:
            return self._verts_packed
        assert self._verts_list is not None
        return self._verts_list[0]

    @property
    def device(self) -> torch.device:
        return self._held_verts().device

    @property
    def dtype(self) -> torch.dtype:
        return self._held_verts().dtype

    def verts_list(self) -> list[torch.Tensor]:
        """``B`` tensors ``(V_i, 3)`` (views of the packed vertices when built from them)."""
        if self._verts_list is None:
            assert self._verts_packed is not None  # a batch holds one of the two
            self._verts_list = list(torch.split(self._verts_packed, self._conn.num_verts))
        return self._verts_list

    def faces_list(self) -> list[PolygonFaces]:
        """``B`` :class:`PolygonFaces` with local indices, on :attr:`device`."""
        dev = self.device
        return self._conn.cached(
            "faces_list",
            dev,
            lambda: [f if dev.type == "cpu" else f.to(dev) for f in self._conn.faces],
        )

    def verts_packed(self) -> torch.Tensor:
        """``(sum V_i, 3)`` all vertices; differentiable in the per-mesh tensors."""
        if self._verts_packed is None:
            vl = self._verts_list
            assert vl is not None  # a batch holds one of the two
            self._verts_packed = vl[0] if len(vl) == 1 else torch.cat(vl, 0)
        return self._verts_packed

    def faces_packed(self) -> PolygonFaces:
        """All faces with global (packed) vertex indices, on :attr:`device`."""
        dev = self.device
        return self._conn.cached("faces_packed", dev, lambda: self._conn.packed().to(dev))

    def num_verts_per_mesh(self) -> torch.Tensor:
        """``(B,)`` int64 ``V_i``."""
        return self._conn.cached(
            "nv", self.device, lambda: torch.tensor(self._conn.num_verts, device=self.device)
        )

    def num_faces_per_mesh(self) -> torch.Tensor:
        """``(B,)`` int64 ``F_i``."""
        return self._conn.cached(
            "nf", self.device, lambda: torch.tensor(self._conn.num_faces, device=self.device)
        )

    def mesh_to_verts_packed_first_idx(self) -> torch.Tensor:
        """``(B,)`` index of each mesh's first vertex in :meth:`verts_packed`."""

        def make() -> torch.Tensor:
            nv = self.num_verts_per_mesh()
            return torch.cumsum(nv, 0) - nv

        return self._conn.cached("first", self.device, make)

    def mesh_to_faces_packed_first_idx(self) -> torch.Tensor:
        """``(B,)`` index of each mesh's first face in :meth:`faces_packed`."""

        def make() -> torch.Tensor:
            nf = self.num_faces_per_mesh()
            return torch.cumsum(nf, 0) - nf

        return self._conn.cached("ffirst", self.device, make)

    def _packed_to_mesh_idx(self, name: str, counts: Callable[[], torch.Tensor]) -> torch.Tensor:
        """``(sum counts,)`` the mesh of every packed element, ``counts()`` ``(B,)`` per mesh,
        cached under ``name``."""
        return self._conn.cached(
            name,
            self.device,
            lambda: torch.repeat_interleave(torch.arange(len(self), device=self.device), counts()),
        )

    def verts_packed_to_mesh_idx(self) -> torch.Tensor:
        """``(sum V_i,)`` the mesh of every packed vertex."""
        return self._packed_to_mesh_idx("v2m", self.num_verts_per_mesh)

    def verts_padded_to_packed_idx(self) -> torch.Tensor:
        """``(sum V_i,)`` where every packed vertex lies in the flattened padded vertices
        ``verts_padded().reshape(-1, 3)``: ``i * V_max + j`` for vertex ``j`` of mesh ``i``
        (pytorch3d's ``verts_padded_to_packed_idx``)."""

        def make() -> torch.Tensor:
            v2m = self.verts_packed_to_mesh_idx()
            local = torch.arange(v2m.numel(), device=self.device)
            local = local - self.mesh_to_verts_packed_first_idx()[v2m]
            return v2m * max(self._conn.num_verts) + local

        return self._conn.cached("v_pad2pack", self.device, make)

    def verts_padded(self) -> torch.Tensor:
        """``(B, V_max, 3)`` the vertices of every mesh, zero rows past its ``V_i``
        (pytorch3d's ``verts_padded``); differentiable in the vertices."""
        verts = self.verts_packed()
        v_max = max(self._conn.num_verts)
        out = verts.new_zeros(len(self) * v_max, 3)
        out = out.index_copy(0, self.verts_padded_to_packed_idx(), verts)
        return out.view(len(self), v_max, 3)

    def faces_padded(self) -> torch.Tensor:
        """``(B, F_max, K_max)`` int64 face corners with indices *local* to each mesh, ``-1``
        past each face's degree and past each mesh's ``F_i`` faces, on :attr:`device`.

        pytorch3d's ``faces_padded`` is this with ``K_max = 3`` (triangles); here ``K_max`` is
        the largest face degree of the batch, and face ``f`` of mesh ``i`` has degree
        ``(faces_padded()[i, f] >= 0).sum()``.
        """

        def make() -> torch.Tensor:
            conn = self._conn
            f_max = max(conn.num_faces)
            k_max = max((int(f.sizes.max()) for f in conn.faces if f.num_faces), default=3)
            out = torch.full((len(self), f_max, k_max), -1, dtype=torch.int64)
            for i, f in enumerate(conn.faces):
                if f.num_faces:
                    face = f.corner_face
                    corner = torch.arange(f.num_corners) - f.offsets[face]
                    out[i, face, corner] = f.indices
            return out.to(self.device)

        return self._conn.cached("faces_padded", self.device, make)

    def faces_packed_to_mesh_idx(self) -> torch.Tensor:
        """``(sum F_i,)`` the mesh of every packed face."""
        return self._packed_to_mesh_idx("f2m", self.num_faces_per_mesh)

    def topology(self) -> Topology:
        """The :class:`~torch_polylap.Topology` of the packed faces, built once.

        Errors that no polygon mesh may have (an index out of range, a face visiting a vertex
        twice) are re-raised as ``"mesh i: ..."`` with the mesh's own face and vertex indices.
        What keeps a mesh from being a consistently oriented manifold (non-manifold edges or
        vertices, flipped faces, a Moebius band, duplicated faces, isolated vertices) is not an
        error: one ``UserWarning`` names each such mesh and its findings in *local* indices
        (see :meth:`topology_reports`). The packed topology's own ``report`` uses *packed*
        indices (vertex ``j`` of mesh ``i`` is ``mesh_to_verts_packed_first_idx()[i] + j``).
        """
        conn = self._conn
        if conn.topology is None:
            total = sum(conn.num_verts)
            single = len(conn.faces) == 1
            faces = conn.source if conn.source is not None else conn.packed()
            try:
                if single:  # packed == local indices: build_topology's own warning is exact
                    topo = get_topology(faces, total)
                else:  # warn below, per mesh and in local indices
                    topo = build_topology(faces, total, warn=False)
            except ValueError:
                # the packed message names packed faces and vertices: find the mesh at fault
                # and report its own, local, message (only paid on failure)
                for i, (f, nv) in enumerate(zip(conn.faces, conn.num_verts, strict=True)):
                    try:
                        build_topology(f, nv, warn=False)
                    except ValueError as err:
                        raise ValueError(f"mesh {i}: {err}") from None
                raise
            conn.topology = topo
            if not single and not topo.report.is_clean:
                self._warn_per_mesh()
        return conn.topology

    def _local_topologies(self) -> dict[int, Topology]:
        """Mesh index -> its own :class:`Topology`, for every mesh whose report is not clean.

        The packed report says which packed vertices and faces are involved; only those meshes
        are rebuilt (once per connectivity, shared by derived batches).
        """
        conn = self._conn
        if conn.local is None:
            topo = self.topology()
            r = topo.report
            if r.is_clean:
                conn.local = {}
            elif len(conn.faces) == 1:
                conn.local = {0: topo}
            else:
                verts = np.concatenate(
                    [
                        r.non_manifold_edges.reshape(-1),
                        r.non_manifold_vertices,
                        r.misoriented_edges.reshape(-1),
                        r.isolated_vertices,
                    ]
                )
                v_first = np.cumsum([0, *conn.num_verts[:-1]])
                f_first = np.cumsum([0, *conn.num_faces[:-1]])
                meshes = np.union1d(
                    np.searchsorted(v_first, verts, side="right") - 1,
                    np.searchsorted(f_first, r.duplicate_faces, side="right") - 1,
                )
                local = {}
                for i in meshes.tolist():
                    t = build_topology(conn.faces[i], conn.num_verts[i], warn=False)
                    if not t.report.is_clean:
                        local[i] = t
                conn.local = local
        return conn.local

    def topology_reports(self) -> dict[int, TopologyReport]:
        """``{i: report}`` for every mesh ``i`` that is not a clean, consistently oriented
        2-manifold, each :class:`~torch_polylap.TopologyReport` in the mesh's own (local)
        vertex and face indices. Empty when every mesh is clean."""
        return {i: t.report for i, t in self._local_topologies().items()}

    def require_manifold(self, what: str, *, vertices: bool = True) -> None:
        """:meth:`Topology.require_manifold` for every mesh: a ValueError ``"mesh i: ..."``
        naming the first non-manifold mesh and its local edges and vertices."""
        if self.topology().is_manifold:
            return
        for i, t in sorted(self._local_topologies().items()):
            try:
                t.require_manifold(what, vertices=vertices)
            except ValueError as err:
                raise ValueError(f"mesh {i}: {err}") from None

    def require_oriented(self, what: str) -> None:
        """:meth:`Topology.require_oriented` for every mesh: a ValueError ``"mesh i: ..."``
        naming the first misoriented (or non-orientable) mesh and its local edges."""
        if self.topology().is_oriented:
            return
        for i, t in sorted(self._local_topologies().items()):
            try:
                t.require_oriented(what)
            except ValueError as err:
                raise ValueError(f"mesh {i}: {err}") from None

    def _warn_per_mesh(self) -> None:
        conn = self._conn
        local = self._local_topologies()
        if not local:
            return
        found = "; ".join(
            f"mesh {i} ({conn.num_verts[i]} vertices, {conn.num_faces[i]} faces): "
            f"{t.report.summary(conn.num_verts[i])}"
            for i, t in sorted(local.items())
        )
        warn_outside_package(
            f"{len(local)} of the {len(conn.faces)} meshes of the batch are not consistently "
            f"oriented 2-manifolds (indices local to each mesh): {found}. L and M0 are well "
            "defined on them; what needs a manifold or an orientation checks for itself. "
            "Inspect PolygonMeshes.topology_reports(); repairs (orient_faces, "
            "remove_duplicate_faces, ...) are in torch_polylap.repair."
        )

    def interior_edge_faces(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(f0, f1)``, each ``(E_I,)``: the two packed faces on each side of every interior
        edge (an edge used by exactly two faces), on :attr:`device`.

        Listed on any mesh: on a misoriented one the two faces of a flipped edge traverse it in
        the same direction (see :meth:`require_oriented`); edges used by 3+ faces
        (non-manifold) are left out, since no pair of faces there is "the two sides".
        """

        def make() -> tuple[torch.Tensor, torch.Tensor]:
            topo = self.topology()
            he_edge = topo.half_edge_edge
            he_face = topo.faces.corner_face
            order = torch.argsort(he_edge, stable=True)
            uses = topo.edge_faces
            first = torch.cumsum(uses, 0) - uses
            start = first[uses == 2]
            pair = he_face[order[start]], he_face[order[start + 1]]
            return pair[0].to(self.device), pair[1].to(self.device)

        return self._conn.cached("interior", self.device, make)

    def edges_packed(self) -> torch.Tensor:
        """``(E, 2)`` undirected edges ``(p, q)``, ``p < q``, of the packed mesh, on the device."""
        return self._conn.cached(
            "edges", self.device, lambda: self.topology().edges.to(self.device)
        )

    def half_edges_packed(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``(src, dst)``, each ``(N,)``: the half-edges of the packed faces (see
        :func:`~torch_polylap.dec.coboundary`), on :attr:`device`."""
        return self._conn.cached(
            "half_edges", self.device, lambda: half_edge_vertices(self.faces_packed())
        )

    # ----------------------------------------------------------------- operators

    def laplacian(
        self, lam: Lam = 1.0, *, validate: bool = True, method: str = "aw11"
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Block-diagonal ``(L, M0)``, each a ``(sum V_i, sum V_i)`` sparse operator (AW11 eq. 3,
        9, 10).

        One assembly over the packed faces; block ``i`` equals
        ``laplacian(verts_i, faces_i, lam, method=method)``. ``method``: ``"aw11"`` (default),
        ``"plms"`` (``lam`` unused), ``"degoes"`` or ``"diamond"`` (``lam`` unused; its ``M0``
        is not diagonal), as in :func:`~torch_polylap.laplacian`.
        Differentiable in the vertices with O(nnz) gradients (``L @ X``, ``L.diagonal()``).
        """
        return laplacian(
            self.verts_packed(), self.topology(), lam, validate=validate, method=method
        )

    def update_packed(self, new_verts_packed: torch.Tensor) -> PolygonMeshes:
        """A batch with the same faces (shared topology and caches) and new packed vertices."""
        total = sum(self._conn.num_verts)
        if not isinstance(new_verts_packed, torch.Tensor) or tuple(new_verts_packed.shape) != (
            total,
            3,
        ):
            shape = getattr(new_verts_packed, "shape", None)
            raise ValueError(
                f"new_verts_packed must have shape ({total}, 3) like verts_packed(), got "
                f"{tuple(shape) if shape is not None else type(new_verts_packed).__name__}."
            )
        if not new_verts_packed.is_floating_point():
            raise ValueError(
                f"new_verts_packed must be floating point, got {new_verts_packed.dtype}."
            )
        return PolygonMeshes._from_packed(self._conn, new_verts_packed)

    def offset_verts(self, offsets_packed: torch.Tensor) -> PolygonMeshes:
        """``update_packed(verts_packed() + offsets_packed)`` (pytorch3d's ``offset_verts``)."""
        return self.update_packed(self.verts_packed() + offsets_packed)

    def to(self, *args: Any, **kwargs: Any) -> PolygonMeshes:
        """The batch with its vertices moved or cast as :meth:`torch.Tensor.to` would move them
        (connectivity and its caches shared).

        Takes torch's forms (see :func:`to_arguments`): ``to(dtype)``, ``to(device)``,
        ``to(device, dtype)``, ``to(tensor)`` (its device and dtype), with ``non_blocking``
        and ``copy`` positionally after them or as keywords, and ``device=``/``dtype=``
        keywords. The dtype must be floating point.
        """
        move = to_arguments(*args, **kwargs)
        return self.update_packed(move.apply(self.verts_packed()))

    def detach(self) -> PolygonMeshes:
        """The batch with detached vertices (connectivity shared)."""
        return self.update_packed(self.verts_packed().detach())
