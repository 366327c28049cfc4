"""Planarization (AW11 sec. 5.3) against Shape-Up: libigl's and a vectorized one, at equal
iteration budgets and at equal time.

    python benchmarks/bench_planarize.py [--meshes NAME ...] [--tol 1e-4]
        [--budgets 1 5 10 50 200] [--positions-solve] [--igl-python /work/igl241/bin/python]
        [--igl-max-seconds 120] [--igl-max-vertices 10000] [--json PATH]

Meshes: every pure-quad mesh of ``../shared/data/meshes/real`` (found by reading them all) and
generated architectural quad grids (a hyperbolic paraboloid over its rulings, a freeform roof,
a perturbed cube-sphere dome); ``--meshes`` picks some by name, and a real mesh named there is
taken whatever its degrees (``lion_vase_poly.off``, hexagon-dominant). Contenders, one thread
each:

* ours: ``torch_polylap.apps.planarize`` with its defaults (Gauss-Newton on the face-plane
  residuals) and with ``method="lbfgs"`` (the paper's descent of ``E_plan``, 60 s at most);
* with ``--positions-solve``: the same Gauss-Newton iterations with each step solved in the
  free vertex coordinates (CHOLMOD on ``C^T C + D``, three rows per vertex), as the default did
  before it solved them in the faces' plane conditions: the old default's linear algebra;
* Shape-Up, vectorized (``shapeup.py`` beside this script): the same local projection and
  prefactored global step as libigl, without its per-face loop; run until it reaches ``tol``,
  for 100,000 iterations, or for ``max(30 s, 10x ours)`` but at most ``--su-max-seconds``
  (300);
* libigl's ``igl.planarize_quad_mesh`` (Shape-Up as in libigl 2.4.1; the function left the
  Python bindings after 2.4.1, so it runs in a separate interpreter, ``--igl-python``, on
  ``.npz`` files and is timed inside that process), at each iteration budget with
  ``threshold = 0``; skipped where its time predicted from the first budget exceeds
  ``--igl-max-seconds`` (120), on meshes of more than ``--igl-max-vertices`` (10,000) and on
  meshes that are not pure quads: its
  iterations cost ``O(V F)`` (a selector matrix of the full width per face). Its output is
  compared with the vectorized Shape-Up's after the same iterations (positions, after removing
  the translation of every connected part, which libigl leaves to round-off: its system matrix
  is singular).

Every result is measured with :func:`torch_polylap.face_nonplanarity` (largest corner distance
from the plane of the face's maximal projection, over the face diameter). Shape change: the
displacement over the bounding-box diagonal and the relative change of the total face area
(:func:`torch_polylap.face_areas`). "At equal time" is the largest non-planarity Shape-Up had
reached when ours had converged (its setup, the factorization, counted; its non-planarity checks
not). Prints Markdown tables; ``--json`` (default ``benchmarks/results/planarize.json``) writes
the numbers.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch
from common import markdown_table, run_meta, table_data, write_results
from shapeup import ShapeUp

import torch_polylap as tp
from torch_polylap.apps import PlanarizeOptions, planarize
from torch_polylap.linalg.factor import CholeskyFactorization

GN = importlib.import_module("torch_polylap.apps.planarize")

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "real"
SHAPEUP = """
import sys, time
import numpy as np, igl
d = np.load(sys.argv[1])
V = np.ascontiguousarray(d["V"], dtype=np.float64)
F = np.ascontiguousarray(d["F"], dtype=np.int64)
start = time.perf_counter()
out = igl.planarize_quad_mesh(V, F, int(d["max_iter"]), 0.0)
seconds = time.perf_counter() - start
np.savez(sys.argv[2], V=np.asarray(out, dtype=np.float64), seconds=seconds)
"""


def hypar(n: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    """``z = x y / 2`` over ``[-1, 1]^2``, the grid along its rulings: every quad is skew."""
    return tp.shapes.quad_grid(n, extent=(-1.0, 1.0, -1.0, 1.0), height=lambda x, y: 0.5 * x * y)


def roof(n: int = 120, m: int = 80) -> tuple[torch.Tensor, torch.Tensor]:
    """A freeform roof: a jittered grid under a two-wave height field."""

    def height(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return 0.3 * torch.sin(math.pi * x) * torch.cos(0.5 * math.pi * y) + 0.1 * x * y

    return tp.shapes.quad_grid(n, m, extent=(0.0, 3.0, 0.0, 2.0), height=height, seed=1, jitter=0.2)


def dome(n: int = 24) -> tuple[torch.Tensor, torch.Tensor]:
    """The upper half of a cube sphere with radial noise: a closed-ring dome of quads."""
    V, F = tp.shapes.quad_sphere(n, noise=0.01, seed=2)
    keep = (V[F][:, :, 2] > -1e-9).all(1)
    F = F[keep]
    used = torch.unique(F)
    remap = torch.full((V.shape[0],), -1, dtype=torch.int64)
    remap[used] = torch.arange(used.numel())
    return V[used], remap[F]


GENERATED: dict[str, Callable[[], tuple[torch.Tensor, torch.Tensor]]] = {
    "hypar 40x40": hypar,
    "roof 120x80": roof,
    "dome 24": dome,
    "roof 300x200": lambda: roof(300, 200),
}


Mesh = tuple[str, torch.Tensor, Any]  # faces: (F, 4) quads, or polygons of mixed degrees


def load_meshes(names: list[str] | None, real: Path) -> list[Mesh]:
    meshes = []
    if real.exists():
        for path in sorted(real.iterdir()):
            if path.suffix not in (".obj", ".off", ".ply") or (names and path.name not in names):
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                V, faces = tp.read_mesh(path)
            F = faces.as_uniform()
            if F is not None and F.shape[1] == 4:
                meshes.append((path.name, V.double(), F))
            elif names:
                meshes.append((path.name, V.double(), faces))
    else:
        print(f"{real} missing: real meshes skipped", file=sys.stderr)
    for name, make in GENERATED.items():
        if not names or name in names:
            V, F = make()
            meshes.append((name, V.double(), F))
    return meshes


def shape(V: torch.Tensor, V0: torch.Tensor, F: Any) -> dict:
    n = tp.face_nonplanarity(V, F)
    diag = float((V0.amax(0) - V0.amin(0)).norm())
    disp = (V - V0).norm(dim=1) / diag
    area0 = float(tp.face_areas(V0, F).sum())
    return {
        "nonplanarity_max": float(n.max()),
        "nonplanarity_mean": float(n.mean()),
        "displacement_max": float(disp.max()),
        "displacement_mean": float(disp.mean()),
        "area_change": float(tp.face_areas(V, F).sum()) / area0 - 1.0,
    }


def libigl(python: str, V: torch.Tensor, F: torch.Tensor, iters: int) -> tuple[np.ndarray, float]:
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, V=V.numpy(), F=F.numpy(), max_iter=iters)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run(
            [python, "-c", SHAPEUP, str(src), str(dst)],
            check=True,
            env=env,
            stderr=subprocess.DEVNULL,  # libigl prints one line per iteration
        )
        out = np.load(dst)
        return np.asarray(out["V"]), float(out["seconds"])


def part_demeaned(X: np.ndarray, part: np.ndarray) -> np.ndarray:
    count = np.bincount(part)
    mean = np.stack([np.bincount(part, X[:, c]) for c in range(3)], axis=1) / count[:, None]
    return X - mean[part]


def positions_step(C: sp.csr_matrix, c: np.ndarray, g0: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The Gauss-Newton step solved in the free vertex coordinates, ``(C^T C + D) dx = -(C^T c
    + g0)``: the matrix the old default factored (its per-face Schur complements sum to
    ``C^T C``), three rows per vertex."""
    H = (C.T @ C + sp.diags(d)).tocsr()
    rhs = torch.from_numpy(C.T @ c + g0)[:, None]
    return -CholeskyFactorization(H, check=False).solve(rhs)[:, 0].numpy()


@contextmanager
def solved_in_positions() -> Iterator[None]:
    original = GN._damped_step
    GN._damped_step = positions_step
    try:
        yield
    finally:
        GN._damped_step = original


def run_ours(V: torch.Tensor, F: Any, tol: float, max_iter: int | None = None, **kw: Any) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # stopping above tol is reported in the table
        start = time.perf_counter()
        method = kw.pop("method", "gauss-newton")
        options = PlanarizeOptions(**kw)
        res = planarize(V, F, tol=tol, max_iter=max_iter, method=method, options=options)
        seconds = time.perf_counter() - start
    return shape(res.verts, V, F) | {
        "seconds": seconds,
        "iterations": res.iterations,
        "converged": res.converged,
    }


def at_time(trace_seconds: list[float], trace_np: list[float], before: float, t: float) -> tuple:
    """Shape-Up's largest non-planarity and iterations done by time ``t``."""
    done = int(np.searchsorted(np.asarray(trace_seconds), t, side="right"))
    return (trace_np[done - 1] if done else before), done


def bench_mesh(name: str, V: torch.Tensor, F: Any, args: argparse.Namespace) -> dict:
    quads = isinstance(F, torch.Tensor)
    topo = tp.get_topology(F, V.shape[0])
    groups = [g.corners_t.t().numpy() for g in topo.groups]
    nf = sum(g.shape[0] for g in groups)
    print(f"{name}: {V.shape[0]} vertices, {nf} faces", file=sys.stderr)
    before = shape(V, V, F)
    rec: dict = {"mesh": name, "V": V.shape[0], "F": nf, "before": before}
    rec["ours"] = gn = run_ours(V, F, args.tol)
    if args.positions_solve:
        with solved_in_positions():
            rec["positions_solve"] = run_ours(V, F, args.tol)
    rec["lbfgs"] = run_ours(V, F, args.tol, method="lbfgs", max_iter=100000, time_limit=60.0)

    su = ShapeUp(V.numpy(), groups)
    limit = min(max(30.0, 10 * gn["seconds"]), args.su_max_seconds)
    trace = su.run(args.su_max_iter, tol=args.tol, time_limit=limit, faces=F)
    reached = trace.nonplanarity[-1] if trace.iterations else before["nonplanarity_max"]
    rec["shapeup"] = shape(torch.from_numpy(trace.verts), V, F) | {
        "setup_seconds": trace.setup_seconds,
        "iterations": trace.iterations,
        "seconds": trace.seconds[-1] if trace.iterations else trace.setup_seconds,
        "converged": reached < args.tol,
    }
    np_eq, it_eq = at_time(
        trace.seconds, trace.nonplanarity, before["nonplanarity_max"], gn["seconds"]
    )
    rec["equal_time"] = {
        "seconds": gn["seconds"],
        "shapeup_iterations": it_eq,
        "shapeup_nonplanarity_max": np_eq,
        "ratio": np_eq / gn["nonplanarity_max"],
    }

    rec["budgets"] = []
    igl_per_iter = None
    for b in args.budgets:
        row: dict = {"budget": b}
        row["ours"] = (
            gn if b >= gn["iterations"] else run_ours(V, F, args.tol, max_iter=b, warn=False)
        )
        if b <= trace.iterations:
            row["shapeup"] = {
                "nonplanarity_max": trace.nonplanarity[b - 1],
                "seconds": trace.seconds[b - 1],
            }
        if (
            have_igl(args)
            and quads
            and V.shape[0] <= args.igl_max_vertices
            and (igl_per_iter is None or igl_per_iter * b <= args.igl_max_seconds)
        ):
            print(f"{name}: libigl Shape-Up, {b} iterations ...", file=sys.stderr)
            Vi, secs = libigl(args.igl_python, V, F, b)
            igl_per_iter = secs / b
            diag = float((V.amax(0) - V.amin(0)).norm())
            vec = su.run(b).verts
            row["libigl"] = {
                "nonplanarity_max": float(tp.face_nonplanarity(torch.from_numpy(Vi), F).max()),
                "seconds": secs,
                "vectorized_difference": float(
                    np.abs(part_demeaned(Vi, su.part) - part_demeaned(vec, su.part)).max() / diag
                ),
            }
        rec["budgets"].append(row)
    return rec


def have_igl(args: argparse.Namespace) -> bool:
    return Path(args.igl_python).exists()


def e(x: float) -> str:
    return f"{x:.2e}"


def report(records: list[dict], tol: float) -> dict:
    """Print the tables and return them for the results: ``tolerance`` (``large`` with
    ``--positions-solve``, :func:`large_table`) and ``budgets``."""
    print(f"\nTo max non-planarity {tol:g}, one thread each:\n")
    positions = all("positions_solve" in r for r in records)
    body = []
    for r in records:
        b, o, lb, s = r["before"], r["ours"], r["lbfgs"], r["shapeup"]
        eq = r["equal_time"]
        su_time = f"{s['seconds']:.2f}" + ("" if s["converged"] else " (not reached)")
        body.append(
            [
                r["mesh"],
                r["V"],
                e(b["nonplanarity_max"]),
                f"{o['iterations']}, {o['seconds']:.2f}",
                e(o["nonplanarity_max"]),
                f"{o['displacement_max']:.2e} / {o['area_change']:+.2%}",
                f"{lb['iterations']}, {lb['seconds']:.2f}, {e(lb['nonplanarity_max'])}",
                f"{s['iterations']}, {su_time}, {e(s['nonplanarity_max'])}",
                f"{s['displacement_max']:.2e} / {s['area_change']:+.2%}",
                f"{eq['shapeup_iterations']}: {e(eq['shapeup_nonplanarity_max'])}",
                f"{eq['ratio']:.0f}",
                f"{s['seconds'] / o['seconds']:.1f}" + ("" if s["converged"] else "+"),
            ]
            + (
                [f"{r['positions_solve']['iterations']}, {r['positions_solve']['seconds']:.2f}"]
                if positions
                else []
            )
        )
    header = [
        "mesh",
        "V",
        "max before",
        "ours: iters, s",
        "ours: max after",
        "ours: disp max / area",
        "L-BFGS: iters, s, max",
        "Shape-Up (vectorized): iters, s, max",
        "Shape-Up: disp max / area",
        "Shape-Up at ours' time: iters: max",
        "max ratio at equal time (SU/ours)",
        "time to tol (SU/ours)",
    ] + (["GN solved in the positions (old): iters, s"] if positions else [])
    print(markdown_table(header, body))
    # the large meshes' results: the comparison with the positions solve in place of this one
    if positions:
        tables = {"large": large_table(records)}
    else:
        tables = {"tolerance": table_data(header, body)}
    print("\nAt equal iteration budgets: largest non-planarity (seconds):\n")
    body = []
    for r in records:
        for row in r["budgets"]:
            o, s, li = row["ours"], row.get("shapeup"), row.get("libigl")
            body.append(
                [
                    r["mesh"],
                    row["budget"],
                    f"{e(o['nonplanarity_max'])} ({o['seconds']:.2f})",
                    f"{e(s['nonplanarity_max'])} ({s['seconds']:.2f})" if s else "–",
                    f"{e(li['nonplanarity_max'])} ({li['seconds']:.2f})" if li else "–",
                    e(li["vectorized_difference"]) if li else "–",
                ]
            )
    header = [
        "mesh",
        "iterations",
        "ours (Gauss-Newton)",
        "Shape-Up, vectorized",
        "Shape-Up, libigl",
        "libigl - vectorized (positions / diag)",
    ]
    print(markdown_table(header, body))
    tables["budgets"] = table_data(header, body)
    return tables


def large_table(records: list[dict]) -> dict:
    """Print and return the table of the large meshes: the steps solved in the plane
    conditions against the same steps solved in the vertex coordinates (``--positions-solve``),
    and the peers to the tolerance and at our time."""
    print("\nSteps in the plane conditions against steps in the positions (same iterates):\n")
    body = []
    for r in records:
        b, o, lb, s = r["before"], r["ours"], r["lbfgs"], r["shapeup"]
        old, eq = r["positions_solve"], r["equal_time"]
        su_time = f"{s['seconds']:.1f}" + ("" if s["converged"] else " (not reached)")
        change = f"{o['displacement_max']:.2e} / {o['area_change']:+.2%}"
        body.append(
            [
                r["mesh"],
                r["V"],
                e(b["nonplanarity_max"]),
                f"{o['iterations']}, {o['seconds']:.1f}",
                f"{old['seconds']:.1f}",
                f"{o['seconds'] / old['seconds']:.3f}",
                f"{e(o['nonplanarity_max'])}, {change}",
                f"{lb['iterations']}, {lb['seconds']:.1f}, {e(lb['nonplanarity_max'])}",
                f"{s['iterations']}, {su_time}, {e(s['nonplanarity_max'])}",
                f"{e(eq['shapeup_nonplanarity_max'])} ({eq['ratio']:.0f}x)",
            ]
        )
    header = [
        "mesh",
        "V",
        "max before",
        "ours: steps, s",
        "old (positions solve): s",
        "ours / old",
        "max after, disp max / area (both)",
        "L-BFGS: iters, s, max",
        "Shape-Up: iters, s, max",
        "Shape-Up at ours' time (ratio)",
    ]
    print(markdown_table(header, body))
    return table_data(header, body)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="+", default=None)
    ap.add_argument("--real-dir", type=Path, default=REAL)
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--budgets", type=int, nargs="+", default=[1, 5, 10, 50, 200])
    ap.add_argument("--su-max-iter", type=int, default=100000)
    ap.add_argument("--su-max-seconds", type=float, default=300.0)
    ap.add_argument(
        "--positions-solve",
        action="store_true",
        help="also time Gauss-Newton with its steps solved in the vertex coordinates (old)",
    )
    ap.add_argument(
        "--igl-python", default=os.environ.get("IGL241_PYTHON", "/work/igl241/bin/python")
    )
    ap.add_argument("--igl-max-seconds", type=float, default=120.0)
    ap.add_argument("--igl-max-vertices", type=int, default=10000)
    ap.add_argument("--json", type=Path, help="default benchmarks/results/planarize.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    meta = run_meta()
    os.environ["OMP_NUM_THREADS"] = "1"
    if not have_igl(args):
        print(f"no libigl 2.4.1 interpreter at {args.igl_python}: libigl skipped", file=sys.stderr)
    # warm-up: the first calls pay one-time imports and kernel initialization
    warm_v, warm_f = hypar(4)
    run_ours(warm_v, warm_f, 1e-4)
    ShapeUp(warm_v.numpy(), warm_f.numpy()).run(2)

    records = [bench_mesh(n, V, F, args) for n, V, F in load_meshes(args.meshes, args.real_dir)]
    tables = report(records, args.tol)
    sections = {"tol": args.tol, "meshes": records, "tables": tables}
    write_results("planarize", sections, meta=meta, path=args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
