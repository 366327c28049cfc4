"""Text blocks shared by the OBJ, OFF and ASCII PLY writers, and the PLY writer.

The blocks are lists of pieces (``bytes`` or uint8 arrays) that the writers hand to
``writelines`` as they are: joining the pieces of a million-face mesh would copy its tens of
megabytes of text once more.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np

from .float_text import ascii8, float_pieces

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
    indices takes several times as long): tokens below ``10**8`` in every line (mesh indices)
    as 16-byte records, packed by a byte mask (:func:`_int_records`); others digit by digit
    (:func:`_int_lines_by_place`)."""
    if len(per_line) == 0:
        return []
    tokens = np.asarray(tokens, dtype=np.int64)
    if len(tokens) and tokens.min() < 0:
        raise ValueError("int_lines writes non-negative integers only")
    if len(prefix) <= 6 and per_line.min() >= 1 and tokens.max() < 10**8:
        pieces: Pieces = []
        line_end = np.cumsum(per_line)
        for lo in range(0, len(per_line), _INT_CHUNK_LINES):
            hi = min(lo + _INT_CHUNK_LINES, len(per_line))
            first = int(line_end[lo - 1]) if lo else 0
            rec, keep = _int_records(
                tokens[first : line_end[hi - 1]], per_line[lo:hi], prefix, first_line=lo == 0
            )
            pieces.append(memoryview(rec[keep]))
        pieces.append(b"\n")
        return pieces
    return [_int_lines_by_place(tokens, per_line, prefix)]


_INT_CHUNK_LINES = 1 << 15  # lines per chunk: the temporaries stay in cache
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
