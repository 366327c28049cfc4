"""Conversions to and from the mesh types of pytorch3d, PyTorch Geometric and trimesh.

Every adapter keeps the vertex tensor as it is (same dtype and device, autograd graph intact),
so a loss computed on the converted mesh back-propagates to the polygon mesh's vertices.

pytorch3d
    ``Meshes`` holds triangles only. :func:`to_pytorch3d` triangulates every polygon with
    :func:`torch_polylap.io.triangulate_faces` (the fan ``(c0, c_j, c_{j+1})`` for faces convex
    in their maximal-projection plane, ear clipping otherwise; orientation kept; planar faces
    tiled exactly) and keeps the vertices, so per-vertex data lines up.
    :func:`from_pytorch3d` reads ``verts_list()``/``faces_list()``: the result is a triangle
    batch (the polygons a ``Meshes`` came from are not recoverable from it).

PyTorch Geometric (``torch_geometric.data.Data``)
    ``pos`` is ``(V, 3)``. torch_geometric stores triangles column-wise as ``face`` ``(3, F)``
    and offsets it by the nodes before it when it batches graphs. For polygon meshes:

    * every face of degree ``k`` (a uniform mesh, quads included): ``face`` is ``(k, F)``;
    * faces of mixed degree: no ``face``; ``polygon_index`` ``(N,)`` holds the corners of all
      faces concatenated, each face in its cyclic order, and ``polygon_sizes`` ``(F,)`` the
      degree of every face (:class:`~torch_polylap.PolygonFaces`' ``indices`` and ``sizes``).
      The ``_index`` suffix makes ``Batch.from_data_list`` offset it by the nodes before it,
      the same as ``face``, and ``Batch.to_data_list`` undo that;
    * ``triangulate=True``: ``face`` is the ``(3, T)`` triangulation (what torch_geometric's
      face-based transforms, ``FaceToEdge``, ``GenerateMeshNormals``, ``SamplePoints``, expect;
      they read any ``(k, F)`` ``face`` as triangles), and unless every face is a triangle the
      polygons are kept in ``polygon_index``/``polygon_sizes``.

    A batch (:class:`~torch_polylap.PolygonMeshes`) is converted mesh by mesh with one
    representation for all (``face (k, F)`` only when every mesh has the same uniform degree
    ``k``) and returned as a ``Batch``. :func:`from_pyg` reads, in this order of precedence,
    ``polygons`` (anything :func:`~torch_polylap.as_faces` accepts), ``polygon_index`` with
    ``polygon_sizes``, or ``face`` ``(k, F)``.

trimesh
    :func:`from_trimesh` and :func:`to_trimesh` (from :mod:`torch_polylap.io`, re-exported).

scipy
    Operators convert with :func:`torch_polylap.sparse.to_scipy` and
    :func:`torch_polylap.sparse.from_scipy`.
"""

from __future__ import annotations

from typing import Any

import torch

from .batch import PolygonMeshes
from .faces import FacesLike, PolygonFaces
from .io import from_trimesh, to_trimesh, triangulate_faces

__all__ = [
    "from_pyg",
    "from_pytorch3d",
    "from_trimesh",
    "to_pyg",
    "to_pytorch3d",
    "to_trimesh",
    "triangle_faces",
]

_PYTORCH3D_INSTALL = (
    "to_pytorch3d needs pytorch3d, which is not installed (it is not on PyPI for most torch "
    "versions and has no extra here). Install it as its INSTALL.md says, e.g. "
    "`pip install 'git+https://github.com/facebookresearch/pytorch3d.git@stable'` or "
    "`conda install pytorch3d -c pytorch3d`, or use triangle_faces(verts, faces) to get the "
    "triangles without it."
)
_PYG_INSTALL = (
    "to_pyg needs torch_geometric, which is not installed: `pip install torch_geometric` "
    "(pure Python; the optional compiled extensions are not needed here)."
)


def _mesh_lists(
    meshes: PolygonMeshes | torch.Tensor, faces: FacesLike | None, name: str
) -> tuple[list[torch.Tensor], list[PolygonFaces], PolygonMeshes | None]:
    """``(verts_list, faces_list, batch)`` of a batch or of one ``(verts, faces)`` mesh."""
    if isinstance(meshes, PolygonMeshes):
        if faces is not None:
            raise TypeError(f"{name}: pass a PolygonMeshes alone, or verts and faces.")
        return meshes.verts_list(), meshes.faces_list(), meshes
    if faces is None:
        raise TypeError(
            f"{name} takes a PolygonMeshes, or the verts (V, 3) and faces of one mesh; "
            f"got {type(meshes).__name__} without faces."
        )
    batch = PolygonMeshes([meshes], [faces])  # validates shapes and index ranges
    return batch.verts_list(), batch.faces_list(), None


def triangle_faces(
    meshes: PolygonMeshes | torch.Tensor, faces: FacesLike | None = None
) -> torch.Tensor | list[torch.Tensor]:
    """The triangles :func:`to_pytorch3d` (and ``to_pyg(triangulate=True)``) hand over.

    Args:
        meshes: a :class:`~torch_polylap.PolygonMeshes`, or the ``(V, 3)`` vertices of one mesh.
        faces: the faces of that one mesh (anything :func:`~torch_polylap.as_faces` accepts).

    Returns:
        For one mesh, ``(T, 3)`` int64 vertex indices on the vertices' device, ``T = sum_f
        (k_f - 2)``, face ``f``'s triangles consecutive and in face order; for a batch, one such
        tensor per mesh with indices local to it. The choice of triangles depends on the
        positions (fan or ear clipping, see :func:`torch_polylap.io.triangulate_faces`) but is
        a constant for autograd; the areas of the triangles of a planar face add up to the
        face's area.
    """
    verts_list, faces_list, batch = _mesh_lists(meshes, faces, "triangle_faces")
    if batch is None:
        v = verts_list[0]
        return torch.from_numpy(triangulate_faces(v, faces_list[0])).to(v.device)
    # one triangulation of the packed mesh, split per mesh and shifted back to local indices
    packed = batch.faces_packed()
    tris = torch.from_numpy(triangulate_faces(batch.verts_packed(), packed))
    per_mesh = torch.zeros(len(batch), dtype=torch.int64).index_add_(
        0, batch.faces_packed_to_mesh_idx().cpu(), packed.sizes.cpu() - 2
    )
    first = batch.mesh_to_verts_packed_first_idx().cpu()
    return [
        (t - first[i]).to(batch.device) for i, t in enumerate(torch.split(tris, per_mesh.tolist()))
    ]


def to_pytorch3d(meshes: PolygonMeshes | torch.Tensor, faces: FacesLike | None = None) -> Any:
    """A ``pytorch3d.structures.Meshes`` of a polygon mesh or batch, faces triangulated.

    Args:
        meshes: a :class:`~torch_polylap.PolygonMeshes`, or the ``(V, 3)`` vertices of one mesh.
        faces: the faces of that one mesh.

    Returns:
        ``Meshes(verts=verts_list, faces=triangles)`` with :func:`triangle_faces`' triangles and
        the vertex tensors themselves (same dtype and device; gradients flow back to them).

    Raises:
        ImportError: pytorch3d is not installed (the message says how to install it).
    """
    verts_list, _, batch = _mesh_lists(meshes, faces, "to_pytorch3d")
    tris = triangle_faces(meshes, faces)
    try:
        from pytorch3d.structures import Meshes
    except ImportError as err:
        raise ImportError(_PYTORCH3D_INSTALL) from err
    return Meshes(verts=list(verts_list), faces=[tris] if batch is None else tris)


def from_pytorch3d(meshes: Any) -> PolygonMeshes:
    """A :class:`~torch_polylap.PolygonMeshes` (triangles) of a ``pytorch3d.structures.Meshes``.

    Reads ``verts_list()`` and ``faces_list()`` only (pytorch3d is not imported); the vertex
    tensors keep their autograd graph. Polygons triangulated by :func:`to_pytorch3d` stay
    triangles: ``Meshes`` does not record them.
    """
    return PolygonMeshes.from_pytorch3d(meshes)


def _pyg_attributes(
    verts: torch.Tensor, faces: PolygonFaces, degree: int | None, triangulate: bool
) -> dict[str, torch.Tensor]:
    dev = verts.device
    if triangulate:
        out = {"face": torch.from_numpy(triangulate_faces(verts, faces)).t().contiguous()}
        if degree == 3:
            return {"face": out["face"].to(dev)}
    elif degree is not None:
        return {"face": faces.indices.view(-1, degree).t().contiguous().to(dev)}
    else:
        out = {}
    out["polygon_index"] = faces.indices
    out["polygon_sizes"] = faces.sizes
    return {key: value.to(dev) for key, value in out.items()}


def _uniform_degree(faces_list: list[PolygonFaces]) -> int | None:
    """The degree ``k`` every face of every mesh has, else ``None``."""
    sizes = torch.cat([f.sizes.cpu() for f in faces_list])
    if sizes.numel() == 0:
        return 3
    k = int(sizes[0])
    return k if bool((sizes == k).all()) else None


def to_pyg(
    meshes: PolygonMeshes | torch.Tensor,
    faces: FacesLike | None = None,
    *,
    triangulate: bool = False,
) -> Any:
    """A torch_geometric ``Data`` (one mesh) or ``Batch`` (a :class:`PolygonMeshes`).

    Args:
        meshes: a :class:`~torch_polylap.PolygonMeshes`, or the ``(V, 3)`` vertices of one mesh.
        faces: the faces of that one mesh.
        triangulate: ``face`` holds the ``(3, T)`` triangulation (:func:`triangle_faces`), and
            the polygons move to ``polygon_index``/``polygon_sizes`` (unless all are triangles).

    Returns:
        ``Data(pos=verts, face=...)``: ``face`` ``(k, F)`` when every face has degree ``k``;
        for mixed degrees ``polygon_index`` ``(N,)`` and ``polygon_sizes`` ``(F,)`` instead
        (see the module docstring). ``pos`` is the vertex tensor itself (gradients flow back);
        the index tensors are int64 on its device. A batch gives
        ``Batch.from_data_list([...])``, whose ``face``/``polygon_index`` carry global indices
        like :meth:`PolygonMeshes.faces_packed` and whose ``batch`` equals
        :meth:`PolygonMeshes.verts_packed_to_mesh_idx`.

    Raises:
        ImportError: torch_geometric is not installed.
    """
    verts_list, faces_list, batch = _mesh_lists(meshes, faces, "to_pyg")
    try:
        from torch_geometric.data import Batch, Data
    except ImportError as err:
        raise ImportError(_PYG_INSTALL) from err
    degree = _uniform_degree(faces_list)
    data = [
        Data(pos=v, **_pyg_attributes(v, f, degree, triangulate))
        for v, f in zip(verts_list, faces_list, strict=True)
    ]
    return data[0] if batch is None else Batch.from_data_list(data)


def _pyg_faces(d: Any, i: int) -> FacesLike:
    """The faces of one torch_geometric graph (see :func:`from_pyg` for the attributes)."""
    polys = getattr(d, "polygons", None)
    if polys is not None:
        return polys
    index, sizes = getattr(d, "polygon_index", None), getattr(d, "polygon_sizes", None)
    if index is not None or sizes is not None:
        if index is None or sizes is None:
            raise ValueError(
                f"graph {i} has only one of `polygon_index` and `polygon_sizes`; polygon "
                "faces need both (the corners of all faces, and every face's degree)."
            )
        return PolygonFaces(index.cpu(), sizes=sizes.cpu())
    face = getattr(d, "face", None)
    if face is None:
        raise ValueError(
            f"graph {i} has no faces: a mesh needs `face` (k, F), or `polygon_index` with "
            "`polygon_sizes`, or `polygons`."
        )
    if not isinstance(face, torch.Tensor) or face.dim() != 2 or face.shape[0] < 3:
        shape = tuple(face.shape) if hasattr(face, "shape") else type(face).__name__
        raise ValueError(
            f"graph {i}: `face` must have shape (3, F) for triangles, or (k, F) for faces of "
            f"k >= 3 corners (torch_geometric stores faces column-wise), got {shape}; for "
            "faces of mixed degree use `polygon_index` and `polygon_sizes`."
        )
    return face.t().cpu()


def _pyg_items(data: Any) -> list[Any]:
    if hasattr(data, "to_data_list"):
        return data.to_data_list()
    if hasattr(data, "pos"):
        return [data]
    return list(data)


def _pyg_meshes(data: Any) -> PolygonMeshes:
    """A :class:`~torch_polylap.PolygonMeshes` of a ``Data``, a list of them, or a ``Batch``."""
    verts, faces = [], []
    for i, d in enumerate(_pyg_items(data)):
        pos = getattr(d, "pos", None)
        if pos is None:
            raise ValueError(f"graph {i} needs `pos` (V, 3) to be a mesh.")
        faces.append(_pyg_faces(d, i))
        verts.append(pos)
    return PolygonMeshes(verts, faces)


def from_pyg(data: Any) -> tuple[torch.Tensor, PolygonFaces] | PolygonMeshes:
    """Polygon meshes from torch_geometric graphs (the inverse of :func:`to_pyg`).

    Args:
        data: one ``Data``, a list of them, or a ``Batch`` (split with ``to_data_list()``).
            Each needs ``pos`` ``(V, 3)`` and faces: ``polygons`` (anything
            :func:`~torch_polylap.as_faces` accepts), else ``polygon_index`` ``(N,)`` with
            ``polygon_sizes`` ``(F,)``, else ``face`` ``(k, F)`` (triangles ``(3, F)``, quads
            ``(4, F)``, ...). Only these attributes are read; torch_geometric is not imported.

    Returns:
        For one ``Data``, ``(verts, faces)``: ``pos`` itself and :class:`PolygonFaces` on the
        CPU; for a list or a ``Batch``, a :class:`~torch_polylap.PolygonMeshes`.

    Raises:
        ValueError: no ``pos``, no faces, a ``face`` that is not ``(k >= 3, F)``, or a face
            index out of range (naming the graph).
    """
    single = hasattr(data, "pos") and not hasattr(data, "to_data_list")
    meshes = _pyg_meshes(data)
    return meshes[0] if single else meshes
