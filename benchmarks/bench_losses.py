"""Benchmark the Laplacian smoothing loss on polygon mesh batches against a triangle cotan loss.

Measured, forward + backward with respect to the packed vertex positions (one training step):

1. ``torch_polylap.losses.laplacian_smoothing(method="polygon")`` on a batch of ``--batch``
   perturbed quad spheres of about ``--faces`` faces each (sizes vary by mesh) and on one quad
   sphere of about ``--big-faces`` faces, with live weights (``L`` differentiated) and frozen
   weights (``L`` under ``no_grad``);
2. the same loss on the triangulated meshes (two triangles per quad), where ``L`` is the cotan
   Laplacian;
3. the baseline on the triangulated meshes: pytorch3d's ``mesh_laplacian_smoothing(method="cot")``
   when pytorch3d is importable (frozen weights only: pytorch3d builds them under ``no_grad``),
   otherwise a plain-torch cotan smoothing loss written below (cotan weights by ``index_add``;
   live: the product as gather + ``index_add``, whose backward is O(nnz); frozen: a torch CSR
   product, its matrix coalesced every call or, the fair comparison and the ratio's
   denominator, scattered onto a CSR pattern built once like ours);
4. peak memory of each step, in one fresh process per mesh case (``VmHWM`` after trimming the
   heap and resetting the counter through ``/proc/self/clear_refs``, as ``bench_laplacian.py``
   does; ``ru_maxrss`` where unavailable), after one warm-up step of each kind.

The topology (``PolygonMeshes.topology()``) is built once outside the timed step, as in a
training loop with fixed connectivity; its one-off cost is reported separately.

Run from the repository root::

    python benchmarks/bench_losses.py                               # 64 x 5k faces and 1M faces
    python benchmarks/bench_losses.py --batch 4 --faces 500 --big-faces 20000 --repeat 1
    # the run recorded in benchmarks/README.md (idle machine, default threads):
    python benchmarks/bench_losses.py --json benchmarks/results/losses.json

Progress goes to stderr, Markdown tables to stdout, JSON to ``--json`` (default
``benchmarks/results/losses.json``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import gc
import multiprocessing
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import common
import numpy as np
import torch

from torch_polylap.batch import PolygonMeshes, per_mesh_mean
from torch_polylap.losses import laplacian_smoothing
from torch_polylap.shapes import quad_sphere

# the plain-torch baseline builds a torch sparse matrix: silence torch's "beta" notices
warnings.filterwarnings("ignore", message="Sparse (CSR tensor support|invariant checks)")

MIN_SAMPLE_SECONDS = 0.05


# ----------------------------------------------------------------------------- meshes


def sphere_resolution(faces: int) -> int:
    return max(2, round(np.sqrt(faces / 6)))


def triangulate(quads: np.ndarray) -> np.ndarray:
    """Two triangles ``(0, 1, 2), (0, 2, 3)`` per quad, same orientation."""
    return np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])


def make_case(name: str, sizes: list[int], noise: float, dtype: torch.dtype) -> dict:
    # cube spheres of 6 n^2 quads, radially perturbed (every quad non-planar), one seed each
    meshes = [
        quad_sphere(sphere_resolution(f), noise=noise, seed=seed, dtype=dtype)
        for seed, f in enumerate(sizes)
    ]
    verts = [v for v, _ in meshes]
    quads = [f for _, f in meshes]
    tris = [torch.from_numpy(triangulate(f.numpy())) for _, f in meshes]
    return {"name": name, "verts": verts, "quads": quads, "tris": tris}


# ----------------------------------------------------------------------------- baselines


def directed_edges(tris: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(rows, cols)``, each ``(6 T,)``: both directions of the edge opposite every corner."""
    i = torch.cat([tris[:, (c + 1) % 3] for c in range(3)])
    j = torch.cat([tris[:, (c + 2) % 3] for c in range(3)])
    return torch.cat([i, j]), torch.cat([j, i])


def csr_pattern(tris: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(crow, col, slot)``: the coalesced CSR pattern of the cotan matrix and the slot of each
    directed entry of :func:`directed_edges` in it, computed once per connectivity."""
    rows, cols = directed_edges(tris)
    keys, slot = torch.unique(rows * n + cols, return_inverse=True)
    crow = torch.zeros(n + 1, dtype=torch.int64)
    torch.cumsum(torch.bincount(keys // n, minlength=n), 0, out=crow[1:])
    return crow, keys % n, slot


def cotan_smoothing(
    verts: torch.Tensor,
    tris: torch.Tensor,
    mesh_idx: torch.Tensor,
    num_meshes: int,
    frozen: bool,
    pattern: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """pytorch3d's "cot" smoothing in plain torch: per vertex ``|sum_q w_pq X_q / sum_q w_pq -
    X_p|``, ``w = (cot a + cot b) / 2``, mean per mesh, mean over the batch.

    Args:
        verts: ``(V, 3)`` packed positions; tris: ``(T, 3)`` packed triangles;
        mesh_idx: ``(V,)`` mesh of each vertex; frozen: weights under ``no_grad``, product with
            a torch CSR matrix (coalesced every call, or scattered onto ``pattern`` from
            :func:`csr_pattern` when given); live: gather + ``index_add`` (O(nnz) backward).
    """
    n = verts.shape[0]
    rows, cols = directed_edges(tris)
    with torch.set_grad_enabled(torch.is_grad_enabled() and not frozen):
        x = verts[tris]  # (T, 3, 3)
        cots = []
        for c in range(3):
            u = x[:, (c + 1) % 3] - x[:, c]
            v = x[:, (c + 2) % 3] - x[:, c]
            cots.append((u * v).sum(1) / torch.linalg.vector_norm(torch.cross(u, v, dim=1), dim=1))
        w = 0.5 * torch.cat(cots)
        w = torch.cat([w, w])
        rowsum = verts.new_zeros(n).index_add(0, rows, w)
        inv = torch.where(rowsum > 0, 1.0 / rowsum, torch.zeros_like(rowsum))
    if frozen and pattern is not None:
        crow, col, slot = pattern
        values = verts.new_zeros(col.numel()).index_add(0, slot, w)
        wx = torch.sparse_csr_tensor(crow, col, values, (n, n)) @ verts
    elif frozen:
        W = torch.sparse_coo_tensor(torch.stack([rows, cols]), w, (n, n))
        wx = W.coalesce().to_sparse_csr() @ verts
    else:
        wx = verts.new_zeros(n, 3).index_add(0, rows, w[:, None] * verts[cols])
    per_vertex = torch.linalg.vector_norm(wx * inv[:, None] - verts, dim=1)
    return per_mesh_mean(per_vertex, mesh_idx, num_meshes).mean()


def pytorch3d_available() -> bool:
    try:
        import pytorch3d.loss  # noqa: F401
    except ImportError:
        return False
    return True


# ----------------------------------------------------------------------------- steps


def build_steps(case: dict, baseline: str) -> dict[str, Callable[[], None]]:
    """Forward + backward closures; connectivity prepared once, outside the closures."""
    quad_batch = PolygonMeshes(case["verts"], case["quads"])
    tri_batch = PolygonMeshes(case["verts"], case["tris"])
    quad_batch.topology()
    tri_batch.topology()
    X = quad_batch.verts_packed().detach()
    tris_packed = tri_batch.faces_packed().as_uniform()
    mesh_idx = tri_batch.verts_packed_to_mesh_idx()
    B = len(quad_batch)

    def ours(batch: PolygonMeshes, frozen: bool) -> Callable[[], None]:
        def step() -> None:
            x = X.clone().requires_grad_(True)
            laplacian_smoothing(batch.update_packed(x), "polygon", frozen_weights=frozen).backward()

        return step

    pattern = csr_pattern(tris_packed, X.shape[0])

    def reference(frozen: bool, cached: bool = False) -> Callable[[], None]:
        def step() -> None:
            x = X.clone().requires_grad_(True)
            pat = pattern if cached else None
            cotan_smoothing(x, tris_packed, mesh_idx, B, frozen, pat).backward()

        return step

    steps = {
        "ours quads live": ours(quad_batch, False),
        "ours quads frozen": ours(quad_batch, True),
        "ours tris live": ours(tri_batch, False),
        "ours tris frozen": ours(tri_batch, True),
    }
    if baseline == "pytorch3d":
        from pytorch3d.loss import mesh_laplacian_smoothing
        from pytorch3d.structures import Meshes

        def p3d() -> None:
            x = X.clone().requires_grad_(True)
            meshes = Meshes(
                list(torch.split(x, tri_batch.num_verts_per_mesh().tolist())), case["tris"]
            )
            mesh_laplacian_smoothing(meshes, method="cot").backward()

        steps["pytorch3d cot frozen"] = p3d
    else:
        steps["torch cot live"] = reference(False)
        steps["torch cot frozen"] = reference(True)
        steps["torch cot frozen, cached pattern"] = reference(True, cached=True)
    return steps


def median_time(fn: Callable[[], None], repeat: int) -> float:
    """Median seconds per call over ``repeat`` samples after a warm-up, calls batched until a
    sample lasts :data:`MIN_SAMPLE_SECONDS` (``common.median_time``)."""
    return common.median_time(fn, repeat, min_sample_s=MIN_SAMPLE_SECONDS)


def memory_child(
    sizes: list[int], noise: float, dtype_name: str, baseline: str, threads: int
) -> dict:
    """Peak RSS growth of each step, in a fresh process, after the setup.

    Every step runs once first (lazy caches such as the Laplacian's diagonal positions are
    then filled, as in a training loop after its first iteration).  Before each measured step
    the heap is trimmed and the kernel's peak counter reset, so the peak is measured from the
    resident memory left by the setup and the warm-up.
    """
    if threads:
        torch.set_num_threads(threads)  # a fresh process: its count for good
    case = make_case("memory", sizes, noise, getattr(torch, dtype_name))
    steps = build_steps(case, baseline)
    for step in steps.values():
        step()
    out = {}
    for name, step in steps.items():
        growth = common.peak_rss_growth(step)
        out[name] = {"method": growth["method"], "delta_bytes": growth["rss_delta_bytes"]}
    return out


def measure_memory(sizes, noise, dtype, baseline, threads) -> dict:
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
        name = str(dtype).removeprefix("torch.")
        return pool.submit(memory_child, sizes, noise, name, baseline, threads).result()


# ----------------------------------------------------------------------------- report


def progress(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def check_agreement(case: dict) -> dict:
    """Ours on triangles vs the plain cotan loss (the same formula where cotan row sums are > 0),
    in float64; the two frozen reference variants must agree with each other too."""
    tri_batch = PolygonMeshes([v.double() for v in case["verts"]], case["tris"])
    X = tri_batch.verts_packed()
    tris = tri_batch.faces_packed().as_uniform()
    idx = tri_batch.verts_packed_to_mesh_idx()
    B = len(tri_batch)
    ours = float(laplacian_smoothing(tri_batch, "polygon"))
    ref = float(cotan_smoothing(X, tris, idx, B, frozen=True))
    cached = float(cotan_smoothing(X, tris, idx, B, True, csr_pattern(tris, X.shape[0])))
    live = float(cotan_smoothing(X, tris, idx, B, frozen=False))
    return {
        "ours_on_tris": ours,
        "cotan_reference": ref,
        "relative_difference": abs(ours - ref) / ref,
        "reference_variants_spread": (max(ref, cached, live) - min(ref, cached, live)) / ref,
    }


def run(args: argparse.Namespace) -> dict:
    dtype = getattr(torch, args.dtype)
    baseline = "pytorch3d" if pytorch3d_available() else "torch"
    rng = np.random.default_rng(0)
    # heterogeneous batch: sizes within +-20% of --faces
    batch_sizes = [int(args.faces * s) for s in rng.uniform(0.8, 1.2, args.batch)]
    specs = [(f"batch {args.batch} x ~{args.faces} quads", batch_sizes)] if args.batch else []
    if args.big_faces:
        specs.append((f"one mesh of ~{args.big_faces} quads", [args.big_faces]))
    results = []
    for name, sizes in specs:
        progress(f"{name}: generating")
        case = make_case(name, sizes, args.noise, dtype)
        start = time.perf_counter()
        PolygonMeshes(case["verts"], case["quads"]).topology()
        topo_seconds = time.perf_counter() - start
        steps = build_steps(case, baseline)
        times = {}
        for step_name, fn in steps.items():
            progress(f"{name}: {step_name}")
            times[step_name] = median_time(fn, args.repeat)
        memory = {}
        if args.memory:
            progress(f"{name}: peak memory (fresh process)")
            memory = measure_memory(sizes, args.noise, dtype, baseline, args.threads)
        results.append(
            {
                "name": name,
                "num_meshes": len(sizes),
                "num_quads": int(sum(len(f) for f in case["quads"])),
                "num_verts": int(sum(len(v) for v in case["verts"])),
                "topology_seconds": topo_seconds,
                "seconds": times,
                "memory": memory,
                "check": check_agreement(case) if len(sizes) <= 64 else None,
            }
        )
        del case, steps
        gc.collect()
    return {"baseline": baseline, "cases": results}


def report(env: dict, data: dict) -> str:
    # the strongest baseline of the run: its sparsity pattern is built once, like ours
    base = (
        "pytorch3d cot frozen"
        if data["baseline"] == "pytorch3d"
        else "torch cot frozen, cached pattern"
    )
    out = [
        f"{env['threads']} threads, {env['dtype']}; median of {env['repeat']}; "
        f"baseline: {data['baseline']} (on the triangulated meshes)"
    ]
    data["tables"] = {}
    for case in data["cases"]:
        out.append(
            f"\n#### {case['name']}: {case['num_quads']:,} quads, {case['num_verts']:,} vertices "
            f"(topology built once: {case['topology_seconds'] * 1e3:.0f} ms)\n"
        )
        rows = []
        for step, seconds in case["seconds"].items():
            mem = case["memory"].get(step)
            mb = (
                f"{mem['delta_bytes'] / 2**20:.0f}"
                if mem and mem["delta_bytes"] is not None
                else "-"
            )
            rows.append(
                [step, f"{seconds * 1e3:.1f}", f"{seconds / case['seconds'][base]:.2f}", mb]
            )
        header = ["fwd+bwd", "ms", f"/ {base}", "peak MB"]
        out.append(common.markdown_table(header, rows))
        key = "batch" if case["name"].startswith("batch") else "big"
        data["tables"][key] = common.table_data(header, rows)
        if case["check"]:
            c = case["check"]
            out.append(
                f"\nCheck (float64): ours on triangles {c['ours_on_tris']:.6g}, cotan reference "
                f"{c['cotan_reference']:.6g}, relative difference {c['relative_difference']:.1e} "
                f"(reference variants agree to {c['reference_variants_spread']:.1e})."
            )
    return "\n".join(out)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--batch", type=int, default=64, help="meshes in the batch; 0 skips the batch (default 64)"
    )
    p.add_argument("--faces", type=int, default=5000, help="faces per batch mesh (default 5000)")
    p.add_argument(
        "--big-faces",
        type=int,
        default=1_000_000,
        help="faces of the single large mesh; 0 skips it (default 1M)",
    )
    p.add_argument("--noise", type=float, default=0.01, help="radial noise (default 0.01)")
    p.add_argument("--repeat", type=int, default=3, help="timed samples (default 3)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    common.add_switch(p, "--memory", "peak memory per step in fresh processes (default on)")
    p.add_argument("--threads", type=int, default=0, help="torch threads; 0 keeps torch's default")
    p.add_argument("--json", type=Path, help=f"default {common.RESULTS / 'losses.json'}")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with common.pinned_threads(args.threads or torch.get_num_threads()):
        return _main(args)


def _main(args: argparse.Namespace) -> int:
    meta = common.run_meta()
    env = {"threads": torch.get_num_threads(), "dtype": args.dtype, "repeat": args.repeat}
    start = time.perf_counter()
    data = run(args)
    env["total_seconds"] = time.perf_counter() - start
    print(report(env, data))
    common.write_results("losses", {"environment": env, **data}, meta=meta, path=args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
