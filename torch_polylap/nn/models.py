"""A small DiffusionNet-like network (Sharp et al. 2022) on polygon meshes.

Per-vertex MLPs interleaved with learned heat diffusion (:class:`LearnedDiffusion`) of the
Alexa-Wardetzky Laplacian, with residual connections; optional HKS input features computed from
the batch's eigenpairs; ``M0``-weighted global mean pooling per mesh for classification.
With ``gradient_features=True`` each block is DiffusionNet's full block: diffusion, then
spatial gradient features of the diffused channels (:class:`SpatialGradientFeatures`, from the
per-vertex tangent gradient operators of
:func:`~torch_polylap.nn.gradient_features.vertex_gradient_operators`), then the per-vertex MLP
on ``[x, diffused, gradient features]`` with a residual connection.

torch.compile (torch 2.13, CPU, checked with ``torch._dynamo.explain``): a spectral
:class:`DiffusionBlock` is one graph without breaks; the whole model with HKS inputs splits
into eight graphs, all breaks in the HKS layer (see :mod:`torch_polylap.nn.spectral_features`);
``mode="implicit"`` breaks at every solve (see :mod:`torch_polylap.nn.diffusion`).
"""

from __future__ import annotations

import torch
from torch import nn

from ..batch import per_mesh_mean
from .diffusion import LearnedDiffusion
from .gradient_features import SpatialGradientFeatures
from .spectral_features import SpectralFeatures
from .spectrum import Spectrum, masses_of

__all__ = ["DiffusionBlock", "DiffusionNetLike"]


class DiffusionBlock(nn.Module):
    """``x + MLP([x, diffuse(x)])``: one residual diffusion block of width ``C``; with
    ``gradient_features=True``, ``x + MLP([x, d, G(d)])`` with ``d = diffuse(x)`` and ``G`` the
    :class:`SpatialGradientFeatures` (``with_rotations=gradient_rotations``).

    ``forward(x (sumV, C), spectrum=None, L=None, M0=None, grad_x=None, grad_y=None) ->
    (sumV, C)``; ``grad_x, grad_y`` ``(sumV, sumV)`` (block-diagonal for a batch) are needed
    with gradient features.
    """

    def __init__(
        self,
        width: int,
        mode: str = "spectral",
        dropout: float = 0.0,
        *,
        gradient_features: bool = False,
        gradient_rotations: bool = True,
    ) -> None:
        super().__init__()
        self.diffusion = LearnedDiffusion(width, mode)
        self.gradient = (
            SpatialGradientFeatures(width, with_rotations=gradient_rotations)
            if gradient_features
            else None
        )
        self.mlp = nn.Sequential(
            nn.Linear((3 if gradient_features else 2) * width, width),
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
        grad_x: torch.Tensor | None = None,
        grad_y: torch.Tensor | None = None,
    ) -> torch.Tensor:
        diffused = self.diffusion(x, spectrum, L, M0)
        if self.gradient is None:
            return x + self.mlp(torch.cat([x, diffused], 1))
        if grad_x is None or grad_y is None:
            raise ValueError(
                "gradient_features=True needs the vertex gradient operators grad_x and grad_y "
                "(torch_polylap.tangent.vertex_gradient_operators, or MeshBatch.grad_x / .grad_y)."
            )
        features = self.gradient(diffused, grad_x, grad_y)
        return x + self.mlp(torch.cat([x, diffused, features], 1))


class DiffusionNetLike(nn.Module):
    """Classifier (one output per mesh) or segmenter (one output per vertex).

    Args:
        in_channels: per-vertex input channels passed as ``x`` (0: HKS features only).
        out_channels: classes (or per-vertex outputs).
        width: hidden channels.
        num_blocks: number of residual diffusion blocks.
        mode: ``"spectral"`` or ``"implicit"`` diffusion (see :class:`LearnedDiffusion`).
        hks_features: number of normalized per-mesh HKS input features (0: none); needs a
            :class:`Spectrum` in ``forward``.
        task: ``"classification"`` (``M0``-weighted mean pooling per mesh, then a linear head)
            or ``"segmentation"``.
        gradient_features: DiffusionNet's spatial gradient features in every block (see
            :class:`DiffusionBlock`); default ``False``, the blocks without them (the model is
            then unchanged, parameters and random initialization included).
        gradient_rotations: with gradient features, learn complex (rotating) ``A`` matrices
            (DiffusionNet's ``with_gradient_rotations``); ``False``: real ones.

    ``forward(x=None, spectrum=None, *, L=None, M0=None, vert_to_mesh=None, grad_x=None,
    grad_y=None)``: ``x (sumV, C_in)``; returns ``(B, out_channels)`` logits for
    classification, ``(sumV, out_channels)`` for segmentation.  With ``mode="implicit"`` pass
    the block-diagonal ``L, M0`` (and, for classification without a spectrum,
    ``vert_to_mesh``); with gradient features the block-diagonal ``grad_x, grad_y``
    (``MeshBatch.grad_x``, ``.grad_y`` from a dataset with ``gradient_operators=True``).
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
        *,
        gradient_features: bool = False,
        gradient_rotations: bool = True,
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
        self.gradient_features = gradient_features
        self.blocks = nn.ModuleList(
            DiffusionBlock(
                width,
                mode,
                dropout,
                gradient_features=gradient_features,
                gradient_rotations=gradient_rotations,
            )
            for _ in range(num_blocks)
        )
        self.head = nn.Linear(width, out_channels)

    def forward(
        self,
        x: torch.Tensor | None = None,
        spectrum: Spectrum | None = None,
        *,
        L: torch.Tensor | None = None,
        M0: torch.Tensor | None = None,
        vert_to_mesh: torch.Tensor | None = None,
        grad_x: torch.Tensor | None = None,
        grad_y: torch.Tensor | None = None,
    ) -> torch.Tensor:
        inputs = [] if x is None else [x]
        if self.features is not None:
            if spectrum is None:
                raise ValueError("hks_features > 0 needs the batch's Spectrum.")
            # log: HKS values span decades across vertices and times
            inputs.append(torch.log(self.features(spectrum)))
        h = self.lift(torch.cat(inputs, 1).to(self.lift.weight.dtype))
        for block in self.blocks:
            h = block(h, spectrum, L, M0, grad_x, grad_y)
        if self.task == "segmentation":
            return self.head(h)
        if spectrum is not None:
            mass, index, num = spectrum.mass, spectrum.vert_to_mesh, spectrum.num_meshes
        elif M0 is not None and vert_to_mesh is not None:
            mass, index = masses_of(M0), vert_to_mesh
            num = int(vert_to_mesh.max()) + 1
        else:
            raise ValueError("classification pooling needs a Spectrum, or M0 and vert_to_mesh.")
        return self.head(per_mesh_mean(h, index, num, weights=mass.to(h.dtype)))
