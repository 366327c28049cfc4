"""mkdocs hook: the examples' committed figures, served under ``figures/`` on the site.

The example scripts write their figures to ``examples/output/`` (committed there, next to the
reports that describe them). The pages embed them as ``figures/NAME.png`` (from a page in a
subfolder, ``../figures/NAME.png``); this hook adds every PNG of ``examples/output`` to the
site's files under that name, so there is one copy of each figure and the strict build checks
every reference to one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

FIGURES = Path(__file__).resolve().parents[1] / "examples" / "output"


def on_files(files: Files, config: Any) -> Files:
    for png in sorted(FIGURES.glob("*.png")):
        files.append(File.generated(config, f"figures/{png.name}", abs_src_path=str(png)))
    return files
