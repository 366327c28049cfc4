"""Learned heat diffusion on polygon meshes (DiffusionNet-style, Sharp et al. 2022, sec. 3.2).

Each channel ``c`` of a per-vertex signal ``x`` is diffused for its own learned time ``t_c``
by the heat operator ``exp(-t_c M0^{-1} L)`` of the Alexa-Wardetzky Laplacian (AW11 eq. 3,
9, 10).  Two discretizations:

* ``"spectral"`` (:meth:`Spectrum.heat_diffusion`): ``Phi exp(-t_c mu) Phi^T M0 x`` in the
  truncated eigenbasis (``k`` eigenpairs per mesh, precomputed once per mesh and cached).
  Cost per forward ``O(sumV * k * C)`` dense work; exact for the low frequencies, drops
  everything above ``mu_k`` (a low-pass filter even at ``t = 0``).
* ``"implicit"`` (:func:`torch_polylap.implicit_heat_diffusion`): one backward Euler step
  ``(M0 + t_c L) u = M0 x`` per channel through :func:`torch_polylap.solve`. Cost per
  forward: ``C`` sparse factorizations of the ``sumV x sumV`` block-diagonal matrix (cached
  for the backward pass), so it is far slower than the spectral mode for many channels; it
  needs no eigenpairs, keeps all frequencies (``1 / (1 + t mu)`` instead of ``exp(-t mu)``)
  and is differentiable in ``L`` and ``M0`` too (gradients to vertex positions).

torch.compile: the spectral path is dense (scatter, batched matmul, gather) and compiles to a
single graph without breaks (checked with ``torch._dynamo.explain`` on torch 2.13, CPU; same
values as eager); the implicit path calls SciPy's SuperLU through
a custom autograd function: Dynamo splits it into ten graphs (nine breaks at the NumPy/SciPy
calls of each layer), so compiling it gains nothing.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..spectral import implicit_heat_diffusion
from .spectrum import Spectrum

__all__ = ["LearnedDiffusion"]


def _inverse_softplus(t: torch.Tensor) -> torch.Tensor:
    return t + torch.log(-torch.expm1(-t))


def raw_times(channels: int, init_times: tuple[float, float]) -> nn.Parameter:
    """``(C,)`` raw parameters whose softplus is ``channels`` times log-spaced over
    ``init_times``; spaced in float64 so every default dtype starts from the same times."""
    low, high = init_times
    times = torch.logspace(math.log10(low), math.log10(high), channels, dtype=torch.float64)
    return nn.Parameter(_inverse_softplus(times).to(torch.get_default_dtype()))


class LearnedDiffusion(nn.Module):
    """Diffuse each of ``channels`` features for its own learned time.

    Times are ``softplus(raw)``: always positive, smooth, and for small times
    ``d t / d raw ~ t``, so gradient steps change a time by a relative amount (times spread
    over decades train evenly).  They start log-spaced over ``init_times`` (deterministic, so
    every replica of a distributed model starts equal).

    Args:
        channels: number of channels ``C``.
        mode: ``"spectral"`` (needs a :class:`Spectrum`) or ``"implicit"`` (needs ``L, M0``).
        init_times: ``(low, high)`` range of initial times, for meshes of unit area.

    Shapes: ``forward(x (sumV, C), spectrum=None, L=None, M0=None) -> (sumV, C)``.
    """

    def __init__(
        self,
        channels: int,
        mode: str = "spectral",
        init_times: tuple[float, float] = (1e-3, 1e-1),
    ) -> None:
        super().__init__()
        if mode not in ("spectral", "implicit"):
            raise ValueError(f"mode must be 'spectral' or 'implicit', got {mode!r}.")
        self.channels, self.mode = channels, mode
        self.raw_times = raw_times(channels, init_times)

    @property
    def times(self) -> torch.Tensor:
        """``(C,)`` current diffusion times (positive)."""
        return nn.functional.softplus(self.raw_times)

    def forward(
        self,
        x: torch.Tensor,
        spectrum: Spectrum | None = None,
        L: torch.Tensor | None = None,
        M0: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if x.dim() != 2 or x.shape[1] != self.channels:
            raise ValueError(
                f"LearnedDiffusion expects x of shape (sumV, {self.channels}), got "
                f"{tuple(x.shape)}."
            )
        times = self.times.to(x.dtype)
        if self.mode == "spectral":
            if spectrum is None:
                raise ValueError("mode 'spectral' needs the batch's Spectrum (eigenpairs).")
            return spectrum.heat_diffusion(x, times)
        if L is None or M0 is None:
            raise ValueError("mode 'implicit' needs the (block-diagonal) L and M0.")
        return implicit_heat_diffusion(L, M0, x, times)

    def extra_repr(self) -> str:
        return f"channels={self.channels}, mode={self.mode!r}"
