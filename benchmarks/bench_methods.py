"""Benchmark the four polygon Laplacians of ``tp.laplacian(method=...)`` against libigl.

For a non-planar ``n x n`` quad grid (``--grid n``, default 1000: 1M quads) and every real mesh in
``--real-dir``, on one thread:

- first assembly of ``(L, M0)`` (topology built from fresh faces; for ``diamond`` also its
  index plan) for ``aw11``, ``plms``, ``degoes`` and ``diamond``;
- cached re-assembly (the same faces, so the topology and pattern are reused);
- libigl's polygon ``cotmatrix(V, I, C)`` (PLMS, Bunge et al. 2020), which has no cache.

Ratios are libigl's time over ours for PLMS, and each method's re-assembly over AW11's. Our times
are medians of ``--repeat`` interleaved rounds after a warm-up round (each round runs every
method's first and cached assembly in turn, so that load from other jobs hits them alike; the
first assembly on a new faces tensor each time); libigl's the median of ``--repeat`` samples.
Meshes where the Diamond Laplacian is undefined (a folded diamond) get "-" for it. Prints a
Markdown table; writes ``benchmarks/results/methods.json`` (or ``--json PATH``).

    python benchmarks/bench_methods.py                  # 1M-quad grid + real meshes
    python benchmarks/bench_methods.py --grid 300 --repeat 3
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import common
import numpy as np
import torch

import torch_polylap as tp

METHODS = ("aw11", "plms", "degoes", "diamond")
TITLES = {"aw11": "AW11", "plms": "PLMS", "degoes": "dGBD20", "diamond": "Diamond"}
ROOT = Path(__file__).resolve().parents[1]


def _fresh(faces: tp.PolygonFaces) -> tp.PolygonFaces:
    """A new faces object (the topology cache is keyed on it): a first assembly."""
    return tp.PolygonFaces(faces.indices.clone(), offsets=faces.offsets.clone())


def bench_mesh(name: str, verts: torch.Tensor, faces, repeat: int) -> dict:
    packed = (
        faces
        if isinstance(faces, tp.PolygonFaces)
        else tp.PolygonFaces(faces.reshape(-1), sizes=torch.full((faces.shape[0],), faces.shape[1]))
    )
    row = {"mesh": name, "verts": int(verts.shape[0]), "faces": int(packed.sizes.numel())}
    topo = tp.get_topology(packed, verts.shape[0])
    methods = [m for m in METHODS if _defined(verts, topo, m)]
    contenders: dict[str, Callable[[], object]] = {}
    for method in methods:
        contenders[f"{method}_first"] = lambda m=method: tp.laplacian(
            verts, _fresh(packed), method=m
        )
        contenders[f"{method}_cached"] = lambda m=method: tp.laplacian(verts, topo, method=m)
    common.interleaved(contenders, 1)  # warm-up
    row.update(common.interleaved(contenders, repeat))
    for method in set(METHODS) - set(methods):
        row[f"{method}_first"] = row[f"{method}_cached"] = None
    try:
        import igl

        idx = packed.indices.numpy().astype(np.int64)
        off = packed.offsets.numpy().astype(np.int64)
        vn = verts.numpy()
        row["igl_plms"] = common.median_time(lambda: igl.cotmatrix(vn, idx, off), repeat)
    except ImportError:
        row["igl_plms"] = None
    return row


def _defined(verts: torch.Tensor, topo: tp.Topology, method: str) -> bool:
    """Whether ``method`` assembles on this mesh (the Diamond Laplacian refuses folds)."""
    try:
        tp.laplacian(verts, topo, method=method)
    except ValueError:
        return False
    return True


def _pair(first: float | None, cached: float | None) -> str:
    return "-" if first is None or cached is None else f"{first:.4g} / {cached:.4g} s"


def _ratio(num: float | None, den: float) -> str:
    return "-" if num is None else f"{num / den:.2f}"


def table(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    header = [
        "mesh",
        "faces",
        *(f"{TITLES[m]} first / cached" for m in METHODS),
        "libigl PLMS",
        "libigl / our PLMS first",
        "PLMS / AW11 cached",
        "dGBD20 / AW11 cached",
        "Diamond / AW11 cached",
    ]
    body = []
    for r in rows:
        igl_t = r["igl_plms"]
        body.append(
            [
                r["mesh"],
                f"{r['faces']:,}",
                *(_pair(r[f"{m}_first"], r[f"{m}_cached"]) for m in METHODS),
                f"{igl_t:.4g} s" if igl_t else "-",
                f"{igl_t / r['plms_first']:.1f}x" if igl_t else "-",
                f"{r['plms_cached'] / r['aw11_cached']:.2f}",
                f"{r['degoes_cached'] / r['aw11_cached']:.2f}",
                _ratio(r["diamond_cached"], r["aw11_cached"]),
            ]
        )
    return header, body


def main() -> None:
    parser = common.script_parser(__doc__, "methods", repeat=3)
    parser.add_argument("--grid", type=int, default=1000, help="n of the n x n quad grid")
    parser.add_argument("--real-dir", type=Path, default=ROOT.parent / "shared/data/meshes/real")
    args = parser.parse_args()
    meta = common.run_meta(threads=1)
    with common.pinned_threads(1):
        rows = run(args)
    header, body = table(rows)
    print(f"torch {torch.__version__}, 1 thread, median of {args.repeat}\n")
    print(common.markdown_table(header, body))
    sections = {"repeat": args.repeat, "tables": {"methods": common.table_data(header, body)}}
    common.write_results("methods", {**sections, "rows": rows}, meta=meta, path=args.json)


def run(args: argparse.Namespace) -> list[dict]:
    rows = []
    verts, faces = common.bench_grid(args.grid)
    print(f"grid {args.grid}x{args.grid}", file=sys.stderr)
    rows.append(bench_mesh(f"quad grid {args.grid}^2", verts, faces, args.repeat))
    if args.real_dir.exists():
        for path in sorted(args.real_dir.iterdir()):
            if path.suffix not in (".obj", ".off", ".ply"):
                continue
            print(path.name, file=sys.stderr)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # skipped OBJ records, Moebius orientation
                v, f = tp.read_mesh(path)
                rows.append(bench_mesh(path.name, v, f, args.repeat))
    return rows


if __name__ == "__main__":
    main()
