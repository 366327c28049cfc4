"""Tests for torch_polylap.io: polygon-preserving OBJ/OFF/PLY reading and writing."""

from __future__ import annotations

import bz2
import gzip
import io
import os
import re
import struct
import warnings
import zipfile

import numpy as np
import pytest
import torch
import trimesh
from conftest import DATA

from torch_polylap import atomic
from torch_polylap.faces import PolygonFaces
from torch_polylap.interop import from_trimesh, to_trimesh
from torch_polylap.io import (
    MeshAttributes,
    SkippedContentWarning,
    read_mesh,
    write_mesh,
)

# A triangle, a quad, a pentagon and a hexagon, each sharing vertices with the next.
MIXED_FACES = [[0, 1, 2], [1, 3, 4, 2], [3, 5, 6, 7, 4], [5, 8, 9, 10, 11, 6]]


@pytest.fixture
def mixed_verts() -> torch.Tensor:
    # Random doubles need all 17 significant digits: a lossy writer would show up.
    return torch.from_numpy(np.random.default_rng(0).normal(size=(12, 3)))


def write_text(path, text: str, newline: str = "\n"):
    path.write_bytes(text.replace("\n", newline).encode("ascii"))
    return path


# --------------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "binary"),
    [("mesh.obj", False), ("mesh.off", False), ("mesh.ply", False), ("mesh.ply", True)],
)
def test_round_trip_is_exact(tmp_path, mixed_verts, name, binary):
    path = tmp_path / name
    write_mesh(path, mixed_verts, MIXED_FACES, binary=binary)
    verts, faces = read_mesh(path)
    assert verts.dtype == torch.float64
    assert torch.equal(verts, mixed_verts)
    assert isinstance(faces, PolygonFaces)
    assert faces.tolist() == MIXED_FACES
    assert faces.indices.dtype == torch.int64


def test_binary_ply_is_binary_and_upper_case_extension_works(tmp_path, mixed_verts):
    path = tmp_path / "MESH.PLY"
    write_mesh(path, mixed_verts.numpy(), PolygonFaces([0, 1, 2, 3], sizes=[4]), binary=True)
    assert b"format binary_little_endian 1.0" in path.read_bytes()[:100]
    verts, faces = read_mesh(path)
    assert torch.equal(verts, mixed_verts)
    assert faces.tolist() == [[0, 1, 2, 3]]


@pytest.mark.parametrize("name", ["big.ply", "big.obj", "big.off"])
def test_face_with_more_than_255_corners_round_trips(tmp_path, name):
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    verts = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
    faces = [list(range(300)), [0, 1, 299]]
    write_mesh(tmp_path / name, verts, faces, binary=name.endswith(".ply"))
    if name.endswith(".ply"):
        assert b"property list int int vertex_indices" in (tmp_path / name).read_bytes()[:400]
    v, f = read_mesh(tmp_path / name)
    assert np.array_equal(v.numpy(), verts)
    assert f.tolist() == faces


def test_write_accepts_float32_tensor_and_uniform_face_array(tmp_path):
    verts = torch.rand(4, 3, dtype=torch.float32, requires_grad=True)
    write_mesh(tmp_path / "q.off", verts, torch.tensor([[0, 1, 2, 3]]))
    v, f = read_mesh(tmp_path / "q.off", dtype=torch.float32)
    assert torch.equal(v, verts.detach())
    assert f.tolist() == [[0, 1, 2, 3]]


def test_read_dtype_and_device(tmp_path, mixed_verts):
    write_mesh(tmp_path / "m.obj", mixed_verts, MIXED_FACES)
    verts, faces = read_mesh(tmp_path / "m.obj", dtype=torch.float32, device="cpu")
    assert verts.dtype == torch.float32
    assert verts.device.type == "cpu"
    assert torch.equal(verts, mixed_verts.float())
    assert faces.device.type == "cpu"


def test_read_to_every_device_and_dtype_keeps_faces_on_cpu(tmp_path, mixed_verts, device, dtype):
    write_mesh(tmp_path / "m.obj", mixed_verts, MIXED_FACES)
    verts, faces = read_mesh(tmp_path / "m.obj", dtype=dtype, device=device)
    assert verts.device.type == device.type and verts.dtype == dtype
    assert torch.equal(verts.cpu(), mixed_verts.to(dtype))  # the written digits round-trip
    assert faces.device.type == "cpu" and faces.tolist() == MIXED_FACES


# --------------------------------------------------------------------------------------------
# OBJ dialects
# --------------------------------------------------------------------------------------------

OBJ_TEXT = """# exported by hand
mtllib scene.mtl
o thing
v 0 0 0
v 1 0 0 1.0
v 1 1 0 0.5 0.25 0.125
v 0 1 0
v 2 0 0   \t
vt 0 0
vt 1 0
vn 0 0 1
g part
usemtl red
s 1
f 1/1/1 2/2/1 3/1/1 4/2/1
f 2//1 5//1 3//1   # a comment after data
s off
f 2/1 5/2 3/1
f -1 -4 -3
v 3 3 3
l 1 2
f -1 -2 \\
  -4
"""

OBJ_FACES = [[0, 1, 2, 3], [1, 4, 2], [1, 4, 2], [4, 1, 2], [5, 4, 2]]


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_obj_dialects(tmp_path, newline):
    path = write_text(tmp_path / "d.obj", OBJ_TEXT, newline)
    with pytest.warns(SkippedContentWarning, match=r"skipped material libraries \(mtllib\)"):
        verts, faces = read_mesh(path)
    expected = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [3, 3, 3]]
    assert verts.tolist() == expected
    assert faces.tolist() == OBJ_FACES


def test_obj_comment_ending_in_backslash_continues_nothing(tmp_path):
    path = write_text(tmp_path / "c.obj", "# C:\\dir\\\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    verts, faces = read_mesh(path)
    assert verts.shape == (3, 3)
    assert faces.tolist() == [[0, 1, 2]]


def test_non_finite_coordinates_are_read(tmp_path):
    path = write_text(tmp_path / "n.obj", "v nan inf -inf\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.warns(UserWarning, match=r"vertex 0: 1 vertices have non-finite coordinates"):
        verts, _ = read_mesh(path)
    assert torch.isnan(verts[0, 0])
    assert verts[0, 1] == float("inf")
    assert verts[0, 2] == float("-inf")


# --------------------------------------------------------------------------------------------
# OFF dialects
# --------------------------------------------------------------------------------------------

OFF_BODY = """# comment between header and data
0 0 0
1 0 0 255 0 0 255
1 1 0
0 1 0    # trailing comment

2 0 0
2 1 0
4 0 1 2 3 255 0 0 1
4 1 4
  5
  2 0.5 0.5 0.5 1
3 0 2 3
"""
OFF_FACES = [[0, 1, 2, 3], [1, 4, 5, 2], [0, 2, 3]]


@pytest.mark.parametrize(
    "header", ["OFF 6 3 12\n", "OFF\n6 3 0\n", "# lead\nCOFF\n\n6 3\n", "NOFF 6 3 0\n", "6 3 0\n"]
)
def test_off_dialects(tmp_path, header):
    path = write_text(tmp_path / "d.off", header + OFF_BODY)
    with pytest.warns(SkippedContentWarning, match="face colours"):
        verts, faces = read_mesh(path)
    assert verts.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [2, 1, 0]]
    assert faces.tolist() == OFF_FACES


def _binary_off(order: str, with_colours: bool) -> bytes:
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], dtype=np.float32)
    body = struct.pack(order + "3i", 5, 2, 0) + verts.astype(order + "f4").tobytes()
    for face in ([0, 1, 2, 3], [1, 4, 2]):
        body += struct.pack(f"{order}{len(face) + 1}i", len(face), *face)
        if with_colours:
            body += struct.pack(order + "i3f", 3, 1.0, 0.0, 0.0)
    return b"OFF BINARY\n" + body


@pytest.mark.parametrize(("order", "with_colours"), [("<", False), (">", True), (">", False)])
def test_binary_off(tmp_path, order, with_colours):
    path = tmp_path / "b.off"
    path.write_bytes(_binary_off(order, with_colours))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        verts, faces = read_mesh(path)
    # the face colours are reported as skipped, and nothing else is
    assert [str(w.message).endswith("face colours (2).") for w in caught] == [True] * with_colours
    assert verts.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]]
    assert faces.tolist() == [[0, 1, 2, 3], [1, 4, 2]]


# --------------------------------------------------------------------------------------------
# PLY written by hand: extra vertex and face properties, extra elements
# --------------------------------------------------------------------------------------------

PLY_VERTS = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.25], [1.0, 1.0, 0.5], [0.0, 1.0, 0.75], [2.0, 0.5, -1.0]]
PLY_MIXED = [[0, 1, 2, 3], [1, 4, 2], [0, 1, 4, 2, 3]]
PLY_QUADS = [[0, 1, 2, 3], [1, 4, 2, 0]]


def _hand_ply(fmt: str, faces: list[list[int]], vertex_list: bool) -> bytes:
    """A PLY with a material element first, vertices with normals, colours (and optionally a
    list property), faces with an int before and a uchar after the index list, then edges."""
    header = [
        "ply",
        f"format {fmt} 1.0",
        "comment made by hand",
        "obj_info nothing to see",
        "element material 2",
        "property uchar ambient",
        "property float shininess",
        f"element vertex {len(PLY_VERTS)}",
        "property float x",
        "property float y",
        "property float z",
        "property float nx",
        "property float ny",
        "property float nz",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
    ]
    if vertex_list:
        header.append("property list uchar float texcoord")
    header += [
        f"element face {len(faces)}",
        "property int material_index",
        "property list uchar int vertex_indices",
        "property uchar flags",
        "element edge 1",
        "property int vertex1",
        "property int vertex2",
        "end_header",
    ]
    head = ("\n".join(header) + "\n").encode("ascii")
    if fmt == "ascii":
        lines = ["7 0.5", "8 1.5"]
        for i, v in enumerate(PLY_VERTS):
            row = f"{v[0]} {v[1]} {v[2]} 0 0 1 {i} 20 30"
            lines.append(row + (f" {i % 3} " + " ".join(["0.5"] * (i % 3)) if vertex_list else ""))
        lines += [f"{i} {len(f)} {' '.join(map(str, f))} 9" for i, f in enumerate(faces)]
        lines.append("0 1")
        return head + ("\n".join(lines) + "\n").encode("ascii")
    o = "<" if fmt == "binary_little_endian" else ">"
    body = struct.pack(o + "Bf", 7, 0.5) + struct.pack(o + "Bf", 8, 1.5)
    for i, v in enumerate(PLY_VERTS):
        body += struct.pack(o + "6f3B", *v, 0.0, 0.0, 1.0, i, 20, 30)
        if vertex_list:
            body += struct.pack(f"{o}B{i % 3}f", i % 3, *([0.5] * (i % 3)))
    for i, f in enumerate(faces):
        body += struct.pack(f"{o}iB{len(f)}iB", i, len(f), *f, 9)
    return head + body + struct.pack(o + "2i", 0, 1)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("faces", [PLY_MIXED, PLY_QUADS], ids=["mixed", "quads"])
@pytest.mark.parametrize("vertex_list", [False, True], ids=["", "vertex-list"])
def test_ply_with_extra_properties(tmp_path, fmt, faces, vertex_list):
    path = tmp_path / "hand.ply"
    path.write_bytes(_hand_ply(fmt, faces, vertex_list))
    with pytest.warns(SkippedContentWarning, match="skipped PLY element 'material'"):
        verts, got = read_mesh(path)
    assert verts.tolist() == PLY_VERTS
    assert got.tolist() == faces


def test_ply_vertex_index_name_and_other_types(tmp_path):
    """'vertex_index' with ushort counts and uint indices, double coordinates."""
    head = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\n"
        "property double y\nproperty double z\nelement face 1\n"
        "property list ushort uint vertex_index\nend_header\n"
    ).encode("ascii")
    body = struct.pack(">9d", 0.1, 0.2, 0.3, 1, 0, 0, 0, 1, 0) + struct.pack(">H3I", 3, 2, 1, 0)
    (tmp_path / "t.ply").write_bytes(head + body)
    verts, faces = read_mesh(tmp_path / "t.ply")
    assert verts[0].tolist() == [0.1, 0.2, 0.3]
    assert faces.tolist() == [[2, 1, 0]]


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------

TRIANGLE_V = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(
    ("name", "text", "line"),
    [
        ("e.obj", TRIANGLE_V + "f 1 2 3\nf 1 2\n", 5),
        ("e.off", "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n2 0 1\n", 7),
    ],
)
def test_face_with_two_vertices(tmp_path, name, text, line):
    path = write_text(tmp_path / name, text)
    with pytest.raises(ValueError, match=rf"line {line}: face 1 has 2 vertices; a polygon needs"):
        read_mesh(path)


_OFF_HEAD = "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n"  # three vertices, one face declared


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        (
            "m.obj",
            TRIANGLE_V + "f 1 2 3\n\nf 1 2 9\n",
            r"m\.obj, line 6: face 1 refers to vertex 9, out of range",
        ),
        ("m.obj", TRIANGLE_V + "f -1 -2 -4\n", r"line 4: face 0 refers to vertex -4"),
        ("m.obj", TRIANGLE_V + "f 0 1 2\n", r"line 4: face 0 refers to vertex 0.*start at 1"),
        (
            "m.obj",
            "v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n",
            r"line 2: cannot parse vertex coordinate 'zero'",
        ),
        (
            "m.obj",
            TRIANGLE_V + "f 1 2 3\nf 1 2.0 3\n",
            r"line 5: face 1 has an unparsable vertex index '2.0'",
        ),
        ("m.obj", "v 0 0 0\nv 1 0\n", r"line 2: a vertex needs 3 coordinates"),
        (
            "m.off",
            "OFF\n4 1 0\n0 0 0\n1 0 0\n0 1 0\n",
            r"m\.off: the file ends after 3 of the 4 vertices",
        ),
        (
            "m.off",
            "OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
            r"ends after 1 of the 2 faces.*truncated",
        ),
        ("m.off", _OFF_HEAD + "4 0 1\n2\n", r"ends after 0 of the 1 faces"),
        ("m.off", _OFF_HEAD + "3 0 1 2\n3 2 1 0\n", r"line 7: data after the 1 faces declared"),
        ("m.off", _OFF_HEAD + "3 0 1 7\n", r"line 6: face 0 refers to vertex 7"),
        (
            "m.off",
            "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1e 0\n3 0 1 2\n",
            r"line 5: cannot parse vertex coordinate '1e'",
        ),
        ("m.off", "OFF\nthree 1 0\n", r"line 2: expected the counts"),
    ],
    ids=[
        "obj-index-range",
        "obj-negative-index-range",
        "obj-index-zero",
        "obj-bad-coordinate",
        "obj-bad-index",
        "obj-two-coordinates",
        "off-verts-missing",
        "off-faces-missing",
        "off-face-cut",
        "off-extra-face",
        "off-index-range",
        "off-bad-number",
        "off-bad-counts",
    ],
)
def test_malformed_text_mesh_is_refused_with_file_and_line(tmp_path, name, text, match):
    """Truncated files, extra faces and bad entries are errors naming the file or line, never
    silently dropped or padded."""
    path = write_text(tmp_path / name, text)
    with pytest.raises(ValueError, match=match):
        read_mesh(path)


def test_binary_off_truncated(tmp_path):
    path = tmp_path / "b.off"
    path.write_bytes(_binary_off("<", False)[:-4])
    with pytest.raises(ValueError, match=r"do not match the 2 faces declared"):
        read_mesh(path)


@pytest.mark.parametrize(
    "writer", [read_mesh, lambda p: write_mesh(p, np.zeros((3, 3)), [[0, 1, 2]])]
)
def test_unknown_extension(tmp_path, writer):
    with pytest.raises(ValueError, match=r"unsupported mesh file extension '\.stl'.*\.obj, \.off"):
        writer(tmp_path / "m.stl")


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_mesh(tmp_path / "nope.obj")


def test_write_rejects_binary_text_format_and_bad_index(tmp_path):
    with pytest.raises(ValueError, match=r"binary=True is only supported for \.ply"):
        write_mesh(tmp_path / "m.obj", np.zeros((3, 3)), [[0, 1, 2]], binary=True)
    with pytest.raises(ValueError, match=r"face 1 refers to vertex 3, out of range for 3"):
        write_mesh(tmp_path / "m.obj", np.zeros((3, 3)), [[0, 1, 2], [2, 1, 3]])
    with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
        write_mesh(tmp_path / "m.obj", np.zeros((3, 2)), [[0, 1, 2]])


PLY_ASCII_HEAD = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"


def test_ply_without_vertex_indices(tmp_path):
    text = (
        PLY_ASCII_HEAD + "property float z\nelement face 1\nproperty list uchar int vertex_list\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
    )
    with pytest.raises(ValueError, match=r"no list property 'vertex_indices'.*\['vertex_list'\]"):
        read_mesh(write_text(tmp_path / "p.ply", text))
    no_face = PLY_ASCII_HEAD + "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    with pytest.raises(ValueError, match=r"declares no 'face' element"):
        read_mesh(write_text(tmp_path / "q.ply", no_face))


_PLY_TWO_FACES = PLY_ASCII_HEAD + (
    "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
)


@pytest.mark.parametrize(
    ("body", "match"),
    [
        (
            "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 10\n",
            r"element 'face' record 1: face 1 refers to vertex 10",
        ),
        ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n2 0 1\n", r"record 1: face 1 has 2 vertices"),
        ("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", r"element 'face' declares 2 records but the file ends"),
        (
            "0 0 0\n1 oops 0\n0 1 0\n3 0 1 2\n3 2 1 0\n",
            r"line 11: element 'vertex' record 1: cannot parse 'y'",
        ),
    ],
    ids=["index-range", "two-vertices", "truncated", "bad-number"],
)
def test_ply_errors_name_element_and_record(tmp_path, body, match):
    path = write_text(tmp_path / "r.ply", _PLY_TWO_FACES + body)
    with pytest.raises(ValueError, match=match):
        read_mesh(path)


@pytest.mark.parametrize("faces", [PLY_MIXED, PLY_QUADS], ids=["mixed", "quads"])
def test_binary_ply_truncated(tmp_path, faces):
    data = _hand_ply("binary_little_endian", faces, vertex_list=False)
    path = tmp_path / "cut.ply"
    path.write_bytes(data[: -(8 + 6)])  # the edge element and part of the last face
    with pytest.raises(ValueError, match=r"element 'face'.*truncated file"):
        read_mesh(path)
    path.write_bytes(data[: data.index(b"end_header") + 11 + 5 + 5 + 10])
    with pytest.raises(ValueError, match=r"element 'vertex' declares 5 records.*ends after 0"):
        read_mesh(path)


# --------------------------------------------------------------------------------------------
# trimesh interop
# --------------------------------------------------------------------------------------------


def test_from_trimesh_box():
    box = trimesh.creation.box()
    verts, faces = from_trimesh(box)
    assert verts.dtype == torch.float64
    assert np.array_equal(verts.numpy(), np.asarray(box.vertices))
    assert faces.tolist() == np.asarray(box.faces).tolist()
    verts32, _ = from_trimesh(box, dtype=torch.float32)
    assert verts32.dtype == torch.float32


def test_from_trimesh_rejects_scene():
    with pytest.raises(TypeError, match="Scene"):
        from_trimesh(trimesh.Scene([trimesh.creation.box()]))


def test_to_trimesh_quads_area_matches_fan_triangulation():
    rng = np.random.default_rng(1)
    n = 4
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    verts = np.stack([ii, jj, 0.3 * rng.random(ii.shape)], axis=-1).reshape(-1, 3).astype(float)
    quads = [
        [i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1]
        for i in range(n)
        for j in range(n)
    ]
    mesh = to_trimesh(torch.from_numpy(verts), quads)
    assert mesh.faces.shape == (2 * len(quads), 3)
    assert np.array_equal(mesh.vertices, verts)

    q = verts[np.array(quads)]
    a, b, c, d = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    area = 0.5 * (
        np.linalg.norm(np.cross(b - a, c - a), axis=1)
        + np.linalg.norm(np.cross(c - a, d - a), axis=1)
    )
    assert mesh.area == pytest.approx(area.sum(), rel=1e-12)


def test_to_trimesh_fans_convex_faces_from_first_corner():
    # a convex (regular) polygon of each degree, in the plane z = 0
    verts, faces = [], []
    for k in (3, 4, 5, 6):
        t = np.linspace(0, 2 * np.pi, k, endpoint=False)
        faces.append(list(range(len(verts), len(verts) + k)))
        verts += np.stack([np.cos(t) + 3 * k, np.sin(t), 0 * t], axis=1).tolist()
    mesh = to_trimesh(np.array(verts), faces)
    fans = [[f[0], f[j], f[j + 1]] for f in faces for j in range(1, len(f) - 1)]
    assert mesh.faces.tolist() == fans


def _two_list_ply(fmt: str) -> bytes:
    """Faces carrying a second list (per-corner texture coordinates) after vertex_indices."""
    faces = [[0, 1, 2, 3], [1, 4, 2]]
    head = (
        f"ply\nformat {fmt} 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
        "property list int float texcoord\nend_header\n"
    ).encode("ascii")
    verts = np.array(PLY_VERTS, dtype=np.float32)
    if fmt == "ascii":
        rows = [" ".join(map(str, v)) for v in PLY_VERTS]
        for f in faces:
            rows.append(f"{len(f)} {' '.join(map(str, f))} {2 * len(f)} " + "0.5 " * 2 * len(f))
        return head + ("\n".join(rows) + "\n").encode("ascii")
    o = "<" if fmt == "binary_little_endian" else ">"
    body = verts.astype(o + "f4").tobytes()
    for f in faces:
        body += struct.pack(f"{o}B{len(f)}i", len(f), *f)
        body += struct.pack(f"{o}i{2 * len(f)}f", 2 * len(f), *([0.5] * 2 * len(f)))
    return head + body


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_face_with_two_lists(tmp_path, fmt):
    path = tmp_path / "two.ply"
    path.write_bytes(_two_list_ply(fmt))
    with pytest.warns(SkippedContentWarning, match="texcoord"):
        verts, faces = read_mesh(path)
    assert verts.tolist() == PLY_VERTS
    assert faces.tolist() == [[0, 1, 2, 3], [1, 4, 2]]


def test_ply_ascii_record_with_wrong_number_of_values(tmp_path):
    head = PLY_ASCII_HEAD + (
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
        "property uchar flags\nend_header\n"
    )
    path = write_text(tmp_path / "w.ply", head + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2 0\n3 0 1 2 0 7\n")
    with pytest.raises(ValueError, match=r"line 15: element 'face' record 1 has 6 values, but its"):
        read_mesh(path)


# --------------------------------------------------------------------------------------------
# files as people download them: wrong content, encodings, line endings, absurd headers
# --------------------------------------------------------------------------------------------

DODECAHEDRON = DATA / "dodecahedron_poly.obj"


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("m.obj", lambda d: gzip.compress(d), r"gzip-compressed data.*decompress it first"),
        ("m.obj", lambda d: bz2.compress(d), r"bzip2-compressed data.*decompress it first"),
        ("m.off", lambda d: _zipped(d), r"a zip archive.*extract the mesh file"),
        ("m.obj", lambda d: d.decode().encode("utf-16"), r"UTF-16.*re-save it as UTF-8"),
        ("m.obj", lambda d: d.decode().encode("utf-16-le"), r"UTF-16.*re-save it as UTF-8"),
        ("m.obj", lambda d: b"<!DOCTYPE html><html>Not found</html>", r"HTML page"),
        (
            "m.obj",
            lambda d: b"ply\nformat ascii 1.0\n",
            r"looks like a PLY file.*rename it to m\.ply",
        ),
        ("m.ply", lambda d: d, r"looks like an OBJ file.*rename it to m\.obj"),
        ("m.obj", lambda d: b"OFF\n3 1 0\n", r"looks like an OFF file.*rename it to m\.off"),
        ("m.obj", lambda d: b"", r"the file is empty"),
        ("m.obj", lambda d: b"v 0 0 0\n" + bytes(range(256)), r"line 2: binary data"),
        ("m.obj", lambda d: b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"3 vertices but no faces"),
        ("m.off", lambda d: b"OFF\n3 0 0\n0 0 0\n1 0 0\n0 1 0\n", r"3 vertices but no faces"),
        ("m.off", lambda d: b"OFF\n1000000000000 1 0\n0 0 0\n", r"line 2 declares 1000000000000"),
        ("m.ply", lambda d: _ply_declaring(10**12), r"declares 1000000000000 records of element"),
    ],
)
def test_what_is_not_a_mesh_is_named(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content(DODECAHEDRON.read_bytes()))
    with pytest.raises(ValueError, match=re.escape(str(path)) + r".*" + message):
        read_mesh(path)


def _zipped(data: bytes) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("mesh.off", data)
    return buffer.getvalue()


def _ply_declaring(num_verts: int) -> bytes:
    return (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {num_verts}\nproperty float x\n"
        "property float y\nproperty float z\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    ).encode() + bytes(40)


def test_directory_device_and_fifo_are_refused_without_hanging(tmp_path):
    (tmp_path / "folder.obj").mkdir()
    with pytest.raises(ValueError, match=r"folder\.obj: is a directory"):
        read_mesh(tmp_path / "folder.obj")
    os.symlink("/dev/zero", tmp_path / "zero.obj")
    with pytest.raises(ValueError, match=r"zero\.obj: is not a regular file"):
        read_mesh(tmp_path / "zero.obj")
    if hasattr(os, "mkfifo"):
        os.mkfifo(tmp_path / "pipe.ply")  # opening it for reading would block forever
        with pytest.raises(ValueError, match=r"pipe\.ply: is not a regular file"):
            read_mesh(tmp_path / "pipe.ply")


@pytest.mark.parametrize("newline", [b"\r\n", b"\r"])
@pytest.mark.parametrize("bom", [b"", b"\xef\xbb\xbf"])
@pytest.mark.parametrize(
    ("name", "binary"), [("m.obj", 0), ("m.off", 0), ("m.ply", 0), ("m.ply", 1)]
)
def test_line_endings_and_byte_order_mark(tmp_path, mixed_verts, newline, bom, name, binary):
    path = tmp_path / name
    write_mesh(path, mixed_verts, MIXED_FACES, binary=bool(binary))
    data = path.read_bytes()
    if binary:  # only the header is text
        end = data.index(b"end_header\n") + len(b"end_header\n")
        data = data[:end].replace(b"\n", newline) + data[end:]
    else:
        data = data.replace(b"\n", newline)
    path.write_bytes(bom + data)
    verts, faces = read_mesh(path)
    assert torch.equal(verts, mixed_verts)
    assert faces.tolist() == MIXED_FACES


def test_line_numbers_count_lone_carriage_returns(tmp_path):
    path = tmp_path / "cr.obj"
    path.write_bytes(b"v 0 0 0\rv 1 0 0\rv 0 1 0\rf 1 2 3\rf 1 2 7\r")
    with pytest.raises(ValueError, match=r"cr\.obj, line 5: face 1 refers to vertex 7"):
        read_mesh(path)


def test_integer_dtype_is_refused(tmp_path, mixed_verts):
    write_mesh(tmp_path / "m.obj", mixed_verts, MIXED_FACES)
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype.*torch\.int64"):
        read_mesh(tmp_path / "m.obj", dtype=torch.int64)


# --------------------------------------------------------------------------------------------
# one warning naming what was skipped; texture coordinates and normals on request
# --------------------------------------------------------------------------------------------


def test_skipped_obj_content_is_named_in_one_warning(tmp_path):
    path = write_text(tmp_path / "d.obj", OBJ_TEXT)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_mesh(path)
    assert len(caught) == 1 and issubclass(caught[0].category, SkippedContentWarning)
    message = str(caught[0].message)
    assert message.startswith(str(path))
    for what in ("texture coordinates (vt) (2)", "normals (vn) (1)", "groups (g) (1)"):
        assert what in message
    for what in ("objects (o)", "materials (usemtl)", "polylines (l)", "return_attributes=True"):
        assert what in message


def test_nothing_skipped_means_no_warning(tmp_path, mixed_verts):
    for name in ("m.obj", "m.off", "m.ply"):
        write_mesh(tmp_path / name, mixed_verts, MIXED_FACES)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            read_mesh(tmp_path / name)


def test_skipped_off_and_ply_content_is_named(tmp_path):
    path = write_text(tmp_path / "d.off", "COFF\n6 3 0\n" + OFF_BODY.replace("COFF", ""))
    with pytest.warns(SkippedContentWarning, match=r"vertex colours \(1\), face colours \(2\)"):
        read_mesh(path)
    path = tmp_path / "hand.ply"
    path.write_bytes(_hand_ply("ascii", PLY_QUADS, vertex_list=False))
    with pytest.warns(SkippedContentWarning, match=r"element 'material'.*nx ny nz red.*'edge'"):
        read_mesh(path)


def test_obj_attributes_round_trip_exactly(tmp_path):
    path = write_text(tmp_path / "d.obj", OBJ_TEXT)
    # the attributes come back; what they cannot hold (materials, objects, ...) is reported
    with pytest.warns(SkippedContentWarning, match="mtllib"):
        verts, faces, attrs = read_mesh(path, return_attributes=True)
    assert faces.tolist() == OBJ_FACES
    assert attrs.uv.tolist() == [[0, 0], [1, 0]]
    assert attrs.normals.tolist() == [[0, 0, 1]]
    # f 1/1/1 2/2/1 3/1/1 4/2/1, f 2//1 5//1 3//1, f 2/1 5/2 3/1, then two faces without
    assert attrs.corner_uv.tolist() == [0, 1, 0, 1, -1, -1, -1, 0, 1, 0] + [-1] * 6
    assert attrs.corner_normals.tolist() == [0] * 7 + [-1] * 9
    rng = np.random.default_rng(3)
    attrs.uv = torch.from_numpy(rng.random((2, 2)))
    attrs.normals = torch.from_numpy(rng.normal(size=(1, 3)))
    write_mesh(tmp_path / "out.obj", verts, faces, attributes=attrs)
    again_verts, again_faces, again = read_mesh(tmp_path / "out.obj", return_attributes=True)
    assert torch.equal(again_verts, verts) and again_faces.tolist() == faces.tolist()
    for key in ("uv", "normals", "corner_uv", "corner_normals"):
        assert torch.equal(getattr(again, key), getattr(attrs, key)), key


def test_attributes_default_return_is_unchanged_and_off_has_none(tmp_path, mixed_verts):
    write_mesh(tmp_path / "m.off", mixed_verts, MIXED_FACES)
    assert len(read_mesh(tmp_path / "m.off")) == 2
    _, _, attrs = read_mesh(tmp_path / "m.off", return_attributes=True)
    assert attrs == MeshAttributes()


def test_ply_per_vertex_normals_as_attributes(tmp_path):
    path = tmp_path / "hand.ply"
    path.write_bytes(_hand_ply("binary_big_endian", PLY_MIXED, vertex_list=False))
    with pytest.warns(SkippedContentWarning, match="material"):
        _, faces, attrs = read_mesh(path, return_attributes=True)
    assert attrs.normals.tolist() == [[0.0, 0.0, 1.0]] * 5
    assert torch.equal(attrs.corner_normals, faces.indices) and attrs.uv is None


def test_write_attributes_checks(tmp_path, mixed_verts):
    attrs = MeshAttributes(uv=torch.zeros(2, 2), corner_uv=torch.zeros(3, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"corner_uv has 3 entries, but the faces have 18"):
        write_mesh(tmp_path / "m.obj", mixed_verts, MIXED_FACES, attributes=attrs)
    attrs.corner_uv = torch.full((18,), 2)
    with pytest.raises(ValueError, match=r"face 0 refers to uv row 2, out of range for 2"):
        write_mesh(tmp_path / "m.obj", mixed_verts, MIXED_FACES, attributes=attrs)
    with pytest.raises(ValueError, match=r"only be written to \.obj"):
        write_mesh(tmp_path / "m.ply", mixed_verts, MIXED_FACES, attributes=attrs)


# --------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------


def test_failed_write_leaves_old_file_and_no_temporary(tmp_path, mixed_verts, monkeypatch):
    path = tmp_path / "m.ply"
    write_mesh(path, mixed_verts, MIXED_FACES)
    old = path.read_bytes()

    def broken_fsync(fd):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        write_mesh(path, mixed_verts * 2, MIXED_FACES, binary=True)
    assert path.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


def test_write_keeps_permissions(tmp_path, mixed_verts):
    path = tmp_path / "m.obj"
    write_mesh(path, mixed_verts, MIXED_FACES)
    umask = os.umask(0o022)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0o600
    path.chmod(0o640)
    write_mesh(path, mixed_verts, MIXED_FACES)
    assert path.stat().st_mode & 0o777 == 0o640
