"""Object File Format: ASCII ``OFF``/``COFF``/``NOFF``/``CNOFF``/``STOFF`` and ``OFF BINARY``.

ASCII files are read in bulk (:func:`_read_off_bulk`: numpy tokens and numbers, a chunk of lines
at a time) when every face record sits on one line; a face wrapped over several lines, and every
malformed file, is read by the record-by-record parser, the reference whose messages name the
offending line.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Iterator

import numpy as np

from .common import (
    BadNumber,
    Parsed,
    Skipped,
    check_count,
    check_faces,
    check_sizes_binary,
    check_text,
    content_lines,
    numbers,
    plain_text,
    text_lines,
)
from .numparse import Scratch, parse_decimal_block, parse_index_block
from .tokens import Chunk, chunks, runs

_OFF_KEYWORD = re.compile(r"(?:ST|C|N)*OFF")
_FIRST_LINE = re.compile(rb"([^\r\n]*)(\r\n|\r|\n|$)")


def _vertex_extras(keyword: str) -> str:
    """What the values after ``x y z`` of a vertex record are, by the header keyword."""
    kinds = [
        kind
        for flag, kind in (("ST", "texture coordinates"), ("N", "normals"), ("C", "colours"))
        if flag in keyword
    ]
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
    if text is not None:
        parsed = _read_off_bulk(text, name, skipped)
        if parsed is not None:
            return parsed
    content = content_lines(text_lines(data), 0)
    head = next(content, None)
    if head is None:
        raise ValueError(f"{name}: the file holds only comments, no OFF header.")
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
    # Only absurd counts are caught here (every record takes more than a byte); a merely
    # truncated file gets the precise message of the record loops below.
    check_count(name, "vertices", num_verts, len(data), f"line {no}")
    check_count(name, "faces", num_faces, len(data), f"line {no}")
    verts = _ascii_vertices(content, num_verts, name, skipped, keyword)
    indices, sizes, face_lines = _ascii_faces(content, num_faces, name, skipped)
    check_faces(name, indices, sizes, num_verts, lambda f: f"line {face_lines[f]}")
    return Parsed(verts, indices, sizes)


def _next_tokens(text: bytes, pos: int) -> tuple[list[str], int] | None:
    """The tokens of the first non-blank line from ``pos`` and the offset after it (None at
    the end of the text)."""
    toks: list[str] = []
    while not toks:
        if pos >= len(text):
            return None
        end = text.find(b"\n", pos)
        end = len(text) if end < 0 else end + 1
        toks, pos = text[pos:end].decode("latin-1").split(), end
    return toks, pos


def _header(text: bytes) -> tuple[str, int, int, int] | None:
    """``(keyword, vertices, faces, byte offset of the body)`` of prepared ASCII OFF text, or
    None when the header is anything but well formed (the reference parser says what)."""
    found = _next_tokens(text, 0)
    if found is None:
        return None
    toks, pos = found
    keyword = toks[0]
    if _OFF_KEYWORD.fullmatch(keyword):
        toks = toks[1:]
        if not toks:
            found = _next_tokens(text, pos)
            if found is None:
                return None
            toks, pos = found
    elif keyword.endswith("OFF"):
        return None
    else:
        keyword = ""
    try:
        num_verts, num_faces = int(toks[0]), int(toks[1])
    except (ValueError, IndexError):
        return None
    if not 0 <= num_verts <= len(text) or not 0 <= num_faces <= len(text):
        return None
    return keyword, num_verts, num_faces, pos


def _read_off_bulk(text: bytes, name: str, skipped: Skipped) -> Parsed | None:
    """ASCII OFF in bulk when each face is one line (``k i1 .. ik [colour]``); None for what
    the record parser must read (wrapped faces, and every error).

    Runs of ``x y z`` lines and of faces of one degree without colours (the usual layout) are
    read as blocks of consecutive tokens; other lines through per-line index arrays."""
    header = _header(text)
    if header is None:
        return None
    keyword, num_verts, num_faces, body = header
    if 6 * num_verts + 8 * num_faces > len(text) - body + 1:
        return None  # no room for the records ("x y z", "3 a b c" lines; the last may end the
        # file without its line break): truncated, and the record parser says so
    # The counts are known: values go straight to the arrays returned (no concatenation).
    verts = np.empty((num_verts, 3))
    coords = verts.reshape(-1)
    size = np.empty(num_faces, dtype=np.int64)
    # Faces of the first face's degree k, read as blocks, go straight into ``block`` (F * k);
    # the first other face switches to pieces joined at the end.
    block: np.ndarray | None = None
    filled = 0
    indices: list[np.ndarray] = []
    extra = coloured = 0
    seen = 0  # content lines before the chunk
    scratch = Scratch()
    try:
        for chunk in chunks(text, body, scratch):
            first, count, _ = chunk.lines()
            if seen + len(count) > num_verts + num_faces:
                return None  # data after the faces: the record parser names the line
            nv = min(max(num_verts - seen, 0), len(count))  # vertex lines in the chunk
            if nv:
                extra_lines = _vertex_lines(
                    chunk, first[:nv], count[:nv], coords[3 * seen : 3 * (seen + nv)], scratch
                )
                if extra_lines is None:
                    return None
                extra += extra_lines
            if nv < len(count):
                if block is None and not indices and 4 <= count[nv] <= 10:
                    block = np.empty(num_faces * (int(count[nv]) - 1), dtype=np.int64)
                dest = None if block is None else block[filled:]
                face_lines = _face_lines(chunk, first[nv:], count[nv:], scratch, dest)
                if face_lines is None:
                    return None
                if block is not None and face_lines[0].base is block:
                    filled += len(face_lines[0])
                else:
                    if block is not None:
                        indices.append(block[:filled])
                        block = None
                    indices.append(face_lines[0])
                faces_before = seen + nv - num_verts
                size[faces_before : faces_before + len(face_lines[1])] = face_lines[1]
                coloured += face_lines[2]
            seen += len(count)
    except BadNumber:
        return None
    del scratch  # before the concatenation, the read's peak of memory
    if seen != num_verts + num_faces:
        return None
    if block is not None:
        index = block[:filled]
    else:
        index = np.concatenate(indices) if indices else np.zeros(0, dtype=np.int64)
    if index.size and (index.min() < 0 or index.max() >= num_verts):
        return None
    skipped.add(_vertex_extras(keyword), extra)
    skipped.add("face colours", coloured)
    return Parsed(verts, index, size)


def _vertex_lines(
    chunk: Chunk, first: np.ndarray, count: np.ndarray, out: np.ndarray, scratch: Scratch
) -> int | None:
    """Read vertex lines into ``out`` (``(3 * lines,)``); the number of lines with extra
    values, or None for a short one."""
    if (count == 3).all():  # consecutive tokens
        at = int(first[0])
        if chunk.sep is not None:
            sep = chunk.sep[at : at + len(out) + 1]
            slow = np.flatnonzero(parse_decimal_block(chunk.buf, chunk.words, sep, out, scratch))
            if len(slow):
                sep = sep.take(np.stack([slow, slow + 1]))
                sep[0] += 1
                out[slow] = chunk.floats_at(sep[0], sep[1])
        else:
            out[...] = chunk.floats(slice(at, at + len(out)))
        return 0
    if (count < 3).any():
        return None
    tokens = (first[:, None] + np.arange(3)).reshape(-1)
    out[...] = chunk.floats(tokens)
    return int((count > 3).sum())


def _face_lines(
    chunk: Chunk,
    first: np.ndarray,
    count: np.ndarray,
    scratch: Scratch,
    dest: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """``(indices, sizes, coloured faces)`` of face lines; None for a face wrapped over lines
    or broken.  A block of one degree is parsed into the front of ``dest`` when given and
    large enough (the indices returned are then that view)."""
    width = int(count[0])
    if 4 <= width <= 10 and (count == width).all():
        # One degree, k = width - 1 a single digit on every line: the indices are a block.
        lines, at = len(count), int(first[0])
        sizes = np.full(lines, width - 1, dtype=np.int64)
        if chunk.sep is not None:
            m = lines * (width - 1)
            if dest is not None and len(dest) >= m:
                indices = dest[:m]
            else:
                indices = np.empty(m, dtype=np.int64)
            sep = chunk.sep[at : at + lines * width + 1]
            if parse_index_block(chunk.buf, chunk.words, sep, width, indices, scratch):
                return indices, sizes, 0
        k_start = chunk.start[at : at + lines * width : width]
        k_end = chunk.end[at : at + lines * width : width]
        if (k_end - k_start == 1).all() and (chunk.buf.take(k_start) == 47 + width).all():
            return chunk.ints_at(*chunk.block(at, lines, width, 1)), sizes, 0
    k = chunk.ints(first)
    if (k < 3).any() or (count < k + 1).any():
        return None
    return chunk.ints(runs(first + 1, k)), k, int((count > k + 1).sum())


def _ascii_vertices(
    content: Iterator[tuple[int, list[str]]],
    num_verts: int,
    name: str,
    skipped: Skipped,
    keyword: str,
) -> np.ndarray:
    # Only flat lists of strings and ints are kept: millions of retained per-line lists would
    # make the cyclic GC rescan them over and over.
    coords: list[str] = []
    vert_lines: list[int] = []
    extra = 0
    for vno, vtoks in content if num_verts else ():
        if len(vtoks) < 3:
            raise ValueError(
                f"{name}, line {vno}: a vertex needs 3 coordinates, got {' '.join(vtoks)!r}."
            )
        coords.extend(vtoks[:3])
        vert_lines.append(vno)
        extra += len(vtoks) > 3
        if len(vert_lines) == num_verts:
            break
    if len(vert_lines) < num_verts:
        raise ValueError(
            f"{name}: the file ends after {len(vert_lines)} of the {num_verts} vertices "
            "declared in the header (truncated file)."
        )
    skipped.add(_vertex_extras(keyword), extra)
    try:
        return numbers(coords, float).reshape(-1, 3)
    except BadNumber as e:
        raise ValueError(
            f"{name}, line {vert_lines[e.position // 3]}: cannot parse vertex coordinate "
            f"{e.token!r}."
        ) from None


def _ascii_faces(
    content: Iterator[tuple[int, list[str]]], num_faces: int, name: str, skipped: Skipped
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Face records are a token stream: k, then k indices, possibly wrapped over several lines;
    tokens left on the line where a record ends are its colour."""
    corners: list[str] = []
    sizes: list[int] = []
    face_lines: list[int] = []
    need = 0
    coloured = 0
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
        coloured += need == 0 and pos + len(taken) < len(ftoks)
    if len(sizes) < num_faces or need:
        complete = len(sizes) - (1 if need else 0)
        raise ValueError(
            f"{name}: the file ends after {complete} of the {num_faces} faces declared in the "
            "header (truncated file)."
        )
    skipped.add("face colours", coloured)
    size_arr = np.asarray(sizes, dtype=np.int64)
    try:
        indices = numbers(corners, int)
    except BadNumber as e:
        f = int(np.searchsorted(np.cumsum(size_arr), e.position, side="right"))
        raise ValueError(
            f"{name}, line {face_lines[f]}: face {f} has an unparsable vertex index {e.token!r}."
        ) from None
    return indices, size_arr, face_lines


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
    check_sizes_binary(name, sizes, "binary OFF face record")
    if with_colours:
        skipped.add("face colours", int((words[starts + sizes + 1] > 0).sum()))
    first = np.repeat(starts + 1, sizes)
    within = np.arange(int(sizes.sum())) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    indices = words[first + within].astype(np.int64)
    check_faces(name, indices, sizes, num_verts, lambda f: f"binary OFF face record {f}")
    return Parsed(verts, indices, sizes)


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
