"""Command line: ``nhjax demo | list | run <experiment> | bench``.

Experiments are scripts (``experiments/*.py``). The CLI finds them in two places,
so that they run from a source checkout and from an installed package alike:

1. a source checkout: ``experiments/`` next to the ``nhjax`` package, when a
   ``pyproject.toml`` sits beside it (``pip install -e .`` or ``PYTHONPATH``);
2. the entry-point group ``nhjax.experiments``: each entry names a package whose
   ``*.py`` files (names not starting with ``_``) are experiments. The nhjax
   distribution registers its own ``experiments`` package there; another project
   can register its package the same way in its pyproject.toml::

       [project.entry-points."nhjax.experiments"]
       mylab = "mylab_experiments"

Where outputs go: in a source checkout, where the script says (most write to the
checkout's ``experiments/out/``). From an installed package, an experiment runs
as if it were ``<workdir>/experiments/<name>.py`` with ``<workdir>`` as the
current directory, so its outputs go to ``<workdir>/experiments/out/``;
``<workdir>`` is ``--workdir`` (default: the current directory), never the
read-only install.

The CLI sits above both packages (``nhjax`` the simulator and ``controls`` the
optimal control): ``nhjax demo`` runs the experiment ``optimal_somersault``,
which imports ``controls``; nothing in the ``nhjax`` package imports it.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.resources
import os
import re
import runpy
import sys
import types
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ENTRY_POINT_GROUP = "nhjax.experiments"


@dataclass(frozen=True)
class Experiment:
    """One experiment script: its ``name``, its ``source`` (a path or an
    importlib.resources Traversable), where it was found (``origin``: "checkout"
    or the entry point's name) and whether it runs in place (a checkout) or
    relocated to a work directory (an installed package)."""

    name: str
    source: object
    origin: str
    in_place: bool

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


def _checkout_dir() -> Path | None:
    d = REPO / "experiments"
    return d if (REPO / "pyproject.toml").is_file() and d.is_dir() else None


def experiments() -> dict[str, Experiment]:
    """Every experiment the CLI can run, by name (checkout first, then the
    entry-point group ``nhjax.experiments``; the first of a name wins)."""
    found: dict[str, Experiment] = {}
    d = _checkout_dir()
    if d is not None:
        for p in sorted(d.glob("*.py")):
            if not p.name.startswith("_"):
                found.setdefault(p.stem, Experiment(p.stem, p, "checkout", True))
    for ep in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            root = importlib.resources.files(ep.value)
        except (ModuleNotFoundError, TypeError) as err:  # a stale registration must not break `nhjax list`
            print(f"nhjax: entry point {ep.name} = {ep.value!r} in group {ENTRY_POINT_GROUP} "
                  f"cannot be loaded ({err})", file=sys.stderr)
            continue
        for f in sorted(root.iterdir(), key=lambda f: f.name):
            if f.is_file() and f.name.endswith(".py") and not f.name.startswith("_"):
                name = f.name[:-3]
                found.setdefault(name, Experiment(name, f, ep.name, False))
    return found


def _get(name: str) -> Experiment:
    exps = experiments()
    if name not in exps:
        known = ", ".join(exps) or "none"
        raise UnknownExperiment(f"no experiment {name!r} (known: {known}); experiments come from experiments/ in a "
                       f"source checkout or from packages registered in the entry-point group {ENTRY_POINT_GROUP}")
    return exps[name]


def load_experiment(name: str) -> types.ModuleType:
    """Import the experiment ``name`` as a module (not as ``__main__``), e.g. to call
    its functions; raises UnknownExperiment (a KeyError) listing the known names."""
    exp = _get(name)
    mod = types.ModuleType(f"nhjax_experiment_{name}")
    with importlib.resources.as_file(exp.source) as path:
        mod.__file__ = str(path)
        code = compile(exp.text(), str(path), "exec")
    sys.modules[mod.__name__] = mod  # dataclasses and pickling look the module up by name
    exec(code, mod.__dict__)
    return mod


@contextlib.contextmanager
def _cwd(path: Path):
    old = os.getcwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(old)


def run_experiment(name: str, args=(), workdir=None) -> None:
    """Run the experiment ``name`` as ``__main__`` with command-line ``args``.

    From a checkout it runs in place. From an installed package it runs as
    ``<workdir>/experiments/<name>.py`` in ``workdir`` (default: the current
    directory), so outputs land in ``<workdir>/experiments/out/``.
    """
    exp = _get(name)
    argv = sys.argv
    try:
        if exp.in_place:
            sys.argv = [str(exp.source), *args]
            runpy.run_path(str(exp.source), run_name="__main__")
            return
        work = Path(workdir or os.getcwd()).resolve()
        (work / "experiments").mkdir(parents=True, exist_ok=True)
        as_if = work / "experiments" / f"{name}.py"
        with importlib.resources.as_file(exp.source) as real:
            code = compile(exp.text(), str(real), "exec")  # tracebacks point at the installed file
        sys.argv = [str(as_if), *args]
        with _cwd(work):
            exec(code, {"__name__": "__main__", "__file__": str(as_if), "__builtins__": __builtins__})
    finally:
        sys.argv = argv


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="nhjax", description=plain(__doc__.splitlines()[0]))
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_demo = sub.add_parser("demo", help="optimize the falling cat's somersault, then show it (numbers, figures)")
    p_demo.add_argument("--out", default="experiments/out", help="directory for figures and JSON")
    p_demo.add_argument("--no-figures", action="store_true")
    p_demo.add_argument("--holonomy", action="store_true",
                        help="instead: the torque-driven somersault along a closed-form holonomy loop")
    sub.add_parser("list", help="list scenes and experiments")
    p_run = sub.add_parser("run", help="run an experiment (experiments/ or a registered package)")
    p_run.add_argument("--workdir", default=None,
                       help="installed package only: run in this directory; outputs go to "
                            "WORKDIR/experiments/out (default: the current directory)")
    p_run.add_argument("experiment")
    p_run.add_argument("args", nargs=argparse.REMAINDER)
    p_bench = sub.add_parser("bench", help="run the benchmarks (needs the [bench] extra)")
    p_bench.add_argument("args", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)

    if args.cmd == "demo":
        if args.holonomy:
            from .demos import somersault

            somersault(out=args.out, figures=not args.no_figures)
            return 0
        demo_args = ["--out", args.out] + (["--no-figures"] if args.no_figures else [])
        return main(["run", "optimal_somersault", *demo_args])
    if args.cmd == "list":
        from .scenes import REGISTRY

        print("scenes (nhjax.scenes):")
        for name, (_, desc) in REGISTRY.items():
            print(f"  {name:24s} {desc}")
        exps = experiments()
        print("experiments (nhjax run <name>):" if exps else
              f"experiments: none found (no checkout next to this install, nothing in {ENTRY_POINT_GROUP})")
        for name, exp in exps.items():
            print(f"  {name:24s} {exp.doc_line()}")
        return 0
    if args.cmd == "run":
        try:
            run_experiment(args.experiment, args.args, workdir=args.workdir)
        except UnknownExperiment as err:
            print(f"nhjax run: {err.args[0]}", file=sys.stderr)
            return 2
        return 0
    if args.cmd == "bench":
        script = REPO / "benchmarks" / "run.py"
        if not script.is_file():
            print("nhjax bench: benchmarks/ is not next to this install (use a source checkout)", file=sys.stderr)
            return 2
        sys.argv = [str(script), *args.args]
        runpy.run_path(str(script), run_name="__main__")
        return 0
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
