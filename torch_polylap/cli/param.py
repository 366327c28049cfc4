"""``polylap param [MESH]``: conformal parameterization of a disk-like mesh (AW11 sec. 5.2)."""

from __future__ import annotations

import argparse
import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..data import DISK_MESH
from ..faces import PolygonFaces
from ..measures import vector_area
from ..topology import Topology
from .common import (
    Result,
    add_laplacian_arguments,
    execute,
    finish_command,
    load_mesh_topology,
    mesh_output,
    method_label,
    plot_outputs,
    result_name,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure


SUMMARY = "conformal (LSCM-type) parameterization of a mesh with boundary"
MESH = DISK_MESH  # a mesh with boundary: the command flattens disks
DESCRIPTION = (
    "Flatten a polygon mesh with boundary by minimizing the conformal energy "
    "E_C = E_D - A (AW11 sec. 5.2): two pinned boundary vertices (default, eq. 12) or a free "
    "boundary (--free-boundary, eq. 13-15). Writes <mesh>_param.obj (the flat mesh, z = 0) "
    "and a figure of the mesh and its image colored by the angle distortion."
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_laplacian_arguments(p)
    p.add_argument(
        "--free-boundary",
        action="store_true",
        help="no pins: minimize E_C subject to A = 1 (boundary Schur complement, AW11 eq. 15)",
    )
    p.add_argument(
        "--pins",
        type=int,
        nargs=2,
        metavar=("I", "J"),
        help="the two pinned boundary vertices (default: two far-apart ones)",
    )
    finish_command(p, run, compute, progress=False)


def compute(args: argparse.Namespace) -> Result:
    from ..apps.conformal import angle_distortion, conformal_energy, conformal_parameterization

    verts, faces, topo, path, label = load_mesh_topology(args)
    if args.pins is not None and args.free_boundary:
        raise ValueError("--pins and --free-boundary exclude each other; pass one of them.")
    start = time.perf_counter()
    uv = conformal_parameterization(
        verts,
        topo,
        pins=args.pins,
        free_boundary=args.free_boundary,
        lam=args.lam,
        method=args.method,
    )
    seconds = time.perf_counter() - start
    uv = uv.detach()
    energy = float(conformal_energy(uv, verts, topo, args.lam, method=args.method))
    dist = angle_distortion(uv, verts, topo)
    # per-face mean |angle error| in degrees (the corners are packed face by face)
    face_err = torch.zeros(faces.num_faces, dtype=uv.dtype).index_add_(
        0, faces.corner_face, dist.per_corner.abs()
    ) / faces.sizes.to(uv.dtype)
    face_err_deg = face_err * 180 / math.pi
    flat = torch.cat([uv, torch.zeros_like(uv[:, :1])], 1)
    signed_area = vector_area(flat, topo)[:, 2]
    flipped = int((signed_area <= 0).sum())
    rows = [
        (
            "vertices / faces / boundary edges",
            f"{verts.shape[0]} / {faces.num_faces} / {topo.boundary_edges.shape[0]}",
        ),
        ("mode", "free boundary (eq. 13-15)" if args.free_boundary else "two pins (eq. 12)"),
        ("lambda / time", f"{args.lam} / {seconds * 1e3:.1f} ms"),
        ("Laplacian", method_label(args)),
        ("conformal energy E_C", f"{energy:.4g}"),
        ("image area / 3D area", f"{float(signed_area.sum()) / float(_area(verts, topo)):.4f}"),
        (
            "angle error mean / rms / max (deg)",
            f"{math.degrees(dist.mean):.3f} / {math.degrees(dist.rms):.3f} / "
            f"{math.degrees(dist.max):.3f}",
        ),
        ("flipped faces", str(flipped)),
    ]
    outputs = [mesh_output(result_name(path, "param", ".obj"), flat, faces)]
    outputs += plot_outputs(
        args, verts, path, "param", lambda up: _figure(verts, uv, faces, face_err_deg, up)
    )
    return Result(f"polylap param: {label}", rows, outputs=outputs)


def _figure(
    verts: torch.Tensor,
    uv: torch.Tensor,
    faces: PolygonFaces,
    face_err_deg: torch.Tensor,
    up: str,
) -> Figure:
    """The mesh and its conformal image, faces colored by their mean angle error."""
    from ..plot import PlotOptions, new_figure, plot_mesh, plot_uv

    fig, (ax3, ax2) = new_figure(1, 2, three_d=[True, False], panel_size=4.5)
    hi = float(np.nanmax(face_err_deg.numpy())) or 1.0
    common: dict[str, Any] = dict(cmap="magma", clim=(0.0, hi), label="mean |angle error| (deg)")
    style = PlotOptions(colorbar=False, up=up, **common)
    plot_mesh(verts, faces, face_err_deg, ax=ax3, title="input", options=style)
    plot_uv(uv, faces, face_err_deg, ax=ax2, title="conformal map", **common)
    return fig


def _area(verts: torch.Tensor, topo: Topology) -> torch.Tensor:
    return torch.linalg.vector_norm(vector_area(verts, topo), dim=1).sum()


def run(args: argparse.Namespace) -> int:
    return execute(compute, args)
