"""A training step as PyTorch users write it, eager against torch.compile, and batches.

Step: ``L, M0 = lap(X, faces)``, a smoothing-and-spectral loss, ``loss.backward()`` (the
optimizer step is left out: torch's optimizers break the graph themselves). Meshes are the
benchmark grid (``common.bench_grid``) of about 10k, 100k and 1M faces, lightly perturbed.

* eager vs ``torch.compile(fullgraph=True)`` (inductor): the compiled step's first call (trace
  and compile, on a cold topology cache) and the steady state, timed interleaved (eager,
  compiled, eager, ...) in one process, medians; peak memory growth of one step of each.
* a fixed-topology batch ``(B, V, 3)`` against ``B`` single-mesh steps in a loop (eager),
  interleaved, medians.
* a dataset (``--dataset N``): one step function compiled once and run over ``N`` quad grids
  of different sizes (100 to 2,000 faces), the operators built inside from an ``(F, 4)``
  faces tensor and ``torch.autograd.grad`` of the loss: graphs compiled (torch.compile's own
  count), the first call, the first (compiling) epoch and warm epochs against eager ones,
  interleaved, and the largest gradient difference from eager. ``--dataset-only`` skips the
  rest; ``--backend aot_eager`` leaves inductor's C++ compiler out.

``python benchmarks/bench_training_step.py [--sizes 10000 100000 1000000] [--batch 8]
[--repeats 5]`` writes ``benchmarks/results/training_step.json`` (or ``--json PATH``). One thread
(``--threads``).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path

import common
import torch

import torch_polylap as tp

DEVICE = torch.device("cpu")


def _grid(faces: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    n = max(2, round(math.sqrt(faces)))
    return common.bench_grid(n, noise=0.02 / n, seed=seed, device=DEVICE)


def _step_fn(lap: tp.PolygonLaplacian, X: torch.Tensor, faces: torch.Tensor):
    def step() -> torch.Tensor:
        L, M0 = lap(X, faces)
        Y = L @ X
        loss = (Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ X).square().sum()
        loss.backward()
        return loss.detach()

    return step


def _clock(fn) -> float:
    sync = torch.cuda.synchronize if DEVICE.type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - start


def eager_vs_compiled(faces: int, repeats: int) -> dict:
    torch._dynamo.reset()  # each size compiles anew, from a static trace
    verts, quads = _grid(faces)
    X_e = verts.clone().requires_grad_(True)
    X_c = verts.clone().requires_grad_(True)
    eager = _step_fn(tp.PolygonLaplacian(), X_e, quads)
    compiled = torch.compile(_step_fn(tp.PolygonLaplacian(), X_c, quads), fullgraph=True)
    tp.topology.clear_topology_cache()  # the compiled step meets the mesh first: cold cache
    compile_s = _clock(compiled)
    eager()  # warm the eager path as well (topology built once)
    times_e, times_c = [], []
    for _ in range(repeats):
        X_e.grad = X_c.grad = None
        times_e.append(_clock(eager))
        X_e.grad = X_c.grad = None
        times_c.append(_clock(compiled))
    X_e.grad = X_c.grad = None
    le, lc = eager(), compiled()
    mem_e = common.peak_rss_growth(eager)["rss_delta_bytes"]
    mem_c = common.peak_rss_growth(compiled)["rss_delta_bytes"]
    te, tc = statistics.median(times_e), statistics.median(times_c)
    return {
        "faces": quads.shape[0],
        "verts": verts.shape[0],
        "eager_s": te,
        "compiled_s": tc,
        "compiled_over_eager": tc / te,
        "compile_first_call_s": compile_s,
        "loss_rel_diff": float(((le - lc).abs() / le.abs()).item()),
        "peak_growth_eager_mb": mem_e / 2**20 if mem_e is not None else None,
        "peak_growth_compiled_mb": mem_c / 2**20 if mem_c is not None else None,
    }


def batch_vs_loop(faces: int, batch: int, repeats: int) -> dict:
    verts, quads = _grid(faces)
    g = torch.Generator().manual_seed(1)
    noise = torch.randn((batch, *verts.shape), generator=g, dtype=verts.dtype).to(DEVICE)
    Vs = verts[None] + 1e-3 * noise
    Vs.requires_grad_(True)
    lap = tp.PolygonLaplacian()

    def batched() -> None:
        L, M0 = lap(Vs, quads)
        Y = L @ Vs
        ((Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ Vs).square().sum()).backward()

    def loop() -> None:
        for b in range(batch):
            X = Vs[b]
            L, M0 = lap(X, quads)
            Y = L @ X
            ((Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ X).square().sum()).backward()

    batched(), loop()
    times_b, times_l = [], []
    for _ in range(repeats):
        Vs.grad = None
        times_b.append(_clock(batched))
        Vs.grad = None
        times_l.append(_clock(loop))
    tb, tl = statistics.median(times_b), statistics.median(times_l)
    return {
        "faces": quads.shape[0],
        "batch": batch,
        "batched_s": tb,
        "loop_s": tl,
        "batched_over_loop": tb / tl,
    }


def _dataset_step(X: torch.Tensor, faces: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    L, M0 = tp.laplacian(X, faces)
    Y = L @ X
    loss = (Y * (M0 @ Y)).sum() + ((M0 + 0.1 * L) @ X).square().sum()
    (g,) = torch.autograd.grad(loss, X)
    return loss.detach(), g


def dataset_epochs(count: int, backend: str, dynamic: bool | None, repeats: int) -> dict:
    """One compiled step over ``count`` meshes of different sizes against the eager step."""
    from torch._dynamo.utils import counters

    sizes = [round(100 * 20 ** (i / max(count - 1, 1))) for i in range(count)]
    meshes = [_grid(f, seed=i) for i, f in enumerate(sizes)]
    torch._dynamo.reset()
    counters.clear()
    compiled = torch.compile(_dataset_step, backend=backend, dynamic=dynamic, fullgraph=True)

    def epoch(fn) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return [fn(v.clone().requires_grad_(True), f) for v, f in meshes]

    first_call_s = _clock(lambda: compiled(meshes[0][0].clone().requires_grad_(True), meshes[0][1]))
    first_epoch_s = _clock(lambda: epoch(compiled))
    graphs = int(counters["stats"]["unique_graphs"])
    epoch(_dataset_step)  # the eager path's topologies built, as the compiled one's are
    times_e, times_c = [], []
    for _ in range(repeats):
        times_e.append(_clock(lambda: epoch(_dataset_step)))
        times_c.append(_clock(lambda: epoch(compiled)))
    diff = max(
        float(((gc - ge).abs().max() / ge.abs().max()).item())
        for (_, gc), (_, ge) in zip(epoch(compiled), epoch(_dataset_step), strict=True)
    )
    te, tc = statistics.median(times_e), statistics.median(times_c)
    return {
        "meshes": count,
        "faces": [int(f.shape[0]) for _, f in meshes],
        "backend": backend,
        "dynamic": dynamic,
        "graphs_compiled": graphs,
        "first_call_s": first_call_s,
        "first_epoch_s": first_epoch_s,
        "eager_epoch_s": te,
        "compiled_epoch_s": tc,
        "compiled_over_eager": tc / te,
        "grad_max_rel_diff": diff,
    }


def _attempt(fn, count: int, backend: str, dynamic: bool | None, repeats: int) -> dict:
    """``fn(...)``'s row, or the error that stopped it (a peer version that cannot compile)."""
    try:
        return fn(count, backend, dynamic, repeats)
    except Exception as err:  # noqa: BLE001  (recorded in the results, not hidden)
        message = str(err).strip().splitlines()
        return {"meshes": count, "backend": backend, "dynamic": dynamic, "error": message[:3]}


def dataset_table(rows: list[dict]) -> dict:
    header = ["meshes", "backend", "dynamic", "graphs compiled", "first call"]
    header += ["first epoch", "warm epoch eager / compiled", "compiled / eager", "grad diff"]
    body = [
        [
            str(r["meshes"]),
            r["backend"],
            str(r["dynamic"]),
            str(r["graphs_compiled"]),
            f"{r['first_call_s']:.1f} s",
            f"{r['first_epoch_s']:.1f} s",
            f"{r['eager_epoch_s'] * 1e3:.0f} / {r['compiled_epoch_s'] * 1e3:.0f} ms",
            f"{r['compiled_over_eager']:.2f}x",
            f"{r['grad_max_rel_diff']:.1e}",
        ]
        if "error" not in r
        else [str(r["meshes"]), r["backend"], str(r["dynamic"]), "error: " + r["error"][-1]]
        + ["-"] * 5
        for r in rows
    ]
    return common.table_data(header, body)


def tables(steps: list[dict], batches: list[dict]) -> dict:
    """The two tables of the README, from the measurements."""

    def mb(x: float | None) -> str:
        return "-" if x is None else f"{x:.0f}"

    header = ["faces", "eager step", "compiled step", "compiled / eager"]
    header += ["first compiled call", "peak memory growth eager / compiled (MB)"]
    body = [
        [
            f"{s['faces']:,}",
            f"{s['eager_s'] * 1e3:.0f} ms",
            f"{s['compiled_s'] * 1e3:.0f} ms",
            f"{s['compiled_over_eager']:.2f}x",
            f"{s['compile_first_call_s']:.0f} s",
            f"{mb(s['peak_growth_eager_mb'])} / {mb(s['peak_growth_compiled_mb'])}",
        ]
        for s in steps
    ]
    bheader = ["faces per mesh", "batch", "batched", "loop of single meshes", "batch / loop"]
    bbody = [
        [
            f"{b['faces']:,}",
            str(b["batch"]),
            f"{b['batched_s'] * 1e3:.0f} ms",
            f"{b['loop_s'] * 1e3:.0f} ms",
            f"{b['batched_over_loop']:.2f}x",
        ]
        for b in batches
    ]
    return {"compile": common.table_data(header, body), "batch": common.table_data(bheader, bbody)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1_000, 10_000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, help="default benchmarks/results/training_step.json")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dataset", type=int, default=0, help="meshes in the dataset case")
    parser.add_argument("--dataset-only", action="store_true")
    parser.add_argument("--backend", default="inductor", help="the dataset case's backend")
    args = parser.parse_args()
    global DEVICE
    DEVICE = torch.device(args.device)
    torch._dynamo.config.trace_autograd_ops = True  # backward() inside the compiled graph
    meta = common.run_meta(threads=args.threads)
    if args.dataset_only:
        with common.pinned_threads(args.threads):
            rows = [
                _attempt(dataset_epochs, args.dataset, args.backend, dynamic, args.repeats)
                for dynamic in (None, True)
            ]
        result = {"dataset": rows, "tables": {"dataset": dataset_table(rows)}}
        print(common.markdown_table(*result["tables"]["dataset"].values()))
        common.write_results("training_dataset", result, meta=meta, path=args.json)
        return
    with common.pinned_threads(args.threads):
        steps = [eager_vs_compiled(n, args.repeats) for n in args.sizes]
        batches = [batch_vs_loop(n, args.batch, args.repeats) for n in args.batch_sizes]
        rows = [dataset_epochs(args.dataset, args.backend, None, args.repeats)] * (args.dataset > 0)
    result = {"eager_vs_compiled": steps, "batch_vs_loop": batches, "dataset": rows}
    result["tables"] = tables(steps, batches)
    if rows:
        result["tables"]["dataset"] = dataset_table(rows)
    for t in result["tables"].values():
        print(common.markdown_table(t["columns"], t["rows"]), "\n")
    common.write_results("training_step", result, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
