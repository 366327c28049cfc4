"""The shape operator and principal curvatures of a polygon mesh, from the normals' gradient.

The shape operator is the derivative of the unit normal, ``S = dn`` (tangent to tangent,
symmetric).  Per face ``f`` it is discretized by applying the package's face gradient
(:func:`~torch_polylap.face_gradient`, exact for linear functions on every polygon: the polygon
gradient of AW11 and de Goes et al. 2020, eq. 8) to the three components of the vertex normals
``n_v`` of :class:`~torch_polylap.vector.TangentFrames`:

    J_f = (grad_f n^x, grad_f n^y, grad_f n^z),     S_f = P_f sym(J_f) P_f,

with ``P_f`` the projector on the face plane and ``sym(J) = (J + J^T) / 2``; this is the
construction of de Goes et al. 2020 (sec. 5.3, eq. 23) without their stabilizer. At a vertex the
face tensors around it are carried to its tangent plane by the minimal rotation
``Q(n_f -> n_v)`` (the connection of :mod:`torch_polylap.vector.transport`) and averaged with
the face areas as weights:

    S_v = sum_{f ~ v} |f| Q S_f Q^T / sum_{f ~ v} |f|,

returned as the ``2 x 2`` symmetric matrix of its coordinates in ``(e_x(v), e_y(v))``.  Its
eigenvalues (in closed form: no eigensolver, so smooth away from umbilics) are the principal
curvatures.  Sign: ``S = dn`` with the outward normal (counter-clockwise faces seen from outside)
gives ``+1 / R`` on a sphere of radius ``R``.

Which normals are differentiated.  ``S_f`` is a derivative of the vertex normals, so an error
``O(h^p)`` in the normals becomes ``O(h^(p-1))`` in ``S``.  The area-weighted normals of
:func:`~torch_polylap.tangent.vertex_tangent_frames` are only first-order accurate on irregular
meshes (``O(h)``: the imbalance of the faces around a vertex does not shrink under refinement),
and ``S`` built from them does not converge there (measured mean errors on the unit-sphere
families: 5% on jittered hexagons and 12% on Voronoi cells at every level; ``docs/vector.md``).
On the sphere the face gradient of the *exact* normals ``n = x`` is exact, so this error is
entirely the normals'.  The default normals are therefore those of a second-order jet (Cazals
and Pouget 2005): at each vertex ``v``, in the frame ``(e_x, e_y, n_0)`` of the area-weighted
normal ``n_0``, the height ``w = a p + b q + c p^2 + d p q + e q^2`` is fitted by least squares
to the vertices ``u`` sharing a face with ``v`` (``(p, q, w)`` the coordinates of ``x_u - x_v``),

    n_v = (n_0 - a e_x - b e_y) / |n_0 - a e_x - b e_y|,                              (2)

the normal of the fitted graph at ``v``, which is ``O(h^2)``-accurate on any sampling (the fit
is exact for quadratic heights) and makes ``S`` first-order accurate
(:func:`fitted_frames`).  Where fewer than five distinct vertices share a face with ``v``
(valence-3 and 4 triangle vertices, the corners of a grid) the quadric is underdetermined and
``n_0`` is kept.
"""

from __future__ import annotations

import torch

from .._typing import MeshFaces
from ..calculus import face_gradient_of
from ..checks import check_verts
from ..kernels.frames import component_norm, stable_norm
from ..measures import vector_area
from ..topology import Topology, get_topology
from ..tracing import outside_transforms, run_eagerly, tracing
from .transport import TangentFrames, minimal_rotation, tangent_frames

__all__ = ["face_shape_operator", "fitted_frames", "shape_operator", "principal_curvatures"]

# Tikhonov weight of the jet's quadratic coefficients, per neighbour, in units of the ring's
# radius (the fit's entries are O(1) per neighbour; the fit runs in float64), well above the
# round-off of the 5 x 5 solve and below what biases a well-posed fit: 1e-4 moved the normals
# of the concave sphere family by up to 0.03 degrees and its curvatures by up to 2%, 1e-6 and
# below changed them by less than 1e-4.
_RIDGE = 1e-8


def _ring_pairs(topo: Topology) -> tuple[torch.Tensor, torch.Tensor]:
    """``(v, u)``: every ordered pair of distinct vertices sharing a face, each pair once, sorted
    by ``v``. Cached on the topology; when traced and not yet cached, computed outside the graph
    (it depends on the faces alone, and its size on their data) and not stored, since a traced
    function must not change the topology it guards on."""
    key = ("vector.ring_pairs", torch.device("cpu"))
    cached = topo.derived.get(key)
    if cached is not None:
        return cached
    if tracing():
        return run_eagerly(_compute_ring_pairs, topo)
    with outside_transforms():
        cached = topo.derived[key] = _compute_ring_pairs(topo)
    return cached


def _compute_ring_pairs(topo: Topology) -> tuple[torch.Tensor, torch.Tensor]:
    faces = topo.faces
    sizes = faces.sizes
    corner_size = torch.repeat_interleave(sizes, sizes)  # k_f of each corner's face
    corner_start = torch.repeat_interleave(faces.offsets[:-1], sizes)
    # corner c is paired with the k_f corners of its face: c repeated k_f times
    first = torch.repeat_interleave(torch.arange(faces.num_corners), corner_size)
    block_start = torch.cumsum(corner_size, 0) - corner_size
    position = torch.arange(first.numel()) - torch.repeat_interleave(block_start, corner_size)
    v = faces.indices[first]
    u = faces.indices[corner_start[first] + position]
    n = topo.num_verts
    code = torch.unique(v[v != u] * n + u[v != u])
    return torch.div(code, n, rounding_mode="floor"), code % n


def fitted_frames(
    verts: torch.Tensor, faces: MeshFaces, frames: TangentFrames | None = None
) -> TangentFrames:
    """Vertex frames whose normals are those of a second-order jet (eq. (2) of the module
    docstring): ``O(h^2)``-accurate normals on irregular meshes, where the area-weighted normals
    are ``O(h)``.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        frames: the frames whose normals ``n_0`` set the fit's height direction; default
            :func:`~torch_polylap.tangent.vertex_tangent_frames` (area-weighted normals).

    Returns:
        :class:`~torch_polylap.vector.TangentFrames`: ``frames`` carried by the minimal rotation
        ``Q(n_0 -> n_v)`` onto the fitted normals ``n_v`` (unchanged where the quadric is
        underdetermined: fewer than five distinct vertices share a face with ``v``).
        Differentiable in ``verts``.
    """
    check_verts(verts)
    return _fitted_frames(verts, get_topology(faces, verts.shape[0]), frames)


def _fitted_frames(
    verts: torch.Tensor, topo: Topology, frames: TangentFrames | None
) -> TangentFrames:
    """:func:`fitted_frames` on a topology, ``verts`` checked."""
    frames = tangent_frames(verts, topo) if frames is None else TangentFrames(*frames)
    v, u = (t.to(verts.device) for t in _ring_pairs(topo))
    n = topo.num_verts
    # the fit runs in float64: its normal equations square the conditioning
    x = verts.double()
    d = x[u] - x[v]
    axes = (frames.e_x, frames.e_y, frames.normal)
    p, q, w = ((d * axis.double()[v]).sum(1) for axis in axes)
    # scale by the ring's radius so the 5 x 5 normal equations are O(1) whatever h is
    count = torch.bincount(v, minlength=n)
    spread = x.new_zeros(n).index_add(0, v, p * p + q * q) / count.clamp_min(1)
    scale = spread.sqrt().clamp_min(torch.finfo(x.dtype).tiny)[v]
    p, q, w = p / scale, q / scale, w / scale
    rows = torch.stack((p, q, p * p, p * q, q * q), 1)
    gram = x.new_zeros(n, 5, 5).index_add(0, v, rows[:, :, None] * rows[:, None, :])
    rhs = x.new_zeros(n, 5).index_add(0, v, rows * w[:, None])
    fit = count >= 5
    # A small Tikhonov term on the quadratic coefficients keeps rings that cannot tell a slope
    # from a curvature solvable (on a grid's boundary q^2 = q at every neighbour): they get the
    # least-curved fit. Rows with no fit solve the identity; their result is discarded.
    ridge = torch.tensor([0.0, 0.0, 1.0, 1.0, 1.0], dtype=x.dtype, device=x.device)
    gram = gram + torch.diag_embed(_RIDGE * count.to(x.dtype)[:, None] * ridge)
    eye = torch.eye(5, dtype=x.dtype, device=x.device)
    gram = torch.where(fit[:, None, None], gram, eye)
    slope = (torch.linalg.solve(gram, rhs)[:, :2] * fit[:, None]).to(verts.dtype)
    normal = frames.normal - slope[:, :1] * frames.e_x - slope[:, 1:] * frames.e_y
    normal = normal / stable_norm(normal, 1, keepdim=True)
    return TangentFrames(
        normal,
        minimal_rotation(frames.normal, normal, frames.e_x),
        minimal_rotation(frames.normal, normal, frames.e_y),
    )


def face_shape_operator(
    verts: torch.Tensor, faces: MeshFaces, frames: TangentFrames | None = None
) -> torch.Tensor:
    """``(F, 3, 3)`` symmetric per-face shape operators ``S_f`` (module docstring), in ambient
    coordinates, tangent to each face's plane (``S_f n_f = 0``): the face gradient of
    ``frames.normal`` (default :func:`fitted_frames`)."""
    check_verts(verts)
    return _face_shape_operator(verts, get_topology(faces, verts.shape[0]), frames)


def _face_shape_operator(
    verts: torch.Tensor, topo: Topology, frames: TangentFrames | None
) -> torch.Tensor:
    """:func:`face_shape_operator` on a topology, ``verts`` checked."""
    frames = _fitted_frames(verts, topo, None) if frames is None else TangentFrames(*frames)
    J = face_gradient_of(verts, topo, frames.normal)  # (F, 3, 3): J[f, d, c] = d n^c / d x_d
    a = vector_area(verts, topo, validate=False)
    n = a / stable_norm(a, 1, keepdim=True)
    P = torch.eye(3, dtype=verts.dtype, device=verts.device) - n[:, :, None] * n[:, None, :]
    return P @ (0.5 * (J + J.transpose(1, 2))) @ P


def shape_operator(
    verts: torch.Tensor, faces: MeshFaces, frames: TangentFrames | None = None
) -> tuple[torch.Tensor, TangentFrames]:
    """The per-vertex shape operator ``S_v`` (module docstring).

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        frames: the vertex frames, whose normals are differentiated; default
            :func:`fitted_frames` (second-order normals).

    Returns:
        ``(V, 2, 2)`` symmetric matrices in the frames' ``(e_x, e_y)`` coordinates, and the
        frames. Differentiable in ``verts``. Isolated vertices get zeros.
    """
    check_verts(verts)
    topo = get_topology(faces, verts.shape[0])
    frames = _fitted_frames(verts, topo, None) if frames is None else TangentFrames(*frames)
    S_f = _face_shape_operator(verts, topo, frames)
    a = vector_area(verts, topo, validate=False)
    area = stable_norm(a, 1)
    n_f = a / area[:, None]
    device = verts.device
    idx = topo.faces.indices.to(device)
    face = topo.faces.corner_face.to(device)
    # Q^T e for the vertex axes e: the axes carried into the face plane by Q(n_v -> n_f)
    n_v, n_c = frames.normal[idx], n_f[face]
    axes = torch.stack(
        [minimal_rotation(n_v, n_c, e[idx]) for e in (frames.e_x, frames.e_y)], 1
    )  # (N, 2, 3)
    per_corner = axes @ S_f[face] @ axes.transpose(1, 2) * area[face, None, None]
    total = verts.new_zeros(topo.num_verts, 2, 2).index_add(0, idx, per_corner)
    weight = verts.new_zeros(topo.num_verts).index_add(0, idx, area[face])
    weight = torch.where(weight > 0, weight, torch.ones_like(weight))
    return total / weight[:, None, None], frames


def principal_curvatures(
    verts: torch.Tensor, faces: MeshFaces, frames: TangentFrames | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Principal curvatures and directions: the eigenpairs of :func:`shape_operator`.

    Args:
        verts: ``(V, 3)`` vertex positions.
        faces: faces in any accepted form, or a :class:`~torch_polylap.topology.Topology`.
        frames: the vertex frames, whose normals are differentiated; default
            :func:`fitted_frames` (second-order normals).

    Returns:
        ``(kmin, kmax, dmin, dmax)``: ``(V,)`` curvatures ``kmin <= kmax`` (``+1 / R`` on a
        sphere of radius ``R`` with outward normals), and ``(V, 3)`` unit tangent directions
        (``dmin = normal x dmax``; each defined up to sign, and arbitrary at umbilics, where
        ``kmin = kmax``). Closed-form ``2 x 2`` eigenpairs, differentiable in ``verts`` away
        from umbilics; at an umbilic ``kmin`` and ``kmax`` take the mean curvature's gradient
        (as ``|x|`` takes 0 at 0), so their sum and product have their true gradients there,
        and the directions have none.
    """
    S, frames = shape_operator(verts, faces, frames)
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    mean = 0.5 * (a + d)
    half_gap = component_norm(0.5 * (a - d), b, torch.zeros_like(b))
    theta = 0.5 * torch.atan2(2 * b, a - d)  # angle of the kmax axis from e_x
    dmax = torch.cos(theta)[:, None] * frames.e_x + torch.sin(theta)[:, None] * frames.e_y
    dmin = torch.linalg.cross(frames.normal, dmax, dim=1)
    return mean - half_gap, mean + half_gap, dmin, dmax
