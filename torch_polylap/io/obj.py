"""Wavefront OBJ: ``v``/``f`` records, and on request ``vt``/``vn`` with per-corner references.

Two parsers read the same files to the same result.  The bulk one (:func:`_read_obj_bulk`)
finds tokens and converts numbers with numpy, a chunk of lines at a time; it handles ``v``,
``vt``, ``vn`` and ``f`` records in bulk and loops in Python only over the other records
(groups, materials...), which files hold few of.  Whenever it meets something it does not
handle (line continuations, per-corner attributes on request) or anything wrong with the file,
it gives up and the line-by-line parser (:func:`_read_obj_lines`) reads the file instead: that
one is the reference, and the one whose messages name the offending line.
"""

from __future__ import annotations

import re
import warnings

import numpy as np

from .common import (
    BadNumber,
    Parsed,
    Skipped,
    check_faces,
    check_text,
    numbers,
    plain_text,
    text_lines,
)
from .float_text import float_pieces
from .tokens import Chunk, chunks, runs
from .writers import Pieces, face_pieces, vertex_block

# Records that carry no polygon connectivity, as the skipped-content warning names them.
_SKIPPED = {
    "vt": "texture coordinates (vt)",
    "vn": "normals (vn)",
    "vp": "parameter-space vertices (vp)",
    "g": "groups (g)",
    "o": "objects (o)",
    "s": "smoothing groups (s)",
    "mtllib": "material libraries (mtllib)",
    "usemtl": "materials (usemtl)",
    "l": "polylines (l)",
    "p": "points (p)",
}
_FREE_FORM = {"cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim", "hole"}
_FREE_FORM |= {"scrv", "sp", "end", "con", "mg", "bevel", "c_interp", "d_interp", "lod"}
_FREE_FORM |= {"shadow_obj", "trace_obj", "ctech", "stech", "call", "csh", "maplib", "usemap"}
_EXTRA_VALUES = "vertex colours or weights (values after x y z)"
_CONTINUATION = re.compile(rb"\\[ \t\x0b\x0c]*(?:\n|$)")


class _Corners:
    """Per-corner ``vt``/``vn`` references of the faces, collected when attributes are wanted."""

    def __init__(self) -> None:
        self.uv: list[str] = []
        self.normals: list[str] = []
        self.uv_before: list[int] = []  # negative references count back from those read so far
        self.normals_before: list[int] = []

    def add_face(self, toks: list[str], num_uv: int, num_normals: int) -> None:
        for tok in toks:
            parts = tok.split("/")
            self.uv.append(parts[1] if len(parts) > 1 and parts[1] else "0")
            self.normals.append(parts[2] if len(parts) > 2 and parts[2] else "0")
        self.uv_before.append(num_uv)
        self.normals_before.append(num_normals)


def read_obj(data: bytes, name: str, skipped: Skipped, want_attributes: bool) -> Parsed:
    """Parse an OBJ file (any line ending, comments, ``\\`` continuations, negative indices).

    A file whose last line is a ``v`` or ``f`` record without a line break after it may have
    been cut short in the middle of that record (a truncated download): it is read, with a
    warning naming the line.  A corner ending in ``/`` (``12/``, what is left of ``12/7`` cut
    short) is an error.
    """
    check_text(data, name, "OBJ")
    text = _plain_text(data)
    parsed = None
    if text is not None and not want_attributes:
        parsed = _read_obj_bulk(text, name, skipped)
    if parsed is None:
        parsed = _read_obj_lines(data, name, skipped, want_attributes)
    _warn_unterminated(data, name)
    return parsed


def _plain_text(data: bytes) -> bytes | None:
    """:func:`plain_text`, or None for line continuations (left to the line parser)."""
    text = plain_text(data)
    if text is None or (b"\\" in text and _CONTINUATION.search(text)):
        return None
    return text


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


def _read_obj_bulk(text: bytes, name: str, skipped: Skipped) -> Parsed | None:
    """Parse OBJ text prepared by :func:`_plain_text` in bulk; None when the file needs the
    line parser (for anything unusual, and for every error, whose message that one words).

    A chunk holding only ``v x y z`` lines, or only faces of one degree (the usual layout), is
    read as a block of consecutive tokens; any other chunk line by line in numpy (keywords
    classified per line, values through index arrays)."""
    coords: list[np.ndarray] = []
    indices: list[np.ndarray] = []
    sizes: list[np.ndarray] = []
    found: list[tuple[int, str, int, str | None]] = []  # (line, what, count, example)
    hint = False
    num_verts = 0
    for chunk in chunks(text):
        uniform = _uniform_block(chunk)
        if uniform is not None:  # only ``v x y z`` lines, or only faces of one degree
            keyword, rows, width = uniform
            start, end = chunk.block(0, rows, width, 1)
            try:
                if keyword == "v":
                    coords.append(chunk.floats_at(start, end))
                    num_verts += rows
                    continue
                written = chunk.ints_at(start, end, cut=47)
            except BadNumber:
                return None
            if not _resolve(written, num_verts):
                return None
            indices.append(written)
            sizes.append(np.full(rows, width - 1, dtype=np.int64))
            continue
        buf, per_line = chunk.buf, chunk.per_line
        lines = np.flatnonzero(per_line)
        key = chunk.first_token[lines]
        count = per_line[lines]
        at = chunk.start[key]
        length = chunk.end[key] - at
        c0, c1 = buf[at], buf[at + 1]
        is_v = (length == 1) & (c0 == 118)
        is_f = (length == 1) & (c0 == 102)
        is_vt = (length == 2) & (c0 == 118) & (c1 == 116)
        is_vn = (length == 2) & (c0 == 118) & (c1 == 110)
        line_no = chunk.line0 + lines + 1

        def note(mask: np.ndarray, what: str, line_no: np.ndarray = line_no) -> None:
            if mask.any():
                found.append((int(line_no[np.argmax(mask)]), what, int(mask.sum()), None))

        note(is_vt, _SKIPPED["vt"])
        note(is_vn, _SKIPPED["vn"])
        hint |= bool(is_vt.any() or is_vn.any())
        for i in np.flatnonzero(~(is_v | is_f | is_vt | is_vn)).tolist():
            parts = chunk.line_text(int(key[i]), int(count[i])).split()
            record = _skipped_what(parts[0], parts, int(line_no[i]))
            if record is not None:
                found.append((int(line_no[i]), *record))

        v_count = count[is_v]
        if (v_count < 4).any():
            return None
        note(v_count > 4, _EXTRA_VALUES, line_no[is_v])
        first = key[is_v]
        try:
            values = chunk.floats((first[:, None] + np.arange(1, 4)).reshape(-1))
        except BadNumber:
            return None
        coords.append(values)

        f_size = count[is_f] - 1
        corners = runs(key[is_f] + 1, f_size)
        try:  # "12/" and "12//" are vertex 12
            written = chunk.ints_at(*chunk.bounds(corners), cut=47)
        except BadNumber:
            return None
        if (written == 0).any():
            return None
        if (written < 0).any():  # negative indices count back from the vertices read so far
            before = num_verts + np.cumsum(is_v.astype(np.int64))[is_f]
            indices.append(np.where(written > 0, written - 1, np.repeat(before, f_size) + written))
        else:
            written -= 1
            indices.append(written)
        sizes.append(f_size)
        num_verts += len(first)

    verts = np.concatenate(coords).reshape(-1, 3) if coords else np.zeros((0, 3))
    index = np.concatenate(indices) if indices else np.zeros(0, dtype=np.int64)
    size = np.concatenate(sizes) if sizes else np.zeros(0, dtype=np.int64)
    if size.size and size.min() < 3:
        return None
    if index.size and (index.min() < 0 or index.max() >= len(verts)):
        return None
    for _, what, n, example in sorted(found, key=lambda item: item[0]):
        skipped.add(what, n, example)
    skipped.attributes_hint |= hint
    return Parsed(verts, index, size)


def _uniform_block(chunk: Chunk) -> tuple[str, int, int] | None:
    """``(keyword, lines, tokens per line)`` when every line of ``chunk`` is a ``v x y z``
    record, or every one an ``f`` record of the same degree (the usual layout: their values
    are then blocks of consecutive tokens); None otherwise."""
    first, count, _ = chunk.lines()
    lines = len(count)
    if lines == 0 or first[0] != 0:
        return None
    width = int(count[0])
    if width < 4 or not (count == width).all():
        return None
    key_start = chunk.start[: lines * width : width]
    if not (chunk.end[: lines * width : width] - key_start == 1).all():
        return None
    key = chunk.buf.take(key_start)
    if width == 4 and (key == 118).all():
        return "v", lines, width
    if (key == 102).all():
        return "f", lines, width
    return None


def _resolve(written: np.ndarray, num_verts: int) -> bool:
    """Turn OBJ's written indices (1-based, negative counting back from the ``num_verts``
    vertices read so far) into 0-based ones, in place; False for a 0 among them."""
    if written.size == 0:
        return True
    low = int(written.min())
    if low > 0:
        written -= 1
        return True
    if (written == 0).any():
        return False
    negative = written < 0
    written -= 1
    np.add(written, num_verts + 1, out=written, where=negative)
    return True


def _read_obj_lines(data: bytes, name: str, skipped: Skipped, want_attributes: bool) -> Parsed:
    """The line-by-line reference parser (every feature, and the messages of every error)."""
    coords: list[str] = []
    vert_lines: list[int] = []
    corners: list[str] = []
    sizes: list[int] = []
    face_lines: list[int] = []
    verts_before: list[int] = []  # negative indices count back from the vertices read so far
    uv: list[str] = []
    normals: list[str] = []
    refs = _Corners() if want_attributes else None
    pending = ""
    start = 0
    for no, line in enumerate(text_lines(data), 1):
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
            if len(parts) > 4:
                skipped.add("vertex colours or weights (values after x y z)")
        elif key == "f":
            # a corner "12/" is vertex 12 (the polyLaplace research code writes faces so); a
            # file cut in the middle of a face is caught by the last-line check instead
            toks = parts[1:]
            if refs is not None:
                refs.add_face(toks, len(uv) // 2, len(normals) // 3)
            if "/" in line:
                toks = [t.partition("/")[0] for t in toks]
            corners.extend(toks)
            sizes.append(len(toks))
            face_lines.append(start)
            verts_before.append(len(vert_lines))
        elif key == "vt" and refs is not None:
            _attribute_values(parts, 2, uv, name, start)
        elif key == "vn" and refs is not None:
            _attribute_values(parts, 3, normals, name, start)
        else:
            _skip_record(key, parts, skipped, start)
    if pending:
        raise ValueError(f"{name}, line {start}: the file ends in a line continuation.")

    try:
        verts = numbers(coords, float).reshape(-1, 3)
    except BadNumber as e:
        raise ValueError(
            f"{name}, line {vert_lines[e.position // 3]}: cannot parse vertex coordinate "
            f"{e.token!r}."
        ) from None
    size_arr = np.asarray(sizes, dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(size_arr)])

    def face_at(corner: int) -> int:
        return int(np.searchsorted(offsets, corner, side="right")) - 1

    try:
        written = numbers(corners, int)
    except BadNumber as e:
        f = face_at(e.position)
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} has an unparsable vertex index {e.token!r}."
        ) from None
    if (written == 0).any():
        f = face_at(int(np.flatnonzero(written == 0)[0]))
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} refers to vertex 0, but OBJ vertex indices "
            "start at 1 (negative indices count back from the last vertex read)."
        )
    before = np.repeat(np.asarray(verts_before, dtype=np.int64), size_arr)
    indices = np.where(written > 0, written - 1, before + written)
    check_faces(name, indices, size_arr, len(verts), lambda f: f"line {face_lines[f]}", written)
    parsed = Parsed(verts, indices, size_arr)
    if refs is not None:
        where = (name, face_lines, size_arr, face_at)
        _add_attribute(parsed, "uv", uv, 2, refs.uv, refs.uv_before, "texture coordinate", where)
        _add_attribute(
            parsed, "normals", normals, 3, refs.normals, refs.normals_before, "normal", where
        )
    return parsed


def _skip_record(key: str, parts: list[str], skipped: Skipped, line: int) -> None:
    """Count a record the reader does not return (a nameless group or ``s off`` loses nothing)."""
    what = _skipped_what(key, parts, line)
    if what is not None:
        skipped.add(*what)
        skipped.attributes_hint |= key in ("vt", "vn")


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


def _attribute_values(parts: list[str], width: int, out: list[str], name: str, line: int) -> None:
    """Append a ``vt`` (u, v; v defaults to 0, w is dropped) or ``vn`` (x, y, z) record."""
    values = parts[1 : 1 + width]
    if width == 2 and len(values) == 1:
        values.append("0")
    if len(values) < width:
        raise ValueError(
            f"{name}, line {line}: {parts[0]!r} needs {width} values, got {' '.join(parts)!r}."
        )
    out.extend(values)


def _add_attribute(
    parsed: Parsed,
    key: str,
    value_tokens: list[str],
    width: int,
    ref_tokens: list[str],
    ref_before: list[int],
    what: str,
    where: tuple,
) -> None:
    """Parse the values of one attribute and resolve its per-corner references (0 = none)."""
    name, face_lines, sizes, face_at = where
    try:
        values = numbers(value_tokens, float).reshape(-1, width)
    except BadNumber as e:
        raise ValueError(f"{name}: cannot parse {what} value {e.token!r}.") from None
    try:
        written = numbers(ref_tokens, int)
    except BadNumber as e:
        f = face_at(e.position)
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} has an unparsable {what} index {e.token!r}."
        ) from None
    before = np.repeat(np.asarray(ref_before, dtype=np.int64), sizes)
    refs = np.where(written > 0, written - 1, np.where(written < 0, before + written, -1))
    bad = (written != 0) & ((refs < 0) | (refs >= len(values)))
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        f = face_at(corner)
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} refers to {what} {int(written[corner])}, "
            f"out of range for the {len(values)} in the file."
        )
    if len(values):
        parsed.attributes[key] = values
    if (refs >= 0).any():
        parsed.attributes["corner_" + key] = refs


def obj_text(
    v: np.ndarray,
    indices: np.ndarray,
    sizes: np.ndarray,
    attributes: dict[str, np.ndarray],
) -> Pieces:
    """OBJ text: ``vt``/``vn`` records and ``v/t/n`` corners when ``attributes`` has them."""
    pieces = vertex_block(v, "v ")
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
