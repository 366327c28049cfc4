"""``polylap smooth [MESH]``: implicit mean-curvature flow (AW11 sec. 5.1)."""

from __future__ import annotations

import argparse
import math
import time
from typing import TYPE_CHECKING

import torch
from tqdm import tqdm

from .._typing import MeshFaces
from ..measures import face_areas, mean_edge_length
from ..operators import laplacian, strong_laplacian
from ..topology import Topology, get_topology
from .common import (
    Result,
    add_mesh_argument,
    add_method_argument,
    add_output_arguments,
    execute,
    figure_output,
    load_mesh,
    mesh_output,
    method_label,
    positive_float,
    positive_int,
    result_name,
    up_axis,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure

# Mean-curvature flow develops singularities in finite time where a thin part of the surface
# pinches off (a cylinder of radius r at t = r^2 / 2): on a coarse mesh with thin ears that is
# within a few default steps, and the ears turn into spikes whose curvature grows without bound.
# A healthy flow lowers the largest scale-free curvature; the command keeps the last step before
# it rises above this multiple of its initial value.
SINGULARITY_FACTOR = 4.0
# With the default time step, a refused step is retried with half the step this many times.
MAX_HALVINGS = 6


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "smooth",
        help="implicit mean-curvature flow",
        description="Smooth a polygon mesh with implicit mean-curvature flow "
        "(M0 + dt L) X' = M0 X (AW11 sec. 5.1), L and M0 rebuilt every step unless --frozen. "
        "Writes <mesh>_smooth.<ext> and a before/after figure colored by the scale-free mean "
        "curvature |H| sqrt(A / 4 pi) (1 on any round sphere). Mean-curvature flow pinches thin "
        "parts in finite time: a step that would raise the largest curvature above "
        f"{SINGULARITY_FACTOR:g} x its initial value is refused (retried with half the default "
        "step, up to 6 times), and the command says where it stopped.",
    )
    add_mesh_argument(p)
    p.add_argument(
        "--dt",
        type=positive_float,
        default=None,
        help="time step in absolute units (length^2; default: 0.1 x squared mean edge length, "
        "halved where a step would pinch)",
    )
    p.add_argument("--steps", type=positive_int, default=10, help="implicit steps (default 10)")
    p.add_argument("--lam", type=positive_float, default=1.0, help="stabilizer weight (default 1)")
    add_method_argument(p)
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
    add_output_arguments(p)
    p.set_defaults(func=run, compute=compute)


def scaled_mean_curvature(
    verts: torch.Tensor, faces: MeshFaces, lam: float, method: str = "aw11"
) -> torch.Tensor:
    """``(V,)`` ``|H| sqrt(A / 4 pi)``: the mean curvature ``|M0^{-1} L X| / 2`` (AW11 sec. 3.2)
    times the radius of the sphere with the mesh's area, so that flows that shrink the mesh
    compare by shape, not size. ``L, M0`` of ``method`` (``"aw11"``, ``"plms"``, ``"degoes"``)."""
    L, M0 = laplacian(verts, faces, lam, method=method)
    H = torch.linalg.vector_norm(strong_laplacian(L, M0, verts), dim=1) / 2
    return H * math.sqrt(float(face_areas(verts, faces).sum()) / (4 * math.pi))


def compute(args: argparse.Namespace) -> Result:
    from ..apps.flow import _require_closed_oriented, enclosed_volume

    verts, faces, path, label = load_mesh(args)
    topo = get_topology(faces, verts.shape[0])
    dt = args.dt if args.dt is not None else 0.1 * float(mean_edge_length(verts, topo)) ** 2
    normalize = None if args.normalize == "none" else args.normalize
    if normalize == "volume":  # checked here: a failing step below means a singularity
        _require_closed_oriented(topo, "normalize='volume'", "Use --normalize area or none.")
    h_before = scaled_mean_curvature(verts, topo, args.lam, args.method)
    interior = torch.ones(verts.shape[0], dtype=torch.bool)
    interior[topo.boundary_vertices] = False
    if not bool(interior.any()):  # a strip of faces: report the boundary values after all
        interior[:] = True
    start = time.perf_counter()
    smoothed, kept, dt, warning = _flow_before_singularity(
        verts, topo, dt, normalize, args, h_before, interior
    )
    seconds = time.perf_counter() - start

    try:  # the volume row only where a volume is defined: closed and consistently oriented
        _require_closed_oriented(topo, "enclosed volume")
        has_volume = True
    except ValueError:
        has_volume = False
    h_after = scaled_mean_curvature(smoothed, topo, args.lam, args.method)
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
    if has_volume:
        rows.append(
            (
                "enclosed volume before / after",
                f"{float(enclosed_volume(verts, topo)):.5g} / "
                f"{float(enclosed_volume(smoothed, topo)):.5g}",
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
        panel = dict(faces=faces, label="|H| sqrt(A/4pi)", up=up_axis(args, verts), clim=(0.0, top))
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


def _flow_before_singularity(
    verts: torch.Tensor,
    topo: Topology,
    dt: float,
    normalize: str | None,
    args: argparse.Namespace,
    h_before: torch.Tensor,
    interior: torch.Tensor,
) -> tuple[torch.Tensor, int, float, str]:
    """Up to ``args.steps`` flow steps that stop short of a singularity.

    A step is refused when the largest scale-free mean curvature over the ``interior`` vertices
    (``(V,)`` bool; boundary vertices carry a boundary term, not curvature) rises above
    ``SINGULARITY_FACTOR`` times the input's, or a round sphere's (1) if that is larger: a thin
    part pinching off or when its system is
    singular (a small closed component shrunk to a point: its masses vanish). With the default
    time step a refused step is retried with half the step, up to ``MAX_HALVINGS`` times; a
    ``--dt`` the user chose is kept. Returns the positions ``(V, 3)``, the steps taken, the
    last time step and the warning that says why the flow stopped early (empty if it did not).
    """
    from ..apps.flow import mean_curvature_flow

    largest = max(float(h_before[interior].max()), 1.0)
    bound = SINGULARITY_FACTOR * largest
    flow = dict(lam=args.lam, normalize=normalize, method=args.method)
    frozen_states = None
    if args.frozen:  # one operator from the input and one factorization: all steps in one call
        frozen_states = mean_curvature_flow(
            verts, topo, dt, args.steps, frozen=True, return_trajectory=True, **flow
        )[1:]
    halvings_left = MAX_HALVINGS if args.dt is None and not args.frozen else 0
    current, taken = verts, 0
    bar = tqdm(total=args.steps, desc="flow", disable=args.no_progress)
    while taken < args.steps:
        reason = ""
        try:
            if frozen_states is not None:
                new = frozen_states[taken]
            else:
                new = mean_curvature_flow(current, topo, dt, 1, **flow)
            h = scaled_mean_curvature(new, topo, args.lam, args.method)
            h = h.where(interior, torch.zeros_like(h))
            if not bool(torch.isfinite(h).all()) or float(h.max()) > bound:
                v = int(torch.nan_to_num(h, nan=float("inf")).argmax())
                reason = (
                    f"the scale-free mean curvature at vertex {v} would reach {float(h[v]):.3g}, "
                    f"more than {SINGULARITY_FACTOR:g} x the input's largest "
                    f"({largest:.3g}): a thin part is pinching off or faces are folding over"
                )
        except ValueError as err:
            reason = f"its system is singular ({err}): a small closed part shrank to a point"
        if not reason:
            current, taken = new, taken + 1
            bar.update()
            continue
        if halvings_left:
            dt, halvings_left = dt / 2, halvings_left - 1
            continue
        bar.close()
        return (
            current,
            taken,
            dt,
            (
                f"stopped after {taken} of {args.steps} steps (dt = {dt:.3g}): at step {taken + 1} "
                f"{reason}. Mean-curvature flow develops such singularities in finite time; for "
                "more smoothing take a smaller --dt with more --steps, or --frozen (one linear "
                "operator from the input: thin parts shrink instead of pinching)."
            ),
        )
    bar.close()
    return current, taken, dt, ""


def _figure(panels: list[dict]) -> Figure:
    from ..plot import plot_meshes

    return plot_meshes(panels)


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
