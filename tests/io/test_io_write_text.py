"""The text writers' bulk formatting: coordinates (``float_text``) and face indices
(``writers.int_lines``).

References: Python's ``float`` (an exact, independent decimal-to-double conversion) for the
round trip, bit for bit; Python's ``repr`` (the shortest round-trip decimal) and ``str`` of
integers for the text itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torch_polylap.io import float_text, read_mesh, write_mesh
from torch_polylap.io.float_text import ascii8, float_lines
from torch_polylap.io.writers import int_lines

PROPERTY = settings(max_examples=200, deadline=None, database=None)

# any finite double: hypothesis draws subnormals, the extremes, -0.0 and integers among them
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
integral = st.integers(-(2**60), 2**60).map(float)


def bits(values: np.ndarray) -> list[int]:
    return np.asarray(values, dtype=np.float64).view(np.int64).reshape(-1).tolist()


def tokens(text: bytes, prefix: bytes) -> list[list[bytes]]:
    """The number tokens of each line of ``text``, checking its layout."""
    assert text.endswith(b"\n")
    rows = []
    for line in text[:-1].split(b"\n"):
        assert line.startswith(prefix)
        rows.append(line[len(prefix) :].split(b" "))
    return rows


def read_back(text: bytes, prefix: bytes) -> np.ndarray:
    return np.array([[float(t) for t in row] for row in tokens(text, prefix)])


@PROPERTY
@given(st.lists(finite | integral, min_size=1, max_size=60), st.sampled_from([1, 2, 3]))
def test_any_finite_double_reads_back_bit_for_bit(xs, width):
    values = np.array(xs[: len(xs) // width * width] or xs[:1] * width).reshape(-1, width)
    text = float_lines(values, b"v ")
    got = read_back(text, b"v ")
    assert bits(got) == bits(values)
    for row in tokens(text, b"v "):  # a decimal, never more digits than a double needs
        for token in row:
            digits = token.split(b"e")[0].lstrip(b"-").replace(b".", b"").lstrip(b"0")
            assert len(digits.rstrip(b"0")) <= 17, token


@PROPERTY
@given(st.lists(finite.filter(lambda x: x == 0 or 1e-300 < abs(x) < 1e16), min_size=1))
def test_text_is_pythons_repr(xs):
    """Away from the rare exceptions (the docstring names them: ties in the last digit of the
    integers beyond 2**53, the short side of a power of two), the shortest decimal, as
    ``repr`` writes it."""
    values = np.array(xs).reshape(-1, 1)
    want = "".join(f"{x!r}\n" for x in xs).encode()
    assert float_lines(values, b"") == want


def test_nan_and_infinities_are_written_as_repr():
    values = np.array([[np.nan, np.inf, -np.inf], [0.0, -0.0, 5e-324]])
    assert float_lines(values, b"v ") == b"v nan inf -inf\nv 0.0 -0.0 5e-324\n"


def finite_only(patterns: np.ndarray) -> np.ndarray:
    """Bit patterns as doubles, nan and infinities (whose payload text cannot keep) as 1.0."""
    values = patterns.view(np.float64)
    return np.where(np.isfinite(values), values, 1.0)


def rounded(rng: np.random.Generator, n: int) -> np.ndarray:
    """Short decimals (as read from files written with few digits), at various scales."""
    return np.round(rng.normal(size=n) * 1e6) / 10.0 ** rng.integers(0, 9, n)


RANDOM = {
    "uniform": lambda rng, n: rng.random(n),
    "normal": lambda rng, n: rng.normal(scale=100.0, size=n),
    "magnitudes": lambda rng, n: rng.choice([-1.0, 1.0], n) * 10.0 ** rng.uniform(-300, 300, n),
    "bit patterns": lambda rng, n: finite_only(rng.integers(-(2**63), 2**63, n, dtype=np.int64)),
    "grid": lambda rng, n: np.arange(n) / 1000.0,
    "integers": lambda rng, n: rng.integers(-(10**17), 10**17, n).astype(np.float64),
    "rounded": lambda rng, n: rounded(rng, n),
}


@pytest.mark.parametrize("kind", sorted(RANDOM))
def test_random_arrays_read_back_bit_for_bit(kind):
    """1e5 values in 33334 lines of three (more lines than one chunk of the formatter): each
    reads back (Python's ``float``) to the same bits, and the text is ``repr``'s but for a
    few values in ten thousand (the exceptions above)."""
    rng = np.random.default_rng(sorted(RANDOM).index(kind))
    values = RANDOM[kind](rng, 100_002).reshape(-1, 3)
    assert len(values) > float_text._CHUNK_ROWS
    text = float_lines(values, b"v ")
    assert bits(read_back(text, b"v ")) == bits(values)
    ours = [t for row in tokens(text, b"v ") for t in row]
    want = [repr(x).encode() for x in values.reshape(-1).tolist()]
    differ = [(a, b) for a, b in zip(ours, want, strict=True) if a != b]
    assert len(differ) <= len(want) // 10_000, differ[:5]
    assert all(len(a) <= len(b) + 1 for a, b in differ)


@pytest.mark.parametrize("suffix", [".obj", ".off", ".ply"])
def test_written_meshes_read_back_bit_for_bit(suffix, tmp_path):
    """Through the files and the package's readers (their bulk parser), 1e5 coordinates."""
    rng = np.random.default_rng(7)
    verts = rng.normal(size=(33_334, 3)) * 10.0 ** rng.integers(-6, 6, (33_334, 1))
    faces = rng.integers(0, len(verts), (1000, 4))
    write_mesh(tmp_path / f"m{suffix}", verts, faces)
    got, read_faces = read_mesh(tmp_path / f"m{suffix}")
    assert bits(got.numpy()) == bits(verts)
    assert read_faces.tolist() == faces.tolist()


def test_many_face_lines_match_python_formatting():
    """More lines than one chunk of the face writer, mixed degrees and index widths."""
    rng = np.random.default_rng(3)
    per_line = rng.integers(1, 9, 70_000)
    values = rng.integers(0, 10 ** rng.integers(1, 9, int(per_line.sum())))
    for prefix in (b"f", b""):
        lines = np.split(values, np.cumsum(per_line)[:-1])
        head = [prefix.decode()] if prefix else []
        want = "".join(" ".join(head + [str(v) for v in line]) + "\n" for line in lines)
        assert int_lines(values, per_line, prefix) == want.encode()


@PROPERTY
@given(st.lists(st.integers(0, 10**8 - 1), min_size=1, max_size=50))
def test_eight_digits_at_once(values):
    """The integer steps that turn a number below 10**8 into its eight ASCII digits."""
    words = ascii8(np.array(values, dtype=np.uint64))
    assert words.astype("<u8").tobytes() == "".join(f"{v:08d}" for v in values).encode()


# decimals of at most 15 significant digits below 1e15 (above, ties at powers of ten are among
# the documented exceptions)
short_decimal = st.builds(
    lambda m, q, neg: float(f"{'-' if neg else ''}{m}e{q}"),
    st.integers(1, 10**15 - 1),
    st.integers(-40, 0),
    st.booleans(),
)


@PROPERTY
@given(st.lists(short_decimal, min_size=1, max_size=60), st.sampled_from([1, 3]))
def test_short_decimals_are_pythons_repr(xs, width):
    """Short decimals (as read from files written with few digits) take the formatter's
    one-division path; it settles them exactly, with no exceptions to ``repr``."""
    values = np.array(xs[: len(xs) // width * width] or xs[:1] * width).reshape(-1, width)
    want = "".join("vt " + " ".join(map(repr, row)) + "\n" for row in values.tolist())
    assert float_lines(values, b"vt ") == want.encode()


def test_next_to_powers_of_ten_are_pythons_repr():
    """Where ``floor(log10(x))`` can be one off: powers of ten and their neighbouring doubles
    (up to 1e22: the double nearest 1e23 is one of the documented ties)."""
    tens = np.array([float(f"1e{k}") for k in range(-30, 23)])
    values = np.concatenate([tens, np.nextafter(tens, 0), np.nextafter(tens, np.inf)])
    values = np.concatenate([values, -values]).reshape(-1, 1)
    want = "".join(f"{x!r}\n" for x in values.reshape(-1).tolist()).encode()
    assert float_lines(values, b"") == want


def test_longest_texts_between_others():
    """24-character texts (``repr``'s, below the bulk path's range) and the longest of the
    bulk path, among others in lines of three: each keeps its separator."""
    longest = [-2.2250738585072014e-308, -1.2345678901234567e-299, -0.00012345678901234568]
    bulk = [-1.2345678901234567e-200, -1.7976931348623157e308, -1.2345678901234567e200]
    values = np.array([longest, bulk, longest[::-1], [1.5e-7, 1e22, -3e-5]])
    want = "".join("v " + " ".join(map(repr, row)) + "\n" for row in values.tolist())
    assert float_lines(values, b"v ") == want.encode()


@PROPERTY
@given(
    st.lists(
        st.lists(
            st.sampled_from([0, 1, 9, 10, 99, 999, 1000, 9999, 10**4, 10**5 - 1, 10**5])
            | st.sampled_from([10**6 - 1, 10**6, 10**7 - 1, 10**7, 10**8 - 1, 10**8])
            | st.integers(0, 10**7),
            min_size=1,
            max_size=6,
        ),
        min_size=1,
        max_size=40,
    ),
    st.sampled_from([b"", b"f", b"ab", b"abcdef"]),
)
def test_index_lines_at_digit_count_boundaries(lines, prefix):
    """Face indices around every change of digit count (the word path below ``10**7``, the
    record path below ``10**8``) format as ``str`` does, lines of one or mixed degrees."""
    tokens = np.array([t for line in lines for t in line], dtype=np.int64)
    per_line = np.array([len(line) for line in lines], dtype=np.int64)
    head = [prefix.decode()] if prefix else []
    want = "".join(" ".join(head + list(map(str, line))) + "\n" for line in lines)
    assert int_lines(tokens, per_line, prefix) == want.encode()


def test_sixteen_and_seventeen_digits_are_pythons_repr():
    """Between 1e-6 and 1e15 the 16- and 17-digit decimals are settled exactly (Dekker's
    product with an exact power of ten): 1e5 doubles of random bits there print as ``repr``,
    no exceptions."""
    rng = np.random.default_rng(11)
    x = rng.choice([-1.0, 1.0], 100_000) * 10.0 ** rng.uniform(-6, 15, 100_000)
    x = (x.view(np.int64) ^ rng.integers(0, 2**20, len(x))).view(np.float64)  # any last bits
    want = "".join(f"{v!r}\n" for v in x.tolist()).encode()
    assert float_lines(x.reshape(-1, 1), b"") == want
