"""Closed-loop MPC (issue 42): the two experiments, run by ``make bench`` with their
defaults, outputs under experiments/out/bench/.

* ``mpc_sphere``: the spherical robot tracks a figure-eight by real-time-iteration
  MPC (horizon 1 s, 20 intervals, a push at 5 s, top 10 % heavier than the model),
  against the same controller written with CasADi + IPOPT in the same run: per-period
  solve times, closed-loop costs, tracking error after the push
  (``mpc_sphere/mpc_sphere.json``).
* ``mpc_cat``: 256 perturbed falling cats (inertias +-10 % between model and plant)
  land turned by pi: success rate, attitude errors, and the batch of 256 closed loops
  against a timed sample of the same loops run one by one (``mpc_cat/mpc_cat.json``).

Each experiment writes its own figures and JSON (with the load average); this script
runs them and prints the JSON's headline fields. Arguments: the experiments to run
(default both); other settings are the experiments' own (``nhjax run mpc_cat --help``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from nhjax.cli import run_experiment

HERE = Path(__file__).resolve().parent
OUT = HERE.parent / "experiments" / "out" / "bench"

#: (experiment, the fields of its JSON printed here)
RUNS = {
    "mpc_sphere": ("period_ms_median", "period_ms_max", "casadi_period_ms_median", "closed_loop_cost",
                   "casadi_closed_loop_cost", "tracking_error_after_push_m", "load_average"),
    "mpc_cat": ("success_rate", "final_attitude_error_deg_max", "batch_seconds", "sequential_seconds",
                "load_average"),
}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    unknown = [a for a in argv if a not in RUNS]
    if unknown:
        raise SystemExit(f"mpc.py: unknown experiments {unknown}; choose from {list(RUNS)}")
    for name in argv or list(RUNS):
        out = OUT / name
        print(f"--- nhjax run {name} --out {out}", flush=True)
        run_experiment(name, ["--out", str(out)])
        result = json.loads((out / f"{name}.json").read_text())
        print(json.dumps({k: result.get(k) for k in RUNS[name]}, indent=1), flush=True)


if __name__ == "__main__":
    main()
