"""Packed eigenpairs of a batch of meshes, with the index maps the learning layers need.

A batch of ``B`` meshes with ``V_b`` vertices each is stored pytorch3d-style as *packed*
tensors: the vertices of all meshes concatenated (``sumV = sum_b V_b`` rows), with
``vert_to_mesh`` saying which mesh each row belongs to.  Every mesh carries the same number
``k`` of eigenpairs of ``L phi = mu M0 phi`` (``M0``-orthonormal, from
:func:`torch_polylap.eigs` or :func:`torch_polylap.cached_eigs`).

Products with the per-mesh eigenbases go through a *padded* view ``(B, V_max, .)`` built by
one scatter (and read back by one gather), so that a whole batch is projected with a single
batched matrix product instead of a Python loop over meshes or vertices.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from ..batch import to_arguments
from ..sparse import as_operator, is_operator

if TYPE_CHECKING:
    from ..batch import PolygonMeshes

__all__ = ["Spectrum"]


def masses_of(M0: torch.Tensor) -> torch.Tensor:
    """``(V,)`` diagonal of a sparse diagonal matrix (``M0``), differentiable in its values.

    A ``(V,)`` dense tensor is returned unchanged, so callers may pass masses directly.

    Raises:
        ValueError: ``M0`` is sparse but not diagonal.
    """
    if M0.layout == torch.strided and not is_operator(M0):
        if M0.dim() != 1:
            raise ValueError(
                f"expected masses of shape (V,) or a sparse M0, got {tuple(M0.shape)}."
            )
        return M0
    M0 = as_operator(M0)
    d = M0.diagonal()
    if M0.pattern.nnz != d.numel() or M0.shape[0] != M0.shape[1]:
        raise ValueError(
            "M0 must be a diagonal matrix (as torch_polylap.laplacian returns it for every "
            "method but 'diamond', whose mass couples the corners of each face); pass the (V,) "
            "masses instead, or use another method."
        )
    return d


@dataclass
class Spectrum:
    """``k`` eigenpairs of each mesh of a batch, packed.

    Attributes:
        evals: ``(B, k)`` eigenvalues, ascending per mesh.
        evecs: ``(sumV, k)`` ``M0``-orthonormal eigenvectors, rows of mesh ``b`` at
            ``first_idx[b] : first_idx[b] + num_verts[b]``.
        mass: ``(sumV,)`` lumped masses (diagonal of ``M0``), used for projections.
        num_verts: ``(B,)`` vertices per mesh (int64).
    Derived index maps: ``first_idx (B,)``, ``vert_to_mesh (sumV,)``, ``local_idx (sumV,)``
    (position of a vertex inside its mesh).
    """

    evals: torch.Tensor
    evecs: torch.Tensor
    mass: torch.Tensor
    num_verts: torch.Tensor

    def __post_init__(self) -> None:
        B, k = self.evals.shape
        n = int(self.num_verts.sum())
        if self.evecs.shape != (n, k) or self.mass.shape != (n,):
            raise ValueError(
                f"Spectrum: evals {tuple(self.evals.shape)} and num_verts (sum {n}) need evecs "
                f"of shape ({n}, {k}) and mass ({n},); got {tuple(self.evecs.shape)} and "
                f"{tuple(self.mass.shape)}."
            )
        counts = self.num_verts.to(device=self.evecs.device, dtype=torch.int64)
        self.num_verts = counts
        self.first_idx = torch.cumsum(counts, 0) - counts
        self.vert_to_mesh = torch.repeat_interleave(torch.arange(B, device=counts.device), counts)
        self.local_idx = torch.arange(n, device=counts.device) - self.first_idx[self.vert_to_mesh]
        self.max_verts = int(counts.max()) if B else 0
        self._padded_evecs: torch.Tensor | None = None

    @classmethod
    def from_meshes(
        cls, items: Sequence[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    ) -> Spectrum:
        """Pack ``[(evals (k,), evecs (V_b, k), M0 or mass (V_b,)), ...]`` (same ``k`` each)."""
        ks = {int(e.shape[0]) for e, _, _ in items}
        if len(ks) != 1:
            raise ValueError(f"every mesh needs the same number of eigenpairs, got k in {ks}.")
        masses = [masses_of(m) for _, _, m in items]
        return cls(
            torch.stack([e for e, _, _ in items]),
            torch.cat([v for _, v, _ in items]),
            torch.cat(masses),
            torch.tensor([m.shape[0] for m in masses], device=masses[0].device),
        )

    @classmethod
    def from_polygon_meshes(
        cls,
        meshes: PolygonMeshes,
        k: int,
        *,
        lam: float = 1.0,
        cache_dir: str | Path | None = None,
        method: str = "aw11",
    ) -> Spectrum:
        """``k`` eigenpairs of each mesh of a :class:`~torch_polylap.batch.PolygonMeshes`.

        With ``cache_dir`` they come from :func:`torch_polylap.cached_eigs` (on-disk cache keyed
        by the mesh and the method, so a dataset computes them once); the masses come from one
        block-diagonal assembly of the batch. ``method``: the Laplacian (``"aw11"``,
        ``"plms"``, ``"degoes"``, see :func:`torch_polylap.laplacian`). No gradient flows into
        the result.
        """
        from ..linalg import eigs
        from ..operators import laplacian
        from ..spectral import cached_eigs

        with torch.no_grad():
            mass = masses_of(meshes.laplacian(lam, method=method)[1])
            pairs = []
            for verts, faces in (meshes[i] for i in range(len(meshes))):
                if cache_dir is not None:
                    pairs.append(cached_eigs(verts, faces, k, cache_dir, lam=lam, method=method))
                else:
                    pairs.append(eigs(*laplacian(verts, faces, lam, method=method), k))
        return cls(
            torch.stack([e for e, _ in pairs]),
            torch.cat([v for _, v in pairs]),
            mass,
            meshes.num_verts_per_mesh(),
        )

    @property
    def num_meshes(self) -> int:
        return int(self.evals.shape[0])

    @property
    def k(self) -> int:
        return int(self.evals.shape[1])

    def to(self, *args: Any, **kwargs: Any) -> Spectrum:
        """The spectrum moved as :meth:`torch.Tensor.to` moves a tensor: ``to(dtype)``,
        ``to(device)``, ``to(device, dtype)``, ``to(tensor)``, keywords ``device``, ``dtype``,
        ``non_blocking``, ``copy`` (:func:`torch_polylap.batch.to_arguments`). The floating
        tensors take the dtype; ``num_verts`` stays int64.
        """
        move = to_arguments(*args, **kwargs)
        return Spectrum(
            move.apply(self.evals),
            move.apply(self.evecs),
            move.apply(self.mass),
            move.apply(self.num_verts),
        )

    def to_padded(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, V_max, C)`` zero-padded view of packed ``x: (sumV, C)`` (one scatter)."""
        out = x.new_zeros(self.num_meshes, self.max_verts, x.shape[1])
        return out.index_put((self.vert_to_mesh, self.local_idx), x)

    def from_padded(self, x: torch.Tensor) -> torch.Tensor:
        """Packed ``(sumV, C)`` rows of padded ``x: (B, V_max, C)`` (one gather)."""
        return x[self.vert_to_mesh, self.local_idx]

    def padded_evecs(self) -> torch.Tensor:
        """``(B, V_max, k)`` eigenvectors, zero rows past each mesh's end (computed once)."""
        if self.evecs.requires_grad:  # a cached tensor would hold a graph across calls
            return self.to_padded(self.evecs)
        if self._padded_evecs is None:
            self._padded_evecs = self.to_padded(self.evecs)
        return self._padded_evecs

    def project(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, k, C)`` spectral coefficients ``Phi_b^T M0_b x_b`` of packed ``x: (sumV, C)``."""
        return self.padded_evecs().transpose(1, 2) @ self.to_padded(self.mass[:, None] * x)

    def heat_diffusion(self, x: torch.Tensor, times: torch.Tensor) -> torch.Tensor:
        """Per-channel heat diffusion ``Phi_b exp(-t_c mu_b) Phi_b^T M0_b x_b`` of a packed batch.

        Args:
            x: ``(sumV, C)`` packed per-vertex signals.
            times: ``(C,)`` non-negative diffusion times, one per channel (differentiable).

        Returns:
            ``(sumV, C)``. For one mesh this equals
            :func:`torch_polylap.spectral_heat_diffusion` with the same eigenpairs.
        """
        coeffs = self.project(x)  # (B, k, C), M0-weighted projection per mesh
        decay = torch.exp(-self.evals[:, :, None] * times[None, None, :])
        return self.synthesize(decay * coeffs)

    def synthesize(self, coeffs: torch.Tensor) -> torch.Tensor:
        """Packed ``(sumV, C)`` signal ``Phi_b c_b`` from coefficients ``(B, k, C)``."""
        return self.from_padded(self.padded_evecs() @ coeffs)
