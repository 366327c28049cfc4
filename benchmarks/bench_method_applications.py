"""The paper's applications with each polygon Laplacian, against exact solutions, in one run.

    python benchmarks/bench_method_applications.py [--levels 3 4] [--json PATH]

For ``method`` in ``aw11`` (Alexa and Wardetzky 2011, ``lam = 1``), ``plms`` (Bunge et al.
2020) and ``degoes`` (de Goes et al. 2020, ``lam = 1``), on the refinement families of
``../shared/data/meshes`` (or ``$POLYLAP_SHARED_MESHES``):

* **mean curvature** (AW11 sec. 3.2): mean of ``| |H| / 2 - 1 |`` over the vertices of the unit
  spheres ``hex``, ``quad``, ``voronoi`` and ``concave`` (vertices projected onto the sphere);
* **mean-curvature flow** (AW11 sec. 5.1): 100 implicit steps to ``t = 0.05`` on the same
  spheres; relative error of the mean radius against the exact ``sqrt(1 - 4 t)``;
* **plate bending** (AW11 sec. 5.4): relative ``M0``-norm error against the Navier series on the
  unit-square grids ``quad``, ``str_hex`` and ``irr_poly`` (:func:`tp.apps.plate_error`);
* **conformal map** (AW11 sec. 5.2, free boundary): the mean absolute corner-angle error of the
  map of the sphere's lower half (the faces with every corner at ``z < 0.2``, a disk), which no
  flat map can make zero; smaller is better, the peers share the same mesh.

Prints one Markdown table per application (rows: meshes, columns: methods) and writes the numbers
to ``benchmarks/results/method_applications.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import argparse
import math
import os
import warnings
from pathlib import Path

import torch
from common import markdown_table, run_meta, table_data, write_results

import torch_polylap as tp

METHODS = ("aw11", "plms", "degoes")
ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("POLYLAP_SHARED_MESHES", ROOT.parent / "shared" / "data" / "meshes"))
SPHERES = ("hex", "quad", "voronoi", "concave")
GRIDS = ("quad", "str_hex", "irr_poly")
FLOW_TIME, FLOW_STEPS = 0.05, 100
KEYS = ("curvature", "flow", "plate", "conformal")  # the results file's table names


def read(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", tp.io.SkippedContentWarning)
        return tp.read_mesh(path, dtype=torch.float64)


def unit_sphere(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    verts, faces = read(path)
    return verts / verts.norm(dim=1, keepdim=True), faces


def curvature_error(verts: torch.Tensor, faces, method: str) -> float:
    H = tp.mean_curvature_normal(verts, faces, method=method)
    return float((H.norm(dim=1) / 2 - 1).abs().mean())


def flow_error(verts: torch.Tensor, faces, method: str) -> float:
    dt = FLOW_TIME / FLOW_STEPS
    X = tp.apps.mean_curvature_flow(verts, faces, dt, FLOW_STEPS, method=method).verts
    m = tp.mass(X, faces)
    centre = (m[:, None] * X).sum(0) / m.sum()
    radius = float((m * (X - centre).norm(dim=1)).sum() / m.sum())
    exact = math.sqrt(1 - 4 * FLOW_TIME)
    return abs(radius - exact) / exact


def plate_error(verts: torch.Tensor, faces, method: str) -> float:
    u = tp.apps.plate_bending(verts, faces, method=method)
    return float(tp.apps.plate_error(verts, faces, u))


def lower_cap(verts: torch.Tensor, faces) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """The faces with every corner below ``z = 0.2``, unreferenced vertices dropped."""
    pf = tp.as_faces(faces)
    below = (verts[pf.indices, 2] < 0.2).to(torch.int64)
    face_of_corner = torch.repeat_interleave(torch.arange(pf.num_faces), pf.sizes)
    count = torch.zeros(pf.num_faces, dtype=torch.int64).index_add_(0, face_of_corner, below)
    keep = count == pf.sizes
    corner_keep = keep[face_of_corner]
    cap = tp.PolygonFaces(pf.indices[corner_keep], sizes=pf.sizes[keep])
    v, f, _ = tp.repair.remove_unreferenced_vertices(verts, cap)
    return v, f


def conformal_error(verts: torch.Tensor, faces, method: str) -> float:
    uv = tp.apps.conformal_parameterization(verts, faces, free_boundary=True, method=method)
    return tp.apps.angle_distortion(uv, verts, faces).mean


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, nargs="+", default=[3, 4])
    parser.add_argument(
        "--json", type=Path, help="default benchmarks/results/method_applications.json"
    )
    args = parser.parse_args()
    if not SHARED.is_dir():
        raise SystemExit(
            f"the refinement families are not here: {SHARED} (set POLYLAP_SHARED_MESHES)"
        )
    torch.set_num_threads(1)
    meta = run_meta()
    tables: dict[str, dict[str, dict[str, float]]] = {
        "mean curvature: mean | |H|/2 - 1 | on the unit sphere": {},
        f"mean-curvature flow: relative radius error at t = {FLOW_TIME}": {},
        "plate bending: relative M0-norm error against Navier": {},
        "free-boundary conformal map of the lower half sphere: mean |angle error| (rad)": {},
    }
    curvature, flow, plate, conformal = tables.values()
    for level in args.levels:
        for family in SPHERES:
            path = SHARED / "sphere" / f"{family}_{level}.obj"
            if not path.is_file():
                continue
            verts, faces = unit_sphere(path)
            cap_verts, cap_faces = lower_cap(verts, faces)
            name = f"sphere {family}_{level} ({verts.shape[0]} v)"
            curvature[name] = {m: curvature_error(verts, faces, m) for m in METHODS}
            flow[name] = {m: flow_error(verts, faces, m) for m in METHODS}
            conformal[name] = {m: conformal_error(cap_verts, cap_faces, m) for m in METHODS}
        for family in GRIDS:
            path = SHARED / "grid" / f"{family}_{level}.obj"
            if not path.is_file():
                continue
            verts, faces = read(path)
            if float(verts[:, 0].min()) < -0.25:  # quad covers [-1/2, 1/2]^2: onto [0, 1]^2
                verts = verts + torch.tensor([0.5, 0.5, 0.0], dtype=verts.dtype)
            name = f"grid {family}_{level} ({verts.shape[0]} v)"
            plate[name] = {m: plate_error(verts, faces, m) for m in METHODS}
    print(f"torch {torch.__version__}, float64, 1 thread\n")
    rendered = {}
    for key, (title, rows) in zip(KEYS, tables.items(), strict=True):
        print(f"### {title}\n")
        body = [[name] + [f"{rows[name][m]:.3g}" for m in METHODS] for name in rows]
        print(markdown_table(["mesh", *METHODS], body))
        print()
        rendered[key] = table_data(["mesh", *METHODS], body)
    sections = {"levels": args.levels, "errors": tables, "tables": rendered}
    write_results("method_applications", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
