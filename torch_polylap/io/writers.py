"""Text blocks shared by the OBJ, OFF and ASCII PLY writers, and the PLY writer.

The blocks are lists of pieces (``bytes`` or uint8 arrays) that the writers hand to
``writelines`` as they are: joining the pieces of a million-face mesh would copy its tens of
megabytes of text once more.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np

from .float_text import ascii8, float_pieces, without_zero_bytes

# Consecutive pieces of a file's text
Pieces: TypeAlias = list[bytes | memoryview]


def vertex_block(v: np.ndarray, prefix: str) -> Pieces:
    """One line per vertex, ``prefix`` then ``x y z``, each the shortest decimal that reads back
    as the same double (Python's ``repr``; built in bulk by :mod:`.float_text`)."""
    return list(float_pieces(v, prefix.encode("ascii")))


def face_block(values: np.ndarray, sizes: np.ndarray, prefix: str = "", base: int = 0) -> bytes:
    """:func:`face_pieces` joined."""
    return b"".join(face_pieces(values, sizes, prefix, base))


def face_pieces(values: np.ndarray, sizes: np.ndarray, prefix: str = "", base: int = 0) -> Pieces:
    """One line per face: ``prefix`` (or the degree when empty) then its corner values.

    ``values`` are integer indices (written plus ``base``) or an object array of ready-made
    corner strings.  Integers are written with numpy (:func:`int_lines`);
    strings are formatted one degree at a time with a single ``%`` per degree, then put back in
    file order.
    """
    if len(sizes) == 0:
        return []
    if values.dtype != object:
        if prefix:
            return int_pieces(values + base, sizes, prefix.encode("ascii"))
        # OFF: each line is the degree, then the indices
        tokens = np.empty(len(values) + len(sizes), dtype=np.int64)
        head = np.cumsum(sizes + 1) - (sizes + 1)
        is_head = np.zeros(len(tokens), dtype=bool)
        is_head[head] = True
        tokens[head] = sizes
        tokens[~is_head] = values + base
        return int_pieces(tokens, sizes + 1, b"")
    starts = np.cumsum(sizes) - sizes
    lines = np.empty(len(sizes), dtype=object)
    for k in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == k)
        rows = values[starts[sel][:, None] + np.arange(k)]
        line = (prefix or str(k)) + " %s" * k + "\n"
        lines[sel] = ((line * len(sel)) % tuple(rows.reshape(-1).tolist())).split("\n")[:-1]
    return [("\n".join(lines.tolist()) + "\n").encode("ascii")]


def int_lines(tokens: np.ndarray, per_line: np.ndarray, prefix: bytes) -> bytes:
    """:func:`int_pieces` joined."""
    return b"".join(int_pieces(tokens, per_line, prefix))


def int_pieces(tokens: np.ndarray, per_line: np.ndarray, prefix: bytes) -> Pieces:
    """Lines of non-negative integers: line ``l`` is ``prefix``, then the next ``per_line[l]``
    of ``tokens`` in decimal, separated by single spaces (one after a non-empty prefix), then
    a line break; without a prefix every line must hold a token.

    Built with numpy, no Python work per token (Python's ``%d`` formatting of millions of
    indices takes several times as long): tokens below ``10**7`` in every line (the indices of
    meshes of up to ten million vertices) as one 8-byte word each (:func:`_int_words`), those
    below ``10**8`` as 16-byte records (:func:`_int_records`), others digit by digit
    (:func:`_int_lines_by_place`)."""
    if len(per_line) == 0:
        return []
    tokens = np.asarray(tokens, dtype=np.int64)
    if len(tokens) and tokens.min() < 0:
        raise ValueError("int_lines writes non-negative integers only")
    if per_line.min() < 1 or len(prefix) > 6 or tokens.max() >= 10**8:
        return [_int_lines_by_place(tokens, per_line, prefix)]
    words = tokens.max() < 10**7
    buffer = np.empty(0, dtype=np.uint64)  # one for every chunk: fresh ones cost page faults
    pieces: Pieces = []
    line_end = np.cumsum(per_line)
    for lo in range(0, len(per_line), _INT_CHUNK_LINES):
        hi = min(lo + _INT_CHUNK_LINES, len(per_line))
        first = int(line_end[lo - 1]) if lo else 0
        chunk = tokens[first : line_end[hi - 1]]
        if words:
            if len(buffer) < len(chunk) + hi - lo:
                buffer = np.empty(len(chunk) + hi - lo, dtype=np.uint64)
            text = _int_words(chunk, per_line[lo:hi], prefix, lo == 0, buffer)
            pieces.append(without_zero_bytes(text))
        else:
            rec, keep = _int_records(chunk, per_line[lo:hi], prefix, first_line=lo == 0)
            pieces.append(memoryview(rec[keep]))
    pieces.append(b"\n")
    return pieces


_INT_CHUNK_LINES = 1 << 15  # lines per chunk: the temporaries stay in cache


def _word(text: bytes) -> int:
    """``text`` (at most 8 bytes) right-aligned in a little-endian word, zero bytes before."""
    return int.from_bytes(text.rjust(8, b"\0"), "little")


# Tokens below 10**7 as " " and their digits right-aligned in a word, zero bytes before: the
# word of v is _LOW4[v] for v < 10**4, else _LOW4[10**4 + v % 10**4] | _HIGH3[v // 10**4]
# (the last four digits in the high half, the others and the space in the low half)
_LOW4 = np.array(
    [_word(b" %d" % v) for v in range(10**4)] + [_word(b"%04d" % v) for v in range(10**4)],
    dtype=np.uint64,
)
_HIGH3 = np.array([0] + [_word(b" %d" % v) >> 32 for v in range(1, 1000)], dtype=np.uint64)


def _int_words(
    tokens: np.ndarray, per_line: np.ndarray, prefix: bytes, first_line: bool, buffer: np.ndarray
) -> np.ndarray:
    """The text of :func:`int_lines` (tokens below ``10**7``, lines not empty, no final line
    break) as bytes with zero bytes in between, to be dropped: per token a word (its space
    and digits, right-aligned, from two table lookups), per line with a prefix a word of the
    line break and the prefix before the line's tokens; without one, the line break takes the
    place of the first token's space.  ``first_line``: no line break before the first line.
    With a prefix the words go to the start of ``buffer`` (uint64, long enough)."""
    v = tokens.astype(np.uint64)
    high = v // np.uint64(10**4)
    low = v - high * np.uint64(10**4)
    low += np.minimum(high, np.uint64(1)) * np.uint64(10**4)
    w = _LOW4.take(low)
    if prefix:
        out = buffer[: len(w) + len(per_line)]
        if (per_line == per_line[0]).all():  # one degree: a line is a row
            rows = out.reshape(len(per_line), -1)
            rows[:, 0] = _word(b"\n" + prefix)
            shape = (len(per_line), -1)
            np.bitwise_or(w.reshape(shape), _HIGH3.take(high).reshape(shape), out=rows[:, 1:])
        else:
            w |= _HIGH3.take(high)
            head_at = np.cumsum(per_line) - per_line + np.arange(len(per_line))
            out[head_at] = _word(b"\n" + prefix)
            is_token = np.ones(len(out), dtype=bool)
            is_token[head_at] = False
            out[is_token] = w
        if first_line:
            out[0] = _word(prefix)
    else:
        out = w
        out |= _HIGH3.take(high)
        heads = np.cumsum(per_line) - per_line
        first = out[heads]
        space = first & (np.uint64(0) - first)  # the lowest bit set: bit 5 of the space
        line_break = (space >> np.uint64(5)) * np.uint64(ord("\n"))
        out[heads] = first - space + line_break
        if first_line:
            out[0] -= line_break[0]
    return out.view(np.uint8)


_POW10_U32 = np.array([10**k for k in range(1, 8)], dtype=np.uint32)
# A 16-byte record keeps bytes [a, b) with a <= 8: row a * 17 + b of this table
_INT_MASKS = np.array([[a <= i < b for i in range(16)] for a in range(9) for b in range(17)])


def _int_records(
    tokens: np.ndarray, per_line: np.ndarray, prefix: bytes, first_line: bool
) -> tuple[np.ndarray, np.ndarray]:
    """``(records, keep)`` for :func:`int_lines` (tokens below ``10**8``, lines not empty):
    per token a 16-byte record, the text before it right-aligned in the first 8 bytes (a
    space; before a line's first token the previous line's break unless ``first_line``,
    ``prefix`` and its space) and its digits from byte 8, all in one uint8 array, and the
    bytes of it to keep."""
    n = len(tokens)
    v = tokens.astype(np.uint32)
    digits = np.ones(n, dtype=np.int64)
    for power in _POW10_U32:
        digits += v >= power
    rec = np.empty((n, 2), dtype=np.uint64)
    rec[:, 1] = ascii8(v) >> ((8 - digits) * 8).astype(np.uint64)  # drop the leading zeros
    before = b" "
    head = b"\n" + prefix + (b" " if prefix else b"")
    rec[:, 0] = int.from_bytes(before.rjust(8, b"\0"), "little")
    heads = np.cumsum(per_line) - per_line
    rec[heads, 0] = int.from_bytes(head.rjust(8, b"\0"), "little")
    start = np.full(n, 8 - len(before), dtype=np.int64)
    start[heads] = 8 - len(head)
    if first_line:
        start[0] += 1  # no line break before the first line
    keep = _INT_MASKS.take(start * 17 + digits + 8, axis=0)
    return rec.view(np.uint8).reshape(-1), keep.reshape(-1)


def _int_lines_by_place(tokens: np.ndarray, per_line: np.ndarray, prefix: bytes) -> bytes:
    """:func:`int_lines` for any tokens (and empty lines): built in one byte array, each
    token's place following from the running sum of the widths, its digits written one
    decimal place at a time for all tokens at once."""
    top = int(tokens.max()) if len(tokens) else 0
    value = tokens.astype(np.uint64 if top >= 2**32 else np.uint32)
    digits = np.ones(len(tokens), dtype=np.int64)
    power = 10
    while power <= top:
        digits += value >= power
        power *= 10
    # bytes of a line besides its tokens and their separators: the prefix and the line break,
    # less the separator the first token does not get when there is no prefix
    lead = len(prefix) if prefix else -1
    line_of = np.repeat(np.arange(len(per_line), dtype=np.int64), per_line)
    widths = np.zeros(len(tokens) + 1, dtype=np.int64)
    np.cumsum(digits + 1, out=widths[1:])  # bytes of the tokens before each, separators included
    rows = np.arange(len(per_line), dtype=np.int64)
    newline = widths[np.cumsum(per_line)] + (rows + 1) * lead + rows
    size = int(newline[-1]) + 1
    out = np.full(size + 1, 32, dtype=np.uint8)  # the extra last byte takes discarded digits
    out[newline] = 10
    if prefix:
        start = np.concatenate([[0], newline[:-1] + 1])
        for i, byte in enumerate(prefix):
            out[start + i] = byte
    at = widths[1:] + (line_of + 1) * lead + line_of - 1  # each token's last digit
    ten = value.dtype.type(10)
    shortest = int(digits.min()) if len(digits) else 0
    for place in range(len(str(top))):
        if place >= shortest:  # tokens with no digit left write to the spare byte
            at = np.where(digits > place, at, size)
        quotient = value // ten
        out[at] = (value - quotient * ten).astype(np.uint8) + np.uint8(48)
        value = quotient
        at -= 1
    return out[:size].tobytes()


def off_text(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray) -> Pieces:
    """ASCII OFF."""
    header = f"OFF\n{len(v)} {len(sizes)} 0\n".encode("ascii")
    return [header, *vertex_block(v, ""), *face_pieces(indices, sizes)]


def ply_text(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray, binary: bool) -> Pieces:
    """ASCII or binary little-endian PLY with double coordinates and int indices."""
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
        return [header, *vertex_block(v, ""), *face_pieces(indices, sizes)]
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
    return [header, np.ascontiguousarray(v, dtype="<f8").reshape(-1).view(np.uint8).data, out.data]
