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
"""

from __future__ import annotations

import torch

from .._typing import MeshFaces
from ..calculus import face_gradient
from ..checks import check_verts
from ..kernels.frames import stable_norm
from ..measures import vector_area
from ..topology import get_topology
from .transport import TangentFrames, minimal_rotation, tangent_frames

__all__ = ["face_shape_operator", "shape_operator", "principal_curvatures"]


def face_shape_operator(
    verts: torch.Tensor, faces: MeshFaces, frames: TangentFrames | None = None
) -> torch.Tensor:
    """``(F, 3, 3)`` symmetric per-face shape operators ``S_f`` (module docstring), in ambient
    coordinates, tangent to each face's plane (``S_f n_f = 0``)."""
    check_verts(verts)
    topo = get_topology(faces, verts.shape[0])
    frames = tangent_frames(verts, topo) if frames is None else TangentFrames(*frames)
    J = face_gradient(verts, topo, frames.normal)  # (F, 3, 3): J[f, d, c] = d n^c / d x_d
    a = vector_area(verts, topo)
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
        frames: the vertex frames; default :func:`~torch_polylap.nn.vertex_tangent_frames`.

    Returns:
        ``(V, 2, 2)`` symmetric matrices in the frames' ``(e_x, e_y)`` coordinates, and the
        frames. Differentiable in ``verts``. Isolated vertices get zeros.
    """
    check_verts(verts)
    topo = get_topology(faces, verts.shape[0])
    frames = tangent_frames(verts, topo) if frames is None else TangentFrames(*frames)
    S_f = face_shape_operator(verts, topo, frames)
    a = vector_area(verts, topo)
    area = stable_norm(a, 1)
    n_f = a / area[:, None]
    device = verts.device
    idx = topo.faces.indices.to(device)
    face = torch.repeat_interleave(
        torch.arange(topo.num_faces, device=device), topo.faces.sizes.to(device)
    )
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

    Returns:
        ``(kmin, kmax, dmin, dmax)``: ``(V,)`` curvatures ``kmin <= kmax`` (``+1 / R`` on a
        sphere of radius ``R`` with outward normals), and ``(V, 3)`` unit tangent directions
        (``dmin = normal x dmax``; each defined up to sign, and arbitrary at umbilics, where
        ``kmin = kmax``). Closed-form ``2 x 2`` eigenpairs, differentiable in ``verts`` away
        from umbilics.
    """
    S, frames = shape_operator(verts, faces, frames)
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    mean = 0.5 * (a + d)
    half_gap = torch.hypot(0.5 * (a - d), b)
    theta = 0.5 * torch.atan2(2 * b, a - d)  # angle of the kmax axis from e_x
    dmax = torch.cos(theta)[:, None] * frames.e_x + torch.sin(theta)[:, None] * frames.e_y
    dmin = torch.linalg.cross(frames.normal, dmax, dim=1)
    return mean - half_gap, mean + half_gap, dmin, dmax
