"""Benchmark ``tp.vector``: the connection Laplacian beside ``L``, and vector heat queries.

    python benchmarks/bench_vector.py [--sizes 130,408] [--repeat 3] [--json PATH]

1. Build and re-assembly of ``tp.vector.connection_laplacian`` beside ``tp.laplacian`` on the
   equi-angular cube spheres ``tp.shapes.quad_sphere(n)`` (``6 n^2`` quads: 101,400 for
   ``n = 130``, 998,784 for ``n = 408``). *Build*: the first call on a new faces tensor (the
   topology, the exploded mesh and the sparsity pattern are computed and cached). *Re-assembly*:
   a later call with new vertex positions (the caches hit; only the values are computed), the
   cost of every training step. Forward plus backward of a scalar loss on the values too, up
   to ``--backward-max`` faces.
2. Vector heat queries on the first size with ``tp.vector.VectorHeatSolver`` beside
   potpourri3d's ``PolygonMeshHeatSolver`` (when installed): solver build, then one parallel
   transport of one vector from one source (the first call, which factors; the second, in
   which ours copies its scalar factor; then per query, the median of 5 calls in each round)
   and one log map per query (the same), with the mean angle error of the transport against
   the exact great-circle transport (vertices within 0.9 pi of the source). potpourri3d's
   polygon solver has no log map. ``--real FILE ...`` adds the same queries on real meshes
   (files of the shared meshes' ``real`` folder, as for ``bench_geodesics.py``, or paths; no
   reference there), with the ratios to potpourri3d.

Everything on one thread (``torch.set_num_threads(1)``; potpourri3d is single-threaded). Each
quantity is the median of ``--repeat`` rounds that alternate the methods (builds run once per
round on a fresh faces tensor). ``/proc/loadavg`` is recorded before and after every section,
since the machine may be shared: compare ratios within one run, not absolute times across runs.
The rows are kept in a dict (``--json`` writes it) and printed as a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from common import cpu_model, run_meta, table_from_markdown, write_results

import torch_polylap as tp

try:
    import potpourri3d as pp3d
except ImportError:  # the comparison is optional
    pp3d = None

Row = dict[str, object]


def loadavg() -> str:
    """The 1, 5 and 15 minute load averages."""
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:  # not Linux
        return "n/a"


def timed(fn: Callable[[], object]) -> tuple[float, object]:
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


# queries timed per round for the per-query rows
QUERIES = 5


def median_of(count: int, fn: Callable[[], object]) -> float:
    """The median seconds of ``count`` calls of ``fn``."""
    return statistics.median(timed(fn)[0] for _ in range(count))


def median_rows(
    section: str, size: str, times: dict[tuple[str, str], list[float]], loads: tuple[str, str]
) -> list[Row]:
    """One row per ``(method, quantity)`` of ``times``: the median of its rounds, with the load
    averages ``loads`` before and after the rounds."""
    return [
        {
            "section": section,
            "mesh": size,
            "method": name,
            "quantity": what,
            "seconds": statistics.median(values),
            "rounds": len(values),
            "load before": loads[0],
            "load after": loads[1],
        }
        for (name, what), values in times.items()
    ]


def operator_rows(n: int, repeat: int, backward_max: int) -> list[Row]:
    """Build and re-assembly of ``L`` and of the connection Laplacian, interleaved."""
    verts, faces = tp.shapes.quad_sphere(n)
    size = f"{faces.shape[0]:,} quads"
    builds: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
        "tp.laplacian": lambda v, f: tp.laplacian(v, f)[0].values(),
        "tp.vector.connection_laplacian": lambda v, f: tp.vector.connection_laplacian(v, f)[
            0
        ].values(),
    }
    g = torch.Generator().manual_seed(0)
    times: dict[tuple[str, str], list[float]] = {}
    load_before = loadavg()
    for _ in range(repeat):
        moved = verts + 1e-3 * torch.randn(verts.shape, generator=g, dtype=verts.dtype)
        for name, build in builds.items():
            fresh = faces.clone()  # a new tensor: the topology cache misses
            elapsed, _ = timed(lambda b=build, f=fresh: b(verts, f))
            times.setdefault((name, "build"), []).append(elapsed)
            elapsed, _ = timed(lambda b=build, f=fresh, m=moved: b(m, f))
            times.setdefault((name, "re-assembly"), []).append(elapsed)
            if faces.shape[0] <= backward_max:

                def step(
                    b: Callable = build, f: torch.Tensor = fresh, m: torch.Tensor = moved
                ) -> None:
                    v = m.clone().requires_grad_(True)
                    (b(v, f) ** 2).sum().backward()

                elapsed, _ = timed(step)
                times.setdefault((name, "re-assembly fwd+bwd"), []).append(elapsed)
            del fresh
    rows = median_rows("operator", size, times, (load_before, loadavg()))
    for what in ("build", "re-assembly", "re-assembly fwd+bwd"):
        pair = [r for r in rows if r["quantity"] == what]
        if len(pair) == 2:
            ratio = float(pair[1]["seconds"]) / float(pair[0]["seconds"])  # type: ignore[arg-type]
            pair[1]["vs L"] = f"{ratio:.1f}x"
    return rows


def query_rows(n: int, repeat: int) -> list[Row]:
    """Solver build, transport and log map per query on the cube sphere, beside potpourri3d,
    with the transport's mean angle error against the exact great-circle transport."""
    verts, faces = tp.shapes.quad_sphere(n)
    source = 0
    vector = torch.linalg.cross(verts[source], torch.tensor([0.3, 0.5, 0.8], dtype=verts.dtype))
    exact = tp.vector.minimal_rotation(
        verts[source].expand_as(verts), verts, vector.expand_as(verts)
    )
    keep = torch.arccos((verts @ verts[source]).clamp(-1, 1)) < 0.9 * np.pi

    def error(X: torch.Tensor) -> float:
        X = X - (X * verts).sum(1, keepdim=True) * verts
        Y = exact - (exact * verts).sum(1, keepdim=True) * verts
        cos = (X * Y).sum(1) / (X.norm(dim=1) * Y.norm(dim=1))
        return float(torch.arccos(cos.clamp(-1, 1))[keep].mean())

    return mesh_query_rows(verts, faces, f"{faces.shape[0]:,} quads", vector, repeat, error)


# the shared meshes next to the repository (POLYLAP_SHARED_MESHES overrides), whose real/
# folder holds the meshes --real names
MESHES = Path(
    os.environ.get("POLYLAP_SHARED_MESHES")
    or Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"
)


def real_query_rows(name: str, repeat: int) -> list[Row]:
    """:func:`mesh_query_rows` on a real mesh (``--real``: a file name in the shared meshes'
    ``real`` folder, or a path), from vertex 0; no reference."""
    path = Path(name) if Path(name).is_file() else MESHES / "real" / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # OBJ groups and materials the reader skips
        verts, faces = tp.read_mesh(path, dtype=torch.float64)
    vector = torch.linalg.cross(verts[0], torch.tensor([0.3, 0.5, 0.8], dtype=verts.dtype))
    size = f"{path.name} ({verts.shape[0]:,} vertices)"
    return mesh_query_rows(verts, faces, size, vector, repeat, None)


def fresh(faces: torch.Tensor | tp.PolygonFaces) -> torch.Tensor | tp.PolygonFaces:
    """A copy of ``faces`` in new tensors, so that the topology cache misses."""
    if isinstance(faces, torch.Tensor):
        return faces.clone()
    return tp.PolygonFaces(faces.indices.clone(), sizes=faces.sizes.clone())


def mesh_query_rows(
    verts: torch.Tensor,
    faces: torch.Tensor | tp.PolygonFaces,
    size: str,
    vector: torch.Tensor,
    repeat: int,
    error: Callable[[torch.Tensor], float] | None,
) -> list[Row]:
    """Solver build, first transport (the factorizations), transport per query and log map per
    query from vertex 0, beside potpourri3d's ``PolygonMeshHeatSolver`` in alternate rounds."""
    source = 0
    runs: dict[str, dict[str, Callable]] = {
        "tp.vector.VectorHeatSolver": {
            "build": lambda: tp.vector.VectorHeatSolver(verts, fresh(faces)),
            "transport": lambda s: s.transport(source, vector),
            "log map": lambda s: s.log_map(source),
        }
    }
    if pp3d is not None:
        V, F = verts.numpy(), faces.tolist()

        def pp_transport(s: object) -> torch.Tensor:
            bx, by, _ = s.get_tangent_frames()  # type: ignore[attr-defined]
            c = s.transport_tangent_vectors(  # type: ignore[attr-defined]
                [source], [[vector.numpy() @ bx[0], vector.numpy() @ by[0]]]
            )
            return torch.from_numpy(c[:, :1] * bx + c[:, 1:] * by)

        runs["potpourri3d.PolygonMeshHeatSolver"] = {
            "build": lambda: pp3d.PolygonMeshHeatSolver(V, F),
            "transport": pp_transport,
        }
    times: dict[tuple[str, str], list[float]] = {}
    errors: dict[str, float] = {}
    load_before = loadavg()
    for _ in range(repeat):  # alternate the methods round by round
        for name, run in runs.items():
            elapsed, solver = timed(run["build"])
            times.setdefault((name, "solver build"), []).append(elapsed)
            # the first query pays the factorizations (cached on the operators)
            elapsed, X = timed(lambda r=run, s=solver: r["transport"](s))
            times.setdefault((name, "first transport (factors)"), []).append(elapsed)
            if error is not None:
                errors[name] = error(X)
            # ours makes faster copies of its scalar factor in the second query
            elapsed, _ = timed(lambda r=run, s=solver: r["transport"](s))
            times.setdefault((name, "second transport"), []).append(elapsed)
            # per query: the median of QUERIES calls in each round, as one call's time swings
            # with a shared machine's load
            elapsed = median_of(QUERIES, lambda r=run, s=solver: r["transport"](s))
            times.setdefault((name, "transport per query"), []).append(elapsed)
            if "log map" in run:
                run["log map"](solver)  # the scalar geodesic systems' factorizations
                elapsed = median_of(QUERIES, lambda r=run, s=solver: r["log map"](s))
                times.setdefault((name, "log map per query"), []).append(elapsed)
            del solver
    rows = median_rows("vector heat", size, times, (load_before, loadavg()))
    peer = {
        str(r["quantity"]): float(r["seconds"])  # type: ignore[arg-type]
        for r in rows
        if r["method"] == "potpourri3d.PolygonMeshHeatSolver"
    }
    for row in rows:
        if row["quantity"] == "transport per query" and errors:
            row["mean angle error (rad)"] = f"{errors[str(row['method'])]:.2g}"
        if row["method"] == "tp.vector.VectorHeatSolver" and row["quantity"] in peer:
            ratio = float(row["seconds"]) / peer[str(row["quantity"])]  # type: ignore[arg-type]
            row["vs potpourri3d"] = f"{ratio:.2f}x"
    return rows


def markdown(rows: list[Row]) -> str:
    keys: list[str] = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for row in rows:
        cells = []
        for k in keys:
            v = row.get(k, "")
            cells.append(f"{v:.3g}" if isinstance(v, float) else str(v))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--sizes",
        default="130,408",
        help="cube sphere resolutions n (6 n^2 quads), comma-separated; queries on the first",
    )
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--backward-max", type=int, default=200_000, help="faces")
    parser.add_argument(
        "--real",
        nargs="*",
        default=[],
        metavar="FILE",
        help="vector heat queries on these meshes too: files of the shared meshes' real/ folder "
        "(e.g. loki.obj) or paths",
    )
    parser.add_argument("--json", type=Path, help="default benchmarks/results/vector.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    meta = run_meta(threads=1)
    sizes = [int(s) for s in args.sizes.split(",")]
    rows: list[Row] = []
    for n in sizes:
        rows += operator_rows(n, args.repeat, args.backward_max)
    rows += query_rows(sizes[0], args.repeat)
    for path in args.real:
        rows += real_query_rows(path, args.repeat)
    print(f"CPU: {cpu_model()} ({platform.machine()}), 1 thread; torch {torch.__version__}")
    print(f"medians of {args.repeat} interleaved rounds; load = /proc/loadavg (1, 5, 15 min)\n")
    text = markdown(rows)
    print(text)
    tables = {"vector": table_from_markdown(text)}
    write_results("vector", {"rows": rows, "tables": tables}, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
