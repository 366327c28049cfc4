"""Per-vertex tangent gradients and DiffusionNet's spatial-gradient features on polygon meshes.

DiffusionNet (Sharp, Attaiki, Crane and Ovsjanikov 2022, section 3.3) complements isotropic
diffusion with *spatial gradient features*: the gradient of every feature channel is taken at
each vertex as a tangent vector, expressed in an arbitrary tangent frame, and the network sees
only quantities invariant to the choice of that frame -- inner products between the gradients
and a learned linear combination of them.  This module provides the three pieces on polygon
meshes:

- :func:`vertex_tangent_frames` (:class:`VertexFrames`) and :func:`vertex_gradient_operators`,
  the frames and the per-vertex tangent gradient operators, defined in
  :mod:`torch_polylap.tangent` (shared with :mod:`torch_polylap.vector`) and exported here;
- :class:`SpatialGradientFeatures` (functional :func:`spatial_gradient_features`): with
  ``g_c = (grad_x x_c) + i (grad_y x_c)`` the tangent gradient of channel ``c`` read as a
  complex number, a learned ``C x C`` matrix ``A`` mixes the channels, ``h = A g``, and the
  output is ``tanh(Re(conj(g_c) h_c))``, the dot product of each gradient with its transformed
  version.  ``A`` is complex (``A_re + i A_im``: a real ``2 x 2`` block ``[[a, -b], [b, a]]``
  per channel pair, a scaled rotation of the tangent vectors) with ``with_rotations=True``, real
  otherwise.  Both commute with rotating a vertex's tangent frame (multiplying its ``g`` by a
  unit complex number), so the features do not depend on the frames chosen.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..tangent import TangentFrames, vertex_gradient_operators, vertex_tangent_frames

__all__ = [
    "vertex_tangent_frames",
    "VertexFrames",
    "vertex_gradient_operators",
    "spatial_gradient_features",
    "SpatialGradientFeatures",
]

VertexFrames = TangentFrames
"""The frames of :func:`vertex_tangent_frames`: :class:`torch_polylap.tangent.TangentFrames`."""


def spatial_gradient_features(
    gx: torch.Tensor,
    gy: torch.Tensor,
    weight_re: torch.Tensor,
    weight_im: torch.Tensor | None = None,
) -> torch.Tensor:
    """``tanh(<g_c, (A g)_c>)`` per vertex and channel (DiffusionNet section 3.3).

    Args:
        gx: ``(V, C)`` first tangent component of the gradients of ``C`` channels
            (``grad_x @ x``).
        gy: ``(V, C)`` second tangent component (``grad_y @ x``).
        weight_re: ``(C, C)`` real part of ``A`` (``(A g)_c = sum_d A[c, d] g_d``).
        weight_im: ``(C, C)`` imaginary part of ``A`` (the rotation component), or ``None``
            for a real ``A`` acting alike on both tangent components.

    Returns:
        ``(V, C)`` features in ``(-1, 1)``, invariant to rotating any vertex's tangent frame.
    """
    hx, hy = gx @ weight_re.T, gy @ weight_re.T
    if weight_im is not None:
        hx = hx - gy @ weight_im.T
        hy = hy + gx @ weight_im.T
    return torch.tanh(gx * hx + gy * hy)


class SpatialGradientFeatures(nn.Module):
    """DiffusionNet's spatial gradient features of ``C`` channels.

    ``forward(x (V, C), grad_x (V, V), grad_y (V, V)) -> (V, C)``: the gradients
    ``g = (grad_x @ x, grad_y @ x)`` and :func:`spatial_gradient_features` with the learned
    ``A``.  For a batch pass the block-diagonal operators (``MeshBatch.grad_x``, ``.grad_y``).

    Args:
        channels: ``C``.
        with_rotations: learn a complex ``A`` (its imaginary part rotates the tangent vectors);
            ``False``: a real ``A``.
    """

    def __init__(self, channels: int, *, with_rotations: bool = True) -> None:
        super().__init__()
        bound = 1.0 / math.sqrt(channels)
        self.weight_re = nn.Parameter(torch.empty(channels, channels).uniform_(-bound, bound))
        self.weight_im = (
            nn.Parameter(torch.empty(channels, channels).uniform_(-bound, bound))
            if with_rotations
            else None
        )

    def forward(self, x: torch.Tensor, grad_x: torch.Tensor, grad_y: torch.Tensor) -> torch.Tensor:
        gx = grad_x @ x.to(grad_x.dtype)
        gy = grad_y @ x.to(grad_y.dtype)
        gx, gy = gx.to(self.weight_re.dtype), gy.to(self.weight_re.dtype)
        return spatial_gradient_features(gx, gy, self.weight_re, self.weight_im)
