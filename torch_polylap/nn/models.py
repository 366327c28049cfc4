"""A small DiffusionNet-like network (Sharp et al. 2022) on polygon meshes.

Per-vertex MLPs interleaved with learned heat diffusion (:class:`LearnedDiffusion`) of the
Alexa-Wardetzky Laplacian, with residual connections; optional HKS input features computed from
the batch's eigenpairs; ``M0``-weighted global mean pooling per mesh for classification.
Unlike DiffusionNet there are no spatial-gradient features (the layer needs a tangent-vector
gradient operator, which this package does not provide for polygon faces yet).

torch.compile (torch 2.13, CPU, checked with ``torch._dynamo.explain``): a spectral
:class:`DiffusionBlock` is one graph without breaks; the whole model with HKS inputs splits
into eight graphs, all breaks in the HKS layer (see :mod:`torch_polylap.nn.spectral_features`);
``mode="implicit"`` breaks at every solve (see :mod:`torch_polylap.nn.diffusion`).
"""

from __future__ import annotations

import torch
from torch import nn

from .diffusion import LearnedDiffusion
from .spectral_features import SpectralFeatures
from .spectrum import Spectrum, diagonal, per_mesh_weighted_mean

__all__ = ["DiffusionBlock", "DiffusionNetLike"]


class DiffusionBlock(nn.Module):
    """``x + MLP([x, diffuse(x)])``: one residual diffusion block of width ``C``.

    ``forward(x (sumV, C), spectrum=None, L=None, M0=None) -> (sumV, C)``.
    """

    def __init__(self, width: int, mode: str = "spectral", dropout: float = 0.0) -> None:
        super().__init__()
        self.diffusion = LearnedDiffusion(width, mode)
        self.mlp = nn.Sequential(
            nn.Linear(2 * width, width),
            nn.ReLU(),
            nn.Dropout(dropout),
            nn.Linear(width, width),
        )

    def forward(
        self,
        x: torch.Tensor,
        spectrum: Spectrum | None = None,
        L: torch.Tensor | None = None,
        M0: torch.Tensor | None = None,
    ) -> torch.Tensor:
        diffused = self.diffusion(x, spectrum, L, M0)
        return x + self.mlp(torch.cat([x, diffused], 1))


class DiffusionNetLike(nn.Module):
    """Classifier (one output per mesh) or segmenter (one output per vertex).

    Args:
        in_channels: per-vertex input channels passed as ``x`` (0: HKS features only).
        out_channels: classes (or per-vertex outputs).
        width: hidden channels; num_blocks: residual diffusion blocks.
        mode: ``"spectral"`` or ``"implicit"`` diffusion (see :class:`LearnedDiffusion`).
        hks_features: number of normalized per-mesh HKS input features (0: none); needs a
            :class:`Spectrum` in ``forward``.
        task: ``"classification"`` (``M0``-weighted mean pooling per mesh, then a linear head)
            or ``"segmentation"``.

    ``forward(x=None, spectrum=None, *, L=None, M0=None, vert_to_mesh=None)``: ``x (sumV, C_in)``;
    returns ``(B, out_channels)`` logits for classification, ``(sumV, out_channels)`` for
    segmentation.  With ``mode="implicit"`` pass the block-diagonal ``L, M0`` (and, for
    classification without a spectrum, ``vert_to_mesh``).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        width: int = 32,
        num_blocks: int = 3,
        mode: str = "spectral",
        hks_features: int = 16,
        task: str = "classification",
        dropout: float = 0.0,
    ) -> None:
        super().__init__()
        if task not in ("classification", "segmentation"):
            raise ValueError(f"task must be 'classification' or 'segmentation', got {task!r}.")
        if in_channels + hks_features == 0:
            raise ValueError("DiffusionNetLike needs input channels or hks_features > 0.")
        self.task = task
        self.features = (
            SpectralFeatures("hks", hks_features, normalize=True) if hks_features else None
        )
        self.lift = nn.Linear(in_channels + hks_features, width)
        self.blocks = nn.ModuleList(DiffusionBlock(width, mode, dropout) for _ in range(num_blocks))
        self.head = nn.Linear(width, out_channels)

    def forward(
        self,
        x: torch.Tensor | None = None,
        spectrum: Spectrum | None = None,
        *,
        L: torch.Tensor | None = None,
        M0: torch.Tensor | None = None,
        vert_to_mesh: torch.Tensor | None = None,
    ) -> torch.Tensor:
        inputs = [] if x is None else [x]
        if self.features is not None:
            if spectrum is None:
                raise ValueError("hks_features > 0 needs the batch's Spectrum.")
            # log: HKS values span decades across vertices and times
            inputs.append(torch.log(self.features(spectrum)))
        h = self.lift(torch.cat(inputs, 1).to(self.lift.weight.dtype))
        for block in self.blocks:
            h = block(h, spectrum, L, M0)
        if self.task == "segmentation":
            return self.head(h)
        if spectrum is not None:
            mass, index, num = spectrum.mass, spectrum.vert_to_mesh, spectrum.num_meshes
        elif M0 is not None and vert_to_mesh is not None:
            mass, index = diagonal(M0), vert_to_mesh
            num = int(vert_to_mesh.max()) + 1
        else:
            raise ValueError("classification pooling needs a Spectrum, or M0 and vert_to_mesh.")
        return self.head(per_mesh_weighted_mean(h, mass.to(h.dtype), index, num))
