"""Tangent frames and the discrete Levi-Civita transport between vertices and faces.

Every vertex ``v`` carries an orthonormal frame ``(n_v, e_x(v), e_y(v))`` (``n_v`` the normalized
sum of the vector areas of the faces around ``v``, see
:func:`torch_polylap.tangent.vertex_tangent_frames`); a tangent vector at ``v`` is stored as its two
coordinates in ``(e_x(v), e_y(v))``, or as the complex number ``X = x + i y``.

A vector at ``v`` is carried into the plane of a face ``f`` around it by the *minimal rotation*
``Q(n_v -> n_f)``, the rotation about ``n_v x n_f`` taking ``n_v`` to the face normal
``n_f = a_f / |a_f|``; this is the vertex-to-face Levi-Civita connection of de Goes, Butts and
Desbrun 2020 (sec. 5.1).  In a frame ``(t1(f), t2(f))`` of the face plane the image of ``e_x(v)``
is the unit complex number ``z_{v,f}``, and the whole transport is multiplication by it:
``X (in v's frame) -> z_{v,f} X (in f's frame)``.  Between two corners ``i``, ``j`` of one face,
the transport *through the face* is

    R^f_{ij} = conj(z_{i,f}) z_{j,f}        (from j's frame to i's frame),

which is flat inside a face (``R^f_{ij} R^f_{jk} = R^f_{ik}``) and does not depend on the face
frame ``(t1, t2)``, which cancels.  Working with the unit complex numbers themselves (rather
than angles from ``atan2``) keeps everything a polynomial-and-square-root function of the
vertices: smooth wherever the normals are defined and ``n_v != -n_f``.
"""

from __future__ import annotations

import torch

from ..faces import PolygonFaces
from ..kernels.frames import stable_norm
from ..measures import vector_area
from ..tangent import TangentFrames, tangent_frames
from ..topology import Topology
from ..tracing import require

__all__ = [
    "TangentFrames",
    "tangent_frames",
    "minimal_rotation",
    "corner_transport",
    "to_ambient",
    "to_tangent",
]


def minimal_rotation(n: torch.Tensor, m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``Q(n -> m) x``: the rotation about ``n x m`` that takes the unit vector ``n`` to ``m``,
    applied to ``x`` (all ``(..., 3)``; Rodrigues' formula written without the angle,
    ``Q x = c x + k x x + (k . x) k / (1 + c)`` with ``c = n . m``, ``k = n x m``).

    Defined for ``n != -m``; callers check that first (:func:`corner_transport`).
    """
    c = (n * m).sum(-1, keepdim=True)
    k = torch.linalg.cross(n, m, dim=-1)
    return c * x + torch.linalg.cross(k, x, dim=-1) + (k * x).sum(-1, keepdim=True) * k / (1 + c)


def face_normals_and_frames(
    verts: torch.Tensor, faces: PolygonFaces, topo: Topology
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(n_f, t1, t2)``, each ``(F, 3)``: unit normals ``a_f / |a_f|`` and a face-plane frame,
    ``t1`` along the first edge projected on the plane (smooth in the vertices, unlike a frame
    built from the normal alone, which needs a seam somewhere on the sphere of normals).
    ``verts`` as checked by the caller (the entry points of :mod:`torch_polylap.vector`)."""
    a = vector_area(verts, topo, validate=False)
    normal = a / stable_norm(a, 1, keepdim=True)
    start = faces.offsets[:-1].to(verts.device)
    idx = faces.indices.to(verts.device)
    edge = verts[idx[start + 1]] - verts[idx[start]]
    t1 = edge - (edge * normal).sum(1, keepdim=True) * normal
    t1 = t1 / stable_norm(t1, 1, keepdim=True)
    return normal, t1, torch.linalg.cross(normal, t1, dim=1)


def corner_transport(
    verts: torch.Tensor, faces: PolygonFaces, topo: Topology, frames: TangentFrames
) -> torch.Tensor:
    """``(N,)`` complex ``z_{v,f}`` per corner (in ``faces.indices`` order): the vertex's ``e_x``
    carried into its face's plane by ``Q(n_v -> n_f)``, in the face frame of
    :func:`face_normals_and_frames` (see the module docstring).

    Raises:
        ValueError: a corner whose vertex normal points against its face's normal (a fold; the
            minimal rotation is undefined there), naming the face and the vertex.
    """
    device = verts.device
    idx = faces.indices.to(device)
    face = faces.corner_face.to(device)
    n_f, t1, t2 = face_normals_and_frames(verts, faces, topo)
    n_v, n_c = frames.normal[idx], n_f[face]
    cos = (n_v * n_c).sum(1)
    folded = cos <= -1 + 1e-6
    fold = "a vertex normal points against its face's normal: the mesh folds over; repair it first."
    if not require(~folded, fold):
        c = int(torch.nonzero(folded)[0, 0])
        raise ValueError(
            f"face {int(face[c])}: the normal at its vertex {int(idx[c])} points against the "
            f"face's normal (cosine {float(cos[c]):.3g}), so no rotation carries the vertex's "
            "tangent plane onto the face; the mesh folds over there (a flipped face or a "
            "needle): repair it first."
        )
    carried = minimal_rotation(n_v, n_c, frames.e_x[idx])
    return torch.complex((carried * t1[face]).sum(1), (carried * t2[face]).sum(1))


def to_ambient(coords: torch.Tensor, frames: TangentFrames) -> torch.Tensor:
    """``(V, ..., 2)`` frame coordinates -> ``(V, ..., 3)`` ambient tangent vectors."""
    shape = (frames.e_x.shape[0],) + (1,) * (coords.dim() - 2) + (3,)
    ex, ey = frames.e_x.reshape(shape), frames.e_y.reshape(shape)
    return coords[..., :1] * ex + coords[..., 1:] * ey


def to_tangent(vectors: torch.Tensor, frames: TangentFrames) -> torch.Tensor:
    """``(V, ..., 3)`` ambient vectors -> ``(V, ..., 2)`` coordinates of their tangent parts."""
    shape = (frames.e_x.shape[0],) + (1,) * (vectors.dim() - 2) + (3,)
    ex, ey = frames.e_x.reshape(shape), frames.e_y.reshape(shape)
    return torch.stack(((vectors * ex).sum(-1), (vectors * ey).sum(-1)), -1)
