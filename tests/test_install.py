"""nhjax as an installed library: a wheel built from this checkout, installed into a
fresh virtual environment (not editable), gives a working ``nhjax`` CLI that lists and
runs the experiments from ``nhjax.experiments`` (the repository's experiments/ folder,
installed under nhjax's namespace: no top-level ``experiments`` in site-packages), and
does not offer ``nhjax bench`` (the benchmarks live in a checkout only).

The fresh venv sees the already-installed dependencies of the running
interpreter through a .pth line (the wheel itself goes in with ``--no-deps``), so
the test needs no network and stays quick; nhjax itself must come from the wheel,
which the test checks.
"""

from __future__ import annotations

import ast
import os
import tomllib
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_simulator_imports_nothing_from_controls():
    offenders = [str(p.relative_to(REPO)) for p in sorted((REPO / "nhjax").rglob("*.py"))
                 if {"controls", "experiments"} & _imports(p)]
    assert not offenders, f"nhjax must not import controls or experiments: {offenders}"


def test_checkout_lists_every_experiment_script():
    from nhjax.cli import experiments

    exps = experiments()
    on_disk = {p.stem for p in (REPO / "experiments").glob("*.py") if not p.name.startswith("_")}
    assert on_disk <= set(exps)
    assert "optimal_somersault" in exps and "__init__" not in exps


def test_pyproject_lists_every_package_of_the_checkout():
    """pyproject.toml lists the packages (find would take experiments/ for a top-level
    package): every folder with an __init__.py is there, experiments/ as nhjax.experiments."""
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {".".join(p.parent.relative_to(REPO).parts) for d in ("nhjax", "controls")
               for p in (REPO / d).rglob("__init__.py")}
    assert set(tool["packages"]) == on_disk | {"nhjax.experiments"}
    assert tool["package-dir"] == {"nhjax.experiments": "experiments"}


def test_every_experiment_takes_out_defaulting_to_its_name(capsys):
    """``nhjax run NAME --help`` for every experiment: its own options, among them
    ``--out`` with a folder named for it as the default; nothing runs."""
    from nhjax.cli import experiments, main

    for name in experiments():
        with pytest.raises(SystemExit) as e:
            main(["run", name, "--help"])
        assert e.value.code == 0, name
        out = capsys.readouterr().out
        assert "--out" in out and f"./{name}" in out, (name, out)


def test_unknown_experiment_is_a_clear_error(capsys):
    from nhjax.cli import main

    assert main(["run", "no_such_experiment"]) == 2
    err = capsys.readouterr().err
    assert "no_such_experiment" in err and "cat_holonomy" in err


def _clean_env():
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["MPLBACKEND"] = "Agg"
    return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv bin dir, work dir): a wheel of this checkout installed into a fresh venv."""
    tmp = tmp_path_factory.mktemp("install")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "out", "*.egg-info", "build")
    for d in ("nhjax", "controls", "experiments"):
        shutil.copytree(REPO / d, src / d, ignore=ignore)
    for f in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / f, src / f)
    wheels = tmp / "wheels"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheels), str(src)],
                   check=True, env=_clean_env(), cwd=tmp)
    (wheel,) = wheels.glob("nhjax-*.whl")
    venv = tmp / "venv"
    # a venv without its own pip (bootstrapping one took 8 s); the running pip installs into it
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    # the running interpreter's packages (jax, diffrax, ...), added after the venv's own
    (Path(site) / "_shared_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q",
                    "--disable-pip-version-check", str(wheel)], check=True, env=_clean_env())
    work = tmp / "work"
    work.mkdir()
    where = subprocess.run([str(py), "-c", "import nhjax, controls, nhjax.experiments as e; "
                            "print(nhjax.__file__); print(controls.__file__); print(e.__file__)"],
                           check=True, capture_output=True, text=True, env=_clean_env(), cwd=work).stdout.split()
    assert all(w.startswith(str(venv)) for w in where), where  # from the wheel, not this checkout
    return venv / "bin", work, Path(site)


def test_no_top_level_experiments_package_is_installed(installed):
    """The wheel installs nhjax (with nhjax.experiments inside) and controls, nothing
    else at the top of site-packages: ``import experiments`` fails in the install."""
    bin_dir, work, site = installed
    (record,) = site.glob("nhjax-*.dist-info/RECORD")
    paths = [line.split(",")[0] for line in record.read_text().splitlines() if line]
    tops = {p.split("/")[0] for p in paths if not p.startswith("..")}  # "../../../bin/nhjax": the script
    assert tops == {"nhjax", "controls", record.parent.name}, tops
    assert (site / "nhjax" / "experiments" / "cat_holonomy.py").is_file()
    assert not (site / "experiments").exists()
    r = subprocess.run([str(bin_dir / "python"), "-c", "import experiments"], capture_output=True, text=True,
                       env=_clean_env(), cwd=work)
    assert r.returncode != 0 and "No module named 'experiments'" in r.stderr, r.stderr


def test_installed_run_help_and_no_bench(installed):
    """From the install: ``nhjax run NAME --help`` shows the experiment's own options
    (its --out defaults to a folder named for it) without running it; ``nhjax bench``
    is not offered (absent from --help; asked for, a clear message and exit 2)."""
    bin_dir, work, _ = installed
    for name in ("cat_holonomy", "steer_sphere"):  # one on nhjax alone, one on controls
        r = subprocess.run([str(bin_dir / "nhjax"), "run", name, "--help"], capture_output=True, text=True,
                           env=_clean_env(), cwd=work)
        assert r.returncode == 0, r.stderr[-2000:]
        assert "--out" in r.stdout and f"./{name}" in r.stdout, r.stdout
    assert sorted(p.name for p in work.iterdir()) == []  # --help wrote nothing
    r = subprocess.run([str(bin_dir / "nhjax"), "--help"], capture_output=True, text=True, env=_clean_env(),
                       cwd=work, check=True)
    assert "{demo,list,run}" in r.stdout and "bench" not in r.stdout, r.stdout
    r = subprocess.run([str(bin_dir / "nhjax"), "bench"], capture_output=True, text=True, env=_clean_env(), cwd=work)
    assert r.returncode == 2 and "source checkout" in r.stderr, (r.returncode, r.stderr)


def test_installed_cli_lists_experiments(installed):
    bin_dir, work, _ = installed
    out = subprocess.run([str(bin_dir / "nhjax"), "list"], check=True, capture_output=True, text=True,
                         env=_clean_env(), cwd=work).stdout
    assert "experiments (nhjax run <name>):" in out
    listed = {line.split()[0] for line in out.split("experiments (nhjax run <name>):")[1].splitlines() if line.strip()}
    on_disk = {p.stem for p in (REPO / "experiments").glob("*.py") if not p.name.startswith("_")}
    assert on_disk <= listed
    assert "FallingCat" in out  # the scene registry


@pytest.mark.slow
def test_installed_cli_runs_an_experiment(installed):
    """cat_holonomy from the wheel: its CSV lands in ./cat_holonomy/ under the working
    directory and holds simulated turns that match the closed form -2 pi f(theta) (the
    script's own check)."""
    bin_dir, work, _ = installed
    res = subprocess.run([str(bin_dir / "nhjax"), "run", "cat_holonomy"], capture_output=True, text=True,
                         env=_clean_env(), cwd=work)
    assert res.returncode == 0, res.stderr[-3000:]
    csv = work / "cat_holonomy" / "cat_holonomy.csv"
    assert csv.is_file() and (work / "cat_holonomy" / "cat_holonomy.png").is_file()
    import numpy as np

    rows = np.genfromtxt(csv, delimiter=",", names=True)
    cols = rows.dtype.names
    sim = [c for c in cols if "sim" in c.lower()]
    exact = [c for c in cols if "closed" in c.lower() or "exact" in c.lower()]
    assert sim and exact, cols
    np.testing.assert_allclose(rows[sim[0]], rows[exact[0]], rtol=0, atol=1e-6)


def test_list_shows_each_experiment_in_one_whole_plain_sentence(capsys):
    from nhjax.cli import first_sentence, main

    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "`" not in out
    lines = out.split("experiments (nhjax run <name>):")[1].strip().splitlines()
    assert len(lines) >= 10
    for line in lines:
        assert line.rstrip().endswith("."), line  # a sentence, not a line of the docstring cut mid-way
    # the first sentence of a paragraph spread over lines, with abbreviations and RST code
    doc = "Ball in a cone (seed 002, Fig. 9.5): the path\nin ``(alpha, rho)``. Default: more.\n\nNext."
    assert first_sentence(doc) == "Ball in a cone (seed 002, Fig. 9.5): the path in (alpha, rho)."


def test_python_m_nhjax_is_the_command_line():
    r = subprocess.run([sys.executable, "-m", "nhjax", "--help"], capture_output=True, text=True, check=True)
    assert "{demo,list,run,bench}" in r.stdout and "`" not in r.stdout
