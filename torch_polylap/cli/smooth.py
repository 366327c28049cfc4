"""``polylap smooth [MESH]``: implicit mean-curvature flow (AW11 sec. 5.1)."""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING

import torch

from ..apps.flow import (
    SINGULARITY_FACTOR,
    FlowOptions,
    enclosed_volume,
    mean_curvature_flow,
    scale_free_mean_curvature,
)
from ..measures import face_areas, mean_edge_length
from ..plot import PlotOptions
from .common import (
    Result,
    add_laplacian_arguments,
    execute,
    figure_output,
    finish_command,
    load_mesh_topology,
    mesh_output,
    method_label,
    positive_float,
    positive_int,
    result_name,
    up_axis,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Mean-curvature flow pinches thin parts in finite time: on a coarse mesh with thin ears that is
# within a few default steps. The command guards the flow (mean_curvature_flow's
# stop_at_singularity) and, with the default time step, retries a refused step with half the
# step this many times; a --dt the user chose is kept.
MAX_HALVINGS = 6


SUMMARY = "implicit mean-curvature flow"
DESCRIPTION = (
    "Smooth a polygon mesh with implicit mean-curvature flow "
    "(M0 + dt L) X' = M0 X (AW11 sec. 5.1), L and M0 rebuilt every step unless --frozen. "
    "Writes <mesh>_smooth.<ext> and a before/after figure colored by the scale-free mean "
    "curvature |H| sqrt(A / 4 pi) (1 on any round sphere). Mean-curvature flow pinches thin "
    "parts in finite time: a step that would raise the largest curvature above "
    f"{SINGULARITY_FACTOR:g} x its initial value is refused (retried with half the default "
    f"step, up to {MAX_HALVINGS} times), and the command says where it stopped."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--dt",
        type=positive_float,
        default=None,
        help="time step in absolute units (length^2; default: 0.1 x squared mean edge length, "
        "halved where a step would pinch)",
    )
    p.add_argument("--steps", type=positive_int, default=10, help="implicit steps (default 10)")
    add_laplacian_arguments(p)
    p.add_argument(
        "--frozen",
        action="store_true",
        help="build L and M0 once from the input (one factorization for all steps)",
    )
    p.add_argument(
        "--normalize",
        choices=("none", "area", "volume"),
        default="none",
        help="rescale after each step to keep the total area or enclosed volume (default none; "
        "volume needs a closed, consistently oriented mesh)",
    )
    finish_command(p, run, compute)


def compute(args: argparse.Namespace) -> Result:
    verts, faces, topo, path, label = load_mesh_topology(args)
    default_dt = args.dt is None
    dt = 0.1 * float(mean_edge_length(verts, topo)) ** 2 if default_dt else args.dt
    start = time.perf_counter()
    options = FlowOptions(
        frozen=args.frozen,
        normalize=None if args.normalize == "none" else args.normalize,
        progress=not args.no_progress,
        stop_at_singularity=True,
        max_halvings=MAX_HALVINGS if default_dt and not args.frozen else 0,
    )
    flow = mean_curvature_flow(
        verts, topo, dt, args.steps, args.lam, method=args.method, options=options
    )
    seconds = time.perf_counter() - start
    smoothed, kept, dt = flow.verts, flow.steps, flow.dt
    warning = ""
    if flow.stopped:
        warning = (
            f"stopped after {kept} of {args.steps} steps (dt = {dt:.3g}): {flow.stopped}. "
            "Mean-curvature flow develops such singularities in finite time; for more smoothing "
            "take a smaller --dt with more --steps, or --frozen (one linear operator from the "
            "input: thin parts shrink instead of pinching)."
        )
    h_before = scale_free_mean_curvature(verts, topo, args.lam, args.method)
    interior = torch.ones(verts.shape[0], dtype=torch.bool)
    interior[topo.boundary_vertices] = False
    if not bool(interior.any()):  # a strip of faces: report the boundary values after all
        interior[:] = True

    try:  # the volume row only where a volume is defined: closed and consistently oriented
        volume_before = float(enclosed_volume(verts, topo))
    except ValueError:
        volume_before = None
    h_after = scale_free_mean_curvature(smoothed, topo, args.lam, args.method)
    shift = torch.linalg.vector_norm(smoothed - verts, dim=1).max()
    diag = torch.linalg.vector_norm(verts.amax(0) - verts.amin(0))
    rows = [
        ("vertices / faces", f"{verts.shape[0]} / {faces.num_faces}"),
        ("dt / steps kept of asked / lambda", f"{dt:.4g} / {kept} of {args.steps} / {args.lam}"),
        ("Laplacian", method_label(args)),
        ("frozen / normalize", f"{args.frozen} / {args.normalize}"),
        ("time", f"{seconds:.2f} s"),
        (
            "total area before / after",
            f"{float(face_areas(verts, topo).sum()):.5g} / "
            f"{float(face_areas(smoothed, topo).sum()):.5g}",
        ),
    ]
    if volume_before is not None:
        rows.append(
            (
                "enclosed volume before / after",
                f"{volume_before:.5g} / {float(enclosed_volume(smoothed, topo)):.5g}",
            )
        )
    rows += [
        (
            "|H| sqrt(A/4pi) mean before / after",
            f"{float(h_before[interior].mean()):.4f} / {float(h_after[interior].mean()):.4f}",
        ),
        (
            "|H| sqrt(A/4pi) std before / after",
            f"{float(h_before[interior].std()):.4f} / {float(h_after[interior].std()):.4f}",
        ),
        ("largest vertex move / bbox diagonal", f"{float(shift / diag):.3g}"),
    ]
    outputs = [mesh_output(result_name(path, "smooth"), smoothed, faces)]
    if not args.no_plot:
        # boundary vertices carry a boundary term, not curvature: leave them out of the color
        # (painted with the interior mean)
        before = h_before.where(interior, h_before[interior].mean())
        after = h_after.where(interior, h_after[interior].mean())
        # the 95th percentile as the top color keeps a few sharp corners from washing it out
        top = float(torch.quantile(h_before[interior], 0.95))
        style = PlotOptions(label="|H| sqrt(A/4pi)", up=up_axis(args, verts), clim=(0.0, top))
        panel = dict(faces=faces, options=style)
        panels = [
            dict(verts=verts, values=before, title="input", **panel),
            dict(
                verts=smoothed,
                values=after,
                title=f"after {kept} steps, dt = {dt:.3g}",
                **panel,
            ),
        ]
        outputs.append(figure_output(result_name(path, "smooth", ".png"), lambda: _figure(panels)))
    return Result(
        f"polylap smooth: {label}",
        rows,
        outputs=outputs,
        warnings=[warning] if warning else [],
        data={"steps_kept": kept, "steps_asked": args.steps, "dt": dt},
    )


def _figure(panels: list[dict]) -> Figure:
    from ..plot import plot_meshes

    return plot_meshes(panels)


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
