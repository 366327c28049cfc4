"""Conversions to and from the mesh types of pytorch3d, PyTorch Geometric and trimesh, and
DiffusionNet's operators of a polygon mesh.

Every mesh adapter keeps the vertex tensor as it is (same dtype and device, autograd graph
intact), so a loss computed on the converted mesh back-propagates to the polygon mesh's
vertices. DiffusionNet's operators are precomputed and carry no gradient, as DiffusionNet's own.

pytorch3d
    ``Meshes`` holds triangles only. :func:`to_pytorch3d` triangulates every polygon with
    :func:`torch_polylap.triangulate.triangulate_faces` (the fan ``(c0, c_j, c_{j+1})`` for
    faces convex in their maximal-projection plane, ear clipping otherwise; orientation kept;
    planar faces tiled exactly) and keeps the vertices, so per-vertex data lines up.
    :func:`from_pytorch3d` reads ``verts_list()``/``faces_list()``: the result is a triangle
    batch (the polygons a ``Meshes`` came from are not recoverable from it).

PyTorch Geometric (``torch_geometric.data.Data``)
    ``pos`` is ``(V, 3)`` and ``edge_index`` ``(2, 2E)`` the mesh's ``E`` undirected edges in
    both directions, sorted by source then target (what ``torch_geometric.utils.to_undirected``
    returns). torch_geometric's ``face`` is ``(3, F)`` triangles (its ``FaceToEdge`` reads a
    ``(4, F)`` ``face`` as tetrahedra), so:

    * a mesh (or batch) of triangles only: ``face`` ``(3, F)``, as torch_geometric stores it;
    * any other mesh: no ``face``; ``polygon_index`` ``(N,)`` holds the corners of all faces
      concatenated, each face in its cyclic order, and ``polygon_sizes`` ``(F,)`` the degree of
      every face (:class:`~torch_polylap.PolygonFaces`' ``indices`` and ``sizes``). The
      ``_index`` suffix makes ``Batch.from_data_list`` offset it by the nodes before it, the
      same as ``face`` and ``edge_index``, and ``Batch.to_data_list`` undo that. No ``face``
      can carry polygons through torch_geometric's ``FaceToEdge``: it reads ``(3, F)`` as
      triangles and ``(4, F)`` as tetrahedra, so any ``face`` adds diagonals (20 edges instead
      of 12 on a 2 x 2 quad grid). ``edge_index`` holds the edges already: leave
      ``FaceToEdge`` out for polygon meshes (torch_geometric 2.8's raises an
      ``AssertionError`` on a graph without ``face``);
    * ``triangulate=True``: ``face`` is the ``(3, T)`` triangulation (for ``SamplePoints``,
      ``GenerateMeshNormals`` and other transforms that need triangles), and unless every face
      is a triangle the polygons are kept in ``polygon_index``/``polygon_sizes``. ``FaceToEdge``
      then replaces ``edge_index`` by the triangulation's edges, diagonals included;
    * ``laplacian=True``: ``edge_index`` is the off-diagonal pattern of ``L`` and
      ``edge_weight`` the entries ``-L_pq`` (see :func:`to_pyg`), so that
      ``torch_geometric.utils.get_laplacian(edge_index, edge_weight)`` is ``L``.

    A batch (:class:`~torch_polylap.PolygonMeshes`) is converted mesh by mesh with one
    representation for all (``face`` only when every mesh is all triangles) and returned as a
    ``Batch``. :func:`from_pyg` reads, in this order of precedence, ``polygons`` (anything
    :func:`~torch_polylap.as_faces` accepts), ``polygon_index`` with ``polygon_sizes``, or
    ``face`` ``(3, F)``.

DiffusionNet
    :func:`to_diffusionnet` returns the seven operators of DiffusionNet's
    ``geometry.get_operators`` (frames, mass, ``L``, eigenpairs, ``gradX``, ``gradY``) in its
    format, built from this package's polygon operators.

trimesh
    :func:`from_trimesh` reads a ``trimesh.Trimesh`` (triangles); :func:`to_trimesh` triangulates
    the polygons as :func:`to_pytorch3d` does, keeping the vertex order.

scipy
    Operators convert with :func:`torch_polylap.sparse.to_scipy` and
    :func:`torch_polylap.sparse.from_scipy`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ._typing import MeshFaces
from .batch import PolygonMeshes
from .checks import check_int, check_verts, check_verts_array
from .faces import FacesLike, PolygonFaces, as_faces
from .kernels import check_method
from .linalg import eigs
from .operators import laplacian as mesh_laplacian
from .sparse import as_operator, sparse_values, to_torch_sparse
from .spectral import check_cache_dir, eigs_through_cache
from .tangent import tangent_frames, vertex_gradient_operators
from .topology import Topology, get_topology
from .triangulate import triangulate_faces

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "from_pyg",
    "from_pytorch3d",
    "from_trimesh",
    "to_diffusionnet",
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
        positions (fan or ear clipping, see
        :func:`torch_polylap.triangulate.triangulate_faces`) but is a constant for autograd; the
        areas of the triangles of a planar face add up to the face's area.
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
    if not (hasattr(meshes, "verts_list") and hasattr(meshes, "faces_list")):
        raise TypeError(
            f"from_pytorch3d needs a pytorch3d Meshes (verts_list/faces_list), got "
            f"{type(meshes).__name__}."
        )
    return PolygonMeshes(list(meshes.verts_list()), list(meshes.faces_list()))


# ------------------------------------------------------------------------------------ trimesh


def from_trimesh(
    mesh: trimesh.Trimesh,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, PolygonFaces]:
    """Convert a :class:`trimesh.Trimesh` to ``(verts, faces)``.

    The result is a triangle mesh (trimesh only stores triangles); use
    :func:`~torch_polylap.read_mesh` to load polygon files without triangulating them.

    Args:
        mesh: the triangle mesh; its vertex order and face order are kept.
        dtype: floating dtype of the returned vertex tensor.
        device: device of the returned vertex tensor (faces stay on the CPU).

    Returns:
        ``(verts, faces)``: a ``(V, 3)`` tensor and :class:`PolygonFaces` of ``F`` triangles.

    Raises:
        TypeError: ``mesh`` is a :class:`trimesh.Scene` or not a mesh at all.
    """
    import trimesh

    if isinstance(mesh, trimesh.Scene):
        raise TypeError(
            "from_trimesh got a trimesh.Scene; merge it into one mesh first, e.g. with "
            "scene.to_geometry() or trimesh.load(path, force='mesh')."
        )
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"from_trimesh needs a trimesh.Trimesh, got {type(mesh).__name__}.")
    verts = torch.tensor(np.asarray(mesh.vertices, dtype=np.float64), dtype=dtype, device=device)
    return verts, as_faces(np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3))


def to_trimesh(verts: torch.Tensor | np.ndarray, faces: FacesLike) -> trimesh.Trimesh:
    """Triangulate a polygon mesh into a :class:`trimesh.Trimesh` (for viewing or export).

    Uses :func:`~torch_polylap.triangulate.triangulate_faces`: faces convex in their
    maximal-projection plane become the fan ``(c0, c_j, c_{j+1})``, non-convex ones are
    ear-clipped, and every triangle keeps the polygon's orientation.  The mesh is built with
    ``process=False`` so the vertex order, and hence per-vertex data, is kept.

    Args:
        verts: ``(V, 3)`` vertex positions (tensor or array).
        faces: anything :func:`~torch_polylap.faces.as_faces` accepts.

    Returns:
        A ``trimesh.Trimesh`` with ``V`` vertices and ``sum_f (k_f - 2)`` triangles, face
        ``f``'s consecutive and in face order.

    Raises:
        ValueError: ``verts`` is not of shape ``(V, 3)`` or ``faces`` cannot be interpreted.
    """
    import trimesh

    v = check_verts_array(verts)
    return trimesh.Trimesh(vertices=v, faces=triangulate_faces(v, faces), process=False)


# ------------------------------------------------------------------------- torch_geometric


def _undirected_edges(faces: PolygonFaces, num_verts: int) -> torch.Tensor:
    """``(2, 2E)`` int64: every edge of the mesh in both directions, sorted by source, then
    target (torch_geometric's coalesced order)."""
    edges = get_topology(faces, num_verts).edges  # (E, 2)
    both = torch.cat((edges, edges.flip(1))).t()
    return both[:, torch.argsort(both[0] * num_verts + both[1])]


def _laplacian_edges(verts: torch.Tensor, faces: PolygonFaces) -> dict[str, torch.Tensor]:
    """``edge_index`` ``(2, nnz - V)``, the off-diagonal pattern of ``L`` (CSR order: sorted by
    row, then column), and ``edge_weight`` the entries ``-L_pq`` (differentiable)."""
    L, _ = mesh_laplacian(verts, faces)
    A = as_operator(L)
    pattern, values = A.pattern, sparse_values(A)
    off = pattern.row != pattern.col
    return {
        "edge_index": torch.stack((pattern.row[off], pattern.col[off])),
        "edge_weight": -values[off],
    }


def _pyg_attributes(
    verts: torch.Tensor,
    faces: PolygonFaces,
    *,
    triangles: bool,
    triangulate: bool,
    with_laplacian: bool,
) -> dict[str, torch.Tensor]:
    """The attributes of one mesh's ``Data`` (see the module docstring)."""
    dev = verts.device
    out: dict[str, torch.Tensor] = {}
    if with_laplacian:
        out.update(_laplacian_edges(verts, faces))
    else:
        out["edge_index"] = _undirected_edges(faces, verts.shape[0])
    if triangles:
        out["face"] = faces.indices.view(-1, 3).t()
    else:
        if triangulate:
            out["face"] = torch.from_numpy(triangulate_faces(verts, faces)).t()
        out["polygon_index"] = faces.indices
        out["polygon_sizes"] = faces.sizes
    return {key: value.contiguous().to(dev) for key, value in out.items()}


def to_pyg(
    meshes: PolygonMeshes | torch.Tensor,
    faces: FacesLike | None = None,
    *,
    triangulate: bool = False,
    laplacian: bool = False,
) -> Any:
    """A torch_geometric ``Data`` (one mesh) or ``Batch`` (a :class:`PolygonMeshes`).

    ``edge_index`` holds the mesh's edges, in both directions and coalesced (12 undirected
    edges on a 2 x 2 quad grid; torch_geometric's ``to_undirected`` and ``coalesce`` leave it
    as it is). Triangle meshes also get ``face`` ``(3, F)``, from which ``FaceToEdge`` rebuilds
    the same ``edge_index``; other meshes get no ``face`` (torch_geometric's ``face`` holds
    triangles or tetrahedra), so leave ``FaceToEdge`` out for them: ``edge_index`` is there.

    Args:
        meshes: a :class:`~torch_polylap.PolygonMeshes`, or the ``(V, 3)`` vertices of one mesh.
        faces: the faces of that one mesh.
        triangulate: for meshes that are not all triangles, put the ``(3, T)`` triangulation
            (:func:`triangle_faces`) in ``face`` for torch_geometric's triangle transforms
            (``SamplePoints``, ``GenerateMeshNormals``); the polygons stay in
            ``polygon_index``/``polygon_sizes``. ``FaceToEdge`` then gives the triangulation's
            edges, diagonals included.
        laplacian: ``edge_index`` is the off-diagonal pattern of the AW11 ``L``
            (:func:`torch_polylap.laplacian` with its defaults) and ``edge_weight``, one entry
            per column, holds ``-L_pq``: torch_geometric's sign for edge weights, so that
            ``get_laplacian(edge_index, edge_weight)`` (``normalization=None``) builds
            ``D - W = L`` (``L`` has zero row sums). On triangles ``-L_pq`` is the cotangent
            weight ``(cot a + cot b) / 2``, positive on Delaunay edges and negative where the
            opposite angles add up to more than pi; on polygons it can be negative too. In
            faces of more than three corners ``L`` couples every pair of corners, so
            ``edge_index`` then holds the mesh's edges and these diagonals. ``edge_weight`` is
            differentiable in the vertices.

    Returns:
        ``Data(pos=verts, edge_index=..., face=... | polygon_index=..., polygon_sizes=...)`` as
        the module docstring describes: ``face`` ``(3, F)`` when every face is a triangle, else
        ``polygon_index`` ``(N,)`` and ``polygon_sizes`` ``(F,)``. ``pos`` is the vertex tensor
        itself (gradients flow back); index tensors are int64 on its device. A batch gives
        ``Batch.from_data_list([...])``, whose ``face``/``polygon_index``/``edge_index`` carry
        global indices like :meth:`PolygonMeshes.faces_packed` and whose ``batch`` equals
        :meth:`PolygonMeshes.verts_packed_to_mesh_idx`.

    Raises:
        ImportError: torch_geometric is not installed.

    Examples:
        >>> import torch
        >>> from torch_geometric.transforms import FaceToEdge
        >>> import torch_polylap as tp
        >>> verts, faces = tp.shapes.quad_grid(2)
        >>> data = tp.to_pyg(verts, faces)
        >>> data.edge_index.shape[1] // 2, "face" in data  # the 12 edges of the 2 x 2 grid
        (12, False)
        >>> square = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> tri = tp.to_pyg(square, [[0, 1, 2], [0, 2, 3]])  # triangles: `face` (3, F) too
        >>> torch.equal(FaceToEdge()(tri.clone()).edge_index, tri.edge_index)
        True
    """
    verts_list, faces_list, batch = _mesh_lists(meshes, faces, "to_pyg")
    try:
        from torch_geometric.data import Batch, Data
    except ImportError as err:
        raise ImportError(_PYG_INSTALL) from err
    triangles = all(bool((f.sizes == 3).all()) for f in faces_list)
    options = {"triangles": triangles, "triangulate": triangulate, "with_laplacian": laplacian}
    data = [
        Data(pos=v, **_pyg_attributes(v, f, **options))
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
            f"graph {i} has no faces: a mesh needs `face` (3, F), or `polygon_index` with "
            "`polygon_sizes`, or `polygons`."
        )
    if not isinstance(face, torch.Tensor) or face.dim() != 2 or face.shape[0] != 3:
        shape = tuple(face.shape) if hasattr(face, "shape") else type(face).__name__
        raise ValueError(
            f"graph {i}: `face` must have shape (3, F), triangles stored column-wise as "
            f"torch_geometric stores them, got {shape} (torch_geometric reads a (4, F) `face` "
            "as tetrahedra). For polygons set `polygon_index` (the corners of all faces, face "
            "after face) and `polygon_sizes` (each face's degree): for quads in a (4, F) "
            "tensor `q`, polygon_index=q.t().reshape(-1) and polygon_sizes=torch.full((F,), 4)."
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
            ``polygon_sizes`` ``(F,)``, else ``face`` ``(3, F)`` triangles. ``edge_index`` is
            not read. Only these attributes are read; torch_geometric is not imported.

    Returns:
        For one ``Data``, ``(verts, faces)``: ``pos`` itself and :class:`PolygonFaces` on the
        CPU; for a list or a ``Batch``, a :class:`~torch_polylap.PolygonMeshes`.

    Raises:
        ValueError: no ``pos``, no faces, a ``face`` that is not ``(3, F)`` (torch_geometric
            reads ``(4, F)`` as tetrahedra; the message says how to pass quads), or a face
            index out of range (naming the graph).
    """
    single = hasattr(data, "pos") and not hasattr(data, "to_data_list")
    meshes = _pyg_meshes(data)
    return meshes[0] if single else meshes


# ------------------------------------------------------------------------------- DiffusionNet


def to_diffusionnet(
    verts: torch.Tensor,
    faces: MeshFaces,
    k_eig: int = 128,
    cache_dir: str | Path | None = None,
    *,
    lam: float = 1.0,
    method: str = "aw11",
) -> tuple[torch.Tensor, ...]:
    """DiffusionNet's operators of a polygon mesh, in the format of its ``get_operators``.

    ``frames, mass, L, evals, evecs, gradX, gradY = to_diffusionnet(verts, faces)`` go into the
    official ``DiffusionNet.forward(x, mass, L, evals, evecs, gradX, gradY)`` as the output of
    ``diffusion_net.geometry.get_operators`` would; DiffusionNet itself is not imported.

    What each is, and how it compares with DiffusionNet's own (triangle meshes):

    - ``L``: this package's weak Laplacian (``method``: ``"aw11"``, ``"plms"``, ``"degoes"``;
      see :func:`torch_polylap.laplacian`), positive semi-definite like DiffusionNet's. On
      triangles AW11 is the cotangent Laplacian DiffusionNet builds.
    - ``mass``: the diagonal of the lumped mass ``M0``; on triangles a third of the areas of
      the triangles around each vertex, DiffusionNet's vertex areas (it adds ``1e-8`` times
      their mean; this does not).
    - ``evals``, ``evecs``: the ``k_eig`` smallest eigenpairs of ``L phi = mu M0 phi``
      (:func:`torch_polylap.eigs`), ascending, ``M0``-orthonormal, eigenvalues clipped at zero
      as DiffusionNet clips them.
    - ``frames``: ``(e_x, e_y, n)`` per vertex, DiffusionNet's order (``frames[:, 2]`` is the
      normal), from :func:`~torch_polylap.tangent.vertex_tangent_frames` (area-weighted normals; the
      tangent axis is chosen otherwise than DiffusionNet's, which its gradient features do not
      see: they are invariant to the choice).
    - ``gradX``, ``gradY``: the tangent gradient in the frames,
      :func:`~torch_polylap.tangent.vertex_gradient_operators` (the area-weighted mean of the face
      gradients around a vertex, exact for linear functions; DiffusionNet fits a gradient to
      the edges by least squares).

    Args:
        verts: ``(V, 3)`` vertex positions, float32 or float64, any device.
        faces: polygon faces in any form :func:`~torch_polylap.as_faces` accepts, or a
            :class:`~torch_polylap.Topology`.
        k_eig: number of eigenpairs, ``0 <= k_eig < V`` (``0``: empty ``evals`` and
            ``evecs``, as DiffusionNet gives for ``diffusion_method="implicit_dense"``).
        cache_dir: folder of an eigenpair cache (created when missing), as DiffusionNet's
            ``op_cache_dir``; entries are keyed by a hash of the positions, the faces,
            ``k_eig``, ``method`` and ``lam`` and shared with :func:`torch_polylap.cached_eigs`
            (and so with :class:`torch_polylap.datasets.PolygonMeshDataset`). The other
            operators are recomputed on every call (one assembly each, no eigensolve). A cache
            that cannot be written (read-only, a path through a file) gives a
            :class:`~torch_polylap.spectral.CacheWriteWarning` (once per folder and process)
            and the uncached result; an unreadable entry gives a warning and is recomputed.
        lam: the AW11 parameter ``lambda`` (see :func:`torch_polylap.laplacian`).
        method: ``"aw11"``, ``"plms"`` or ``"degoes"``.

    Returns:
        ``(frames, mass, L, evals, evecs, gradX, gradY)``, all on ``verts``' device in its
        dtype (computed in float64 on the CPU, as DiffusionNet computes them, then cast):
        ``frames`` ``(V, 3, 3)``, ``mass`` ``(V,)``, ``evals`` ``(k_eig,)``, ``evecs``
        ``(V, k_eig)`` dense; ``L``, ``gradX``, ``gradY`` ``(V, V)`` coalesced torch sparse COO
        tensors with int64 indices. None carries a gradient (precomputed operators, as in
        DiffusionNet); for differentiable ones use :func:`torch_polylap.laplacian`,
        :func:`torch_polylap.eigs` and :func:`~torch_polylap.tangent.vertex_gradient_operators`.

    Raises:
        ValueError: no faces (DiffusionNet's point-cloud operators are not built here), an
            invalid mesh, ``k_eig`` out of range, or a ``cache_dir`` that names a file.
    """
    k_eig, cache = _check_diffusionnet_args(verts, faces, k_eig, cache_dir, method)
    n = verts.shape[0]
    topo = get_topology(faces, n)  # cached on a faces tensor across calls
    v64 = verts.detach().to(device="cpu", dtype=torch.float64)
    with torch.no_grad():
        L, M0 = mesh_laplacian(v64, topo, lam, method=method)
        normal, e_x, e_y = tangent_frames(v64, topo)
        grad_x, grad_y = vertex_gradient_operators(v64, topo, frames=(e_x, e_y))
        if k_eig == 0:
            evals, evecs = v64.new_zeros(0), v64.new_zeros(n, 0)
        elif cache is None:
            evals, evecs = eigs(L, M0, k_eig)
        else:
            evals, evecs = eigs_through_cache(v64, topo, k_eig, cache, lam, method, (L, M0))

    def cast(t: torch.Tensor) -> torch.Tensor:
        return t.to(device=verts.device, dtype=verts.dtype)

    def coo(A: torch.Tensor) -> torch.Tensor:
        return cast(to_torch_sparse(A, layout=torch.sparse_coo)).coalesce()

    frames = torch.stack((e_x, e_y, normal), dim=1)  # frames[v, i] is axis i of vertex v
    return (
        cast(frames),
        cast(M0.diagonal()),
        coo(L),
        cast(evals.clamp_min(0)),
        cast(evecs),
        coo(grad_x),
        coo(grad_y),
    )


def _check_diffusionnet_args(
    verts: torch.Tensor,
    faces: MeshFaces,
    k_eig: int,
    cache_dir: str | Path | None,
    method: str,
) -> tuple[int, Path | None]:
    """Check :func:`to_diffusionnet`'s arguments before any work: ``k_eig`` as an int, and the
    cache folder or None."""
    check_verts(verts)
    check_method(method, diagonal_mass="to_diffusionnet")
    k_eig = check_int(k_eig, "k_eig", least=0)
    n = verts.shape[0]
    if not 0 <= k_eig < n:
        raise ValueError(
            f"to_diffusionnet: k_eig={k_eig} eigenpairs of a mesh with {n} vertices; pass "
            f"0 <= k_eig < {n} (0 for DiffusionNet's implicit_dense diffusion)."
        )
    cache = None if cache_dir is None else Path(cache_dir)
    if cache is not None:
        check_cache_dir(cache)  # before any work
    given = faces.faces if isinstance(faces, Topology) else as_faces(faces)
    if given.num_faces == 0:
        raise ValueError(
            "to_diffusionnet needs a mesh with faces; for a point cloud use DiffusionNet's own "
            "diffusion_net.geometry.get_operators."
        )
    return k_eig, cache
