"""Conformal parameterization of polygon meshes (AW11 sec. 5.2): polygonal LSCM / DCP.

The conformal energy of a flat image ``Y = (u, v)`` of a mesh is (AW11 eq. 11)

    E_C(Y) = E_D(Y) - A(Y),   E_D = 1/2 (u^T L u + v^T L v),
    A(Y) = 1/2 sum over boundary half-edges (s -> t) of (u_s v_t - u_t v_s),

the Dirichlet energy with the polygon Laplacian ``L`` minus the signed area of the image, a
quadratic form in the boundary vertices only (the half-edges of interior edges cancel). In the
stacked unknown ``z = [u; v]`` (length ``2V``), ``E_C = 1/2 z^T L_C z`` with

    L_C = [[L, -S], [-S^T, L]],   S[s, t] = +1/2, S[t, s] = -1/2 for each boundary half-edge,

so the area couples ``u`` and ``v`` on the boundary only. Two ways to remove the similarity
freedom (translation, rotation, scale):

* pinned (LSCM, Levy et al. 2002): prescribe two boundary vertices and solve ``L_C z = 0`` on
  the rest (AW11 eq. 12), a sparse ``2(V-2)`` system;
* free boundary (Mullen et al. 2008, AW11 eq. 13-15): minimize ``E_C`` subject to
  ``A(Y) = 1`` (``Q`` = the area form, AW11 Fig. 3). Interior vertices are eliminated with the
  Schur complement ``L_B = L_BB - L_IB^T L_II^{-1} L_IB`` (AW11 eq. 15), which leaves a dense
  generalized eigenproblem over the boundary vertices only.

On triangle meshes ``L`` is the cotan Laplacian (AW11 Theorem 2) and both reduce to cotan LSCM
and spectral conformal parameterization.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .._typing import MeshFaces
from ..checks import check_verts
from ..kernels import check_method
from ..linalg import dirichlet_solve, solve, top_eigenpair
from ..measures import face_normals, vector_area
from ..operators import laplacian
from ..sparse import block_diag, from_coo, submatrix
from ..topology import Topology, get_topology, half_edge_vertices

__all__ = [
    "conformal_parameterization",
    "conformal_energy",
    "conformal_matrix",
    "angle_distortion",
    "AngleDistortion",
]


def _require_oriented_edges(topo: Topology, what: str, *, vertices: bool = False) -> None:
    """The area form ``A(Y) = sum_f area(Y_f)`` reduces to the boundary half-edges only when
    every interior edge is used by two faces traversing it in opposite directions (their
    half-edges cancel): refuse non-manifold edges and misoriented or non-orientable meshes,
    naming the repair (:mod:`torch_polylap.repair`). ``vertices=True`` (the parameterization)
    also refuses non-manifold vertices: two sheets sharing only a vertex can turn about it
    freely, so ``L_C`` is singular there."""
    topo.require_manifold(what, vertices=vertices)
    topo.require_oriented(what)


def _boundary_half_edges(topo: Topology) -> tuple[torch.Tensor, torch.Tensor]:
    """``(src, dst)`` of the half-edges on the boundary, oriented as their faces (call
    :func:`_require_oriented_edges` first: on a manifold, oriented mesh these are exactly the
    half-edges of :meth:`Topology.boundary_loops`, without the graph walk that orders them)."""
    src, dst = half_edge_vertices(topo.faces)
    on_boundary = topo.edge_faces[topo.half_edge_edge] == 1
    return src[on_boundary], dst[on_boundary]


def _check_mesh(verts: torch.Tensor, topo: Topology) -> torch.Tensor:
    """Raise for meshes the parameterization cannot handle; return the boundary vertices."""
    _require_oriented_edges(topo, "conformal_parameterization", vertices=True)
    if bool(topo.isolated.any()):
        v = int(torch.nonzero(topo.isolated)[0, 0])
        raise ValueError(
            f"vertex {v} is used by no face; remove unreferenced vertices before parameterizing."
        )
    boundary = topo.boundary_vertices
    if boundary.numel() == 0:
        chi = topo.euler_characteristic()
        genus = f", genus {(2 - chi) // 2}" if chi % 2 == 0 else ""
        raise ValueError(
            f"the mesh has no boundary (closed, Euler characteristic {chi}{genus}): a conformal "
            "map to the plane needs a mesh with boundary. Cut the surface open (e.g. remove a "
            "face or cut along a seam) first."
        )
    n_comp, _ = topo.connected_components()  # no isolated vertex: components of the faces
    if n_comp > 1:
        raise ValueError(
            f"the mesh has {n_comp} connected components; parameterize each component separately."
        )
    return boundary


def _require_disk(topo: Topology) -> None:
    """Refuse a mesh that is not a topological disk (one boundary loop, Euler characteristic
    ``V - E + F = 1``) for the free-boundary map.

    Its area form sums over all boundary loops, and with holes or handles the top eigenpair of
    area over Dirichlet energy (AW11 eq. 14) need not be an embedding: a torus with one hole
    and a cube sphere with five holes were folded over (corner angle errors of 250-285
    degrees).
    Call after :func:`_check_mesh` (one component, manifold, oriented, with boundary)."""
    loops = len(topo.boundary_loops())
    chi = topo.euler_characteristic()
    if loops == 1 and chi == 1:
        return
    genus = (2 - loops - chi) // 2  # chi = 2 - 2 genus - loops on a connected orientable surface
    raise ValueError(
        "free_boundary=True needs a topological disk (one boundary loop, Euler characteristic 1), "
        f"but the mesh has {loops} boundary loop{'s' if loops > 1 else ''} and Euler "
        f"characteristic {chi} (genus {genus}). Cut it into a disk first: along seams that join "
        "the boundary loops and through each handle. (The pinned map, free_boundary=False, "
        "accepts holes, but can fold over on curved meshes: check its angle_distortion.)"
    )


def conformal_matrix(
    verts: torch.Tensor, faces: MeshFaces, lam: float = 1.0, *, method: str = "aw11"
) -> torch.Tensor:
    """The ``(2V, 2V)`` matrix ``L_C`` of the conformal energy ``E_C = 1/2 z^T L_C z``.

    Args:
        verts: ``(V, 3)`` positions of the source mesh.
        faces: polygon faces (any form accepted by :func:`torch_polylap.as_faces`).
        lam: stabilizer weight of :func:`torch_polylap.laplacian`.
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` (``lam`` unused) or
            ``"degoes"`` (see :func:`torch_polylap.laplacian`).

    Returns:
        A symmetric sparse operator acting on ``z = [u; v]`` (AW11 eq. 11-12); its values are
        differentiable in ``verts`` with O(nnz) gradients (``L_C @ z``).

    Raises:
        ValueError: an edge used by 3+ faces, or faces not consistently oriented (the area
            term is a sum over boundary half-edges only when interior half-edges cancel); the
            message names the edges and the repair, e.g.
            :func:`torch_polylap.repair.orient_faces`.
    """
    topo = get_topology(faces, verts.shape[0])
    _require_oriented_edges(topo, "conformal_matrix")
    L, _ = laplacian(verts, topo, lam, method=check_method(method))
    n = topo.num_verts
    s, t = _boundary_half_edges(topo)
    s, t = s.to(L.device), t.to(L.device)
    half = torch.full((s.numel(),), 0.5, dtype=verts.dtype, device=verts.device)
    # -dA/d(u_s v_t) entries of the signed area, a constant symmetric matrix
    area = from_coo(
        torch.cat((s, n + t, t, n + s)),
        torch.cat((n + t, s, n + s, t)),
        torch.cat((-half, -half, half, half)),
        (2 * n, 2 * n),
        symmetric=True,
    )
    return block_diag([L, L]) + area


def _signed_area(uv: torch.Tensor, topo: Topology) -> torch.Tensor:
    """Signed area of the flat image: 1/2 sum over boundary half-edges of ``u_s v_t - u_t v_s``."""
    s, t = _boundary_half_edges(topo)
    s, t = s.to(uv.device), t.to(uv.device)
    return 0.5 * (uv[s, 0] * uv[t, 1] - uv[t, 0] * uv[s, 1]).sum()


def conformal_energy(
    uv: torch.Tensor,
    verts: torch.Tensor,
    faces: MeshFaces,
    lam: float = 1.0,
    *,
    method: str = "aw11",
) -> torch.Tensor:
    """``E_C(Y) = E_D(Y) - A(Y)`` (AW11 eq. 11), a differentiable scalar.

    Args:
        uv: ``(V, 2)`` flat image of the vertices.
        verts: ``(V, 3)`` source positions (``L`` is built from them).
        faces: polygon faces, consistently oriented, every edge used by at most two faces
            (else a ValueError says which repair to run, as in :func:`conformal_matrix`).
        lam: stabilizer weight of the Laplacian.
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` (``lam`` unused) or
            ``"degoes"`` (see :func:`torch_polylap.laplacian`).

    Returns:
        ``1/2 sum_c uv_c^T L uv_c`` minus the signed area of the image. Non-negative whenever
        ``L_C`` is PSD, which we observed for every mesh and ``lam`` tried (0.1 to 3; not
        proven here); zero exactly for similarities of a planar mesh (linear precision of
        ``L``).
    """
    if uv.dim() != 2 or uv.shape[1] != 2 or uv.shape[0] != verts.shape[0]:
        raise ValueError(f"uv must have shape ({verts.shape[0]}, 2), got {tuple(uv.shape)}.")
    topo = get_topology(faces, verts.shape[0])
    _require_oriented_edges(topo, "conformal_energy")
    L, _ = laplacian(verts, topo, lam, method=check_method(method))
    dirichlet = 0.5 * (uv * (L @ uv.to(L.dtype))).sum()
    return dirichlet - _signed_area(uv, topo)


def _default_pins(verts: torch.Tensor, boundary: torch.Tensor) -> torch.Tensor:
    """Two far-apart boundary vertices: the one farthest from the first boundary vertex, and
    the one farthest from it (a deterministic double sweep)."""
    xb = verts.detach()[boundary.to(verts.device)]
    a = int(torch.argmax(torch.linalg.vector_norm(xb - xb[0], dim=1)))
    b = int(torch.argmax(torch.linalg.vector_norm(xb - xb[a], dim=1)))
    return boundary[torch.tensor([a, b])]


def _check_pins(
    pins: torch.Tensor | list[int],
    pin_uv: torch.Tensor | None,
    verts: torch.Tensor,
    boundary: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    n = verts.shape[0]
    pins = torch.as_tensor(pins, dtype=torch.int64).reshape(-1).cpu()
    if pins.numel() != 2:
        raise ValueError(f"pins must hold exactly two vertex indices, got {pins.numel()}.")
    for p in pins.tolist():
        if not 0 <= p < n:
            raise ValueError(f"pin {p} is out of range for a mesh with {n} vertices.")
        if not bool((boundary == p).any()):
            raise ValueError(
                f"pin {p} is not a boundary vertex; pin two vertices of the boundary "
                "(see Topology.boundary_vertices)."
            )
    if int(pins[0]) == int(pins[1]):
        raise ValueError(f"the two pins are the same vertex {int(pins[0])}; pin two vertices.")
    if pin_uv is None:
        # differentiable in verts, like the rest of the pinned solution
        dist = torch.linalg.vector_norm(verts[pins[0]] - verts[pins[1]])
        zero = torch.zeros_like(dist)
        pin_uv = torch.stack((torch.stack((zero, zero)), torch.stack((dist, zero))))
    else:
        pin_uv = torch.as_tensor(pin_uv, dtype=verts.dtype, device=verts.device)
        if pin_uv.shape != (2, 2):
            raise ValueError(f"pin_uv must have shape (2, 2), got {tuple(pin_uv.shape)}.")
        if not bool(torch.isfinite(pin_uv).all()) or bool((pin_uv[0] == pin_uv[1]).all()):
            raise ValueError("pin_uv must be two distinct finite points.")
    return pins, pin_uv


def _pinned(
    verts: torch.Tensor,
    topo: Topology,
    lam: float,
    pins: torch.Tensor,
    pin_uv: torch.Tensor,
    method: str = "aw11",
) -> torch.Tensor:
    n = topo.num_verts
    LC = conformal_matrix(verts, topo, lam, method=method)
    fixed = torch.cat((pins, pins + n)).to(verts.device)
    fixed_values = torch.cat((pin_uv[:, 0], pin_uv[:, 1]))
    z = dirichlet_solve(LC, verts.new_zeros(2 * n), fixed, fixed_values)
    return torch.stack((z[:n], z[n:]), 1)


def _orthonormal_complement_of_ones(
    m: int, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """``(m, m-1)`` orthonormal basis of the vectors summing to zero (a Householder reflection)."""
    w = torch.full((m,), 1.0 / math.sqrt(m), dtype=dtype, device=device)
    w[0] -= 1.0
    w = w / torch.linalg.vector_norm(w)
    H = torch.eye(m, dtype=dtype, device=device) - 2.0 * torch.outer(w, w)  # e_0 -> constant
    return H[:, 1:]


def _free_boundary(
    verts: torch.Tensor, topo: Topology, lam: float, boundary: torch.Tensor, method: str = "aw11"
) -> torch.Tensor:
    """AW11 eq. 13-15, in float64 and differentiable in ``verts``: the Schur complement by a
    sparse solve with the interior block, then the top eigenpair of the area form over the
    Dirichlet form on zero-mean boundary positions, as a Hermitian problem in ``z = u + i v``
    (the real ``2m`` problem has every eigenvalue twice: rotating ``z`` by ``i`` keeps both
    forms, so its eigenvectors have no derivative; the complex one's top eigenvalue is simple)."""
    n = topo.num_verts
    x = verts.to(torch.float64)
    device = x.device
    L = laplacian(x, topo, lam, method=method)[0]
    b = torch.sort(boundary.to(device)).values
    m = b.numel()
    on_boundary = torch.zeros(n, dtype=torch.bool, device=device)
    on_boundary[b] = True
    interior = torch.nonzero(~on_boundary).reshape(-1)
    L_schur = submatrix(L, b, b).to_dense()
    harmonic = None
    if interior.numel():
        L_IB = submatrix(L, interior, b).to_dense()
        harmonic = solve(submatrix(L, interior, interior), L_IB)  # L_II^{-1} L_IB, (I, m)
        L_schur = L_schur - L_IB.T @ harmonic  # AW11 eq. 15
    L_schur = 0.5 * (L_schur + L_schur.T)
    index = torch.full((n,), -1, dtype=torch.int64, device=device)
    index[b] = torch.arange(m, device=device)
    s, t = (index[e.to(device)] for e in _boundary_half_edges(topo))
    # area form A(z) = z^H (-i S / 2) z on z = u + i v (S[s, t] = 1/2, S[t, s] = -1/2)
    S = torch.zeros(m, m, dtype=torch.float64, device=device)
    S.index_put_((s, t), torch.full_like(s, 1, dtype=torch.float64), accumulate=True)
    S.index_put_((t, s), torch.full_like(s, -1, dtype=torch.float64), accumulate=True)
    # translations lie in the kernel of both forms: restrict to zero-mean boundary positions
    N = _orthonormal_complement_of_ones(m, torch.float64, device)
    K = N.T @ L_schur @ N
    C = torch.linalg.cholesky(0.5 * (K + K.T)).to(torch.complex128)
    H = (N.T @ S @ N).to(torch.complex128) * -0.5j
    # maximize A / E_D: the top eigenpair of C^-1 H C^-H. Its eigenvalue nu relates to AW11
    # eq. 14 by mu = 1/nu - 1
    CiH = torch.linalg.solve_triangular(C, H, upper=False)
    M = torch.linalg.solve_triangular(C, CiH.mH, upper=False)
    nu, w = top_eigenpair(0.5 * (M + M.mH))
    ratio = float(nu.detach())
    if not ratio > 0:
        raise ValueError(
            "free-boundary parameterization found no orientation-preserving solution "
            f"(largest area / Dirichlet ratio {ratio:.3g}); check the face orientation."
        )
    z = N.to(torch.complex128) @ torch.linalg.solve_triangular(C.mH, w[:, None], upper=True)[:, 0]
    yb = torch.stack((z.real, z.imag), 1)
    y = x.new_zeros(n, 2).index_put((b,), yb)
    if harmonic is not None:
        y = y.index_put((interior,), -harmonic @ yb)
    # scale so that the image has the source's total area (vector areas of the faces)
    area = 0.5 * (yb[s, 0] * yb[t, 1] - yb[t, 0] * yb[s, 1]).sum()  # > 0 since nu > 0
    total = torch.linalg.vector_norm(vector_area(x, topo), dim=1).sum()
    y = y * torch.sqrt(total / area)
    y = y - y.mean(0)
    # the eigenvector's phase (the image's rotation) is arbitrary: turn the default pins to +u
    p, q = _default_pins(verts, boundary).tolist()
    c = y[q] - y[p]
    rotation = torch.stack((torch.stack((c[0], -c[1])), torch.stack((c[1], c[0])))) / c.norm()
    return (y @ rotation).to(verts.dtype)


def conformal_parameterization(
    verts: torch.Tensor,
    faces: MeshFaces,
    pins: torch.Tensor | list[int] | None = None,
    pin_uv: torch.Tensor | None = None,
    *,
    free_boundary: bool = False,
    lam: float = 1.0,
    method: str = "aw11",
) -> torch.Tensor:
    """Flat conformal map of a disk-like polygon mesh minimizing ``E_C`` (AW11 sec. 5.2).

    Args:
        verts: ``(V, 3)`` positions, float32 or float64.
        faces: polygon faces of one connected, consistently oriented mesh with boundary. The
            pinned map takes any number of boundary loops (the area form sums over all of
            them); ``free_boundary=True`` needs a topological disk (one loop, Euler
            characteristic 1).
        pins: two boundary vertex indices to prescribe (pinned mode). Default: two far-apart
            boundary vertices (a deterministic double farthest-point sweep). That choice is
            read from the data: where two boundary vertices are equally far (a symmetric
            boundary), moving the vertices by any amount switches it and the map jumps, so
            gradients there do not describe the map (central differences grow as ``1 / h``).
            For a loss through ``uv``, pass fixed ``pins``. ``free_boundary`` rotates its map
            by the default pins: the same jump, unseen by losses invariant under rotation.
        pin_uv: ``(2, 2)`` their target positions. Default: ``(0, 0)`` and ``(d, 0)`` with
            ``d`` their distance in 3D.
        free_boundary: solve AW11 eq. 13-15 instead (no pins): minimize ``E_C`` subject to
            ``A(Y) = 1`` via the boundary Schur complement (eq. 15); the result is scaled to
            the source's total face area, centered at the origin and rotated so that the
            default pins (see ``pins``) lie along the ``u`` axis.
        lam: stabilizer weight of the Laplacian.
        method: the Laplacian, ``"aw11"`` (default), ``"plms"`` (``lam`` unused) or
            ``"degoes"`` (see :func:`torch_polylap.laplacian`).

    Returns:
        ``uv``: ``(V, 2)``, dtype and device of ``verts``, differentiable in ``verts`` (and
        ``pin_uv``): the pinned map by a sparse solve with adjoint backward, the free-boundary
        map through the Schur complement's sparse solve and the top eigenpair of a dense
        ``(m-1) x (m-1)`` Hermitian matrix (``m`` boundary vertices; its backward needs that
        eigenvalue to be simple, and raises if it is not).

    Raises:
        ValueError: a non-manifold edge or vertex, faces not consistently oriented or a
            non-orientable mesh (the message names the first offending edges and the repair,
            e.g. ``verts, faces, rep = torch_polylap.repair.orient_faces(verts, faces)``), no
            boundary, several connected components, unreferenced vertices, pins that are not
            two distinct boundary vertices, ``pins`` with ``free_boundary``, a mesh that is not
            a topological disk with ``free_boundary`` (the message gives its boundary loops,
            Euler characteristic and genus).
    """
    check_verts(verts)
    check_method(method)
    topo = get_topology(faces, verts.shape[0])
    boundary = _check_mesh(verts, topo)
    if free_boundary:
        if pins is not None or pin_uv is not None:
            raise ValueError("free_boundary=True places the whole boundary; do not pass pins.")
        _require_disk(topo)
        return _free_boundary(verts, topo, lam, boundary, method)
    if pins is None:
        if pin_uv is not None:
            raise ValueError("pin_uv was given without pins; pass the two pinned vertices too.")
        pins = _default_pins(verts, boundary)
    pins, pin_uv = _check_pins(pins, pin_uv, verts, boundary)
    return _pinned(verts, topo, lam, pins, pin_uv, method)


@dataclass
class AngleDistortion:
    """Corner-angle error of a flat map, see :func:`angle_distortion`.

    Attributes:
        per_corner: ``(N,)`` signed error ``theta_2D - theta_3D`` in radians, in the packed
            corner order of the faces (face by face, corner by corner).
        mean: mean absolute error (radians).
        rms: root mean square error (radians).
        max: largest absolute error (radians).
    """

    per_corner: torch.Tensor
    mean: float
    rms: float
    max: float


def _interior_angle(p: torch.Tensor, q: torch.Tensor, n: torch.Tensor | None) -> torch.Tensor:
    """Angle from ``q`` to ``p``, counter-clockwise about ``n`` (in 2D if ``n`` is None), in
    ``[0, 2 pi)``."""
    if n is None:
        sin = q[:, 0] * p[:, 1] - q[:, 1] * p[:, 0]
        cos = (q * p).sum(1)
    else:
        sin = (n * torch.linalg.cross(q, p, dim=1)).sum(1)
        # the in-plane parts of p and q: the normal components leave sin unchanged
        cos = (q * p).sum(1) - (q * n).sum(1) * (p * n).sum(1)
    return torch.remainder(torch.atan2(sin, cos), 2 * torch.pi)


def angle_distortion(uv: torch.Tensor, verts: torch.Tensor, faces: MeshFaces) -> AngleDistortion:
    """Per-corner angle error of a flat map ``uv`` of a polygon mesh.

    The source angle of corner ``i`` of face ``f`` is measured in the plane of ``f``'s maximal
    projection (normal ``a_f / |a_f|``, AW11 sec. 3.2): the counter-clockwise angle about that
    normal from ``x_{i+1} - x_i`` to ``x_{i-1} - x_i`` after projecting both to the plane, in
    ``[0, 2 pi)`` (reflex corners of non-convex faces included). The image angle is the same in
    the plane. For planar faces this is the ordinary corner angle; for a non-planar face it is
    the angle of the maximal projection, which the parameterization of a single polygon
    reproduces exactly (AW11 sec. 5.2). Flipped image corners show errors near ``2 pi``.

    Args:
        uv: ``(V, 2)`` image positions.
        verts: ``(V, 3)`` source positions.
        faces: the polygon faces.

    Returns:
        :class:`AngleDistortion` with the per-corner errors and their mean/RMS/max magnitude.
    """
    if uv.dim() != 2 or uv.shape[1] != 2 or uv.shape[0] != verts.shape[0]:
        raise ValueError(f"uv must have shape ({verts.shape[0]}, 2), got {tuple(uv.shape)}.")
    topo = get_topology(faces, verts.shape[0])
    pf = topo.faces.to(verts.device)
    nxt, prv, cur = pf.indices[pf.next_corner], pf.indices[pf.prev_corner], pf.indices
    normals = face_normals(verts, topo)[pf.corner_face]
    theta_3d = _interior_angle(verts[prv] - verts[cur], verts[nxt] - verts[cur], normals)
    uv = uv.to(verts.dtype)
    theta_2d = _interior_angle(uv[prv] - uv[cur], uv[nxt] - uv[cur], None)
    err = theta_2d - theta_3d
    mag = err.detach().abs()
    if not mag.numel():  # a mean and a maximum of nothing would be NaN and an IndexError
        raise ValueError("angle_distortion: the mesh has no faces, so no angle to compare.")
    return AngleDistortion(
        per_corner=err,
        mean=float(mag.mean()),
        rms=float(mag.square().mean().sqrt()),
        max=float(mag.max()),
    )
