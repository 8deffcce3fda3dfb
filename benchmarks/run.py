"""`make bench` / `nhjax bench`: regenerate every benchmark table and plot.

Each benchmark is a script in this directory with a main(); they share one
process so that peers and nhjax are measured in the same run on one machine.
"""

import runpy
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
BENCHMARKS = ["cat_work_precision", "scene_work_precision", "batch_throughput", "compile_times", "rolling_work_precision", "somersault_peer", "steering_peer", "long_run", "impacts", "reduction_work_precision", "ocp_batch", "rkmk87_work_precision", "mpc"]

if __name__ == "__main__":
    chosen = sys.argv[1:] or BENCHMARKS
    unknown = [name for name in chosen if name not in BENCHMARKS]
    if unknown:
        raise SystemExit(f"nhjax bench: unknown benchmarks {unknown}; known: {', '.join(BENCHMARKS)}")
    for name in chosen:
        print(f"=== {name}")
        # each script reads its own options from sys.argv: none here (its full run), not
        # the names of the benchmarks chosen
        sys.argv = [str(HERE / f"{name}.py")]
        runpy.run_path(sys.argv[0], run_name="__main__")
