"""Every public entry point on empty and degenerate meshes: a result or a clear error.

The entry points, the input classes and the outcome classes are those of the sweep in
``benchmarks/reliability.py`` (which records the whole table): a **clear error** is a
``ValueError``, ``TypeError`` or ``ImportError`` (or an exception class of this package) raised
by this package's own code, a **raw error** anything from inside torch, numpy or scipy (or an
``IndexError``, ...), and a result holding a NaN counts as wrong. Ill-conditioned but valid
systems give a result or a clear error; every command of the CLI, interrupted at each phase,
ends with its one line and status 130.
"""

from __future__ import annotations

import importlib.util
import sys
import warnings

import pytest
import torch
from conftest import ROOT

import torch_polylap as tp

BENCH = ROOT / "benchmarks"


def _reliability():
    sys.path.insert(0, str(BENCH))  # the script imports its neighbour `common`
    try:
        spec = importlib.util.spec_from_file_location(
            "benchmarks_reliability", BENCH / "reliability.py"
        )
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    return module


sweep = _reliability()
ACCEPTED = {"valid", "warned", "clear error"}


def _check(outcome: str, detail: str) -> None:
    assert outcome in ACCEPTED, detail


@pytest.mark.parametrize("input_class", sweep.EMPTY_INPUTS)
@pytest.mark.parametrize("name", sorted(sweep.ENTRY_POINTS))
def test_entry_point_on_an_empty_or_degenerate_mesh(name, input_class):
    _check(*sweep.sweep_entry(name, input_class))


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(sweep.ENTRY_POINTS))
def test_entry_point_recipe_runs_on_a_regular_mesh(name):
    """The sweep's calls are right: on a regular grid each gives a result (or the error of a
    missing optional package, or enclosed_volume's of an open mesh)."""
    outcome, detail = sweep.sweep_entry(name, "regular mesh")
    if outcome == "clear error":
        assert detail.startswith("ImportError") or name == "apps.enclosed_volume", detail
    else:
        assert outcome in ("valid", "warned"), detail


@pytest.mark.parametrize("name", sorted(sweep.ILL_CONDITIONED))
def test_ill_conditioned_systems_give_a_result_or_a_clear_error(name):
    outcome, detail = sweep.sweep_outcome(sweep.ILL_CONDITIONED[name])
    assert outcome in ACCEPTED, detail
    if name == "solve, L + 1e-12 M0":  # positive definite: solved, with the warning
        assert (outcome, detail) == ("warned", "IllConditionedWarning")


# -- the raw errors the sweep found, fixed ---------------------------------------------------


def _isolated():
    """A quad and a triangle beside vertices 5 and 6, which no face references."""
    return sweep.INPUTS["isolated vertices beside faces"]()


def test_chebyshev_operator_names_a_vertex_without_mass():
    """Its normalization divides by the masses: a vertex no face references made every entry
    NaN (lambda_max is a maximum over all rows); the repair the message names makes it work."""
    V, F = _isolated()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the unreferenced vertices
        L, M0 = tp.laplacian(V, F)
    with pytest.raises(ValueError, match=r"vertex 5 has mass 0 \(2 such vertices\).*remove_unref"):
        tp.nn.chebyshev_operator(L, M0)
    V, F, _ = tp.repair.remove_unreferenced_vertices(V, F)
    S_hat = tp.nn.chebyshev_operator(*tp.laplacian(V, F))
    # the symmetric normalization scaled by 2 / lambda_max, minus I: spectrum within [-1, 1]
    evals = torch.linalg.eigvalsh(S_hat.to_dense())
    assert evals.min() >= -1 - 1e-12 and evals.max() <= 1 + 1e-12


@pytest.mark.filterwarnings("ignore:the mesh .* is not a consistently oriented")  # no faces
def test_angle_distortion_of_a_mesh_without_faces_is_a_clear_error():
    V = torch.rand(4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="angle_distortion: the mesh has no faces"):
        tp.apps.angle_distortion(V[:, :2], V, torch.zeros((0, 3), dtype=torch.long))


def test_planarize_a_mesh_without_vertices_is_a_clear_error():
    with pytest.raises(ValueError, match="planarize: the mesh has no vertices"):
        tp.apps.planarize(torch.zeros((0, 3), dtype=torch.float64), [])


# -- the CLI, interrupted at each phase ------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(not hasattr(sweep.signal, "SIGHUP"), reason="needs POSIX signals")
@pytest.mark.parametrize("phase", sweep.CLI_PHASES)
@pytest.mark.parametrize("command", sorted(sweep.CLI_COMMANDS))
def test_every_command_interrupted_at_every_phase(command, phase):
    outcome, detail = sweep.cli_interrupt(command, phase)
    assert outcome == "clear", detail
