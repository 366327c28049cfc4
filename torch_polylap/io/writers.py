"""Text blocks shared by the OBJ, OFF and ASCII PLY writers, and the PLY writer."""

from __future__ import annotations

import numpy as np


def vertex_block(v: np.ndarray, prefix: str) -> bytes:
    """One line per vertex, ``prefix`` then ``x y z`` as Python's ``repr``: the shortest
    decimal that reads back as the same double (at most 17 significant digits; a third faster
    to format than ``%.17g``, and shorter)."""
    if len(v) == 0:
        return b""
    text = ((prefix + "%r %r %r\n") * len(v)) % tuple(v.reshape(-1).tolist())
    return text.encode("ascii")


def face_block(values: np.ndarray, sizes: np.ndarray, prefix: str = "", base: int = 0) -> bytes:
    """One line per face: ``prefix`` (or the degree when empty) then its corner values.

    ``values`` are integer indices (written plus ``base``) or an object array of ready-made
    corner strings.  Integers are written digit by digit with numpy (:func:`int_lines`);
    strings are formatted one degree at a time with a single ``%`` per degree, then put back in
    file order.
    """
    if len(sizes) == 0:
        return b""
    if values.dtype != object:
        if prefix:
            return int_lines(values + base, sizes, prefix.encode("ascii"))
        # OFF: each line is the degree, then the indices
        tokens = np.empty(len(values) + len(sizes), dtype=np.int64)
        head = np.cumsum(sizes + 1) - (sizes + 1)
        is_head = np.zeros(len(tokens), dtype=bool)
        is_head[head] = True
        tokens[head] = sizes
        tokens[~is_head] = values + base
        return int_lines(tokens, sizes + 1, b"")
    starts = np.cumsum(sizes) - sizes
    lines = np.empty(len(sizes), dtype=object)
    for k in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == k)
        rows = values[starts[sel][:, None] + np.arange(k)]
        line = (prefix or str(k)) + " %s" * k + "\n"
        lines[sel] = ((line * len(sel)) % tuple(rows.reshape(-1).tolist())).split("\n")[:-1]
    return ("\n".join(lines.tolist()) + "\n").encode("ascii")


def int_lines(tokens: np.ndarray, per_line: np.ndarray, prefix: bytes) -> bytes:
    """Lines of non-negative integers: line ``l`` is ``prefix``, then the next ``per_line[l]``
    of ``tokens`` in decimal, separated by single spaces (one after a non-empty prefix), then
    a line break; without a prefix every line must hold a token.

    Built in one byte array (Python's ``%d`` formatting of millions of indices takes twice as
    long): each token's place follows from the running sum of the widths, and its digits are
    written one decimal place at a time for all tokens at once."""
    if len(per_line) == 0:
        return b""
    tokens = np.asarray(tokens, dtype=np.int64)
    if len(tokens) and tokens.min() < 0:
        raise ValueError("int_lines writes non-negative integers only")
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


def off_bytes(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray) -> bytes:
    """ASCII OFF."""
    header = f"OFF\n{len(v)} {len(sizes)} 0\n".encode("ascii")
    return header + vertex_block(v, "") + face_block(indices, sizes)


def ply_bytes(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray, binary: bool) -> bytes:
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
        return header + vertex_block(v, "") + face_block(indices, sizes)
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
    return header + v.astype("<f8").tobytes() + out.tobytes()
