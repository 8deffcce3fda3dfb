"""Command line: ``nhjax demo | list | run <experiment> | bench``."""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _experiments() -> dict[str, Path]:
    d = REPO / "experiments"
    return {p.stem: p for p in sorted(d.glob("*.py"))} if d.is_dir() else {}


def _first_doc_line(path: Path) -> str:
    text = path.read_text()
    for quote in ('"""', "'''"):
        if quote in text:
            doc = text.split(quote)[1].strip().splitlines()
            return doc[0] if doc else ""
    return ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="nhjax", description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_demo = sub.add_parser("demo", help="optimize the falling cat's somersault, then show it (numbers, figures)")
    p_demo.add_argument("--out", default="experiments/out", help="directory for figures and JSON")
    p_demo.add_argument("--no-figures", action="store_true")
    p_demo.add_argument("--holonomy", action="store_true",
                        help="instead: the torque-driven somersault along a closed-form holonomy loop")
    sub.add_parser("list", help="list scenes and experiments")
    p_run = sub.add_parser("run", help="run an experiment script from experiments/")
    p_run.add_argument("experiment")
    p_run.add_argument("args", nargs=argparse.REMAINDER)
    p_bench = sub.add_parser("bench", help="run the benchmarks (needs the [bench] extra)")
    p_bench.add_argument("args", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)

    if args.cmd == "demo":
        from .demos import optimal_somersault, somersault

        demo = somersault if args.holonomy else optimal_somersault
        demo(out=args.out, figures=not args.no_figures)
        return 0
    if args.cmd == "list":
        from .scenes import REGISTRY

        print("scenes (nhjax.scenes):")
        for name, (_, desc) in REGISTRY.items():
            print(f"  {name:24s} {desc}")
        exps = _experiments()
        print("experiments (nhjax run <name>):" if exps else "experiments: none found next to this install")
        for name, path in exps.items():
            print(f"  {name:24s} {_first_doc_line(path)}")
        return 0
    if args.cmd == "run":
        exps = _experiments()
        if args.experiment not in exps:
            known = ", ".join(exps) or "none"
            print(f"nhjax run: no experiment '{args.experiment}' (known: {known})", file=sys.stderr)
            return 2
        sys.argv = [str(exps[args.experiment]), *args.args]
        runpy.run_path(str(exps[args.experiment]), run_name="__main__")
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
