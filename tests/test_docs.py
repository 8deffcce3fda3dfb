"""The documentation site builds without a warning, and its notebook pages show the
notebooks as they are (the Python blocks of the pages and of README.md run as tests of
their own, through pytest-markdown-docs)."""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _code(path):
    cells = json.loads(path.read_text())["cells"]
    return ["".join(c["source"]) for c in cells if c["cell_type"] == "code"]


def test_notebook_pages_are_the_current_notebooks():
    """docs/notebooks/ holds executed copies of notebooks/ (their figures); a copy whose
    code differs from its notebook shows old code and old figures."""
    sources = sorted((ROOT / "notebooks").glob("*.ipynb"))
    copies = {p.name: p for p in (ROOT / "docs" / "notebooks").glob("*.ipynb")}
    assert sorted(copies) == [p.name for p in sources], "run `make docs-notebooks`"
    stale = [p.name for p in sources if _code(p) != _code(copies[p.name])]
    assert not stale, f"docs/notebooks/ copies older than notebooks/ ({', '.join(stale)}): run `make docs-notebooks`"
    for name, copy in copies.items():
        cells = json.loads(copy.read_text())["cells"]
        assert any(o.get("output_type") in ("display_data", "execute_result") and "image/png" in o.get("data", {})
                   for c in cells for o in c.get("outputs", ())), f"{name}: no figure"


def test_site_builds_strictly(tmp_path):
    """`mkdocs build --strict` (what `make docs` runs): the API pages cover every public
    name (docs/ext/coverage_check.py), every link and reference resolves, every
    docstring parses."""
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-5000:] + run.stderr[-5000:]
    assert (tmp_path / "site" / "api" / "simulate" / "index.html").is_file()
