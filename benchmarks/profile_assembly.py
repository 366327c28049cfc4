"""Where the time of re-assembly, forward+backward and the topology build goes, at 1M quads.

    python benchmarks/profile_assembly.py [--n 1000] [--top 10] [--compiled] [--json PATH]

Writes ``benchmarks/results/profile_assembly.json`` (or ``--json PATH``). On the ``n x n``
non-planar quad grid of ``common.bench_grid``, one torch thread, float64, CPU, after one
warm-up call each:

* ``reassembly``: ``tp.laplacian(verts, topo)`` on a cached topology, profiled with
  ``torch.profiler`` (the torch operators by self CPU time: what each kind of pass costs);
* ``fwd_bwd``: the same plus ``(L X)^2`` summed and its gradient to the vertices;
* ``topology``: ``tp.build_topology``, profiled with ``cProfile`` (most of it is numpy, which
  torch's profiler does not see), the functions by their own time;
* with ``--compiled``, ``reassembly_compiled`` and ``fwd_bwd_compiled``: the same two through
  ``tp.CompiledLaplacian`` (compiled before profiling; each compiled graph is one row, named
  forward or backward).

Each table lists the ``--top`` entries with their share of the profiled total, so the rows say
which passes a faster implementation would have to remove, whatever the machine's speed.
"""

from __future__ import annotations

import cProfile
import pstats
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import common
import torch

import torch_polylap as tp


def forward_backward(
    verts: torch.Tensor,
    topo: tp.Topology,
    assemble: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None,
) -> None:
    """Re-assembly (``tp.laplacian``, or ``assemble``), ``sum((L X)^2)`` and its gradient to
    the vertices."""
    X = verts.detach().requires_grad_(True)
    L, _ = tp.laplacian(X, topo) if assemble is None else assemble(X)
    (L @ X).square().sum().backward()


def _profiled(fn: Callable[[], object]) -> list:
    """The operator events of one call of ``fn`` (after a warm-up call) with nonzero self time."""
    fn()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        fn()
    return [e for e in prof.key_averages() if e.self_cpu_time_total > 0]


def compiled_graphs(fn: Callable[[], object]) -> set[str]:
    """The profiler keys of the compiled graphs that one call of ``fn`` runs."""
    return {e.key for e in _profiled(fn) if e.key.startswith(_GRAPH)}


_GRAPH = "## Call CompiledFxGraph"


def torch_profile(
    fn: Callable[[], object], top: int, graphs: dict[str, str] | None = None
) -> tuple[list[str], list[list[str]]]:
    """The ``top`` torch operators of one call of ``fn`` by self CPU time, with their share.

    A compiled graph's row is named by ``graphs`` (profiler key to label; a graph missing
    from it is the backward graph: the forward ones are looked up by running them alone)."""
    events = _profiled(fn)
    for e in events:
        if e.key.startswith(_GRAPH):
            e.key = (graphs or {}).get(e.key, "compiled backward graph")
    events.sort(key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events)
    rows = [
        [
            e.key,
            str(e.count),
            f"{e.self_cpu_time_total / 1e3:,.1f}",
            f"{100 * e.self_cpu_time_total / total:.1f}%",
        ]
        for e in events[:top]
    ]
    rows.append(["all operators (profiled)", "", f"{total / 1e3:,.1f}", "100%"])
    return ["torch operator", "calls", "self ms", "share"], rows


def python_profile(fn: Callable[[], object], top: int) -> tuple[list[str], list[list[str]]]:
    """The ``top`` functions of one call of ``fn`` by their own time (``cProfile``)."""
    fn()
    profiler = cProfile.Profile()
    profiler.enable()
    fn()
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    entries = []
    for (file, line, name), (_, calls, own, _, _) in stats.items():
        where = f"{Path(file).name}:{line}" if line else file
        entries.append((own, calls, f"{name} ({where})"))
    entries.sort(reverse=True)
    total = sum(own for own, _, _ in entries)
    rows = [
        [label, str(calls), f"{own * 1e3:,.1f}", f"{100 * own / total:.1f}%"]
        for own, calls, label in entries[:top]
    ]
    rows.append(["all functions", "", f"{total * 1e3:,.1f}", "100%"])
    return ["function", "calls", "own ms", "share"], rows


def main(argv: list[str] | None = None) -> int:
    parser = common.script_parser(__doc__, "profile_assembly")
    parser.add_argument("--n", type=int, default=1000, help="grid side (n x n quads)")
    parser.add_argument("--top", type=int, default=10, help="rows per profile")
    parser.add_argument(
        "--compiled",
        action="store_true",
        help="also profile tp.CompiledLaplacian (compiling it first takes tens of seconds)",
    )
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    meta = common.run_meta(threads=1)
    verts, faces = common.bench_grid(args.n)
    tables = {}
    with common.pinned_threads(1), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo = tp.build_topology(faces, verts.shape[0])
        profiles = {
            "reassembly": torch_profile(lambda: tp.laplacian(verts, topo), args.top),
            "fwd_bwd": torch_profile(lambda: forward_backward(verts, topo), args.top),
            "topology": python_profile(lambda: tp.build_topology(faces, verts.shape[0]), args.top),
        }
        if args.compiled:
            compiled = tp.CompiledLaplacian(topo)
            profiles["reassembly_compiled"] = torch_profile(
                lambda: compiled(verts),
                args.top,
                dict.fromkeys(compiled_graphs(lambda: compiled(verts)), "compiled assembly"),
            )
            moving = verts.detach().requires_grad_(True)
            forward = compiled_graphs(lambda: compiled(moving))
            profiles["fwd_bwd_compiled"] = torch_profile(
                lambda: forward_backward(verts, topo, compiled),
                args.top,
                dict.fromkeys(forward, "compiled forward graph (saves for backward)"),
            )
    for name, (header, rows) in profiles.items():
        print(f"\n{name}, {faces.shape[0]:,} quads\n")
        print(common.markdown_table(header, rows))
        tables[name] = common.table_data(header, rows)
    common.write_results(
        "profile_assembly",
        {"n": args.n, "faces": int(faces.shape[0]), "tables": tables},
        meta=meta,
        path=args.json,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
