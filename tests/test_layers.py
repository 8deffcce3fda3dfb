"""The layers and the absence of import circles, as import-linter contracts.

The contracts live in pyproject.toml (``[tool.importlinter]``): nhjax's modules in
layers (lie -> mechanics -> integrate / scenes -> controls -> the experiments, demos
and CLI on top), the simulator never importing ``controls``, and no import circle
between the modules of any package (function-level imports count: an import moved
into a function to dodge a circle is still a circle). ``lint-imports`` checks them
here; a copy of the packages with a planted circle and a planted upward import
shows that the check fails when a contract breaks.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(cwd: Path, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return subprocess.run([str(LINT), "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True)


def _contracts() -> dict:
    return {c["id"]: c for c in tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]}


def test_the_import_contracts_hold():
    r = _lint(REPO)
    assert r.returncode == 0, r.stdout[-6000:] + r.stderr[-2000:]
    assert "0 broken" in r.stdout


def test_every_simulator_module_is_forbidden_controls():
    """The forbidden contract lists every module of nhjax but the top layer (CLI, demos,
    experiments): a new module cannot slip past it."""
    contracts = _contracts()
    top = {m.strip().strip("()") for m in contracts["nhjax-layers"]["layers"][0].split(":")}
    children = {p.stem for p in (REPO / "nhjax").glob("*.py") if p.name != "__init__.py"}
    children |= {p.parent.name for p in (REPO / "nhjax").glob("*/__init__.py")}
    sources = set(contracts["simulator-without-controls"]["source_modules"])
    assert sources == {f"nhjax.{c}" for c in children - top}


def test_a_broken_contract_fails_the_check(tmp_path):
    """A function-level import of integrate inside nhjax.lie (a circle, and an upward
    import) and an import of controls in nhjax.mechanics: lint-imports fails and names
    the contracts and the imports."""
    for d in ("nhjax", "controls"):
        shutil.copytree(REPO / d, tmp_path / d, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy2(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    with open(tmp_path / "nhjax" / "lie" / "so3.py", "a") as f:
        f.write("\n\ndef _planted():\n    from ..integrate import simulate\n\n    return simulate\n")
    with open(tmp_path / "nhjax" / "mechanics" / "rigid.py", "a") as f:
        f.write("\n\nimport controls  # noqa: E402\n")
    r = _lint(tmp_path, pythonpath=tmp_path)
    assert r.returncode != 0, r.stdout[-3000:]
    out = r.stdout
    assert "nhjax.lie.so3 -> nhjax.integrate" in out, out[-6000:]
    assert "nhjax.mechanics.rigid -> controls" in out, out[-6000:]
    for contract in ("nhjax-layers", "simulator-without-controls", "no-circles"):
        assert _contracts()[contract]["name"].split("(")[0].strip() in " ".join(out.split()), contract
