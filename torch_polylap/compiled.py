"""Opt-in compiled re-assembly of ``L`` and ``M0`` for a mesh whose vertices move.

:class:`CompiledLaplacian` compiles, for one topology, the assembly in its gather form
(:func:`~torch_polylap.assembly.assemble_gathered`: every stored value gathered from the per-face
entries, no scatter) with ``torch.compile``: the kernels and the gathers fuse into a few loops,
forward and backward. On a 1M-quad grid on one CPU thread it re-assembles in about two thirds
of the eager time and runs forward plus backward in about four fifths (the sparse products, not
compiled, weigh as much as the assembly there; the documentation's performance page has the
measurements). The compilation is paid at the first call (seconds to tens of seconds with
inductor's C++ backend; again for a new dtype, device or ``requires_grad``), so it is worth it
for a loop of many steps on one mesh, not for one call. Nothing compiles unless this class is
used: :func:`~torch_polylap.laplacian` stays eager.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ._typing import MeshFaces
from .assembly import (
    FLOAT32_STRETCH_LIMIT,
    FlaggedAssembly,
    assemble_gathered,
    gather_plan_of,
    warn_float32_products,
)
from .assembly.diamond import diamond_flagged
from .checks import Lam, check_lam, check_verts
from .kernels import block_kernel, check_method
from .kernels.diamond import DiamondPlan, diamond_plan
from .operators import laplacian
from .sparse.operator import operator_on
from .topology import Topology, TopologyView, topology_of

__all__ = ["CompiledLaplacian"]

DiamondFlagged = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


class CompiledLaplacian:
    """``(L, M0)`` of one mesh connectivity for any vertex positions, assembled by compiled code.

    Equal to ``tp.laplacian(verts, faces, lam, method=method, validate=validate)`` to
    round-off, with the same gradients (reverse mode; forward mode and torch.func transforms
    are the eager function's).

    Args:
        faces: the connectivity, as :func:`~torch_polylap.laplacian` takes it (a prebuilt
            :class:`~torch_polylap.topology.Topology` included).
        lam: the stabilizer weight, a number (a tensor ``lam`` that requires grad: use
            :func:`~torch_polylap.laplacian`).
        method: ``"aw11"``, ``"plms"``, ``"degoes"`` or ``"diamond"``, as for
            :func:`~torch_polylap.laplacian`.
        validate: the eager function's checks, computed inside the compiled code and read with
            one sync; when one fails (non-finite or degenerate input, or a float32 face too
            thin for float32) the call is answered by the eager function, which names the
            offending element or evaluates such faces in float64. A float32 face so thin
            that products with ``L`` lose accuracy gives the eager function's
            :class:`~torch_polylap.checks.Float32PrecisionWarning`, raised outside the
            compiled code from a flag it returns.
        options: passed to ``torch.compile`` (default ``{"dynamic": False}``).

    Examples:
        >>> import torch, torch_polylap as tp
        >>> from torch_polylap.shapes import quad_grid
        >>> V, F = quad_grid(4, bump=0.1)
        >>> lap = tp.CompiledLaplacian(F)  # compiles at the first call
        >>> L, M0 = lap(V.double())  # doctest: +SKIP
    """

    def __init__(
        self,
        faces: MeshFaces | Topology,
        lam: Lam = 1.0,
        *,
        method: str = "aw11",
        validate: bool = True,
        options: dict[str, object] | None = None,
    ) -> None:
        if isinstance(lam, torch.Tensor):
            raise TypeError(
                "CompiledLaplacian takes a number for lam; for a tensor lam (learnable), use "
                "torch_polylap.laplacian."
            )
        self.faces = faces
        self.lam = check_lam(lam)
        self.method = check_method(method)
        self.validate = validate
        self.options: dict[str, object] = {"dynamic": False} if options is None else options
        self._compiled: tuple[TopologyView, Callable[[torch.Tensor], FlaggedAssembly]] | None
        self._compiled = None
        self._compiled_diamond: tuple[DiamondPlan, Callable[[torch.Tensor], DiamondFlagged]] | None
        self._compiled_diamond = None

    def __call__(self, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L, M0)`` for ``verts`` ``(V, 3)``, as :func:`~torch_polylap.laplacian`."""
        verts = check_verts(verts, finite=False)
        topo = topology_of(self.faces, verts)
        if self.method == "diamond":
            return self._diamond(topo, verts)
        view = topo.on(verts.device)
        values, masses, ok, accurate, stretch = self._assembly(topo, view)(verts)
        if self.validate:
            # one sync for every check; NaN stretch means a degenerate face, which ok flags
            flags = torch.stack((ok, accurate, ~(stretch > FLOAT32_STRETCH_LIMIT))).tolist()
            if not (flags[0] and flags[1]):
                return laplacian(verts, topo, self.lam, method=self.method)
            if not flags[2]:
                warn_float32_products(verts, topo, block_kernel(self.method, self.lam))
        assert masses is not None
        L = operator_on(view.pattern, values, symmetric=True)
        return L, operator_on(view.diagonal, masses, symmetric=True)

    def _diamond(self, topo: Topology, verts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(L, M0)`` of ``method="diamond"`` by its compiled assembly (no per-face blocks)."""
        plan = diamond_plan(topo, verts.device)  # eagerly: its index tensors enter as constants
        if self._compiled_diamond is None or self._compiled_diamond[0] is not plan:
            fn = torch.compile(  # type: ignore[call-overload]
                lambda v: diamond_flagged(v, plan), fullgraph=True, **self.options
            )
            self._compiled_diamond = (plan, fn)
        L, M, ok, _ = self._compiled_diamond[1](verts)
        if self.validate and not bool(ok):
            return laplacian(verts, topo, self.lam, method=self.method)
        return operator_on(plan.pattern, L, symmetric=True), operator_on(
            plan.pattern, M, symmetric=True
        )

    def _assembly(
        self, topo: Topology, view: TopologyView
    ) -> Callable[[torch.Tensor], FlaggedAssembly]:
        """The compiled assembly on ``topo`` and ``view``'s device (the last one asked for is
        kept: a new mesh or device compiles again)."""
        if self._compiled is not None and self._compiled[0] is view:
            return self._compiled[1]
        kernel = block_kernel(self.method, self.lam)
        plan = gather_plan_of(topo, view)  # eagerly: its index tensors enter as constants

        def assemble(verts: torch.Tensor) -> FlaggedAssembly:
            with torch.autocast(verts.device.type, enabled=False):
                return assemble_gathered(verts, view, kernel, plan, want_mass=True)

        fn = torch.compile(assemble, fullgraph=True, **self.options)  # type: ignore[call-overload]
        self._compiled = (view, fn)
        return fn
