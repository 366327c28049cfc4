"""Benchmark the face gradient operator against libigl and adobe-lagrange, in one run.

    python benchmarks/bench_gradient.py [--grid 707] [--repeat 3] [--json PATH]

* **Triangles, against ``igl.grad``**: an ``n x n`` non-planar quad grid (``--grid``, default
  707: about 1M triangles) split into triangles; libigl's linear finite-element gradient
  ``(3F, V)`` (component-major rows) against ``tp.gradient_operator`` on the same triangles
  (face-major rows; the same matrix up to that row order, checked here), and
  ``tp.gradient_operator`` on the quads themselves.
* **Polygons, against adobe-lagrange** (``polyddg.DifferentialOperators(mesh).gradient()``, de
  Goes et al. 2020 eq. 8, which on any polygon is the gradient of this package: the vector area
  crossed with the opposite-edge vectors, over twice the squared area), on every real mesh of
  ``../shared/data/meshes/real`` (or ``$POLYLAP_SHARED_MESHES/real``); values compared.

Ours is timed twice: "first" builds the topology from a fresh faces tensor (what a one-off call
costs), "cached" reuses it (what every step of a loop over changing positions costs). Peers
build from scratch every time (they have no cache). Median of ``--repeat`` samples after a
warm-up, one thread. Prints Markdown tables with the ratios peer / ours; writes
``benchmarks/results/gradient.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import common
import numpy as np
import scipy.sparse as sp
import torch

import torch_polylap as tp

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("POLYLAP_SHARED_MESHES", ROOT.parent / "shared" / "data" / "meshes"))


def ours(verts: torch.Tensor, faces: torch.Tensor | tp.PolygonFaces, repeat: int) -> dict:
    """Seconds of ``tp.gradient_operator`` with a fresh topology and with the cached one."""

    def fresh() -> object:
        copy = faces.clone() if isinstance(faces, torch.Tensor) else tp.as_faces(faces).to("cpu")
        if isinstance(copy, tp.PolygonFaces):
            copy = tp.PolygonFaces(copy.indices.clone(), offsets=copy.offsets.clone())
        return tp.gradient_operator(verts, copy)

    first = common.median_time(fresh, repeat)
    topo = tp.get_topology(faces, verts.shape[0])
    cached = common.median_time(lambda: tp.gradient_operator(verts, topo), repeat)
    return {"first": first, "cached": cached}


def timing_row(label: str, peer_s: float, mine: dict, diff: float) -> list[str]:
    """A table row: the peer's time, ours (:func:`ours`), the speedups and the operators'
    relative difference."""
    return [
        label,
        common.fmt_time(peer_s),
        common.fmt_time(mine["first"]),
        common.fmt_time(mine["cached"]),
        f"{peer_s / mine['first']:.2f}x",
        f"{peer_s / mine['cached']:.2f}x",
        f"{diff:.1e}",
    ]


def triangle_row(n: int, repeat: int) -> tuple[list[str], dict]:
    import igl

    verts, quads = common.bench_grid(n)
    q = quads.numpy()
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    tris_t = torch.from_numpy(tris)
    V, F = verts.numpy(), tris.astype(np.int64)
    igl_s = common.median_time(lambda: igl.grad(V, F), repeat)
    mine = ours(verts, tris_t, repeat)
    mine_quads = ours(verts, quads, repeat)
    # the same matrix up to row order: libigl's rows are (component, face), ours (face, component)
    G_igl = sp.csr_matrix(igl.grad(V, F))
    G = tp.sparse.to_scipy(tp.gradient_operator(verts, tris_t))
    nf = F.shape[0]
    order = (3 * np.arange(nf)[None, :] + np.arange(3)[:, None]).reshape(-1)
    diff = abs(G[order] - G_igl).max() / abs(G_igl).max()
    row = timing_row(f"{n} x {n} grid: {nf:,} triangles ({len(V):,} v)", igl_s, mine, diff)
    row.append(f"{common.fmt_time(mine_quads['first'])} / {common.fmt_time(mine_quads['cached'])}")
    data = {"faces": nf, "igl": igl_s, "ours": mine, "ours_quads": mine_quads, "rel_diff": diff}
    return row, data


def lagrange_row(path: Path, repeat: int) -> tuple[list[str], dict]:
    import lagrange
    from lagrange import polyddg

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        verts, faces = tp.read_mesh(path, dtype=torch.float64)
    sizes = faces.sizes.numpy().astype(np.uint32)
    indices = faces.indices.numpy().astype(np.uint32)
    V = verts.numpy()

    def peer() -> sp.spmatrix:
        mesh = lagrange.SurfaceMesh()
        mesh.add_vertices(V)
        mesh.add_hybrid(sizes, indices)
        return polyddg.DifferentialOperators(mesh).gradient()

    peer_s = common.median_time(peer, repeat)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # non-manifold or isolated vertices: one warning each
        mine = ours(verts, faces, repeat)
        G = tp.sparse.to_scipy(tp.gradient_operator(verts, faces))
    G_peer = sp.csr_matrix(peer())
    scale = abs(G_peer).max()
    diff = abs(G - G_peer).max() / scale if G.shape == G_peer.shape else float("nan")
    row = timing_row(f"{path.name} ({faces.num_faces:,} f)", peer_s, mine, diff)
    return row, {"faces": faces.num_faces, "lagrange": peer_s, "ours": mine, "rel_diff": diff}


def main() -> None:
    parser = common.script_parser(__doc__, "gradient", repeat=3)
    parser.add_argument("--grid", type=int, default=707)
    args = parser.parse_args()
    meta = common.run_meta(threads=1)
    report: dict = {"repeat": args.repeat, "real": {}, "tables": {}}
    print(f"torch {torch.__version__}, float64, 1 thread\n")
    with common.pinned_threads(1):
        row, report["grid"] = triangle_row(args.grid, args.repeat)
        header = ["mesh", "igl.grad", "ours first", "ours cached", "igl / first"]
        header += ["igl / cached", "max rel diff", "ours on the quads (first / cached)"]
        print(common.markdown_table(header, [row]), "\n")
        report["tables"]["triangles"] = common.table_data(header, [row])
        real = SHARED / "real"
        rows = []
        if real.is_dir():
            for path in sorted(real.iterdir()):
                if path.suffix in (".obj", ".off", ".ply"):
                    row, report["real"][path.name] = lagrange_row(path, args.repeat)
                    rows.append(row)
            header = ["mesh", "lagrange", "ours first", "ours cached", "lagrange / first"]
            header += ["lagrange / cached", "max rel diff"]
            print(common.markdown_table(header, rows))
            report["tables"]["polygons"] = common.table_data(header, rows)
        else:
            print(f"(no real meshes at {real}: set POLYLAP_SHARED_MESHES)")
    common.write_results("gradient", report, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
