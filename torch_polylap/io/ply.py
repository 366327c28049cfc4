"""Polygon File Format (Stanford PLY): ASCII and binary, any extra properties and elements.

ASCII bodies are read a chunk of lines at a time (:mod:`.text`): when an element has at most
one list property, a record's layout follows from its list length, and its values are
converted in one numpy call per chunk; records of elements with several lists, and broken ones
(whose messages name the line), are walked property by property.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .common import (
    BadNumber,
    Parsed,
    Skipped,
    check_count,
    check_faces,
    check_text,
    face_of,
    joined,
    plain_text,
)
from .text import Chunk, chunks, runs

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}
_FACE_LISTS = ("vertex_indices", "vertex_index")
_PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class PlyProperty:
    name: str
    dtype: str  # numpy type code without byte order, e.g. "f4"
    count_dtype: str | None = None  # set for list properties


@dataclass
class PlyElement:
    name: str
    count: int
    props: list[PlyProperty] = field(default_factory=list)

    def find(self, prop: str) -> PlyProperty | None:
        return next((p for p in self.props if p.name == prop), None)


# per-vertex attributes returned with return_attributes=True: property names by common writer
_NORMAL_NAMES = ("nx", "ny", "nz")
_UV_NAMES = (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))


def read_ply(data: bytes, name: str, skipped: Skipped, want_attributes: bool) -> Parsed:
    """Parse an ASCII or binary PLY; with ``want_attributes``, per-vertex normals
    (``nx ny nz``) and texture coordinates (``u v``, ``s t``, ``texture_u texture_v``)."""
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
    for el in elements:  # absurd counts (a record takes a byte); the readers name truncation
        if el.props:
            check_count(name, f"records of element {el.name!r}", el.count, len(data) - body)
    normals, uv = _vertex_attributes(vertex)
    wanted = {"vertex": {"x", "y", "z"}, "face": {face_list.name}}
    if want_attributes:
        wanted["vertex"] |= set(normals) | set(uv)
    _name_skipped(elements, wanted, skipped, bool(normals or uv) and not want_attributes)
    record_line: dict[str, np.ndarray] = {}  # ASCII PLY: each record's line, per element
    if fmt == "ascii":
        check_text(data[body:], name, "ASCII PLY", header_lines + 1)
        columns = _read_ply_ascii(data, body, header_lines, elements, wanted, name, record_line)
    else:  # each element's records, up to the first of each wanted name
        columns, pos = {}, body
        last = max(next(i for i, e in enumerate(elements) if e.name == w) for w in wanted)
        for el in elements[: last + 1]:
            want = wanted.get(el.name, set())
            cols, pos = binary_element(data, pos, _PLY_FORMATS[fmt], el, want, name)
            if el.name in wanted:
                columns[el.name] = cols

    def where(f: int) -> str:
        line = record_line.get("face")
        return (f"line {int(line[f])}: " if line is not None else "") + f"element 'face' record {f}"

    vcols = columns["vertex"]
    verts = np.stack([np.asarray(vcols[a], dtype=np.float64) for a in "xyz"], axis=1)
    values, counts = list_column(columns["face"][face_list.name])
    sizes = counts.astype(np.int64)
    if face_list.dtype[0] == "f":
        _check_whole(name, values, sizes, face_list.name, where)
    indices = values.astype(np.int64)
    check_faces(name, indices, sizes, len(verts), where)
    parsed = Parsed(verts, indices, sizes)
    for key, names in (("normals", normals), ("uv", uv)):
        if want_attributes and names:
            parsed.attributes[key] = np.stack(
                [np.asarray(vcols[n], dtype=np.float64) for n in names], 1
            )
            parsed.attributes["corner_" + key] = indices.copy()
    return parsed


def _check_whole(
    name: str, values: np.ndarray, sizes: np.ndarray, prop: str, where: Callable[[int], str]
) -> None:
    """Refuse a float-typed index list holding anything but whole numbers (``2.0`` is vertex
    2; ``2.9`` is no vertex: truncating it would silently pick another face)."""
    bad = ~(values == np.trunc(values)) | (np.abs(values) >= 2.0**62)
    if bad.any():
        corner = int(np.flatnonzero(bad)[0])
        f = face_of(sizes, corner)
        raise ValueError(
            f"{name}, {where(f)}: face {f} lists {float(values[corner])!r} in {prop!r}, which is "
            "no vertex index (a whole number): the file is corrupt or not a mesh; re-export it."
        )


def _vertex_attributes(vertex: PlyElement) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Names of the vertex's normal and texture-coordinate properties (empty when absent)."""

    def scalars(names: tuple[str, ...]) -> bool:
        return all((p := vertex.find(n)) is not None and p.count_dtype is None for n in names)

    normals = _NORMAL_NAMES if scalars(_NORMAL_NAMES) else ()
    uv = next((names for names in _UV_NAMES if scalars(names)), ())
    return normals, uv


def _name_skipped(
    elements: list[PlyElement], wanted: dict[str, set[str]], skipped: Skipped, hint: bool
) -> None:
    """Count the properties and elements the reader does not return, for the warning."""
    for el in elements:
        if el.name not in wanted:
            skipped.add(f"PLY element {el.name!r}", el.count)
            continue
        extra = [p.name for p in el.props if p.name not in wanted[el.name]]
        if extra:
            skipped.add(f"PLY {el.name} properties {' '.join(extra)}", el.count)
    skipped.attributes_hint |= hint


def _parse_ply_header(data: bytes, name: str) -> tuple[str, list[PlyElement], int, int]:
    """Format, elements, byte offset of the body, and number of header lines.

    The header's line ending (LF, CRLF or a lone CR) is the one ending the ``ply`` line; the
    body starts right after the ``end_header`` line's ending.
    """
    first = re.match(rb"ply[ \t]*(\r\n|\r|\n)", data)
    if first is None:
        raise ValueError(f"{name}: not a PLY file (it does not start with a 'ply' line).")
    newline = first.group(1)
    fmt = None
    elements: list[PlyElement] = []
    pos = first.end()
    no = 1
    while True:
        end = data.find(newline, pos)
        if end < 0:
            raise ValueError(
                f"{name}: the PLY header has no 'end_header' line (truncated or corrupt file)."
            )
        no += 1
        line = data[pos:end]
        pos = end + len(newline)
        if re.search(rb"[\x00-\x08\x0e-\x1f\x7f]", line):
            raise ValueError(
                f"{name}, line {no}: binary data in the PLY header (corrupt file); re-export or "
                "re-download it."
            )
        toks = line.decode("latin-1").split()
        if not toks or toks[0] in ("comment", "obj_info"):
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
                elements.append(PlyElement(toks[1], count))
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


def _parse_ply_property(toks: list[str], no: int, name: str) -> PlyProperty:
    def type_code(t: str) -> str:
        if t not in _PLY_TYPES:
            raise ValueError(
                f"{name}, line {no}: unknown PLY property type {t!r} "
                f"(known: {', '.join(_PLY_TYPES)})."
            )
        return _PLY_TYPES[t]

    if len(toks) == 3:
        return PlyProperty(toks[2], type_code(toks[1]))
    if len(toks) == 5 and toks[1] == "list":
        count = type_code(toks[2])
        if count[0] == "f":
            raise ValueError(f"{name}, line {no}: a list count type must be an integer type.")
        return PlyProperty(toks[4], type_code(toks[3]), count)
    raise ValueError(f"{name}, line {no}: malformed property line {' '.join(toks)!r}.")


# a scalar property's values, or a list property's (values, list lengths)
_Column = np.ndarray | tuple[np.ndarray, np.ndarray]
_Columns = dict[str, dict[str, _Column]]


def list_column(column: _Column) -> tuple[np.ndarray, np.ndarray]:
    """A column that the header declares a list (checked by the caller)."""
    assert isinstance(column, tuple)
    return column


def binary_element(
    data: bytes, pos: int, order: str, el: PlyElement, want: set[str], name: str
) -> tuple[dict[str, _Column], int]:
    """An element's records, of fixed length or, with list properties, of varying length.

    When every record's lists have the lengths of the first record's (no lists, all-triangle or
    all-quad faces), one structured ``frombuffer`` reads everything.  Otherwise a Python loop
    walks the records reading only the list lengths, and numpy gathers all values from those
    offsets.
    """
    if el.count == 0 or not el.props:  # no records, or records of no bytes
        return {p.name: _empty_column(p) for p in el.props if p.name in want}, pos
    uniform = _binary_uniform(data, pos, order, el, want, name)
    if uniform is not None:
        return uniform
    # per property: its (items') size, and for a list its length's size and reader
    layout = [(np.dtype(p.dtype).itemsize, *_length_reader(data, order, p)) for p in el.props]
    offsets: list[list[int]] = [[] for _ in el.props]
    p, size, record = pos, len(data), 0
    plan = list(zip(layout, offsets, strict=True))
    try:
        for record in range(el.count):
            for (item, count_size, read), starts in plan:
                starts.append(p)
                if read is None:
                    p += item
                    continue
                k = read(p)
                if k < 0:
                    raise ValueError(
                        f"{name}: PLY element {el.name!r} record {record} has a list of "
                        f"negative length {k}."
                    )
                p += count_size + k * item
                if p > size:
                    raise ValueError(
                        f"{name}: PLY element {el.name!r} record {record} declares a list of {k} "
                        f"values, but only {max(size - (p - k * item), 0)} bytes are left in the "
                        "file (truncated file, or a corrupt count); re-export or re-download it."
                    )
    except (IndexError, struct.error):
        p = size + 1
    if p > size:
        raise ValueError(
            f"{name}: the file ends before record {record} of the {el.count} records of PLY "
            f"element {el.name!r} is complete (truncated file)."
        )
    buf = np.frombuffer(data, np.uint8)
    cols: dict[str, _Column] = {}
    for prop, starts, (item, count_size, _) in zip(el.props, offsets, layout, strict=True):
        if prop.name not in want:
            continue
        at = np.asarray(starts, dtype=np.int64)
        if prop.count_dtype is None:
            cols[prop.name] = _gather(buf, at, order + prop.dtype)
            continue
        sizes = _gather(buf, at, order + prop.count_dtype).astype(np.int64)
        corners = np.repeat(at + count_size, sizes) + runs(np.zeros_like(at), sizes) * item
        cols[prop.name] = (_gather(buf, corners, order + prop.dtype), sizes)
    return cols, p


def _length_reader(
    data: bytes, order: str, prop: PlyProperty
) -> tuple[int, Callable[[int], int] | None]:
    """Size and reader (byte offset -> value) of a list's length; (0, None) for a scalar."""
    if prop.count_dtype is None:
        return 0, None
    if prop.count_dtype == "u1":
        return 1, data.__getitem__
    unpack = struct.Struct(order + _STRUCT_CODES[prop.count_dtype]).unpack_from
    return struct.calcsize(_STRUCT_CODES[prop.count_dtype]), lambda q: unpack(data, q)[0]


def _binary_uniform(
    data: bytes, pos: int, order: str, el: PlyElement, want: set[str], name: str
) -> tuple[dict[str, _Column], int] | None:
    """Read an element in one go if all its lists (if any) have the first record's lengths."""
    fields: list[tuple[Any, ...]] = []  # (name, dtype) or (name, dtype, shape)
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
        if k < 0 or p + count_dt.itemsize + k * np.dtype(prop.dtype).itemsize > len(data):
            return None  # the record-by-record walk says what is wrong
        lengths[i] = k
        fields.append((f"c{i}", count_dt))
        fields.append((f"p{i}", order + prop.dtype, (k,)))
        p += count_dt.itemsize + k * np.dtype(prop.dtype).itemsize
    dt = np.dtype(fields)
    available = (len(data) - pos) // dt.itemsize
    if available < el.count and not lengths:  # records of one size: the count says it all
        raise ValueError(
            f"{name}: PLY element {el.name!r} declares {el.count} records but the file ends "
            f"after {available} (truncated file)."
        )
    if available < el.count:
        return None
    rec = np.frombuffer(data, dt, el.count, pos)
    if not all((rec[f"c{i}"] == k).all() for i, k in lengths.items()):
        return None
    cols: dict[str, _Column] = {}
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


def _empty_column(prop: PlyProperty) -> _Column:
    if prop.count_dtype is None:
        return np.zeros(0, dtype=prop.dtype)
    return np.zeros(0, dtype=prop.dtype), np.zeros(0, dtype=np.int64)


def _read_ply_ascii(
    data: bytes,
    pos: int,
    header_lines: int,
    elements: list[PlyElement],
    wanted: dict[str, set[str]],
    name: str,
    record_line: dict[str, np.ndarray],
) -> _Columns:
    """Columns of the wanted elements of the ASCII body ``data[pos:]``, each record one
    non-blank line, read a chunk of lines at a time (the reader stops once it has them all);
    ``record_line`` gets the line number of each of their records."""
    # '#' starts no comment in a PLY body: a token holding one is no number
    if any(data.find(byte, pos) >= 0 for byte in (b"\r", b"\x85", b"\xa0")):
        text, begin = plain_text(data[pos:], comments=False), 0
    else:  # read in place: no copy of the file
        text, begin = data, pos
    spans: list[tuple[PlyElement, int]] = []  # the elements up to the last wanted, and rank
    rank = 0
    for el in elements:
        if {sp[0].name for sp in spans if sp[0].name in wanted} == set(wanted):
            break
        spans.append((el, rank))
        rank += el.count
    reader = {
        el.name: _AsciiElement(el, wanted[el.name], name) for el, _ in spans if el.name in wanted
    }
    seen = 0  # records (non-blank lines) before the chunk
    for chunk in chunks(text, begin, header_lines):
        if seen >= rank:
            break
        _, tokens, count, line_no = chunk.records()
        for el, first in spans:
            a, b = max(first - seen, 0), min(first + el.count - seen, len(count))
            if a < b and el.name in reader:
                reader[el.name].add(chunk, tokens[a:b], count[a:b], line_no[a:b], seen + a - first)
        seen += len(count)
    for el, first in spans:
        if first + el.count > seen:
            raise ValueError(
                f"{name}: PLY element {el.name!r} declares {el.count} records but the file ends "
                f"after {max(seen - first, 0)} (truncated file)."
            )
    out: _Columns = {}
    for key, element in reader.items():
        out[key] = element.columns()
        record_line[key] = joined(element.lines, np.int64)
    return out


class _AsciiElement:
    """The wanted properties of one ASCII PLY element, collected a chunk at a time."""

    def __init__(self, el: PlyElement, want: set[str], name: str) -> None:
        self.el = el
        self.want = want
        self.name = name
        lists = [i for i, p in enumerate(el.props) if p.count_dtype is not None]
        self.at = lists[0] if len(lists) == 1 else None  # the one list property
        self.walk = len(lists) > 1  # records laid out by every list's length: walked
        self.values: dict[str, list[np.ndarray]] = {}
        self.sizes: dict[str, list[np.ndarray]] = {}
        self.lines: list[np.ndarray] = []

    def _error(self, no: int, record: int, what: str) -> ValueError:
        return ValueError(f"{self.name}, line {no}: element {self.el.name!r} record {record}{what}")

    def add(
        self, chunk: Chunk, first: np.ndarray, count: np.ndarray, line_no: np.ndarray, record0: int
    ) -> None:
        """Read the records of ``chunk`` on lines ``line_no`` (first token and token count of
        each: see :meth:`Chunk.records`), the first being record ``record0`` of the element."""
        self.lines.append(line_no)
        layout = None if self.walk else self._layout(chunk, first, count)
        broken = None
        if layout is None:
            self.walk = True  # from here on: the walk names what is wrong
            layout, broken = self._walk(chunk, first, count)
        errors = []  # (record, message): the first in the file is raised
        for prop, (tokens, sizes) in layout.items():
            try:
                values = chunk.values(tokens, _kind(prop))
            except BadNumber as e:
                r = e.position
                if sizes is not None:
                    r = face_of(sizes, r)
                errors.append((r, f": cannot parse {prop.name!r} value {e.token!r}."))
                continue
            self.values.setdefault(prop.name, []).append(values)
            if sizes is not None:
                self.sizes.setdefault(prop.name, []).append(sizes)
        if broken is not None:
            errors.append(broken)
        if errors:
            r, what = min(errors)
            raise self._error(int(line_no[r]), record0 + r, what)

    def _layout(self, chunk: Chunk, first: np.ndarray, count: np.ndarray) -> _Layout | None:
        """The wanted properties' tokens (and list lengths) when each record has at most one
        list and fits the element (its layout then follows from the list length); else None."""
        n, at = len(self.el.props), self.at
        k = np.zeros(len(first), dtype=np.int64)
        if at is not None:
            if (count <= at).any():  # a record too short to hold the list's length
                return None
            try:
                k = chunk.values(first + at, int)
            except BadNumber:
                return None
        if (k < 0).any() or (count != n + k).any():
            return None
        out: _Layout = {}
        for i, prop in enumerate(self.el.props):
            if prop.name not in self.want:
                continue
            if i == at:
                out[prop] = (runs(first + at + 1, k), k)
            else:  # the scalars after the list sit k further
                out[prop] = (first + i + (k if at is not None and i > at else 0), None)
        return out

    def _walk(
        self, chunk: Chunk, first: np.ndarray, count: np.ndarray
    ) -> tuple[_Layout, tuple[int, str] | None]:
        """:meth:`_layout` record by record, property by property, up to the first record that
        does not fit the element, and that record and what is wrong with it (or None)."""
        tokens: dict[str, list[int]] = {p.name: [] for p in self.el.props if p.name in self.want}
        sizes: dict[str, list[int]] = {p.name: [] for p in self.el.props}
        broken = None
        for r, (t0, n) in enumerate(zip(first.tolist(), count.tolist(), strict=True)):
            got: dict[str, list[int]] = {name: [] for name in tokens}
            lengths: dict[str, int] = {}
            at = 0
            for prop in self.el.props:
                if prop.count_dtype is None:
                    got.get(prop.name, []).append(t0 + at)
                    at += 1
                    continue
                try:
                    if at >= n:
                        raise ValueError
                    k = int(chunk.text(int(chunk.start[t0 + at]), int(chunk.end[t0 + at])))
                except ValueError:
                    broken = (r, f": expected the length of list {prop.name!r}.")
                    break
                if k < 0:
                    broken = (r, f": list {prop.name!r} has negative length {k}.")
                    break
                got.get(prop.name, []).extend(range(t0 + at + 1, t0 + at + 1 + k))
                lengths[prop.name] = k
                at += 1 + k
            if broken is None and at != n:
                broken = (r, f" has {n} values, but its properties need {at}.")
            if broken is not None:
                break
            for name, more in got.items():
                tokens[name] += more
            for name, k in lengths.items():
                sizes[name].append(k)
        layout = {
            p: (
                np.asarray(tokens[p.name], dtype=np.int64),
                None if p.count_dtype is None else np.asarray(sizes[p.name], dtype=np.int64),
            )
            for p in self.el.props
            if p.name in tokens
        }
        return layout, broken

    def columns(self) -> dict[str, _Column]:
        """Each wanted property: an array (scalar) or (values, sizes) (list)."""
        cols: dict[str, _Column] = {}
        for prop in self.el.props:
            if prop.name in self.want:
                values = joined(self.values.get(prop.name, []), np.float64)
                if _kind(prop) is int:
                    values = values.astype(np.int64)
                sizes = joined(self.sizes.get(prop.name, []), np.int64)
                cols[prop.name] = values if prop.count_dtype is None else (values, sizes)
        return cols


# per wanted property: its token indices, and for a list each record's length
_Layout = dict[PlyProperty, tuple[np.ndarray, np.ndarray | None]]


def _kind(prop: PlyProperty) -> type:
    """How ASCII values are read: list items of an integer type as ints, all else as floats."""
    return int if prop.count_dtype is not None and prop.dtype[0] != "f" else float
