"""Quickstart: build L and M0 on a polygon mesh and look at what they say about its geometry.

    python examples/quickstart.py [mesh.obj|.off|.ply] [--out examples/output]

Without an argument it uses the embedded Spot control cage (quads, triangles and pentagons).
Writes ``quickstart.png`` to ``--out``: the mesh with its faces colored by mean curvature.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import torch_polylap as tp
from torch_polylap.data import DEFAULT_MESH


def main(path: Path, out: Path) -> None:
    verts, faces = tp.read_mesh(path)  # (V, 3) float64 and PolygonFaces, polygons kept
    print(f"{path.name}: {verts.shape[0]} vertices, {faces!r}")

    L, M0 = tp.laplacian(verts, faces, lam=1.0)  # sparse (V, V), L PSD, M0 diagonal
    nnz = tp.sparse.sparse_values(L).numel()  # the differentiable value array, O(nnz)
    print(f"L: {tuple(L.shape)}, {nnz} nonzeros; total mass {M0.diagonal().sum():.4f}")

    # Without the stabilizer (lam = 0) L X is the area gradient (Lemma 3 of the paper), and the
    # area is homogeneous of degree 2, so 1/2 tr(X^T L X) is exactly the total area.
    L0, _ = tp.laplacian(verts, faces, lam=0.0)
    dirichlet = 0.5 * (verts * (L0 @ verts)).sum()
    area = tp.face_areas(verts, faces).sum()
    print(f"1/2 tr(X^T L0 X) = {dirichlet:.6f}  vs  total area = {area:.6f}")

    # Mean curvature vector H = M0^-1 L X; |H| / 2 is the mean curvature
    H = tp.mean_curvature_normal(verts, faces)
    curvature = H.norm(dim=1) / 2
    print(f"mean curvature: median {curvature.median():.3f}, max {curvature.max():.3f}")

    # How far from planar are the faces? (corner height over the maximal projection / diameter)
    nonplanar = tp.face_nonplanarity(verts, faces)
    energy = tp.planarity_energy(verts, faces)
    print(f"non-planarity: max {nonplanar.max():.3e}, planarity energy {energy:.3e}")

    # Gradients reach the vertex positions through plain torch algebra in O(nnz) memory:
    # L @ X, M0 + t * L, solves, ... (never a dense V x V matrix)
    X = verts.clone().requires_grad_(True)
    L, M0 = tp.laplacian(X, faces)
    smoothed = tp.solve(M0 + 0.01 * L, M0 @ X)  # one implicit smoothing step
    ((L @ X) ** 2).sum().add((smoothed - X).square().sum()).backward()
    print(f"|grad| of |L X|^2 + |smoothing step|^2 w.r.t. the vertices: {X.grad.norm():.4f}")

    # scipy interop
    S = tp.sparse.to_scipy(L)
    print(f"scipy: {type(S).__name__} {S.shape}, symmetric: {abs(S - S.T).max() == 0}")

    # A figure (matplotlib): faces colored by the mean curvature of their corners
    from torch_polylap.plot import PlotOptions, plot_mesh

    out.mkdir(parents=True, exist_ok=True)
    png = out / "quickstart.png"
    label = "mean curvature |H| / 2"
    style = PlotOptions(label=label, up="y")
    plot_mesh(verts, faces, curvature, path=png, title=path.name, options=style)
    print(f"wrote {png}")


if __name__ == "__main__":
    torch.set_printoptions(precision=4)
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", nargs="?", type=Path, default=DEFAULT_MESH)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = parser.parse_args()
    main(args.mesh, args.out)
