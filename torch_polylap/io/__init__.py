"""Reading and writing polygon meshes (OBJ, OFF, PLY) without triangulating them.

trimesh's loaders (and most other Python mesh readers) triangulate every polygon on load, which
destroys exactly the structure the polygon Laplacian is about.  The readers here keep each face
as written, in its cyclic order, and return it as :class:`~torch_polylap.faces.PolygonFaces`.

Reading never returns a partial or empty mesh without saying so.  Files that cannot describe a
polygon mesh (compressed or archived data, another format behind a wrong extension, binary
garbage, UTF-16 text, a file without faces, counts the file has no room for, a truncated file)
raise a :class:`ValueError` that names the file, the line (text formats) or the element and
record (PLY) at fault, and what to do.  What a file holds beyond positions and polygons
(texture coordinates, normals, groups, materials, colours, extra PLY properties) is named in
one :class:`SkippedContentWarning` per read; ``return_attributes=True`` returns texture
coordinates and normals.  Writing is atomic: a file is either the old one or the complete new
one, whatever happens during the write.

Modules: :mod:`.obj`, :mod:`.off`, :mod:`.ply` (one reader per format), :mod:`.text` (the
text readers' tokens and numbers: numpy's parser), :mod:`.common` (what they share),
:mod:`.writers` (text blocks, PLY).  The triangles that :func:`torch_polylap.interop.to_trimesh`
hands over come from :mod:`torch_polylap.triangulate`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, overload

import numpy as np
import torch

from .._typing import ArrayLike
from ..atomic import atomic_write
from ..checks import check_verts_array
from ..faces import FacesLike, PolygonFaces, as_faces
from .common import (
    MeshAttributes,
    Parsed,
    PathLike,
    Skipped,
    SkippedContentWarning,
    check_content,
    check_mesh,
    read_regular_file,
)
from .obj import obj_text, read_obj
from .off import read_off
from .ply import read_ply
from .writers import off_text, ply_text

__all__ = [
    "MeshAttributes",
    "SkippedContentWarning",
    "read_mesh",
    "write_mesh",
]

_READERS = {".obj": read_obj, ".off": read_off, ".ply": read_ply}
_SUPPORTED = tuple(_READERS)


@overload
def read_mesh(
    path: PathLike,
    dtype: torch.dtype = ...,
    device: torch.device | str | None = ...,
    *,
    return_attributes: Literal[False] = ...,
) -> tuple[torch.Tensor, PolygonFaces]: ...
@overload
def read_mesh(
    path: PathLike,
    dtype: torch.dtype = ...,
    device: torch.device | str | None = ...,
    *,
    return_attributes: Literal[True],
) -> tuple[torch.Tensor, PolygonFaces, MeshAttributes]: ...
@overload
def read_mesh(
    path: PathLike,
    dtype: torch.dtype = ...,
    device: torch.device | str | None = ...,
    *,
    return_attributes: bool = ...,
) -> tuple[torch.Tensor, PolygonFaces] | tuple[torch.Tensor, PolygonFaces, MeshAttributes]: ...
def read_mesh(
    path: PathLike,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    *,
    return_attributes: bool = False,
) -> tuple[torch.Tensor, PolygonFaces] | tuple[torch.Tensor, PolygonFaces, MeshAttributes]:
    """Read a polygon mesh from an OBJ, OFF or PLY file, keeping every face as a polygon.

    The format is chosen by the file extension (``.obj``, ``.off``, ``.ply``, any case); a file
    whose content is another of the three formats is an error that says which.  Supported: OBJ
    ``v``/``f`` records (``i``, ``i/t``, ``i//n``, ``i/t/n`` and negative indices); ASCII OFF
    with ``OFF``/``COFF``/``NOFF``/``CNOFF``/``STOFF`` headers and binary ``OFF BINARY``; PLY in
    ASCII and binary (little and big endian) with any extra properties and elements.  Text is
    read with LF, CRLF or CR line endings and an optional UTF-8 byte-order mark.

    Args:
        path: the file to read.
        dtype: floating dtype of the returned vertex tensor (and attributes).
        device: device of the returned vertex tensor (faces always stay on the CPU).
        return_attributes: also return :class:`MeshAttributes`: OBJ ``vt``/``vn`` with their
            per-corner references; PLY per-vertex ``nx ny nz`` and ``u v`` (or ``s t``,
            ``texture_u texture_v``).  OFF files give empty attributes.

    Returns:
        ``(verts, faces)``: a ``(V, 3)`` tensor of ``dtype`` on ``device`` and
        :class:`PolygonFaces` with 0-based int64 indices on the CPU; with
        ``return_attributes=True``, ``(verts, faces, attributes)``.

    Warns:
        SkippedContentWarning: once, naming everything in the file that is not returned.
        UserWarning: vertices with non-finite coordinates (they are returned as read).

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: a non-floating ``dtype``; unsupported extension; a directory or other
            non-regular file; content that is not a mesh of the extension's format; a
            malformed file: unparsable numbers, a face with fewer than 3 vertices or a vertex
            index out of range, fewer vertices or faces than the header declares (or more than
            the file has room for), no faces at all, a PLY without a ``face`` element holding
            ``vertex_indices``.

    Examples:
        A square and a triangle, written and read back unchanged:

        >>> import pathlib, tempfile
        >>> import torch
        >>> import torch_polylap as tp
        >>> verts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0.5, 0]],
        ...                      dtype=torch.float64)
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     path = pathlib.Path(folder) / "mesh.obj"
        ...     tp.write_mesh(path, verts, [[0, 1, 2, 3], [1, 4, 2]])
        ...     verts2, faces2 = tp.read_mesh(path)
        >>> torch.equal(verts2, verts), faces2.tolist()
        (True, [[0, 1, 2, 3], [1, 4, 2]])
    """
    if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
        raise ValueError(
            f"read_mesh: dtype must be a floating dtype such as torch.float64, got {dtype}; "
            "an integer dtype would truncate the coordinates."
        )
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise ValueError(
            f"{path}: unsupported mesh file extension {path.suffix!r}; "
            f"supported extensions are {', '.join(_SUPPORTED)}."
        )
    name = str(path)
    data = read_regular_file(path)
    check_content(data, name, path.suffix.lower())
    skipped = Skipped()
    parsed = reader(data, name, skipped, return_attributes)
    check_mesh(name, parsed, lambda v: f"vertex {v}")
    skipped.warn(name)
    verts = torch.from_numpy(parsed.verts).to(dtype=dtype, device=device)
    faces = PolygonFaces(torch.from_numpy(parsed.indices), sizes=torch.from_numpy(parsed.sizes))
    if not return_attributes:
        return verts, faces
    return verts, faces, _attributes_tensors(parsed, dtype, device)


def _attributes_tensors(
    parsed: Parsed, dtype: torch.dtype, device: torch.device | str | None
) -> MeshAttributes:
    out = MeshAttributes()
    for key, value in parsed.attributes.items():
        t = torch.from_numpy(value)
        setattr(out, key, t if key.startswith("corner_") else t.to(dtype=dtype, device=device))
    return out


def write_mesh(
    path: PathLike,
    verts: ArrayLike,
    faces: FacesLike,
    *,
    binary: bool = False,
    attributes: MeshAttributes | None = None,
) -> None:
    """Write a polygon mesh as OBJ, OFF or PLY, chosen by the file extension, atomically.

    Coordinates are written as Python's ``repr`` of each double (text formats: the shortest
    decimal that reads back as the same double) or as doubles (binary PLY), so reading the
    file back with ``dtype=torch.float64`` reproduces ``verts`` bit for bit.  The file is
    written to a temporary file in the same folder and moved onto ``path`` only once complete
    (see :func:`~torch_polylap.atomic.atomic_write`): an existing file is never left
    half-overwritten.

    Args:
        path: the file to write (replaced if it exists).
        verts: ``(V, 3)`` vertex positions, a tensor (detached and moved to the CPU) or an array.
        faces: anything :func:`~torch_polylap.faces.as_faces` accepts.
        binary: write a ``binary_little_endian`` PLY (double coordinates, ``uchar int``
            ``vertex_indices``, or ``int int`` when a face has more than 255 corners).
            Only valid for ``.ply``.
        attributes: texture coordinates and normals with per-corner references, written as OBJ
            ``vt``/``vn`` records and ``v/t/n`` corners (``.obj`` only); reading the file back
            with ``return_attributes=True`` reproduces them exactly.

    Raises:
        ValueError: unsupported extension, ``binary=True`` for a text-only format, attributes
            for a format other than OBJ, ``verts`` not of shape ``(V, 3)``, or a face, texture
            coordinate or normal index out of range.
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
    if attributes is not None and ext != ".obj":
        raise ValueError(
            f"{path}: attributes (texture coordinates, normals) can only be written to .obj files."
        )
    v = check_verts_array(verts)
    pf = as_faces(faces)
    indices = pf.indices.cpu().numpy()
    sizes = pf.sizes.cpu().numpy()
    _check_range(path, "vertex", indices, len(v), "vertices", pf)
    if ext == ".obj":
        text = obj_text(v, indices, sizes, _attributes_numpy(path, attributes, pf))
    elif ext == ".off":
        text = off_text(v, indices, sizes)
    else:
        text = ply_text(v, indices, sizes, binary)
    atomic_write(path, lambda f: f.writelines(text))


def _check_range(
    path: Path, what: str, refs: np.ndarray, count: int, of: str, pf: PolygonFaces, low: int = 0
) -> None:
    """Reject a corner reference outside ``[low, count)``, naming the face."""
    bad = (refs < low) | (refs >= count)
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        face = int(np.searchsorted(pf.offsets.cpu().numpy(), corner, side="right")) - 1
        raise ValueError(
            f"{path}: face {face} refers to {what} {int(refs[corner])}, "
            f"out of range for {count} {of}."
        )


def _attributes_numpy(
    path: Path, attributes: MeshAttributes | None, pf: PolygonFaces
) -> dict[str, np.ndarray]:
    """Attributes as float64 / int64 arrays, checked against the faces."""
    if attributes is None:
        return {}
    out: dict[str, np.ndarray] = {}
    for key, width in (("uv", 2), ("normals", 3)):
        values = getattr(attributes, key)
        corners = getattr(attributes, "corner_" + key)
        if values is not None:
            out[key] = np.asarray(_numpy(values), dtype=np.float64).reshape(-1, width)
        if corners is None:
            continue
        refs = np.asarray(_numpy(corners), dtype=np.int64).reshape(-1)
        if len(refs) != pf.num_corners:
            raise ValueError(
                f"{path}: corner_{key} has {len(refs)} entries, but the faces have "
                f"{pf.num_corners} corners."
            )
        # -1: a corner without this attribute
        _check_range(path, f"{key} row", refs, len(out.get(key, ())), f"{key} rows", pf, low=-1)
        out["corner_" + key] = refs
    return out


def _numpy(x: torch.Tensor | np.ndarray) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
