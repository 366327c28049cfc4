"""Benchmark torch_polylap's AW11 Laplacian against libigl and scipy.

Measured on non-planar quad grids (``--sizes``, an ``n x n`` grid has ``n^2`` faces) and on the
real polygon meshes of ``--real-dir``:

1. first assembly of ``(L, M0)``: ``build_topology`` + ``laplacian``;
2. re-assembly of ``(L, M0)`` with the cached ``Topology``;
3. forward + backward of ``sum((L X)^2)`` with respect to the vertex positions ``X``;
4. ``L @ X`` for ``X`` ``(V, 3)``: ``torch_polylap.sparse.spmm`` and plain ``L @ X`` on a
   detached ``L``;
5. peak memory of (3), in a fresh process per grid size;
6. with ``--compiled``: (2) and (3) through ``tp.CompiledLaplacian`` (the opt-in compiled
   assembly), its compile time, and the targets for it (``COMPILED_RATIOS``).

Side by side: libigl's triangle ``cotmatrix`` on the fan triangulation of the same mesh (two
triangles per grid quad), libigl's polygon ``cotmatrix`` (Bunge et al. 2020) and scipy's CSR
product for (4).  Every time is the median of ``--repeat`` samples after a warm-up call
(fast operations are repeated within a sample, see :func:`median_time`).

Run from the repository root::

    python benchmarks/bench_laplacian.py                 # 10k, 100k, 1M faces + real meshes
    python benchmarks/bench_laplacian.py --sizes 100 316 --repeat 1 --json /tmp/smoke.json

Progress goes to stderr; the report (Markdown tables) goes to stdout; the numbers to
``benchmarks/results/laplacian.json`` (or ``--json PATH``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import os
import platform
import resource
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import common
import igl
import numpy as np
import scipy
import torch
from common import (
    add_switch,
    bench_grid,
    cpu_model,
    markdown_table,
    peak_rss_growth,
    run_meta,
    synchronizer,
    table_data,
    write_results,
)

import torch_polylap as tp

DEFAULT_SIZES = (100, 316, 1000)
# ../shared beside the repository holds the real meshes (see ../shared/data/meshes/README.md)
DEFAULT_REAL_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "real"
MESH_SUFFIXES = (".obj", ".off", ".ply")
# Non-orientable meshes: checked (L and M0 build with a warning, the topology reports the
# non-orientable component and refuses what needs an orientation), not timed.
NON_ORIENTABLE = ("moebius.obj",)
# A timing sample repeats a fast call until it lasts this long, so sub-millisecond operations
# are not dominated by timer and scheduling noise.
MIN_SAMPLE_SECONDS = 0.05
# name -> (numerator, denominator, target upper bound) of the compiled assembly (--compiled)
COMPILED_RATIOS: dict[str, tuple[str, str, float]] = {
    "re-asm compiled / igl tri": ("reassembly_compiled", "igl_tri", 0.05),
    "fwd+bwd compiled / re-asm compiled": ("fwd_bwd_compiled", "reassembly_compiled", 2.0),
}
CORRECTNESS_TOL = 1e-10
MEMORY_TARGET_BYTES = 3 * 2**30
# Warn when other processes kept more than this fraction of the cores busy during the run:
# torch's multi-threaded kernels then wait for descheduled threads and slow down by far more.
BUSY_CORES_PER_CORE = 0.1

# name -> (numerator, denominator, target upper bound or None)
RATIOS: dict[str, tuple[str, str, float | None]] = {
    "first / igl tri": ("first", "igl_tri", 0.7),
    "re-asm / igl tri": ("reassembly", "igl_tri", 0.1),
    "fwd+bwd / first": ("fwd_bwd", "first", 3.0),
    "spmm / scipy": ("spmm", "scipy_matmul", 2.0),
    "L@X / scipy": ("torch_matmul", "scipy_matmul", 2.0),
    "first / igl poly": ("first", "igl_poly", None),
}

Faces = torch.Tensor | tp.PolygonFaces


@dataclass
class Mesh:
    """A benchmark mesh: float64 positions and faces, plus the inputs of the libigl baselines."""

    name: str
    verts: np.ndarray  # (V, 3) float64
    faces: Faces  # (F, k) tensor for grids, PolygonFaces for files
    packed: tp.PolygonFaces

    @property
    def num_faces(self) -> int:
        return self.packed.num_faces

    def fan_triangles(self) -> np.ndarray:
        """``(T, 3)`` fan triangulation ``(c0, ci, ci+1)`` of every face (2 triangles per quad)."""
        idx = self.packed.indices.numpy()
        sizes = self.packed.sizes.numpy()
        offsets = self.packed.offsets.numpy()
        per_face = sizes - 2
        owner = np.repeat(np.arange(sizes.size), per_face)
        local = np.arange(per_face.sum()) - np.repeat(np.cumsum(per_face) - per_face, per_face)
        first = offsets[owner]
        return idx[np.stack((first, first + local + 1, first + local + 2), 1)]


def grid_mesh(n: int) -> Mesh:
    """An ``n x n`` quad grid of the unit square lifted to ``z = 0.05 sin(7x) cos(5y)``
    (``common.bench_grid``).

    The lift makes the quads non-planar, so the AW11 stabilizer is exercised on every face.
    """
    verts, faces = bench_grid(n)
    return Mesh(f"grid {n}x{n}", verts.numpy(), faces, tp.as_faces(faces))


def file_mesh(path: Path) -> Mesh:
    """A mesh read with ``torch_polylap.read_mesh`` (polygons kept as written)."""
    verts, faces = tp.read_mesh(path)
    return Mesh(path.name, verts.numpy(), faces, faces)


def median_time(fn: Callable[[], object], repeat: int, sync: Callable[[], None]) -> float:
    """Median seconds per call of ``fn`` over ``repeat`` samples (``common.median_time``): one
    warm-up call, then calls per sample doubled until a sample lasts :data:`MIN_SAMPLE_SECONDS`,
    so that sub-millisecond operations are timed over many calls."""
    return common.median_time(fn, repeat, sync=sync, min_sample_s=MIN_SAMPLE_SECONDS)


def forward_backward(
    verts: torch.Tensor,
    topo: tp.Topology,
    assemble: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] | None = None,
) -> None:
    """One training step's worth of work: ``(L, M0)`` from ``X``, ``sum((L X)^2)``, backward
    (``assemble``: instead of ``tp.laplacian(X, topo)``)."""
    X = verts.detach().requires_grad_(True)
    L, _ = tp.laplacian(X, topo) if assemble is None else assemble(X)
    loss = (tp.sparse.spmm(L, X) ** 2).sum()
    loss.backward()


def bench_compiled(
    verts: torch.Tensor, topo: tp.Topology, repeat: int, sync: Callable[[], None]
) -> dict[str, float]:
    """Seconds of the first calls of ``tp.CompiledLaplacian`` (compilation included: without
    and with gradients), its re-assembly and its forward + backward."""
    compiled = tp.CompiledLaplacian(topo)
    start = time.perf_counter()
    compiled(verts)
    sync()
    first = time.perf_counter() - start
    start = time.perf_counter()
    forward_backward(verts, topo, compiled)
    sync()
    first_grad = time.perf_counter() - start
    return {
        "compile": first,
        "compile_grad": first_grad,
        "reassembly_compiled": median_time(lambda: compiled(verts), repeat, sync),
        "fwd_bwd_compiled": median_time(
            lambda: forward_backward(verts, topo, compiled), repeat, sync
        ),
    }


def bench_mesh(
    mesh: Mesh, dtype: torch.dtype, device: torch.device, repeat: int, compiled: bool = False
) -> dict:
    """Median seconds of every measured operation on ``mesh``, plus its sizes."""
    sync = synchronizer(device)
    num_verts = mesh.verts.shape[0]
    verts = torch.as_tensor(mesh.verts, dtype=dtype, device=device)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # isolated-vertex warnings were reported by validate()
        topo = tp.build_topology(mesh.faces, num_verts)
        L, _ = tp.laplacian(verts, topo)
        S = tp.sparse.to_scipy(L)
        X_np = verts.cpu().numpy()
        tris = mesh.fan_triangles()
        corners = mesh.packed.indices.numpy()
        offsets = mesh.packed.offsets.numpy()
        times = {
            "topology": median_time(lambda: tp.build_topology(mesh.faces, num_verts), repeat, sync),
            "first": median_time(
                lambda: tp.laplacian(verts, tp.build_topology(mesh.faces, num_verts)), repeat, sync
            ),
            "reassembly": median_time(lambda: tp.laplacian(verts, topo), repeat, sync),
            "fwd_bwd": median_time(lambda: forward_backward(verts, topo), repeat, sync),
            "spmm": median_time(lambda: tp.sparse.spmm(L, verts), repeat, sync),
            "torch_matmul": median_time(lambda: L @ verts, repeat, sync),
            "scipy_matmul": median_time(lambda: S @ X_np, repeat, sync),
            "igl_tri": median_time(lambda: igl.cotmatrix(mesh.verts, tris), repeat, sync),
            "igl_poly": median_time(
                lambda: igl.cotmatrix(mesh.verts, corners, offsets), repeat, sync
            ),
        }
        if compiled:
            times.update(bench_compiled(verts, topo, repeat, sync))
    ratios = {name: times[a] / times[b] for name, (a, b, _) in RATIOS.items()}
    if compiled:
        ratios.update({name: times[a] / times[b] for name, (a, b, _) in COMPILED_RATIOS.items()})
    return {
        "name": mesh.name,
        "faces": mesh.num_faces,
        "verts": num_verts,
        "nnz": topo.nnz,
        "degrees": sorted(set(mesh.packed.sizes.tolist())),
        "seconds": times,
        "ratios": ratios,
    }


def peak_memory_child(n: int, dtype_name: str, device_name: str) -> dict:
    """Peak memory of one forward + backward on the ``n x n`` grid; runs in a fresh process.

    The setup (mesh, positions, topology on the device) is done first; the peak-RSS counter is
    then reset and the step run once.  Where ``/proc/self/clear_refs`` cannot be written the
    peak falls back to ``ru_maxrss`` since process start (an upper bound).
    """
    device = torch.device(device_name)
    mesh = grid_mesh(n)
    verts = torch.as_tensor(mesh.verts, dtype=getattr(torch, dtype_name), device=device)
    topo = tp.build_topology(mesh.faces, verts.shape[0])
    topo.on(device)
    del mesh
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        cuda_baseline = torch.cuda.memory_allocated(device)
    result = peak_rss_growth(lambda: forward_backward(verts, topo))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        result["cuda_delta_bytes"] = torch.cuda.max_memory_allocated(device) - cuda_baseline
    return result


def measure_peak_memory(n: int, dtype: torch.dtype, device: torch.device) -> dict:
    """Run :func:`peak_memory_child` in a freshly spawned interpreter and return its result."""
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
        dtype_name = str(dtype).removeprefix("torch.")
        return pool.submit(peak_memory_child, n, dtype_name, str(device)).result()


def check_against_igl(n: int, device: torch.device) -> dict:
    """On the triangle split of the ``n x n`` grid, ``L`` must be ``-igl.cotmatrix`` (float64)."""
    mesh = grid_mesh(n)
    tris = mesh.fan_triangles()
    verts = torch.as_tensor(mesh.verts, dtype=torch.float64, device=device)
    L, _ = tp.laplacian(verts, torch.from_numpy(tris))
    diff = tp.sparse.to_scipy(L) + igl.cotmatrix(mesh.verts, tris)
    max_abs = float(abs(diff).max()) if diff.nnz else 0.0
    return {
        "mesh": f"{mesh.name} split into triangles",
        "max_abs_diff": max_abs,
        "tolerance": CORRECTNESS_TOL,
        "passed": max_abs <= CORRECTNESS_TOL,
    }


def check_non_orientable(path: Path) -> dict:
    """A non-orientable mesh: ``L`` and ``M0`` must build (with one warning), the topology must
    report a non-orientable component, and ``require_oriented`` must raise a ValueError."""
    verts, faces = tp.read_mesh(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        topo = tp.build_topology(faces, verts.shape[0])
        L, M0 = tp.laplacian(verts, topo)
    problems = []
    if not any("not a consistently oriented" in str(w.message) for w in caught):
        problems.append("no warning")
    if topo.report.non_orientable_components < 1:
        problems.append("no non-orientable component reported")
    if not bool(torch.isfinite(L.values()).all() and torch.isfinite(M0.values()).all()):
        problems.append("L or M0 not finite")
    try:
        topo.require_oriented("bench_laplacian")
        problems.append("require_oriented did not raise")
        message = ""
    except ValueError as err:
        message = str(err)
    return {
        "mesh": path.name,
        "passed": not problems,
        "message": "; ".join(problems) if problems else message,
    }


def validate(mesh: Mesh) -> list[str]:
    """Build ``L`` once; raises on meshes the library rejects, returns the warnings it gave."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tp.laplacian(torch.from_numpy(mesh.verts), tp.build_topology(mesh.faces, len(mesh.verts)))
    return [str(w.message) for w in caught]


def real_meshes(directory: Path) -> tuple[list[Mesh], list[dict], list[dict]]:
    """The meshes of ``directory`` that load and build; the skipped ones; the non-orientable
    checks."""
    meshes, skipped, orient_checks = [], [], []
    for path in sorted(p for p in directory.iterdir() if p.suffix.lower() in MESH_SUFFIXES):
        if path.name in NON_ORIENTABLE:
            orient_checks.append(check_non_orientable(path))
            continue
        try:
            mesh = file_mesh(path)
            notes = validate(mesh)
        except (OSError, ValueError) as err:
            skipped.append({"mesh": path.name, "reason": f"{type(err).__name__}: {err}"})
            progress(f"skip {path.name}: {type(err).__name__}: {err}")
            continue
        for note in notes:
            progress(f"note {path.name}: {note}")
        meshes.append(mesh)
    return meshes, skipped, orient_checks


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def fmt_ms(seconds: float) -> str:
    ms = seconds * 1e3
    return f"{ms:.3g}" if ms < 1000 else f"{ms:,.0f}"


def fmt_ratio(value: float, target: float | None) -> str:
    text = f"{value:.3g}"
    if target is None:
        return text
    return f"{text} {'✓' if value <= target else '✗'}"


def fmt_mb(num_bytes: int | None) -> str:
    return "–" if num_bytes is None else f"{num_bytes / 2**20:,.0f}"


# the timing table's millisecond columns: header -> key of a result's "seconds"
TIMING_COLUMNS = {
    "topology": "topology",
    "first": "first",
    "re-asm": "reassembly",
    "fwd+bwd": "fwd_bwd",
    "spmm": "spmm",
    "L@X": "torch_matmul",
    "scipy L@X": "scipy_matmul",
    "igl tri": "igl_tri",
    "igl poly": "igl_poly",
}


def timing_table(results: list[dict]) -> dict:
    header = ["mesh", "F", "V", "nnz(L)", *TIMING_COLUMNS, "fwd+bwd Δ MB", "process MB"]
    rows = []
    for r in results:
        s, mem = r["seconds"], r.get("memory") or {}
        rows.append(
            [r["name"], f"{r['faces']:,}", f"{r['verts']:,}", f"{r['nnz']:,}"]
            + [fmt_ms(s[key]) for key in TIMING_COLUMNS.values()]
            + [
                fmt_mb(mem.get("cuda_delta_bytes", mem.get("rss_delta_bytes"))),
                fmt_mb(mem.get("rss_peak_bytes")),
            ]
        )
    return table_data(header, rows)


def ratio_table(results: list[dict]) -> dict:
    header = ["mesh"] + [
        name if t is None else f"{name} (≤ {t:g})" for name, (_, _, t) in RATIOS.items()
    ]
    rows = [
        [r["name"]] + [fmt_ratio(r["ratios"][name], t) for name, (_, _, t) in RATIOS.items()]
        for r in results
    ]
    return table_data(header, rows)


def scaling_table(grids: list[dict]) -> dict:
    keys = {
        "first": "first",
        "re-asm": "reassembly",
        "fwd+bwd": "fwd_bwd",
        "spmm": "spmm",
        "igl tri": "igl_tri",
    }
    header = ["grid", "F"] + [f"{name} µs/face" for name in keys]
    base = grids[0]
    rows = []
    for r in grids:
        cells = [r["name"], f"{r['faces']:,}"]
        for key in keys.values():
            per_face = r["seconds"][key] / r["faces"]
            growth = per_face / (base["seconds"][key] / base["faces"])
            cells.append(f"{per_face * 1e6:.3g} (×{growth:.2f})")
        rows.append(cells)
    return table_data(header, rows)


def cpu_counters() -> tuple[float, float] | None:
    """``(busy CPU-seconds of the whole machine, CPU-seconds of this process and its children)``.

    Read from ``/proc/stat`` (Linux); None elsewhere.
    """
    try:
        with open("/proc/stat") as stat:
            ticks = [int(t) for t in stat.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = ticks[3] + ticks[4]  # idle + iowait; steal counts as busy (another VM ran)
    busy = (sum(ticks) - idle) / os.sysconf("SC_CLK_TCK")
    own = sum(
        getattr(resource.getrusage(who), field)
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
        for field in ("ru_utime", "ru_stime")
    )
    return busy, own


def other_processes_cores(
    start: tuple[float, float] | None, stop: tuple[float, float] | None, seconds: float
) -> float | None:
    """Average number of cores kept busy by other processes between two :func:`cpu_counters`."""
    if start is None or stop is None or seconds <= 0:
        return None
    return max(0.0, ((stop[0] - start[0]) - (stop[1] - start[1])) / seconds)


def environment(args: argparse.Namespace, device: torch.device) -> dict:
    cpu = cpu_model()
    return {
        "cpu": cpu,
        "cpu_count": multiprocessing.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "device": str(device),
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
        "dtype": args.dtype,
        "repeat": args.repeat,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "torch_polylap": tp.__version__,
    }


def md(t: dict) -> str:
    return markdown_table(t["columns"], t["rows"])


def compiled_table(results: list[dict]) -> dict:
    """Eager against compiled (``tp.CompiledLaplacian``) re-assembly and forward + backward."""
    header = [
        "mesh",
        "compile s (no grad, grad)",
        "re-asm eager",
        "re-asm compiled",
        "fwd+bwd eager",
        "fwd+bwd compiled",
    ] + [f"{name} (≤ {t:g})" for name, (_, _, t) in COMPILED_RATIOS.items()]
    rows = []
    for r in results:
        s = r["seconds"]
        rows.append(
            [r["name"], f"{s['compile']:.1f}, {s['compile_grad']:.1f}"]
            + [
                fmt_ms(s[key])
                for key in ("reassembly", "reassembly_compiled", "fwd_bwd", "fwd_bwd_compiled")
            ]
            + [fmt_ratio(r["ratios"][name], t) for name, (_, _, t) in COMPILED_RATIOS.items()]
        )
    return table_data(header, rows)


def tables(grids: list[dict], reals: list[dict]) -> dict:
    """The report's tables (``timings``, ``ratios``, ``scaling`` for the grids, ``compiled``
    with ``--compiled``)."""
    out = {"timings": timing_table(grids + reals), "ratios": ratio_table(grids + reals)}
    if grids:
        out["scaling"] = scaling_table(grids)
    measured = [r for r in grids + reals if "reassembly_compiled" in r["seconds"]]
    if measured:
        out["compiled"] = compiled_table(measured)
    return out


def report(env: dict, checks: dict, grids: list[dict], reals: list[dict]) -> str:
    """The Markdown report printed to stdout."""
    tables_ = tables(grids, reals)
    lines = [
        f"Machine: {env['cpu']}, {env['cpu_count']} cores, torch {env['torch']} with "
        f"{env['torch_threads']} threads; device {env['device']}"
        + (f" ({env['gpu']})" if env["gpu"] else "")
        + f", {env['dtype']}. Median of {env['repeat']} sample(s) after a warm-up; a sample "
        f"repeats calls faster than {MIN_SAMPLE_SECONDS * 1e3:g} ms. Times in ms.",
        "",
    ]
    other = env.get("other_processes_cores")
    if other is not None:
        lines += [
            f"Other processes kept {other:.2f} of {env['cpu_count']} cores busy on average "
            "during the run.",
            "",
        ]
        if other > BUSY_CORES_PER_CORE * env["cpu_count"]:
            lines += ["**Warning: the machine was not idle; the timings are unreliable.**", ""]
    tri = checks["igl_triangles"]
    lines.append(
        f"Correctness: {tri['mesh']}: max |L + igl.cotmatrix| = "
        f"{tri['max_abs_diff']:.2e} (tol {tri['tolerance']:g}) "
        f"{'PASS' if tri['passed'] else 'FAIL'}"
    )
    for check in checks["non_orientable"]:
        verdict = (
            "L and M0 built, reported, require_oriented raises ValueError: PASS"
            if check["passed"]
            else f"FAIL ({check['message']})"
        )
        lines.append(f"Correctness: {check['mesh']} (non-orientable) {verdict}")
    lines += [
        "",
        "### Timings (ms)",
        "",
        md(tables_["timings"]),
        "",
        "### Ratios (✓ meets the target)",
        "",
        md(tables_["ratios"]),
    ]
    if grids:
        lines += [
            "",
            "### Time per face on the grids (growth relative to the smallest)",
            "",
            md(tables_["scaling"]),
        ]
    if "compiled" in tables_:
        lines += [
            "",
            "### Compiled assembly (tp.CompiledLaplacian; ms unless noted)",
            "",
            md(tables_["compiled"]),
        ]
    memories = [g["memory"] for g in grids if g.get("memory")]
    if memories:
        largest = grids[-1]
        delta = largest["memory"].get("cuda_delta_bytes", largest["memory"]["rss_delta_bytes"])
        if delta is not None:
            verdict = "✓" if delta < MEMORY_TARGET_BYTES else "✗"
            lines += [
                "",
                f"Peak fwd+bwd memory on {largest['name']}: {fmt_mb(delta)} MB "
                f"(target < {MEMORY_TARGET_BYTES / 2**30:g} GB at 1M faces) {verdict}; "
                f"measured with {largest['memory']['method']}.",
            ]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Benchmark torch_polylap's Laplacian (assembly, fwd+bwd, L@X, memory) "
        "against libigl and scipy; prints Markdown tables to stdout.",
    )
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="*",
        default=list(DEFAULT_SIZES),
        metavar="N",
        help="grid resolutions n (n x n quads = n^2 faces); "
        "default: %(default)s; pass none to skip the grids",
    )
    add_switch(parser, "--real", "also benchmark the meshes in --real-dir (default: on)")
    parser.add_argument(
        "--real-dir",
        type=Path,
        default=DEFAULT_REAL_DIR,
        help="directory of .obj/.off/.ply meshes (default: %(default)s)",
    )
    parser.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="timed samples per measurement, the median is reported (default: 3)",
    )
    parser.add_argument(
        "--dtype",
        choices=("float64", "float32"),
        default="float64",
        help="dtype of torch_polylap's computations (libigl is always float64)",
    )
    parser.add_argument(
        "--device",
        default="cpu",
        help="torch device for torch_polylap, e.g. cpu or cuda (default: cpu)",
    )
    add_switch(
        parser, "--memory", "measure peak fwd+bwd memory per grid in a fresh process (default: on)"
    )
    parser.add_argument(
        "--compiled",
        action="store_true",
        help="also time tp.CompiledLaplacian (compiles once per mesh: tens of seconds each)",
    )
    parser.add_argument(
        "--json", type=Path, metavar="PATH", help="default: benchmarks/results/laplacian.json"
    )
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    if any(n < 1 for n in args.sizes):
        parser.error("--sizes must be positive")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(
            "CUDA is not available in this torch build or on this machine; nothing to "
            "benchmark on --device cuda."
        )
        return 0
    dtype = getattr(torch, args.dtype)
    started = time.perf_counter()
    counters = cpu_counters()
    meta = run_meta()
    env = environment(args, device)

    sizes = sorted(args.sizes)
    checks = {
        "igl_triangles": check_against_igl(sizes[0] if sizes else 10, device),
        "non_orientable": [],
    }
    progress(f"correctness vs igl: max abs diff {checks['igl_triangles']['max_abs_diff']:.2e}")

    grids = []
    for n in sizes:
        progress(f"grid {n}x{n} ...")
        result = bench_mesh(grid_mesh(n), dtype, device, args.repeat, args.compiled)
        if args.memory:
            result["memory"] = measure_peak_memory(n, dtype, device)
        grids.append(result)

    reals, skipped = [], []
    if args.real:
        meshes, skipped, checks["non_orientable"] = real_meshes(args.real_dir)
        for mesh in meshes:
            progress(f"{mesh.name} ...")
            reals.append(bench_mesh(mesh, dtype, device, args.repeat, args.compiled))

    elapsed = time.perf_counter() - started
    env["other_processes_cores"] = other_processes_cores(counters, cpu_counters(), elapsed)
    print(report(env, checks, grids, reals))
    for skip in skipped:
        print(f"\nSkipped {skip['mesh']}: {skip['reason']}")
    progress(f"total time {elapsed:.1f} s")
    payload: dict[str, Any] = {
        "environment": env,
        "checks": checks,
        "grids": grids,
        "real": reals,
        "skipped": skipped,
        "targets": {
            name: t
            for name, (_, _, t) in (
                {**RATIOS, **COMPILED_RATIOS} if args.compiled else RATIOS
            ).items()
        },
        "memory_target_bytes": MEMORY_TARGET_BYTES,
        "total_seconds": elapsed,
        "tables": tables(grids, reals),
    }
    write_results("laplacian", payload, meta=meta, path=args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
