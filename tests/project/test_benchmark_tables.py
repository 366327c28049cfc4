"""The tables of benchmarks/README.md are generated from the committed results and cannot drift.

``benchmarks/tables.py`` renders each ``<!-- table:NAME/TABLE -->`` block from
``benchmarks/results/NAME.json``; these tests assert the README equals what it renders, that
every results file carries the metadata header of ``common.write_results``, and that the
README's opening list names every script.
"""

from __future__ import annotations

import importlib.util
import json
import re
import sys

import pytest
from conftest import ROOT

BENCH = ROOT / "benchmarks"
README = BENCH / "README.md"
RESULTS = BENCH / "results"


def _module(name: str):
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


tables = _module("tables")


@pytest.mark.parametrize("page", tables.PAGES, ids=lambda p: p.name)
def test_generated_tables_equal_the_committed_results(page):
    text = page.read_text()
    assert tables.stale_blocks(text) == [], "run python benchmarks/tables.py"
    assert tables.regenerate(text) == text


def test_every_results_file_is_in_the_readme_and_has_a_header():
    text = README.read_text()
    shown = {m["ref"].split("/")[0] for m in tables.BLOCK.finditer(text)}
    for path in sorted(RESULTS.glob("*.json")):
        data = json.loads(path.read_text())
        assert data["benchmark"] == path.stem, path
        meta = data["meta"]
        for key in ("date", "command", "machine", "versions", "threads"):
            assert key in meta, f"{path.name}: meta has no {key!r}"
        assert "load_before" in meta and "load_after" in meta, path
        assert data["tables"], f"{path.name}: no tables"
        for key in data["tables"]:
            assert f"<!-- table:{path.stem}/{key} -->" in text, f"{path.name}: {key} not shown"
        assert path.stem in shown, path


def test_a_changed_cell_is_reported(tmp_path):
    """The check fails when a README cell no longer matches the results (not a no-op)."""
    results = tmp_path / "results"
    results.mkdir()
    (results / "demo.json").write_text(
        json.dumps(
            {
                "benchmark": "demo",
                "meta": {"date": "2026-01-02T03:04:05+00:00", "machine": {"cpu": "X"}},
                "tables": {"t": {"columns": ["a", "b|c"], "rows": [["1", "22"]]}},
            }
        )
    )
    text = (
        "intro\n<!-- table:demo/t -->\nold\n<!-- /table:demo/t -->\n"
        "<!-- run:demo -->\n<!-- /run:demo -->\n"
    )
    fresh = tables.regenerate(text, results)
    table = "| a | b\\|c |\n|---|------|\n| 1 | 22   |\n"
    assert fresh.startswith("intro\n<!-- table:demo/t -->\n" + table)
    assert "Run: 2026-01-02, X." in fresh
    assert tables.stale_blocks(fresh, results) == []
    assert tables.stale_blocks(fresh.replace("| 22 ", "| 23 "), results) == ["table:demo/t"]
    assert tables.stale_blocks(text, results) == ["table:demo/t", "run:demo"]
    with pytest.raises(KeyError, match="no table 'u'"):
        tables.regenerate(text.replace("demo/t", "demo/u"), results)
    with pytest.raises(FileNotFoundError, match="nothing"):
        tables.regenerate(text.replace("demo", "nothing"), results)


def test_opening_list_names_every_script():
    intro = README.read_text().split("\n## ")[0]
    listed = set(re.findall(r"`([\w]+\.(?:py|sh))`", intro))
    scripts = {p.name for p in BENCH.glob("*.py")} | {p.name for p in BENCH.glob("*.sh")}
    assert scripts - listed == set(), "benchmarks/README.md's opening list misses these"


def test_write_results_writes_the_header(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    common = _module("common")
    meta = common.run_meta(["bench_demo.py", "--n", "3"], threads=1)
    path = common.write_results(
        "demo",
        {"tables": {"t": common.table_data(["a"], [[1]])}, "where": tmp_path},
        meta=meta,
        path=tmp_path / "demo.json",
    )
    data = json.loads(path.read_text())
    assert data["benchmark"] == "demo"
    assert data["meta"]["command"] == "python bench_demo.py --n 3"
    assert data["meta"]["threads"] == 1
    assert data["meta"]["versions"]["torch"] and data["meta"]["machine"]["cores"]
    assert len(data["meta"]["load_after"]) == (3 if sys.platform == "linux" else 0)
    assert data["tables"]["t"] == {"columns": ["a"], "rows": [["1"]]}
    assert data["where"] == str(tmp_path)
    assert not list(tmp_path.glob("*.tmp"))


def test_bench_grid_is_the_lifted_unit_square(monkeypatch):
    import torch

    monkeypatch.syspath_prepend(str(BENCH))
    common = _module("common")
    verts, faces = common.bench_grid(4, 3)
    assert verts.shape == (20, 3) and faces.shape == (12, 4)
    x, y = verts[:, 0], verts[:, 1]
    assert torch.equal(verts[:, 2], 0.05 * torch.sin(7 * x) * torch.cos(5 * y))
    assert float(x.min()) == 0.0 and float(x.max()) == 1.0 and float(y.max()) == 1.0
    noisy, _ = common.bench_grid(4, 3, noise=0.01, seed=1)
    again, _ = common.bench_grid(4, 3, noise=0.01, seed=1)
    assert torch.equal(noisy, again) and not torch.equal(noisy, verts)
