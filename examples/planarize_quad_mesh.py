"""Planarize a quad-dominant mesh with the planarizing flow of AW11 sec. 5.3.

    python examples/planarize_quad_mesh.py [MESH] [--tol 1e-4] [--out examples/output]

Default mesh: the embedded Catmull-Clark cage of Spot (``torch_polylap/data/spot_control_mesh.obj``:
160 quads, 16 pentagons, 4 triangles, strongly non-planar), the kind of production base mesh of
AW11 Fig. 4. The flow is an unconstrained L-BFGS descent of ``E_plan`` (lambda = 2). Prints the
non-planarity (largest corner distance from the maximal projection's plane over the face
diameter) before and after, the vertex displacement and the change of size, and writes
``examples/output/planarize_quad_mesh.png`` (faces colored by log10 non-planarity, before and
after).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import torch_polylap as tp
from torch_polylap.apps import planarize
from torch_polylap.data import DEFAULT_MESH
from torch_polylap.plot import PlotOptions, new_figure, plot_mesh, save_figure


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mesh", nargs="?", type=Path, default=DEFAULT_MESH)
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--max-iter", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    V, F = tp.read_mesh(args.mesh)
    V = V.double()
    res = planarize(V, F, lam=2.0, tol=args.tol, max_iter=args.max_iter)

    def size(X: torch.Tensor) -> float:
        return float((X.amax(0) - X.amin(0)).norm())

    area0 = float(tp.face_areas(V, F).sum())
    area1 = float(tp.face_areas(res.verts, F).sum())
    rows = [
        ("mesh", f"{args.mesh.name}: {V.shape[0]} vertices, {F.num_faces} faces"),
        ("non-planarity max / mean, before", "{:.3e} / {:.3e}".format(*res.nonplanarity_before)),
        ("non-planarity max / mean, after", "{:.3e} / {:.3e}".format(*res.nonplanarity_after)),
        ("displacement max / mean (of bbox diagonal)", "{:.3e} / {:.3e}".format(*res.displacement)),
        ("bbox diagonal after / before", f"{size(res.verts) / size(V):.4f}"),
        ("total face area after / before", f"{area1 / area0:.4f}"),
        ("L-BFGS iterations / seconds", f"{res.iterations} / {res.seconds:.2f}"),
        ("converged (max < tol)", f"{res.converged} (tol {args.tol:g})"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")

    before = torch.log10(tp.face_nonplanarity(V, F).clamp_min(1e-8))
    after = torch.log10(tp.face_nonplanarity(res.verts, F).clamp_min(1e-8))
    clim = (float(torch.minimum(before.min(), after.min())), float(before.max()))
    fig, axes = new_figure(1, 2, three_d=True, panel_size=4.5)
    up = "y"  # the OBJ models here are y-up
    style = PlotOptions(cmap="viridis", clim=clim, label="log10 non-planarity", up=up)
    plot_mesh(V, F, before, ax=axes[0], title="input", options=style)
    plot_mesh(res.verts, F, after, ax=axes[1], title="planarized", options=style)
    png = args.out / "planarize_quad_mesh.png"
    save_figure(fig, png)
    print(f"\nwrote {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
