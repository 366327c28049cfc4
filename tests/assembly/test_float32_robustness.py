"""float32 assembly: finite and right at every scale or refused, accurate gradients or float64.

Two ways float32 used to fail silently:

* scale: ``s^2`` of a face under- or overflows float32 outside about ``1e-19 .. 1e19``, and
  ``L`` came out NaN (Spot at scale ``1e-18``: 122 of 1,720 entries) or the masses wrong. The
  assembly now normalizes the coordinates by a power of two (``L`` is scale invariant), so
  ``L`` is right at every finite scale, and masses that float32 cannot represent (``M0``
  scales with ``s^2``) are refused with an error naming the vertex and the scale.
* conditioning: on thin or nearly degenerate faces (and, for PLMS, nearly planar ones) float32
  blocks and their gradients were off by up to 1e4 relative. Faces whose kernel bounds the
  error above ``FLOAT32_TOLERANCE`` are evaluated in float64.

The reference everywhere is the float64 assembly on the same (float32-rounded) coordinates,
with the same float32-rounded cotangents, whose gradients agree with finite differences
(tests/assembly/test_gradients.py). ``COUNTS`` records the cases per category
(docs/math/properties.md, "Finite precision").
"""

from __future__ import annotations

import re
import warnings
from collections import Counter

import numpy as np
import pytest
import torch
from conftest import DATA, hex_pent_mesh, mixed_mesh

import torch_polylap as tp
from torch_polylap.assembly import FLOAT32_TOLERANCE
from torch_polylap.kernels import block_kernel
from torch_polylap.shapes import quad_grid
from torch_polylap.sparse import sparse_values

hypothesis = pytest.importorskip(
    "hypothesis", reason="hypothesis not installed: pip install .[test]"
)
from hypothesis import HealthCheck, assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

# float32 on thin faces is this module's subject: the warning that products with L and the
# gradients lose accuracy is expected (test_faces_too_thin_for_a_float32_gradient_warn and
# tests/assembly/test_float32_warning.py assert it)
pytestmark = pytest.mark.filterwarnings("ignore::torch_polylap.checks.Float32PrecisionWarning")

COUNTS: Counter = Counter()
FUZZ = settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)
F32 = torch.finfo(torch.float32)
MASS_ERROR = r"mass of vertex \d+ .* outside the normal range of torch.float32 .* M0 scales"
METHODS = ("aw11", "plms", "degoes")


@pytest.fixture(scope="module", autouse=True)
def _print_counts():
    yield
    print("\nfloat32 cases per category:", dict(sorted(COUNTS.items())))


def _spot() -> tuple[torch.Tensor, tp.PolygonFaces]:
    with pytest.warns(tp.io.SkippedContentWarning):
        return tp.read_mesh(DATA / "spot_control_mesh.obj")


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).abs().max() / b.double().abs().max())


# ---------------------------------------------------------------------------------------------
# scale


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale", [1e-30, 1e-18, 1e20, 1e30])
def test_laplacian_of_spot_is_right_at_any_scale(scale, method, device):
    """Spot x 1e-18 gave 122 NaN entries, x 1e20 refused a valid face, x 1e30 was all NaN;
    ``validate=False`` skips the masses' range check (they are out of float32's range)."""
    V, F = _spot()
    V32 = (V * scale).float().to(device)
    ref = tp.laplacian(V32.double(), F, method=method)[0]
    out = tp.laplacian(V32, F, method=method, validate=False)[0]
    assert out.device.type == device.type
    assert torch.isfinite(sparse_values(out)).all()
    assert _relative(sparse_values(out), sparse_values(ref)) <= 1e-4


@pytest.mark.parametrize("scale", [1e-30, 1e-19, 1e20, 1e30])
def test_masses_out_of_float32_range_are_refused(scale, device):
    """M0 of Spot x 1e20 (about 1e38) overflows float32 and x 1e-19 underflows: an error naming
    a vertex, its mass and the scale, where NaN, zeros or subnormals were returned."""
    V, F = _spot()
    with pytest.raises(ValueError, match=MASS_ERROR):
        tp.laplacian((V * scale).float().to(device), F)


@pytest.mark.parametrize("method", METHODS)
def test_masses_in_range_at_extreme_coordinates_are_right(method, device):
    V, F = _spot()
    V32 = (V * 1e-17).float().to(device)
    L, M0 = tp.laplacian(V32, F, method=method)
    L64, M64 = tp.laplacian(V32.double(), F, method=method)
    assert _relative(sparse_values(L), sparse_values(L64)) <= 1e-4
    assert _relative(M0.diagonal(), M64.diagonal()) <= 1e-5


def test_a_face_too_small_against_the_coordinates_is_named(device):
    """A unit mesh plus a tiny face at the origin and a vertex at 1e20: the tiny face cannot
    be evaluated next to that scale in float32."""
    V = torch.tensor(
        [[0, 0, 0], [1e-18, 0, 0], [0, 1e-18, 0], [1e20, 0, 0], [1, 1, 0], [2, 1, 0], [1, 2, 0]],
        device=device,
    )
    with (
        pytest.warns(UserWarning, match="belong to no face"),
        pytest.raises(ValueError, match=r"face 0 \(vertices \[0, 1, 2\]\) is about .* too small"),
    ):
        tp.laplacian(V, [[0, 1, 2], [4, 5, 6]])


def test_a_non_finite_block_is_named(device):
    """A stabilizer weight of 1e38 overflows the blocks' sums: the first such face is named."""
    V, F = quad_grid(3, bump=0.3, seed=1, dtype=torch.float32, device=device)
    with pytest.raises(ValueError, match=r"face \d+ \(vertices .*\) has a non-finite block"):
        tp.laplacian(V, F, 1e38)


def test_non_finite_output_under_vmap_raises_the_generic_message(device):
    V, F = _spot()
    topo = tp.build_topology(F, V.shape[0])
    batch = torch.stack([V, V * 1e30]).float().to(device)
    with pytest.raises(ValueError, match="cannot be named"):
        torch.func.vmap(lambda X: sparse_values(tp.laplacian(X, topo)[1]))(batch)


def _random_polygon_mesh(seed: int) -> tuple[torch.Tensor, list[list[int]]]:
    """A jittered, bumpy quad grid with some cells split into triangles and some pairs merged
    into hexagons."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 6))
    V, F = quad_grid(n, bump=float(rng.uniform(0, 0.5)), seed=seed)
    faces: list[list[int]] = []
    quads = F.tolist()
    i = 0
    while i < len(quads):
        q = quads[i]
        r = rng.random()
        if r < 0.25:
            faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
        elif r < 0.4 and i + 1 < len(quads) and quads[i + 1][0] == q[3]:
            nxt = quads[i + 1]  # the next cell along y shares the edge (q[3], q[2])
            faces.append([q[0], q[1], q[2], nxt[2], nxt[3], q[3]])
            i += 1
        else:
            faces.append(q)
        i += 1
    rotation = torch.linalg.qr(torch.from_numpy(rng.standard_normal((3, 3))))[0]
    return V @ rotation.T + torch.from_numpy(rng.uniform(-3, 3, 3)), faces


@FUZZ
@given(
    seed=st.integers(0, 10_000),
    exponent=st.floats(-30, 30),
    method=st.sampled_from(METHODS),
    kind=st.sampled_from(["random", "mixed", "hexpent"]),
)
def test_any_scale_gives_the_float64_operator_or_a_mass_range_error(seed, exponent, method, kind):
    if kind == "random":
        V, F = _random_polygon_mesh(seed)
    else:
        V, F = mixed_mesh() if kind == "mixed" else hex_pent_mesh()
    scale = 10.0**exponent
    V32 = (V * scale).float()
    L64, M64 = tp.laplacian(V32.double(), F, 1.5, method=method)
    masses = M64.diagonal()
    representable = bool(((masses >= F32.tiny) & (masses <= F32.max)).all())
    try:
        L, M0 = tp.laplacian(V32, F, 1.5, method=method)
    except ValueError as err:
        assert not representable, f"refused a mesh whose masses float32 represents: {err}"
        assert re.search(MASS_ERROR, str(err)), str(err)
        COUNTS["scale: error"] += 1
        return
    assert representable
    assert torch.isfinite(sparse_values(L)).all() and torch.isfinite(sparse_values(M0)).all()
    assert _relative(sparse_values(L), sparse_values(L64)) <= 1e-4
    assert _relative(M0.diagonal(), masses) <= 1e-4
    COUNTS["scale: valid"] += 1


# ---------------------------------------------------------------------------------------------
# conditioning


def _gradient_error(verts: torch.Tensor, faces: list[list[int]], method: str) -> float:
    """Relative error (2-norm) of the float32 gradient of a random linear function of ``L``'s
    and ``M0``'s values against float64, both with the same float32 coordinates and weights."""
    topo = tp.build_topology(faces, verts.shape[0])
    grads = {}
    gen = torch.Generator().manual_seed(len(faces))
    w_l = w_m = None
    for dtype in (torch.float32, torch.float64):
        X = verts.float().to(dtype).requires_grad_(True)
        L, M0 = tp.laplacian(X, topo, 1.0, method=method)
        lv, mv = sparse_values(L), sparse_values(M0)
        if w_l is None:
            w_l, w_m = torch.randn(lv.shape, generator=gen), torch.randn(mv.shape, generator=gen)
        ((lv * w_l.to(lv)).sum() + (mv * w_m.to(mv)).sum()).backward()
        grads[dtype] = X.grad.double()
    ref = grads[torch.float64]
    return float((grads[torch.float32] - ref).norm() / ref.norm())


def _thinness(P: torch.Tensor) -> float:
    """``|f| / s^2`` of one face (float64)."""
    e = torch.roll(P, -1, 0) - P
    g = 0.5 * (e + torch.roll(e, 1, 0))
    area = 0.5 * torch.linalg.cross(P, torch.roll(P, -1, 0)).sum(0).norm()
    return float(area / (g * g).sum())


def _rotated(P: torch.Tensor, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    rotation = torch.linalg.qr(torch.from_numpy(rng.standard_normal((3, 3))))[0]
    return P @ rotation.T + torch.from_numpy(rng.uniform(-2, 2, 3))


def test_plms_gradient_on_a_nearly_planar_quad(device):
    """A unit square with heights 1e-5 (any real fine mesh has such faces): PLMS's float32
    gradient was off by 100 % (its weights carry 1 / height^2 terms)."""
    h = 1e-5
    P = torch.tensor([[0, 0, h], [1, 0, -h], [1, 1, h], [0, 1, -h]], dtype=torch.float64)
    P = _rotated(P, 0).to(device)
    assert _gradient_error(P, [[0, 1, 2, 3]], "plms") <= FLOAT32_TOLERANCE


@pytest.mark.parametrize("method", METHODS)
def test_gradient_on_a_thin_concave_quad(method, device):
    """A dart of thinness 1e-6: float32 gradients were off by several percent (AW11, dGBD20)
    and NaN (PLMS)."""
    t = 5e-7
    P = torch.tensor([[0, 0, 0], [2, t, 0], [0, 2 * t, 0], [1, 0.4 * t, 0]], dtype=torch.float64)
    P = _rotated(P, 1)
    assert 9e-7 <= _thinness(P) < 2e-6
    assert _gradient_error(P.to(device), [[0, 1, 2, 3]], method) <= FLOAT32_TOLERANCE


def _random_face(seed: int, k: int, squash: float, concave: bool, height: float) -> torch.Tensor:
    """A star-shaped ``k``-gon squashed to thinness about ``squash`` (one corner pulled in
    when ``concave``), lifted by relative heights ``height`` and moved off the origin; rotated
    unless it is planar.

    PLMS decides planarity at ``k eps`` of the working precision, so a planar face rotated
    out of a coordinate plane (heights at float32's round-off) is planar to float32 and not to
    float64: a jump in its weights, not an error of either. Planar faces stay in ``z = 0``.
    """
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * np.pi, k))
    radii = rng.uniform(0.5, 1.0, k)
    if concave:
        radii[rng.integers(k)] *= rng.uniform(0.0, 0.3)
    z = height * rng.choice([-1.0, 1.0], k) * rng.uniform(0.5, 1.0, k)
    P = torch.from_numpy(np.stack([radii * np.cos(angles), squash * radii * np.sin(angles), z], 1))
    if height == 0.0:
        return P + torch.tensor([rng.uniform(-2, 2), rng.uniform(-2, 2), 0.0])
    return _rotated(P, seed)


@FUZZ
@given(
    seed=st.integers(0, 10_000),
    k=st.integers(3, 7),
    squash=st.floats(-6, 0).map(lambda e: 10.0**e),
    concave=st.booleans(),
    height=st.one_of(st.just(0.0), st.floats(-5, -1).map(lambda e: 10.0**e)),
    method=st.sampled_from(METHODS),
)
def test_float32_gradient_matches_float64_on_ill_conditioned_faces(
    seed, k, squash, concave, height, method
):
    """Thin, concave, planar and nearly planar faces: the float32 gradient is within the
    tolerance of the float64 one. Thinness below 1e-6 is out of scope: the float32 backward
    itself (the sums of the cotangents, before any kernel) then loses that much."""
    P = _random_face(seed, k, squash, concave, height * squash)
    t = _thinness(P.float().double())
    assume(t >= 1e-6)
    shape = "thin" if t < 1e-3 else "regular"
    COUNTS[f"gradient: {shape} {'concave' if concave else 'convex'}"] += 1
    assert _gradient_error(P, [list(range(k))], method) <= FLOAT32_TOLERANCE


def test_well_conditioned_faces_stay_in_float32():
    """The fallback costs nothing on a mesh of reasonable faces: no face exceeds the bound."""
    V, F = quad_grid(20, bump=0.3, seed=3, dtype=torch.float32)
    topo = tp.build_topology(F, V.shape[0])
    kernel = block_kernel("aw11", 1.0)
    for grp in topo.groups:
        error = kernel(V.t().contiguous(), grp, grp.corners_t)[4]
        assert float(error.max()) * F32.eps <= FLOAT32_TOLERANCE


def _dart() -> tuple[torch.Tensor, list[list[int]]]:
    """The thin concave dart above, in float32: its blocks need float64."""
    t = 5e-7
    P = torch.tensor([[0, 0, 0], [2, t, 0], [0, 2 * t, 0], [1, 0.4 * t, 0]], dtype=torch.float64)
    return _rotated(P, 1).float(), [[0, 1, 2, 3]]


def test_ill_conditioned_float32_faces_are_refused_where_float64_cannot_run(device):
    """Traced or transformed, the float64 re-evaluation needs a host read it cannot make:
    such faces are refused rather than returned inaccurate."""
    P, faces = _dart()
    P = P.to(device)
    torch._dynamo.reset()
    with pytest.raises(RuntimeError, match="too thin or nearly degenerate for float32"):
        torch.compile(lambda X: tp.laplacian(X, faces)[0] @ X, backend="aot_eager")(P)
    torch._dynamo.reset()
    with pytest.raises(ValueError, match="too thin or nearly degenerate for float32"):
        torch.func.vmap(lambda X: (tp.laplacian(X, faces)[0] @ X).sum())(P[None])
    with pytest.raises(ValueError, match="too thin or nearly degenerate for float32"):
        torch.func.grad(lambda X: (tp.laplacian(X, faces)[0] @ X).square().sum())(P)
    # validate=False accepts the error, as documented
    torch.func.grad(lambda X: (tp.laplacian(X, faces, validate=False)[0] @ X).square().sum())(P)


def test_an_eager_float32_batch_with_ill_conditioned_faces_is_evaluated_mesh_by_mesh(device):
    P, faces = _dart()
    batch = torch.stack([P, P * 1.5]).to(device)
    L, M0 = tp.laplacian(batch, faces)
    # bitwise on the CPU; CUDA's parallel sums may order the shared entries differently
    exact = {"rtol": 0, "atol": 0} if device.type == "cpu" else {"rtol": 1e-6, "atol": 0}
    for b in range(2):
        Lb, Mb = tp.laplacian(batch[b], faces)
        torch.testing.assert_close(L[b].to_dense(), Lb.to_dense(), **exact)
        torch.testing.assert_close(M0.diagonal()[b], Mb.diagonal(), **exact)


def test_faces_too_thin_for_a_float32_gradient_warn(device):
    """Below thinness ~1e-6 float32's own backward loses the accuracy that float64 blocks
    keep: a warning says so (float64 input, or a fatter face, gives none)."""
    P, faces = _dart()  # thinness ~1e-6
    P = P.to(device)
    with pytest.warns(tp.checks.Float32PrecisionWarning, match="block in float64 would not help"):
        tp.laplacian(P, faces)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tp.laplacian(P.double(), faces)
        t = 1e-2  # s^2 / |f| = 50: products lose 1.5e-4 (at 1e-3, 500: 1.5e-2, which warns)
        fat = [[0, 0, 0], [2, t, 0], [0, 2 * t, 0], [1, 0.4 * t, 0]]
        tp.laplacian(torch.tensor(fat, dtype=torch.float32, device=device), faces)
