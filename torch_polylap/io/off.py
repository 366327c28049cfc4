"""Object File Format: ASCII ``OFF``/``COFF``/``NOFF``/``CNOFF``/``STOFF`` and ``OFF BINARY``.

ASCII bodies are read a chunk of lines at a time (:mod:`.text`): the vertex lines' numbers in
one numpy call per chunk, and the face records, when each sits on one line (the usual layout),
likewise.  Face records wrapped over several lines are followed token by token.  Every error
names the line of the record at fault.
"""

from __future__ import annotations

import re
import struct

import numpy as np

from .common import (
    BadNumber,
    Parsed,
    Skipped,
    check_count,
    check_faces,
    check_text,
    joined,
    plain_text,
)
from .ply import PlyElement, PlyProperty, binary_element, list_column
from .text import Chunk, chunks, runs

_OFF_KEYWORD = re.compile(r"(?:ST|C|N)*OFF")
_FIRST_LINE = re.compile(rb"([^\r\n]*)(\r\n|\r|\n|$)")
_LINE = re.compile(rb"[^\n]*\n?")


def _vertex_extras(keyword: str) -> str:
    """What the values after ``x y z`` of a vertex record are, by the header keyword."""
    flags = (("ST", "texture coordinates"), ("N", "normals"), ("C", "colours"))
    kinds = [kind for flag, kind in flags if flag in keyword]
    return "vertex " + " and ".join(kinds) if kinds else "extra vertex values (colours?)"


def read_off(data: bytes, name: str, skipped: Skipped, want_attributes: bool) -> Parsed:
    """Parse ASCII or binary OFF.  OFF files carry no per-corner attributes; per-vertex
    normals, colours and texture coordinates are skipped (and named in the warning)."""
    first = _FIRST_LINE.match(data)
    assert first is not None  # the pattern matches any input (possibly empty)
    toks = first.group(1).decode("latin-1").split()
    if len(toks) >= 2 and toks[1].upper() == "BINARY" and _OFF_KEYWORD.fullmatch(toks[0]):
        return _read_off_binary(data[first.end() :], toks[0], name, skipped)

    check_text(data, name, "OFF")
    text = plain_text(data)
    keyword, num_verts, num_faces, body, line0 = _header(text, name)
    # Only absurd counts are caught here (every record takes more than a byte); a merely
    # truncated file gets the precise message of the record readers below.
    check_count(name, "vertices", num_verts, len(data), f"line {line0}")
    check_count(name, "faces", num_faces, len(data), f"line {line0}")
    reader = _OffReader(name, num_verts, num_faces, len(text) - body)
    for chunk in chunks(text, body, line0):
        reader.add(chunk)
    return reader.finish(skipped, keyword)


def _header(text: bytes, name: str) -> tuple[str, int, int, int, int]:
    """``(keyword, vertices, faces, body's byte offset, counts' line)`` of ASCII OFF text."""
    found = (
        (m.end(), no, toks)
        for no, m in enumerate(_LINE.finditer(text), 1)
        if (toks := m.group().decode("latin-1").split())
    )
    pos, no, toks = next(found, (0, 0, []))
    if not toks:
        raise ValueError(f"{name}: the file holds only comments, no OFF header.")
    keyword = toks[0]
    if _OFF_KEYWORD.fullmatch(keyword):
        toks = toks[1:]
        if not toks:
            pos, no, toks = next(found, (0, 0, []))
            if not toks:
                raise ValueError(f"{name}: the file ends after the {keyword!r} header.")
    elif keyword.endswith("OFF"):
        raise ValueError(
            f"{name}, line {no}: unsupported OFF variant {keyword!r} "
            "(supported: OFF, COFF, NOFF, CNOFF, STOFF and 'OFF BINARY')."
        )
    else:
        keyword = ""
    try:
        num_verts, num_faces = int(toks[0]), int(toks[1])
        if num_verts < 0 or num_faces < 0:
            raise ValueError
    except (ValueError, IndexError):
        raise ValueError(
            f"{name}, line {no}: expected the counts 'vertices faces [edges]', got "
            f"{' '.join(toks)!r}."
        ) from None
    return keyword, num_verts, num_faces, pos, no


class _OffReader:
    """Collects the vertex and face records of an ASCII OFF body, a :class:`Chunk` at a time."""

    def __init__(self, name: str, num_verts: int, num_faces: int, room: int) -> None:
        self.name = name
        self.num_verts = num_verts
        self.num_faces = num_faces
        # rows for the vertex lines the body has room for ("x y z" and a line break: 6 bytes;
        # more are declared only by a truncated file, which fails before filling them)
        self.verts = np.empty((min(num_verts, (room + 1) // 6), 3))
        self.read = 0  # vertex lines read
        self.extra = 0  # vertex lines with values after x y z
        self.indices: list[np.ndarray] = []
        self.sizes: list[np.ndarray] = []
        self.face_lines: list[np.ndarray] = []
        self.faces = 0  # face records begun
        self.need = 0  # corners the last face record still lacks (wrapped over lines)
        self.coloured = 0

    def add(self, chunk: Chunk) -> None:
        """Read the records of ``chunk``."""
        lines, first, count, line_no = chunk.records()
        nv = min(self.num_verts - self.read, len(lines))
        if nv:
            self._vertices(chunk, lines[:nv], first[:nv], count[:nv], line_no[:nv])
        if nv < len(lines):
            self._faces(chunk, first[nv:], count[nv:], line_no[nv:])

    def _vertices(
        self,
        chunk: Chunk,
        lines: np.ndarray,
        first: np.ndarray,
        count: np.ndarray,
        line_no: np.ndarray,
    ) -> None:
        short = int(np.argmax(count < 3)) if (count < 3).any() else len(count)
        self.extra += int((count[:short] > 3).sum())
        tokens = (first[:short, None] + np.arange(3)).reshape(-1)
        try:  # the lines before a short one: the first error in the file is named
            values = chunk.values(tokens, float)
        except BadNumber as e:
            raise ValueError(
                f"{self.name}, line {line_no[e.position // 3]}: cannot parse vertex coordinate "
                f"{e.token!r}."
            ) from None
        if short < len(count):
            raise ValueError(
                f"{self.name}, line {line_no[short]}: a vertex needs 3 coordinates, got "
                f"{chunk.line_text(int(lines[short]))!r}."
            )
        self.verts[self.read : self.read + len(first)] = values.reshape(-1, 3)
        self.read += len(first)

    def _faces(
        self, chunk: Chunk, first: np.ndarray, count: np.ndarray, line_no: np.ndarray
    ) -> None:
        """Face lines: in bulk when each is one record ``k i1 .. ik [colour]``, else token-wise."""
        found = None if self.need else _one_per_line(chunk, first, count)
        if found is not None and self.faces + len(first) <= self.num_faces:
            sizes, corners, coloured, values = found
            starts = np.cumsum(sizes) - sizes
            self._add_faces(chunk, corners, sizes, starts, line_no, values)
            self.coloured += coloured
            return
        corner_list: list[int] = []
        sizes_list: list[int] = []
        lines_list: list[int] = []
        starts_list: list[int] = []

        def add() -> None:  # a record begun in an earlier chunk gets its later corners here:
            # in this chunk's numbering they come before its first record
            lists = (corner_list, sizes_list, starts_list, lines_list)
            self._add_faces(chunk, *(np.asarray(x, dtype=np.int64) for x in lists))

        for at, n, no in zip(first.tolist(), count.tolist(), line_no.tolist(), strict=True):
            pos = 0
            if self.need == 0:
                face = self.faces + len(sizes_list)
                token = chunk.text(int(chunk.start[at]), int(chunk.end[at]))
                try:
                    k: int | None = int(token)
                except ValueError:
                    k = None
                error = None
                if face == self.num_faces:
                    error = f"data after the {self.num_faces} faces declared in the header."
                elif k is None:
                    error = f"face {face} starts with {token!r}, expected its vertex count."
                elif k < 3:
                    error = f"face {face} has {k} vertices; a polygon needs at least 3."
                if error is not None or k is None:
                    add()  # an unparsable index before it is the first error
                    raise ValueError(f"{self.name}, line {no}: {error}")
                self.need = k
                sizes_list.append(self.need)
                lines_list.append(no)
                starts_list.append(len(corner_list))
                pos = 1
            take = min(self.need, n - pos)
            corner_list += range(at + pos, at + pos + take)
            self.need -= take
            self.coloured += self.need == 0 and pos + take < n
        add()

    def _add_faces(
        self,
        chunk: Chunk,
        corners: np.ndarray,
        sizes: np.ndarray,
        starts: np.ndarray,
        line_no: np.ndarray,
        values: np.ndarray | None = None,
    ) -> None:
        """Faces of ``sizes`` whose corners are the tokens ``corners`` (``values``, when
        already read), starting at ``starts`` of them, on lines ``line_no``."""
        try:
            self.indices.append(chunk.values(corners, int) if values is None else values)
        except BadNumber as e:
            f = int(np.searchsorted(starts, e.position, side="right")) - 1
            face = self.faces + f if f >= 0 else self.faces - 1
            no = int(line_no[f]) if f >= 0 else int(self.face_lines[-1][-1])
            raise ValueError(
                f"{self.name}, line {no}: face {face} has an unparsable vertex index {e.token!r}."
            ) from None
        self.sizes.append(sizes)
        self.face_lines.append(line_no)
        self.faces += len(sizes)

    def finish(self, skipped: Skipped, keyword: str) -> Parsed:
        """The mesh read; raises for a truncated file and indices out of range."""
        if self.read < self.num_verts:
            raise ValueError(
                f"{self.name}: the file ends after {self.read} of the {self.num_verts} vertices "
                "declared in the header (truncated file)."
            )
        if self.faces < self.num_faces or self.need:
            complete = self.faces - (1 if self.need else 0)
            raise ValueError(
                f"{self.name}: the file ends after {complete} of the {self.num_faces} faces "
                "declared in the header (truncated file)."
            )
        indices, sizes = joined(self.indices, np.int64), joined(self.sizes, np.int64)
        face_lines = joined(self.face_lines, np.int64)
        check_faces(self.name, indices, sizes, self.num_verts, lambda f: f"line {face_lines[f]}")
        skipped.add(_vertex_extras(keyword), self.extra)
        skipped.add("face colours", self.coloured)
        return Parsed(self.verts, indices, sizes)


def _one_per_line(
    chunk: Chunk, first: np.ndarray, count: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray | None] | None:
    """``(sizes, corner tokens, coloured faces, their values or None)`` when every line is
    one face record ``k i1 .. ik [colour]`` with ``k >= 3``, else None.  Lines of one degree
    without colours are read as one block of integers, ``k`` included."""
    if len(first) and (count == count[0]).all():  # one degree, no colours: a block of ints
        width = int(count[0])
        try:
            block = chunk.values(np.arange(first[0], first[0] + len(first) * width), int)
        except BadNumber:
            return None
        block = block.reshape(len(first), width)
        if width >= 4 and (block[:, 0] == width - 1).all():
            sizes = np.full(len(first), width - 1, dtype=np.int64)
            corners = (first[:, None] + np.arange(1, width)).reshape(-1)
            return sizes, corners, 0, block[:, 1:].reshape(-1)
    try:
        k = chunk.values(first, int)
    except BadNumber:
        return None
    if (k < 3).any() or (count < k + 1).any():
        return None
    return k, runs(first + 1, k), int((count > k + 1).sum()), None


def _read_off_binary(body: bytes, keyword: str, name: str, skipped: Skipped) -> Parsed:
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
            f"{name}: binary OFF counts do not fit the file size (truncated, corrupt, or not "
            "binary OFF); re-export or re-download it."
        )
    vert_end = 12 + 4 * floats_per_vert * num_verts
    check_count(name, "faces", num_faces, (len(body) - vert_end) // 16, "the binary OFF header")
    verts = np.frombuffer(body, order + "f4", floats_per_vert * num_verts, 12)
    verts = verts.reshape(num_verts, floats_per_vert)[:, :3].astype(np.float64)
    skipped.add(_vertex_extras(keyword), num_verts if floats_per_vert > 3 else 0)
    # the face records: a list of int32 indices after an int32 length, and Geomview's colours
    # another such list of floats
    corners = PlyProperty("vertex_indices", "i4", "i4")
    for props in ([corners], [corners, PlyProperty("colours", "f4", "i4")]):
        face = PlyElement("face", num_faces, props)
        try:
            cols, end = binary_element(body, vert_end, order, face, {p.name for p in props}, name)
        except ValueError:  # a negative length, or lists past the file's end
            continue
        if len(body) - end < 4:
            break
    else:
        raise ValueError(
            f"{name}: binary OFF face records do not match the {num_faces} faces declared "
            "(truncated file or unknown layout)."
        )
    values, sizes = list_column(cols["vertex_indices"])
    if len(props) > 1:
        skipped.add("face colours", int((list_column(cols["colours"])[1] > 0).sum()))
    indices = values.astype(np.int64)
    check_faces(name, indices, sizes, num_verts, lambda f: f"binary OFF face record {f}")
    return Parsed(verts, indices, sizes)
