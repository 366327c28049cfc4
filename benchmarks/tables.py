"""Regenerate the tables of ``benchmarks/README.md`` and ``docs/performance.md`` from the
committed results.

    python benchmarks/tables.py            # rewrite the README's generated blocks
    python benchmarks/tables.py --check    # exit 1 (naming the blocks) if any is out of date

The README marks each generated block with a pair of HTML comments:

* ``<!-- table:NAME/TABLE -->`` ... ``<!-- /table:NAME/TABLE -->``: the table ``TABLE`` of
  ``results/NAME.json`` (its ``"tables"`` entry: ``columns`` and ``rows`` of cells as printed);
* ``<!-- run:NAME -->`` ... ``<!-- /run:NAME -->``: one paragraph on how ``results/NAME.json``
  was made (date, machine, load, versions, threads, command; and whether the numbers were
  transcribed from an earlier run's report rather than written by the script).

Everything between a pair is replaced; everything outside is left as written. Needs only the
standard library, so the test that keeps the README and the results in step runs anywhere.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
README = HERE / "README.md"
RESULTS = HERE / "results"
# every page with generated blocks: the benchmarks' README and the docs site's performance page
PAGES = (README, HERE.parent / "docs" / "performance.md")

BLOCK = re.compile(
    r"(<!-- (?P<kind>table|run):(?P<ref>[\w.\-/]+) -->\n)"
    r"(?P<body>.*?)"
    r"(<!-- /(?P=kind):(?P=ref) -->)",
    re.S,
)


def load(name: str, results: Path = RESULTS) -> dict:
    """``results/<name>.json`` as a dict; a clear error when it is missing."""
    path = results / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no results file for the README's block {name!r}")
    return json.loads(path.read_text())


def markdown(columns: list[str], rows: list[list[str]]) -> str:
    """A Markdown table, columns padded to their widest cell (``|`` in a cell escaped)."""
    cells = [[str(c).replace("|", "\\|") for c in r] for r in [columns, *rows]]
    for number, r in enumerate(cells[1:], 1):
        if len(r) != len(columns):
            raise ValueError(f"row {number} has {len(r)} cells for {len(columns)} columns: {r}")
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    lines = [
        "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in cells
    ]
    lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
    return "\n".join(lines)


def render_table(ref: str, results: Path = RESULTS) -> str:
    """The Markdown of ``NAME/TABLE``."""
    name, _, key = ref.partition("/")
    tables = load(name, results).get("tables", {})
    if key not in tables:
        raise KeyError(f"results/{name}.json has no table {key!r} (it has: {sorted(tables)})")
    return markdown(tables[key]["columns"], tables[key]["rows"])


# the reference meshes' folder as a run recorded it (beside the repository), named instead:
# the pages cite nothing outside the repository
MESHES = re.compile(r"(?:\.\./)+shared/data/meshes")


def render_run(name: str, results: Path = RESULTS) -> str:
    """One paragraph on how ``results/<name>.json`` was made, from its ``meta`` header."""
    meta = load(name, results)["meta"]
    machine = meta.get("machine", {})
    versions = meta.get("versions", {})
    peers = meta.get("peers") or {}
    parts = [f"{(meta.get('date') or '?')[:10]}, {machine.get('cpu') or '?'}"]
    if machine.get("cores"):
        parts[0] += f" ({machine['cores']} cores)"
    soft = [f"{k} {v}" for k, v in {**versions, **peers}.items() if v and k != "torch_polylap"]
    if soft:
        parts.append(", ".join(soft))
    if meta.get("threads") is not None:
        parts.append(f"{meta['threads']} thread{'s' if meta['threads'] != 1 else ''}")
    if meta.get("environment"):
        parts.append(" ".join(f"{k}={v}" for k, v in meta["environment"].items()))
    before, after = meta.get("load_before"), meta.get("load_after")
    loads = [
        " ".join(f"{x:g}" for x in values) + f" {when}"
        for values, when in ((before, "before"), (after, "after"))
        if values
    ]
    if loads:
        parts.append("load average " + ", ".join(loads))
    text = "Run: " + "; ".join(parts) + "."
    if meta.get("command"):
        text += f" Command: `{meta['command']}`."
    if meta.get("transcribed"):
        text += f" {meta['transcribed']}"
    if meta.get("note"):
        text += f" {meta['note']}"
    return MESHES.sub("$MESHES", text)


def regenerate(text: str, results: Path = RESULTS) -> str:
    """``text`` with every generated block replaced by what the results give."""

    def block(match: re.Match[str]) -> str:
        ref = match["ref"]
        body = render_table(ref, results) if match["kind"] == "table" else render_run(ref, results)
        return f"{match.group(1)}{body}\n{match.group(5)}"

    return BLOCK.sub(block, text)


def stale_blocks(text: str, results: Path = RESULTS) -> list[str]:
    """The ``kind:ref`` of every block whose content differs from what the results give."""
    new = regenerate(text, results)
    fresh = {f"{m['kind']}:{m['ref']}": m["body"] for m in BLOCK.finditer(new)}
    return [
        f"{m['kind']}:{m['ref']}"
        for m in BLOCK.finditer(text)
        if fresh[f"{m['kind']}:{m['ref']}"] != m["body"]
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only report out-of-date blocks")
    parser.add_argument(
        "--page", type=Path, action="append", help="a page to process (default: all of PAGES)"
    )
    args = parser.parse_args(argv)
    status = 0
    for page in args.page or PAGES:
        text = page.read_text()
        if args.check:
            for ref in stale_blocks(text):
                print(f"{page}: block {ref} is out of date; run benchmarks/tables.py")
                status = 1
            continue
        new = regenerate(text)
        if new != text:
            page.write_text(new)
            print(f"rewrote {page}", file=sys.stderr)
    return status

if __name__ == "__main__":
    sys.exit(main())
