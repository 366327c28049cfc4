"""The bulk (numpy) text parsing behind read_mesh, against independent references.

* Number conversion against Python's ``float``/``int`` (CPython's correctly rounded dtoa):
  random doubles written with ``repr`` and ``%.17g``, random decimal strings, exact binary
  midpoints (ties), and the edges of the double range; bit for bit.
* The bulk OBJ parser against the line-by-line reference parser on random OBJ text: whenever
  the bulk one answers, the same vertices, faces and skipped-content warning.
* The tokenizer's lines and tokens against ``str.split``, and the bulk readers with chunks of
  a few dozen bytes (every record layout meeting a chunk boundary) against the reference
  parsers.
* Peak memory of a read, and the reader bugs: truncated corners, files cut inside a record,
  float PLY index lists, impossible PLY list lengths.
"""

from __future__ import annotations

import re
import struct
import tracemalloc
import warnings
from contextlib import contextmanager
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from torch_polylap.io import SkippedContentWarning, numparse, read_mesh, write_mesh
from torch_polylap.io import obj as obj_module
from torch_polylap.io import tokens as tokens_module
from torch_polylap.io.common import Skipped
from torch_polylap.io.numparse import (
    PAD,
    Scratch,
    parse_decimal_block,
    parse_floats,
    parse_index_block,
    parse_ints,
    parse_plain_floats,
    text_buffer,
    token_marks,
    word_view,
)

PROPERTY = settings(max_examples=150, deadline=None, database=None)


def _buffer(tokens: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    text = b" " * PAD + b" ".join(tokens) + b" " * PAD
    lengths = np.array([len(t) for t in tokens], dtype=np.int64)
    start = PAD + np.cumsum(lengths + 1) - (lengths + 1)
    return np.frombuffer(text, dtype=np.uint8), start, start + lengths


def bulk_floats(tokens: list[bytes]) -> tuple[list[float], list[bool]]:
    """parse_floats on ``tokens`` (the dot / exponent positions found here by ``bytes.find``,
    as the tokenizer finds them), as (values, slow)."""
    buf, start, end = _buffer(tokens)
    dot = np.array([t.find(b".") for t in tokens], dtype=np.int64)
    exp = np.array([max(t.find(b"e"), t.find(b"E")) for t in tokens], dtype=np.int64)
    dot = np.where(dot >= 0, start + dot, -1)
    exp = np.where(exp >= 0, start + exp, -1)
    values, slow = parse_floats(buf, word_view(buf), start, end, dot, exp)
    return values.tolist(), slow.tolist()


def same_bits(a: float, b: float) -> bool:
    return struct.pack("<d", a) == struct.pack("<d", b)


def check_floats(tokens: list[bytes]) -> int:
    """Every token converted in bulk equals float(token) bit for bit; returns how many were."""
    values, slow = bulk_floats(tokens)
    for token, value, left in zip(tokens, values, slow, strict=True):
        if not left:
            assert same_bits(value, float(token)), (token, value, float(token))
    return len(tokens) - sum(slow)


doubles = st.floats(allow_nan=False, allow_infinity=False, width=64)


@PROPERTY
@given(st.lists(doubles, min_size=1, max_size=200))
def test_written_doubles_convert_exactly(xs):
    check_floats([repr(x).encode() for x in xs] + [b"%.17g" % x for x in xs])


def test_most_written_doubles_take_the_bulk_path():
    """Only products within the error bound of a rounding boundary (and exact powers of two
    written in full) are left to Python: well under 2% of random doubles."""
    rng = np.random.default_rng(0)
    xs = np.concatenate([rng.normal(size=20000), np.exp(rng.uniform(-600, 600, 20000))])
    tokens = [repr(x).encode() for x in xs.tolist()] + [b"%.17g" % x for x in xs.tolist()]
    assert check_floats(tokens) >= 0.98 * len(tokens)


@st.composite
def decimal_strings(draw) -> bytes:
    digits = draw(st.text("0123456789", min_size=1, max_size=24))
    point = draw(st.integers(-1, len(digits)))
    text = digits if point < 0 else digits[:point] + "." + digits[point:]
    if draw(st.booleans()):
        text += draw(st.sampled_from("eE")) + draw(st.sampled_from(["", "+", "-"]))
        text += str(draw(st.integers(0, 400)))
    return (draw(st.sampled_from(["", "-", "+"])) + text).encode()


@PROPERTY
@given(st.lists(decimal_strings(), min_size=1, max_size=200))
def test_random_decimals_convert_exactly(tokens):
    check_floats(tokens)


def _exact_decimal(value: Fraction) -> bytes:
    """The finite decimal expansion of a dyadic rational."""
    num, den = value.numerator, value.denominator
    places = den.bit_length() - 1  # den is a power of two: 2**p needs p decimal places
    scaled = num * 5**places
    sign = "-" if scaled < 0 else ""
    digits = str(abs(scaled)).rjust(places + 1, "0")
    return f"{sign}{digits[: len(digits) - places]}.{digits[len(digits) - places :]}".encode()


@PROPERTY
@given(st.integers(2**52, 2**53 - 1), st.integers(-80, 80), st.sampled_from([-1, 0, 1]))
def test_midpoints_between_doubles_round_to_even(m, e, nudge):
    """The decimal of an exact midpoint between two doubles, and its neighbours in the last
    written digit: ties must go to the even significand."""
    midpoint = (Fraction(2 * m + 1) * Fraction(2) ** e) / 2
    token = _exact_decimal(midpoint + nudge * Fraction(1, 10**40))
    check_floats([token, token[:19], token[:25]])


def test_edge_cases_convert_exactly():
    tokens = [
        b"0", b"-0", b"-0.0", b"0e5", b"1", b"1.", b".5", b"-.5", b"+.5e1", b"1e5", b"1E+05",
        b"1e-5", b"9007199254740993", b"9007199254740992", b"9007199254740994",
        b"2.2250738585072011e-308", b"2.2250738585072014e-308", b"4.9e-324", b"1e-320",
        b"1.7976931348623157e308", b"1.7976931348623158e308", b"1e309", b"1e400", b"1e-400",
        b"0.0030000000000000001", b"0.00034997964196241757", b"123456789012345678.9",
        b"00000000000000000000001.5", b"0.1", b"0.2", b"0.3", b"3.14159265358979323846",
    ]  # fmt: skip
    check_floats(tokens)


def test_non_numbers_are_left_to_python():
    tokens = [b"nan", b"inf", b"-Infinity", b"1_0", b"1e", b"-", b".", b"e5", b"1.5d3", b"0x1"]
    _, slow = bulk_floats(tokens)
    assert all(slow)


def plain_floats(tokens: list[bytes]) -> tuple[list[float], list[bool]]:
    """parse_plain_floats on ``tokens``, as (values, slow)."""
    buf, start, end = _buffer(tokens)
    values, slow = parse_plain_floats(buf, word_view(buf), start, end)
    return values.tolist(), slow.tolist()


@PROPERTY
@given(
    st.lists(st.one_of(decimal_strings(), doubles.map(lambda x: repr(x).encode())), max_size=200)
)
def test_plain_floats_are_exact_or_left_slow(tokens):
    """The point-finding path: whatever it does not leave slow is float(token) bit for bit."""
    values, slow = plain_floats(tokens)
    for token, value, left in zip(tokens, values, slow, strict=True):
        if not left:
            assert same_bits(value, float(token)), (token, value, float(token))


@PROPERTY
@given(
    st.lists(
        st.tuples(st.sampled_from(["", "-", "+"]), st.text("0123456789", min_size=0, max_size=7),
                  st.booleans(), st.text("0123456789", min_size=0, max_size=12)),
        min_size=1, max_size=100,
    )
)  # fmt: skip
@example([("", "90100", True, "76093836566")])  # near a rounding boundary: left to the others
def test_plain_floats_read_fixed_notation_in_bulk(parts):
    """Fixed notation with at most 7 integer digits and 19 in all (integers: 8 digits) reads
    exactly whenever it is not left to the other paths, and is never left when its digits
    make an integer of at most 2**53 (Clinger's case: one exact division); a token without
    digits is slow. Longer significands may be left where the product lands too near a
    rounding boundary for the 64-bit arithmetic to decide."""
    tokens = [
        (sign + whole + ("." if point else "") + frac).encode()
        for sign, whole, point, frac in parts
    ]
    values, slow = plain_floats(tokens)
    for (_, whole, point, frac), token, value, left in zip(
        parts, tokens, values, slow, strict=True
    ):
        if not whole + frac:  # "", "-", ".", "+."
            assert left, token
        elif len(whole) + len(frac) <= (19 if point else 8):
            assert left or same_bits(value, float(token)), (token, value, float(token))
            assert not left or int(whole + frac) > 2**53, token


def test_token_marks_find_points_exponents_and_odd_tokens():
    tokens = [b"1.5", b"-2e5", b"3.0E-7", b"1.2.3", b"1e5e5", b"1-2", b"1,5", b"1/2", b"e.5", b"7"]
    buf, start, end = _buffer(tokens)
    dot, exp, odd = token_marks(buf, start, end)
    assert odd.tolist() == [False, False, False, True, True, True, True, True, True, False]
    plain = [0, 1, 2, 9]  # where odd, parse_floats is not asked for a value
    assert (np.where(dot >= 0, dot - start, -1))[plain].tolist() == [1, -1, 1, -1]
    assert (np.where(exp >= 0, exp - start, -1))[plain].tolist() == [-1, 2, 3, -1]


@PROPERTY
@given(st.lists(st.integers(-(10**16) + 1, 10**16 - 1), min_size=1, max_size=200))
def test_integers_convert_exactly(ints):
    tokens = [str(i).encode() for i in ints] + [b"+%d" % abs(i) for i in ints]
    buf, start, end = _buffer(tokens)
    values, slow = parse_ints(buf, word_view(buf), start, end)
    assert not slow.any()
    assert values.tolist() == [int(t) for t in tokens]
    odd = [b"1.0", b"-", b"", b"1_0", b"12345678901234567", b"1/2", b"x"]
    buf, start, end = _buffer(odd)
    assert parse_ints(buf, word_view(buf), start, end)[1].all()


def _block(tokens: list[bytes], blanks: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(buf, words, sep)`` of ``tokens`` joined by the single-byte ``blanks`` (and a final
    line break), as the tokenizer gives them to the block parsers."""
    body = tokens[0] + b"".join(b + t for b, t in zip(blanks, tokens[1:], strict=False)) + b"\n"
    buf, words = text_buffer(2 * PAD + len(body))
    buf[PAD : PAD + len(body)] = np.frombuffer(body, dtype=np.uint8)
    sep = np.flatnonzero(buf[PAD - 1 : PAD + len(body)] <= 32) + PAD - 1
    assert len(sep) == len(tokens) + 1
    return buf, words, sep


def block_floats(tokens: list[bytes], blanks: list[bytes]) -> tuple[list[float], list[bool]]:
    buf, words, sep = _block(tokens, blanks)
    out = np.empty(len(tokens))
    slow = parse_decimal_block(buf, words, sep, out, Scratch())
    return out.tolist(), slow.tolist()


def check_block_floats(tokens: list[bytes], blanks: list[bytes]) -> int:
    """What the block parser does not leave slow is float(token) bit for bit (so a token
    Python refuses is always slow); returns how many it read."""
    values, slow = block_floats(tokens, blanks)
    for token, value, left in zip(tokens, values, slow, strict=True):
        if not left:
            assert same_bits(value, float(token)), (token, value)
    return len(tokens) - sum(slow)


junk_tokens = st.text("0123456789.-+eE_xn,/", min_size=1, max_size=8).map(str.encode)
float_tokens = st.one_of(
    doubles.map(lambda x: repr(x).encode()),
    doubles.map(lambda x: b"%.17g" % x),
    decimal_strings(),
    junk_tokens,
)
blank_bytes = st.sampled_from([b" "] * 6 + [b"\n", b"\t"])


@st.composite
def token_blocks(draw, tokens: st.SearchStrategy[bytes]) -> tuple[list[bytes], list[bytes]]:
    toks = draw(st.lists(tokens, min_size=1, max_size=120))
    return toks, [draw(blank_bytes) for _ in toks[1:]]


# the fixture only switches a module constant, the same for every example
WITH_FIXTURE = settings(PROPERTY, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(params=["long double", "integer"])
def quotients(request, monkeypatch):
    """The block parser's hard quotients through the 64-bit long double division (where numpy
    has one) and through the integer path used elsewhere."""
    if request.param == "long double":
        if numparse._POW10_LD is None:
            pytest.skip("no 80-bit long double on this platform")
    else:
        monkeypatch.setattr(numparse, "_POW10_LD", None)
    monkeypatch.setattr(numparse, "EXPONENTS_IN_BULK", 1)  # even one: read by parse_floats
    return request.param


@WITH_FIXTURE
@given(token_blocks(float_tokens))
def test_block_floats_are_exact_or_left_slow(quotients, block):
    check_block_floats(*block)


@WITH_FIXTURE
@given(
    st.lists(
        st.tuples(st.sampled_from(["", "-", "+"]), st.text("0123456789", max_size=8),
                  st.booleans(), st.text("0123456789", max_size=11)),
        min_size=1, max_size=100,
    )
)  # fmt: skip
def test_block_floats_read_fixed_notation(quotients, parts):
    """Fixed notation with up to 8 digits before the point is read by the block parser itself
    when its quotient is one division (at most 15 digits: below 2**53; longer ones may rarely
    be undecided), exactly; a token without a digit is slow."""
    tokens = [(a + b + ("." if c else "") + d).encode() for a, b, c, d in parts]
    values, slow = block_floats(tokens, [b" "] * (len(tokens) - 1))
    for (_, whole, point, frac), token, value, left in zip(
        parts, tokens, values, slow, strict=True
    ):
        if not whole + frac:
            assert left, token
        elif len(whole if point else whole + frac) <= 8 and len(whole + frac) <= 15:
            assert not left, token
        if not left:
            assert same_bits(value, float(token)), (token, value)


unit_tokens = st.builds(
    lambda sign, digit, frac: f"{sign}{digit}.{frac}".encode(),
    st.sampled_from(["", "", "-", "+"]),
    st.sampled_from("0123456789"),
    st.text("0123456789", max_size=20),
)


@WITH_FIXTURE
@given(token_blocks(st.one_of(unit_tokens, unit_tokens, unit_tokens, junk_tokens)))
def test_block_floats_with_one_digit_before_the_point(quotients, block):
    """Mostly ``d.ddd`` tokens, whose points the block parser takes where they must be without
    a search: junk among them (misplaced or extra points, signs alone) is still slow."""
    check_block_floats(*block)


def test_block_floats_leave_points_outside_their_token_slow():
    for tokens in ([b"-", b"..5"], [b"-", b"..5", b"0.5"], [b"1.", b"-.", b"."], [b"1.5", b"2"]):
        values, slow = block_floats(tokens, [b" "] * (len(tokens) - 1))
        for token, value, left in zip(tokens, values, slow, strict=True):
            try:
                expected = float(token)
            except ValueError:
                assert left, token
            else:
                assert left or same_bits(value, expected), token


def test_block_floats_read_written_doubles_themselves(quotients):
    """Shortest-repr doubles of every magnitude mesh files hold (exponents included) are read
    without the per-token paths, but for under 1%."""
    rng = np.random.default_rng(1)
    xs = np.concatenate([rng.normal(size=20000), rng.uniform(-1e-6, 1e-6, 5000)]).tolist()
    tokens = [repr(x).encode() for x in xs] + [b"%.17g" % x for x in xs]
    values, slow = block_floats(tokens, [b" "] * (len(tokens) - 1))
    assert sum(slow) < 0.01 * len(tokens)
    for token, value, left in zip(tokens, values, slow, strict=True):
        if not left:
            assert same_bits(value, float(token)), (token, value)


@settings(PROPERTY, max_examples=40)
@given(st.lists(st.tuples(st.integers(0, 2**64 - 1), st.integers(0, 27)), min_size=1))
def test_long_double_quotients_are_correctly_rounded_or_undecided(cases):
    """w / 10**k by one 64-bit long double division: the correctly rounded double (Python's
    Fraction to float) unless left undecided."""
    if numparse._POW10_LD is None:
        pytest.skip("no 80-bit long double on this platform")
    w = np.array([c[0] for c in cases], dtype=np.uint64)
    k = np.array([c[1] for c in cases], dtype=np.int64)
    done = numparse._divide_exact(w, k)
    assert done is not None
    for (wi, ki), value, undecided in zip(cases, *done, strict=True):
        if not undecided:
            assert same_bits(value, float(Fraction(wi, 10**ki))), (wi, ki)


def test_long_double_quotients_leave_the_midpoints_undecided():
    """Exact midpoints between doubles are undecided (ties to even would be right, but
    the path cannot tell them from quotients rounded onto a midpoint)."""
    if numparse._POW10_LD is None:
        pytest.skip("no 80-bit long double on this platform")
    midpoint = 2**54 + 2  # between the doubles 2**54 and 2**54 + 4
    w = np.array([midpoint, midpoint * 10], dtype=np.uint64)
    k = np.array([0, 1], dtype=np.int64)
    done = numparse._divide_exact(w, k)
    assert done is not None
    assert done[1].tolist() == [True, True]


@st.composite
def face_blocks(draw) -> tuple[list[bytes], int, bool]:
    """Lines ``k i1 .. ik`` of one degree, and whether each token is what the index block
    parser reads (digits only, at most 16; every k right)."""
    k = draw(st.integers(3, 9))
    index = st.one_of(
        st.integers(0, 10**7).map(str), st.text("0123456789", min_size=1, max_size=18)
    )
    readable = True
    tokens = []
    for _ in range(draw(st.integers(1, 30))):
        line = [draw(index) for _ in range(k)]
        head = str(k)
        if draw(st.integers(0, 19)) == 0:
            line[draw(st.integers(0, k - 1))] = draw(st.sampled_from(["-1", "1.0", "x", "1/2"]))
            readable = False
        if draw(st.integers(0, 19)) == 0:
            head = draw(st.sampled_from([str(k + 1), "03", "a"]))
            readable = False
        readable &= all(len(t) <= 16 for t in line)
        tokens += [head.encode()] + [t.encode() for t in line]
    return tokens, k + 1, readable


@PROPERTY
@given(face_blocks(), blank_bytes)
def test_index_blocks_read_exactly_or_decline(case, blank):
    tokens, width, readable = case
    buf, words, sep = _block(tokens, [blank] * (len(tokens) - 1))
    out = np.empty(len(tokens) // width * (width - 1), dtype=np.int64)
    read = parse_index_block(buf, words, sep, width, out, Scratch())
    assert read == readable
    if read:
        indices = [t for i, t in enumerate(tokens) if i % width]
        assert out.tolist() == [int(t) for t in indices]


# --------------------------------------------------------------------------------------------
# the bulk OBJ parser against the line parser
# --------------------------------------------------------------------------------------------


def _obj_line(draw, num_verts: int) -> str:
    kinds = ["v", "v", "f", "f", "f", "vt", "vn", "g", "s", "o", "#"]
    kind = draw(st.sampled_from(kinds * 4 + ["bad"]))
    pad = draw(st.sampled_from(["", "", " ", "\t"]))
    if kind == "v":
        n = draw(st.sampled_from([3] * 10 + [4, 2]))
        values = [draw(st.sampled_from([repr, "{:.17g}".format]))(draw(doubles)) for _ in range(n)]
        return pad + "v " + " ".join(values)
    if kind == "f":
        in_range = st.one_of(st.integers(1, num_verts), st.integers(-num_verts, -1))
        index = st.one_of(*[in_range] * 15, st.integers(-num_verts - 2, num_verts + 2))
        suffix = st.sampled_from(["", "/1", "//2", "/1/2"] * 10 + ["/"])
        corners = [str(draw(index)) + draw(suffix) for _ in range(draw(st.integers(3, 6)))]
        return pad + "f " + " ".join(corners)
    if kind in ("vt", "vn"):
        return f"{kind} 0.5 0.25 1"
    if kind == "#":
        return "# a comment f 1 2 3"
    if kind == "bad":
        return draw(st.sampled_from(["v 1 x 2", "f 1 2.5 3", "foo", "vp 1", "l 1 2", "f", "f 1 2"]))
    return kind + draw(st.sampled_from(["", " off", " name", " default", " 0"]))


@st.composite
def obj_texts(draw) -> bytes:
    lines = [f"v {i} 0 {-i}" for i in range(8)]
    lines += [_obj_line(draw, 8) for _ in range(draw(st.integers(1, 12)))]
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    text = newline.join(lines) + draw(st.sampled_from([newline, ""]))
    return text.encode()


def _parse(parser, text: bytes):
    skipped = Skipped()
    try:
        parsed = parser(text, skipped)
    except ValueError as e:
        return "error", str(e)
    if parsed is None:
        return None
    return (
        parsed.verts.view(np.int64).tolist(),
        parsed.indices.tolist(),
        parsed.sizes.tolist(),
        skipped.counts,
        skipped.examples,
        skipped.attributes_hint,
    )


@settings(PROPERTY, max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(obj_texts())
def test_bulk_obj_parser_agrees_with_line_parser(text):
    plain = obj_module._plain_text(text)
    assert plain is not None
    bulk = _parse(lambda t, s: obj_module._read_obj_bulk(plain, "m.obj", s), text)
    lines = _parse(lambda t, s: obj_module._read_obj_lines(t, "m.obj", s, False), text)
    if bulk is None:  # it gives up on broken files only (these have no \\ continuations)
        assert lines[0] == "error"
    else:
        assert lines == bulk


@contextmanager
def chunk_bytes(size: int):
    """Cut texts into chunks of about ``size`` bytes (every layout then meets a boundary), and
    convert even a few tokens with the numpy paths (small files otherwise go to Python's)."""
    saved = tokens_module.CHUNK_BYTES, tokens_module.PYTHON_BELOW, numparse.EXPONENTS_IN_BULK
    tokens_module.CHUNK_BYTES = size
    tokens_module.PYTHON_BELOW = 0
    numparse.EXPONENTS_IN_BULK = 1
    try:
        yield
    finally:
        tokens_module.CHUNK_BYTES, tokens_module.PYTHON_BELOW, numparse.EXPONENTS_IN_BULK = saved


@st.composite
def token_texts(draw) -> bytes:
    word = st.text("0123456789.-vf/e", min_size=1, max_size=6)
    lines = []
    for _ in range(draw(st.integers(0, 12))):
        sep = draw(st.sampled_from([" "] * 6 + ["\t", "  ", "\x0b", "\x0c"]))
        lead, trail = (draw(st.sampled_from([""] * 4 + [" ", "\t"])) for _ in range(2))
        lines.append(lead + sep.join(draw(st.lists(word, max_size=5))) + trail)
    return ("\n".join(lines) + draw(st.sampled_from(["\n", ""]))).encode()


@settings(PROPERTY, max_examples=300)
@given(token_texts(), st.sampled_from([1, 8, 24, 1 << 21]))
def test_tokens_and_lines_are_those_of_str_split(text, size):
    """Per-line token counts, each line's first token and every token's text, whatever the
    blanks (single spaces take the tokenizer's shortcut, anything else its line search)."""
    lines = text.decode().split("\n") if text else []
    if text.endswith(b"\n"):
        lines.pop()
    got_counts, got_first, got_tokens = [], [], []
    with chunk_bytes(size):
        for chunk in tokens_module.chunks(text):
            got_counts += chunk.per_line.tolist()
            got_first += [
                chunk.text(int(t)) if n else None
                for t, n in zip(chunk.first_token, chunk.per_line, strict=True)
            ]
            got_tokens += [chunk.text(i) for i in range(len(chunk.start))]
    assert got_counts == [len(line.split()) for line in lines]
    assert got_first == [line.split()[0] if line.split() else None for line in lines]
    assert got_tokens == text.decode().split()


@st.composite
def uniform_obj_texts(draw) -> bytes:
    """Runs of ``v x y z`` lines and of faces of one degree (the tokenizer's block layout),
    with corner suffixes, negative indices and the odd other record."""
    lines: list[str] = []
    num_verts = 0
    for _ in range(draw(st.integers(1, 3))):
        new = draw(st.integers(3, 8))
        for _ in range(new):
            values = [draw(st.sampled_from([repr, "{:.6f}".format]))(draw(doubles)) for _ in "xyz"]
            lines.append("v " + " ".join(values))
        num_verts += new
        k = draw(st.integers(3, 5))
        suffix = draw(st.sampled_from(["", "/1", "//1", "/1/1"]))
        index = st.one_of(st.integers(1, num_verts), st.integers(-num_verts, -1))
        for _ in range(draw(st.integers(1, 8))):
            lines.append("f " + " ".join(f"{draw(index)}{suffix}" for _ in range(k)))
        if draw(st.integers(0, 3)) == 0:
            lines.append(draw(st.sampled_from(["g part", "usemtl m", "vt 0 1", "s 1"])))
    return ("\n".join(lines) + "\n").encode()


@settings(PROPERTY, max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(uniform_obj_texts(), obj_texts()), st.sampled_from([16, 64, 256]))
def test_bulk_obj_parser_agrees_with_line_parser_across_chunks(text, size):
    """Small chunks: block and per-line paths, on either side of every boundary, give what the
    line parser gives; the bulk parser declines only files that are in error."""
    plain = obj_module._plain_text(text)
    assert plain is not None
    with chunk_bytes(size):
        bulk = _parse(lambda t, s: obj_module._read_obj_bulk(plain, "m.obj", s), text)
    lines = _parse(lambda t, s: obj_module._read_obj_lines(t, "m.obj", s, False), text)
    if bulk is None:
        assert lines[0] == "error"
    else:
        assert lines == bulk


@settings(PROPERTY, max_examples=100, suppress_health_check=[HealthCheck.too_slow])
@given(uniform_obj_texts(), st.sampled_from([16, 64, 1 << 21]))
def test_bulk_obj_parser_reads_block_layouts(text, size):
    plain = obj_module._plain_text(text)
    assert plain is not None
    with chunk_bytes(size):
        bulk = _parse(lambda t, s: obj_module._read_obj_bulk(plain, "m.obj", s), text)
    assert bulk is not None
    assert bulk == _parse(lambda t, s: obj_module._read_obj_lines(t, "m.obj", s, False), text)


def test_bulk_parser_handles_real_files_it_is_given(tmp_path):
    """The common cases do take the bulk path: mixed degrees, CRLF, comments, negative and
    v/vt/vn indices, vt/vn/g/usemtl records."""
    text = (
        b"# head\r\nmtllib a.mtl\r\nv 0 0 0\r\nv 1 0 0 # c\r\nv 1 1 0\r\nv 0 1 0 0.5\r\n"
        b"vt 0 0\r\nvn 0 0 1\r\ng grp\r\nusemtl m\r\nf 1/1/1 2/1/1 3/1/1 4/1/1\r\n"
        b"f -4 -3 -1\r\nf 1//1 2//1 3//1\r\n"
    )
    plain = obj_module._plain_text(text)
    assert plain is not None
    got = _parse(lambda t, s: obj_module._read_obj_bulk(plain, "m.obj", s), text)
    assert got is not None
    assert got == _parse(lambda t, s: obj_module._read_obj_lines(t, "m.obj", s, False), text)
    assert got[1:3] == ([0, 1, 2, 3, 0, 1, 3, 0, 1, 2], [4, 3, 3])


# --------------------------------------------------------------------------------------------
# memory
# --------------------------------------------------------------------------------------------


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    s = np.linspace(0.0, 1.0, n + 1)
    xs, ys = np.meshgrid(s, s, indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), 0.05 * np.sin(7 * xs).ravel()], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    quads = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)
    return verts, quads.reshape(-1, 4)


@pytest.mark.parametrize("name", ["grid.obj", "grid.off", "grid.ply"])
def test_peak_memory_of_a_read_is_a_few_times_the_file(tmp_path, name):
    """A ~20 MB file: the read's peak (the file's bytes included; numpy arrays are
    traced by tracemalloc) stays under 5x its size (about 4x here, under 3x on a 90 MB file:
    the chunk work arrays are a fixed ~20 MB); the line parsers peaked at 8-38x."""
    verts, quads = _grid(450)
    path = tmp_path / name
    write_mesh(path, verts, quads)
    size = path.stat().st_size
    assert size > 15e6
    tracemalloc.start()
    try:
        got, faces = read_mesh(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert np.array_equal(got.numpy(), verts) and faces.num_faces == len(quads)
    assert peak <= 5 * size, f"peak {peak / size:.1f}x the file size"


# --------------------------------------------------------------------------------------------
# reader bugs: nothing silent
# --------------------------------------------------------------------------------------------

TRIANGLE_V = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\n"


@pytest.mark.parametrize("corner", ["3/", "3//"])
def test_obj_corner_with_trailing_slashes_is_the_vertex(tmp_path, corner):
    """``f 1/ 2/ 3/`` (the polyLaplace research code's export) names vertices 1, 2, 3."""
    path = tmp_path / "slashes.obj"
    path.write_bytes(f"{TRIANGLE_V}f 1 2 4\nf 1 2 {corner}\n".encode())
    _, faces = read_mesh(path)
    plain = tmp_path / "plain.obj"
    plain.write_bytes(f"{TRIANGLE_V}f 1 2 4\nf 1 2 3\n".encode())
    _, want = read_mesh(plain)
    assert faces.indices.tolist() == want.indices.tolist()


@pytest.mark.parametrize("last", ["f 1 2 3", "v 0.5 0.5 0.5"])
def test_obj_ending_inside_a_record_warns(tmp_path, last):
    path = tmp_path / "cut.obj"
    body = TRIANGLE_V + "f 1 2 4\n" + last
    path.write_bytes(body.encode())
    what = "face" if last.startswith("f") else "vertex"
    with pytest.warns(UserWarning, match=rf"cut\.obj, line 6: the file ends inside a {what}"):
        read_mesh(path)
    path.write_bytes((body + "\n").encode())  # with its line break: complete, no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_mesh(path)


PLY_HEAD = (
    "ply\nformat {fmt} 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face 1\nproperty list {count} {item} vertex_indices\nend_header\n"
)
PLY_VERTS = [0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0]


def _ply(fmt: str, face: list[float], item: str = "float", count: str = "uchar", k=None) -> bytes:
    head = PLY_HEAD.format(fmt=fmt, count=count, item=item).encode()
    k = len(face) if k is None else k
    if fmt == "ascii":
        rows = ["0 0 0", "1 0 0", "0 1 0", "1 1 0", " ".join(map(str, [k, *face]))]
        return head + ("\n".join(rows) + "\n").encode()
    codes = {"float": "f", "double": "d", "int": "i", "uchar": "B", "uint": "I"}
    body = struct.pack("<12f", *PLY_VERTS)
    body += struct.pack(f"<{codes[count]}{len(face)}{codes[item]}", k, *face)
    return head + body


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
@pytest.mark.parametrize("item", ["float", "double"])
def test_ply_float_index_lists_must_hold_whole_numbers(tmp_path, fmt, item):
    path = tmp_path / "f.ply"
    path.write_bytes(_ply(fmt, [0.7, 1.7, 2.9], item))
    line = r"line 14: " if fmt == "ascii" else ""
    with pytest.raises(
        ValueError,
        match=rf"f\.ply, {line}element 'face' record 0: face 0 lists 0\.(7|69)\d* in "
        r"'vertex_indices', which is no vertex index",
    ):
        read_mesh(path)
    path.write_bytes(_ply(fmt, [0.0, 1.0, 3.0], item))  # whole numbers: read as indices
    assert read_mesh(path)[1].tolist() == [[0, 1, 3]]


@pytest.mark.parametrize("count", [2**30, 2**31 + 5, 2**32 - 1])
def test_ply_list_longer_than_the_file_names_its_length(tmp_path, count):
    path = tmp_path / "long.ply"
    path.write_bytes(_ply("binary_little_endian", [0, 1, 2], "int", "uint", k=count))
    with pytest.raises(
        ValueError,
        match=rf"long\.ply: PLY element 'face' record 0 declares a list of {count} values, but "
        r"only 12 bytes are left",
    ):
        read_mesh(path)


def test_ply_truncated_mixed_faces_names_the_record(tmp_path):
    verts, quads = _grid(3)
    faces = [list(quads[0]), [0, 1, 5], *map(list, quads[1:])]
    path = tmp_path / "m.ply"
    write_mesh(path, verts, faces, binary=True)
    path.write_bytes(path.read_bytes()[:-3])
    with pytest.raises(ValueError, match=r"element 'face' record 9 .*truncated file"):
        read_mesh(path)


def test_skipped_warning_is_the_same_through_both_parsers(tmp_path):
    text = "o x\nv 0 0 0 1\nv 1 0 0\nv 0 1 0\nvt 0 0\nfoo 1\ng a\nf 1 2 3\nbar\nbaz\nqux\n"
    path = tmp_path / "w.obj"
    path.write_bytes(text.encode())
    with pytest.warns(SkippedContentWarning) as bulk:
        read_mesh(path)
    path.write_bytes(text.replace("g a", "g a\x1b").encode())  # ESC: the line parser reads it
    with pytest.warns(SkippedContentWarning) as lines:
        read_mesh(path)
    message = str(bulk[0].message)
    assert message == str(lines[0].message)
    assert re.search(r"unknown keyword \(4: 'foo' at line 6, 'bar' at line 9, 'baz' at", message)


@st.composite
def off_texts(draw) -> tuple[bytes, bool]:
    """Random ASCII OFF text, and whether a face record is wrapped over two lines."""
    num_verts = draw(st.integers(3, 8))
    keyword = draw(st.sampled_from(["OFF\n", "COFF\n", "OFF ", "", "NOFF\n\n"]))
    declared_faces = draw(st.integers(1, 5))
    lines = [f"{keyword}{num_verts} {declared_faces} 0"]
    wrapped = False
    for _ in range(num_verts + draw(st.sampled_from([0] * 8 + [-1]))):
        values = [repr(draw(doubles)) for _ in range(draw(st.sampled_from([3] * 6 + [2, 4, 7])))]
        lines.append(" ".join(values) + draw(st.sampled_from(["", "", "  # c"])))
    for _ in range(declared_faces + draw(st.sampled_from([0] * 8 + [-1, 1]))):
        k = draw(st.sampled_from([3, 4, 5, 2]))
        corners = [
            str(draw(st.integers(0, num_verts - (draw(st.integers(0, 20)) > 0)))) for _ in range(k)
        ]
        colour = draw(st.sampled_from(["", "", " 255 0 0", " 1"]))
        wrap = draw(st.sampled_from([" "] * 8 + ["\n"]))
        wrapped |= wrap == "\n"
        lines.append(f"{k}{wrap}" + " ".join(corners) + colour)
        if draw(st.integers(0, 9)) == 0:
            lines.append(draw(st.sampled_from(["", "# comment", "   "])))
    return ("\n".join(lines) + "\n").encode(), wrapped


@st.composite
def uniform_off_texts(draw) -> tuple[bytes, bool]:
    """OFF in the block layout: ``x y z`` lines, then runs of faces of one degree each (the
    first run's degree sizes the index array; a later one switches to joined pieces)."""
    num_verts = draw(st.integers(3, 12))
    degree, count = st.integers(3, 5), st.integers(1, 10)
    runs = [(draw(degree), draw(count)) for _ in range(draw(st.integers(1, 2)))]
    lines = [f"OFF\n{num_verts} {sum(n for _, n in runs)} 0"]
    for _ in range(num_verts):
        fmt = draw(st.sampled_from([repr, "{:.6f}".format, "{:.3e}".format]))
        lines.append(" ".join(fmt(draw(doubles)) for _ in "xyz"))
    for k, faces in runs:
        for _ in range(faces):
            corners = (str(draw(st.integers(0, num_verts - 1))) for _ in range(k))
            lines.append(f"{k} " + " ".join(corners))
    return ("\n".join(lines) + "\n").encode(), False


@settings(PROPERTY, max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(off_texts(), uniform_off_texts()), st.sampled_from([16, 64, 1 << 21]))
def test_bulk_off_parser_agrees_with_record_parser(case, size):
    from torch_polylap.io import off as off_module

    text, wrapped = case
    from torch_polylap.io.common import plain_text

    with chunk_bytes(size):
        bulk = _parse(lambda t, s: off_module._read_off_bulk(plain_text(t), "m.off", s), text)

    def reference(t: bytes, s: Skipped):
        # the record parser, with the bulk one switched off
        original = off_module._read_off_bulk
        off_module._read_off_bulk = lambda *args: None
        try:
            return off_module.read_off(t, "m.off", s, False)
        finally:
            off_module._read_off_bulk = original

    lines = _parse(reference, text)
    if bulk is not None:
        assert lines == bulk
    elif not wrapped:
        assert lines[0] == "error"  # it gives up only on broken files and wrapped faces


# --------------------------------------------------------------------------------------------
# the bulk ASCII PLY parser against the record parser
# --------------------------------------------------------------------------------------------


def _ply_value(draw, kind: str) -> str:
    if kind == "f":
        return draw(st.sampled_from([repr, "{:.17g}".format]))(draw(doubles))
    return str(draw(st.integers(0, 300)))


@st.composite
def ply_ascii_texts(draw) -> bytes:
    """Random ASCII PLY: extra vertex properties, scalars around the face list, an extra
    element, float or int index lists, and now and then a broken record, a blank line or a
    missing one."""
    num_verts, num_faces = draw(st.integers(3, 6)), draw(st.integers(1, 4))
    vprops = [("x", "f"), ("y", "f"), ("z", "f")]
    vprops += draw(st.sampled_from([[], [("nx", "f"), ("ny", "f"), ("nz", "f")], [("red", "i")]]))
    before = draw(st.sampled_from([[], [("flags", "i")]]))
    after = draw(st.sampled_from([[], [("material", "i")], [("w", "f"), ("q", "i")]]))
    item = draw(st.sampled_from(["int", "uint", "float"]))
    count = draw(st.sampled_from(["uchar", "int"]))
    edge_at = draw(st.sampled_from([None, 1, 2]))
    type_name = {"f": "double", "i": "int"}

    head = ["ply", "format ascii 1.0", f"element vertex {num_verts}"]
    head += [f"property {type_name[k]} {p}" for p, k in vprops]
    elements = [("vertex", num_verts), ("face", num_faces)]
    face_head = [f"element face {num_faces}"]
    face_head += [f"property {type_name[k]} {p}" for p, k in before]
    face_head += [f"property list {count} {item} vertex_indices"]
    face_head += [f"property {type_name[k]} {p}" for p, k in after]
    edge_head = ["element edge 2", "property int vertex1", "property int vertex2"]
    if edge_at == 1:
        head += edge_head
        elements.insert(1, ("edge", 2))
    head += face_head
    if edge_at == 2:
        head += edge_head
        elements.append(("edge", 2))
    head.append("end_header")

    rows = []
    for name, n in elements:
        for _ in range(n):
            if name == "vertex":
                row = [_ply_value(draw, k) for _, k in vprops]
            elif name == "edge":
                row = [str(draw(st.integers(0, num_verts - 1))) for _ in range(2)]
            else:
                k = draw(st.sampled_from([3] * 8 + [4] * 8 + [5, 6, 2]))
                index = st.integers(0, num_verts - (draw(st.integers(0, 60)) > 0))
                corners = [str(draw(index)) for _ in range(k)]
                if item == "float":
                    corners = [c + draw(st.sampled_from([".0", ""] * 10 + [".5"])) for c in corners]
                row = [_ply_value(draw, k) for _, k in before] + [str(k), *corners]
                row += [_ply_value(draw, k) for _, k in after]
            broken = draw(st.integers(0, 80))
            if broken == 0 and len(row) > 1:
                row.pop()
            elif broken == 1:
                row[draw(st.integers(0, len(row) - 1))] = draw(st.sampled_from(["x1", "nan", "#"]))
            elif broken == 2:
                rows.append("")
            rows.append(draw(st.sampled_from([" ", " ", "  ", "\t"])).join(row))
    rows += draw(st.sampled_from([[], [], ["1 2"], [""]]))
    if draw(st.integers(0, 15)) == 0:
        rows.pop()
    newline = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    return (newline.join(head + rows) + draw(st.sampled_from([newline, ""]))).encode()


def _read_ply_both(text: bytes, want_attributes: bool):
    """``read_ply`` with its bulk ASCII parser, and with only the record parser; and whether
    the bulk one answered."""
    from torch_polylap.io import ply as ply_module

    answered = []
    bulk_parser = ply_module._read_ply_ascii_bulk

    def spy(*args):
        got = bulk_parser(*args)
        answered.append(got is not None)
        return got

    results = []
    for parser in (spy, lambda *args: None):
        ply_module._read_ply_ascii_bulk = parser
        try:
            results.append(
                _parse(lambda t, s: ply_module.read_ply(t, "m.ply", s, want_attributes), text)
            )
        finally:
            ply_module._read_ply_ascii_bulk = bulk_parser
    return results[0], results[1], any(answered)


@settings(PROPERTY, max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(ply_ascii_texts(), st.booleans())
def test_bulk_ply_parser_agrees_with_record_parser(text, want_attributes):
    """The same vertices, faces, attributes, warning and error message (naming the line)
    either way; the bulk parser gives up only where the record parser refuses the file (or on a
    '#', which an element that is not read may hold)."""
    bulk, reference, answered = _read_ply_both(text, want_attributes)
    assert bulk == reference
    if not answered and b"#" not in text:
        assert reference[0] == "error"


def test_bulk_ply_parser_reads_what_write_mesh_writes(tmp_path):
    verts, quads = _grid(4)
    faces = [[0, 1, 6], *map(list, quads)]
    path = tmp_path / "m.ply"
    write_mesh(path, verts, faces)
    bulk, reference, answered = _read_ply_both(path.read_bytes(), False)
    assert answered and bulk == reference
    assert np.array_equal(np.array(bulk[0]).view(np.float64).reshape(-1, 3), verts)


@pytest.mark.parametrize(
    ("record", "message"),
    [
        ("4 0 1 2", r"line 15: element 'face' record 1 has 4 values, but its properties need 5"),
        ("3 0 1 9", r"line 15: element 'face' record 1: face 1 refers to vertex 9, out of range"),
        ("3 0 1 x", r"line 15: element 'face' record 1: cannot parse 'vertex_indices' value 'x'"),
    ],
)
def test_broken_ascii_ply_records_name_their_line(tmp_path, record, message):
    head = PLY_HEAD.format(fmt="ascii", count="uchar", item="int").replace("face 1", "face 2")
    rows = ["0 0 0", "1 0 0", "0 1 0", "1 1 0", "3 0 1 2", record]
    path = tmp_path / "b.ply"
    path.write_bytes((head + "\n".join(rows) + "\n").encode())
    with pytest.raises(ValueError, match=r"b\.ply, " + message):
        read_mesh(path)


# --------------------------------------------------------------------------------------------
# the vectorized integer writer
# --------------------------------------------------------------------------------------------


@PROPERTY
@given(
    st.lists(
        st.lists(st.integers(0, 2**63 - 1) | st.integers(0, 10**7), min_size=1, max_size=7),
        max_size=30,
    ),
    st.sampled_from([b"", b"f", b"ab"]),
)
def test_int_lines_match_python_formatting(lines, prefix):
    from torch_polylap.io.writers import int_lines

    tokens = np.array([t for line in lines for t in line], dtype=np.int64)
    per_line = np.array([len(line) for line in lines], dtype=np.int64)
    want = "".join(
        " ".join(([prefix.decode()] if prefix else []) + list(map(str, line))) + "\n"
        for line in lines
    )
    assert int_lines(tokens, per_line, prefix) == want.encode()


@settings(PROPERTY, max_examples=40)
@given(sizes=st.lists(st.integers(3, 7), min_size=1, max_size=20), seed=st.integers(0, 2**32))
def test_written_faces_read_back_through_every_text_format(sizes, seed, tmp_path_factory):
    """Mixed and uniform degrees: OBJ, OFF and ASCII PLY text of the faces is what Python's
    formatting gives, and reads back to the same faces."""
    from torch_polylap.io.writers import face_block

    rng = np.random.default_rng(seed)
    num_verts = int(sum(sizes)) + 1
    indices = rng.integers(0, num_verts, int(sum(sizes)))
    sizes_arr = np.array(sizes, dtype=np.int64)
    rows = np.split(indices, np.cumsum(sizes_arr)[:-1])
    obj = "".join("f " + " ".join(str(i + 1) for i in row) + "\n" for row in rows)
    off = "".join(f"{len(row)} " + " ".join(map(str, row)) + "\n" for row in rows)
    assert face_block(indices, sizes_arr, prefix="f", base=1) == obj.encode()
    assert face_block(indices, sizes_arr) == off.encode()
    verts = rng.normal(size=(num_verts, 3))
    folder = tmp_path_factory.mktemp("faces")
    faces = [row.tolist() for row in rows]
    for name in ("m.obj", "m.off", "m.ply"):
        write_mesh(folder / name, verts, faces)
        got, read_faces = read_mesh(folder / name)
        assert np.array_equal(got.numpy(), verts) and read_faces.tolist() == faces


@settings(PROPERTY, max_examples=40)
@given(coords=st.lists(doubles, min_size=9, max_size=30))
def test_written_coordinates_read_back_bit_for_bit(coords, tmp_path_factory):
    """Any finite doubles (subnormals, -0.0, the extremes) written as text read back to the
    same bits: the writers' shortest round-trip decimals and the bulk readers agree."""
    verts = np.array(coords[: len(coords) // 3 * 3]).reshape(-1, 3)
    faces = [[0, 1, 2]]
    folder = tmp_path_factory.mktemp("coords")
    for name in ("c.obj", "c.off", "c.ply"):
        write_mesh(folder / name, verts, faces)
        got, _ = read_mesh(folder / name)
        assert got.numpy().view(np.int64).tolist() == verts.view(np.int64).tolist()
