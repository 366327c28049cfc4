"""The connection Laplacian of a polygon mesh: the scalar Laplacian with the transport inserted.

Every polygon Laplacian of the package is a sum of per-face blocks,
``L = sum_f P_f^T L_f P_f`` with ``L_f 1 = 0``, so its quadratic form is, face by face,

    u^T L u = sum_f sum_{i < j in f} w^f_{ij} (u_i - u_j)^2,     w^f_{ij} = -(L_f)_{ij},

over *every* pair of corners of a face (a polygon's block couples non-adjacent corners too).
For tangent vectors ``X_i`` (complex coordinates in the vertex frames, see
:mod:`torch_polylap.vector.transport`) the difference ``u_i - u_j`` becomes
``X_i - R^f_{ij} X_j`` with the transport through the face ``R^f_{ij} = conj(z_i) z_j``:

    E(X) = sum_f sum_{i < j in f} w^f_{ij} |X_i - R^f_{ij} X_j|^2 = X^* A X,
    A = sum_f D_f^* (L_f (x) 1) D_f,        D_f = diag(z_{i,f})_{i in f}.               (1)

So ``A`` has the scalar diagonal ``L_ii`` and off-diagonal entries
``sum_f (L_f)_{ij} conj(z_{i,f}) z_{j,f}`` (complex Hermitian).  Because the transport is flat
inside each face, every face term is the scalar block ``L_f`` seen through a unitary change of
frame: ``A`` is positive semi-definite whenever each ``L_f`` is, *whatever the signs of the
weights* (negative cotangent-like weights occur on obtuse triangles and on non-convex polygons,
where the usual edge-based construction ``sum w_ij |X_i - R_ij X_j|^2`` is not definite). On a
planar mesh every ``R^f_{ij}`` is the identity in a common frame and ``A = L (x) I_2``. On
triangles it is the vertex-based connection Laplacian of Knoeppel et al. 2013 and de Goes et al.
2020 (sec. 5.2); on polygons it inherits each method's own stabilizer (AW11's ``lam d^T Pi d``,
de Goes et al.'s 1-form projection, PLMS's virtual vertex).

With the ``n``-fold connection (``z -> z^n``, Knoeppel et al. 2013, sec. 4) the same operator
acts on ``n``-direction fields stored as ``X = r e^{i n theta}``.

The real ``(2V, 2V)`` form interleaves the coordinates (row ``2 v + c``: component ``c`` of
vertex ``v``, ``c = 0`` along ``e_x``, ``1`` along ``e_y``), each complex entry ``a + i b``
becoming the block ``[[a, -b], [b, a]]``: it is symmetric and acts on the real vector
``(x_0, y_0, x_1, y_1, ...)``, i.e. a ``(V, 2)`` tensor flattened.

The per-face blocks ``L_f`` come from the package's own kernels through the public
:func:`~torch_polylap.laplacian`, evaluated on the *exploded* mesh in which every face has its own
copies of its corners: its Laplacian holds exactly the blocks ``L_f``, unsummed.
"""

from __future__ import annotations

import torch

from .._typing import MeshFaces
from ..checks import Lam, check_int, check_verts
from ..faces import PolygonFaces
from ..kernels import check_method
from ..operators import laplacian
from ..sparse import SparseOperator, diag, sparse_values
from ..sparse.construct import csr_indices
from ..sparse.operator import operator_on
from ..sparse.pattern import SparsityPattern
from ..topology import Topology, build_topology, get_topology
from ..tracing import outside_transforms
from .transport import TangentFrames, corner_transport, tangent_frames

__all__ = ["connection_laplacian", "vector_mass"]


def _exploded(topo: Topology) -> Topology:
    """The topology of the mesh whose face ``f`` owns fresh corners ``offsets[f] .. + k_f``
    (cached on ``topo``, built once)."""
    key = ("vector.exploded", torch.device("cpu"))
    cached = topo.derived.get(key)
    if cached is None:
        with outside_transforms():
            faces = topo.faces
            n = faces.num_corners
            cached = build_topology(PolygonFaces(torch.arange(n), faces.sizes), n, warn=False)
        topo.derived[key] = cached
    return cached


def _block_layout(
    topo: Topology, blocks: torch.Tensor, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, SparsityPattern, torch.Tensor]:
    """For the exploded Laplacian ``blocks`` (entries = corner pairs of one face):
    ``(row corner, column corner, pattern, inverse)`` with ``pattern`` the ``(2V, 2V)``
    interleaved CSR pattern and ``inverse`` sending the four real entries of every corner pair
    (order ``xx, xy, yx, yy``) to their place in it; cached per topology and device, so that
    the operators of every call share one pattern and its cached transposes and unions."""
    key = ("vector.connection", torch.device(device))
    cached = topo.derived.get(key)
    if cached is None:
        with outside_transforms():
            crow_x, col_x = csr_indices(blocks)
            row_x = torch.repeat_interleave(
                torch.arange(crow_x.numel() - 1, device=device), crow_x.diff()
            )
            idx = topo.faces.indices.to(device)
            vi, vj = 2 * idx[row_x], 2 * idx[col_x]
            rows = torch.stack((vi, vi, vi + 1, vi + 1), 1).reshape(-1)
            cols = torch.stack((vj, vj + 1, vj, vj + 1), 1).reshape(-1)
            size = 2 * topo.num_verts
            unique, inverse = torch.unique(rows * size + cols, sorted=True, return_inverse=True)
            urow = torch.div(unique, size, rounding_mode="floor")
            crow = torch.zeros(size + 1, dtype=torch.int64, device=device)
            crow[1:] = torch.cumsum(torch.bincount(urow, minlength=size), 0)
            pattern = SparsityPattern(crow, unique - urow * size, (size, size))
            cached = (row_x, col_x, pattern, inverse)
        topo.derived[key] = cached
    return cached


def _face_blocks(
    verts: torch.Tensor, topo: Topology, lam: Lam, method: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """The exploded Laplacian (the unsummed blocks ``L_f``) and the ``(V,)`` vertex masses."""
    exploded = _exploded(topo)
    idx = topo.faces.indices.to(verts.device)
    try:
        blocks, corner_mass = laplacian(verts[idx], exploded, lam, method=method)
    except ValueError:
        # name the mesh's own vertices in the message, not the exploded copies
        laplacian(verts, topo, lam, method=method)
        raise
    mass = verts.new_zeros(topo.num_verts).index_add(0, idx, corner_mass.diagonal())
    return blocks, mass


def _checked_frames(frames: TangentFrames | tuple, num_verts: int) -> TangentFrames:
    frames = TangentFrames(*frames)
    for name, f in zip(TangentFrames._fields, frames, strict=True):
        if not isinstance(f, torch.Tensor) or f.shape != (num_verts, 3):
            shape = tuple(f.shape) if isinstance(f, torch.Tensor) else type(f).__name__
            raise ValueError(f"frames.{name} must be a ({num_verts}, 3) tensor, got {shape}.")
    return frames


def vector_mass(mass: torch.Tensor) -> SparseOperator:
    """The ``(2V, 2V)`` diagonal mass of interleaved tangent vectors from the ``(V,)`` masses."""
    return diag(mass.repeat_interleave(2))


def connection_laplacian(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    method: str = "aw11",
    symmetry: int = 1,
    frames: TangentFrames | tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> tuple[SparseOperator, SparseOperator, TangentFrames]:
    """The connection Laplacian ``A`` of tangent vector fields (eq. (1) of the module docstring),
    its mass ``M`` and the vertex frames it is written in.

    Args:
        verts: ``(V, 3)`` vertex positions, float32 or float64.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        lam: the stabilizer weight of the scalar Laplacian (see :func:`~torch_polylap.laplacian`).
        method: the scalar Laplacian whose face blocks are used: ``"aw11"``, ``"plms"`` or
            ``"degoes"`` (see :func:`~torch_polylap.laplacian`).
        symmetry: ``n`` of the ``n``-fold connection (angles times ``n``): 1 for vector fields,
            2 for line fields, 4 for cross fields.
        frames: ``(normal, e_x, e_y)``, each ``(V, 3)`` orthonormal per vertex; default
            :func:`~torch_polylap.tangent.vertex_tangent_frames` (area-weighted normals).

    Returns:
        ``A``: ``(2V, 2V)`` symmetric positive semi-definite
        :class:`~torch_polylap.sparse.SparseOperator` on interleaved coordinates (row
        ``2 v + c``), with ``4 nnz(L)`` entries; ``M``: ``(2V, 2V)`` diagonal, ``M0``'s masses
        repeated; ``frames``: the :class:`~torch_polylap.vector.TangentFrames` used.
        Values differentiable in ``verts`` (and ``frames``) with O(nnz) gradients; the pattern is
        cached with the topology.

    Raises:
        ValueError: bad input as for :func:`~torch_polylap.laplacian`; a vertex whose normal
            points against one of its faces' normals (a fold), naming both.

    Examples:
        On the unit sphere the smallest eigenvalues of ``A X = mu M X`` approach
        ``l (l + 1) - 1``: 1 six times, then 5 ten times.

        >>> import torch, torch_polylap as tp
        >>> verts, faces = tp.shapes.quad_sphere(6)
        >>> A, M, frames = tp.vector.connection_laplacian(verts, faces)
        >>> mu, _ = tp.eigs(A, M, k=16)
        >>> [round(float(m), 1) for m in mu[[0, 5, 6, 15]]]
        [1.0, 1.0, 5.0, 5.0]
    """
    check_verts(verts)
    check_method(method, face_blocks="connection_laplacian")
    symmetry = check_int(symmetry, "symmetry")  # n of n-direction fields
    topo = get_topology(faces, verts.shape[0])
    frames = None if frames is None else _checked_frames(frames, topo.num_verts)
    return connection_laplacian_of(verts, topo, lam, method, symmetry, frames)


def connection_laplacian_of(
    verts: torch.Tensor,
    topo: Topology,
    lam: Lam,
    method: str,
    symmetry: int = 1,
    frames: TangentFrames | None = None,
) -> tuple[SparseOperator, SparseOperator, TangentFrames]:
    """:func:`connection_laplacian` on a topology, without checking its arguments again (for
    callers that have checked them)."""
    if frames is None:
        frames = tangent_frames(verts, topo)
    blocks, mass = _face_blocks(verts, topo, lam, method)
    row_x, col_x, pattern, inverse = _block_layout(topo, blocks, verts.device)
    z = corner_transport(verts, topo.faces, topo, frames)
    if symmetry != 1:
        z = z**symmetry
    entry = sparse_values(blocks) * (z[row_x].conj() * z[col_x])
    re, im = entry.real, entry.imag
    parts = torch.stack((re, -im, im, re), 1).reshape(-1)
    values = parts.new_zeros(pattern.nnz).index_add(0, inverse, parts)
    A = operator_on(pattern, values, symmetric=True)
    return A, vector_mass(mass), frames
