"""The README is a front page, the docs site the manual, and shipped text cites only the repository.

Checked here: the README's length, its set-up commands and that its quickstart runs; that the
generated list of supported operator operations matches the operator's dispatch table; that
the docs embed every committed figure of the examples and nothing else; and that README,
CHANGELOG, docs, package and tests neither cite internal issue numbers nor files outside the
repository (the reference meshes outside it are located by ``tests/meshes.py`` alone).
"""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from conftest import ROOT

from torch_polylap.data import DEFAULT_MESH

README = ROOT / "README.md"
FIGURES = ROOT / "examples" / "output"
SPOT = DEFAULT_MESH

# The one place allowed to name the reference-mesh folder beside the clone: the helper that
# locates it (with $POLYLAP_SHARED_MESHES as the override).
SHARED_HELPER = ROOT / "tests" / "meshes.py"

# External projects whose issue trackers a comment may cite ("matplotlib issue #32272").
EXTERNAL = ("matplotlib", "pytorch", "torch", "scipy", "numpy", "libigl", "trimesh", "mkdocs")


def shipped_files() -> list[Path]:
    files = [README, ROOT / "CHANGELOG.md", ROOT / "mkdocs.yml"]
    for folder in ("docs", "torch_polylap", "tests"):
        for suffix in ("*.md", "*.py"):
            files += sorted((ROOT / folder).rglob(suffix))
    return [f for f in files if "__pycache__" not in f.parts]


def internal_issue_refs(text: str) -> list[str]:
    """The word "issue" followed by a number, or a hash and a number: references to an issue
    tracker that is not shipped (a number after a library's name is that library's tracker)."""
    found = []
    pattern = re.compile(r"(?i)\bissues?[ -]#?\d+|(?<![\w/&#])#\d{1,4}\b")
    for m in pattern.finditer(text):
        before = text[max(0, m.start() - 30) : m.start()].lower()
        if any(re.search(rf"\b{name}\s+(issue\s*)?$", before) for name in EXTERNAL):
            continue
        found.append(m.group())
    return found


# the samples are assembled at run time, so that this file itself cites no issue
WORD, HASH = "iss" + "ue", "#"


def test_issue_ref_pattern():
    sample = f"the {WORD}-12 table; see {WORD} 7 and {HASH}31"
    assert internal_issue_refs(sample) == [f"{WORD}-12", f"{WORD} 7", f"{HASH}31"]
    assert internal_issue_refs("overflows on some runs (matplotlib issue #32272)") == []
    assert internal_issue_refs("colour #1f77b4, '#000000', ## Heading, x[#]") == []


def test_readme_is_a_front_page():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250
    # the two set-up commands: install and run the main job on the embedded mesh; run the tests
    assert 'pip install torch==2.13.0 && pip install -e ".[test]" && polylap info\n' in text
    assert "python -m pytest -q             # default: skips the slow tests\n" in text


def test_readme_links_resolve():
    text = README.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert targets, "the README links into the docs"
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, f"README links to files that do not exist: {missing}"


def test_readme_quickstart_runs():
    text = README.read_text(encoding="utf-8")
    code = re.search(r"## Quickstart\n\n```python\n(.*?)```", text, re.S)[1]
    assert '"mesh.obj"' in code and "range(100)" in code
    code = code.replace('"mesh.obj"', repr(str(SPOT))).replace("range(100)", "range(2)")
    namespace: dict = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Spot's texture coordinates are skipped, and said so
        exec(compile(code, "README.md quickstart", "exec"), namespace)
    X = namespace["X"]
    assert X.grad is not None and X.grad.shape == X.shape
    assert bool(X.grad.isfinite().all()) and float(X.grad.abs().sum()) > 0


def test_supported_operations_page_is_current():
    result = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "gen_supported_ops.py"), "--check"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr


def test_docs_embed_every_committed_figure():
    referenced = set()
    for page in (ROOT / "docs").rglob("*.md"):
        referenced |= set(re.findall(r"!\[[^\]]*\]\((?:\.\./)*figures/([^)]+)\)", page.read_text()))
    committed = {p.name for p in FIGURES.glob("*.png")}
    assert referenced <= committed, f"embedded, not in examples/output: {referenced - committed}"
    assert committed <= referenced, f"committed, shown on no docs page: {committed - referenced}"


# A document cited by a capitalized name (a project's notes, specs, sources) must be in the
# repository, but for other projects' own: DiffusionNet's INSTALL.md, and the SOURCES.md of the
# reference mesh collection the data tests read when it is present.
_CITABLE_MARKDOWN = {p.name for p in ROOT.rglob("*.md") if ".git" not in p.parts} | {
    "INSTALL.md",
    "SOURCES.md",
}


def documents_elsewhere(text: str) -> list[str]:
    """The capitalized Markdown documents ``text`` cites that are neither in the repository nor
    in :data:`_CITABLE_MARKDOWN`."""
    return sorted(set(re.findall(r"\b[A-Z][A-Z-]*\.md\b", text)) - _CITABLE_MARKDOWN)


def test_documents_elsewhere_are_found():
    notes = "NOTES" + ".md"  # assembled, so that this file cites no such document itself
    assert documents_elsewhere(f"see {notes}, README.md and run.md") == [notes]


@pytest.mark.parametrize("path", shipped_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_shipped_text_cites_only_the_repository(path):
    text = path.read_text(encoding="utf-8")
    problems = [f"internal issue reference {r!r}" for r in internal_issue_refs(text)]
    if path != SHARED_HELPER:
        problems += [f"{m!r} (outside the repository)" for m in re.findall(r"\.\./shared\S*", text)]
    problems += [f"{name} (not in the repository)" for name in documents_elsewhere(text)]
    problems += [
        f"internal target {m.group()!r}"
        for m in re.finditer(r"(?i)\btarget\b[^|\n]{0,40}\b(missed|met)\b", text)
    ]
    assert not problems, f"{path.relative_to(ROOT)}: " + "; ".join(problems)
