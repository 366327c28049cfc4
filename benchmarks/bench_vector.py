"""Benchmark ``tp.vector``: the connection Laplacian's build and vector heat transport.

    python benchmarks/bench_vector.py [--n 130] [--repeat 3] [--json PATH]

Writes ``benchmarks/results/vector.json`` (or ``--json PATH``).

1. Build time of ``tp.vector.connection_laplacian`` beside ``tp.laplacian`` on the equi-angular
   cube sphere ``tp.shapes.quad_sphere(n)`` (``6 n^2`` quads: 101,400 for ``n = 130``), first
   call (topology and pattern caches cold) and repeated calls (warm), forward only and forward
   plus backward of a scalar loss on the values.
2. Parallel transport of one tangent vector from one source with ``tp.vector.VectorHeatSolver``
   beside potpourri3d's ``PolygonMeshHeatSolver.transport_tangent_vectors`` (when installed),
   on the same mesh in the same run: solver build and one query, then one more query, with the
   mean angle error against the exact great-circle transport (vertices within 0.9 pi of the
   source).

Everything on one thread (``torch.set_num_threads(1)``; potpourri3d is single-threaded); best of
``--repeat`` rounds that alternate the methods (other processes only ever add time). The load
average is printed with the numbers, since the machine may be shared.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from common import cpu_model, run_meta, table_data, write_results

import torch_polylap as tp

try:
    import potpourri3d as pp3d
except ImportError:  # the comparison is optional
    pp3d = None


def best(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """The smallest wall time of ``repeat`` calls, and the last result."""
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def build_times(verts: torch.Tensor, faces: torch.Tensor, repeat: int) -> dict[str, float]:
    """Cold and warm builds of ``L`` and of the connection Laplacian, forward and backward."""
    out = {}
    for name, build in (
        ("laplacian", lambda v, f: tp.laplacian(v, f)[0]),
        ("connection_laplacian", lambda v, f: tp.vector.connection_laplacian(v, f)[0]),
    ):
        fresh = faces.clone()  # a new tensor: the topology cache misses
        t0 = time.perf_counter()
        build(verts, fresh)
        out[f"{name} cold"] = time.perf_counter() - t0
        out[f"{name} warm"], _ = best(lambda b=build, f=fresh: b(verts, f), repeat)

        def forward_backward(b: Callable = build, f: torch.Tensor = fresh) -> None:
            v = verts.clone().requires_grad_(True)
            (b(v, f).values() ** 2).sum().backward()

        out[f"{name} warm fwd+bwd"], _ = best(forward_backward, repeat)
    return out


def transport_times(verts: torch.Tensor, faces: torch.Tensor, repeat: int) -> dict[str, float]:
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

    out: dict[str, float] = {}
    runs: dict[str, tuple[Callable[[], object], Callable[[object], torch.Tensor]]] = {
        "torch_polylap": (
            lambda: tp.vector.VectorHeatSolver(verts, faces),
            lambda s: s.transport(source, vector),
        )
    }
    if pp3d is not None:
        V, F = verts.numpy(), faces.numpy()

        def pp_query(s: object) -> torch.Tensor:
            bx, by, _ = s.get_tangent_frames()
            c = s.transport_tangent_vectors(
                [source], [[vector.numpy() @ bx[0], vector.numpy() @ by[0]]]
            )
            return torch.from_numpy(c[:, :1] * bx + c[:, 1:] * by)

        runs["potpourri3d"] = (lambda: pp3d.PolygonMeshHeatSolver(V, F), pp_query)
    totals: dict[str, list[float]] = {k: [] for k in runs}
    queries: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeat):  # alternate the methods round by round
        for name, (build, query) in runs.items():
            t0 = time.perf_counter()
            solver = build()
            X = query(solver)
            totals[name].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            query(solver)
            queries[name].append(time.perf_counter() - t0)
            out[f"{name} error"] = error(X)
    for name in runs:
        out[f"{name} build+query"] = min(totals[name])
        out[f"{name} query"] = min(queries[name])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=130, help="cube sphere resolution (6 n^2 quads)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", type=Path, help="default benchmarks/results/vector.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    meta = run_meta()
    verts, faces = tp.shapes.quad_sphere(args.n)
    load = os.getloadavg()
    results = {"faces": faces.shape[0], "verts": verts.shape[0]}
    results.update(build_times(verts, faces, args.repeat))
    results.update(transport_times(verts, faces, args.repeat))
    results["loadavg before, after"] = [load[0], os.getloadavg()[0]]
    print(f"cube sphere n = {args.n}: {faces.shape[0]} quads, {verts.shape[0]} vertices")
    print(f"CPU: {cpu_model()} ({platform.machine()}), 1 thread; load average {load[0]:.2f}")
    print("| quantity | value |\n|---|---|")
    body = []
    for key, value in results.items():
        text = f"{value:.3g}" if isinstance(value, float) else str(value)
        if isinstance(value, list):
            text = ", ".join(f"{v:.3g}" for v in value)
        print(f"| {key} | {text} |")
        body.append([key, text])
    tables = {"vector": table_data(["quantity", "value"], body)}
    write_results("vector", {"n": args.n, **results, "tables": tables}, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
