"""Property-based tests of the mesh readers and writers (hypothesis).

* Random valid polygon meshes written in every format read back bit for bit; the text
  formats hold each coordinate as Python's ``repr``; comments and blank lines added to the
  text change nothing; a number replaced by a non-number gives a ValueError naming the file
  and the line.
* Random corruptions of real files (truncation, flipped bytes, garbage lines, other line
  endings, a byte-order mark, a wrong extension) either raise a ValueError naming the file or
  give a valid mesh: finite coordinates (or a warning saying they are not), every index in
  range, at least one face, and exactly the faces the corrupted file declares (OFF/PLY header
  counts) or holds (OBJ ``f`` records, a cut last line included).

The number of inputs tried per category is printed at the end of the module (``pytest -s``).
"""

from __future__ import annotations

import re
import warnings
from collections import Counter

import numpy as np
import pytest
import torch
from conftest import DATA
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_polylap.io import MeshAttributes, SkippedContentWarning, read_mesh, write_mesh

FUZZ = settings(
    max_examples=100,
    deadline=None,
    database=None,  # no .hypothesis folder in the working tree
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
TRIED: Counter = Counter()


@pytest.fixture(scope="module", autouse=True)
def report_counts():
    yield
    print("\nfuzz inputs tried per category:", dict(sorted(TRIED.items())))


# --------------------------------------------------------------------------------------------
# round trips of random valid meshes
# --------------------------------------------------------------------------------------------

FORMATS = [("m.obj", False), ("m.off", False), ("m.ply", False), ("m.ply", True)]
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@st.composite
def polygon_meshes(draw) -> tuple[np.ndarray, list[list[int]]]:
    num_verts = draw(st.integers(3, 40))
    coords = draw(st.lists(finite, min_size=3 * num_verts, max_size=3 * num_verts))
    index = st.integers(0, num_verts - 1)
    faces = draw(st.lists(st.lists(index, min_size=3, max_size=9), min_size=1, max_size=30))
    return np.array(coords, dtype=np.float64).reshape(num_verts, 3), faces


@FUZZ
@given(mesh=polygon_meshes(), fmt=st.sampled_from(FORMATS))
def test_random_meshes_round_trip_bit_for_bit(tmp_path, mesh, fmt):
    TRIED["round trip"] += 1
    verts, faces = mesh
    name, binary = fmt
    write_mesh(tmp_path / name, verts, faces, binary=binary)
    got_verts, got_faces = read_mesh(tmp_path / name)
    assert np.array_equal(got_verts.numpy().view(np.int64), verts.view(np.int64))  # -0.0 too
    assert got_faces.tolist() == faces
    if not binary:
        prefix = "v " if name.endswith(".obj") else ""
        lines = "".join(prefix + " ".join(map(repr, row)) + "\n" for row in verts.tolist())
        assert lines.encode() in (tmp_path / name).read_bytes()


TEXT_FORMATS = ["m.obj", "m.off", "m.ply"]


@FUZZ
@given(mesh=polygon_meshes(), name=st.sampled_from(TEXT_FORMATS[:2]), data=st.data())
def test_comments_and_blank_lines_change_nothing(tmp_path, mesh, name, data):
    TRIED["comments / blank lines"] += 1
    verts, faces = mesh
    write_mesh(tmp_path / name, verts, faces)
    lines = (tmp_path / name).read_bytes().split(b"\n")
    extra = st.sampled_from([b"", b"   ", b"# a comment 1 2 3", b"\t# f 1 2 3"])
    for _ in range(data.draw(st.integers(1, 5))):
        at = data.draw(st.integers(1, len(lines) - 1))  # after the first line (OFF's keyword)
        lines.insert(at, data.draw(extra))
    at = data.draw(st.integers(1, len(lines) - 2))
    lines[at] += data.draw(st.sampled_from([b" # trailing", b"#", b" "]))
    (tmp_path / name).write_bytes(b"\n".join(lines))
    got_verts, got_faces = read_mesh(tmp_path / name)
    assert np.array_equal(got_verts.numpy().view(np.int64), verts.view(np.int64))
    assert got_faces.tolist() == faces


@FUZZ
@given(
    mesh=polygon_meshes(),
    name=st.sampled_from(TEXT_FORMATS),
    data=st.data(),
    bad=st.sampled_from([b"x", b"1..5", b"--2", b"1e", b"0x1", b"1,5", b"nan(1)"]),
)
def test_a_broken_number_is_named_with_its_line(tmp_path, mesh, name, data, bad):
    """Any number of a written text file replaced by a non-number: the error names the line."""
    TRIED["broken number"] += 1
    verts, faces = mesh
    write_mesh(tmp_path / name, verts, faces)
    lines = (tmp_path / name).read_bytes().split(b"\n")
    first = lines.index(b"end_header") + 1 if name == "m.ply" else 2 * (name == "m.off")
    no = data.draw(st.integers(first, len(lines) - 2))
    toks = lines[no].split(b" ")
    which = data.draw(st.integers(1 if name == "m.obj" else 0, len(toks) - 1))
    toks[which] = bad
    lines[no] = b" ".join(toks)
    (tmp_path / name).write_bytes(b"\n".join(lines))
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / name}, line {no + 1}: ")):
        read_mesh(tmp_path / name)


@FUZZ
@given(mesh=polygon_meshes(), data=st.data())
def test_random_obj_attributes_round_trip(tmp_path, mesh, data):
    TRIED["attribute round trip"] += 1
    verts, faces = mesh
    corners = sum(len(f) for f in faces)
    num_uv, num_n = data.draw(st.integers(1, 10)), data.draw(st.integers(1, 10))
    attrs = MeshAttributes(
        uv=torch.tensor(data.draw(st.lists(finite, min_size=2 * num_uv, max_size=2 * num_uv))),
        normals=torch.tensor(data.draw(st.lists(finite, min_size=3 * num_n, max_size=3 * num_n))),
        corner_uv=torch.tensor(
            data.draw(st.lists(st.integers(-1, num_uv - 1), min_size=corners, max_size=corners))
        ),
        corner_normals=torch.tensor(
            data.draw(st.lists(st.integers(-1, num_n - 1), min_size=corners, max_size=corners))
        ),
    )
    attrs.uv, attrs.normals = attrs.uv.reshape(-1, 2), attrs.normals.reshape(-1, 3)
    write_mesh(tmp_path / "a.obj", verts, faces, attributes=attrs)
    _, got_faces, got = read_mesh(tmp_path / "a.obj", return_attributes=True)
    assert got_faces.tolist() == faces
    assert torch.equal(got.uv, attrs.uv) and torch.equal(got.normals, attrs.normals)
    for key in ("corner_uv", "corner_normals"):
        expected = getattr(attrs, key)
        if (expected >= 0).any():
            assert torch.equal(getattr(got, key), expected)
        else:  # no corner refers to a row: the reader reports no per-corner indices at all
            assert getattr(got, key) is None


# --------------------------------------------------------------------------------------------
# corruptions of real files
# --------------------------------------------------------------------------------------------


def _seeds() -> list[tuple[str, bytes]]:
    """Real meshes: OBJ (with vt, o, s records), ASCII OFF with colours, binary PLY."""
    files = ["dodecahedron_poly.obj", "tetris.obj", "spot_control_mesh.obj", "bunny_poly.ply"]
    return [(name, (DATA / name).read_bytes()) for name in files + ["mixedFaring.off"]]


def _small_off_and_ply(tmp_dir) -> list[tuple[str, bytes]]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedContentWarning)
        verts, faces = read_mesh(DATA / "dodecahedron_poly.obj")
    out = []
    for name, binary in (("dodeca.off", False), ("dodeca.ply", False), ("dodeca_b.ply", True)):
        write_mesh(tmp_dir / name, verts, faces, binary=binary)
        out.append((name, (tmp_dir / name).read_bytes()))
    return out


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> list[tuple[str, bytes]]:
    return _seeds() + _small_off_and_ply(tmp_path_factory.mktemp("seeds"))


def _obj_face_records(data: bytes) -> int:
    """``f`` records in OBJ text, lines joined at ``\\`` continuations as the reader does."""
    text = data.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n")
    count, pending = 0, ""
    for line in text.split("\n"):
        line = (pending + line).split("#", 1)[0]
        if line.rstrip().endswith("\\"):
            pending = line.rstrip()[:-1] + " "
            continue
        pending = ""
        count += line.split()[:1] == ["f"]
    return count


def _declared_faces(data: bytes, ext: str) -> int | None:
    """The face count an OFF or PLY header declares (None when it cannot be found)."""
    if ext == ".ply":
        m = re.search(rb"element face (\d+)", data[:4096])
        return int(m.group(1)) if m else None
    lines = re.split(rb"\r\n|\r|\n", data.removeprefix(b"\xef\xbb\xbf"))
    toks = [t for line in lines for t in line.split(b"#")[0].split()][:4]
    numbers = [int(t) for t in toks[:3] if t.isdigit()]
    return numbers[1] if len(numbers) >= 2 else None


def _check_outcome(path, data: bytes, ext: str) -> str:
    """Read a corrupted file; assert a ValueError naming it or a complete, valid mesh."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            verts, faces = read_mesh(path)
        except ValueError as e:
            assert str(path) in str(e), f"the message does not name the file: {e}"
            return "error"
    v = verts.numpy()
    said_nonfinite = any("non-finite" in str(w.message) for w in caught)
    assert np.isfinite(v).all() or said_nonfinite
    assert faces.num_faces >= 1
    idx = faces.indices.numpy()
    assert idx.min() >= 0 and idx.max() < len(v)
    assert (faces.sizes.numpy() >= 3).all()
    if ext == ".obj":
        assert faces.num_faces == _obj_face_records(data), "an OBJ face was dropped silently"
    else:
        declared = _declared_faces(data, ext)
        assert declared is None or faces.num_faces == declared, "fewer faces than declared"
    return "mesh"


def _write(tmp_path, name: str, data: bytes):
    path = tmp_path / name
    path.write_bytes(data)
    return path


seed_index = st.integers(0, 7)


@FUZZ
@given(which=seed_index, where=st.floats(0, 1))
def test_truncated_files(tmp_path, seeds, which, where):
    name, data = seeds[which % len(seeds)]
    cut = data[: int(where * len(data))]
    TRIED["truncate: " + _check_outcome(_write(tmp_path, name, cut), cut, name[-4:])] += 1


@FUZZ
@given(
    which=seed_index,
    flips=st.lists(st.tuples(st.floats(0, 1), st.integers(1, 255)), min_size=1, max_size=5),
)
def test_flipped_bytes(tmp_path, seeds, which, flips):
    name, data = seeds[which % len(seeds)]
    buf = bytearray(data)
    for where, mask in flips:
        buf[min(int(where * len(buf)), len(buf) - 1)] ^= mask
    out = bytes(buf)
    TRIED["flip bytes: " + _check_outcome(_write(tmp_path, name, out), out, name[-4:])] += 1


garbage_line = st.one_of(
    st.binary(min_size=1, max_size=40),
    st.text(st.characters(min_codepoint=32, max_codepoint=126), min_size=1, max_size=40).map(
        str.encode
    ),
    st.sampled_from([b"f 1 2", b"v 1 2", b"f 1 2 999999", b"3 0 1", b"vt 0.5", b"nan nan nan"]),
)


@FUZZ
@given(which=seed_index, where=st.floats(0, 1), line=garbage_line)
def test_garbage_lines(tmp_path, seeds, which, where, line):
    name, data = seeds[which % len(seeds)]
    breaks = [m.end() for m in re.finditer(rb"\n", data)] or [len(data)]
    at = breaks[min(int(where * len(breaks)), len(breaks) - 1)]
    out = data[:at] + line.replace(b"\n", b" ") + b"\n" + data[at:]
    TRIED["garbage line: " + _check_outcome(_write(tmp_path, name, out), out, name[-4:])] += 1


@FUZZ
@given(
    which=seed_index,
    newline=st.sampled_from([b"\r\n", b"\r", b"\n\r"]),
    bom=st.booleans(),
    every=st.integers(1, 3),
)
def test_line_endings_and_bom(tmp_path, seeds, which, newline, bom, every):
    """Text with other line endings (on every ``every``-th line: mixed endings) and an optional
    UTF-8 byte-order mark reads as the original.  A PLY header keeps one line ending (the
    reader takes the first line's) and a binary body is left alone."""
    name, data = seeds[which % len(seeds)]
    text_end = len(data)
    if name.endswith(".ply"):
        every, newline = 1, newline.strip(b"\n") or b"\r"
        if b"format binary" in data[:300]:
            text_end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:text_end].split(b"\n")
    endings = [newline if i % every == 0 else b"\n" for i in range(len(lines) - 1)]
    text = b"".join(line + end for line, end in zip(lines, endings, strict=False)) + lines[-1]
    out = (b"\xef\xbb\xbf" if bom else b"") + text + data[text_end:]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SkippedContentWarning)
        original = read_mesh(_write(tmp_path, "orig" + name[-4:], data))
        got = read_mesh(_write(tmp_path, name, out))
    TRIED["line endings / BOM"] += 1
    assert torch.equal(got[0], original[0]) and got[1].tolist() == original[1].tolist()


@FUZZ
@given(which=seed_index, ext=st.sampled_from([".obj", ".off", ".ply"]))
def test_wrong_extension(tmp_path, seeds, which, ext):
    name, data = seeds[which % len(seeds)]
    if name.endswith(ext):
        ext = {".obj": ".off", ".off": ".ply", ".ply": ".obj"}[ext]
    path = _write(tmp_path, "renamed" + ext, data)
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*extension is wrong.*rename"):
        read_mesh(path)
    TRIED["wrong extension"] += 1
