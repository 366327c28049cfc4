"""Wavefront OBJ: ``v``/``f`` records, and on request ``vt``/``vn`` with per-corner references.

The text is read a chunk of lines at a time (:mod:`.text`): each line's keyword is classified
with numpy, the ``v``, ``vt``, ``vn`` and ``f`` records' numbers are converted in one numpy call
per chunk and kind, and only the other records (groups, materials...), which files hold few
of, are looked at line by line.  Every error names the line of the record at fault.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from .common import BadNumber, Parsed, Skipped, check_text, face_of, joined, plain_text
from .text import Chunk, chunks, runs
from .writers import Pieces, face_pieces, float_pieces

# Records that carry no polygon connectivity, as the skipped-content warning names them.
_SKIPPED = {key: f"{what} ({key})" for key, what in (
    ("vt", "texture coordinates"), ("vn", "normals"), ("vp", "parameter-space vertices"),
    ("g", "groups"), ("o", "objects"), ("s", "smoothing groups"), ("l", "polylines"),
    ("mtllib", "material libraries"), ("usemtl", "materials"), ("p", "points"),
)}  # fmt: skip
_FREE_FORM = {"cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim", "hole"}
_FREE_FORM |= {"scrv", "sp", "end", "con", "mg", "bevel", "c_interp", "d_interp", "lod"}
_FREE_FORM |= {"shadow_obj", "trace_obj", "ctech", "stech", "call", "csh", "maplib", "usemap"}
_EXTRA_VALUES = "vertex colours or weights (values after x y z)"
_CONTINUATION = re.compile(rb"\\[ \t\x0b\x0c]*(?:\n|$)")
_SLASH = 47
# per reference kind: its rows' name in messages, and the attributes key
_WHAT = {"vertex": "vertex", "uv": "texture coordinate", "normals": "normal"}


def read_obj(data: bytes, name: str, skipped: Skipped, want_attributes: bool) -> Parsed:
    """Parse an OBJ file (any line ending, comments, ``\\`` continuations, negative indices).

    A file whose last line is a ``v`` or ``f`` record without a line break after it may have
    been cut short in the middle of that record (a truncated download): it is read, with a
    warning naming the line.  A corner ending in ``/`` (``12/``, what is left of ``12/7`` cut
    short) is vertex 12 (the polyLaplace research code writes faces so).
    """
    check_text(data, name, "OBJ")
    reader = _ObjReader(name, want_attributes)
    for chunk in chunks(_join_continuations(plain_text(data), name)):
        counts = {kind: refs.count for kind, refs in reader.refs.items()}
        faces = reader.faces
        try:
            reader.add(chunk)
        except ValueError:
            # a chunk's errors are found kind by kind: line by line, the first one in the file
            probe = _ObjReader(name, want_attributes)
            for kind, refs in probe.refs.items():
                refs.count = counts[kind]
            probe.faces = faces
            for line in chunk.lines():
                probe.add(line)
            raise
    parsed = reader.finish(skipped)
    _warn_unterminated(data, name)
    return parsed


def _join_continuations(text: bytes, name: str) -> bytes:
    """``text`` with each line ending in ``\\`` joined to the next: the record on its first
    line, blank lines in place of the others, so that line numbers stay (comments are already
    cut, so a backslash ending a comment continues nothing)."""
    if b"\\" not in text or not _CONTINUATION.search(text):
        return text
    out: list[bytes] = []
    pending: bytes | None = None
    held = 0
    for line in text.split(b"\n"):
        if pending is not None:
            line = pending + line
        stripped = line.rstrip()
        if stripped.endswith(b"\\"):
            pending, held = stripped[:-1] + b" ", held + 1
            continue
        out += [line] + [b""] * held
        pending, held = None, 0
    if pending is not None:
        raise ValueError(f"{name}, line {len(out) + 1}: the file ends in a line continuation.")
    return b"\n".join(out)


def _warn_unterminated(data: bytes, name: str) -> None:
    """Warn when the file ends inside a ``v`` or ``f`` record: without the line break that
    ends every other line, its last number or corner may be missing."""
    tail = data[-4096:]
    cut = max(tail.rfind(b"\n"), tail.rfind(b"\r"))
    last = tail[cut + 1 :]
    if b"#" in last:  # the record ended where its comment began
        return
    keyword = last.split()[:1]
    if keyword not in ([b"v"], [b"f"]):
        return
    what = "face" if keyword == [b"f"] else "vertex"
    line = data.count(b"\n") + data.count(b"\r") - data.count(b"\r\n") + 1
    warnings.warn(
        f"{name}, line {line}: the file ends inside a {what} record (no line break after it); "
        f"if the file was cut short, that {what} may have lost corners or digits. Check the "
        "file is complete (re-download or re-export it).",
        UserWarning,
        stacklevel=4,
    )


@dataclass
class _Refs:
    """One kind of per-corner reference (vertex, texture coordinate, normal) as read so far:
    0-based rows, and the first corner whose negative reference counts back past the first
    row (a message needs the file's row count, known at the end only)."""

    rows: list[np.ndarray] = field(default_factory=list)
    count: int = 0  # rows (v, vt or vn records) read so far
    before_first: tuple[int, int] | None = None  # (corner, written reference)


class _ObjReader:
    """Collects the records of an OBJ file, a :class:`Chunk` at a time."""

    def __init__(self, name: str, want_attributes: bool) -> None:
        self.name = name
        self.want = want_attributes
        self.coords: list[np.ndarray] = []
        self.values: dict[str, list[np.ndarray]] = {"uv": [], "normals": []}
        self.refs = {"vertex": _Refs(), "uv": _Refs(), "normals": _Refs()}
        self.sizes: list[np.ndarray] = []
        self.face_lines: list[np.ndarray] = []
        self.found: list[tuple[int, str, int, str | None]] = []  # (line, what, count, example)
        self.hint = False
        self.faces = 0
        self.corners = 0

    def add(self, chunk: Chunk) -> None:
        """Read the records of ``chunk``."""
        lines, key, count, line_no = chunk.records()
        at = chunk.start.take(key)
        length = chunk.end.take(key) - at
        c0, c1 = chunk.buf.take(at), chunk.buf.take(np.minimum(at + 1, len(chunk.buf) - 1))
        is_v = (length == 1) & (c0 == 118)
        is_f = (length == 1) & (c0 == 102)
        is_vt = (length == 2) & (c0 == 118) & (c1 == 116)
        is_vn = (length == 2) & (c0 == 118) & (c1 == 110)
        for i in np.flatnonzero(~(is_v | is_f | is_vt | is_vn)).tolist():
            parts = chunk.line_text(int(lines[i])).split()
            record = _skipped_what(parts[0], parts, int(line_no[i]))
            if record is not None:
                self.found.append((int(line_no[i]), *record))
        kinds = {"vertex": is_v, "uv": is_vt, "normals": is_vn}
        # rows of each kind before each face line: negative references count back from them
        before = {kind: self.refs[kind].count + np.cumsum(m)[is_f] for kind, m in kinds.items()}
        for kind, m in kinds.items():
            if kind == "vertex" or self.want:
                self._rows(chunk, kind, lines[m], key[m], count[m] - 1, line_no[m])
            elif m.any():
                what = _SKIPPED["vt" if kind == "uv" else "vn"]
                self.found.append((int(line_no[np.argmax(m)]), what, int(m.sum()), None))
                self.hint = True
        self._faces(chunk, key[is_f], count[is_f] - 1, line_no[is_f], before)

    def _rows(
        self,
        chunk: Chunk,
        kind: str,
        lines: np.ndarray,
        key: np.ndarray,
        given: np.ndarray,
        line_no: np.ndarray,
    ) -> None:
        """``v`` (x, y, z; values after them skipped), ``vt`` (u, v; v defaults to 0, w is
        dropped) or ``vn`` (x, y, z) records, ``given`` values after their keywords."""
        width = 2 if kind == "uv" else 3
        short = given < (1 if kind == "uv" else 3)
        if short.any():
            i = int(np.argmax(short))
            needs = "a vertex needs 3 coordinates" if kind == "vertex" else (
                f"{chunk.line_text(int(lines[i])).split()[0]!r} needs {width} values"
            )  # fmt: skip
            raise ValueError(
                f"{self.name}, line {line_no[i]}: {needs}, got {chunk.line_text(int(lines[i]))!r}."
            )
        extra = given > 3
        if kind == "vertex" and extra.any():
            line = int(line_no[np.argmax(extra)])
            self.found.append((line, _EXTRA_VALUES, int(extra.sum()), None))
        values = np.zeros(len(key) * width)
        tokens = (key[:, None] + 1 + np.arange(width)).reshape(-1)
        pick: np.ndarray | slice = slice(None)  # every value given (vertices always)
        if (given < width).any():
            pick = np.flatnonzero((np.arange(width) < given[:, None]).reshape(-1))
        try:
            values[pick] = chunk.values(tokens[pick], float)
        except BadNumber as e:
            what = "vertex coordinate" if kind == "vertex" else f"{_WHAT[kind]} value"
            line = line_no[np.arange(len(tokens))[pick][e.position] // width]
            raise ValueError(
                f"{self.name}, line {line}: cannot parse {what} {e.token!r}."
            ) from None
        (self.coords if kind == "vertex" else self.values[kind]).append(values)
        self.refs[kind].count += len(key)

    def _faces(
        self,
        chunk: Chunk,
        key: np.ndarray,
        size: np.ndarray,
        line_no: np.ndarray,
        before: dict[str, np.ndarray],
    ) -> None:
        if (size < 3).any():
            f = int(np.argmax(size < 3))
            raise ValueError(
                f"{self.name}, line {line_no[f]}: face {self.faces + f} has {int(size[f])} "
                "vertices; a polygon needs at least 3."
            )
        corners = runs(key + 1, size)
        start, end = chunk.start.take(corners), chunk.end.take(corners)
        parts = {"vertex": (start, chunk.cut(start, end, _SLASH))}
        if self.want:
            first = parts["vertex"][1]
            second = chunk.cut(start, end, _SLASH, 1)
            third = chunk.cut(start, end, _SLASH, 2)
            parts["uv"] = (np.minimum(first + 1, end), second)
            parts["normals"] = (np.minimum(second + 1, end), third)
        for kind, (a, b) in parts.items():
            given = b > a  # an empty texture or normal reference: none
            written = np.zeros(len(a), dtype=np.int64)
            try:
                if kind == "vertex":  # most corners are the vertex alone: nothing to cut
                    cut = b if (b < end).any() else None
                    written = chunk.values(corners, int, end=cut)
                elif given.any():
                    written[given] = chunk.values(corners[given], int, a[given], b[given])
            except BadNumber as e:
                corner = e.position if kind == "vertex" else int(np.flatnonzero(given)[e.position])
                f = face_of(size, corner)
                raise ValueError(
                    f"{self.name}, line {line_no[f]}: face {self.faces + f} has an unparsable "
                    f"{_WHAT[kind]} index {e.token!r}."
                ) from None
            if kind == "vertex" and (written == 0).any():
                f = face_of(size, int(np.argmax(written == 0)))
                raise ValueError(
                    f"{self.name}, line {line_no[f]}: face {self.faces + f} refers to vertex 0, "
                    "but OBJ vertex indices start at 1 (negative indices count back from the "
                    "last vertex read)."
                )
            self._resolve(self.refs[kind], written, np.repeat(before[kind], size))
        self.sizes.append(size)
        self.face_lines.append(line_no)
        self.faces += len(size)
        self.corners += len(corners)

    def _resolve(self, refs: _Refs, written: np.ndarray, before: np.ndarray) -> None:
        """0-based rows of 1-based references (negative: back from ``before``; 0: none, -1)."""
        rows = written - 1
        negative = written < 0
        if negative.any():
            rows[negative] = before[negative] + written[negative]
            past = negative & (rows < 0)
            if past.any() and refs.before_first is None:
                corner = int(np.argmax(past))
                refs.before_first = (self.corners + corner, int(written[corner]))
        refs.rows.append(rows)

    def finish(self, skipped: Skipped) -> Parsed:
        """The mesh read; raises for references past the file's rows."""
        verts = joined(self.coords, np.float64).reshape(-1, 3)
        sizes = joined(self.sizes, np.int64)
        face_lines = joined(self.face_lines, np.int64)
        indices = self._checked("vertex", len(verts), sizes, face_lines)
        parsed = Parsed(verts, indices, sizes)
        if self.want:
            for kind, width in (("uv", 2), ("normals", 3)):
                values = joined(self.values[kind], np.float64).reshape(-1, width)
                rows = self._checked(kind, len(values), sizes, face_lines)
                if len(values):
                    parsed.attributes[kind] = values
                if (rows >= 0).any():
                    parsed.attributes["corner_" + kind] = rows
        for _, what, n, example in sorted(self.found, key=lambda item: item[0]):
            skipped.add(what, n, example)
        skipped.attributes_hint |= self.hint
        return parsed

    def _checked(
        self, kind: str, total: int, sizes: np.ndarray, face_lines: np.ndarray
    ) -> np.ndarray:
        """The rows of references of ``kind``, refusing one outside the ``total`` rows."""
        refs = self.refs[kind]
        rows = joined(refs.rows, np.int64)
        past = np.flatnonzero(rows >= total)
        bad = [(int(past[0]), int(rows[past[0]]) + 1)] if len(past) else []
        if refs.before_first is not None:
            bad.append(refs.before_first)
        if bad:
            corner, written = min(bad)
            f = face_of(sizes, corner)
            of = "vertices in the file" if kind == "vertex" else "in the file"
            raise ValueError(
                f"{self.name}, line {face_lines[f]}: face {f} refers to {_WHAT[kind]} {written}, "
                f"out of range for the {total} {of}."
            )
        return rows


def _skipped_what(key: str, parts: list[str], line: int) -> tuple[str, int, str | None] | None:
    """What :meth:`Skipped.add` gets for a record that is not returned, or None."""
    if key in ("g", "o") and (len(parts) == 1 or parts[1:] == ["default"]):
        return None
    if key == "s" and parts[1:] in (["off"], ["0"]):
        return None
    if key in _SKIPPED:
        return _SKIPPED[key], 1, None
    if key in _FREE_FORM:
        return "free-form curves and surfaces", 1, None
    return "records with an unknown keyword", 1, f"{key[:20]!r} at line {line}"


def obj_text(
    v: np.ndarray,
    indices: np.ndarray,
    sizes: np.ndarray,
    attributes: dict[str, np.ndarray],
) -> Pieces:
    """OBJ text: ``vt``/``vn`` records and ``v/t/n`` corners when ``attributes`` has them."""
    pieces = float_pieces(v, b"v ")
    if "uv" in attributes:
        pieces += float_pieces(attributes["uv"], b"vt ")  # exact, as the vertices
    if "normals" in attributes:
        pieces += float_pieces(attributes["normals"], b"vn ")
    corner_uv = attributes.get("corner_uv")
    corner_normals = attributes.get("corner_normals")
    if corner_uv is None and corner_normals is None:
        pieces += face_pieces(indices, sizes, base=1, prefix="f")
    else:
        pieces += face_pieces(_corner_tokens(indices, corner_uv, corner_normals), sizes, "f")
    return pieces


def _corner_tokens(
    indices: np.ndarray, corner_uv: np.ndarray | None, corner_normals: np.ndarray | None
) -> np.ndarray:
    """``v``, ``v/t``, ``v//n`` or ``v/t/n`` (1-based) for each corner, as strings."""
    n = len(indices)
    uv = np.full(n, -1, dtype=np.int64) if corner_uv is None else corner_uv
    nrm = np.full(n, -1, dtype=np.int64) if corner_normals is None else corner_normals
    tokens = (indices + 1).astype(str).astype(object)
    has_uv, has_n = uv >= 0, nrm >= 0
    tokens[has_uv | has_n] += "/"
    tokens[has_uv] += (uv[has_uv] + 1).astype(str).astype(object)
    tokens[has_n] += "/" + (nrm[has_n] + 1).astype(str).astype(object)
    return tokens
