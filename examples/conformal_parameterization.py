"""Conformal parameterization of non-planar polygon patches (AW11 sec. 5.2), against the same
vertices triangulated two ways.

    python examples/conformal_parameterization.py [--lam 1.0] [--out examples/output]
        [--families DIR] [--level 2]

Meshes: the embedded hexagon/pentagon hemisphere cap (``torch_polylap/data/hex_hemisphere.obj``,
75 slightly non-planar hexagons) and a procedural patch of irregular, non-planar quads on a
saddle; and, when the folder ``--families`` exists (the refinement families of the AW11
literature, not shipped with the package), every polygon family of it at ``--level``, mapped to
``[-1, 1]^2`` and lifted onto the same saddle, for a second table: free-boundary maps, polygon
against both fans, one row per family. Each mesh is flattened with the polygon Laplacian and,
for comparison, the same vertex set triangulated by two different fans (every polygon cut from
its corner 0, or from its corner 1); on triangles this package's Laplacian is the cotan
Laplacian, so those maps are cotan LSCM (pinned) and spectral conformal maps (free boundary).

All three maps are scored on the *polygon* mesh: ``E_C`` with the polygon Laplacian, normalized
by the image area (scale free), and the polygon corner-angle error (corners of the faces'
maximal projections vs. the image, ``torch_polylap.apps.angle_distortion``). The triangle maps
are also given their own ``E_C / A`` on their own triangles. Writes
``examples/output/conformal_parameterization.png`` (the free-boundary maps, polygons colored by
their mean absolute angle error) and ``conformal_parameterization.md``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

import torch_polylap as tp
from torch_polylap.apps import angle_distortion, conformal_energy, conformal_parameterization
from torch_polylap.data import DISK_MESH
from torch_polylap.plot import new_figure, plot_uv, save_figure
from torch_polylap.shapes import quad_grid

FAMILIES = Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes" / "grid"


def saddle(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    return 0.6 * (x**2 - y**2)


def saddle_quads(n: int = 10, seed: int = 0) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """An ``n x n`` grid of irregular quads on the saddle ``z = 0.6 (x^2 - y^2)``."""
    verts, quads = quad_grid(
        n,
        extent=(-1.0, 1.0, -1.0, 1.0),
        seed=seed,
        jitter=0.15,
        height=saddle,
    )
    return verts, tp.as_faces(quads)


def lifted_family(path: Path) -> tuple[torch.Tensor, tp.PolygonFaces]:
    """A planar grid family mesh, scaled to ``[-1, 1]^2`` and lifted onto :func:`saddle`."""
    verts, faces = tp.read_mesh(path)
    xy = verts[:, :2].double()
    lo, hi = xy.amin(0), xy.amax(0)
    xy = 2 * (xy - lo) / (hi - lo) - 1
    return torch.cat((xy, saddle(xy[:, 0], xy[:, 1])[:, None]), 1), tp.as_faces(faces)


def family_table(folder: Path, level: int, lam: float) -> str:
    """Free-boundary maps of every polygon family at ``level``: polygon vs. both fans."""
    lines = [
        "| family | faces (degrees) | mean angle error (deg): polygons / fan 0 / fan 1 "
        "| polygons / better fan | E_C/A (polygon L): polygons / fan 0 / fan 1 |",
        "|---|---|---|---|---|",
    ]
    for path in sorted(folder.glob(f"*_{level}.obj")):
        family = path.stem.rsplit("_", 1)[0]
        V, F = lifted_family(path)
        if bool((F.sizes == 3).all()):
            continue  # a triangle mesh is its own fan: the maps coincide
        scores = [
            score(conformal_parameterization(V, t, lam=lam, free_boundary=True), V, F, t, lam)
            for t in (F, fan(F, 0), fan(F, 1))
        ]
        means = [s["mean"] for s in scores]
        degrees = "/".join(str(k) for k in torch.unique(F.sizes).tolist())
        lines.append(
            f"| {family} | {F.num_faces} ({degrees}) | "
            + " / ".join(f"{m:.3f}" for m in means)
            + f" | {means[0] / min(means[1:]):.3f} | "
            + " / ".join(f"{s['ec_poly']:.3e}" for s in scores)
            + " |"
        )
    return "\n".join(lines)


def fan(faces: tp.PolygonFaces, start: int) -> torch.Tensor:
    """Triangulate every polygon as a fan from its corner ``start`` (same vertices)."""
    tris = []
    for k in torch.unique(faces.sizes).tolist():
        ids = torch.nonzero(faces.sizes == k).reshape(-1)
        corners = faces.indices[faces.offsets[ids][:, None] + torch.arange(k)]  # (F_k, k)
        corners = torch.roll(corners, -start, dims=1)
        for j in range(1, k - 1):  # a loop over the fan's triangles, not over faces
            tris.append(corners[:, [0, j, j + 1]])
    return torch.cat(tris)


def image_area(uv: torch.Tensor, faces) -> float:
    flat = torch.cat((uv, torch.zeros_like(uv[:, :1])), 1)
    return float(tp.vector_area(flat, faces)[:, 2].sum())


def score(uv, verts, poly, tri, lam) -> dict:
    dist = angle_distortion(uv, verts, poly)
    area = image_area(uv, poly)
    own = tri if tri is not None else poly
    return {
        "ec_poly": float(conformal_energy(uv, verts, poly, lam)) / area,
        "ec_own": float(conformal_energy(uv, verts, own, lam)) / area,
        "mean": math.degrees(dist.mean),
        "rms": math.degrees(dist.rms),
        "max": math.degrees(dist.max),
        "per_corner": dist.per_corner.abs(),
    }


def face_mean(per_corner: torch.Tensor, faces: tp.PolygonFaces) -> torch.Tensor:
    fid = torch.repeat_interleave(torch.arange(faces.num_faces), faces.sizes)
    s = torch.zeros(faces.num_faces, dtype=per_corner.dtype).index_add_(0, fid, per_corner)
    return torch.rad2deg(s / faces.sizes.to(per_corner.dtype))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lam", type=float, default=1.0)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "output")
    ap.add_argument("--families", type=Path, default=FAMILIES)
    ap.add_argument("--level", type=int, default=2)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    V_hex, F_hex = tp.read_mesh(DISK_MESH)
    meshes = {
        "hex hemisphere": (V_hex.double(), tp.as_faces(F_hex)),
        "saddle quads": saddle_quads(),
    }
    lines = [
        "| mesh | mode | tessellation | E_C/A (polygon L) | E_C/A (own mesh) "
        "| angle error mean / rms / max (deg) |",
        "|---|---|---|---|---|---|",
    ]
    fig, axes = new_figure(len(meshes), 3, three_d=False, panel_size=3.6)
    panels = []
    for m, (name, (V, F)) in enumerate(meshes.items()):
        tess = {"polygons": None, "fan from corner 0": fan(F, 0), "fan from corner 1": fan(F, 1)}
        for free in (False, True):
            for t, (label, tri) in enumerate(tess.items()):
                uv = conformal_parameterization(
                    V, tri if tri is not None else F, lam=args.lam, free_boundary=free
                )
                s = score(uv, V, F, tri, args.lam)
                mode = "free boundary" if free else "two pins"
                lines.append(
                    f"| {name} | {mode} | {label} | {s['ec_poly']:.3e} | {s['ec_own']:.3e} "
                    f"| {s['mean']:.3f} / {s['rms']:.3f} / {s['max']:.3f} |"
                )
                if free:
                    panels.append(
                        (
                            axes[3 * m + t],
                            uv,
                            F,
                            face_mean(s["per_corner"], F),
                            f"{name}: {label}\nmean |angle err| {s['mean']:.2f} deg",
                        )
                    )
    hi = max(float(p[3].max()) for p in panels)
    for ax, uv, F, vals, title in panels:
        plot_uv(uv, F, vals, ax=ax, title=title, clim=(0.0, hi), label="deg")
    png = args.out / "conformal_parameterization.png"
    save_figure(fig, png)
    table = "\n".join(lines)
    print(table)
    text = (
        "# Conformal parameterization: polygons vs. triangulations\n\n"
        f"lambda = {args.lam}; E_C/A = conformal energy over image area (scale free); angle "
        "errors on the polygon corners (maximal-projection angles).\n\n" + table + "\n"
    )
    if args.families.is_dir():
        families = family_table(args.families, args.level, args.lam)
        print("\n" + families)
        text += (
            f"\n## The grid families at level {args.level} on the saddle, free boundary\n\n"
            + families
            + "\n"
        )
    else:
        print(f"\n{args.families} not found: the family table is skipped")
    (args.out / "conformal_parameterization.md").write_text(text)
    print(f"\nwrote {png} and {args.out / 'conformal_parameterization.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
