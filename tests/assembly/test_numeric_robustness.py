"""L is scale invariant and M0 scales by s^2: both hold to round-off far from unit scale.

The per-face kernels work in a scaled frame (geometry.quad_entries, geometry.polygon_entries),
so no quantity of order s^4 is formed; before, the squared vector area underflowed at
s ~ 1e-77 (float64) and overflowed at 1e77. Also: half precision and bad ``lam`` are refused.
"""

from __future__ import annotations

import pytest
import torch
from conftest import hex_pent_mesh, mixed_mesh

import torch_polylap as tp
from torch_polylap.checks import check_lam, check_verts
from torch_polylap.kernels.aw11 import polygon_entries
from torch_polylap.kernels.frames import gather_corners
from torch_polylap.shapes import quad_grid

SCALES = [
    (torch.float64, 1e-150, 1e-10),
    (torch.float64, 1e150, 1e-10),
    (torch.float64, 1e-30, 1e-10),
    (torch.float32, 1e-8, 1e-4),
    (torch.float32, 1e8, 1e-4),
]


def _relative(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


@pytest.mark.parametrize("dtype,scale,tol", SCALES)
def test_quad_laplacian_is_scale_invariant(dtype, scale, tol, device):
    V, F = quad_grid(5, bump=0.3, seed=7, device=device)
    V = V.to(dtype)
    L1, M1 = tp.laplacian(V, F)
    Ls, Ms = tp.laplacian(V * scale, F)
    assert torch.isfinite(Ls.values()).all()
    assert _relative(Ls.to_dense(), L1.to_dense()) <= tol
    masses = M1.to_dense().diagonal().double() * scale**2
    assert _relative(Ms.to_dense().diagonal().double(), masses) <= tol


@pytest.mark.parametrize("dtype,scale,tol", SCALES)
@pytest.mark.parametrize("mesh", [mixed_mesh, hex_pent_mesh])
def test_polygon_kernel_is_scale_invariant(mesh, dtype, scale, tol):
    V, F = mesh()
    V = V.to(dtype)
    topo = tp.build_topology(F, V.shape[0])
    for grp in topo.groups:
        ref = polygon_entries(
            gather_corners(V.t().contiguous(), grp.corners_t), grp.pair_i, grp.pair_j, 1.5
        )
        out = polygon_entries(
            gather_corners((V * scale).t().contiguous(), grp.corners_t), grp.pair_i, grp.pair_j, 1.5
        )
        assert _relative(out[0], ref[0]) <= tol
        assert _relative(out[1].double(), ref[1].double() * scale**2) <= tol


def test_polygon_kernel_matches_the_assembly_at_unit_scale():
    V, F = hex_pent_mesh()
    topo = tp.build_topology(F, V.shape[0])
    for (ids, ref), grp in zip(tp.dec.local_laplacians(V, topo, 2.0), topo.groups, strict=True):
        x = gather_corners(V.t().contiguous(), grp.corners_t)
        off, _, _ = polygon_entries(x, grp.pair_i, grp.pair_j, 2.0)
        assert torch.equal(ids, grp.face_ids)
        assert torch.allclose(off.t(), ref[:, grp.pair_i, grp.pair_j], rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("scale", [1e-150, 1e150])
def test_mixed_laplacian_is_scale_invariant(scale, device):
    V, F = mixed_mesh()
    V = V.to(device)
    L1 = tp.laplacian(V, F)[0].to_dense()
    Ls = tp.laplacian(V * scale, F)[0].to_dense()
    assert _relative(Ls, L1) <= 1e-10


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_is_refused_clearly(dtype, device):
    V, _ = quad_grid(2, device=device)
    with pytest.raises(TypeError, match=r"float32 or float64\), got torch\.b?float16; use verts"):
        check_verts(V.to(dtype))


@pytest.mark.parametrize("lam", [float("nan"), float("inf"), -1.0, torch.tensor(-0.5)])
def test_bad_lam_is_refused(lam):
    with pytest.raises(ValueError, match="lam must be a finite number >= 0"):
        check_lam(lam)


def test_lam_zero_and_tensors_are_accepted():
    t = torch.tensor(2.0, requires_grad=True)
    assert check_lam(0.0) == 0.0 and check_lam(t) is t and check_lam(3) == 3


@pytest.mark.parametrize("scale", [1e-150, 1e150])
def test_face_measures_are_exact_at_extreme_scales(scale, device):
    """Areas scale by s^2, normals not at all, at scales where a plain norm of the vector area
    under- or overflows."""
    V, F = mixed_mesh()
    V = V.to(device)
    torch.testing.assert_close(tp.mass(V * scale, F) / scale**2, tp.mass(V, F), rtol=1e-13, atol=0)
    torch.testing.assert_close(
        tp.face_areas(V * scale, F) / scale**2, tp.face_areas(V, F), rtol=1e-13, atol=0
    )
    torch.testing.assert_close(tp.face_normals(V * scale, F), tp.face_normals(V, F))
