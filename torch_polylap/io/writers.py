"""Text blocks shared by the OBJ, OFF and ASCII PLY writers, and the PLY writer."""

from __future__ import annotations

import numpy as np


def vertex_block(v: np.ndarray, prefix: str) -> str:
    """One line per vertex, ``prefix`` then ``x y z`` with 17 significant digits (exact)."""
    if len(v) == 0:
        return ""
    return ((prefix + "%.17g %.17g %.17g\n") * len(v)) % tuple(v.reshape(-1).tolist())


def face_block(values: np.ndarray, sizes: np.ndarray, prefix: str = "", base: int = 0) -> str:
    """One line per face: ``prefix`` (or the degree when empty) then its corner values.

    ``values`` are integer indices (written plus ``base``) or an object array of ready-made
    corner strings.  Faces are formatted one degree at a time with a single ``%`` per degree,
    then put back in file order.
    """
    if len(sizes) == 0:
        return ""
    text = values.dtype == object
    if (sizes == sizes[0]).all():  # one degree: one % over everything, no re-ordering
        k = int(sizes[0])
        line = (prefix or str(k)) + (" %s" if text else " %d") * k + "\n"
        flat = values if text else values + base
        return (line * len(sizes)) % tuple(flat.tolist())
    starts = np.cumsum(sizes) - sizes
    lines = np.empty(len(sizes), dtype=object)
    for k in np.unique(sizes).tolist():
        sel = np.flatnonzero(sizes == k)
        rows = values[starts[sel][:, None] + np.arange(k)]
        if not text:
            rows = rows + base
        line = (prefix or str(k)) + (" %s" if text else " %d") * k + "\n"
        lines[sel] = ((line * len(sel)) % tuple(rows.reshape(-1).tolist())).split("\n")[:-1]
    return "\n".join(lines.tolist()) + "\n"


def off_bytes(v: np.ndarray, indices: np.ndarray, sizes: np.ndarray) -> bytes:
    """ASCII OFF."""
    text = f"OFF\n{len(v)} {len(sizes)} 0\n" + vertex_block(v, "") + face_block(indices, sizes)
    return text.encode("ascii")


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
        return header + (vertex_block(v, "") + face_block(indices, sizes)).encode("ascii")
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
