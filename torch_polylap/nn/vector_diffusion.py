"""Rotation-equivariant layers on tangent vector features (vector DiffusionNet-style).

A vector feature has ``C`` channels of tangent vectors per vertex, stored as ``(V, C, 2)``
coordinates in the vertex frames of :func:`torch_polylap.vector.connection_laplacian`.  The
layers here commute with the quarter turn ``J (x, y) = (-y, x)`` applied in every frame, hence
with every rotation ``e^{i theta}`` of all the vectors by one angle, and they are written with
operators that transform like the vectors under a change of frames (gauge equivariance):

* :class:`LearnedVectorDiffusion`: each channel diffused for its own learned time by one
  implicit step of the connection heat flow, ``(M + t_c A) y = M x`` (the vector analogue of
  :class:`~torch_polylap.nn.LearnedDiffusion`'s ``"implicit"`` mode).  ``A``'s ``2 x 2`` blocks
  are complex numbers ``[[a, -b], [b, a]]`` and ``M`` repeats a scalar per vertex, so both
  commute with ``J`` and so does the solve.
* :class:`VectorLinear`: channel mixing by complex weights, ``y_o = sum_i (a_oi + b_oi J) x_i``
  (complex multiplications commute with rotations).
* :class:`VectorGate`: a magnitude gate, ``y_c = x_c sigmoid(w_c |x_c| + b_c)``: the gate reads
  only lengths, which rotations keep.

A truncated spectral diffusion with the connection Laplacian's eigenvectors would be
equivariant only if the truncation kept every complex eigenspace whole; the implicit step has
no such condition, so it is the one provided.  Under torch.compile the layer's forward is one
graph (the solve is a traced custom operator).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..linalg import solve
from ..sparse import as_operator
from .diffusion import raw_times

__all__ = ["LearnedVectorDiffusion", "VectorLinear", "VectorGate", "rotate_vectors"]


def rotate_vectors(x: torch.Tensor, angle: float | torch.Tensor) -> torch.Tensor:
    """``(..., 2)`` frame coordinates rotated by ``angle`` (a scalar, or broadcastable to
    ``x.shape[:-1]``, e.g. ``(V, 1)`` for one angle per vertex)."""
    angle = torch.as_tensor(angle, dtype=x.dtype, device=x.device)
    c, s = torch.cos(angle), torch.sin(angle)
    return torch.stack((c * x[..., 0] - s * x[..., 1], s * x[..., 0] + c * x[..., 1]), -1)


def _check(x: torch.Tensor, channels: int, name: str) -> None:
    if x.dim() != 3 or x.shape[1] != channels or x.shape[2] != 2:
        raise ValueError(
            f"{name} expects tangent vectors of shape (V, {channels}, 2), got {tuple(x.shape)}."
        )


class LearnedVectorDiffusion(nn.Module):
    """Diffuse each of ``channels`` tangent vector features for its own learned time.

    ``(M + t_c A) y_c = M x_c`` with ``A, M`` from
    :func:`~torch_polylap.vector.connection_laplacian` (or a block-diagonal batch of them),
    solved by :func:`~torch_polylap.solve` (one factorization per channel, cached for the
    backward pass).  Times are ``softplus(raw)`` and start log-spaced over ``init_times``, as in
    :class:`~torch_polylap.nn.LearnedDiffusion`.

    Args:
        channels: number of channels ``C``.
        init_times: ``(low, high)`` range of initial times, for meshes of unit area.

    Shapes: ``forward(x (V, C, 2), A (2V, 2V), M (2V, 2V)) -> (V, C, 2)``, coordinates in the
    frames ``A`` was built in.  Differentiable in ``x``, the times and ``A``'s and ``M``'s
    values (so in the vertex positions).
    """

    def __init__(self, channels: int, init_times: tuple[float, float] = (1e-3, 1e-1)) -> None:
        super().__init__()
        self.channels = channels
        self.raw_times = raw_times(channels, init_times)

    @property
    def times(self) -> torch.Tensor:
        """``(C,)`` current diffusion times (positive)."""
        return nn.functional.softplus(self.raw_times)

    def forward(self, x: torch.Tensor, A: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
        _check(x, self.channels, "LearnedVectorDiffusion")
        if A.shape != (2 * x.shape[0], 2 * x.shape[0]) or M.shape != A.shape:
            raise ValueError(
                f"LearnedVectorDiffusion: A and M must be ({2 * x.shape[0]}, {2 * x.shape[0]}) "
                f"for {x.shape[0]} vertices (interleaved coordinates), got {tuple(A.shape)} "
                f"and {tuple(M.shape)}."
            )
        n = x.shape[0]
        A, M = as_operator(A), as_operator(M)
        flat = x.permute(0, 2, 1).reshape(2 * n, self.channels)  # row 2 v + c, as A's
        rhs = M @ flat
        times = self.times.to(x.dtype)
        # M + t A keeps A's pattern (it holds the whole diagonal), also under torch.compile
        columns = [solve(M + times[c] * A, rhs[:, c]) for c in range(self.channels)]
        return torch.stack(columns, 1).reshape(n, 2, self.channels).permute(0, 2, 1)

    def extra_repr(self) -> str:
        return f"channels={self.channels}"


class VectorLinear(nn.Module):
    """``y_o = sum_i (a_oi + b_oi J) x_i``: channel mixing by complex weights.

    Args:
        in_channels: ``C_in``.
        out_channels: ``C_out``.

    Shapes: ``(V, C_in, 2) -> (V, C_out, 2)``.  No bias: a fixed vector would pick a direction
    and break the equivariance.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.in_channels, self.out_channels = in_channels, out_channels
        scale = 1.0 / math.sqrt(2 * in_channels)
        self.real = nn.Parameter(scale * torch.randn(out_channels, in_channels))
        self.imag = nn.Parameter(scale * torch.randn(out_channels, in_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check(x, self.in_channels, "VectorLinear")
        a, b = self.real.to(x.dtype), self.imag.to(x.dtype)
        re, im = x[..., 0], x[..., 1]  # (V, C_in)
        return torch.stack((re @ a.T - im @ b.T, re @ b.T + im @ a.T), -1)

    def extra_repr(self) -> str:
        return f"in_channels={self.in_channels}, out_channels={self.out_channels}"


class VectorGate(nn.Module):
    """``y_c = x_c sigmoid(w_c |x_c| + b_c)``: a non-linearity of the lengths only.

    ``|x_c|`` is computed as ``sqrt(|x_c|^2 + eps^2)`` so that the gradient stays finite at
    zero vectors.  Shapes: ``(V, C, 2) -> (V, C, 2)``.
    """

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.channels, self.eps = channels, eps
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check(x, self.channels, "VectorGate")
        length = torch.sqrt(x.square().sum(-1) + self.eps**2)  # (V, C)
        gate = torch.sigmoid(self.weight.to(x.dtype) * length + self.bias.to(x.dtype))
        return x * gate[..., None]

    def extra_repr(self) -> str:
        return f"channels={self.channels}"
