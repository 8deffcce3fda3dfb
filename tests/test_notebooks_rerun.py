"""Every notebook in notebooks/ runs twice in one kernel without error.

A reader re-runs cells: "Run all" a second time, in the same kernel, must work as
the first did (no loop variable shadowing a function of an earlier cell, no state
a cell assumes fresh). nbmake (``--nbmake``) runs each notebook once in a fresh
kernel; here nbclient executes all its cells, then all of them again in the same
kernel, and a cell that raises fails the test with its traceback. Slow: a first
run compiles for up to minutes (``make test-all`` runs it).
"""

from __future__ import annotations

import os
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

NOTEBOOKS = sorted((Path(__file__).resolve().parent.parent / "notebooks").glob("*.ipynb"))


def _run_twice(nb, cwd: Path):
    """Execute the code cells of ``nb``, then all of them again, in one kernel; returns
    None, or (run, cell index, error) for the first cell that raised."""
    client = NotebookClient(nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(cwd)}})
    code = [(i, c) for i, c in enumerate(nb.cells) if c.cell_type == "code"]
    assert code, "a notebook without code cells"
    with client.setup_kernel(env=dict(os.environ)):
        for run in ("first", "second"):
            for index, cell in code:
                try:
                    client.execute_cell(cell, index)
                except CellExecutionError as err:
                    return run, index, err
    return None


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_twice_in_one_kernel(path, monkeypatch):
    monkeypatch.setenv("MPLBACKEND", "Agg")  # the kernel inherits it: figures without a display
    failed = _run_twice(nbformat.read(path, as_version=4), path.parent)
    if failed is not None:
        run, index, err = failed
        pytest.fail(f"{path.name}, {run} run, cell {index}:\n{err}")


def test_the_second_run_catches_what_the_first_does_not(tmp_path):
    """A notebook that only fails when run again (its output folder exists by then):
    the check names the second run and the cell."""
    nb = nbformat.v4.new_notebook(cells=[
        nbformat.v4.new_code_cell("from pathlib import Path"),
        nbformat.v4.new_code_cell("Path('out').mkdir()"),
        nbformat.v4.new_code_cell("print('done')"),
    ])
    run, index, err = _run_twice(nb, tmp_path)
    assert (run, index) == ("second", 1) and "FileExistsError" in str(err)
