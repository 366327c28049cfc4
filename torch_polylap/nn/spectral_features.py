"""Heat and wave kernel signatures as a layer, for batches of polygon meshes.

Built on :func:`torch_polylap.heat_kernel_signature` (Sun, Ovsjanikov & Guibas 2009) and
:func:`torch_polylap.wave_kernel_signature` (Aubry, Schlickewei & Cremers 2011) of the
Alexa-Wardetzky operators (AW11 eq. 3, 9, 10).

Default sampling follows the papers, per mesh, from its own eigenvalues: HKS times
log-spaced over ``[4 ln 10 / mu_max, 4 ln 10 / mu_min]`` (Sun et al. sec. 4; ``mu_min`` the
smallest non-zero eigenvalue), WKS log-energies evenly spaced over
``[log mu_min, log mu_max]`` with bandwidth 7 times the spacing (Aubry et al. sec. 4).  Learnable
samples are positions ``s in [0, 1]`` on that per-mesh log scale (so a feature means the same
relative scale on every mesh) or, with ``times=``/``energies=``, absolute values.

torch.compile: works, but graph-breaks several times per mesh (the per-mesh ``tolist()`` of
the batch offsets, data-dependent checks on the eigenvalues, boolean masks of zero
eigenvalues): six breaks for a one-mesh batch on torch 2.13. Fixed (non-learnable) features do
not change during training; compute them once per mesh outside the compiled region.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..spectral import heat_kernel_signature, wave_kernel_signature
from .spectrum import Spectrum

__all__ = ["hks_time_range", "wks_energy_range", "SpectralFeatures"]


def _nonzero_range(evals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    keep = evals > 1e-12 * evals.abs().max().clamp_min(torch.finfo(evals.dtype).tiny)
    if not bool(keep.any()):
        raise ValueError("spectral features need at least one non-zero eigenvalue (k >= 2).")
    positive = evals[keep]
    return positive.min(), positive.max()


def hks_time_range(evals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(t_min, t_max) = (4 ln 10 / mu_max, 4 ln 10 / mu_min)`` (Sun et al. 2009, sec. 4)."""
    mu_min, mu_max = _nonzero_range(evals)
    return 4 * math.log(10) / mu_max, 4 * math.log(10) / mu_min


def wks_energy_range(evals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log mu_min, log mu_max)`` over the non-zero eigenvalues (Aubry et al. 2011, sec. 4)."""
    mu_min, mu_max = _nonzero_range(evals)
    return torch.log(mu_min), torch.log(mu_max)


class SpectralFeatures(nn.Module):
    """Per-vertex HKS or WKS features ``(sumV, num_features)`` of a packed batch.

    Args:
        kind: ``"hks"`` or ``"wks"``.
        num_features: number of times (HKS) or energies (WKS).
        learnable: make the samples parameters.
        times: absolute HKS times ``(T,)`` instead of the per-mesh default (kept positive as
            ``exp(log_times)`` when learnable).
        energies: absolute WKS log-energies ``(E,)`` instead of the per-mesh default.
        normalize: divide each feature by its ``M0``-weighted mean over the mesh (scale- and
            resolution-robust inputs for learning; the HKS mean is the heat trace over the area).

    ``forward(spectrum: Spectrum) -> (sumV, F)``.
    """

    def __init__(
        self,
        kind: str = "hks",
        num_features: int = 16,
        *,
        learnable: bool = False,
        times: torch.Tensor | None = None,
        energies: torch.Tensor | None = None,
        normalize: bool = False,
    ) -> None:
        super().__init__()
        if kind not in ("hks", "wks"):
            raise ValueError(f"kind must be 'hks' or 'wks', got {kind!r}.")
        absolute = times if kind == "hks" else energies
        if (times is not None and kind != "hks") or (energies is not None and kind != "wks"):
            raise ValueError("pass `times` for kind='hks' and `energies` for kind='wks'.")
        self.kind, self.normalize, self.absolute = kind, normalize, absolute is not None
        if absolute is not None:
            values = torch.as_tensor(absolute, dtype=torch.get_default_dtype()).reshape(-1)
            if kind == "hks":
                if bool((values <= 0).any()):
                    raise ValueError("HKS `times` must be positive.")
                values = values.log()  # stored as log-times: positive for any parameter value
            num_features = values.numel()
        else:
            values = torch.linspace(0.0, 1.0, num_features)
        self.num_features = num_features
        if learnable:
            self.samples = nn.Parameter(values)
        else:
            self.register_buffer("samples", values)

    def samples_for(self, evals: torch.Tensor) -> torch.Tensor:
        """The times (HKS) or log-energies (WKS) used for a mesh with eigenvalues ``evals``."""
        s = self.samples.to(evals.dtype)
        if self.absolute:
            return s.exp() if self.kind == "hks" else s
        low, high = (hks_time_range if self.kind == "hks" else wks_energy_range)(evals)
        if self.kind == "hks":
            return torch.exp(torch.log(low) + s * (torch.log(high) - torch.log(low)))
        return low + s * (high - low)

    def forward(self, spectrum: Spectrum) -> torch.Tensor:
        outs = []
        firsts, counts = spectrum.first_idx.tolist(), spectrum.num_verts.tolist()
        for b, (first, count) in enumerate(zip(firsts, counts, strict=True)):
            evals, evecs = spectrum.evals[b], spectrum.evecs[first : first + count]
            samples = self.samples_for(evals)
            if self.kind == "hks":
                feats = heat_kernel_signature(evals, evecs, samples)
            else:
                sigma = None if self.num_features > 1 else 1.0
                feats = wave_kernel_signature(evals, evecs, samples, sigma)
            if self.normalize:
                m = spectrum.mass[first : first + count]
                feats = feats * (m.sum() / (m @ feats).clamp_min(torch.finfo(feats.dtype).tiny))
            outs.append(feats)
        return torch.cat(outs)

    def extra_repr(self) -> str:
        scale = "absolute" if self.absolute else "per-mesh"
        return f"kind={self.kind!r}, num_features={self.num_features}, {scale}"
