"""Both number converters of the text readers give what Python's ``float`` and ``int`` give.

numpy's parser is the default; pyarrow's (the ``fast-text`` extra) goes first when it is
installed (the pyarrow cases are skipped without it).  Reference: Python's ``float``/``int``
of each token (correctly rounded, and independent of both), compared bit for bit: tokens of
every shape through :meth:`Chunk.values`, and random doubles written and read back.
"""

from __future__ import annotations

from contextlib import contextmanager, nullcontext

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_polylap.io import read_mesh, write_mesh
from torch_polylap.io import text as text_module
from torch_polylap.io.common import BadNumber

PROPERTY = settings(
    max_examples=150,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],  # device: read only
)
PARSERS = ["numpy", "pyarrow"]

doubles = st.floats(width=64, allow_nan=False)  # the infinities too
decimals = st.builds(
    "{}{}.{}e{}".format,
    st.sampled_from(["", "-", "+"]),
    st.text("0123456789", min_size=1, max_size=25),
    st.text("0123456789", max_size=25),
    st.integers(-340, 320),
)
# spellings Python accepts, or refuses, that a C parser may read otherwise
special = st.sampled_from(
    ["nan", "-nan", "+NaN", "inf", "-Infinity", "1.", ".5", "-0", "00.5", "1e400", "1_0",
     "4.9e-324", "2.4703282292062328e-324", "2.4703282292062327e-324", "0x10", "1e", "nan(1)",
     "1.5f", "+-1", "\x1b1"]
)  # fmt: skip
integers = st.integers(-(10**18) + 1, 10**18 - 1).map(str) | st.sampled_from(
    ["+5", "007", "-0", "1_000", "99999999999999999999", "1.0", "x", "0x1", "0X1f"]
)
spaces = st.sampled_from([" ", "  ", "\t", "\n", " \n\n "])


@contextmanager
def parser(name: str):
    """Numbers converted by ``name``: pyarrow (skipped where it is not installed) or numpy."""
    if name == "pyarrow":
        pytest.importorskip("pyarrow")
        yield
        return
    saved = text_module._arrow
    text_module._arrow = lambda: None
    try:
        yield
    finally:
        text_module._arrow = saved


def python_values(tokens: list[str], kind: type) -> list[int] | int:
    """The bits (floats) or values (ints) Python gives, or the index of the first refused."""
    out = []
    for i, tok in enumerate(tokens):
        try:
            value = kind(tok)
        except ValueError:
            return i
        if kind is int and not -(2**63) <= value < 2**63:  # no int64: refused too
            return i
        out.append(int(np.float64(value).view(np.int64)) if kind is float else value)
    return out


def chunk_values(tokens: list[str], seps: list[str], kind: type, pick: list[bool]):
    """What :meth:`Chunk.values` makes of the picked tokens, joined by ``seps``."""
    text = "".join(t + s for t, s in zip(tokens, seps, strict=False)).encode("latin-1")
    chunk = text_module.Chunk(text, 0, len(text), 0)
    assert len(chunk.start) == len(tokens)
    wanted = np.flatnonzero(pick)
    try:
        out = chunk.values(wanted, kind)
    except BadNumber as e:
        return int(wanted[e.position])
    return out.view(np.int64).tolist() if kind is float else out.tolist()


@pytest.mark.parametrize("name", PARSERS)
@PROPERTY
@given(data=st.data(), kind=st.sampled_from([float, int]))
def test_tokens_convert_as_python_does(name, data, kind):
    token = (st.floats(width=64).map(repr) | decimals | special) if kind is float else integers
    tokens = data.draw(st.lists(token, min_size=1, max_size=30))
    seps = data.draw(st.lists(spaces, min_size=len(tokens), max_size=len(tokens)))
    pick = data.draw(st.lists(st.booleans(), min_size=len(tokens), max_size=len(tokens)))
    pick[data.draw(st.integers(0, len(tokens) - 1))] = True  # at least one token
    chosen = [t for t, p in zip(tokens, pick, strict=True) if p]
    want = python_values(chosen, kind)
    if not isinstance(want, list):  # the index of the first refused token
        want = int(np.flatnonzero(pick)[want])
    with parser(name):
        assert chunk_values(tokens, seps, kind, pick) == want


@pytest.mark.parametrize("name", PARSERS)
@PROPERTY
@given(
    coords=st.lists(doubles, min_size=9, max_size=60), fmt=st.sampled_from(["obj", "off", "ply"])
)
def test_any_double_written_reads_back_bit_for_bit(name, coords, fmt, tmp_path_factory, device):
    verts = np.array(coords[: len(coords) // 3 * 3]).reshape(-1, 3)
    path = tmp_path_factory.mktemp("parsers") / f"m.{fmt}"
    write_mesh(path, verts, [[0, 1, 2]])
    finite = np.isfinite(verts).all()
    with parser(name), nullcontext() if finite else pytest.warns(UserWarning, match="non-finite"):
        got, faces = read_mesh(path, device=device)
    assert got.device.type == device.type and faces.tolist() == [[0, 1, 2]]
    assert got.cpu().numpy().view(np.int64).tolist() == verts.view(np.int64).tolist()


@pytest.mark.parametrize("name", PARSERS)
@pytest.mark.parametrize(
    ("fmt", "text", "message"),
    [
        ("off", "OFF\n3 1 0\n0 0 0\n1 2e 0\n0 1 0\n3 0 1 2\n",
         "line 4: cannot parse vertex coordinate '2e'"),
        ("obj", "v 0 0 0\nv 1 0 0\nv 0 1 1_0\nv 0 x 1\nf 1 2 3\n",
         "line 4: cannot parse vertex coordinate 'x'"),
        ("ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
         "property double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
         "0 0 0\n1 0 0\n0 1 nan(7)\n3 0 1 2\n", "line 12: element 'vertex' record 2: cannot parse"),
    ],
)  # fmt: skip
def test_a_refused_number_names_its_line(name, fmt, text, message, tmp_path):
    path = tmp_path / f"m.{fmt}"
    path.write_text(text)
    with parser(name), pytest.raises(ValueError, match=message):
        read_mesh(path)


def test_pyarrow_converts_plain_tokens_itself():
    """With pyarrow installed, it (not the numpy fallback) converts what it can: Python's
    values; what Python spells otherwise ("+1" as an int, "1_0") it leaves to the others."""
    pytest.importorskip("pyarrow")
    piece = np.frombuffer(b"0.1 -2e-3\t\n7 +1 1_0", dtype=np.uint8)
    at = np.array([0, 4, 11])
    got = text_module._arrow_numbers(piece[:12], at, np.float64)
    assert got is not None and got.tolist() == [0.1, -2e-3, 7.0]
    assert text_module._arrow_numbers(piece[:15], np.array([11, 13]), np.int64) is None
    assert text_module._arrow_numbers(piece, np.array([16]), np.float64) is None
