"""Structural properties of L and M0 (docs/math/properties.md) on real polygon meshes.

Meshes: every file of the shared mesh directory's ``real/`` folder
(``meshes.shared_meshes_dir``, listed in its SOURCES.md; skipped when that directory is absent),
read from the in-repository copy in tests/data/ when there is one, plus the in-repository sphere
and grid meshes (always run). All in float64 with lambda = 1.

Cost control: dense eigenvalues only below DENSE_MAX vertices; up to SPARSE_MAX vertices PSD-ness
and the kernel dimension come from the inertia of a sparse symmetric factorization (exact
counts, one LU each); above that only cheap checks (symmetry, row sums, quadratic forms of
random and smooth fields, masses, counts, Euler characteristic).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
import torch

import torch_polylap as tp
from torch_polylap.apps import conformal_parameterization

try:  # tests/ on sys.path (pytest's default import mode)
    from meshes import DATA_DIR, SHARED_SKIP_REASON, load, require_shared, shared_meshes_dir
except ImportError:  # tests/ imported as a package
    from tests.meshes import DATA_DIR, SHARED_SKIP_REASON, load, require_shared, shared_meshes_dir

LAM = 1.0
DENSE_MAX = 2000  # dense eigvalsh up to here (~0.5 s at 2000 vertices on 2 cores)
SPARSE_MAX = 21000  # sparse factorizations up to here (rockerArm, 20088: ~0.5 s)


# Facts about the files, copied from the shared real/SOURCES.md (V, F, degree
# histogram "deg", boundary edges / boundary loops "bdry"), plus:
#   comps: connected components (SOURCES notes: catmark_car has 31 separate parts, others 1);
#   genus: per SOURCES notes where stated (quadknot, rockerArm: 1; spot: 0; bunny-dual: closed
#          dual of the bunny, 0) or evident from the shape (dodecahedron, the hex_cos_6 sphere,
#          the closed bunny_poly: 0; the flat grids and tetris are discs: 0); None = not stated;
#   flat: the planar meshes (z = 0 grids, and tetris, which lies in the plane y = -0.002002).
REAL = {
    "tetris.obj": dict(
        V=52, F=16, deg={4: 1, 5: 1, 6: 3, 7: 2, 8: 5, 9: 3, 10: 1}, bdry=(16, 1),
        comps=1, genus=0, flat=True,
    ),
    "dodecahedron_poly.obj": dict(
        V=20, F=12, deg={5: 12}, bdry=(0, 0), comps=1, genus=0, flat=False
    ),
    "spot_control_mesh.obj": dict(
        V=188, F=180, deg={3: 4, 4: 160, 5: 16}, bdry=(0, 0), comps=1, genus=0, flat=False
    ),
    "moebius.obj": dict(
        V=280, F=224, deg={4: 224}, bdry=(112, 1), comps=1, genus=None, flat=False
    ),
    "quadknot.obj": dict(
        V=1440, F=1440, deg={4: 1440}, bdry=(0, 0), comps=1, genus=1, flat=False
    ),
    "bunny_poly.ply": dict(
        V=1241, F=1482, deg={3: 486, 4: 996}, bdry=(0, 0), comps=1, genus=0, flat=False
    ),
    "catmark_car.obj": dict(
        V=1642, F=1575, deg={4: 1575}, bdry=(60, 11), comps=31, genus=None, flat=False
    ),
    "mixedFaring.off": dict(
        V=2310, F=2258, deg={3: 770, 4: 1130, 5: 47, 6: 263, 7: 48}, bdry=(161, 4),
        comps=1, genus=None, flat=False,
    ),
    "spot_quadrangulated.obj": dict(
        V=2930, F=2928, deg={4: 2928}, bdry=(0, 0), comps=1, genus=0, flat=False
    ),
    "grid_concave_4.obj": dict(
        V=12657, F=6272, deg={5: 112, 6: 6160}, bdry=(336, 1), comps=1, genus=0, flat=True
    ),
    "polyfem_concave_1.obj": dict(
        V=8023, F=6986, deg={4: 6888, 20: 14, 24: 84}, bdry=(168, 1), comps=1, genus=0,
        flat=True,
    ),
    "rockerArm.obj": dict(
        V=20088, F=10044,
        deg={3: 3, 4: 462, 5: 3066, 6: 3811, 7: 1778, 8: 636, 9: 219, 10: 55, 11: 12, 12: 2},
        bdry=(0, 0), comps=1, genus=1, flat=False,
    ),
    "sword-quad-dominant.obj": dict(
        V=22293, F=22465, deg={3: 348, 4: 22117}, bdry=(0, 0), comps=1, genus=None, flat=False
    ),
    "lion_vase_poly.off": dict(
        V=46206, F=23105, deg={3: 1, 4: 27, 5: 2188, 6: 18685, 7: 2175, 8: 29}, bdry=(0, 0),
        comps=1, genus=None, flat=False,
    ),
    "grid_voronoi_5.obj": dict(
        V=50866, F=25600, deg={4: 217, 5: 6096, 6: 14306, 7: 4695, 8: 282, 9: 4},
        bdry=(589, 1), comps=1, genus=0, flat=True,
    ),
    "loki.obj": dict(
        V=27514, F=27352, deg={4: 27352}, bdry=(328, 4), comps=1, genus=None, flat=False
    ),
    "bunny-dual.off": dict(
        V=72774, F=36389, deg={5: 2986, 6: 30429, 7: 2974}, bdry=(0, 0), comps=1, genus=0,
        flat=False,
    ),
    "hex_cos_6.obj": dict(
        V=81920, F=40962, deg={5: 12, 6: 40950}, bdry=(0, 0), comps=1, genus=0, flat=False
    ),
}  # fmt: skip

# In-repository refinement meshes (no count table for these): unit spheres are closed genus-0
# surfaces; the grids are flat discs (one boundary loop).
FAMILY = {
    **{
        f"sphere/{n}.obj": dict(bdry_loops=0, comps=1, genus=0, flat=False)
        for n in ("hex_2", "hex_3", "quad_2", "quad_3", "voronoi_3", "concave_3", "hex_cos_3")
    },
    **{
        f"grid/{n}.obj": dict(bdry_loops=1, comps=1, genus=0, flat=True)
        for n in ("quad_2", "quad_3", "voronoi_3", "concave_3", "str_hex_3", "dia_quad_3")
    },
}

ORIENTABLE_REAL = [n for n in REAL if n != "moebius.obj"]
ALL_MESHES = ORIENTABLE_REAL + list(FAMILY)
FLAT_MESHES = [n for n in ALL_MESHES if {**REAL, **FAMILY}[n]["flat"]]


def _path(name: str):
    """In-repository copy when there is one, else the shared file (skipping when absent)."""
    local = DATA_DIR / name
    if local.is_file():
        return local
    path = require_shared() / "real" / name
    if not path.is_file():
        pytest.skip(f"{path} is missing from the shared mesh directory")
    return path


class MeshOps:
    """Everything the tests need about one mesh, computed once per session."""

    def __init__(self, name: str):
        self.verts, self.faces = load(_path(name))
        self.V = self.verts.shape[0]
        self.topo = tp.build_topology(self.faces, self.V)
        L, M0 = tp.laplacian(self.verts, self.faces, LAM)
        self.L = tp.sparse.to_scipy(L)
        self.M0 = tp.sparse.to_scipy(M0)
        self.m = self.M0.diagonal()
        self.maxabs = abs(self.L).max()
        # Rayleigh quotients e_i^T L e_i = L_ii are lower bounds of lambda_max, and the largest
        # absolute row sum (Gershgorin) an upper bound: lambda_max lies in [diag_max, gersh].
        self.diag_max = self.L.diagonal().max()
        self.gersh = abs(self.L).sum(axis=1).max()

    @functools.cached_property
    def n_components(self) -> int:
        return csgraph.connected_components(self.L, directed=False)[0]

    @functools.cached_property
    def boundary_vertices(self) -> np.ndarray:
        return self.topo.boundary_vertices.numpy()


@functools.cache
def mesh_ops(name: str) -> MeshOps:
    return MeshOps(name)


def negative_pivots(A: sp.spmatrix) -> int:
    """Number of negative eigenvalues of the symmetric ``A`` (Sylvester's law of inertia).

    Sparse LU with a symmetric permutation and no row pivoting, ``P A P^T = L U``, is an
    ``L D L^T`` factorization with ``D = diag(U)``, which has the inertia of ``A``. The
    factorization is checked to have pivoted symmetrically.
    """
    lu = spla.splu(
        sp.csc_matrix(A),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options=dict(SymmetricMode=True),
    )
    assert np.array_equal(lu.perm_r, lu.perm_c), "the factorization pivoted off the diagonal"
    return int((lu.U.diagonal() < 0).sum())


# --------------------------------------------------------------------------------------------
# Reading and counts
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(REAL))
def test_counts_match_sources(name):
    facts = REAL[name]
    verts, faces = load(_path(name))
    assert verts.dtype == torch.float64
    assert verts.shape == (facts["V"], 3)
    assert faces.num_faces == facts["F"]
    degrees, counts = np.unique(faces.sizes.numpy(), return_counts=True)
    assert dict(zip(degrees.tolist(), counts.tolist(), strict=True)) == facts["deg"]
    assert bool(torch.isfinite(verts).all())


def test_in_repo_copies_equal_shared_files():
    root = shared_meshes_dir()
    if root is None:
        pytest.skip(SHARED_SKIP_REASON)
    for name in REAL:
        local = DATA_DIR / name
        if local.is_file():
            assert local.read_bytes() == (root / "real" / name).read_bytes(), name


def _sources_planarity() -> dict[str, tuple[float, float]]:
    """The "planar max/med" column of SOURCES.md: least-squares-plane non-planarity of the
    faces of degree > 3, max and median, printed to two digits."""
    root = require_shared()
    table = {}
    for line in (root / "real" / "SOURCES.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 13 and "/" in cells[9] and cells[0] in REAL:
            high, median = (float(v) for v in cells[9].split("/"))
            table[cells[0]] = (high, median)
    return table


@pytest.mark.parametrize("name", [n for n in REAL if n != "moebius.obj"])
def test_fitted_plane_nonplanarity_matches_sources(name):
    """face_nonplanarity(plane="fit") reproduces the independently computed SOURCES.md column."""
    expected = _sources_planarity().get(name)
    if expected is None:
        pytest.skip(f"{name} has no planarity entry in SOURCES.md")
    verts, faces = load(_path(name))
    values = tp.face_nonplanarity(verts, faces, plane="fit")[faces.sizes > 3].numpy()
    # numpy's median averages the two middle values (torch.median returns the lower one)
    for ours, printed in zip((values.max(), np.median(values)), expected, strict=True):
        digit = 10.0 ** math.floor(math.log10(printed)) / 10 if printed > 0 else 1e-12
        assert abs(float(ours) - printed) <= 0.51 * digit, (name, float(ours), printed)


@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")  # on purpose
def test_moebius_builds_operators_and_refuses_what_needs_an_orientation():
    verts, faces = load(_path("moebius.obj"))
    with pytest.warns(UserWarning, match=r"1 non-orientable component"):
        topo = tp.build_topology(faces, verts.shape[0])
    assert topo.is_manifold and not topo.is_oriented
    assert topo.report.non_orientable_components == 1
    L, M0 = tp.laplacian(verts, topo, LAM)
    Ls, Ms = tp.sparse.to_scipy(L), tp.sparse.to_scipy(M0)
    assert abs(Ls - Ls.T).max() == 0 and np.abs(Ls.sum(1)).max() < 1e-10 * abs(Ls).max()
    assert Ms.diagonal().min() > 0
    with pytest.raises(ValueError, match=r"conformal_parameterization needs an oriented mesh"):
        conformal_parameterization(verts, topo)
    with pytest.raises(ValueError, match=r"1 of its components cannot be oriented"):
        tp.losses.normal_consistency((verts, faces))


@pytest.mark.parametrize("name", ORIENTABLE_REAL)
def test_boundary_matches_sources(name):
    ops = mesh_ops(name)
    n_edges, n_loops = REAL[name]["bdry"]
    bnd = ops.topo.boundary_edges.numpy()
    assert bnd.shape[0] == n_edges
    # Loops as SOURCES.md counts them: components of the boundary-edge graph.
    if n_edges:
        used, inv = np.unique(bnd, return_inverse=True)
        inv = inv.reshape(-1, 2)
        g = sp.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), (used.size, used.size))
        loops = csgraph.connected_components(g, directed=False)[0]
    else:
        loops = 0
    assert loops == n_loops


@pytest.mark.parametrize("name", ALL_MESHES)
def test_euler_characteristic_and_components(name):
    facts = {**REAL, **FAMILY}[name]
    ops = mesh_ops(name)
    chi = ops.topo.euler_characteristic()
    assert chi == ops.V - ops.topo.num_edges + ops.faces.num_faces  # no isolated vertices
    assert ops.n_components == facts["comps"]
    loops = facts["bdry"][1] if name in REAL else facts["bdry_loops"]
    # chi = sum over components of (2 - 2 g - b). With loops counted as graph components this
    # is exact when no two loops touch (true for every mesh whose genus is given).
    if facts["genus"] is not None:
        assert chi == 2 * facts["comps"] - 2 * facts["genus"] - loops
    elif facts["comps"] == 1:
        # Genus not stated: it must still come out a non-negative integer.
        twice_genus = 2 - loops - chi
        assert twice_genus >= 0 and twice_genus % 2 == 0, chi


# --------------------------------------------------------------------------------------------
# L and M0
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ALL_MESHES)
def test_symmetric_and_rows_sum_to_zero(name):
    ops = mesh_ops(name)
    L = ops.L
    assert L.shape == (ops.V, ops.V)
    assert np.isfinite(L.data).all()
    # Each off-diagonal entry is computed once and scattered to (i, j) and (j, i): symmetric to
    # round-off, i.e. a few ulps of the largest entry.
    asym = abs(L - L.T).max() if (L - L.T).nnz else 0.0
    assert asym <= 1e-14 * ops.maxabs
    # L 1 = 0: each row's entries cancel; the error is round-off of that sum, ~ eps * sum |L_pj|.
    row_sum = np.abs(np.asarray(L.sum(axis=1)).ravel())
    row_abs = np.asarray(abs(L).sum(axis=1)).ravel()
    assert np.all(row_sum <= 1e-13 * row_abs)
    # Positive diagonal: PSD, and no vertex has an empty row (no isolated vertices here).
    assert np.all(L.diagonal() > 0)


@pytest.mark.parametrize("name", ALL_MESHES)
def test_psd_and_kernel_is_constants_per_component(name):
    ops = mesh_ops(name)
    L, k = ops.L, ops.n_components
    if ops.V <= DENSE_MAX:
        w = np.linalg.eigvalsh(L.toarray())
        # PSD to round-off: eigenvalue errors are ~ eps * lambda_max * sqrt(V) << 1e-10.
        assert w[0] >= -1e-10 * w[-1], w[:3] / w[-1]
        # Kernel: zero eigenvalues sit at ~1e-15 lambda_max; the smallest non-zero ones at
        # >= 1e-5 lambda_max on these meshes. 1e-8 splits the two with margin on both sides.
        assert int((w < 1e-8 * w[-1]).sum()) == k, w[: k + 2] / w[-1]
    if ops.V <= SPARSE_MAX:
        eye = sp.identity(ops.V, format="csc")
        # Same thresholds via inertia (exact counts, no eigenvalues needed). diag_max <=
        # lambda_max, so these shifts are at most the dense test's thresholds: stricter.
        # L + 1e-10 diag_max I positive definite <=> lambda_min > -1e-10 diag_max.
        assert negative_pivots(L + 1e-10 * ops.diag_max * eye) == 0
        # #eigenvalues < 1e-8 diag_max == number of connected components.
        assert negative_pivots(L - 1e-8 * ops.diag_max * eye) == k
    else:
        # Big meshes, cheap version: x^T L x >= 0 for random fields (high frequencies) and for
        # smooth ones (the coordinates, products and low-frequency waves: the low end of the
        # spectrum, where a wrong sign would show first). Tolerance as above, with the
        # Gershgorin bound standing in for lambda_max.
        rng = np.random.default_rng(0)
        X = ops.verts.numpy()
        Xc = (X - X.mean(0)) / np.abs(X - X.mean(0)).max()
        fields = [rng.normal(size=ops.V) for _ in range(3)]
        fields += [Xc[:, 0], Xc[:, 1], Xc[:, 2], Xc[:, 0] * Xc[:, 1], Xc[:, 1] * Xc[:, 2]]
        fields += [np.sin(math.pi * (Xc @ rng.normal(size=3))) for _ in range(3)]
        for x in fields:
            assert x @ (L @ x) >= -1e-10 * ops.gersh * (x @ x)
        # Kernel contains the constants on each component (row sums, tested above, say L 1 = 0).
        assert np.abs(L @ np.ones(ops.V)).max() <= 1e-13 * ops.gersh


@pytest.mark.parametrize("name", ALL_MESHES)
def test_mass(name):
    ops = mesh_ops(name)
    M0 = ops.M0.tocoo()
    assert np.array_equal(M0.row, M0.col)  # diagonal
    assert not ops.topo.isolated.any()  # every vertex of these files is referenced
    assert np.all(ops.m > 0)
    areas = tp.face_areas(ops.verts, ops.faces).numpy()
    assert np.all(areas > 0)
    # sum_p m_p = sum_f k_f (|f| / k_f) = sum_f |f|: the same numbers summed in another order.
    assert ops.m.sum() == pytest.approx(areas.sum(), rel=1e-12)
    np.testing.assert_allclose(ops.m, tp.mass(ops.verts, ops.faces).numpy(), rtol=1e-12)


@pytest.mark.parametrize("name", FLAT_MESHES)
def test_linear_precision_on_flat_meshes(name):
    ops = mesh_ops(name)
    X = ops.verts.numpy()
    # Planar to round-off (tetris is not in z = 0 but in the plane y = -0.002002).
    s = np.linalg.svd(X - X.mean(0), compute_uv=False)
    assert s[2] <= 1e-12 * s[0]
    LX = ops.L @ X
    # (L X)_p = sum_j L_pj (x_j - x_p) = 0 at interior vertices: the terms that must cancel
    # have size scale_p = sum_j |L_pj| |x_j - x_p|; round-off leaves ~eps * scale_p * (few).
    C = ops.L.tocoo()
    d = np.linalg.norm(X[C.col] - X[C.row], axis=1)
    scale = np.bincount(C.row, weights=np.abs(C.data) * d, minlength=ops.V)
    interior = np.ones(ops.V, dtype=bool)
    interior[ops.boundary_vertices] = False
    assert interior.sum() > 0.5 * ops.V
    err = np.linalg.norm(LX, axis=1)
    assert np.all(err[interior] <= 1e-10 * scale[interior]), (err / scale)[interior].max()
    # Not vacuous: at the boundary L X is the (non-zero) outward conormal.
    assert np.max(err[~interior] / scale[~interior]) > 1e-3
