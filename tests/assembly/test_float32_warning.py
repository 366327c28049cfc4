"""float32 operators that say so: a Float32PrecisionWarning when products with L lose accuracy.

On a face of stretch ``r = s^2 / |f|`` (2 for a square) a block's entries grow as ``r`` while
``L_f X`` of smooth data stays of the face's size, so float32 products with ``L`` (``L @ X``
and the gradients of losses through it) lose about ``eps r^2 / 2`` relative: the blocks are
right (thin faces are re-evaluated in float64), their products cancel. The reference here is
float64 on the same float32-rounded coordinates; the warning must fire where the float32
gradient of ``|L X|^2`` is far off and stay silent on well-shaped meshes, real ones included.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from meshes import DATA_DIR, read_mesh, require_shared

import torch_polylap as tp
from torch_polylap.checks import Float32PrecisionWarning

METHODS = ("aw11", "plms", "degoes")
PACKAGE_DATA = Path(tp.__file__).resolve().parent / "data"
EPS32 = torch.finfo(torch.float32).eps
WARNING = (
    r"face (\d+) \(vertices \[[\d, ]+\]\) is so thin \(s\^2 / \|f\| = ([\d.e+]+), 2 for a "
    r"square\) that float32 products with L .* lose about ([\d.]+) of float32's 7 digits "
    r"\(relative error ([\d.e+-]+) on this face\)\.( Evaluating its block in float64 would "
    r"not help: .*)? Use float64 vertices"
)


def _darts(t: float, device: torch.device) -> tuple[torch.Tensor, list[list[int]]]:
    """Two nearly degenerate concave quads of width about ``t`` (darts, faces 0 and 1, face 1
    the thinner) on either side of an edge, a fat quad on top, rotated out of the coordinate
    planes and moved: float64 coordinates of a manifold disc."""
    P = torch.tensor(
        [
            [0, 0, 0],
            [2, t, 0],
            [0, 2 * t, 0],
            [1, 0.4 * t, 0],
            [1, -t, 0],
            [1.2, -0.5 * t, 0],
            [2, 1, 0],
            [0, 1, 0],
        ],
        dtype=torch.float64,
    )
    faces = [[0, 1, 2, 3], [1, 0, 4, 5], [2, 1, 6, 7]]
    rng = np.random.default_rng(3)
    rotation = torch.linalg.qr(torch.from_numpy(rng.standard_normal((3, 3))))[0]
    return (P @ rotation.T + 0.5).to(device), faces


def _stretch(P: torch.Tensor, face: list[int]) -> float:
    """``s^2 / |f|`` of one face, in float64, from its definition (half-diagonals, vector
    area)."""
    Q = P[face].double()
    e = torch.roll(Q, -1, 0) - Q
    g = 0.5 * (e + torch.roll(e, 1, 0))
    area = 0.5 * torch.linalg.cross(Q, torch.roll(Q, -1, 0)).sum(0).norm()
    return float((g * g).sum() / area)


def _gradient_error(P: torch.Tensor, faces: list[list[int]], method: str) -> float:
    """Relative error (2-norm) of the float32 gradient of ``|L X|^2`` against float64, both on
    the same float32 coordinates."""
    grads = []
    for dtype in (torch.float32, torch.float64):
        X = P.float().to(dtype).requires_grad_(True)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Float32PrecisionWarning)
            L = tp.laplacian(X, faces, method=method)[0]
        ((L @ X) ** 2).sum().backward()
        grads.append(X.grad.double())
    return float((grads[0] - grads[1]).norm() / grads[1].norm())


@pytest.mark.parametrize("method", ("aw11", "degoes"))
@pytest.mark.parametrize("t", [1e-4, 1e-5, 1e-6])
def test_thin_concave_quads_warn_where_float32_gradients_fail(t, method, device):
    """The darts' float32 gradients of ``|L X|^2`` are off by 1 to 13 relative on the mesh and
    up to 2e4 on the thinner dart alone: one warning names that dart, with an expected error
    within a factor 30 of the one measured on it alone (on the mesh the fat quad's larger
    gradient dilutes it)."""
    P, faces = _darts(t, device)
    measured = _gradient_error(P, faces, method)
    assert measured > 0.5
    with pytest.warns(Float32PrecisionWarning) as record:
        tp.laplacian(P.float(), faces, method=method)
    assert len(record) == 1
    found = re.search(WARNING, str(record[0].message))
    assert found, str(record[0].message)
    face, stretch, digits, expected = (float(g) for g in found.groups()[:4])
    assert (found.group(5) is not None) == (expected > 1)
    thinnest = max(range(len(faces)), key=lambda f: _stretch(P, faces[f]))
    assert face == thinnest
    assert stretch == pytest.approx(_stretch(P, faces[thinnest]), rel=1e-2)
    assert expected == pytest.approx(EPS32 * stretch**2 / 2, rel=0.35)  # printed to 1 digit
    assert digits == pytest.approx(min(np.log10(expected / EPS32), -np.log10(EPS32)), abs=0.1)
    alone = _gradient_error(P[faces[thinnest]], [[0, 1, 2, 3]], method)
    assert alone / 30 <= expected <= alone * 30


@pytest.mark.parametrize("method", ("aw11", "degoes"))
@pytest.mark.parametrize("t", [1e-1, 1e-2])
def test_fatter_darts_are_silent_and_accurate(t, method, device):
    P, faces = _darts(t, device)
    assert _gradient_error(P, faces, method) <= 1e-2
    with warnings.catch_warnings():
        warnings.simplefilter("error", Float32PrecisionWarning)
        tp.laplacian(P.float(), faces, method=method)


@pytest.mark.parametrize("method", METHODS)
def test_no_warning_in_float64(method, device):
    P, faces = _darts(1e-6, device)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tp.laplacian(P, faces, method=method)


def test_validate_false_skips_the_check(device):
    P, faces = _darts(1e-5, device)
    with warnings.catch_warnings():
        warnings.simplefilter("error", Float32PrecisionWarning)
        tp.laplacian(P.float(), faces, validate=False)


def test_the_planarity_operator_does_not_warn(device):
    """Its blocks (``lam d^T Pi d``) do not divide by the area."""
    P, faces = _darts(1e-4, device)
    with warnings.catch_warnings():
        warnings.simplefilter("error", Float32PrecisionWarning)
        tp.planarity_laplacian(P.float(), faces)


def test_batch_module_and_packed_meshes_warn_once(device):
    """Every eager form: one warning per call; the batch names the mesh."""
    P, faces = _darts(1e-5, device)
    fat, _ = _darts(1e-1, device)
    with pytest.warns(Float32PrecisionWarning, match=r"mesh 1 of the batch: face 1 ") as record:
        tp.laplacian(torch.stack([fat, P]).float(), faces)
    assert len(record) == 1
    with pytest.warns(Float32PrecisionWarning, match="face 1 ") as record:
        tp.PolygonLaplacian()(P.float(), faces)
    assert len(record) == 1
    meshes = tp.PolygonMeshes([fat.float(), P.float()], [faces, faces])
    with pytest.warns(Float32PrecisionWarning, match="face 4 ") as record:
        meshes.laplacian()
    assert len(record) == 1


def test_compiled_laplacian_warns_outside_the_graph(device):
    """The compiled assembly returns the stretch as a flag; the warning is raised eagerly."""
    P, faces = _darts(1e-4, device)  # blocks right in float32: no eager fallback
    lap = tp.CompiledLaplacian(faces, options={"backend": "aot_eager", "dynamic": False})
    with pytest.warns(Float32PrecisionWarning, match="face 1 ") as record:
        L, _ = lap(P.float())
    assert len(record) == 1
    with pytest.warns(Float32PrecisionWarning, match="face 1 "):
        L_eager = tp.laplacian(P.float(), faces)[0]
    torch.testing.assert_close(L.to_dense(), L_eager.to_dense())


def test_torch_func_skips_the_check(device):
    """Under torch.func transforms no Python branch reads traced values: no warning."""
    P, faces = _darts(1e-4, device)
    topo = tp.build_topology(faces, P.shape[0])

    def energy(X: torch.Tensor) -> torch.Tensor:
        L = tp.laplacian(X, topo)[0]
        return ((L @ X) ** 2).sum()

    with warnings.catch_warnings():
        warnings.simplefilter("error", Float32PrecisionWarning)
        grad = torch.func.grad(energy)(P.float())
    assert torch.isfinite(grad).all()


def _assert_silent(path: Path, device: torch.device) -> None:
    V, F = read_mesh(path, dtype=torch.float32)
    for method in METHODS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # topology reports of the files: not this test's
            warnings.simplefilter("error", Float32PrecisionWarning)
            tp.laplacian(V.to(device), F, method=method)


@pytest.mark.parametrize(
    "path",
    sorted(DATA_DIR.glob("*.*")) + sorted(PACKAGE_DATA.glob("*.obj")),
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_embedded_meshes_are_silent_in_float32(path, device):
    if path.suffix not in (".obj", ".off", ".ply"):
        pytest.skip("not a mesh")
    _assert_silent(path, device)


@pytest.mark.slow
def test_shared_real_meshes_are_silent_in_float32(device):
    """Their thinnest face (loki's) has ``s^2 / |f|`` about 264: an expected 4e-3."""
    for path in sorted((require_shared() / "real").iterdir()):
        if path.suffix in (".obj", ".off", ".ply"):
            _assert_silent(path, device)
