"""The text writers: coordinates as Python's ``repr`` and face indices as ``str``.

References: Python's ``repr`` of each double (the shortest decimal that reads back exactly)
and ``str`` of each index, formatted here line by line; Python's ``float`` (an exact,
independent decimal-to-double conversion) for the round trip, bit for bit.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_polylap.io import read_mesh, write_mesh, writers
from torch_polylap.io.writers import face_pieces, float_pieces

PROPERTY = settings(max_examples=200, deadline=None, database=None)

# any finite double: hypothesis draws subnormals, the extremes, -0.0 and integers among them
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
integral = st.integers(-(2**60), 2**60).map(float)


def bits(values: np.ndarray) -> list[int]:
    return np.asarray(values, dtype=np.float64).view(np.int64).reshape(-1).tolist()


def float_text(values: np.ndarray, prefix: bytes) -> bytes:
    return b"".join(float_pieces(values, prefix))


def want_lines(values: np.ndarray, prefix: str) -> bytes:
    return "".join(prefix + " ".join(map(repr, row)) + "\n" for row in values.tolist()).encode()


@PROPERTY
@given(st.lists(finite | integral, min_size=1, max_size=60), st.sampled_from([1, 2, 3]))
def test_any_finite_double_is_written_as_repr_and_reads_back(xs, width):
    values = np.array(xs[: len(xs) // width * width] or xs[:1] * width).reshape(-1, width)
    text = float_text(values, b"v ")
    assert text == want_lines(values, "v ")
    got = [[float(t) for t in line.split()[1:]] for line in text.decode().splitlines()]
    assert bits(np.array(got)) == bits(values)


def test_nan_and_infinities_are_written_as_repr():
    values = np.array([[np.nan, np.inf, -np.inf], [0.0, -0.0, 5e-324]])
    assert float_text(values, b"v ") == b"v nan inf -inf\nv 0.0 -0.0 5e-324\n"


def finite_only(patterns: np.ndarray) -> np.ndarray:
    """Bit patterns as doubles, nan and infinities (whose payload text cannot keep) as 1.0."""
    values = patterns.view(np.float64)
    return np.where(np.isfinite(values), values, 1.0)


RANDOM = {
    "normal": lambda rng, n: rng.normal(scale=100.0, size=n),
    "magnitudes": lambda rng, n: rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-300, 300, n),
    "bit patterns": lambda rng, n: finite_only(rng.integers(-(2**63), 2**63, n, dtype=np.int64)),
    "integers": lambda rng, n: rng.integers(-(10**17), 10**17, n).astype(np.float64),
}


@pytest.mark.parametrize("kind", sorted(RANDOM))
def test_random_arrays_are_repr_across_pieces(kind):
    """More lines than one piece of the writer: every number is ``repr``'s, in order."""
    rng = np.random.default_rng(sorted(RANDOM).index(kind))
    values = RANDOM[kind](rng, 3 * (writers._CHUNK_LINES + 7)).reshape(-1, 3)
    pieces = float_pieces(values, b"")
    assert len(pieces) == 2
    assert b"".join(pieces) == want_lines(values, "")


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply"])
def test_written_files_hold_repr_and_read_back_bit_for_bit(suffix, tmp_path):
    """Through the files and the package's readers: the vertex lines are ``repr``'s text."""
    rng = np.random.default_rng(7)
    verts = rng.normal(size=(3000, 3)) * 10.0 ** rng.integers(-6, 6, (3000, 1))
    faces = rng.integers(0, len(verts), (1000, 4))
    path = tmp_path / f"m{suffix}"
    write_mesh(path, verts, faces)
    assert want_lines(verts, "v " if suffix == ".obj" else "") in path.read_bytes()
    got, read_faces = read_mesh(path)
    assert bits(got.numpy()) == bits(verts)
    assert read_faces.tolist() == faces.tolist()


@PROPERTY
@given(
    st.lists(
        st.lists(st.integers(0, 2**62), min_size=3, max_size=7),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from(["", "f"]),
    st.sampled_from([0, 1]),
)
def test_face_lines_are_str_of_each_index(lines, prefix, base):
    """Mixed and uniform degrees, any index: the lines ``str`` formatting gives, in order."""
    values = np.array([t for line in lines for t in line], dtype=np.int64)
    sizes = np.array([len(line) for line in lines], dtype=np.int64)
    want = "".join(
        " ".join([prefix or str(len(line))] + [str(t + base) for t in line]) + "\n"
        for line in lines
    )
    assert b"".join(face_pieces(values, sizes, prefix, base)) == want.encode()


def test_many_face_lines_keep_their_order_across_pieces():
    """More lines than one piece of the writer, mixed degrees."""
    rng = np.random.default_rng(3)
    sizes = rng.integers(3, 9, writers._CHUNK_LINES + 100)
    values = rng.integers(0, 10**8, int(sizes.sum()))
    lines = np.split(values, np.cumsum(sizes)[:-1])
    want = "".join("f " + " ".join(str(v) for v in line) + "\n" for line in lines)
    assert b"".join(face_pieces(values, sizes, "f")) == want.encode()
