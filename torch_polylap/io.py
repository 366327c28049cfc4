"""Reading and writing polygon meshes (OBJ, OFF, PLY) without triangulating them.

trimesh's loaders (and most other Python mesh readers) triangulate every polygon on load, which
destroys exactly the structure the polygon Laplacian is about.  The readers here keep each face
as written, in its cyclic order, and return it as :class:`~torch_polylap.faces.PolygonFaces`.

Reading never validates geometry (non-finite coordinates, orientation, manifoldness): it only
rejects files that cannot describe a polygon mesh, with a :class:`ValueError` that names the file
and the line (text formats) or the element and record (PLY) at fault.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .faces import FacesLike, PolygonFaces, as_faces

if TYPE_CHECKING:
    import trimesh

__all__ = ["from_trimesh", "read_mesh", "to_trimesh", "write_mesh"]

PathLike = str | os.PathLike
ArrayLike = torch.Tensor | np.ndarray

_SUPPORTED = (".obj", ".off", ".ply")

# A reader returns (verts (V, 3) float64, flat 0-based int64 indices, int64 face sizes).
_Parsed = tuple[np.ndarray, np.ndarray, np.ndarray]


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


def read_mesh(
    path: PathLike,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, PolygonFaces]:
    """Read a polygon mesh from an OBJ, OFF or PLY file, keeping every face as a polygon.

    The format is chosen by the file extension (``.obj``, ``.off``, ``.ply``, any case).
    Supported: OBJ ``v``/``f`` records (``i``, ``i/t``, ``i//n``, ``i/t/n`` and negative
    indices); ASCII OFF with ``OFF``/``COFF``/``NOFF``/``CNOFF`` headers and binary ``OFF BINARY``;
    PLY in ASCII and binary (little and big endian) with any extra properties and elements.

    Args:
        path: the file to read.
        dtype: floating dtype of the returned vertex tensor.
        device: device of the returned vertex tensor (faces always stay on the CPU).

    Returns:
        ``(verts, faces)``: a ``(V, 3)`` tensor of ``dtype`` on ``device`` and
        :class:`PolygonFaces` with 0-based int64 indices on the CPU.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unsupported extension, or a malformed file: unparsable numbers, a face with
            fewer than 3 vertices or a vertex index out of range, fewer vertices or faces than
            the header declares, a PLY without a ``face`` element holding ``vertex_indices``.
    """
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise ValueError(
            f"{path}: unsupported mesh file extension {path.suffix!r}; "
            f"supported extensions are {', '.join(_SUPPORTED)}."
        )
    verts, indices, sizes = reader(path.read_bytes(), str(path))
    faces = PolygonFaces(torch.from_numpy(indices), sizes=torch.from_numpy(sizes))
    return torch.from_numpy(verts).to(dtype=dtype, device=device), faces


def write_mesh(path: PathLike, verts: ArrayLike, faces: FacesLike, *, binary: bool = False) -> None:
    """Write a polygon mesh as OBJ, OFF or PLY, chosen by the file extension.

    Coordinates are written with 17 significant digits (text formats) or as doubles (binary PLY),
    so reading the file back with ``dtype=torch.float64`` reproduces ``verts`` bit for bit.

    Args:
        path: the file to write (overwritten if it exists).
        verts: ``(V, 3)`` vertex positions, a tensor (detached and moved to the CPU) or an array.
        faces: anything :func:`~torch_polylap.faces.as_faces` accepts.
        binary: write a ``binary_little_endian`` PLY (double coordinates, ``uchar int``
            ``vertex_indices``, or ``int int`` when a face has more than 255 corners).
            Only valid for ``.ply``.

    Raises:
        ValueError: unsupported extension, ``binary=True`` for a text-only format, ``verts`` not
            of shape ``(V, 3)``, or a face index outside ``[0, V)``.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in _SUPPORTED:
        raise ValueError(
            f"{path}: unsupported mesh file extension {path.suffix!r}; "
            f"supported extensions are {', '.join(_SUPPORTED)}."
        )
    if binary and ext != ".ply":
        raise ValueError(f"{path}: binary=True is only supported for .ply files.")
    v = _verts_numpy(verts)
    pf = as_faces(faces)
    indices = pf.indices.cpu().numpy()
    sizes = pf.sizes.cpu().numpy()
    if indices.size and (indices.min() < 0 or indices.max() >= len(v)):
        bad = int(np.flatnonzero((indices < 0) | (indices >= len(v)))[0])
        face = int(np.searchsorted(pf.offsets.cpu().numpy(), bad, side="right")) - 1
        raise ValueError(
            f"{path}: face {face} refers to vertex {int(indices[bad])}, "
            f"out of range for {len(v)} vertices."
        )
    if ext == ".obj":
        text = _vertex_block(v, "v ") + _face_block(indices, sizes, base=1, prefix="f")
        path.write_bytes(text.encode("ascii"))
    elif ext == ".off":
        text = (
            f"OFF\n{len(v)} {len(sizes)} 0\n" + _vertex_block(v, "") + _face_block(indices, sizes)
        )
        path.write_bytes(text.encode("ascii"))
    else:
        path.write_bytes(_ply_bytes(v, indices, sizes, binary))


def from_trimesh(
    mesh: trimesh.Trimesh,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, PolygonFaces]:
    """Convert a :class:`trimesh.Trimesh` to ``(verts, faces)``.

    The result is a triangle mesh (trimesh only stores triangles); use :func:`read_mesh` to load
    polygon files without triangulating them.

    Args:
        mesh: the triangle mesh; its vertex order and face order are kept.
        dtype: floating dtype of the returned vertex tensor.
        device: device of the returned vertex tensor (faces stay on the CPU).

    Returns:
        ``(verts, faces)``: a ``(V, 3)`` tensor and :class:`PolygonFaces` of ``F`` triangles.

    Raises:
        TypeError: ``mesh`` is a :class:`trimesh.Scene` or not a mesh at all.
    """
    import trimesh

    if isinstance(mesh, trimesh.Scene):
        raise TypeError(
            "from_trimesh got a trimesh.Scene; merge it into one mesh first, e.g. with "
            "scene.to_geometry() or trimesh.load(path, force='mesh')."
        )
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"from_trimesh needs a trimesh.Trimesh, got {type(mesh).__name__}.")
    verts = torch.tensor(np.asarray(mesh.vertices, dtype=np.float64), dtype=dtype, device=device)
    return verts, as_faces(np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3))


def to_trimesh(verts: ArrayLike, faces: FacesLike) -> trimesh.Trimesh:
    """Fan-triangulate a polygon mesh into a :class:`trimesh.Trimesh` (for viewing or export).

    Face ``(c0, c1, ..., c_{k-1})`` becomes the ``k - 2`` triangles ``(c0, c_j, c_{j+1})``, in
    face order.  A fan from the first corner is only a faithful triangulation of convex (or
    mildly non-convex, nearly planar) faces; for strongly non-convex polygons its triangles
    overlap or leave the polygon.  The mesh is built with ``process=False`` so the vertex order,
    and hence per-vertex data, is kept.

    Args:
        verts: ``(V, 3)`` vertex positions (tensor or array).
        faces: anything :func:`~torch_polylap.faces.as_faces` accepts.

    Returns:
        A ``trimesh.Trimesh`` with ``V`` vertices and ``sum_f (k_f - 2)`` triangles.

    Raises:
        ValueError: ``verts`` is not of shape ``(V, 3)`` or ``faces`` cannot be interpreted.
    """
    import trimesh

    v = _verts_numpy(verts)
    pf = as_faces(faces)
    indices = pf.indices.cpu().numpy()
    sizes = pf.sizes.cpu().numpy()
    starts = pf.offsets.cpu().numpy()[:-1]
    per_face = sizes - 2
    first = np.repeat(starts, per_face)
    tri_start = np.cumsum(per_face) - per_face
    j = np.arange(int(per_face.sum())) - np.repeat(tri_start, per_face) + 1
    tris = np.stack([indices[first], indices[first + j], indices[first + j + 1]], axis=1)
    return trimesh.Trimesh(vertices=v, faces=tris, process=False)


# --------------------------------------------------------------------------------------------
# shared helpers
# --------------------------------------------------------------------------------------------


class _BadNumber(Exception):
    """Position of the first token that is not a number, for locating it in the file."""

    def __init__(self, position: int, token: str) -> None:
        super().__init__(position, token)
        self.position = position
        self.token = token


def _numbers(tokens: list[str], kind: type) -> np.ndarray:
    """Convert number tokens in one C-level pass; on failure say which token broke it."""
    dtype = np.float64 if kind is float else np.int64
    try:
        return np.array(tokens, dtype=dtype).reshape(-1)
    except (ValueError, OverflowError):
        for i, tok in enumerate(tokens):
            try:
                np.array(tok, dtype=dtype)
            except (ValueError, OverflowError):
                raise _BadNumber(i, tok) from None
        raise


def _check_faces(
    name: str,
    indices: np.ndarray,
    sizes: np.ndarray,
    num_verts: int,
    where: Callable[[int], str],
    written: np.ndarray | None = None,
) -> None:
    """Reject faces with < 3 corners and indices outside ``[0, V)``, naming the face."""
    if sizes.size and sizes.min() < 3:
        f = int(np.flatnonzero(sizes < 3)[0])
        raise ValueError(
            f"{name}, {where(f)}: face {f} has {int(sizes[f])} vertices; "
            "a polygon needs at least 3."
        )
    bad = (indices < 0) | (indices >= num_verts)
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        f = int(np.searchsorted(np.cumsum(sizes), corner, side="right"))
        shown = int((indices if written is None else written)[corner])
        raise ValueError(
            f"{name}, {where(f)}: face {f} refers to vertex {shown}, "
            f"out of range for the {num_verts} vertices in the file."
        )


def _content_lines(lines: list[str], start: int) -> Iterator[tuple[int, list[str]]]:
    """``(1-based line number, tokens)`` of each line from ``start`` that has data after
    removing ``#`` comments."""
    for no in range(start, len(lines)):
        line = lines[no]
        if "#" in line:
            line = line[: line.index("#")]
        toks = line.split()
        if toks:
            yield no + 1, toks


def _verts_numpy(verts: ArrayLike) -> np.ndarray:
    if isinstance(verts, torch.Tensor):
        v = verts.detach().cpu().to(torch.float64).numpy()
    else:
        v = np.asarray(verts, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"verts must have shape (V, 3), got {tuple(v.shape)}.")
    return v


# --------------------------------------------------------------------------------------------
# OBJ
# --------------------------------------------------------------------------------------------


def _read_obj(data: bytes, name: str) -> _Parsed:
    # latin-1 maps every byte to one character, so odd bytes in comments cannot fail decoding.
    lines = data.decode("latin-1").split("\n")
    coords: list[str] = []
    vert_lines: list[int] = []
    corners: list[str] = []
    sizes: list[int] = []
    face_lines: list[int] = []
    verts_before: list[int] = []  # negative indices count back from the vertices read so far
    pending = ""
    start = 0
    for no, line in enumerate(lines, 1):
        if pending:
            line = pending + line
        else:
            start = no
        # Comments are cut first so that a backslash at the end of a comment continues nothing.
        if "#" in line:
            line = line[: line.index("#")]
        if "\\" in line:
            stripped = line.rstrip()
            if stripped.endswith("\\"):
                pending = stripped[:-1] + " "
                continue
        pending = ""
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise ValueError(
                    f"{name}, line {start}: a vertex needs 3 coordinates, got {line.strip()!r}."
                )
            coords.extend(parts[1:4])
            vert_lines.append(start)
        elif key == "f":
            toks = parts[1:]
            if "/" in line:
                toks = [t.partition("/")[0] for t in toks]
            corners.extend(toks)
            sizes.append(len(toks))
            face_lines.append(start)
            verts_before.append(len(vert_lines))
        # Everything else (vt, vn, vp, g, o, s, usemtl, mtllib, l, p, crease tags...) carries
        # no polygon connectivity.
    if pending:
        raise ValueError(f"{name}, line {start}: the file ends in a line continuation.")

    try:
        verts = _numbers(coords, float).reshape(-1, 3)
    except _BadNumber as e:
        raise ValueError(
            f"{name}, line {vert_lines[e.position // 3]}: cannot parse vertex coordinate "
            f"{e.token!r}."
        ) from None
    size_arr = np.asarray(sizes, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(size_arr)])
    try:
        written = _numbers(corners, int)
    except _BadNumber as e:
        f = int(np.searchsorted(offsets, e.position, side="right")) - 1
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} has an unparsable vertex index {e.token!r}."
        ) from None
    if (written == 0).any():
        f = int(np.searchsorted(offsets, int(np.flatnonzero(written == 0)[0]), side="right")) - 1
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} refers to vertex 0, but OBJ vertex indices "
            "start at 1 (negative indices count back from the last vertex read)."
        )
    before = np.repeat(np.asarray(verts_before, dtype=np.int64), size_arr)
    indices = np.where(written > 0, written - 1, before + written)
    _check_faces(name, indices, size_arr, len(verts), lambda f: f"line {face_lines[f]}", written)
    return verts, indices, size_arr


# --------------------------------------------------------------------------------------------
# OFF
# --------------------------------------------------------------------------------------------

_OFF_KEYWORD = re.compile(r"(?:ST|C|N)*OFF")


def _read_off(data: bytes, name: str) -> _Parsed:
    first_end = data.find(b"\n")
    first = data[: first_end if first_end >= 0 else len(data)].decode("latin-1").split()
    if len(first) >= 2 and first[1].upper() == "BINARY" and _OFF_KEYWORD.fullmatch(first[0]):
        return _read_off_binary(data[first_end + 1 :], first[0], name)

    lines = data.decode("latin-1").split("\n")
    content = _content_lines(lines, 0)
    head = next(content, None)
    if head is None:
        raise ValueError(f"{name}: the file is empty.")
    no, toks = head
    keyword = toks[0]
    if _OFF_KEYWORD.fullmatch(keyword):
        toks = toks[1:]
        if not toks:
            head = next(content, None)
            if head is None:
                raise ValueError(f"{name}: the file ends after the {keyword!r} header.")
            no, toks = head
    elif keyword.endswith("OFF"):
        raise ValueError(
            f"{name}, line {no}: unsupported OFF variant {keyword!r} "
            "(supported: OFF, COFF, NOFF, CNOFF, STOFF and 'OFF BINARY')."
        )
    try:
        num_verts, num_faces = int(toks[0]), int(toks[1])
        if num_verts < 0 or num_faces < 0:
            raise ValueError
    except (ValueError, IndexError):
        raise ValueError(
            f"{name}, line {no}: expected the counts 'vertices faces [edges]', got "
            f"{' '.join(toks)!r}."
        ) from None

    # Only flat lists of strings and ints are kept: millions of retained per-line lists would
    # make the cyclic GC rescan them over and over.
    coords: list[str] = []
    vert_lines: list[int] = []
    for vno, vtoks in islice(content, num_verts):
        if len(vtoks) < 3:
            raise ValueError(
                f"{name}, line {vno}: a vertex needs 3 coordinates, got {' '.join(vtoks)!r}."
            )
        coords.extend(vtoks[:3])
        vert_lines.append(vno)
    if len(vert_lines) < num_verts:
        raise ValueError(
            f"{name}: the file ends after {len(vert_lines)} of the {num_verts} vertices "
            "declared in the header (truncated file)."
        )
    try:
        verts = _numbers(coords, float).reshape(-1, 3)
    except _BadNumber as e:
        raise ValueError(
            f"{name}, line {vert_lines[e.position // 3]}: cannot parse vertex coordinate "
            f"{e.token!r}."
        ) from None

    # Face records are a token stream: k, then k indices, possibly wrapped over several lines;
    # tokens left on the line where a record ends are its colour and are dropped.
    corners: list[str] = []
    sizes: list[int] = []
    face_lines: list[int] = []
    need = 0
    for fno, ftoks in content:
        if len(sizes) == num_faces and need == 0:
            raise ValueError(
                f"{name}, line {fno}: data after the {num_faces} faces declared in the header."
            )
        pos = 0
        if need == 0:
            try:
                need = int(ftoks[0])
            except ValueError:
                raise ValueError(
                    f"{name}, line {fno}: face {len(sizes)} starts with {ftoks[0]!r}, "
                    "expected its vertex count."
                ) from None
            if need < 3:
                raise ValueError(
                    f"{name}, line {fno}: face {len(sizes)} has {need} vertices; "
                    "a polygon needs at least 3."
                )
            sizes.append(need)
            face_lines.append(fno)
            pos = 1
        taken = ftoks[pos : pos + need]
        corners.extend(taken)
        need -= len(taken)
    if len(sizes) < num_faces or need:
        complete = len(sizes) - (1 if need else 0)
        raise ValueError(
            f"{name}: the file ends after {complete} of the {num_faces} faces declared in the "
            "header (truncated file)."
        )
    size_arr = np.asarray(sizes, dtype=np.int64)
    try:
        indices = _numbers(corners, int)
    except _BadNumber as e:
        f = int(np.searchsorted(np.cumsum(size_arr), e.position, side="right"))
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} has an unparsable vertex index {e.token!r}."
        ) from None
    _check_faces(name, indices, size_arr, num_verts, lambda f: f"line {face_lines[f]}")
    return verts, indices, size_arr


def _read_off_binary(body: bytes, keyword: str, name: str) -> _Parsed:
    """Binary OFF: int32 counts, float32 vertex records, int32 face records.

    Geomview's specification is big endian with a colour count (and colours) after each face;
    common writers (PMP, OpenMesh) use the machine's little endian and no colour count.  The
    byte order is the one giving plausible counts, the face layout the one that ends exactly at
    the end of the file.
    """
    floats_per_vert = 3 + 3 * ("N" in keyword) + 4 * ("C" in keyword) + 2 * ("ST" in keyword)
    if len(body) < 12:
        raise ValueError(f"{name}: binary OFF ends inside its counts (truncated file).")
    for order in ("<", ">"):
        num_verts, num_faces, _ = struct.unpack_from(order + "iii", body)
        if 0 <= num_verts and 0 <= num_faces and 12 + 4 * floats_per_vert * num_verts <= len(body):
            break
    else:
        raise ValueError(
            f"{name}: binary OFF counts do not fit the file size (truncated or not binary OFF)."
        )
    vert_end = 12 + 4 * floats_per_vert * num_verts
    verts = np.frombuffer(body, order + "f4", floats_per_vert * num_verts, 12)
    verts = verts.reshape(num_verts, floats_per_vert)[:, :3].astype(np.float64)
    words = np.frombuffer(body, order + "i4", (len(body) - vert_end) // 4, vert_end)
    for with_colours in (False, True):
        starts = _walk_off_faces(words, num_faces, with_colours)
        if starts is not None:
            break
    else:
        raise ValueError(
            f"{name}: binary OFF face records do not match the {num_faces} faces declared "
            "(truncated file or unknown layout)."
        )
    sizes = words[starts].astype(np.int64)
    _check_sizes_binary(name, sizes, "binary OFF face")
    first = np.repeat(starts + 1, sizes)
    within = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    indices = words[first + within].astype(np.int64)
    _check_faces(name, indices, sizes, num_verts, lambda f: f"binary OFF face record {f}")
    return verts, indices, sizes


def _walk_off_faces(words: np.ndarray, num_faces: int, with_colours: bool) -> np.ndarray | None:
    """Start of each face record in ``words``, or None if they do not end at the file's end."""
    if num_faces == 0:
        return np.zeros(0, dtype=np.int64) if len(words) == 0 else None
    k = int(words[0]) if len(words) else -1
    if not with_colours and k >= 0 and len(words) == num_faces * (k + 1):
        starts = np.arange(num_faces, dtype=np.int64) * (k + 1)
        if (words[starts] == k).all():
            return starts
    seq = words.tolist()
    starts_list = []
    p = 0
    n = len(seq)
    try:
        for _ in range(num_faces):
            starts_list.append(p)
            k = seq[p]
            if k < 0:
                return None
            p += k + 1
            if with_colours:
                p += seq[p] + 1
    except IndexError:
        return None
    return np.asarray(starts_list, dtype=np.int64) if p == n else None


def _check_sizes_binary(name: str, sizes: np.ndarray, what: str) -> None:
    if sizes.size and sizes.min() < 3:
        f = int(np.flatnonzero(sizes < 3)[0])
        raise ValueError(
            f"{name}, {what} {f}: face {f} has {int(sizes[f])} vertices; "
            "a polygon needs at least 3."
        )


# --------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}
_FACE_LISTS = ("vertex_indices", "vertex_index")
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class _PlyProperty:
    name: str
    dtype: str  # numpy type code without byte order, e.g. "f4"
    count_dtype: str | None = None  # set for list properties


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[_PlyProperty] = field(default_factory=list)

    def find(self, prop: str) -> _PlyProperty | None:
        return next((p for p in self.props if p.name == prop), None)


def _read_ply(data: bytes, name: str) -> _Parsed:
    fmt, elements, body, header_lines = _parse_ply_header(data, name)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    face = next((e for e in elements if e.name == "face"), None)
    if vertex is None:
        raise ValueError(f"{name}: the PLY header declares no 'vertex' element.")
    for axis in "xyz":
        prop = vertex.find(axis)
        if prop is None or prop.count_dtype is not None:
            raise ValueError(f"{name}: PLY element 'vertex' has no scalar property {axis!r}.")
    if face is None:
        raise ValueError(
            f"{name}: the PLY header declares no 'face' element, so the file holds no polygons."
        )
    face_list = next((face.find(n) for n in _FACE_LISTS if face.find(n) is not None), None)
    if face_list is None or face_list.count_dtype is None:
        raise ValueError(
            f"{name}: PLY element 'face' has no list property 'vertex_indices' "
            f"(or 'vertex_index'); its properties are {[p.name for p in face.props]}."
        )
    wanted = {"vertex": {"x", "y", "z"}, "face": {face_list.name}}
    if fmt == "ascii":
        columns = _read_ply_ascii(data, body, header_lines, elements, wanted, name)
    else:
        columns = _read_ply_binary(data, body, _PLY_FORMATS[fmt], elements, wanted, name)
    verts = np.stack([columns["vertex"][a].astype(np.float64) for a in "xyz"], axis=1)
    values, counts = columns["face"][face_list.name]
    indices = values.astype(np.int64)
    sizes = counts.astype(np.int64)
    _check_faces(name, indices, sizes, len(verts), lambda f: f"element 'face' record {f}")
    return verts, indices, sizes


def _parse_ply_header(data: bytes, name: str) -> tuple[str, list[_PlyElement], int, int]:
    """Format, elements, byte offset of the body, and number of header lines."""
    if not data.startswith(b"ply"):
        raise ValueError(f"{name}: not a PLY file (it does not start with 'ply').")
    fmt = None
    elements: list[_PlyElement] = []
    pos = 0
    no = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise ValueError(f"{name}: the PLY header has no 'end_header' line.")
        no += 1
        toks = data[pos:end].decode("latin-1").split()
        pos = end + 1
        if not toks or toks[0] in ("ply", "comment", "obj_info"):
            continue
        if toks[0] == "end_header":
            break
        if toks[0] == "format":
            if len(toks) < 2 or toks[1] not in _PLY_FORMATS:
                raise ValueError(
                    f"{name}, line {no}: unknown PLY format {' '.join(toks[1:])!r} "
                    f"(supported: {', '.join(_PLY_FORMATS)})."
                )
            fmt = toks[1]
        elif toks[0] == "element":
            try:
                count = int(toks[2])
                if count < 0:
                    raise ValueError
                elements.append(_PlyElement(toks[1], count))
            except (IndexError, ValueError):
                raise ValueError(
                    f"{name}, line {no}: expected 'element <name> <count>', got {' '.join(toks)!r}."
                ) from None
        elif toks[0] == "property":
            prop = _parse_ply_property(toks, no, name)
            if not elements:
                raise ValueError(f"{name}, line {no}: property before any element.")
            elements[-1].props.append(prop)
        else:
            raise ValueError(f"{name}, line {no}: unknown PLY header line {' '.join(toks)!r}.")
    if fmt is None:
        raise ValueError(f"{name}: the PLY header has no 'format' line.")
    return fmt, elements, pos, no


def _parse_ply_property(toks: list[str], no: int, name: str) -> _PlyProperty:
    def type_code(t: str) -> str:
        if t not in _PLY_TYPES:
            raise ValueError(
                f"{name}, line {no}: unknown PLY property type {t!r} "
                f"(known: {', '.join(_PLY_TYPES)})."
            )
        return _PLY_TYPES[t]

    if len(toks) == 3:
        return _PlyProperty(toks[2], type_code(toks[1]))
    if len(toks) == 5 and toks[1] == "list":
        count = type_code(toks[2])
        if count[0] == "f":
            raise ValueError(f"{name}, line {no}: a list count type must be an integer type.")
        return _PlyProperty(toks[4], type_code(toks[3]), count)
    raise ValueError(f"{name}, line {no}: malformed property line {' '.join(toks)!r}.")


_Columns = dict[str, dict[str, object]]


def _read_ply_binary(
    data: bytes,
    pos: int,
    order: str,
    elements: list[_PlyElement],
    wanted: dict[str, set[str]],
    name: str,
) -> _Columns:
    """Per wanted element, each wanted property: an array (scalar) or (values, sizes) (list)."""
    out: _Columns = {}
    for el in elements:
        if set(out) == set(wanted):
            break  # later elements (edges, materials...) are not needed
        if any(p.count_dtype is not None for p in el.props):
            cols, pos = _binary_list_element(data, pos, order, el, wanted.get(el.name, set()), name)
        else:
            cols, pos = _binary_fixed_element(
                data, pos, order, el, wanted.get(el.name, set()), name
            )
        if el.name in wanted:
            out[el.name] = cols
    return out


def _binary_fixed_element(
    data: bytes, pos: int, order: str, el: _PlyElement, want: set[str], name: str
) -> tuple[dict[str, object], int]:
    dt = np.dtype([(f"p{i}", order + p.dtype) for i, p in enumerate(el.props)])
    available = (len(data) - pos) // dt.itemsize if dt.itemsize else el.count
    if available < el.count:
        raise ValueError(
            f"{name}: PLY element {el.name!r} declares {el.count} records but the file ends "
            f"after {available} (truncated file)."
        )
    rec = np.frombuffer(data, dt, el.count, pos) if dt.itemsize else None
    cols = {p.name: rec[f"p{i}"] for i, p in enumerate(el.props) if p.name in want}
    return cols, pos + el.count * dt.itemsize


def _binary_list_element(
    data: bytes, pos: int, order: str, el: _PlyElement, want: set[str], name: str
) -> tuple[dict[str, object], int]:
    """An element with list properties: records of varying length.

    When every record's lists have the lengths of the first record's (all-triangle or all-quad
    faces), one structured ``frombuffer`` reads everything.  Otherwise a Python loop walks the
    records reading only the list counts, and numpy gathers all values from those positions.
    """
    if el.count == 0:
        return {p.name: _empty_column(p) for p in el.props if p.name in want}, pos
    uniform = _binary_uniform_lists(data, pos, order, el, want)
    if uniform is not None:
        return uniform

    # Records split into segments: segment j is the scalars before list j followed by list j;
    # the last segment is the scalars after the last list.
    lists = [i for i, p in enumerate(el.props) if p.count_dtype is not None]
    seg_of = np.searchsorted(lists, np.arange(len(el.props)))  # segment of each property
    seg_scalar_bytes = [0] * (len(lists) + 1)
    prop_offset: list[int] = []
    for i, prop in enumerate(el.props):
        prop_offset.append(seg_scalar_bytes[seg_of[i]])
        if prop.count_dtype is None:
            seg_scalar_bytes[seg_of[i]] += np.dtype(prop.dtype).itemsize
    readers: list[Callable[[int], int]] = []
    steps: list[tuple[int, int, int]] = []  # (scalar bytes before the count, count size, item size)
    for j, i in enumerate(lists):
        prop = el.props[i]
        if prop.count_dtype == "u1":
            readers.append(data.__getitem__)
        else:
            unpack = struct.Struct(order + _STRUCT_CODES[prop.count_dtype]).unpack_from
            readers.append(lambda q, unpack=unpack: unpack(data, q)[0])
        steps.append(
            (
                seg_scalar_bytes[j],
                np.dtype(prop.count_dtype).itemsize,
                np.dtype(prop.dtype).itemsize,
            )
        )
    tail = seg_scalar_bytes[-1]
    seg_starts: list[list[int]] = [[] for _ in range(len(lists) + 1)]
    # seg_starts has one more list (the tail after the last list property) than readers
    plan = list(zip(readers, steps, seg_starts, strict=False))
    last = seg_starts[-1]
    p = pos
    try:
        for record in range(el.count):
            for read, (before, count_size, item_size), starts in plan:
                starts.append(p)
                p += before
                k = read(p)
                if k < 0:
                    raise ValueError(
                        f"{name}: PLY element {el.name!r} record {record} has a list of "
                        f"negative length {k}."
                    )
                p += count_size + k * item_size
            last.append(p)
            p += tail
    except (IndexError, struct.error):
        p = len(data) + 1
    if p > len(data):
        record = min(len(last), el.count - 1)  # the first record not fully inside the file
        raise ValueError(
            f"{name}: the file ends before record {record} of the {el.count} records of PLY "
            f"element {el.name!r} is complete (truncated file)."
        )
    buf = np.frombuffer(data, np.uint8)
    cols: dict[str, object] = {}
    for i, prop in enumerate(el.props):
        if prop.name not in want:
            continue
        at = np.asarray(seg_starts[seg_of[i]], dtype=np.int64) + prop_offset[i]
        if prop.count_dtype is None:
            cols[prop.name] = _gather(buf, at, order + prop.dtype)
            continue
        sizes = _gather(buf, at, order + prop.count_dtype).astype(np.int64)
        _check_sizes_binary(name, sizes, f"element {el.name!r} record")
        item = np.dtype(prop.dtype).itemsize
        first = np.repeat(at + np.dtype(prop.count_dtype).itemsize, sizes)
        within = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        cols[prop.name] = (_gather(buf, first + within * item, order + prop.dtype), sizes)
    return cols, p


def _binary_uniform_lists(
    data: bytes, pos: int, order: str, el: _PlyElement, want: set[str]
) -> tuple[dict[str, object], int] | None:
    """Read a list element in one go if all its lists have the first record's lengths."""
    fields = []
    lengths: dict[int, int] = {}
    p = pos
    for i, prop in enumerate(el.props):
        if prop.count_dtype is None:
            fields.append((f"p{i}", order + prop.dtype))
            p += np.dtype(prop.dtype).itemsize
            continue
        count_dt = np.dtype(order + prop.count_dtype)
        if p + count_dt.itemsize > len(data):
            return None
        k = int(np.frombuffer(data, count_dt, 1, p)[0])
        if k < 0:
            return None
        lengths[i] = k
        fields.append((f"c{i}", count_dt))
        fields.append((f"p{i}", order + prop.dtype, (k,)))
        p += count_dt.itemsize + k * np.dtype(prop.dtype).itemsize
    dt = np.dtype(fields)
    if pos + el.count * dt.itemsize > len(data):
        return None
    rec = np.frombuffer(data, dt, el.count, pos)
    if not all((rec[f"c{i}"] == k).all() for i, k in lengths.items()):
        return None
    cols: dict[str, object] = {}
    for i, prop in enumerate(el.props):
        if prop.name not in want:
            continue
        if prop.count_dtype is None:
            cols[prop.name] = rec[f"p{i}"]
        else:
            sizes = np.full(el.count, lengths[i], dtype=np.int64)
            cols[prop.name] = (rec[f"p{i}"].reshape(-1), sizes)
    return cols, pos + el.count * dt.itemsize


def _gather(buf: np.ndarray, at: np.ndarray, dtype: str) -> np.ndarray:
    """Values of ``dtype`` stored (unaligned) at byte offsets ``at`` of ``buf``."""
    dt = np.dtype(dtype)
    raw = buf[at[:, None] + np.arange(dt.itemsize)]
    return raw.view(dt).reshape(-1)


def _empty_column(prop: _PlyProperty) -> object:
    if prop.count_dtype is None:
        return np.zeros(0, dtype=prop.dtype)
    return np.zeros(0, dtype=prop.dtype), np.zeros(0, dtype=np.int64)


def _read_ply_ascii(
    data: bytes,
    pos: int,
    header_lines: int,
    elements: list[_PlyElement],
    wanted: dict[str, set[str]],
    name: str,
) -> _Columns:
    lines = data[pos:].decode("latin-1").split("\n")
    # Records are found by line index; tokens are split from the line when needed, so no
    # per-record lists stay alive (millions of them make the cyclic GC rescan quadratically).
    records = [i for i, line in enumerate(lines) if line and not line.isspace()]
    out: _Columns = {}
    start = 0
    for el in elements:
        if set(out) == set(wanted):
            break
        rows = records[start : start + el.count]
        start += el.count
        if len(rows) < el.count:
            raise ValueError(
                f"{name}: PLY element {el.name!r} declares {el.count} records but the file ends "
                f"after {len(rows)} (truncated file)."
            )
        if el.name in wanted:
            table = _AsciiRows(lines, rows, header_lines + 1)
            out[el.name] = _ascii_element(table, el, wanted[el.name], name)
    return out


@dataclass
class _AsciiRows:
    """The records of one ASCII PLY element: ``lines[rows[r]]`` is record ``r``."""

    lines: list[str]
    rows: list[int]
    first_line: int  # file line number of lines[0]

    def line_no(self, record: int) -> int:
        return self.rows[record] + self.first_line


_Tokens = tuple[dict[str, list[str]], dict[str, list[int] | np.ndarray]]


def _ascii_element(
    table: _AsciiRows, el: _PlyElement, want: set[str], name: str
) -> dict[str, object]:
    """Wanted properties of an ASCII element: arrays (scalars) or (values, sizes) (lists)."""
    scalars, sizes = _ascii_tokens_fast(table, el, want) or _ascii_tokens(table, el, want, name)
    cols: dict[str, object] = {}
    for prop in el.props:
        if prop.name not in scalars:
            continue
        kind = int if prop.count_dtype is not None and prop.dtype[0] != "f" else float
        try:
            values = _numbers(scalars[prop.name], kind)
        except _BadNumber as e:
            record = e.position
            if prop.count_dtype is not None:
                record = int(np.searchsorted(np.cumsum(sizes[prop.name]), e.position, "right"))
            raise ValueError(
                f"{name}, line {table.line_no(record)}: element {el.name!r} record {record}: "
                f"cannot parse {prop.name!r} value {e.token!r}."
            ) from None
        if prop.count_dtype is None:
            cols[prop.name] = values
        else:
            cols[prop.name] = (values, np.asarray(sizes[prop.name], dtype=np.int64))
    return cols


def _ascii_tokens_fast(table: _AsciiRows, el: _PlyElement, want: set[str]) -> _Tokens | None:
    """Tokens of the wanted properties, column-wise, for elements with at most one list.

    Then a record's layout follows from its list length alone, so every record is sliced the
    same way and the lengths are checked afterwards, all at once.  None when some record does
    not fit (the caller's record-by-record walk then reports where).
    """
    lists = [i for i, p in enumerate(el.props) if p.count_dtype is not None]
    if len(lists) > 1:
        return None
    n = len(el.props)
    at = lists[0] if lists else n
    after = n - at - 1 if lists else 0
    # Scalars after the list are addressed from the end of the record.
    picks = [i if i < at else i - n for i, p in enumerate(el.props) if i != at and p.name in want]
    picked: list[str] = []
    counts: list[str] = []
    values: list[str] = []
    lengths: list[int] = []
    end = -after or None
    lines = table.lines
    try:
        for r in table.rows:
            toks = lines[r].split()
            lengths.append(len(toks))
            picked.extend([toks[i] for i in picks])
            if lists:
                counts.append(toks[at])
                values.extend(toks[at + 1 : end])
    except IndexError:
        return None
    length = np.asarray(lengths, dtype=np.int64)
    if lists:
        try:
            sizes = _numbers(counts, int)
        except _BadNumber:
            return None
        if (sizes < 0).any() or (length != at + 1 + after + sizes).any():
            return None
    elif (length != n).any():
        return None
    scalar_names = [p.name for i, p in enumerate(el.props) if i != at and p.name in want]
    scalars = {nm: picked[j :: len(picks)] for j, nm in enumerate(scalar_names)}
    if lists and el.props[at].name in want:
        scalars[el.props[at].name] = values
        return scalars, {el.props[at].name: sizes}
    return scalars, {}


def _ascii_tokens(table: _AsciiRows, el: _PlyElement, want: set[str], name: str) -> _Tokens:
    """Tokens of the wanted properties, walking each record property by property."""
    scalars: dict[str, list[str]] = {p.name: [] for p in el.props if p.name in want}
    sizes: dict[str, list[int]] = {
        p.name: [] for p in el.props if p.name in want and p.count_dtype is not None
    }
    for record, r in enumerate(table.rows):
        toks = table.lines[r].split()
        no = table.line_no(record)
        at = 0
        for prop in el.props:
            if prop.count_dtype is None:
                if prop.name in scalars:
                    scalars[prop.name].append(toks[at] if at < len(toks) else "")
                at += 1
                continue
            try:
                k = int(toks[at])
            except (IndexError, ValueError):
                raise ValueError(
                    f"{name}, line {no}: element {el.name!r} record {record}: expected the "
                    f"length of list {prop.name!r}."
                ) from None
            if k < 0:
                raise ValueError(
                    f"{name}, line {no}: element {el.name!r} record {record}: list "
                    f"{prop.name!r} has negative length {k}."
                )
            if prop.name in scalars:
                scalars[prop.name].extend(toks[at + 1 : at + 1 + k])
                sizes[prop.name].append(k)
            at += 1 + k
        if at != len(toks):
            raise ValueError(
                f"{name}, line {no}: element {el.name!r} record {record} has {len(toks)} values, "
                f"but its properties need {at}."
            )
    return scalars, sizes


# --------------------------------------------------------------------------------------------
# writers
# --------------------------------------------------------------------------------------------


def _vertex_block(v: np.ndarray, prefix: str) -> str:
    if len(v) == 0:
        return ""
    return ((prefix + "%.17g %.17g %.17g\n") * len(v)) % tuple(v.reshape(-1).tolist())


def _face_block(indices: np.ndarray, sizes: np.ndarray, base: int = 0, prefix: str = "") -> str:
    """One line per face, ``prefix`` (or the degree when empty) then the indices + ``base``.

    Faces are formatted one degree at a time with a single ``%`` per degree, then put back in
    file order.
    """
    if len(sizes) == 0:
        return ""
    starts = np.cumsum(sizes) - sizes
    lines = np.empty(len(sizes), dtype=object)
    for k in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == k)
        rows = indices[starts[sel][:, None] + np.arange(k)] + base
        line = (prefix or str(k)) + " %d" * k + "\n"
        lines[sel] = ((line * len(sel)) % tuple(rows.reshape(-1).tolist())).split("\n")[:-1]
    return "\n".join(lines.tolist()) + "\n"


def _ply_bytes(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray, binary: bool) -> bytes:
    count_type = "uchar" if len(sizes) == 0 or sizes.max() <= 255 else "int"
    header = (
        "ply\n"
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        "comment written by torch_polylap\n"
        f"element vertex {len(v)}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {len(sizes)}\n"
        f"property list {count_type} int vertex_indices\n"
        "end_header\n"
    ).encode("ascii")
    if not binary:
        return header + (_vertex_block(v, "") + _face_block(indices, sizes)).encode("ascii")
    count_size = 1 if count_type == "uchar" else 4
    # Each face record is its count followed by its int32 indices; place both by byte offset.
    starts = np.cumsum(sizes) - sizes
    record_at = starts * 4 + np.arange(len(sizes)) * count_size
    out = np.empty(len(sizes) * count_size + len(indices) * 4, dtype=np.uint8)
    counts = sizes.astype("<u1" if count_size == 1 else "<i4").view(np.uint8)
    out[(record_at[:, None] + np.arange(count_size)).reshape(-1)] = counts
    corner_at = np.repeat(record_at + count_size, sizes) + 4 * (
        np.arange(len(indices)) - np.repeat(starts, sizes)
    )
    out[(corner_at[:, None] + np.arange(4)).reshape(-1)] = indices.astype("<i4").view(np.uint8)
    return header + v.astype("<f8").tobytes() + out.tobytes()


_READERS: dict[str, Callable[[bytes, str], _Parsed]] = {
    ".obj": _read_obj,
    ".off": _read_off,
    ".ply": _read_ply,
}
