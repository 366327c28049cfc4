"""The Alexa-Wardetzky Laplacian ``L``, the lumped mass ``M0`` and their relatives.

For a face with ``k`` corners (AW11 sec. 3.3, MATH.md):

    L_f = d^T M_f d = G G^T / |f| + lambda d^T Pi d                 (AW11 eq. 3 and 9)

with ``G`` the rows ``g_i = (x_{i+1} - x_{i-1}) / 2`` and ``Pi`` the projector onto the kernel of
the maximal projection's edge matrix.  ``L = sum_f P_f^T L_f P_f`` is symmetric positive
semi-definite (the paper's sign; libigl's ``cotmatrix`` is ``-L`` on triangles), and ``M0`` is
diagonal with ``m_p = sum_{f ni p} |f| / k_f`` (AW11 eq. 10).

Assembly only evaluates the ``k (k - 1) / 2`` off-diagonal entries of each block; the diagonal
follows from ``L_f 1 = 0`` (``d 1 = 0``), which holds exactly and saves a third of the work.
All entries are closed-form elementwise expressions over the faces of one degree, scattered
onto the pattern cached in :class:`~torch_polylap.topology.Topology`.
"""

from __future__ import annotations

import torch
from torch import nn

from .checks import check_lam, check_verts
from .faces import FacesLike
from .geometry import (
    corner_terms,
    gather_coordinates,
    gather_corners,
    plane_basis,
    polygon_entries,
    quad_entries,
    stable_norm,
)
from .methods import BlockEntries, BlockKernel, check_method, method_kernel
from .sparse import SparseOperator, diag, operator_from_parts
from .topology import DegreeGroup, Topology, build_topology, get_topology, half_edge_vertices

__all__ = [
    "laplacian",
    "mass",
    "PolygonLaplacian",
    "planarity_laplacian",
    "planarity_energy",
    "face_planarity_energy",
    "coboundary",
    "one_form_inner_product",
    "mean_curvature_normal",
    "strong_laplacian",
    "vector_area",
    "face_areas",
    "face_normals",
    "face_nonplanarity",
    "local_laplacians",
    "get_topology",
]

Lam = float | torch.Tensor
MeshFaces = FacesLike | Topology


def _block_entries(
    x: torch.Tensor, grp: DegreeGroup, lam: Lam, geometric: bool = True
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Off-diagonal entries ``(L_f)_ij``, ``i < j``, of every face of one degree.

    Args:
        x: ``(3, k, F)`` corner positions (the quad kernel also accepts the tuple of three
            ``(k, F)`` coordinate tensors that :func:`gather_coordinates` returns).
        lam: weight of the stabilizer; ``geometric=False`` keeps only ``lam d^T Pi d`` (the
            planarity operator's blocks).

    Returns:
        ``off`` ``(P, F)``: entry ``(pair_i[p], pair_j[p])`` of each face's block;
        ``area`` ``(F,)``: ``|f|``; ``size2`` ``(F,)``: a squared length of the face (sum of
        ``|g_i|^2``), against which a zero area is judged.
    """
    if grp.k == 4:
        return quad_entries(x.unbind(0), lam, geometric)
    return polygon_entries(x, grp.pair_i, grp.pair_j, lam, geometric)


def _row_sums(off: torch.Tensor, grp: DegreeGroup) -> torch.Tensor:
    """``(k, F)`` sums of the off-diagonal entries in each row of every block.

    ``L_f 1 = 0`` makes the diagonal their negative. Accumulated row by row (a small BLAS
    matmul would cost milliseconds of threading overhead per call on small meshes).
    """
    sums = off.new_zeros(grp.k, off.shape[1])
    sums.index_add_(0, grp.pair_i, off)
    return sums.index_add_(0, grp.pair_j, off)


def _raise_bad_input(verts: torch.Tensor, topo: Topology) -> None:
    bad_v = ~torch.isfinite(verts).all(1)
    if bool(bad_v.any()):
        v = int(torch.nonzero(bad_v)[0, 0])
        raise ValueError(
            f"vertex {v} has non-finite coordinates {verts[v].tolist()} "
            f"({int(bad_v.sum())} such vertices); fix or remove them before building operators."
        )
    eps = torch.finfo(verts.dtype).eps
    for _, grp, x in _face_loop(verts, topo):
        _, area, size2 = _block_entries(x, grp, 0.0)
        bad = area <= eps * size2
        if bool(bad.any()):
            local = int(torch.nonzero(bad)[0, 0])
            f = int(grp.face_ids[local])
            raise ValueError(
                f"face {f} (vertices {topo.faces[f].tolist()}) has zero vector area "
                f"(|f| = {float(area[local]):.3g}); its corners are collinear or its loop cancels "
                f"out ({int(bad.sum())} such face(s) of degree {grp.k}). The Laplacian divides by "
                "|f|: remove the face, collapse it, or move its vertices apart. Thin faces with "
                "non-zero area are fine."
            )


def _aw11_kernel(lam: Lam, geometric: bool) -> BlockKernel:
    """AW11's per-face blocks (quads in closed form) and lumped masses ``|f| / k`` (eq. 10)."""

    def kernel(verts_t: torch.Tensor, grp: DegreeGroup, corners_t: torch.Tensor) -> BlockEntries:
        if grp.k == 4:
            off, area, size2 = quad_entries(gather_coordinates(verts_t, corners_t), lam, geometric)
        else:
            x = gather_corners(verts_t, corners_t)
            off, area, size2 = _block_entries(x, grp, lam, geometric)
        return off, (area / grp.k).expand(grp.k, -1), area, size2

    return kernel


def _assemble(
    verts: torch.Tensor,
    topo: Topology,
    kernel: BlockKernel,
    want_mass: bool,
    validate: bool,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """CSR values of ``sum_f P_f^T L_f P_f`` and, optionally, the lumped masses, from the per-face
    blocks that ``kernel`` evaluates for each chunk of faces of one degree."""
    groups, _, _ = topo.on(verts.device)
    verts_t = verts.t().contiguous()
    values = verts.new_zeros(topo.nnz)
    masses = verts.new_zeros(topo.num_verts) if want_mass else None
    eps = torch.finfo(verts.dtype).eps
    degenerate = []
    for grp in groups:
        for chunk in grp.chunks:
            off, corner_mass, area, size2 = kernel(verts_t, grp, chunk.corners_t)
            flat = off.reshape(-1)
            values.index_add_(0, chunk.pos_upper, flat)
            values.index_add_(0, chunk.pos_lower, flat)
            values.index_add_(0, chunk.pos_diag, _row_sums(off, grp).reshape(-1), alpha=-1)
            if masses is not None:
                masses.index_add_(0, chunk.corners_t.reshape(-1), corner_mass.reshape(-1))
            if validate:
                degenerate.append((area <= eps * size2).any())
    if validate:
        ok = torch.isfinite(verts).all()
        if degenerate:
            ok = ok & ~torch.stack(degenerate).any()
        if not bool(ok):
            _raise_bad_input(verts, topo)
    return values, masses


def _checked_lam(lam: Lam, validate: bool = True) -> Lam:
    """``lam`` checked finite and >= 0; a tensor only with ``validate`` (reading it syncs)."""
    return check_lam(lam) if validate or not isinstance(lam, torch.Tensor) else lam


def _check_layout(layout: torch.layout) -> None:
    if layout not in (torch.sparse_csr, torch.sparse_coo):
        raise ValueError(f"layout must be torch.sparse_csr or torch.sparse_coo, got {layout}.")


def _operator(topo: Topology, values: torch.Tensor, layout: torch.layout) -> SparseOperator:
    """The symmetric ``V x V`` operator with ``values`` on the topology's cached pattern."""
    _check_layout(layout)
    return SparseOperator(topo.pattern(values.device), values, symmetric=True, layout=layout)


def laplacian(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    layout: torch.layout = torch.sparse_csr,
    validate: bool = True,
    method: str = "aw11",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The weak Laplacian ``L`` and lumped mass ``M0`` of a polygon mesh (AW11 eq. 3, 9, 10).

    Args:
        verts: ``(V, 3)`` vertex positions, float32 or float64, any device. ``L`` and ``M0``
            follow its dtype and device, and their values are differentiable functions of it.
        faces: ``(F, k)`` indices, a list of index lists of mixed degree, a
            :class:`~torch_polylap.PolygonFaces`, or a prebuilt
            :class:`~torch_polylap.topology.Topology` (cached on tensors/PolygonFaces).
        lam: weight ``lambda > 0`` of the stabilizer ``lambda d^T Pi d`` (AW11 eq. 9 with
            ``U = lambda Id``);
            a float or a 0-dim tensor (which may require grad). Default 1 (the paper finds
            ``1 <= lambda <= 3`` comparable). Triangles do not depend on it (Theorem 2).
        layout: the layout the operators report, ``torch.sparse_csr`` (default) or
            ``torch.sparse_coo``; either way they store CSR indices and offer ``crow_indices()``,
            ``col_indices()`` and the COO ``indices()``.
        validate: check for non-finite coordinates and zero-area faces (one device sync). With
            ``False`` a zero-area face gives huge but finite entries instead of an error.
        method: ``"aw11"`` (default, this docstring), ``"plms"`` (Bunge et al. 2020, "Polygon
            Laplacian Made Simple": a virtual vertex per face, ``lam`` ignored) or ``"degoes"``
            (de Goes et al. 2020, with ``lam`` their ``beta``); see :mod:`torch_polylap.methods`.
            All three share the topology, pattern, sign and dtype/device rules.

    Returns:
        ``L``: ``(V, V)`` :class:`~torch_polylap.sparse.SparseOperator`, symmetric positive
        semi-definite, rows sum to zero, kernel the constants on each connected component.
        ``M0``: ``(V, V)`` diagonal :class:`~torch_polylap.sparse.SparseOperator`.  Both are torch
        tensors whose algebra keeps O(nnz) gradients: ``L @ X``, ``M0 + t * L``, ``L.T``,
        ``M0.diagonal()``, the value array ``tp.sparse.sparse_values(L)`` (see
        :mod:`torch_polylap.sparse`).

    Raises:
        ValueError: bad connectivity (see :func:`~torch_polylap.topology.build_topology`),
            non-finite coordinates or zero-area faces, naming the vertex or face.
    """
    check_verts(verts, finite=False)
    _check_layout(layout)
    lam = _checked_lam(lam, validate)
    check_method(method)
    topo = get_topology(faces, verts.shape[0])
    kernel = _aw11_kernel(lam, True) if method == "aw11" else method_kernel(method, lam)
    values, masses = _assemble(verts, topo, kernel, True, validate)
    assert masses is not None
    return _operator(topo, values, layout), diag(masses, layout=layout)


def mass(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """``(V,)`` lumped masses ``m_p = sum_{f ni p} |f| / k_f`` (AW11 eq. 10), diagonal of ``M0``."""
    check_verts(verts, finite=False)
    topo = get_topology(faces, verts.shape[0])
    groups, _, _ = topo.on(verts.device)
    verts_t = verts.t().contiguous()
    m = verts.new_zeros(topo.num_verts)
    for grp in groups:
        _, _, a = corner_terms(gather_corners(verts_t, grp.corners_t))
        share = (stable_norm(a, 0) / grp.k).expand(grp.k, -1).reshape(-1)
        m = m.index_add(0, grp.corners_t.reshape(-1), share)
    return m


def planarity_laplacian(
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: Lam = 1.0,
    *,
    layout: torch.layout = torch.sparse_csr,
    validate: bool = True,
) -> torch.Tensor:
    """The planarity operator of AW11 sec. 5.3, ``sum_f P_f^T (lambda d^T Pi d) P_f``, ``(V, V)``.

    ``1/2 sum_c X_c^T Lplan X_c`` is zero exactly when every face is planar; see
    :func:`planarity_energy` for that energy without building the matrix. Triangles contribute
    nothing.
    """
    check_verts(verts, finite=False)
    lam = _checked_lam(lam, validate)
    topo = get_topology(faces, verts.shape[0])
    values, _ = _assemble(verts, topo, _aw11_kernel(lam, False), False, validate)
    return _operator(topo, values, layout)


def _face_loop(verts: torch.Tensor, faces: MeshFaces):
    check_verts(verts, finite=False)
    topo = get_topology(faces, verts.shape[0])
    groups, _, _ = topo.on(verts.device)
    verts_t = verts.t().contiguous()
    for grp in groups:
        yield topo, grp, gather_corners(verts_t, grp.corners_t)


def vector_area(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """``(F, 3)`` vector area ``a_f = 1/2 sum_i x_i x x_{i+1}`` of every face (AW11 Lemma 1, eq. 8).

    Its norm is the area of the maximal projection and its direction that projection's normal;
    it depends only on the boundary loop, so it is well defined for non-planar faces.
    """
    out = None
    for topo, grp, x in _face_loop(verts, faces):
        if out is None:
            out = verts.new_zeros(topo.num_faces, 3)
        _, _, a = corner_terms(x)
        out = out.index_copy(0, grp.face_ids, a.t())
    return out if out is not None else verts.new_zeros(0, 3)


def face_areas(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """``(F,)`` face areas ``|f| = |a_f|`` (area of the maximal projection)."""
    return stable_norm(vector_area(verts, faces), 1)


def face_normals(verts: torch.Tensor, faces: MeshFaces) -> torch.Tensor:
    """``(F, 3)`` unit normals of the faces' maximal projections, ``a_f / |a_f|``."""
    a = vector_area(verts, faces)
    return a / stable_norm(a, 1, keepdim=True)


def face_nonplanarity(
    verts: torch.Tensor, faces: MeshFaces, plane: str = "projection"
) -> torch.Tensor:
    """``(F,)`` non-planarity of every face: the largest distance of a corner from a plane through
    the corners' centroid, over the face diameter. Zero for planar faces and for triangles; scale
    invariant.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`Topology`.
        plane: ``"projection"``: the plane of the maximal projection (normal ``a_f / |a_f|``,
            AW11 sec. 3), differentiable; ``"fit"``: the least-squares plane of the corners
            (normal: the eigenvector of the smallest eigenvalue of their covariance), the usual
            measure in planarization papers. ``"fit"`` is a measure, not a loss: it is computed
            without gradient (an eigenvector's derivative is unstable where the two smallest
            eigenvalues meet); use ``planarity_energy`` as a loss.
    """
    if plane not in ("projection", "fit"):
        raise ValueError(f'face_nonplanarity: plane must be "projection" or "fit", got {plane!r}.')
    out = verts.new_zeros(0)
    for topo, grp, x in _face_loop(verts if plane == "projection" else verts.detach(), faces):
        if out.numel() == 0:
            out = verts.new_zeros(topo.num_faces)
        centered = x - x.mean(1, keepdim=True)  # (3, k, F)
        if plane == "projection":
            _, _, a = corner_terms(x)
            n = a / stable_norm(a, 0)
        else:
            covariance = torch.einsum("ikf,jkf->fij", centered, centered)
            n = torch.linalg.eigh(covariance)[1][:, :, 0].T
        height = (centered * n[:, None]).sum(0).abs().amax(0)
        diff = x.index_select(1, grp.pair_i) - x.index_select(1, grp.pair_j)
        diameter = torch.linalg.vector_norm(diff, dim=0).amax(0)
        out = out.index_copy(0, grp.face_ids, height / diameter)
    return out


def face_planarity_energy(verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0) -> torch.Tensor:
    """``(F,)`` per-face planarity energy ``lambda/2 |Pi E|_F^2`` (AW11 sec. 5.3).

    ``E`` is the face's ``k x 3`` edge matrix and ``Pi E`` its part outside the column space of
    the maximal projection's edges, which vanishes exactly for planar faces (and triangles).
    Summed over faces it is ``E_plan = 1/2 sum_c X_c^T Lplan X_c``; evaluated face by face
    without building ``Lplan``.  On a mesh of triangles only it is zero, and still connected to
    ``verts`` (a zero gradient, so a loss built on it can always call ``backward()``).
    """
    lam = _checked_lam(lam)
    out = verts.new_zeros(0)
    for topo, grp, x in _face_loop(verts, faces):
        if out.numel() == 0:
            out = verts.new_zeros(topo.num_faces) + 0.0 * verts.sum()
        if grp.k == 3:
            continue
        e, _, a = corner_terms(x)
        n = a / stable_norm(a, 0).clamp_min(torch.finfo(verts.dtype).tiny)
        q1, q2 = plane_basis(e, n)
        # Pi E = E - q1 (q1^T E) - q2 (q2^T E), formed explicitly: subtracting squared norms
        # instead would cancel catastrophically exactly where a planarizing flow converges.
        residual = e - q1 * (e * q1).sum(1, keepdim=True) - q2 * (e * q2).sum(1, keepdim=True)
        out = out.index_copy(0, grp.face_ids, 0.5 * lam * (residual * residual).sum((0, 1)))
    return out


def planarity_energy(verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0) -> torch.Tensor:
    """``E_plan = 1/2 sum_c X_c^T Lplan X_c`` (AW11 sec. 5.3), a differentiable scalar: the sum
    of :func:`face_planarity_energy`."""
    return face_planarity_energy(verts, faces, lam).sum()


def local_laplacians(
    verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0, *, geometric: bool = True
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Dense blocks ``L_f = d^T M_f d``: ``(face_ids (F_k,), blocks (F_k, k, k))`` per degree.

    For inspection and tests; :func:`laplacian` never materializes them.
    ``geometric=False`` gives the planarity blocks ``lambda d^T Pi d``.
    """
    lam = _checked_lam(lam)
    out = []
    for _, grp, x in _face_loop(verts, faces):
        off, _, _ = _block_entries(x, grp, lam, geometric)
        blocks = verts.new_zeros(x.shape[2], grp.k, grp.k)
        blocks[:, grp.pair_i, grp.pair_j] = off.t()
        blocks[:, grp.pair_j, grp.pair_i] = off.t()
        ar = torch.arange(grp.k, device=verts.device)
        blocks[:, ar, ar] = -_row_sums(off, grp).t()
        out.append((grp.face_ids, blocks))
    return out


def coboundary(
    faces: MeshFaces,
    num_verts: int | None = None,
    *,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The half-edge coboundary ``d`` (AW11 eq. 2), ``(N, V)`` sparse CSR; ``N`` counts corners.

    Row ``h`` is the half-edge leaving corner ``h`` of the packed faces (corner ``c`` of face ``f``
    goes to corner ``c + 1``): ``(d u)_h = u(next) - u(this)``. Together with
    :func:`one_form_inner_product`, ``L = d^T M1 d``. Its entries are ``+-1`` in ``dtype``.
    """
    topo = faces if isinstance(faces, Topology) else build_topology(faces, num_verts)
    this_v, next_v = half_edge_vertices(topo.faces)
    n = this_v.numel()
    cols = torch.stack((torch.minimum(this_v, next_v), torch.maximum(this_v, next_v)), 1)
    sign = torch.where(this_v < next_v, 1.0, -1.0).to(dtype)
    vals = torch.stack((-sign, sign), 1)  # -1 at the tail, +1 at the head, sorted by column
    crow = torch.arange(0, 2 * n + 1, 2)
    return operator_from_parts(
        crow.to(device),
        cols.reshape(-1).to(device),
        vals.reshape(-1).to(device),
        (n, topo.num_verts),
    )


def one_form_inner_product(verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0) -> torch.Tensor:
    """The inner product on 1-forms ``M1 = blockdiag(M_f)`` (AW11 eq. 5, 9), ``(N, N)`` sparse CSR.

    ``M_f = B B^T / |f| + lambda Pi`` with the midpoints ``B`` taken relative to the face's vertex
    centroid (the paper's choice for stability; ``M_f`` itself depends on the origin, ``d^T M_f d``
    does not). Positive definite for ``lambda > 0`` (Theorem 1). Rows follow :func:`coboundary`.
    """
    lam = _checked_lam(lam)
    parts = []
    topo = None
    for topo, grp, x in _face_loop(verts, faces):  # noqa: B007 (topo is used after the loop)
        e, _, a = corner_terms(x)
        area = stable_norm(a, 0)
        b = 0.5 * (x + torch.roll(x, -1, dims=1))
        b = b - x.mean(1, keepdim=True)
        geo = torch.einsum("cif,cjf->fij", b, b) / area[:, None, None]
        q1, q2 = plane_basis(e, a / area)
        proj = torch.eye(grp.k, dtype=x.dtype, device=x.device) - (
            torch.einsum("if,jf->fij", q1, q1) + torch.einsum("if,jf->fij", q2, q2)
        )
        parts.append((grp, geo + lam * proj))
    if topo is None:
        return operator_from_parts(
            torch.zeros(1, dtype=torch.int64),
            torch.zeros(0, dtype=torch.int64),
            verts.new_zeros(0),
            (0, 0),
        )
    pf = topo.faces
    n = pf.num_corners
    off = pf.offsets.to(verts.device)
    sizes = pf.sizes.to(verts.device)
    row_len = torch.repeat_interleave(sizes, sizes)
    crow = torch.zeros(n + 1, dtype=torch.int64, device=verts.device)
    torch.cumsum(row_len, 0, out=crow[1:])
    col = torch.empty(int(crow[-1]), dtype=torch.int64, device=verts.device)
    values = verts.new_zeros(int(crow[-1]))
    for grp, blocks in parts:
        k = grp.k
        first = off[grp.face_ids]  # (F_k,) first corner of each face
        rows = first[:, None] + torch.arange(k, device=verts.device)  # (F_k, k)
        slots = crow[rows][:, :, None] + torch.arange(k, device=verts.device)  # (F_k, k, k)
        col[slots.reshape(-1)] = (
            (first[:, None, None] + torch.arange(k, device=verts.device))
            .expand(-1, k, k)
            .reshape(-1)
        )
        values = values.index_put((slots.reshape(-1),), blocks.reshape(-1))
    return operator_from_parts(crow, col, values, (n, n), symmetric=True)


def strong_laplacian(L: torch.Tensor, M0: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """``M0^{-1} L u`` (AW11 eq. 3, the pointwise Laplacian), ``u`` of shape ``(V,)`` or ``(V, c)``.

    Rows of isolated vertices (zero mass) are set to zero rather than divided by zero.
    """
    m = M0.diagonal()
    Lu = L @ u
    inv = torch.where(m > 0, 1.0 / torch.where(m > 0, m, torch.ones_like(m)), torch.zeros_like(m))
    return Lu * (inv if u.dim() == 1 else inv[:, None])


def mean_curvature_normal(verts: torch.Tensor, faces: MeshFaces, lam: Lam = 1.0) -> torch.Tensor:
    """``(V, 3)`` mean curvature vector ``H = M0^{-1} L X`` (AW11 sec. 3.2).

    ``H`` tends to ``2 H_mean n`` (outward ``n`` for counter-clockwise faces seen from outside),
    so on the unit sphere ``|H| / 2 -> 1``.
    """
    L, M0 = laplacian(verts, faces, lam)
    return strong_laplacian(L, M0, verts)


class PolygonLaplacian(nn.Module):
    """``nn.Module`` computing ``(L, M0)`` with the topology cached across calls.

    Args:
        lam: stabilizer weight (see :func:`laplacian`).
        learn_lam: make ``lam`` a learnable ``nn.Parameter``.
        layout: ``torch.sparse_csr`` (default) or ``torch.sparse_coo``.
        validate: see :func:`laplacian`.
        method: ``"aw11"`` (default), ``"plms"`` or ``"degoes"`` (see :func:`laplacian`).

    ``forward(verts, faces=None)``: ``verts`` ``(V, 3)``; ``faces`` in any accepted form, or
    ``None`` to reuse the faces of the previous call.  The topology is rebuilt only when the
    faces change (a different object, or a tensor modified in place), so a training loop with
    fixed connectivity only recomputes values.
    """

    def __init__(
        self,
        lam: float = 1.0,
        *,
        learn_lam: bool = False,
        layout: torch.layout = torch.sparse_csr,
        validate: bool = True,
        method: str = "aw11",
    ) -> None:
        super().__init__()
        _check_layout(layout)
        self.method = check_method(method)
        value = float(check_lam(lam))
        self.lam: float | nn.Parameter = nn.Parameter(torch.tensor(value)) if learn_lam else value
        self.layout = layout
        self.validate = validate
        self.topology: Topology | None = None

    def _topology_for(self, faces: MeshFaces | None, num_verts: int) -> Topology:
        if faces is None:
            if self.topology is None:
                raise ValueError("PolygonLaplacian: pass faces on the first call.")
            return self.topology
        # The package's one topology cache (keyed weakly on the faces tensor): the module
        # keeps no reference to the faces, so a loop over fresh tensors pins no memory.
        self.topology = get_topology(faces, num_verts)
        return self.topology

    def forward(
        self, verts: torch.Tensor, faces: MeshFaces | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        check_verts(verts, finite=False)
        topo = self._topology_for(faces, verts.shape[0])
        lam = self.lam.to(verts.dtype) if isinstance(self.lam, torch.Tensor) else self.lam
        return laplacian(
            verts, topo, lam, layout=self.layout, validate=self.validate, method=self.method
        )

    def extra_repr(self) -> str:
        lam = float(self.lam) if isinstance(self.lam, torch.Tensor) else self.lam
        return (
            f"lam={lam}, method={self.method!r}, layout={self.layout}, "
            f"cached={self.topology is not None}"
        )
