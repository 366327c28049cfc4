"""Benchmark torch_polylap's mesh readers and writers against Python mesh I/O libraries.

    python benchmarks/bench_io.py                     # edge cases, real meshes, 1M-quad grid
    python benchmarks/bench_io.py --grid 300 --repeat 3 --json /tmp/io.json

Libraries (each optional; a missing one is reported and skipped): plyfile (PLY), meshio (OBJ,
OFF, PLY), potpourri3d (``read_polygon_mesh``; ``write_mesh`` writes OBJ), trimesh (reads all
three, triangulating; not timed as a writer since it cannot write polygons), openmesh
(``read_polymesh`` / ``write_mesh``) and Adobe's lagrange (``lagrange.io.load_mesh`` /
``save_mesh``, OBJ and PLY; already in the ``test`` extra).

For every file each library's reader is run once and its result compared with
``torch_polylap.read_mesh``'s: the same vertex count and coordinates, and the same polygons in the
same order (not triangulated, not reordered, not rotated). Files:

* edge cases written by this script: mixed-degree polygons (3- to 6-gons, one unreferenced
  vertex) in OBJ, OFF, ASCII PLY and binary PLY (``list uchar int``), OFF with comments, OBJ
  with ``v/vt/vn`` corners, with negative indices, with groups and materials between faces,
  with CRLF line endings, and a big-endian PLY with float coordinates, ``list int uint`` and
  extra properties; and six malformed files (an index out of range, an unparsable coordinate,
  a truncated file), which a reader should reject rather than return a mesh from;
* ``tests/data/*.{obj,off,ply}`` and the real meshes of ``--real-dir``
  (``../shared/data/meshes/real`` beside the repository; skipped with a message if absent);
* an ``n x n`` quad grid (``--grid n``, default 1000: 1M quads), written by ``write_mesh`` as
  OBJ, OFF, binary PLY and ASCII PLY.

Times are medians of ``--repeat`` samples (``--grid-repeat`` on the grid) with torch pinned to
one thread (a sample lasts at least 50 ms; shorter calls are repeated within it); the
correctness call is the warm-up. A library's read time includes turning its result into flat
``(verts, indices, sizes)`` arrays, what ``read_mesh`` returns (on the grid its bare call is
timed too, "raw", and plyfile's ``known_list_len`` fast path, and read_mesh's peak memory
with tracemalloc); its write time includes building
its input from those arrays. A library that fails on a file is not timed on it. Written
files are read back with ``read_mesh`` and compared with what was written. Ratios are the
library's time over ours (above 1: the library is slower). Prints Markdown; ``--json`` writes
every number.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import multiprocessing
import os
import platform
import sys
import tempfile
import tracemalloc
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import torch
from common import (
    RESULTS,
    bench_grid,
    cpu_model,
    fmt_time,
    markdown_table,
    median_time,
    pinned_threads,
    run_meta,
    table_data,
    table_from_markdown,
    write_results,
)

import torch_polylap as tp
from torch_polylap.faces import PolygonFaces
from torch_polylap.io import SkippedContentWarning
from torch_polylap.io import text as text_module

ROOT = Path(__file__).resolve().parents[1]
REAL_DIR = ROOT.parent / "shared" / "data" / "meshes" / "real"
MESH_EXTS = (".obj", ".off", ".ply")
CHECK_TIMEOUT = 120.0  # seconds a library gets for its first read or write of a file

# (verts (V, 3) float64, indices (sum of degrees,) int64, sizes (F,) int64)
Mesh = tuple[np.ndarray, np.ndarray, np.ndarray]


def _try_import(name: str):
    try:
        return __import__(name)
    except ImportError:
        return None


plyfile = _try_import("plyfile")
meshio = _try_import("meshio")
pp3d = _try_import("potpourri3d")
trimesh = _try_import("trimesh")
om = _try_import("openmesh")
lagrange = _try_import("lagrange")


# ---------------------------------------------------------------- adapters: library -> Mesh


def flat_lists(lists) -> tuple[np.ndarray, np.ndarray]:
    """``(indices, sizes)`` of a sequence of index sequences (lists or arrays)."""
    sizes = np.fromiter(map(len, lists), np.int64, len(lists))
    indices = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(sizes.sum()))
    return indices, sizes


def ours_read(path: Path) -> Mesh:
    verts, faces = tp.read_mesh(path)
    return verts.numpy(), faces.indices.numpy(), faces.sizes.numpy()


def numpy_read(path: Path) -> Mesh:
    """``ours_read`` with numpy's number parser alone, as without the ``fast-text`` extra."""
    saved = text_module._arrow
    text_module._arrow = lambda: None
    try:
        return ours_read(path)
    finally:
        text_module._arrow = saved


def plyfile_raw(path: Path):
    return plyfile.PlyData.read(str(path))


def plyfile_read(path: Path) -> Mesh:
    return plyfile_mesh(plyfile_raw(path))


def plyfile_known_len(path: Path, degree: int) -> Mesh:
    """plyfile's fast path for lists of a length known in advance (every face a ``degree``-gon;
    binary files only: ASCII ones are parsed as usual)."""
    known = {"face": {"vertex_indices": degree}}
    return plyfile_mesh(plyfile.PlyData.read(str(path), known_list_len=known))


def plyfile_mesh(data) -> Mesh:
    """``Mesh`` of a ``PlyData``: faces an object array of index arrays, or ``(F, k)``."""
    v = data["vertex"].data
    verts = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    f = data["face"].data
    lists = f["vertex_indices" if "vertex_indices" in f.dtype.names else "vertex_index"]
    if lists.dtype != object:  # known_list_len: an (F, k) array
        return verts, lists.reshape(-1).astype(np.int64), np.full(len(lists), lists.shape[1])
    sizes = np.fromiter(map(len, lists), np.int64, len(lists))
    indices = np.concatenate(lists).astype(np.int64) if len(lists) else np.zeros(0, np.int64)
    return verts, indices, sizes


def meshio_raw(path: Path):
    # meshio prints its errors and then calls sys.exit(1): keep the first, turn the second into
    # an exception that says what it printed.
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            return meshio.read(str(path))
    except SystemExit:
        raise RuntimeError("sys.exit: " + " / ".join(out.getvalue().split("\n")[:2])) from None


POLYGON_CELLS = ("triangle", "quad", "polygon")


def meshio_read(path: Path) -> Mesh:
    mesh = meshio_raw(path)
    blocks = [np.asarray(c.data, dtype=np.int64) for c in mesh.cells if c.type in POLYGON_CELLS]
    other = sorted({c.type for c in mesh.cells} - set(POLYGON_CELLS))
    if other:
        raise RuntimeError(f"cells of type {other}")
    sizes = np.concatenate([np.full(len(b), b.shape[1]) for b in blocks])
    indices = np.concatenate([b.reshape(-1) for b in blocks])
    return np.asarray(mesh.points, dtype=np.float64), indices, sizes


def pp3d_raw(path: Path):
    return pp3d.read_polygon_mesh(str(path))


def pp3d_read(path: Path) -> Mesh:
    verts, faces = pp3d_raw(path)
    return (np.asarray(verts, dtype=np.float64), *flat_lists(faces))


def trimesh_raw(path: Path):
    return trimesh.load(str(path), process=False, force="mesh")


def trimesh_read(path: Path) -> Mesh:
    mesh = trimesh_raw(path)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    return np.asarray(mesh.vertices, np.float64), faces.reshape(-1), np.full(len(faces), 3)


def openmesh_raw(path: Path):
    return om.read_polymesh(str(path))


def openmesh_read(path: Path) -> Mesh:
    mesh = openmesh_raw(path)
    if mesh.n_faces() == 0:  # what it returns, after a message on stderr, for many broken files
        empty = np.zeros(0, dtype=np.int64)
        return np.array(mesh.points(), dtype=np.float64).reshape(-1, 3), empty, empty
    padded = mesh.face_vertex_indices().astype(np.int64)  # (F, max degree), -1 padded
    keep = padded >= 0
    return np.array(mesh.points(), dtype=np.float64), padded[keep], keep.sum(1)


def lagrange_raw(path: Path):
    return lagrange.io.load_mesh(str(path), quiet=True)


def lagrange_read(path: Path) -> Mesh:
    mesh = lagrange_raw(path)
    indices = mesh.attribute(mesh.attr_id_corner_to_vertex).data.astype(np.int64)
    if mesh.is_hybrid:
        first = mesh.attribute(mesh.attr_id_facet_to_first_corner).data.astype(np.int64)
        sizes = np.diff(np.append(first, len(indices)))
    else:
        sizes = np.full(mesh.num_facets, mesh.vertex_per_facet, dtype=np.int64)
    return np.array(mesh.vertices, dtype=np.float64), indices, sizes


# ---------------------------------------------------------------- adapters: Mesh -> file

# write formats: "obj", "off", "ply" (ASCII), "plyb" (binary little endian)
FORMAT_EXT = {"obj": ".obj", "off": ".off", "ply": ".ply", "plyb": ".ply"}
FORMAT_NAME = {"obj": "OBJ", "off": "OFF", "ply": "ASCII PLY", "plyb": "binary PLY"}


def ours_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    faces = PolygonFaces(torch.from_numpy(indices), sizes=torch.from_numpy(sizes))
    tp.write_mesh(path, verts, faces, binary=fmt == "plyb")


def plyfile_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    vertex = np.empty(len(verts), dtype=[("x", "f8"), ("y", "f8"), ("z", "f8")])
    vertex["x"], vertex["y"], vertex["z"] = verts.T
    face = np.empty(len(sizes), dtype=[("vertex_indices", object)])
    face["vertex_indices"] = np.split(indices.astype(np.int32), np.cumsum(sizes)[:-1])
    elements = [
        plyfile.PlyElement.describe(vertex, "vertex"),
        plyfile.PlyElement.describe(
            face, "face", val_types={"vertex_indices": "i4"}, len_types={"vertex_indices": "u1"}
        ),
    ]
    plyfile.PlyData(elements, text=fmt == "ply").write(str(path))


def degree_runs(indices: np.ndarray, sizes: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """``(k, (n, k) array)`` for each run of consecutive faces of one degree, in file order."""
    cuts = np.flatnonzero(np.diff(sizes)) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [len(sizes)]])
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    return [
        (int(sizes[a]), indices[offsets[a] : offsets[b]].reshape(b - a, int(sizes[a])))
        for a, b in zip(starts.tolist(), ends.tolist(), strict=True)
    ]


def meshio_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    names = {3: "triangle", 4: "quad"}
    cells = [(names.get(k, "polygon"), block) for k, block in degree_runs(indices, sizes)]
    kwargs = {"binary": fmt == "plyb"} if fmt in ("ply", "plyb") else {}
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        meshio.write_points_cells(str(path), verts, cells, **kwargs)


def pp3d_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    if len(np.unique(sizes)) != 1:
        raise RuntimeError("write_mesh takes an (F, k) array: one degree only")
    pp3d.write_mesh(verts, indices.reshape(len(sizes), -1), str(path))


def openmesh_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    padded = np.full((len(sizes), int(sizes.max())), -1, dtype=np.int32)
    padded[np.arange(padded.shape[1]) < sizes[:, None]] = indices
    om.write_mesh(str(path), om.PolyMesh(verts, padded), binary=fmt == "plyb")


def lagrange_write(path: Path, mesh: Mesh, fmt: str) -> None:
    verts, indices, sizes = mesh
    out = lagrange.SurfaceMesh()
    out.add_vertices(verts)
    out.add_hybrid(sizes.astype(np.uint32), indices.astype(np.uint32))
    lagrange.io.save_mesh(str(path), out, binary=fmt == "plyb")


@dataclass
class Library:
    name: str
    dist: str  # distribution name, for the version
    read: Callable[[Path], Mesh] | None
    raw: Callable[[Path], object] | None
    reads: tuple[str, ...]  # file extensions
    write: Callable[[Path, Mesh, str], None] | None = None
    writes: tuple[str, ...] = ()
    available: bool = True
    version: str = field(default="")

    def __post_init__(self) -> None:
        try:
            self.version = version(self.dist)
        except PackageNotFoundError:
            self.version = "-"


LIBRARIES = [
    Library(
        "plyfile", "plyfile", plyfile_read, plyfile_raw, (".ply",), plyfile_write, ("ply", "plyb"),
        plyfile is not None,
    ),
    Library(
        "meshio", "meshio", meshio_read, meshio_raw, MESH_EXTS, meshio_write,
        ("obj", "off", "ply", "plyb"), meshio is not None,
    ),
    Library(
        "potpourri3d", "potpourri3d", pp3d_read, pp3d_raw, MESH_EXTS, pp3d_write, ("obj",),
        pp3d is not None,
    ),
    Library(
        "trimesh", "trimesh", trimesh_read, trimesh_raw, MESH_EXTS, None, (), trimesh is not None
    ),
    Library(
        "openmesh", "openmesh", openmesh_read, openmesh_raw, MESH_EXTS, openmesh_write,
        ("obj", "off", "ply", "plyb"), om is not None,
    ),
    Library(
        "lagrange", "adobe-lagrange", lagrange_read, lagrange_raw, MESH_EXTS, lagrange_write,
        ("obj", "ply", "plyb"), lagrange is not None,
    ),
]  # fmt: skip


# ---------------------------------------------------------------- comparison


def _canonical(indices: np.ndarray, sizes: np.ndarray) -> list[tuple[int, ...]]:
    """Each face rotated to start at its smallest index (order and orientation kept)."""
    out = []
    for face in np.split(indices, np.cumsum(sizes)[:-1]):
        i = int(np.argmin(face))
        out.append(tuple(np.roll(face, -i).tolist()))
    return out


def compare(ref: Mesh, got: Mesh) -> str:
    """``"same"`` or what differs between a library's mesh and ours, in a few words."""
    rv, ri, rs = ref
    gv, gi, gs = got
    notes = []
    if len(gv) != len(rv):
        notes.append(f"V {len(rv)}->{len(gv)}")
    elif not np.array_equal(gv, rv):
        err = np.max(np.abs(gv - rv)) / max(np.max(np.abs(rv)), 1e-300)
        notes.append(f"coords rounded ({err:.0e})" if err < 1e-4 else "coords differ")
    if np.array_equal(gs, rs) and np.array_equal(gi, ri):
        pass
    elif len(gs) > len(rs) and np.all(gs == 3) and np.any(rs > 3):
        notes.append(f"triangulated (F {len(rs)}->{len(gs)})")
    elif len(gs) < len(rs):
        notes.append(f"faces lost (F {len(rs)}->{len(gs)})")
    elif len(gs) != len(rs):
        notes.append(f"F {len(rs)}->{len(gs)}")
    elif len(gv) == len(rv):
        mine, theirs = _canonical(ri, rs), _canonical(gi, gs)
        if mine == theirs:
            notes.append("faces rotated")
        elif sorted(mine) == sorted(theirs):
            notes.append("faces reordered")
        else:
            notes.append("faces differ")
    else:
        notes.append("faces differ")
    return "; ".join(notes) or "same"


def short_error(e: BaseException, folder: Path | None = None) -> str:
    """``"error: "`` and the first 60 characters of the message (``folder`` cut from paths)."""
    text = " ".join(str(e).split()) or type(e).__name__
    if folder is not None:
        text = text.replace(str(folder) + "/", "")
    return "error: " + (text if len(text) <= 60 else text[:57] + "...")


def guarded(check: Callable[[], dict], timeout: float) -> dict:
    """``check()`` in a forked child: its dict, or ``{"verdict": ...}`` saying that it raised,
    hung (no answer in ``timeout`` seconds: the child is killed) or crashed."""
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)

    def child() -> None:
        try:
            out = quietly(check)
        except BaseException as e:  # noqa: BLE001 -- meshio raises SystemExit
            out = {"verdict": short_error(e), "error": " ".join(str(e).split())[:500]}
        send.send(out)

    proc = ctx.Process(target=child, daemon=True)
    proc.start()
    send.close()
    try:
        if receive.poll(timeout):
            return receive.recv()
        if proc.is_alive():
            return {"verdict": f"hangs (killed after {timeout:g} s)"}
        return {"verdict": f"crashes (exit code {proc.exitcode})"}
    except EOFError:
        proc.join()
        return {"verdict": f"crashes (exit code {proc.exitcode})"}
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
        receive.close()


def failed(entry: dict) -> bool:
    return entry["verdict"].startswith(("error", "hangs", "crashes", "read back"))


def quietly(fn: Callable[[], object]) -> object:
    """Call ``fn`` with Python-level warnings silenced (C++ prints still reach the terminal)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn()


# ---------------------------------------------------------------- inputs


def quad_grid(n: int) -> Mesh:
    """The benchmark grid (``common.bench_grid``) as flat arrays: ``n^2`` quads, 17-digit coords."""
    verts, faces = bench_grid(n)
    return verts.numpy(), faces.reshape(-1).numpy(), np.full(n * n, 4, dtype=np.int64)


def mixed_mesh() -> Mesh:
    """A small planar mesh of a quad, two triangles, a pentagon and a hexagon, in mixed order."""
    verts = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0], [0.5, -1, 0], [1.5, -1, 0],
         [2, 1.5, 0], [1.5, 2.1, 0], [0.5, 2.1, 0], [-0.5, 1.5, 0], [1.0, 0.5, 0.25]],
        dtype=np.float64,
    )  # fmt: skip
    faces = [[0, 1, 2, 3], [1, 4, 2], [0, 5, 6, 4, 1], [2, 4, 7], [3, 2, 7, 8, 9, 10]]
    return (verts, *flat_lists(faces))


def edge_cases(folder: Path) -> dict[str, Path]:
    """Small files exercising what real files contain; the mixed ones written by ``write_mesh``."""
    mesh = mixed_mesh()
    out = {}
    for label, fmt in (
        ("mixed degrees, OBJ", "obj"),
        ("mixed degrees, OFF", "off"),
        ("mixed degrees, ASCII PLY", "ply"),
        ("mixed degrees, binary PLY (list uchar int)", "plyb"),
    ):
        path = folder / f"mixed_{fmt}{FORMAT_EXT[fmt]}"
        ours_write(path, mesh, fmt)
        out[label] = path
    verts, indices, sizes = mesh
    vlines = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist())
    faces = np.split(indices + 1, np.cumsum(sizes)[:-1])

    def obj_faces(corner: Callable[[int, int], str]) -> str:
        return "".join(
            "f " + " ".join(corner(int(c), j) for j, c in enumerate(face)) + "\n" for face in faces
        )

    def plain(c: int, j: int) -> str:
        return str(c)

    texts = {
        "OFF with comments": (
            "off_comments.off",
            f"OFF\n# a comment line\n\n{len(verts)} {len(sizes)} 0  # counts\n"
            + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in verts.tolist())
            + "# faces\n"
            + "".join(
                f"{len(f)} " + " ".join(str(int(c) - 1) for c in f) + "  # face\n" for f in faces
            ),
        ),
        "OBJ v/vt/vn corners": (
            "obj_vtn.obj",
            vlines
            + "vt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\n"
            + obj_faces(lambda c, j: f"{c}/{j % 3 + 1}/1"),
        ),
        "OBJ negative indices": (
            "obj_negative.obj",
            vlines + obj_faces(lambda c, j: str(c - 1 - len(verts))),
        ),
        "OBJ groups, materials, objects": (
            "obj_groups.obj",
            "mtllib none.mtl\no first\n"
            + vlines
            + "g a\nusemtl red\ns 1\n"
            + "".join(obj_faces(plain).splitlines(True)[:2])
            + "o second\ng b\nusemtl blue\ns off\n"
            + "".join(obj_faces(plain).splitlines(True)[2:]),
        ),
        "OBJ CRLF line endings": (
            "obj_crlf.obj",
            (vlines + obj_faces(plain)).replace("\n", "\r\n"),
        ),
    }
    for label, (name, text) in texts.items():
        path = folder / name
        path.write_bytes(text.encode("ascii"))
        out[label] = path
    path = folder / "ply_big_endian.ply"
    path.write_bytes(big_endian_ply(mesh))
    out["big-endian PLY, float, list int uint, extra props"] = path
    return out


def big_endian_ply(mesh: Mesh) -> bytes:
    """Binary big-endian PLY: float32 x y z + normals + uchar colour; ``list int uint`` faces."""
    verts, indices, sizes = mesh
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment extra properties\n"
        f"element vertex {len(verts)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
        f"element face {len(sizes)}\nproperty list int uint vertex_indices\n"
        "property uchar flags\nend_header\n"
    ).encode("ascii")
    vrec = np.zeros(
        len(verts),
        dtype=[("p", ">f4", 3), ("n", ">f4", 3), ("red", "u1")],
    )
    vrec["p"] = verts
    vrec["n"] = (0, 0, 1)
    vrec["red"] = 200
    body = bytearray(vrec.tobytes())
    for face in np.split(indices, np.cumsum(sizes)[:-1]):
        body += np.array([len(face)], ">i4").tobytes() + face.astype(">u4").tobytes() + b"\x07"
    return header + bytes(body)


def malformed_cases(folder: Path) -> dict[str, Path]:
    """Broken files a reader should reject rather than return a wrong mesh from."""
    square = "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"
    texts = {
        "malformed: OFF face index out of range": (
            "bad_index.off",
            f"OFF\n4 1 0\n{square}4 0 1 2 7\n",
        ),
        "malformed: OFF coordinate 'x'": (
            "bad_number.off",
            "OFF\n4 1 0\n0 0 0\n1 0 x\n1 1 0\n0 1 0\n4 0 1 2 3\n",
        ),
        "malformed: OFF truncated (1 of 2 faces)": (
            "truncated.off",
            f"OFF\n4 2 0\n{square}4 0 1 2 3\n",
        ),
        "malformed: OBJ face index out of range": (
            "bad_index.obj",
            "".join("v " + line + "\n" for line in square.splitlines()) + "f 1 2 3 9\n",
        ),
        "malformed: OBJ coordinate 'x'": ("bad_number.obj", "v 0 0 0\nv 1 x 0\nv 1 1 0\nf 1 2 3\n"),
    }
    out = {}
    for label, (name, text) in texts.items():
        path = folder / name
        path.write_bytes(text.encode("ascii"))
        out[label] = path
    path = folder / "truncated.ply"
    ours_write(path, mixed_mesh(), "plyb")
    path.write_bytes(path.read_bytes()[:-10])
    out["malformed: binary PLY truncated (10 bytes short)"] = path
    return out


def bench_malformed(label: str, path: Path, libs: list[Library]) -> dict:
    """Whether ours and each library raise on a broken file (``"raises"``, for whatever reason:
    the message is kept as ``error``) or return a mesh."""

    def verdict(read: Callable[[Path], Mesh]) -> dict:
        def check() -> dict:
            verts, _, sizes = read(path)
            return {"verdict": f"returns a mesh (V={len(verts)}, F={len(sizes)})"}

        out = guarded(check, CHECK_TIMEOUT)
        if out["verdict"].startswith("error"):
            return {"verdict": "raises", "error": out["error"].replace(str(path.parent) + "/", "")}
        return out

    row = {"case": label, "file": path.name, "ours": verdict(ours_read), "libs": {}}
    for lib in libs:
        if path.suffix.lower() not in lib.reads:
            row["libs"][lib.name] = {"verdict": "n/a"}
        else:
            row["libs"][lib.name] = verdict(lib.read)
    return row


def real_meshes(real_dir: Path) -> dict[str, Path]:
    """``tests/data``'s top-level meshes and those of ``real_dir`` (its copy wins), by name."""
    found = {p.name: p for p in sorted((ROOT / "tests" / "data").iterdir())}
    if real_dir.is_dir():
        found.update({p.name: p for p in sorted(real_dir.iterdir())})
    else:
        print(f"{real_dir} not found: only tests/data's meshes are used", file=sys.stderr)
    return {name: p for name, p in sorted(found.items()) if p.suffix.lower() in MESH_EXTS}


# ---------------------------------------------------------------- measurements


def peak_memory(fn: Callable[[], object]) -> int:
    """Peak bytes allocated during ``fn()`` (tracemalloc: Python objects and numpy arrays; the
    file's bytes count, as they are read inside the call)."""
    tracemalloc.start()
    try:
        quietly(fn)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def time_call(fn: Callable[[], object], repeat: int) -> float:
    """Median seconds of ``fn`` (its first call, the correctness check, was the warm-up)."""
    return quietly(lambda: median_time(fn, repeat, warmup=False, min_sample_s=0.05))


def bench_read(
    label: str, path: Path, libs: list[Library], repeat: int, timing: bool, raw: bool = False
) -> dict:
    """Read ``path`` with ours and each library: the verdict and (``timing``) median seconds
    of the read (and with ``raw``, of the library's bare call)."""
    row = {"case": label, "file": path.name, "bytes": path.stat().st_size, "libs": {}}
    try:
        ref = quietly(lambda: ours_read(path))
    except Exception as e:  # a file ours rejects: say so and compare nothing
        row["ours"] = {"verdict": short_error(e)}
        return row
    row["V"], row["F"] = len(ref[0]), len(ref[2])
    row["degrees"] = sorted(set(ref[2].tolist()))
    row["ours"] = {"verdict": "reference"}
    if timing:
        row["ours"]["read_s"] = time_call(lambda: ours_read(path), repeat)
    if raw:
        row["ours"]["peak_bytes"] = peak_memory(lambda: ours_read(path))
    for lib in libs:
        if path.suffix.lower() not in lib.reads:
            row["libs"][lib.name] = {"verdict": "n/a"}
            continue
        print(f"  {lib.name} reads {path.name}", file=sys.stderr)
        entry = guarded(lambda lib=lib: {"verdict": compare(ref, lib.read(path))}, CHECK_TIMEOUT)
        row["libs"][lib.name] = entry
        if timing and not failed(entry):
            try:
                entry["read_s"] = time_call(lambda lib=lib: lib.read(path), repeat)
                if raw:
                    entry["raw_s"] = time_call(lambda lib=lib: lib.raw(path), repeat)
            except Exception as e:  # a reader that fails on a later call of the same file
                row["libs"][lib.name] = {"verdict": "later call: " + short_error(e)}
                continue
            entry["ratio"] = entry["read_s"] / row["ours"]["read_s"]
    return row


def bench_write(
    label: str, mesh: Mesh, fmt: str, folder: Path, libs: list[Library], repeat: int
) -> dict:
    """Write ``mesh`` as ``fmt`` with ours and each library; read each file back with ours."""
    row = {"case": label, "format": fmt, "F": len(mesh[2]), "libs": {}}
    path = folder / f"written_ours{FORMAT_EXT[fmt]}"
    row["ours"] = {"write_s": time_call(lambda: ours_write(path, mesh, fmt), repeat)}
    row["ours"]["verdict"] = compare(mesh, quietly(lambda: ours_read(path)))
    for lib in libs:
        if lib.write is None or fmt not in lib.writes:
            row["libs"][lib.name] = {"verdict": "n/a"}
            continue
        print(f"  {lib.name} writes {label} as {fmt}", file=sys.stderr)
        path = folder / f"written_{lib.name}{FORMAT_EXT[fmt]}"

        def check(lib: Library = lib, path: Path = path) -> dict:
            lib.write(path, mesh, fmt)
            try:
                verdict = compare(mesh, ours_read(path))
            except Exception as e:
                verdict = "read back: " + short_error(e, folder)
            return {"verdict": verdict, "bytes": path.stat().st_size}

        entry = guarded(check, CHECK_TIMEOUT)
        row["libs"][lib.name] = entry
        if failed(entry) and not entry["verdict"].startswith("read back"):
            continue
        entry["write_s"] = time_call(lambda lib=lib, path=path: lib.write(path, mesh, fmt), repeat)
        entry["ratio"] = entry["write_s"] / row["ours"]["write_s"]
        path.unlink()
    return row


def interleaved_grid(n: int, repeat: int, folder: Path) -> list[dict]:
    """Ours against lagrange on the ``n x n`` quad grid, the two calls alternating (A B A B) so
    that load from other processes hits both alike: median wall and CPU (process) seconds of
    each read (OBJ, OFF, ASCII PLY, as ``write_mesh`` writes them) and write (OBJ, ASCII PLY:
    lagrange writes no OFF), the ratios ours / lagrange, and the peak memory of one more call
    of ours (tracemalloc) over the file's size.  With pyarrow installed (the ``fast-text``
    extra), ours reads through it, and ours with numpy's parser alone ("numpy") is a third
    side of each read, in the same rounds; its peak is the one tracemalloc sees whole (it does
    not see pyarrow's buffers, which take the place of numpy arrays of the same size)."""
    import time

    grid = quad_grid(n)
    arrow = text_module._arrow() is not None
    rows = []
    for fmt in ("obj", "off", "ply"):
        path = folder / f"grid{FORMAT_EXT[fmt]}"
        ours_write(path, grid, fmt)
        cases = [
            ("read", fmt, lambda path=path: ours_read(path), lambda path=path: lagrange_raw(path))
        ]
        numpy_only = (lambda path=path: numpy_read(path)) if arrow else None
        if fmt in ("obj", "ply"):
            out = folder / f"lagrange{FORMAT_EXT[fmt]}"
            cases.append(
                (
                    "write",
                    fmt,
                    lambda path=path, fmt=fmt: ours_write(path, grid, fmt),
                    lambda out=out, fmt=fmt: lagrange_write(out, grid, fmt),
                )
            )
        for what, fmt_, ours, theirs in cases:
            sides = [("ours", ours), ("lagrange", theirs)]
            if what == "read" and numpy_only is not None:
                sides.append(("numpy", numpy_only))
            samples: dict[str, list[tuple[float, float]]] = {name: [] for name, _ in sides}
            for _, fn in sides:  # warm-up
                quietly(fn)
            for _ in range(repeat):
                for name, fn in sides:
                    wall, cpu = time.perf_counter(), time.process_time()
                    quietly(fn)
                    samples[name].append((time.perf_counter() - wall, time.process_time() - cpu))
            med = {k: np.median(np.array(v), axis=0) for k, v in samples.items()}
            peaks = {}
            for name, fn in sides:
                if name == "lagrange":
                    continue
                tracemalloc.start()  # numpy's arrays are traced too; the read's own peak
                quietly(fn)
                peaks[name] = tracemalloc.get_traced_memory()[1]
                tracemalloc.stop()
            rows.append(
                {
                    "op": what,
                    "format": FORMAT_NAME[fmt_],
                    "bytes": path.stat().st_size,
                    "ours_wall_s": float(med["ours"][0]),
                    "ours_cpu_s": float(med["ours"][1]),
                    "lagrange_wall_s": float(med["lagrange"][0]),
                    "lagrange_cpu_s": float(med["lagrange"][1]),
                    "ours_peak_bytes": peaks["ours"],
                    **(
                        {
                            "numpy_wall_s": float(med["numpy"][0]),
                            "numpy_cpu_s": float(med["numpy"][1]),
                            "numpy_peak_bytes": peaks["numpy"],
                        }
                        if "numpy" in med
                        else {}
                    ),
                }
            )
        if fmt != "obj":
            path.unlink()
    return rows


def interleaved_table(rows: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the interleaved comparison (ratios ours / lagrange); with the numpy
    side, its CPU time, ratio to lagrange and peak too ("–" for writes)."""
    head = ["op", "format", "ours wall", "lagrange wall", "ours/lagrange wall", "ours CPU",
            "lagrange CPU", "ours/lagrange CPU", "ours peak/file"]  # fmt: skip
    numpy_side = any("numpy_cpu_s" in r for r in rows)
    if numpy_side:
        head += ["numpy CPU", "numpy/lagrange CPU", "numpy peak/file"]
    table = []
    for r in rows:
        row = [
            r["op"], r["format"], fmt_time(r["ours_wall_s"]), fmt_time(r["lagrange_wall_s"]),
            f"{r['ours_wall_s'] / r['lagrange_wall_s']:.2f}", fmt_time(r["ours_cpu_s"]),
            fmt_time(r["lagrange_cpu_s"]), f"{r['ours_cpu_s'] / r['lagrange_cpu_s']:.2f}",
            f"{r['ours_peak_bytes'] / r['bytes']:.2f}",
        ]  # fmt: skip
        if numpy_side and "numpy_cpu_s" in r:
            row += [fmt_time(r["numpy_cpu_s"]), f"{r['numpy_cpu_s'] / r['lagrange_cpu_s']:.2f}",
                    f"{r['numpy_peak_bytes'] / r['bytes']:.2f}"]  # fmt: skip
        elif numpy_side:
            row += ["–", "–", "–"]
        table.append(row)
    return head, table


# ---------------------------------------------------------------- report

ABBREV = {
    "same": "ok",
    "n/a": "–",
}


def verdict_cell(entry: dict) -> str:
    return ABBREV.get(entry["verdict"], entry["verdict"])


def time_cell(entry: dict, key: str) -> str:
    """``"1.23x"`` (library / ours) with the verdict when it is not "same"; ``–`` if untimed."""
    if key not in entry:
        return "–" if entry["verdict"] == "n/a" else verdict_cell(entry).split(":")[0]
    cell = f"{entry['ratio']:.2f}x"
    return cell if entry["verdict"] == "same" else f"{cell} ({entry['verdict'].split(' (')[0]})"


def report(results: dict, libs: list[Library]) -> str:
    names = [lib.name for lib in libs]
    out = [
        f"Machine: {results['machine']['cpu']}, Python {results['machine']['python']}, "
        f"torch {results['machine']['torch']}, numpy {results['machine']['numpy']}; torch "
        f"pinned to 1 thread; median of {results['repeat']} samples "
        f"({results['grid_repeat']} on the quad grid). {results['machine']['cores']} cores; "
        f"1-minute load average {results['machine']['load_before']:.1f} at the start, "
        f"{results['machine']['load_after']:.1f} at the end (other processes slow every "
        "timing; ratios of calls timed minutes apart carry that noise).",
        "",
        "Versions: " + ", ".join(f"{lib.name} {lib.version}" for lib in libs),
        "",
        "### Correctness: what each library returns, against read_mesh",
        "",
    ]
    rows = [
        [r["case"], *(verdict_cell(r["libs"][n]) for n in names)]
        for r in results["edge_cases"] + results["real"] + results["grid_read"]
        if "libs" in r and r["libs"]
    ]
    out += [markdown_table(["file", *names], rows), ""]
    out += ["### Malformed files: an exception (for any reason), or a mesh", ""]
    rows = [
        [r["case"], r["ours"]["verdict"], *(verdict_cell(r["libs"][n]) for n in names)]
        for r in results["malformed"]
    ]
    out += [markdown_table(["file", "ours", *names], rows), ""]
    for title, key in (("real meshes", "real"), ("the quad grid", "grid_read")):
        out += [f"### Read times on {title}: ours, and each library's time over ours", ""]
        rows = []
        for r in results[key]:
            if "read_s" not in r["ours"]:
                continue
            cells = [time_cell(r["libs"][n], "read_s") for n in names]
            rows.append([r["case"], r["F"], fmt_time(r["ours"]["read_s"]), *cells])
        out += [markdown_table(["file", "F", "ours", *names], rows), ""]
    out += ["### Raw library call (no conversion to flat arrays) on the quad grid", ""]
    rows = []
    for r in results["grid_read"]:
        cells = []
        for n in names:
            e = r["libs"][n]
            cells.append(fmt_time(e["raw_s"]) if "raw_s" in e else "–")
        rows.append([r["case"], fmt_time(r["ours"]["read_s"]), *cells])
    out += [markdown_table(["file", "ours", *names], rows), ""]
    for r in results["grid_read"]:
        if "peak_bytes" in r["ours"]:
            peak = r["ours"]["peak_bytes"]
            out.append(
                f"* {r['case']}: read_mesh's peak memory {peak / 2**20:.0f} MiB, "
                f"{peak / r['bytes']:.1f}x the file's {r['bytes'] / 2**20:.0f} MiB"
            )
        if "plyfile_known_list_len_s" in r:
            seconds = r["plyfile_known_list_len_s"]
            out.append(
                f"* {r['case']}: plyfile with `known_list_len` (every face a quad, declared in "
                f"advance) {fmt_time(seconds)}, {seconds / r['ours']['read_s']:.2f}x ours"
            )
    out.append("")
    out += ["### Write times: ours, and each library's time over ours (read back by ours)", ""]
    wnames = [lib.name for lib in libs if lib.write is not None]
    rows = []
    for r in results["write"]:
        cells = [time_cell(r["libs"][n], "write_s") for n in wnames]
        ours = fmt_time(r["ours"]["write_s"])
        if r["ours"]["verdict"] != "same":
            ours += f" ({r['ours']['verdict']})"
        rows.append([r["case"], r["format"], r["F"], ours, *cells])
    out += [markdown_table(["mesh", "format", "F", "ours", *wnames], rows), ""]
    return "\n".join(out)


# the report's headings, and the names of their tables in the results file
TABLES = {
    "Correctness": "correctness",
    "Malformed": "malformed",
    "Read times on real meshes": "read_real",
    "Read times on the quad grid": "read_grid",
    "Raw library call": "raw_grid",
    "Write times": "write",
}


def report_tables(text: str) -> dict:
    """The tables of :func:`report`'s Markdown, by the names of :data:`TABLES`."""
    out = {}
    for section in text.split("\n### ")[1:]:
        heading, _, body = section.partition("\n")
        key = next((k for h, k in TABLES.items() if heading.startswith(h)), None)
        if key and "|" in body:
            table = table_from_markdown(body.split("\n\n* ")[0])
            if table["rows"]:
                out[key] = table
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--grid", type=int, default=1000, help="quad grid n (n^2 faces); 0: none")
    parser.add_argument("--repeat", type=int, default=5, help="timed samples per measurement")
    parser.add_argument("--grid-repeat", type=int, default=3, help="the same on the quad grid")
    parser.add_argument("--real-dir", type=Path, default=REAL_DIR)
    parser.add_argument("--no-real", action="store_true", help="skip tests/data and --real-dir")
    parser.add_argument(
        "--write-real", nargs="*", default=["rockerArm.obj", "lion_vase_poly.off"],
        help="real meshes also timed as writers (in every format)",
    )  # fmt: skip
    parser.add_argument(
        "--interleaved",
        action="store_true",
        help="only ours against lagrange on the --grid, alternating calls (wall and CPU time)",
    )
    parser.add_argument("--json", type=Path, help="default benchmarks/results/io.json")
    args = parser.parse_args(argv)
    meta = run_meta(threads=1)
    warnings.simplefilter("ignore", SkippedContentWarning)
    if args.interleaved:
        with pinned_threads(1), tempfile.TemporaryDirectory(prefix="bench_io_") as tmp:
            rows = interleaved_grid(args.grid, args.grid_repeat, Path(tmp))
        head, table = interleaved_table(rows)
        print(
            f"Quad grid {args.grid}x{args.grid}, ours and lagrange alternating, medians of "
            f"{args.grid_repeat} rounds, one thread.\n"
        )
        print(markdown_table(head, table))
        tables = {"interleaved": table_data(head, table)}
        path = args.json or RESULTS / "io_interleaved.json"
        write_results("io_interleaved", {"rows": rows, "tables": tables}, meta=meta, path=path)
        return

    libs = [lib for lib in LIBRARIES if lib.available]
    for lib in LIBRARIES:
        if not lib.available:
            print(f"{lib.name} is not installed: skipped", file=sys.stderr)
    results = {
        "machine": {
            "cpu": cpu_model(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "numpy": np.__version__,
            "cores": os.cpu_count(),
            "load_before": os.getloadavg()[0],
        },
        "repeat": args.repeat,
        "grid_repeat": args.grid_repeat,
        "versions": {lib.name: lib.version for lib in libs},
        "edge_cases": [],
        "malformed": [],
        "real": [],
        "grid_read": [],
        "write": [],
    }
    with pinned_threads(1), tempfile.TemporaryDirectory(prefix="bench_io_") as tmp:
        folder = Path(tmp)
        print("edge cases", file=sys.stderr)
        for label, path in edge_cases(folder).items():
            results["edge_cases"].append(bench_read(label, path, libs, args.repeat, False))
        for label, path in malformed_cases(folder).items():
            results["malformed"].append(bench_malformed(label, path, libs))
        if not args.no_real:
            print("real meshes", file=sys.stderr)
            meshes = real_meshes(args.real_dir)
            for name, path in meshes.items():
                results["real"].append(bench_read(name, path, libs, args.repeat, True))
            for name in args.write_real:
                if name not in meshes:
                    print(f"{name} not found: not timed as a writer", file=sys.stderr)
                    continue
                mesh = quietly(lambda path=meshes[name]: ours_read(path))
                for fmt in FORMAT_EXT:
                    results["write"].append(bench_write(name, mesh, fmt, folder, libs, args.repeat))
        if args.grid:
            n = args.grid
            label = f"quad grid {n}x{n}"
            print(label, file=sys.stderr)
            grid = quad_grid(n)
            for fmt in FORMAT_EXT:
                row = bench_write(label, grid, fmt, folder, libs, args.grid_repeat)
                results["write"].append(row)
                path = folder / f"written_ours{FORMAT_EXT[fmt]}"  # bench_write's file
                case = f"{label}, {FORMAT_NAME[fmt]}"
                row = bench_read(case, path, libs, args.grid_repeat, True, raw=True)
                if plyfile is not None and fmt in ("ply", "plyb"):
                    row["plyfile_known_list_len_s"] = time_call(
                        lambda path=path: plyfile_known_len(path, 4), args.grid_repeat
                    )
                results["grid_read"].append(row)
                path.unlink()
    results["machine"]["load_after"] = os.getloadavg()[0]
    text = report(results, libs)
    print(text)
    results["tables"] = report_tables(text)
    write_results("io", results, meta=meta, path=args.json)


if __name__ == "__main__":
    main()
