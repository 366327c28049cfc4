"""What the OBJ, OFF and PLY readers share: safe file access, content sniffing, number parsing,
face checks and the one warning about skipped content.  Atomic file replacement lives in
:mod:`torch_polylap.atomic` (the eigenpair cache and the command line use it too).

Every error is a :class:`ValueError` whose message starts with the file name (and the line or
record where that makes sense) and says what to do about it.
"""

from __future__ import annotations

import os
import re
import stat
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

__all__ = ["MeshAttributes", "SkippedContentWarning"]

PathLike = str | os.PathLike


class SkippedContentWarning(UserWarning):
    """A mesh file held data the reader does not return (texture coordinates, normals, groups,
    materials, colours, extra PLY properties...).  One is issued per read, naming everything
    skipped; filter this class to silence it."""


@dataclass
class MeshAttributes:
    """Texture coordinates and normals of a mesh, indexed per face corner (as OBJ stores them).

    Attributes:
        uv: ``(N_t, 2)`` texture coordinates, or ``None`` when the file has none.
        normals: ``(N_n, 3)`` normals, or ``None``.
        corner_uv: ``(C,)`` int64 row of ``uv`` for each face corner, packed like the faces'
            ``indices`` (``C = faces.num_corners``); ``-1`` for a corner without one.  ``None``
            when no corner refers to a texture coordinate.
        corner_normals: ``(C,)`` int64 row of ``normals`` per corner, ``-1`` for none, or
            ``None``.

    Per-vertex attributes (PLY ``nx ny nz``/``u v``) come as one row per vertex with the corner
    arrays equal to the faces' vertex indices.
    """

    uv: torch.Tensor | None = None
    normals: torch.Tensor | None = None
    corner_uv: torch.Tensor | None = None
    corner_normals: torch.Tensor | None = None


@dataclass
class Parsed:
    """What a format reader returns: ``verts (V, 3)`` float64, flat 0-based int64 ``indices``,
    int64 face ``sizes``, and the attributes in numpy form (``uv``, ``normals``,
    ``corner_uv``, ``corner_normals`` keys, only those present)."""

    verts: np.ndarray
    indices: np.ndarray
    sizes: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)


class Skipped:
    """What a reader did not return, collected while reading and reported in one warning."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.examples: dict[str, list[str]] = {}
        self.attributes_hint = False  # set when return_attributes=True would return some of it

    def add(self, what: str, count: int = 1, example: str | None = None) -> None:
        """Count ``count`` skipped items of kind ``what``; keep the first few ``example``s
        (e.g. unknown keywords and their lines) for the message."""
        if not count:
            return
        self.counts[what] = self.counts.get(what, 0) + count
        if example is not None:
            shown = self.examples.setdefault(what, [])
            if len(shown) < 3:
                shown.append(example)

    def warn(self, name: str) -> None:
        """Issue the one :class:`SkippedContentWarning` of this read, if anything was skipped."""
        if not self.counts:
            return
        items = ", ".join(
            f"{what} ({n}{': ' if what in self.examples else ''}"
            f"{', '.join(self.examples.get(what, []))})"
            for what, n in self.counts.items()
        )
        hint = ""
        if self.attributes_hint:
            hint = " Pass return_attributes=True to get texture coordinates and normals."
        warnings.warn(
            f"{name}: read vertex positions and polygons only; skipped {items}.{hint}",
            SkippedContentWarning,
            stacklevel=3,
        )


def read_regular_file(path: Path) -> bytes:
    """The bytes of ``path`` without a leading UTF-8 byte-order mark (some Windows editors write
    one), refusing directories, devices, FIFOs and sockets (reading those could block forever
    or never end)."""
    st = os.stat(path)  # FileNotFoundError for a missing file, as open() would raise
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(
            f"{path}: is a directory, not a mesh file; pass one .obj, .off or .ply file in it."
        )
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(
            f"{path}: is not a regular file (a device, FIFO or socket), so it may never end; "
            "copy the mesh into a regular file and read that."
        )
    return path.read_bytes().removeprefix(_UTF8_BOM)


# (magic bytes, what the data is, what to do)
_MAGIC = (
    (b"\x1f\x8b", "gzip-compressed data", "decompress it first (gunzip, or Python's gzip module)"),
    (b"PK\x03\x04", "a zip archive", "extract the mesh file from it first (unzip)"),
    (b"PK\x05\x06", "an empty zip archive", "extract the mesh file from the full archive"),
    (b"BZh", "bzip2-compressed data", "decompress it first (bunzip2, or Python's bz2 module)"),
    (b"\xfd7zXZ\x00", "xz-compressed data", "decompress it first (unxz, or Python's lzma module)"),
    (b"\x28\xb5\x2f\xfd", "zstd-compressed data", "decompress it first (unzstd)"),
    (b"7z\xbc\xaf\x27\x1c", "a 7-Zip archive", "extract the mesh file from it first (7z x)"),
    (b"Rar!", "a RAR archive", "extract the mesh file from it first (unrar)"),
    (b"glTF", "a binary glTF (.glb) file", "convert it to OBJ, OFF or PLY first"),
    (b"Kaydara FBX Binary", "an FBX file", "convert it to OBJ, OFF or PLY first"),
    (b"\xff\xfe", "UTF-16 (or UTF-32) text", "re-save it as UTF-8 or ASCII text"),
    (b"\xfe\xff", "UTF-16 text", "re-save it as UTF-8 or ASCII text"),
)
_UTF8_BOM = b"\xef\xbb\xbf"
_OBJ_KEYWORDS = {b"v", b"vt", b"vn", b"f", b"o", b"g", b"mtllib", b"usemtl", b"s"}
_OFF_HEADER = re.compile(rb"\s*(?:#[^\n\r]*[\r\n]+\s*)*(?:ST|C|N|4|n)*OFF(?:\s|$)")
_FORMAT_NAMES = {".obj": "an OBJ", ".off": "an OFF", ".ply": "a PLY"}


def check_content(data: bytes, name: str, ext: str) -> None:
    """Reject data that is no mesh of format ``ext`` with a message saying what it looks like.

    Catches compressed and archived files, other 3D formats, web pages, UTF-16 text, empty
    files and a mesh whose extension names another of the three formats.
    """
    fmt = _FORMAT_NAMES[ext]
    if not data or data.isspace():
        raise ValueError(f"{name}: the file is empty; the download or export did not finish.")
    for magic, what, todo in _MAGIC:
        if data.startswith(magic) and (magic != b"BZh" or data[3:4].isdigit()):
            raise ValueError(f"{name}: this looks like {what}, not {fmt} file: {todo}.")
    actual = sniff_format(data)
    # binary PLY and OFF bodies are full of NULs; their ASCII first line rules out UTF-16
    if actual is None and _looks_utf16(data[:256]):
        raise ValueError(
            f"{name}: this looks like UTF-16 text, not {fmt} file: re-save it as UTF-8 or ASCII."
        )
    head = data[:512].lstrip().lower()
    if head.startswith((b"<!doctype html", b"<html")):
        raise ValueError(
            f"{name}: this is an HTML page, not {fmt} file (a failed download or a link to a web "
            "page): download the mesh file itself."
        )
    if head.startswith(b"<?xml") or head.startswith(b"<collada"):
        raise ValueError(
            f"{name}: this is an XML file (COLLADA or X3D?), not {fmt} file: convert it to OBJ, "
            "OFF or PLY first."
        )
    if head.startswith(b"solid") and b"facet" in data[:4096]:
        raise ValueError(
            f"{name}: this looks like an ASCII STL file, not {fmt} file: STL holds only "
            "triangles; convert it or use the polygon mesh it was made from."
        )
    if actual is not None and actual != ext:
        raise ValueError(
            f"{name}: this looks like {_FORMAT_NAMES[actual]} file, not {fmt} file (the "
            f"extension is wrong): rename it to {Path(name).stem}{actual} and read that."
        )


def sniff_format(data: bytes) -> str | None:
    """``".ply"``, ``".off"`` or ``".obj"`` when the content clearly is that format, else None."""
    if re.match(rb"ply[ \t]*[\r\n]", data):
        return ".ply"
    if _OFF_HEADER.match(data[:4096]):
        return ".off"
    for line in re.split(rb"[\r\n]+", data[:4096])[:50]:
        toks = line.split(None, 1)
        if not toks or toks[0].startswith(b"#"):
            continue
        if toks[0] in _OBJ_KEYWORDS and len(toks) > 1 and toks[0] != b"s":
            return ".obj"
        break
    return None


def _looks_utf16(head: bytes) -> bool:
    """ASCII text stored as UTF-16 has a NUL in every other byte."""
    if len(head) < 8:
        return False
    even, odd = head[0::2], head[1::2]
    return even.count(0) > 0.4 * len(even) or odd.count(0) > 0.4 * len(odd)


# bytes that never occur in text meshes: NUL and the C0 controls other than tab, the line
# breaks, VT, FF and ESC (random bytes hit one with probability ~1/9 per byte)
_BINARY = bytes(range(9)) + bytes(range(14, 27)) + bytes(range(28, 32)) + b"\x7f"
_NOT_BINARY = bytes(set(range(256)) - set(_BINARY))


def check_text(data: bytes, name: str, fmt: str, first_line: int = 1) -> None:
    """Reject binary bytes in what must be text, naming the first line holding one."""
    found = data.translate(None, _NOT_BINARY)  # one C loop; the rare hit is then located
    if not found:
        return
    at = data.index(found[:1])
    line = first_line + data.count(b"\n", 0, at) + data.count(b"\r", 0, at)
    line -= data.count(b"\r\n", 0, at)
    raise ValueError(
        f"{name}, line {line}: binary data (byte 0x{data[at]:02x}) in a text {fmt} file: "
        "the file is corrupt, compressed or in another format; re-export or re-download it."
    )


_COMMENT = re.compile(rb"#[^\n]*")
_LATIN1_SPACES = bytes.maketrans(b"\x85\xa0", b"  ")


def plain_text(data: bytes, comments: bool = True) -> bytes:
    """``data`` as the text readers read it: ``\\n`` line breaks, ``#`` comments removed when
    ``comments`` (line breaks kept, so line numbers stay), and the non-ASCII bytes that
    ``str.split`` splits at on latin-1 text made spaces."""
    text = data
    if b"\r" in text:
        text = text.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if comments and b"#" in text:
        text = _COMMENT.sub(b"", text)
    if b"\x85" in text or b"\xa0" in text:
        text = text.translate(_LATIN1_SPACES)
    return text


def check_count(name: str, what: str, count: int, room: int, where: str = "the header") -> None:
    """Reject a declared element count the file has no room for (a corrupt header would
    otherwise ask for terabytes or loop for hours)."""
    if count > room:
        raise ValueError(
            f"{name}: {where} declares {count} {what}, but the file has room for at most {room}: "
            "the header is corrupt or the file truncated; re-export or re-download it."
        )


class BadNumber(Exception):
    """Position of the first token that is not a number, for locating it in the file."""

    def __init__(self, position: int, token: str) -> None:
        super().__init__(position, token)
        self.position = position
        self.token = token


def numbers(tokens: list[str], kind: type) -> np.ndarray:
    """Python's ``kind`` (float or int) of each token as float64 or int64, or which one broke."""
    out = np.zeros(len(tokens), dtype=np.float64 if kind is float else np.int64)
    for i, tok in enumerate(tokens):
        try:
            out[i] = kind(tok)
        except (ValueError, OverflowError):
            raise BadNumber(i, tok) from None
    return out


def joined(pieces: list[np.ndarray], dtype: type) -> np.ndarray:
    """The arrays ``pieces`` end to end (an empty one of ``dtype`` for none)."""
    return np.concatenate(pieces) if pieces else np.zeros(0, dtype=dtype)


def face_of(sizes: np.ndarray, corner: int) -> int:
    """The face holding packed corner ``corner``, of faces of ``sizes`` corners each."""
    return int(np.searchsorted(np.cumsum(sizes), corner, side="right"))


def check_faces(
    name: str,
    indices: np.ndarray,
    sizes: np.ndarray,
    num_verts: int,
    where: Callable[[int], str],
) -> None:
    """Reject faces with < 3 corners and indices outside ``[0, num_verts)``, naming the face."""
    if sizes.size and sizes.min() < 3:
        f = int(np.flatnonzero(sizes < 3)[0])
        raise ValueError(
            f"{name}, {where(f)}: face {f} has {int(sizes[f])} vertices; "
            "a polygon needs at least 3."
        )
    bad = (indices < 0) | (indices >= num_verts)
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        f = face_of(sizes, corner)
        raise ValueError(
            f"{name}, {where(f)}: face {f} refers to vertex {int(indices[corner])}, "
            f"out of range for the {num_verts} vertices in the file."
        )


def check_mesh(name: str, parsed: Parsed, where: Callable[[int], str]) -> None:
    """Reject a file without faces; warn about non-finite coordinates (naming the first)."""
    if parsed.sizes.size == 0:
        raise ValueError(
            f"{name}: the file holds {len(parsed.verts)} vertices but no faces (a point cloud, a "
            "line drawing, or a truncated file); a polygon Laplacian needs polygon faces."
        )
    if np.isfinite(parsed.verts).all():
        return
    finite = np.isfinite(parsed.verts).all(axis=1)
    v = int(np.flatnonzero(~finite)[0])
    warnings.warn(
        f"{name}, {where(v)}: {int((~finite).sum())} vertices have non-finite coordinates "
        f"(first: vertex {v}, {parsed.verts[v].tolist()}); fix them before building operators.",
        UserWarning,
        stacklevel=3,
    )
