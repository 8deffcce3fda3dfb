"""Command line: ``nhjax demo | list | run <experiment> | bench``.

Experiments are the modules of the package ``nhjax.experiments`` (the repository's
``experiments/`` folder, installed under nhjax's namespace) and of any package
registered in the entry-point group ``nhjax.experiments``, whose ``*.py`` modules
(names not starting with ``_``) are experiments too; another project registers its
package in its pyproject.toml::

    [project.entry-points."nhjax.experiments"]
    mylab = "mylab_experiments"

``nhjax run NAME ARGS`` runs the module as ``python -m <package>.NAME ARGS`` does.
Every experiment takes ``--out``: where its figures and tables go, by default a
folder named for the experiment under the current directory (never inside the
install). ``nhjax run NAME --help`` lists its options.

``nhjax bench`` runs ``benchmarks/run.py`` of a source checkout; an install without
the checkout does not offer it (it is left out of ``--help`` and says so when asked).

The CLI sits above both packages (``nhjax`` the simulator and ``controls`` the
optimal control): ``nhjax demo`` runs the experiment ``optimal_somersault``,
which imports ``controls``; the simulator itself imports nothing from ``controls``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.resources
import re
import runpy
import sys
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

from .demos import somersault
from .scenes import REGISTRY

REPO = Path(__file__).resolve().parent.parent
ENTRY_POINT_GROUP = "nhjax.experiments"
#: nhjax's own experiments (the repository's experiments/ folder, installed here)
OWN_PACKAGE = "nhjax.experiments"


@dataclass(frozen=True)
class Experiment:
    """One experiment: its ``name``, its ``module`` (``<package>.<name>``), its
    ``source`` (an importlib.resources Traversable) and where it was found
    (``origin``: "nhjax" or the entry point's name)."""

    name: str
    module: str
    source: object
    origin: str

    def text(self) -> str:
        return self.source.read_text()

    def doc_line(self) -> str:
        """The first sentence of the script's docstring, as plain text."""
        text = self.text()
        for quote in ('"""', "'''"):
            if quote in text:
                return first_sentence(text.split(quote)[1])
        return ""


def plain(text: str) -> str:
    """RST markup a terminal shows literally (``code``, `refs`) as plain text."""
    return re.sub(r"`{1,2}([^`]+)`{1,2}", r"\1", text)


def first_sentence(doc: str) -> str:
    """The first sentence of a docstring's first paragraph (lines joined), as plain text:
    what ``nhjax list`` shows beside a name, never cut mid-sentence."""
    para = " ".join(doc.strip().split("\n\n")[0].split())
    m = re.search(r"\.(\s+(?=[A-Z(])|$)", para)
    return plain(para[: m.start() + 1] if m else para)


class UnknownExperiment(KeyError):
    """No experiment of that name (the message lists the known ones)."""


def _packages():
    """(origin, package) of every experiment package: nhjax's own first, then the
    entry-point group's."""
    yield "nhjax", OWN_PACKAGE
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        if ep.value != OWN_PACKAGE:
            yield ep.name, ep.value


def experiments() -> dict[str, Experiment]:
    """Every experiment the CLI can run, by name (``nhjax.experiments`` first, then the
    entry-point group ``nhjax.experiments``; the first of a name wins)."""
    found: dict[str, Experiment] = {}
    for origin, package in _packages():
        try:
            root = importlib.resources.files(package)
        except (ModuleNotFoundError, TypeError) as err:  # a stale registration must not break `nhjax list`
            hint = ("; nhjax's experiments come with an install (pip install -e . in a checkout), not with "
                    "PYTHONPATH" if package == OWN_PACKAGE else "")
            print(f"nhjax: experiment package {package!r} ({origin}) cannot be loaded ({err}){hint}", file=sys.stderr)
            continue
        for f in sorted(root.iterdir(), key=lambda f: f.name):
            if f.is_file() and f.name.endswith(".py") and not f.name.startswith("_"):
                name = f.name[:-3]
                found.setdefault(name, Experiment(name, f"{package}.{name}", f, origin))
    return found


def _get(name: str) -> Experiment:
    exps = experiments()
    if name not in exps:
        known = ", ".join(exps) or "none"
        raise UnknownExperiment(f"no experiment {name!r} (known: {known}); experiments are the modules of "
                                f"{OWN_PACKAGE} and of packages registered in the entry-point group "
                                f"{ENTRY_POINT_GROUP}")
    return exps[name]


def load_experiment(name: str):
    """Import the experiment ``name`` as a module (not as ``__main__``), e.g. to call
    its functions; raises UnknownExperiment (a KeyError) listing the known names."""
    return importlib.import_module(_get(name).module)


def run_experiment(name: str, args=()) -> None:
    """Run the experiment ``name`` as ``__main__`` with command-line ``args``, as
    ``python -m <package>.<name> ARGS`` would; its outputs go where its ``--out`` says
    (by default a folder named for it under the current directory)."""
    exp = _get(name)
    argv = sys.argv
    try:
        sys.argv = [f"nhjax run {name}", *args]
        runpy.run_module(exp.module, run_name="__main__", alter_sys=True)  # __main__ is the experiment
    finally:
        sys.argv = argv


def _bench_script() -> Path | None:
    """benchmarks/run.py of the source checkout this nhjax runs from, if any."""
    script = REPO / "benchmarks" / "run.py"
    return script if (REPO / "pyproject.toml").is_file() and script.is_file() else None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    bench = _bench_script()
    if bench is None and argv[:1] == ["bench"]:
        print("nhjax bench: the benchmarks are not installed with nhjax; they run from a source checkout "
              "(git clone, then `make bench` there)", file=sys.stderr)
        return 2
    commands = "demo | list | run <experiment>" + (" | bench" if bench is not None else "")
    parser = argparse.ArgumentParser(prog="nhjax", description=f"Command line: nhjax {commands}.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_demo = sub.add_parser("demo", help="optimize the falling cat's somersault, then show it (numbers, figures)")
    p_demo.add_argument("--out", default=None,
                        help="folder for figures and JSON (default: ./optimal_somersault, or ./somersault "
                             "with --holonomy)")
    p_demo.add_argument("--no-figures", action="store_true")
    p_demo.add_argument("--holonomy", action="store_true",
                        help="instead: the torque-driven somersault along a closed-form holonomy loop")
    sub.add_parser("list", help="list scenes and experiments")
    p_run = sub.add_parser("run", help="run an experiment (nhjax.experiments or a registered package); "
                                       "nhjax run NAME --help shows its options")
    p_run.add_argument("experiment")
    p_run.add_argument("args", nargs=argparse.REMAINDER)
    if bench is not None:  # a source checkout: benchmarks/ beside the package
        p_bench = sub.add_parser("bench", help="run the benchmarks (needs the [bench] extra)")
        p_bench.add_argument("args", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)

    if args.cmd == "demo":
        if args.holonomy:
            somersault(out=args.out or "somersault", figures=not args.no_figures)
            return 0
        demo_args = (["--out", args.out] if args.out else []) + (["--no-figures"] if args.no_figures else [])
        return main(["run", "optimal_somersault", *demo_args])
    if args.cmd == "list":
        print("scenes (nhjax.scenes):")
        for name, (_, desc) in REGISTRY.items():
            print(f"  {name:24s} {desc}")
        exps = experiments()
        print("experiments (nhjax run <name>):" if exps else "experiments: none found")
        for name, exp in exps.items():
            print(f"  {name:24s} {exp.doc_line()}")
        return 0
    if args.cmd == "run":
        try:
            run_experiment(args.experiment, args.args)
        except UnknownExperiment as err:
            print(f"nhjax run: {err.args[0]}", file=sys.stderr)
            return 2
        return 0
    if args.cmd == "bench":
        sys.argv = [str(bench), *args.args]
        runpy.run_path(str(bench), run_name="__main__")
        return 0
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
