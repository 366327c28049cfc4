"""Text blocks shared by the OBJ, OFF and ASCII PLY writers, and the PLY writer.

Numbers are printed by Python: coordinates with ``%r`` (``repr``: the shortest decimal that
reads back as the same double, so every float64 written reads back bit for bit), indices with
``%s`` of ints, a few thousand lines per ``%`` call.  The blocks are lists of such pieces, which
the writers hand to ``writelines`` as they are: joining the pieces of a million-face mesh would
copy its tens of megabytes of text once more.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np

# Consecutive pieces of a file's text
Pieces: TypeAlias = list[bytes | memoryview]
_CHUNK_LINES = 1 << 15  # lines per piece: the Python objects of one piece stay few


def float_pieces(values: np.ndarray, prefix: bytes) -> Pieces:
    """One line per row of the ``(n, m)`` ``values``: ``prefix`` then the row's numbers, each
    Python's ``repr`` of it (``nan``, ``inf``, ``-0.0``, ``1e-05``, ``0.1``), separated by
    single spaces."""
    values = np.asarray(values, dtype=np.float64)
    line = prefix.decode("ascii") + " ".join(["%r"] * values.shape[1]) + "\n"
    return [
        ((line * len(rows)) % tuple(rows.reshape(-1).tolist())).encode("ascii")
        for rows in np.array_split(values, range(_CHUNK_LINES, len(values), _CHUNK_LINES))
        if len(rows)
    ]


def face_pieces(values: np.ndarray, sizes: np.ndarray, prefix: str = "", base: int = 0) -> Pieces:
    """One line per face: ``prefix`` (or the degree when empty) then its corner values,
    separated by single spaces.

    ``values`` are integer indices (written plus ``base``) or an object array of ready-made
    corner strings.  The lines of each degree are formatted by one ``%`` per chunk, then put
    back in file order.
    """
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    pieces: Pieces = []
    for lo in range(0, len(sizes), _CHUNK_LINES):
        size = sizes[lo : lo + _CHUNK_LINES]
        corners = values[offsets[lo] : offsets[lo + len(size)]]
        if corners.dtype != object:
            corners = corners + base
        starts = np.cumsum(size) - size
        lines = np.empty(len(size), dtype=object)
        for k in np.unique(size).tolist():
            sel = np.flatnonzero(size == k)
            rows = corners[starts[sel][:, None] + np.arange(k)] if len(sel) < len(size) else corners
            line = (prefix or str(k)) + " %s" * k + "\n"
            text = (line * len(sel)) % tuple(rows.reshape(-1).tolist())
            if len(sel) == len(size):
                pieces.append(text.encode("ascii"))
                break
            lines[sel] = text.split("\n")[:-1]
        else:
            pieces.append(("\n".join(lines.tolist()) + "\n").encode("ascii"))
    return pieces


def off_text(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray) -> Pieces:
    """ASCII OFF."""
    header = f"OFF\n{len(v)} {len(sizes)} 0\n".encode("ascii")
    return [header, *float_pieces(v, b""), *face_pieces(indices, sizes)]


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
        return [header, *float_pieces(v, b""), *face_pieces(indices, sizes)]
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
