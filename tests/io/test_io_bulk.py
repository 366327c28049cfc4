"""The chunked text readers behind read_mesh, against independent references.

* Random OBJ text (vertices, faces with ``v/vt/vn`` corners and negative indices, other
  records, comments, blank lines, broken records) against a few lines of plain Python parsing:
  the same vertices and faces bit for bit, or a ValueError naming the line; and the same
  answer with chunks of a few dozen bytes (every record layout meeting a chunk boundary).
* Random ASCII OFF text (wrapped faces, colours, comments) and ASCII PLY text likewise read
  the same whatever the chunk size.
* Peak memory of a read, and the reader bugs: truncated corners, files cut inside a record,
  float PLY index lists, impossible PLY list lengths, broken ASCII PLY records.
"""

from __future__ import annotations

import re
import struct
import tracemalloc
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_polylap.io import SkippedContentWarning, read_mesh, write_mesh
from torch_polylap.io import text as text_module
from torch_polylap.io.writers import face_pieces

PROPERTY = settings(max_examples=150, deadline=None, database=None)
doubles = st.floats(allow_nan=False, allow_infinity=False, width=64)


@contextmanager
def chunk_bytes(size: int):
    """Cut texts into chunks of about ``size`` bytes."""
    saved = text_module.CHUNK_BYTES
    text_module.CHUNK_BYTES = size
    try:
        yield
    finally:
        text_module.CHUNK_BYTES = saved


def _read(path: Path, size: int):
    """read_mesh's vertices (as flat bits), faces and warnings, or ``("error", message)``."""
    with chunk_bytes(size), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            verts, faces = read_mesh(path)
        except ValueError as e:
            return "error", str(e)
    messages = sorted(str(w.message) for w in caught)
    return verts.numpy().view(np.int64).reshape(-1).tolist(), faces.tolist(), messages


# --------------------------------------------------------------------------------------------
# OBJ against plain Python parsing
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


def obj_reference(text: bytes) -> tuple[list[float], list[list[int]]] | None:
    """Vertices and faces of OBJ text by ``str.split``, ``float`` and ``int``; None when the
    text is broken (a short or unparsable vertex, a bad index, a face of fewer than 3)."""
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    for line in text.decode("latin-1").replace("\r\n", "\n").replace("\r", "\n").split("\n"):
        toks = line.split("#")[0].split()
        try:
            if toks[:1] == ["v"]:
                verts.append([float(t) for t in toks[1:4]])
                if len(verts[-1]) < 3:
                    return None
            elif toks[:1] == ["f"]:
                written = [int(t.split("/")[0]) for t in toks[1:]]
                faces.append([w - 1 if w > 0 else len(verts) + w if w < 0 else -1 for w in written])
        except ValueError:
            return None
    if any(len(f) < 3 or min(f) < 0 or max(f) >= len(verts) for f in faces):
        return None
    return [x for v in verts for x in v], faces


@settings(PROPERTY, suppress_health_check=[HealthCheck.too_slow])
@given(obj_texts(), st.sampled_from([16, 64]))
def test_obj_reads_as_plain_python_parsing_in_any_chunks(tmp_path_factory, text, size):
    path = tmp_path_factory.mktemp("obj") / "m.obj"
    path.write_bytes(text)
    got = _read(path, 1 << 20)
    assert _read(path, size) == got
    want = obj_reference(text)
    if want is None or not want[1]:
        assert got[0] == "error" and re.search(r"m\.obj(, line \d+)?: ", got[1]), got
    else:
        assert got[:2] == (np.array(want[0]).view(np.int64).tolist(), want[1])


# --------------------------------------------------------------------------------------------
# OFF and ASCII PLY across chunk boundaries
# --------------------------------------------------------------------------------------------


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


@settings(PROPERTY, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(off_texts(), uniform_off_texts()), st.sampled_from([16, 64]))
def test_off_reads_the_same_in_any_chunks(tmp_path_factory, case, size):
    """Wrapped faces, colours, comments and broken records: the same mesh or message whatever
    the chunks; a valid file's faces are its records."""
    text, _ = case
    path = tmp_path_factory.mktemp("off") / "m.off"
    path.write_bytes(text)
    got = _read(path, 1 << 20)
    assert _read(path, size) == got
    if got[0] != "error":
        tokens = [t for line in text.decode().split("\n") for t in line.split("#")[0].split()]
        assert len(got[1]) == int(tokens[2 if tokens[0].endswith("OFF") else 1])


def test_ascii_ply_reads_the_same_in_any_chunks(tmp_path):
    """Mixed degrees, extra properties before and after the list, an element after the faces."""
    rng = np.random.default_rng(5)
    verts = rng.normal(size=(40, 3))
    sizes = rng.integers(3, 7, 30)
    head = (
        "ply\nformat ascii 1.0\nelement vertex 40\nproperty double x\nproperty uchar red\n"
        "property double y\nproperty double z\nelement face 30\nproperty int flags\n"
        "property list uchar int vertex_indices\nproperty float weight\nelement edge 1\n"
        "property int a\nend_header\n"
    )
    rows = [f"{x!r} 7 {y!r} {z!r}" for x, y, z in verts.tolist()]
    faces = [rng.integers(0, 40, k).tolist() for k in sizes]
    rows += [f"1 {len(f)} " + " ".join(map(str, f)) + " 0.5" for f in faces]
    path = tmp_path / "m.ply"
    path.write_bytes((head + "\n".join(rows) + "\n\n3\n").encode())
    got = _read(path, 1 << 20)
    assert got[:2] == (verts.view(np.int64).reshape(-1).tolist(), faces)
    for size in (16, 64):
        assert _read(path, size) == got


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
    traced by tracemalloc) stays under 4x its size (2.6-3.3x here: the file, the arrays
    returned, their pieces before they are joined, and a megabyte chunk's work arrays)."""
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
    assert peak <= 4 * size, f"peak {peak / size:.1f}x the file size"


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


def test_skipped_warning_names_records_in_file_order(tmp_path):
    text = "o x\nv 0 0 0 1\nv 1 0 0\nv 0 1 0\nvt 0 0\nfoo 1\ng a\x1b\nf 1 2 3\nbar\nbaz\nqux\n"
    path = tmp_path / "w.obj"
    path.write_bytes(text.encode())
    with pytest.warns(SkippedContentWarning) as caught:
        read_mesh(path)
    message = str(caught[0].message)
    assert re.search(r"unknown keyword \(4: 'foo' at line 6, 'bar' at line 9, 'baz' at", message)
    assert message.index("objects (o)") < message.index("vertex colours") < message.index("(vt)")


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
# the writers
# --------------------------------------------------------------------------------------------


@given(sizes=st.lists(st.integers(3, 7), min_size=1, max_size=20), seed=st.integers(0, 2**32))
def test_written_faces_read_back_through_every_text_format(sizes, seed, tmp_path_factory):
    """Mixed and uniform degrees: OBJ, OFF and ASCII PLY text of the faces is what Python's
    formatting gives, and reads back to the same faces."""
    rng = np.random.default_rng(seed)
    num_verts = int(sum(sizes)) + 1
    indices = rng.integers(0, num_verts, int(sum(sizes)))
    sizes_arr = np.array(sizes, dtype=np.int64)
    rows = np.split(indices, np.cumsum(sizes_arr)[:-1])
    obj = "".join("f " + " ".join(str(i + 1) for i in row) + "\n" for row in rows)
    off = "".join(f"{len(row)} " + " ".join(map(str, row)) + "\n" for row in rows)
    assert b"".join(face_pieces(indices, sizes_arr, prefix="f", base=1)) == obj.encode()
    assert b"".join(face_pieces(indices, sizes_arr)) == off.encode()
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
    same bits: the writers' ``repr`` decimals and the readers agree."""
    verts = np.array(coords[: len(coords) // 3 * 3]).reshape(-1, 3)
    faces = [[0, 1, 2]]
    folder = tmp_path_factory.mktemp("coords")
    for name in ("c.obj", "c.off", "c.ply"):
        write_mesh(folder / name, verts, faces)
        got, _ = read_mesh(folder / name)
        assert got.numpy().view(np.int64).tolist() == verts.view(np.int64).tolist()
