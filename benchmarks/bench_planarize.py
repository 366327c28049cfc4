"""Planarizing flow (AW11 sec. 5.3) against libigl's Shape-Up quad planarization.

    python benchmarks/bench_planarize.py [--meshes spot_quadrangulated.obj ...] [--tol 1e-4]
        [--shapeup-iters 10 50 200] [--igl-python /work/igl241/bin/python] [--json PATH]

For every pure-quad mesh: ``torch_polylap.apps.planarize`` with ``method="lbfgs"`` (L-BFGS on
``E_plan``, lambda = 2, no constraints, stopped when the largest non-planarity is below
``--tol``) and with its default ``method="gauss-newton"`` (Gauss-Newton on the face-plane
residuals, a separate table) against
``igl.planarize_quad_mesh`` (Shape-Up projections, Bouaziz et al. 2012, as in libigl; parameters
``maxIter`` and ``threshold``; ``threshold`` is set to ``--tol``, libigl's own stopping measure).
``planarize_quad_mesh`` left libigl's Python bindings after 2.4.1, so it runs in a separate
interpreter (``--igl-python``, a venv with libigl 2.4.1 and numpy < 2) on ``.npz`` files and is
timed inside that process. Both run single-threaded (torch threads and OMP_NUM_THREADS = 1): the
machine is shared and multi-threaded kernels stall under load.

Every result is measured with the same function, :func:`torch_polylap.face_nonplanarity`
(largest corner distance from the plane of the face's maximal projection, over the face
diameter; a second table uses each face's least-squares plane, ``plane="fit"``), and
displacement is relative to the bounding-box diagonal. Prints a Markdown table;
``--json`` (default ``benchmarks/results/planarize.json``) writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import torch_polylap as tp
from torch_polylap.apps import planarize

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "real"
DEFAULT_MESHES = ["quadknot.obj", "catmark_car.obj", "spot_quadrangulated.obj"]
SHAPEUP = """
import sys, time
import numpy as np, igl
d = np.load(sys.argv[1])
V = np.ascontiguousarray(d["V"], dtype=np.float64)
F = np.ascontiguousarray(d["F"], dtype=np.int64)
start = time.perf_counter()
out = igl.planarize_quad_mesh(V, F, int(d["max_iter"]), float(d["threshold"]))
seconds = time.perf_counter() - start
np.savez(sys.argv[2], V=np.asarray(out, dtype=np.float64), seconds=seconds)
"""


def stats(V: torch.Tensor, V0: torch.Tensor, F: torch.Tensor) -> dict:
    n = tp.face_nonplanarity(V, F)
    fit = tp.face_nonplanarity(V, F, plane="fit")
    diag = float((V0.amax(0) - V0.amin(0)).norm())
    disp = (V - V0).norm(dim=1) / diag
    return {
        "nonplanarity_max": float(n.max()),
        "nonplanarity_mean": float(n.mean()),
        "fit_plane_max": float(fit.max()),
        "fit_plane_mean": float(fit.mean()),
        "displacement_max": float(disp.max()),
        "displacement_mean": float(disp.mean()),
    }


def shape_up(python: str, V: torch.Tensor, F: torch.Tensor, max_iter: int, threshold: float):
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        np.savez(src, V=V.numpy(), F=F.numpy(), max_iter=max_iter, threshold=threshold)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        subprocess.run([python, "-c", SHAPEUP, str(src), str(dst)], check=True, env=env)
        out = np.load(dst)
        return torch.from_numpy(out["V"]), float(out["seconds"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", nargs="+", default=DEFAULT_MESHES)
    ap.add_argument("--real-dir", type=Path, default=REAL)
    ap.add_argument("--tol", type=float, default=1e-4)
    ap.add_argument("--max-iter", type=int, default=2000, help="L-BFGS iteration limit")
    ap.add_argument("--shapeup-iters", type=int, nargs="+", default=[10, 50, 200])
    ap.add_argument(
        "--igl-python", default=os.environ.get("IGL241_PYTHON", "/work/igl241/bin/python")
    )
    ap.add_argument(
        "--json", type=Path, default=Path(__file__).parent / "results" / "planarize.json"
    )
    args = ap.parse_args()
    torch.set_num_threads(1)
    have_igl = Path(args.igl_python).exists()
    if not have_igl:
        print(
            f"no libigl 2.4.1 interpreter at {args.igl_python}: Shape-Up skipped", file=sys.stderr
        )

    # warm-up: the first L-BFGS call pays one-time imports and kernel initialization
    warm_v = torch.rand(9, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    planarize(
        warm_v, torch.tensor([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6], [4, 5, 8, 7]]), max_iter=3
    )
    rows, records, gn_rows = [], [], []
    for name in args.meshes:
        path = args.real_dir / name
        if not path.exists():
            print(f"{path} missing, skipped", file=sys.stderr)
            continue
        V, faces = tp.read_mesh(path)
        F = faces.as_uniform()
        if F is None or F.shape[1] != 4:
            print(f"{name} is not a pure quad mesh, skipped", file=sys.stderr)
            continue
        V = V.double()
        before = stats(V, V, F)
        print(f"{name}: planarize (ours) ...", file=sys.stderr)
        start = time.perf_counter()
        res = planarize(V, F.clone(), lam=2.0, tol=args.tol, max_iter=args.max_iter, method="lbfgs")
        ours_time = time.perf_counter() - start
        ours = stats(res.verts, V, F) | {"seconds": ours_time, "iterations": res.iterations}
        print(f"{name}: planarize (ours, Gauss-Newton) ...", file=sys.stderr)
        start = time.perf_counter()
        res_gn = planarize(V, F.clone(), tol=args.tol, method="gauss-newton")
        gn = stats(res_gn.verts, V, F) | {
            "seconds": time.perf_counter() - start,
            "iterations": res_gn.iterations,
        }
        gn_rows.append((name, V.shape[0], before, ours, gn))
        rec = {"mesh": name, "V": V.shape[0], "F": F.shape[0], "before": before, "ours": ours}
        rec["gauss_newton"] = gn
        rec["shape_up"] = []
        for it in args.shapeup_iters if have_igl else []:
            print(f"{name}: Shape-Up maxIter={it} ...", file=sys.stderr)
            Vs, secs = shape_up(args.igl_python, V, F, it, args.tol)
            s = stats(Vs, V, F) | {"seconds": secs, "max_iter": it}
            s["max_ratio"] = s["nonplanarity_max"] / ours["nonplanarity_max"]
            s["time_ratio"] = secs / ours_time
            s["target_met"] = bool(s["max_ratio"] >= 10 and s["time_ratio"] >= 10)
            rec["shape_up"].append(s)
            rows.append((name, V.shape[0], before, ours, s))
        if not rec["shape_up"]:
            rows.append((name, V.shape[0], before, ours, None))
        records.append(rec)

    print(
        f"\nPlanarization, tol = {args.tol:g} (ours: L-BFGS on E_plan, lambda = 2; "
        "Shape-Up: igl.planarize_quad_mesh, threshold = tol); one thread each.\n"
    )
    print(
        "| mesh | V | max / mean before | ours: max / mean after | ours: disp max / mean "
        "| ours: iters, s | Shape-Up maxIter | Shape-Up: max / mean after | Shape-Up: disp "
        "max / mean | Shape-Up s | max ratio (SU/ours) | time ratio (SU/ours) | 10x/10x met |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, nv, b, o, s in rows:
        left = (
            f"| {name} | {nv} | {b['nonplanarity_max']:.2e} / {b['nonplanarity_mean']:.2e} "
            f"| {o['nonplanarity_max']:.2e} / {o['nonplanarity_mean']:.2e} "
            f"| {o['displacement_max']:.2e} / {o['displacement_mean']:.2e} "
            f"| {o['iterations']}, {o['seconds']:.2f} "
        )
        if s is None:
            print(left + "| – | – | – | – | – | – | – |")
            continue
        print(
            left
            + f"| {s['max_iter']} | {s['nonplanarity_max']:.2e} / {s['nonplanarity_mean']:.2e} "
            f"| {s['displacement_max']:.2e} / {s['displacement_mean']:.2e} | {s['seconds']:.2f} "
            f"| {s['max_ratio']:.1f} | {s['time_ratio']:.2f} | {('no', 'yes')[s['target_met']]} |"
        )
    print(
        "\nOur two optimizers (L-BFGS on E_plan, the old default; Gauss-Newton on the face-plane "
        "residuals, the default), to the same tol:\n"
    )
    print(
        "| mesh | V | max before | method | iterations | s | max / mean after | disp max / mean |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, nv, b, o, g in gn_rows:
        for label, r in (("L-BFGS", o), ("Gauss-Newton", g)):
            print(
                f"| {name} | {nv} | {b['nonplanarity_max']:.2e} | {label} | {r['iterations']} "
                f"| {r['seconds']:.2f} | {r['nonplanarity_max']:.2e} / "
                f"{r['nonplanarity_mean']:.2e} | {r['displacement_max']:.2e} / "
                f"{r['displacement_mean']:.2e} |"
            )
    print(
        "\nThe same results measured against each face's least-squares plane "
        '(`face_nonplanarity(..., plane="fit")`), max / mean:\n'
    )
    print("| mesh | before | ours | Shape-Up maxIter | Shape-Up | max ratio (SU/ours) |")
    print("|---|---|---|---|---|---|")
    for name, _, b, o, s in rows:
        su = (
            f"| {s['max_iter']} | {s['fit_plane_max']:.2e} / {s['fit_plane_mean']:.2e} "
            f"| {s['fit_plane_max'] / o['fit_plane_max']:.1f} |"
            if s is not None
            else "| – | – | – |"
        )
        print(
            f"| {name} | {b['fit_plane_max']:.2e} / {b['fit_plane_mean']:.2e} "
            f"| {o['fit_plane_max']:.2e} / {o['fit_plane_mean']:.2e} " + su
        )
    env = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "threads": 1,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"tol": args.tol, "env": env, "meshes": records}, indent=2))
    print(f"\nwrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
