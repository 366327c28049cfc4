"""What the block kernels return: the entries of a chunk of faces of one degree (``F`` faces,
``P = k (k - 1) / 2`` corner pairs ``i < j``)."""

from __future__ import annotations

from typing import NamedTuple

import torch

__all__ = ["FaceEntries", "BlockEntries"]


class FaceEntries(NamedTuple):
    """The raw output of a method's formula (AW11, dGBD20) for one chunk of faces."""

    off: torch.Tensor
    """``(P, F)``: entry ``(pair_i[p], pair_j[p])`` of each face's block."""
    area: torch.Tensor
    """``(F,)``: the face area ``|f|``."""
    size2: torch.Tensor
    """``(F,)``: a squared length of the face, against which a zero area is judged."""


class BlockEntries(NamedTuple):
    """What a :data:`~torch_polylap.kernels.BlockKernel` hands the assembly for one chunk."""

    off: torch.Tensor
    """``(P, F)``: the off-diagonal entries of the blocks (the diagonal is minus their row
    sums)."""
    corner_mass: torch.Tensor
    """``(k, F)``: each corner's share of the lumped mass (AW11 eq. 10)."""
    area: torch.Tensor
    """``(F,)``: the face area."""
    size2: torch.Tensor
    """``(F,)``: a squared length of the face, against which a zero area is judged."""
    error: torch.Tensor
    """``(F,)``: a bound on the relative error of each block and its gradient in units of the
    working precision's eps (not differentiable)."""
