"""The exact rescaling of the coordinates that every assembly form starts from.

``L`` is scale invariant and ``M0`` scales with the square of the mesh's size, so the kernels
see the coordinates multiplied by a power of two that brings the largest magnitude into
``[1/2, 1)`` (exact in floating point): no intermediate under- or overflows whatever the
mesh's scale, and the masses are scaled back.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

__all__ = ["Normalizer", "normalizer", "unscaled"]


class Normalizer(NamedTuple):
    scale: torch.Tensor
    """0-dim power of two that brings the largest coordinate magnitude into ``[1/2, 1)``."""
    unscale: torch.Tensor
    """0-dim, its reciprocal."""
    finite: torch.Tensor
    """0-dim bool: every coordinate is finite (NaN and infinities reach the extremes)."""


def normalizer(verts: torch.Tensor) -> Normalizer:
    """The exact rescaling of the coordinates (multiplying by powers of two), without a
    device sync, and whether they are finite: one pass over ``verts`` for both."""
    info = torch.finfo(verts.dtype)
    if verts.numel() == 0:
        one = verts.new_ones(())
        return Normalizer(one, one, torch.ones((), dtype=torch.bool, device=verts.device))
    extremes = torch.stack(torch.aminmax(verts.detach()))
    low, high = extremes.unbind(0)
    exponent = torch.frexp(torch.maximum(high, -low)).exponent
    # within the normal range both ways; a non-finite maximum is refused by the validation
    exponent = exponent.clamp(int(math.log2(info.tiny)) + 1, int(math.log2(info.max)) - 1)
    one = verts.new_ones(())
    return Normalizer(
        torch.ldexp(one, -exponent), torch.ldexp(one, exponent), torch.isfinite(extremes).all()
    )


def unscaled(masses: torch.Tensor | None, unscale: torch.Tensor) -> torch.Tensor | None:
    """The masses of the normalized coordinates in the caller's units (two factors: the
    square of ``unscale`` alone can overflow where the product does not)."""
    return None if masses is None else masses * unscale * unscale
