"""The reliability table: generated inputs of each class that once gave silent wrong answers.

For each category, random cases are generated and each outcome is classified against an
independent reference: **error** (a clear exception), **warned** (a result with a warning),
**valid** (a result that matches the reference), or **silent wrong** (a result that does not,
with no error or warning: the goal is 0).

Categories and references:

* ``eigs, repeated eigenvalues``: disjoint copies of a small mesh (every eigenvalue repeated);
  the ``k`` smallest eigenvalues against dense ``scipy.linalg.eigh``.
* ``eigs, non-symmetric matrix``: ``L`` with random row scaling (not symmetric): must refuse.
* ``solve, singular or indefinite``: CG on ``L`` (singular) or ``L - s M`` (indefinite); a
  result counts as valid only if its residual is below ``1e-6``.
* ``float32, extreme scales``: the mesh scaled by ``10^e``, ``|e| <= 30``; ``L`` against float64
  (scale invariant) to ``1e-4``, masses against float64 ``* s^2``.
* ``float32, thin faces``: darts of thinness ``1e-6`` to ``1e-2`` (the documented range; thinner
  faces lose gradient accuracy in float32's own backward), the gradient of a fixed linear
  function of ``L``'s entries against float64 to ``1e-2``.
* ``measures, non-finite coordinates``: a NaN or inf vertex; must refuse.
* ``PLY, non-integral indices``: a face list with a fractional index; must refuse.
* ``free-boundary map, not a disk``: a grid with holes; must refuse.

Then the sweep (below): every public entry point on empty and degenerate meshes
(``ENTRY_POINTS`` x ``INPUTS``), ill-conditioned but valid systems (``ILL_CONDITIONED``), and
every CLI command sent SIGINT at each phase (``CLI_COMMANDS`` x ``CLI_PHASES``; some minutes,
``--no-cli`` skips it), each run classified as a result, a clear error or a raw error.

``python benchmarks/reliability.py [--cases 40] [--seed 0] [--no-cli]`` writes
``benchmarks/results/reliability.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import select
import signal
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import torch
from common import bench_grid, markdown_table, run_meta, script_parser, table_data, write_results

import torch_polylap as tp
from torch_polylap.triangulate import triangulate_faces

Outcome = str  # "error", "warned", "valid", "silent wrong"


def _classify(run: Callable[[], bool]) -> Outcome:
    """``run`` returns whether its result matches the reference; exceptions are errors."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            right = run()
        except (ValueError, RuntimeError, TypeError, ArithmeticError):
            return "error"
    if any(issubclass(w.category, UserWarning) for w in caught) and right:
        return "warned"
    return "valid" if right else "silent wrong"


def eigs_repeated(rng: np.random.Generator) -> bool:
    verts, faces = bench_grid(
        int(rng.integers(3, 6)), int(rng.integers(3, 6)), noise=0.05, seed=int(rng.integers(99))
    )
    copies = int(rng.integers(5, 30))
    V = verts.shape[0]
    all_verts = torch.cat([verts + 10.0 * c for c in range(copies)])
    all_faces = torch.cat([faces + V * c for c in range(copies)])
    L, M0 = tp.laplacian(all_verts, all_faces)
    k = int(rng.integers(copies + 1, min(4 * copies, all_verts.shape[0] // 2)))
    evals, _ = tp.eigs(L, M0, k)
    dense = scipy.linalg.eigh(
        L.to_dense().numpy(), np.diag(M0.diagonal().numpy()), eigvals_only=True
    )
    return bool(np.abs(evals.numpy() - dense[:k]).max() <= 1e-6 * max(1.0, dense[k - 1]))


def eigs_non_symmetric(rng: np.random.Generator) -> bool:
    verts, faces = bench_grid(6, 6, noise=0.05, seed=int(rng.integers(99)))
    L, M0 = tp.laplacian(verts, faces)
    w = torch.from_numpy(rng.uniform(0.5, 2.0, verts.shape[0]))
    tp.eigs(L * w[:, None], M0, 4)
    return False  # an answer for a non-symmetric matrix is not the symmetric problem's


def solve_singular(rng: np.random.Generator) -> bool:
    verts, faces = bench_grid(8, 8, noise=0.05, seed=int(rng.integers(99)))
    L, M0 = tp.laplacian(verts, faces)
    A = L if rng.random() < 0.5 else L - float(rng.uniform(5, 50)) * M0
    b = torch.from_numpy(rng.standard_normal(verts.shape[0]))
    x = tp.solve(A, b, backend="cg")
    return bool(((A @ x - b).norm() / b.norm()) <= 1e-6)


def float32_scales(rng: np.random.Generator) -> bool:
    verts, faces = bench_grid(5, 5, noise=0.05, seed=int(rng.integers(99)))
    s = 10.0 ** float(rng.uniform(-30, 30))
    L64, M64 = tp.laplacian(verts, faces)
    L32, M32 = tp.laplacian((verts * s).float(), faces)
    l_err = (L32.to_dense().double() - L64.to_dense()).abs().max() / L64.to_dense().abs().max()
    m_err = (M32.diagonal().double() / (s * s) / M64.diagonal() - 1).abs().max()
    return bool(torch.isfinite(L32.values()).all() and l_err <= 1e-4 and m_err <= 1e-4)


def float32_thin(rng: np.random.Generator) -> bool:
    t = 10.0 ** float(rng.uniform(-6, -2))
    P = torch.tensor([[0, 0, 0], [2, t, 0], [0, 2 * t, 0], [1, 0.4 * t, 0]], dtype=torch.float64)
    P = P + float(rng.uniform(-1, 1)) * torch.tensor([0.0, 0.0, t])
    method = str(rng.choice(["aw11", "plms", "degoes"]))
    weights = torch.from_numpy(rng.standard_normal(16))

    def grad(X: torch.Tensor) -> torch.Tensor:
        # the vector-Jacobian product of L's values with fixed weights: the kernels' gradient
        # alone, without the cancellation a float32 loss such as |L X|^2 adds on thin faces
        X = X.clone().requires_grad_(True)
        L, _ = tp.laplacian(X, [[0, 1, 2, 3]], method=method)
        (g,) = torch.autograd.grad((L.to_dense().reshape(-1) * weights.to(X.dtype)).sum(), X)
        return g

    g64, g32 = grad(P.float().double()), grad(P.float()).double()
    return bool((g32 - g64).norm() <= 1e-2 * g64.norm())


def measures_non_finite(rng: np.random.Generator) -> bool:
    verts, faces = bench_grid(4, 4, noise=0.05, seed=int(rng.integers(99)))
    verts[int(rng.integers(verts.shape[0])), int(rng.integers(3))] = float(
        rng.choice([math.nan, math.inf, -math.inf])
    )
    measure = rng.choice(["mass", "face_areas", "planarity_energy", "vector_area"])
    out = getattr(tp, str(measure))(verts, faces)
    return bool(torch.isfinite(out).all())  # finite out of non-finite in would be a guess


def ply_fractional(rng: np.random.Generator) -> bool:
    corners = rng.uniform(0, 3, 3)
    corners[rng.integers(3)] += 0.5  # at least one index is not whole
    body = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n".replace("v ", "")
    text = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar float vertex_indices\nend_header\n"
        + body
        + "3 "
        + " ".join(f"{c:.2f}" for c in corners)
        + "\n"
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "frac.ply"
        path.write_text(text)
        tp.read_mesh(path)
    return False  # reading a fractional index as some integer is a guess


def free_boundary_not_a_disk(rng: np.random.Generator) -> bool:
    n = int(rng.integers(6, 10))
    verts, faces = bench_grid(n, n)
    holes = rng.choice(len(faces), size=int(rng.integers(1, 4)), replace=False)
    keep = [f for i, f in enumerate(torch.as_tensor(faces).tolist()) if i not in set(holes)]
    tp.apps.conformal_parameterization(verts.double(), keep, free_boundary=True)
    # a map is only right if the holes merged into the outer boundary (then it is a disk)
    topo = tp.build_topology(keep, verts.shape[0])
    return len(topo.boundary_loops()) == 1


CATEGORIES: dict[str, Callable[[np.random.Generator], bool]] = {
    "eigs, repeated eigenvalues": eigs_repeated,
    "eigs, non-symmetric matrix": eigs_non_symmetric,
    "solve (CG), singular or indefinite": solve_singular,
    "float32, scales 1e-30 to 1e30": float32_scales,
    "float32, thin faces (gradients)": float32_thin,
    "measures, non-finite coordinates": measures_non_finite,
    "PLY, non-integral indices": ply_fractional,
    "free-boundary map, not a disk": free_boundary_not_a_disk,
}


# --------------------------------------------------------------------------------------------
# The sweep: every public entry point on each class of degenerate input
# --------------------------------------------------------------------------------------------
#
# Each entry point runs one typical call on a mesh of each input class; the outcome is
# "valid" (a result without NaN: an infinite distance to a vertex no path reaches is an
# answer), "warned" (a result and a warning of this package), "clear error" (a ValueError,
# TypeError or ImportError, or an exception class of this package, raised by this package's
# own code: its message names the problem), "raw error" (anything raised inside torch, numpy
# or scipy, or an IndexError, ZeroDivisionError, ...; "raw error, assembly" where it comes
# from the assembly of tp.laplacian on a mesh without vertices) or "NaN result" (NaN out of a
# finite input, without an error). The goal: no raw error and no NaN result.

PACKAGE = Path(tp.__file__).resolve().parent

Mesh = tuple[torch.Tensor, torch.Tensor]


def _no_faces() -> torch.Tensor:
    return torch.zeros((0, 3), dtype=torch.long)


def _regular() -> Mesh:
    """A bumpy 3 x 3 quad grid: every entry point gives a valid result on it (the recipes'
    own check)."""
    verts, faces = bench_grid(3, 3, noise=0.05, seed=1)
    return verts, torch.as_tensor(faces)


def _isolated() -> Mesh:
    """A quad and a triangle with two vertices that no face references."""
    verts = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0.1], [0, 1, 0], [2, 0.5, 0.3], [5, 5, 5], [6, 5, 5]],
        dtype=torch.float64,
    )
    return verts, [[0, 1, 2, 3], [1, 4, 2]]  # type: ignore[return-value]


INPUTS: dict[str, Callable[[], Mesh]] = {
    "regular mesh": _regular,
    "0 vertices, 0 faces": lambda: (torch.zeros((0, 3), dtype=torch.float64), _no_faces()),
    "vertices, 0 faces": lambda: (
        torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1.0]], dtype=torch.float64),
        _no_faces(),
    ),
    "isolated vertices beside faces": _isolated,
}
EMPTY_INPUTS = [name for name in INPUTS if name != "regular mesh"]


def _operators(verts: torch.Tensor, faces: object) -> tuple[torch.Tensor, torch.Tensor]:
    """``L, M0`` of the mesh; of a mesh without vertices the 0 x 0 matrices, so that an entry
    point taking operators is swept on its own (``laplacian`` is swept itself)."""
    if verts.shape[0] == 0:
        empty = tp.sparse.from_scipy(sp.csr_matrix((0, 0)), symmetric=True)
        return empty, empty
    return tp.laplacian(verts, faces)


def _signal(verts: torch.Tensor, channels: int | None = None) -> torch.Tensor:
    n = verts.shape[0]
    shape = (n,) if channels is None else (n, channels)
    return torch.linspace(0.0, 1.0, n * (channels or 1), dtype=verts.dtype).reshape(shape)


def _written(write: Callable[[Path], object]) -> Callable[[torch.Tensor, object], object]:
    def run(verts: torch.Tensor, faces: object) -> object:
        with tempfile.TemporaryDirectory() as tmp:
            return write(Path(tmp))

    return run


def _write_and_read(ext: str, binary: bool = False) -> Callable[[torch.Tensor, object], object]:
    def run(verts: torch.Tensor, faces: object) -> object:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"mesh.{ext}"
            tp.write_mesh(path, verts, faces, binary=binary)
            return tp.read_mesh(path)

    return run


def _spectrum(verts: torch.Tensor, faces: object) -> tp.nn.Spectrum:
    return tp.nn.Spectrum.from_polygon_meshes(tp.PolygonMeshes([verts], [faces]), 2)


def _diffusion_net(verts: torch.Tensor, faces: object) -> torch.Tensor:
    L, M0 = _operators(verts, faces)
    model = tp.nn.DiffusionNetLike(
        3, 2, width=4, num_blocks=1, mode="implicit", hks_features=0, task="segmentation"
    )
    return model(verts.float(), L=L.float(), M0=M0.float())


def _chebyshev(verts: torch.Tensor, faces: object) -> torch.Tensor:
    L, M0 = _operators(verts, faces)
    return tp.nn.ChebyshevFilter(2, 3).double()(_signal(verts, 2), L, M0)


def _vector_diffusion(verts: torch.Tensor, faces: object) -> torch.Tensor:
    A, M, _ = tp.vector.connection_laplacian(verts, faces)
    x = _signal(verts, 4).reshape(-1, 2, 2)
    return tp.nn.LearnedVectorDiffusion(2).double()(x, A, M)


def _pins(verts: torch.Tensor) -> list[int]:
    return [0, 2] if verts.shape[0] > 2 else []


# name -> a typical call on (verts, faces); everything a user reaches from the top level, the
# applications, the layers, the losses and the writers that takes a mesh or its operators
ENTRY_POINTS: dict[str, Callable[[torch.Tensor, object], object]] = {
    # operators and measures
    "laplacian": lambda V, F: tp.laplacian(V, F),
    "laplacian (plms)": lambda V, F: tp.laplacian(V, F, method="plms"),
    "laplacian (degoes)": lambda V, F: tp.laplacian(V, F, method="degoes"),
    "PolygonLaplacian": lambda V, F: tp.PolygonLaplacian()(V, F),
    "CompiledLaplacian": lambda V, F: tp.CompiledLaplacian(F)(V),
    "planarity_laplacian": lambda V, F: tp.planarity_laplacian(V, F),
    "mass": lambda V, F: tp.mass(V, F),
    "face_areas": lambda V, F: tp.face_areas(V, F),
    "face_normals": lambda V, F: tp.face_normals(V, F),
    "vector_area": lambda V, F: tp.vector_area(V, F),
    "edge_lengths": lambda V, F: tp.edge_lengths(V, F),
    "mean_edge_length": lambda V, F: tp.mean_edge_length(V, F),
    "face_nonplanarity": lambda V, F: tp.face_nonplanarity(V, F),
    "face_planarity_energy": lambda V, F: tp.face_planarity_energy(V, F),
    "planarity_energy": lambda V, F: tp.planarity_energy(V, F),
    "build_topology": lambda V, F: tp.build_topology(F, V.shape[0]),
    "get_topology": lambda V, F: tp.get_topology(F, V.shape[0]),
    "as_faces": lambda V, F: tp.as_faces(F),
    "PolygonMeshes.laplacian": lambda V, F: tp.PolygonMeshes([V], [F]).laplacian(),
    # calculus
    "corner_gradients": lambda V, F: tp.corner_gradients(V, F),
    "face_gradient": lambda V, F: tp.face_gradient(V, F, _signal(V)),
    "gradient_operator": lambda V, F: tp.gradient_operator(V, F),
    "divergence": lambda V, F: tp.divergence(
        V, F, torch.ones(len(tp.as_faces(F)), 3, dtype=V.dtype)
    ),
    "mean_curvature_normal": lambda V, F: tp.mean_curvature_normal(V, F),
    "strong_laplacian": lambda V, F: tp.strong_laplacian(*_operators(V, F), _signal(V)),
    "implicit_heat_diffusion": lambda V, F: tp.implicit_heat_diffusion(
        *_operators(V, F), _signal(V, 2), 0.1
    ),
    "heat_geodesic_distance": lambda V, F: tp.heat_geodesic_distance(V, F, [0]),
    "HeatGeodesicSolver": lambda V, F: tp.HeatGeodesicSolver(V, F).distance([0]),
    # solves and spectra
    "solve": lambda V, F: tp.solve((lambda L, M0: M0 + 0.1 * L)(*_operators(V, F)), _signal(V)),
    "dirichlet_solve": lambda V, F: tp.dirichlet_solve(
        _operators(V, F)[0],
        torch.zeros(V.shape[0], dtype=V.dtype),
        torch.tensor([0]),
        torch.ones(1, dtype=V.dtype),
    ),
    "eigs": lambda V, F: tp.eigs(*_operators(V, F), 2),
    "cached_eigs": lambda V, F: _written(lambda d: tp.cached_eigs(V, F, 2, d))(V, F),
    "spectral_heat_diffusion": lambda V, F: tp.spectral_heat_diffusion(
        _signal(V), *tp.eigs(*_operators(V, F), 2), _operators(V, F)[1], 0.1
    ),
    "heat_kernel_signature": lambda V, F: tp.heat_kernel_signature(
        *tp.eigs(*_operators(V, F), 2), torch.tensor([0.1], dtype=V.dtype)
    ),
    # I/O and interop
    "write_mesh / read_mesh (obj)": _write_and_read("obj"),
    "write_mesh / read_mesh (off)": _write_and_read("off"),
    "write_mesh / read_mesh (ply)": _write_and_read("ply"),
    "write_mesh / read_mesh (binary ply)": _write_and_read("ply", binary=True),
    "triangulate.triangulate_faces": lambda V, F: triangulate_faces(V, F),
    "to_trimesh": lambda V, F: tp.to_trimesh(V, F),
    "to_pyg": lambda V, F: tp.to_pyg(V, F),
    "to_pytorch3d": lambda V, F: tp.to_pytorch3d(V, F),
    # tangent vector fields
    "vector.connection_laplacian": lambda V, F: tp.vector.connection_laplacian(V, F),
    "vector.fitted_frames": lambda V, F: tp.vector.fitted_frames(V, F),
    "vector.shape_operator": lambda V, F: tp.vector.shape_operator(V, F),
    "vector.face_shape_operator": lambda V, F: tp.vector.face_shape_operator(V, F),
    "vector.principal_curvatures": lambda V, F: tp.vector.principal_curvatures(V, F),
    "vector.smoothest_field": lambda V, F: tp.vector.smoothest_field(V, F),
    "vector.virtual_refinement": lambda V, F: tp.vector.virtual_refinement(V, F),
    "vector.HodgeDecomposition": lambda V, F: tp.vector.HodgeDecomposition(V, F).from_vertices(
        torch.ones(V.shape[0], 3, dtype=V.dtype)
    ),
    "vector.VectorHeatSolver": lambda V, F: tp.vector.VectorHeatSolver(V, F).transport(
        [0], torch.tensor([[1.0, 0.0, 0.0]], dtype=V.dtype)
    ),
    # applications
    "apps.mean_curvature_flow": lambda V, F: tp.apps.mean_curvature_flow(V, F, 1e-3, 1),
    "apps.scale_free_mean_curvature": lambda V, F: tp.apps.scale_free_mean_curvature(V, F),
    "apps.enclosed_volume": lambda V, F: tp.apps.enclosed_volume(V, F),
    "apps.plate_bending": lambda V, F: tp.apps.plate_bending(V, F),
    "apps.conformal_parameterization": lambda V, F: tp.apps.conformal_parameterization(V, F),
    "apps.conformal_energy": lambda V, F: tp.apps.conformal_energy(V[:, :2], V, F),
    "apps.conformal_matrix": lambda V, F: tp.apps.conformal_matrix(V, F),
    "apps.angle_distortion": lambda V, F: tp.apps.angle_distortion(V[:, :2], V, F).per_corner,
    "apps.planarize": lambda V, F: (
        tp.apps.planarize(V, F, max_iter=2, options=tp.apps.PlanarizeOptions(warn=False)).verts
    ),
    # layers
    "nn.Spectrum.from_polygon_meshes": _spectrum,
    "nn.SpectralFeatures": lambda V, F: tp.nn.SpectralFeatures(num_features=4)(_spectrum(V, F)),
    "nn.LearnedDiffusion (implicit)": lambda V, F: tp.nn.LearnedDiffusion(2, "implicit").double()(
        _signal(V, 2), None, *_operators(V, F)
    ),
    "nn.ChebyshevFilter": _chebyshev,
    "nn.vertex_tangent_frames": lambda V, F: tp.nn.vertex_tangent_frames(V, F).normal,
    "nn.vertex_gradient_operators": lambda V, F: tp.nn.vertex_gradient_operators(V, F),
    "nn.DiffusionNetLike (implicit)": _diffusion_net,
    "nn.LearnedVectorDiffusion": _vector_diffusion,
    # losses
    "losses.laplacian_smoothing": lambda V, F: tp.losses.laplacian_smoothing((V, F)),
    "losses.laplacian_smoothing (cot)": lambda V, F: tp.losses.laplacian_smoothing((V, F), "cot"),
    "losses.mean_curvature_smoothing": lambda V, F: tp.losses.mean_curvature_smoothing((V, F)),
    "losses.dirichlet_energy": lambda V, F: tp.losses.dirichlet_energy((V, F), _signal(V)),
    "losses.planarity_loss": lambda V, F: tp.losses.planarity_loss((V, F)),
    "losses.bending_energy": lambda V, F: tp.losses.bending_energy((V, F)),
    "losses.normal_consistency": lambda V, F: tp.losses.normal_consistency((V, F)),
}


def _spot() -> Mesh:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tp.io.SkippedContentWarning)
        verts, faces = tp.read_mesh(PACKAGE / "data" / "spot_control_mesh.obj")
    return verts, faces  # type: ignore[return-value]


def _shifted_solve(shift: float) -> Callable[[], object]:
    def run() -> object:
        verts, faces = _spot()
        L, M0 = tp.laplacian(verts, faces)
        return tp.solve(L + shift * M0, M0 @ _signal(verts))

    return run


def _shifted_eigs(sigma: float) -> Callable[[], object]:
    def run() -> object:
        return tp.eigs(*tp.laplacian(*_spot()), 4, sigma=sigma)

    return run


def _geodesics(**options: float) -> Callable[[], object]:
    def run() -> object:
        verts, faces = _spot()
        if "t" in options:
            options["t"] *= float(tp.mean_edge_length(verts, faces)) ** 2
        return tp.heat_geodesic_distance(verts, faces, [0], **options)

    return run


# valid but ill-conditioned systems (on spot, 188 vertices): a result, or a clear error where
# the system is numerically singular (no digit of a solution would be right)
ILL_CONDITIONED: dict[str, Callable[[], object]] = {
    "solve, L + 1e-10 M0": _shifted_solve(1e-10),
    "solve, L + 1e-12 M0": _shifted_solve(1e-12),
    "solve, L + 1e-14 M0": _shifted_solve(1e-14),
    "eigs, sigma = -1e-12": _shifted_eigs(-1e-12),
    "eigs, sigma = +1e-12": _shifted_eigs(1e-12),
    "heat_geodesic_distance, t = 1e-12 h^2": _geodesics(t=1e-12),
    "heat_geodesic_distance, poisson_lam = 1e-12": _geodesics(poisson_lam=1e-12),
}


def _through_assembly(err: BaseException) -> bool:
    """Whether ``err`` came through the assembly of ``tp.laplacian`` (``assembly.py``)."""
    tb = err.__traceback__
    while tb is not None:
        if Path(tb.tb_frame.f_code.co_filename).resolve() == PACKAGE / "assembly.py":
            return True
        tb = tb.tb_next
    return False


def _raised_here(err: BaseException) -> bool:
    """Whether the innermost frame of ``err``'s traceback is code of this package."""
    tb = err.__traceback__
    if tb is None:
        return False
    while tb.tb_next is not None:
        tb = tb.tb_next
    return Path(tb.tb_frame.f_code.co_filename).resolve().is_relative_to(PACKAGE)


def _no_nan(result: object) -> bool:
    """Whether no floating-point tensor or array in ``result`` holds a NaN."""
    if isinstance(result, torch.Tensor):
        if result.layout != torch.strided:
            return _no_nan(tp.sparse.sparse_values(result))
        return not result.is_floating_point() or not bool(torch.isnan(result).any())
    if isinstance(result, np.ndarray):
        return result.dtype.kind != "f" or not bool(np.isnan(result).any())
    if isinstance(result, tuple | list):
        return all(_no_nan(r) for r in result)
    if dataclasses.is_dataclass(result) and not isinstance(result, type):
        return all(_no_nan(getattr(result, f.name)) for f in dataclasses.fields(result))
    if isinstance(result, tp.nn.Spectrum):
        return _no_nan([result.evals, result.evecs, result.mass])
    return True


def sweep_outcome(call: Callable[[], object]) -> tuple[str, str]:
    """``(outcome, detail)`` of ``call()``: ``"valid"``, ``"warned"``, ``"clear error"``,
    ``"raw error"``, ``"raw error, assembly"`` or ``"NaN result"`` (see above); the detail is
    the exception's type and first line, or the warnings' categories."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            result = call()
        except Exception as err:
            # ImportError: an optional dependency, named with the command that installs it
            named = isinstance(err, ValueError | TypeError | ImportError)
            ours = type(err).__module__.startswith("torch_polylap")
            clear = (ours or named) and _raised_here(err)
            first = (str(err).splitlines() or [""])[0]
            detail = f"{type(err).__name__}: {first}"
            if clear:
                return "clear error", detail
            return ("raw error, assembly" if _through_assembly(err) else "raw error"), detail
    if not _no_nan(result):
        return "NaN result", type(result).__name__
    warned = [
        w.category.__name__
        for w in caught
        if w.category.__module__.startswith("torch_polylap") and w.category is not UserWarning
    ]
    return ("warned", ", ".join(sorted(set(warned)))) if warned else ("valid", "")


def sweep_entry(name: str, input_class: str) -> tuple[str, str]:
    """The outcome of entry point ``name`` on a mesh of ``input_class`` (see ``INPUTS``)."""
    verts, faces = INPUTS[input_class]()
    return sweep_outcome(lambda: ENTRY_POINTS[name](verts, faces))


# --------------------------------------------------------------------------------------------
# CLI commands interrupted by Ctrl-C at each phase
# --------------------------------------------------------------------------------------------

REPO = PACKAGE.parent
CLI_COMMANDS: dict[str, list[str]] = {
    "info": ["--eigs", "2", "--json"],
    "smooth": ["--steps", "1", "--no-progress"],
    "param": [],
    "planarize": ["--max-iter", "1", "--no-progress"],
    "spectrum": ["-k", "2", "--npz"],
    "bench": [
        str(REPO / "tests" / "data" / "dodecahedron_poly.obj"),
        *("--repeat", "1", "-k", "2", "--json", "--no-progress"),
    ],
    "demo": ["--no-plot", "--no-progress"],
}

# The child: the console script's launcher with a hook that blocks at one phase and says so
# on stdout (the command's own output goes to /dev/null); the parent then sends SIGINT.
CLI_CHILD = """
import atexit, os, sys, time

phase, argv = sys.argv[1], sys.argv[2:]
marker = sys.__stdout__


def block(where):
    marker.write("blocked in " + where + "\\n")
    marker.flush()
    time.sleep(600)


class BlockTorch:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            sys.meta_path.remove(self)  # once: Python's shutdown may import again
            block("start-up")


if phase == "start-up":
    sys.meta_path.insert(0, BlockTorch())
else:
    import torch_polylap.atomic as atomic
    import torch_polylap.cli.common as common

    if phase == "compute":  # the mesh just read
        read = common.read_mesh
        common.read_mesh = lambda *a, **k: (read(*a, **k), block("compute"))[0]
    elif phase == "writing":  # a temporary complete, not yet moved into place
        atomic.os.fsync = lambda fd: block("writing")
    elif phase == "after writing":  # the command done, the process ending
        atexit.register(block, "after writing")
sys.stdout = open(os.devnull, "w")
sys.argv = ["polylap", *argv]
from _polylap_launcher import main

sys.exit(main())  # as pip's console-script wrapper calls it
"""
CLI_PHASES = ("start-up", "compute", "writing", "after writing")


def cli_interrupt(command: str, phase: str, timeout: float = 300.0) -> tuple[str, str]:
    """``(outcome, detail)`` of ``polylap COMMAND`` sent SIGINT at ``phase``: ``"clear"``
    (status 130 and the one line ``polylap: interrupted``), ``"raw"`` (anything else, or no
    exit within ``timeout`` seconds of the signal) or ``"not reached"`` (the command ended
    without reaching the phase)."""
    with tempfile.TemporaryDirectory() as out:
        argv = [sys.executable, "-c", CLI_CHILD, phase, command, *CLI_COMMANDS[command]]
        argv += ["-o", out]
        env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
        proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=out
        )
        try:
            ready, _, _ = select.select([proc.stdout], [], [], timeout)
            line = proc.stdout.readline() if ready else ""  # type: ignore[union-attr]
            if not line.startswith("blocked in"):
                proc.kill()
                _, err = proc.communicate()
                return "not reached", f"status {proc.returncode}: {err.strip()[-200:]}"
            proc.send_signal(signal.SIGINT)
            try:
                _, err = proc.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
                return "raw", f"still running {timeout:g} s after the signal: {err[-200:]}"
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    lines = err.strip().splitlines()
    clear = (
        proc.returncode == 130
        and lines[-1:] == ["polylap: interrupted"]
        and err.count("polylap:") == 1
        and "Traceback" not in err
    )
    return ("clear" if clear else "raw"), f"status {proc.returncode}: {' | '.join(lines[-2:])}"


def _sweep_tables() -> tuple[dict, dict]:
    """The entry points on each input class, and the ill-conditioned systems: ``(results,
    tables)``."""
    entries = {name: {c: list(sweep_entry(name, c)) for c in INPUTS} for name in ENTRY_POINTS}
    ill = {name: list(sweep_outcome(call)) for name, call in ILL_CONDITIONED.items()}
    header = ["entry point", *INPUTS]
    body = [[name, *(r[c][0] for c in INPUTS)] for name, r in entries.items()]
    outcomes = ["valid", "warned", "clear error", "raw error", "raw error, assembly", "NaN result"]
    counts = [[c, *(sum(r[c][0] == o for r in entries.values()) for o in outcomes)] for c in INPUTS]
    tables = {
        "sweep": table_data(header, body),
        "sweep_counts": table_data(["input class", *outcomes], counts),
        "ill_conditioned": table_data(
            ["system", "outcome", "detail"], [[n, *r] for n, r in ill.items()]
        ),
    }
    print(markdown_table(header, body))
    print(markdown_table(["input class", *outcomes], counts))
    print(markdown_table(["system", "outcome", "detail"], [[n, *r] for n, r in ill.items()]))
    return {"entry_points": entries, "ill_conditioned": ill}, tables


def _cli_table() -> tuple[dict, dict]:
    """Every command interrupted at each phase: ``(results, tables)``."""
    runs = {
        command: {phase: list(cli_interrupt(command, phase)) for phase in CLI_PHASES}
        for command in CLI_COMMANDS
    }
    header = ["command", *CLI_PHASES]
    body = [[command, *(r[p][0] for p in CLI_PHASES)] for command, r in runs.items()]
    print(markdown_table(header, body))
    return {"cli": runs}, {"cli": table_data(header, body)}


def main() -> None:
    parser = script_parser(__doc__, "reliability")
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--no-cli", action="store_true", help="skip the interrupted CLI commands (minutes)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    meta = run_meta()
    rows = {}
    for name, case in CATEGORIES.items():
        rng = np.random.default_rng(args.seed)
        counts = {"error": 0, "warned": 0, "valid": 0, "silent wrong": 0}
        for _ in range(args.cases):
            counts[_classify(functools.partial(case, rng))] += 1
        rows[name] = counts
    header = ["category", "cases", "error", "warned", "valid", "silent wrong"]
    body = [[name, sum(c.values()), *c.values()] for name, c in rows.items()]
    print(markdown_table(header, body))
    sections: dict = {"seed": args.seed, "cases": args.cases, "rows": rows}
    sections["tables"] = {"reliability": table_data(header, body)}
    sweep, tables = _sweep_tables()
    sections["sweep"] = sweep
    sections["tables"].update(tables)
    if not args.no_cli:
        cli, tables = _cli_table()
        sections["sweep"].update(cli)
        sections["tables"].update(tables)
    write_results("reliability", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
