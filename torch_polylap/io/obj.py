"""Wavefront OBJ: ``v``/``f`` records, and on request ``vt``/``vn`` with per-corner references."""

from __future__ import annotations

import numpy as np

from .common import (
    BadNumber,
    Parsed,
    Skipped,
    check_faces,
    check_text,
    numbers,
    text_lines,
)
from .writers import face_block, vertex_block

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
    """Parse an OBJ file (any line ending, comments, ``\\`` continuations, negative indices)."""
    check_text(data, name, "OBJ")
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
    if key in ("g", "o") and (len(parts) == 1 or parts[1:] == ["default"]):
        return
    if key == "s" and parts[1:] in (["off"], ["0"]):
        return
    if key in _SKIPPED:
        skipped.add(_SKIPPED[key])
        skipped.attributes_hint |= key in ("vt", "vn")
    elif key in _FREE_FORM:
        skipped.add("free-form curves and surfaces")
    else:
        skipped.add("records with an unknown keyword", example=f"{key[:20]!r} at line {line}")


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


def obj_bytes(
    v: np.ndarray,
    indices: np.ndarray,
    sizes: np.ndarray,
    attributes: dict[str, np.ndarray],
) -> bytes:
    """OBJ text: ``vt``/``vn`` records and ``v/t/n`` corners when ``attributes`` has them."""
    blocks = [vertex_block(v, "v ")]
    if "uv" in attributes:
        blocks.append(_value_block(attributes["uv"], "vt"))
    if "normals" in attributes:
        blocks.append(_value_block(attributes["normals"], "vn"))
    corner_uv = attributes.get("corner_uv")
    corner_normals = attributes.get("corner_normals")
    if corner_uv is None and corner_normals is None:
        blocks.append(face_block(indices, sizes, base=1, prefix="f"))
    else:
        blocks.append(face_block(_corner_tokens(indices, corner_uv, corner_normals), sizes, "f"))
    return "".join(blocks).encode("ascii")


def _value_block(values: np.ndarray, prefix: str) -> str:
    if len(values) == 0:
        return ""
    line = prefix + " %.17g" * values.shape[1] + "\n"
    return (line * len(values)) % tuple(values.reshape(-1).tolist())


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
