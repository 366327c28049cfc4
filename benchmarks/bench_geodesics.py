"""Benchmark heat-method geodesic distances against exact distances and potpourri3d, in one run.

    python benchmarks/bench_geodesics.py [--levels 3 4 5] [--repeat 3] [--json PATH]

On the shared refinement families (``../shared/data/meshes``): the unit spheres ``hex``,
``quad``, ``voronoi`` and ``concave`` (vertices normalized onto the sphere; source vertex 0;
exact distance: the great-circle distance) and the planar grids ``quad``, ``voronoi`` and
``concave`` (source: the vertex nearest the centre of the square; exact: Euclidean distance).
For each mesh it reports the mean relative error over the vertices other than the source of

* ``torch_polylap.heat_geodesic_distance`` (defaults: ``t = 4 h^2``, heat ``lam = 1``, Poisson
  ``lam = 0.1``), and the same at Crane et al.'s ``t = h^2`` with ``lam = 1`` in both steps;
* potpourri3d's ``PolygonMeshHeatSolver`` (Bunge et al.'s polygon Laplacian, ``t_coef = 1``),
  when installed (``pip install potpourri3d``);

On the real meshes of ``../shared/data/meshes/real`` (``--real``; the consistently oriented
manifolds with ``--real-min-verts`` to ``--real-max-verts`` vertices) the reference is libigl's
exact polyhedral geodesic distance (``igl.exact_geodesic``, Mitchell-Mount-Papadimitriou) on the
ear-clipped triangulation of the polygons, from vertex 0, over the vertices of its connected
component.

and the median seconds (over ``--repeat`` rounds that alternate the methods, so that the load
of a shared machine falls on all of them alike) of building the solver plus one query
("total"), of the next query on the built solver ("second": ours makes the faster copies of
its factors there) and of the one after it ("query": the cost of every later query), in
wall-clock time and in the process's CPU time (which other processes inflate less), with the
ratios ours / potpourri3d.
The load average is read before and after. Prints a Markdown table and writes the numbers
to ``benchmarks/results/geodesics.json`` (or ``--json PATH``). ``POLYLAP_SHARED_MESHES`` overrides
where the meshes are.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from common import run_meta, table_from_markdown, write_results

import torch_polylap as tp
from torch_polylap.triangulate import triangulate_faces

# A method: build its solver and answer one query -> (solver, distances); one more query.
Method = tuple[Callable[[], tuple[object, object]], Callable[[object], object]]

MESHES = Path(
    os.environ.get("POLYLAP_SHARED_MESHES")
    or Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
)
SPHERES = ("hex", "quad", "voronoi", "concave")
GRIDS = ("quad", "voronoi", "concave")

try:
    import potpourri3d as pp3d
except ImportError:  # the comparison is optional
    pp3d = None


def interleaved_medians(methods: dict[str, Method], repeat: int) -> dict[str, dict]:
    """Per method: the distances and the median wall-clock and CPU seconds over ``repeat``
    rounds of "build the solver and answer one query", "the second query" and "a third
    query" (the steady state: ours makes copies of its factors in the second).  The rounds
    alternate the methods, so that a shared machine's load falls on all of them alike."""
    times: dict[str, dict[str, list[float]]] = {name: {} for name in methods}
    dists = {}
    for _ in range(repeat):
        for name, (build_and_query, query) in methods.items():
            wall0, cpu0 = time.perf_counter(), time.process_time()
            solver, dist = build_and_query()
            wall1, cpu1 = time.perf_counter(), time.process_time()
            query(solver)
            wall2, cpu2 = time.perf_counter(), time.process_time()
            query(solver)
            wall3, cpu3 = time.perf_counter(), time.process_time()
            dists[name] = np.asarray(dist)
            spans = {
                "total_s": wall1 - wall0,
                "second_s": wall2 - wall1,
                "query_s": wall3 - wall2,
                "total_cpu_s": cpu1 - cpu0,
                "second_cpu_s": cpu2 - cpu1,
                "query_cpu_s": cpu3 - cpu2,
            }
            for key, value in spans.items():
                times[name].setdefault(key, []).append(value)
    return {
        name: {"dist": dists[name]} | {k: float(np.median(v)) for k, v in times[name].items()}
        for name in methods
    }


def mean_relative_error(dist: np.ndarray, exact: np.ndarray, source: int) -> float:
    keep = (np.arange(exact.size) != source) & np.isfinite(exact) & (exact > 0)
    return float(np.mean(np.abs(dist[keep] - exact[keep]) / exact[keep]))


def load_case(kind: str, family: str, level: int):
    """``(verts, faces, source, exact distances)`` or ``None`` when the file is missing."""
    path = MESHES / kind / f"{family}_{level}.obj"
    if not path.is_file():
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # OBJ materials and object names the reader skips
        verts, faces = tp.read_mesh(path, dtype=torch.float64)
    if kind == "sphere":
        verts = verts / verts.norm(dim=1, keepdim=True)
        source = 0
        exact = torch.arccos((verts @ verts[source]).clamp(-1.0, 1.0))
    else:
        centre = 0.5 * (verts.amin(0) + verts.amax(0))
        source = int((verts - centre).norm(dim=1).argmin())
        exact = (verts - verts[source]).norm(dim=1)
    return verts, faces, source, exact.numpy()


def ours(verts, faces, source, **options) -> Method:
    topo = tp.get_topology(faces, verts.shape[0])  # built once per mesh, as a user would keep it

    def build_and_query():
        solver = tp.HeatGeodesicSolver(verts, topo, **options)
        return solver, solver.distance([source]).numpy()

    return build_and_query, lambda solver: solver.distance([source])


def potpourri(verts, faces, source) -> Method:
    V = verts.numpy()
    polys = faces.tolist()

    def build_and_query():
        solver = pp3d.PolygonMeshHeatSolver(V, polys)
        return solver, solver.compute_distance([source])

    return build_and_query, lambda solver: solver.compute_distance([source])


def load_real_case(path: Path, min_verts: int, max_verts: int):
    """``(verts, faces, source 0, exact distances on the triangulation)`` of a real mesh, or
    ``None`` when it is too large or not a consistently oriented manifold (the exact algorithm
    and the peer need one). Vertices of other components are dropped from the comparison by
    giving them a NaN reference."""
    import igl

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        verts, faces = tp.read_mesh(path, dtype=torch.float64)
        topo = tp.get_topology(faces, verts.shape[0])
    if not min_verts <= verts.shape[0] <= max_verts:
        return None
    if not (topo.is_manifold and topo.is_oriented):
        return None
    if bool(topo.isolated.any()):
        return None
    tris = triangulate_faces(verts, faces).astype(np.int64)
    exact = igl.exact_geodesic(
        verts.numpy(),
        tris,
        VS=np.array([0], dtype=np.int64),
        VT=np.arange(verts.shape[0], dtype=np.int64),
    )
    _, labels = topo.connected_components()
    exact = np.where(labels.numpy() == int(labels[0]), exact, np.nan)
    return verts, faces, 0, exact


def run_case(kind, family, level, repeat, case=None) -> dict | None:
    case = load_case(kind, family, level) if case is None else case
    if case is None:
        return None
    verts, faces, source, exact = case
    h = float(tp.mean_edge_length(verts, faces))
    methods = {
        "ours": ours(verts, faces, source),
        "ours_t=h^2,lam=1": ours(verts, faces, source, t=h * h, poisson_lam=1.0),
    }
    if pp3d is not None:
        methods["potpourri3d"] = potpourri(verts, faces, source)
    try:
        results = interleaved_medians(methods, repeat)
    except (RuntimeError, ValueError):  # the peer refuses some meshes: reference only
        methods.pop("potpourri3d", None)
        results = interleaved_medians(methods, repeat)
    row = {"kind": kind, "family": family, "level": level, "verts": verts.shape[0]}
    row["source"] = source
    for name, m in results.items():
        row[name] = {"mean_rel_error": mean_relative_error(m["dist"], exact, source)}
        row[name] |= {k: v for k, v in m.items() if k.endswith("_s")}
    return row


def markdown(rows: list[dict]) -> str:
    has_pp = any("potpourri3d" in r for r in rows)
    head = "| mesh | V | error (ours) | error (t=h^2, lam=1) |"
    rule = "|---|---:|---:|---:|"
    if has_pp:
        head += (
            " error (potpourri3d) | total ours / pp3d (wall, CPU) |"
            " query ours / pp3d (wall, CPU) |"
        )
        rule += "---:|---:|---:|"
    head += " total ours (s) | second query ours (s) | query ours (s) |"
    rule += "---:|---:|---:|"
    lines = [head, rule]
    for r in rows:
        o, c = r["ours"], r["ours_t=h^2,lam=1"]
        level = f"_{r['level']}" if r["level"] else ""
        cells = [f"{r['kind']}/{r['family']}{level}", str(r["verts"])]
        cells += [f"{o['mean_rel_error']:.2e}", f"{c['mean_rel_error']:.2e}"]
        if has_pp:
            p = r.get("potpourri3d")
            cells += (
                [
                    f"{p['mean_rel_error']:.2e}",
                    f"{o['total_s'] / p['total_s']:.2f}, {o['total_cpu_s'] / p['total_cpu_s']:.2f}",
                    f"{o['query_s'] / p['query_s']:.2f}, {o['query_cpu_s'] / p['query_cpu_s']:.2f}",
                ]
                if p
                else ["-"] * 3
            )
        cells += [f"{o['total_s']:.4f}", f"{o['second_s']:.4f}", f"{o['query_s']:.4f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def load_average() -> str:
    """``/proc/loadavg``'s three load averages, or ``"?"`` off Linux."""
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "?"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levels", type=int, nargs="*", default=[3, 4, 5])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--real", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--real-min-verts", type=int, default=0)
    parser.add_argument("--real-max-verts", type=int, default=100000)
    # potpourri3d solves on one thread; torch's two-thread kernels also stall whenever another
    # process holds a core of a shared machine, which made timings swing tenfold.
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--json", type=Path, help="default benchmarks/results/geodesics.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    meta = run_meta()
    if not MESHES.is_dir():
        raise SystemExit(f"{MESHES} not found: the refinement families live outside the repo.")
    if pp3d is None:
        print("potpourri3d is not installed: comparing against the exact distances only.")
    load_before = load_average()
    print(f"load average before: {load_before}", flush=True)
    rows = []
    for kind, families in (("sphere", SPHERES), ("grid", GRIDS)):
        for family in families:
            for level in args.levels:
                row = run_case(kind, family, level, args.repeat)
                if row is not None:
                    rows.append(row)
                    print(f"done {kind}/{family}_{level}", flush=True)
    real = MESHES / "real"
    if args.real and real.is_dir():
        for path in sorted(real.iterdir()):
            if path.suffix not in (".obj", ".off", ".ply"):
                continue
            case = load_real_case(path, args.real_min_verts, args.real_max_verts)
            if case is None:
                continue
            row = run_case("real", path.stem, 0, args.repeat, case)
            if row is not None:
                rows.append(row)
                print(f"done real/{path.name}", flush=True)
    table = markdown(rows)
    load_after = load_average()
    print(table)
    print(f"load average before: {load_before}, after: {load_after}")
    sections = {"repeat": args.repeat, "statistic": "median", "rows": rows}
    sections["tables"] = {"geodesics": table_from_markdown(table)}
    write_results("geodesics", sections, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
