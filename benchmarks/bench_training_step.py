"""A training step as PyTorch users write it, eager against torch.compile, and batches.

Step: ``L, M0 = lap(X, faces)``, a smoothing-and-spectral loss, ``loss.backward()`` (the
optimizer step is left out: torch's optimizers break the graph themselves). Meshes are the
benchmark grid (``common.bench_grid``) of about 10k, 100k and 1M faces, lightly perturbed.

* eager vs ``torch.compile(fullgraph=True)`` (inductor): the compiled step's first call (trace
  and compile, on a cold topology cache) and the steady state, timed interleaved (eager,
  compiled, eager, ...) in one process, medians; peak memory growth of one step of each.
* a fixed-topology batch ``(B, V, 3)`` against ``B`` single-mesh steps in a loop (eager),
  interleaved, medians.

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
    args = parser.parse_args()
    global DEVICE
    DEVICE = torch.device(args.device)
    torch._dynamo.config.trace_autograd_ops = True  # backward() inside the compiled graph
    meta = common.run_meta(threads=args.threads)
    with common.pinned_threads(args.threads):
        steps = [eager_vs_compiled(n, args.repeats) for n in args.sizes]
        batches = [batch_vs_loop(n, args.batch, args.repeats) for n in args.batch_sizes]
    result = {"eager_vs_compiled": steps, "batch_vs_loop": batches}
    result["tables"] = tables(steps, batches)
    for t in result["tables"].values():
        print(common.markdown_table(t["columns"], t["rows"]), "\n")
    common.write_results("training_step", result, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
