"""Copy benchmark outputs into the docs tree, where the benchmarks page is generated from.

    python docs/benchmarks/snapshot.py [NAME ...]     (default: every experiments/out/bench/*.json)

``benchmarks/*.py`` write ``experiments/out/bench/NAME.json`` (not tracked by git). This
copies each into ``docs/benchmarks/data/NAME.json``, adding to its ``meta`` what the
page prints beside every figure when the benchmark did not record it: the date
(``measured``, from the file's modification time) and the machine (``platform``,
``cpu_count``: this machine's, so snapshot on the machine that ran the benchmark).
A benchmark that records no load average is printed with "load not recorded". The
benchmark's plot ``NAME.png``, if it wrote one, is copied to ``docs/benchmarks/NAME.png``
and shown under the tables.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "experiments" / "out" / "bench"
DATA = Path(__file__).resolve().parent / "data"


def snapshot(path: Path) -> Path:
    out = json.loads(path.read_text())
    if not isinstance(out, dict) or "meta" not in out:
        out = {"meta": {}, "rows": out} if isinstance(out, list) else {"meta": {}, **out}
    meta = out["meta"]
    meta.setdefault("measured", time.strftime("%Y-%m-%d %H:%M", time.localtime(path.stat().st_mtime)))
    meta.setdefault("platform", platform.platform())
    meta.setdefault("cpu_count", os.cpu_count())
    meta.setdefault("command", f"python benchmarks/{path.stem}.py")
    DATA.mkdir(exist_ok=True)
    target = DATA / path.name
    target.write_text(json.dumps(out, indent=1) + "\n")
    plot = path.with_suffix(".png")
    if plot.is_file():
        shutil.copy2(plot, DATA.parent / plot.name)
    return target


if __name__ == "__main__":
    names = sys.argv[1:]
    paths = [SOURCE / f"{n}.json" for n in names] if names else sorted(SOURCE.glob("*.json"))
    for p in paths:
        print(f"{p} -> {snapshot(p)}")
