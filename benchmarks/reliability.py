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

``python benchmarks/reliability.py [--cases 40] [--seed 0]`` writes
``benchmarks/results/reliability.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import argparse
import functools
import math
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import scipy.linalg
import torch
from common import bench_grid, markdown_table, run_meta, table_data, write_results

import torch_polylap as tp

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="default benchmarks/results/reliability.json")
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
    sections = {"seed": args.seed, "cases": args.cases, "rows": rows}
    sections["tables"] = {"reliability": table_data(header, body)}
    write_results("reliability", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
