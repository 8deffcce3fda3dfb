"""MkDocs hook: tables generated at build time, so that they cannot drift from their source.

* ``<!-- bench:NAME -->`` in a page becomes the tables of the benchmark snapshot
  ``docs/benchmarks/data/NAME.json`` (copied from ``experiments/out/bench/`` by
  ``docs/benchmarks/snapshot.py``), each headed by the date, machine, load average and
  command of its run.
* ``<!-- scenes-table -->`` becomes the table of ``nhjax.scenes.REGISTRY``.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from mkdocs.exceptions import PluginError

DATA = Path(__file__).resolve().parents[1] / "benchmarks" / "data"
_BENCH = re.compile(r"<!-- bench:(\w+) -->")


def on_page_markdown(markdown, page, config, files):
    markdown = _BENCH.sub(lambda m: _bench(m.group(1)), markdown)
    if "<!-- scenes-table -->" in markdown:
        markdown = markdown.replace("<!-- scenes-table -->", _scenes())
    return markdown


def _scenes() -> str:
    from nhjax.scenes import REGISTRY

    rows = _head("scene", "what it models")
    for name, (cls, description) in REGISTRY.items():
        rows.append(f"| [`{name}`][{cls.__module__}.{cls.__qualname__}] | {description} |")
    return "\n".join(rows)


# ----------------------------------------------------------------- benchmarks
def _bench(name: str) -> str:
    path = DATA / f"{name}.json"
    if not path.is_file():
        raise PluginError(f"benchmarks page: no snapshot {path}; run the benchmark, then "
                          f"python docs/benchmarks/snapshot.py {name}")
    data = json.loads(path.read_text())
    try:
        tables = globals()[f"_table_{name}"](data)
    except KeyError as e:
        raise PluginError(f"benchmarks page: no table for {name} (or a field {e} missing from {path})") from None
    plot = DATA.parent / f"{name}.png"
    return tables + (f"\n\n![{name}: the benchmark's plot of this run](benchmarks/{name}.png)" if plot.is_file() else "")


def _run(meta) -> str:
    start, end = meta.get("load_average_start"), meta.get("load_average_end")
    load = (f"load average {start[0]:.2f} at the start, {end[0]:.2f} at the end" if start and end
            else "load not recorded")
    return (f"*Measured {meta['measured']} on {meta['platform']}, {meta['cpu_count']} cores; {load}; "
            f"`{meta['command']}`.*")


def _g(x, digits=3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return f"{x:.{digits}g}"


def _ms(seconds) -> str:
    return f"{seconds * 1e3:.3g} ms"


def _head(*columns) -> list[str]:
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]


def _table_batch_throughput(d) -> str:
    out = [_run(d["meta"]), "", *_head("workload", "members", "steps min / median / max", "nhjax defaults [traj/s]",
                                         "diagnostics off", "Numba prange", "defaults / Numba",
                                         "worst error nhjax / Numba")]
    for r in d["batches"]:
        out.append(f"| {r['workload']} | {r['batch']} | {r['steps_min']} / {r['steps_median']:g} / {r['steps_max']} "
                   f"| {r['defaults_traj_per_s']:.0f} | {r['lean_traj_per_s']:.0f} | {r['numba_traj_per_s']:.0f} "
                   f"| {r['defaults_vs_numba']:.2f}x | {_g(r['nhjax_worst_error'], 2)} / {_g(r['numba_worst_error'], 2)} |")
    s = d["single"]
    out += ["", "One trajectory of the same workload, after compile:", "",
            *_head("path", "time per solve", "error", "steps"),
            f"| `jax.jit` of `simulate` on its defaults | {_ms(s['jit_seconds'])} | {_g(s['jit_error'], 2)} | {s['steps']} |",
            f"| `jax.jit`, `saveat=2, track_work=False, diagnostics=False` | {_ms(s['jit_lean_seconds'])} "
            f"| {_g(s['jit_lean_error'], 2)} | {s['steps']} |",
            f"| eager `simulate()` (checks and diagnostics included) | {_ms(s['simulate_seconds'])} | | |",
            f"| Numba Dormand-Prince 5(4) | {_ms(s['numba_seconds'])} | {_g(s['numba_error'], 2)} | {s['numba_steps']} |"]
    g = d["gradients"]
    out += ["", f"Gradient of a terminal cost with respect to the two torque amplitudes (one forward solve "
            f"{_ms(g['forward_seconds'])}):", "",
            *_head("adjoint", "gradient / forward solve", "error against central differences", "compile")]
    for r in g["rows"]:
        if "unsupported" in r:
            out.append(f"| {r['adjoint']} | unsupported | | |")
        else:
            out.append(f"| {r['adjoint']} | {r['ratio_to_forward']:.2f}x | {_g(r['error_vs_fd'], 2)} "
                       f"| {r['compile_seconds']:.1f} s |")
    f = d["first_call"]
    out += ["", f"First `simulate()` of the cat in a fresh process: {f['first_call_s']:.2f} s with an empty "
            f"cache, {f['warm_first_call_s']:.2f} s with the stored programs (`import nhjax` apart: "
            f"{f['import_s']:.2f} s)."]
    return "\n".join(out)


def _table_compile_times(d) -> str:
    out = [_run(d["meta"]), "", *_head("scene or path", "first answer, empty cache (the other process)",
                                         "with the stored programs", "run after compile", "steps", "load average")]
    for r in d["rows"]:
        other = max(r["cold_runs_s"])
        steps = r["steps"] if r["steps"] and r["steps"] > 0 else ""
        load = r.get("load_average")
        load = f"{load[0]:.2f} -> {load[1]:.2f}" if load else ""
        out.append(f"| {r['scene']} | {r['first_call_s']:.2f} s ({other:.2f} s) | {r['warm_first_call_s']:.2f} s "
                   f"| {_ms(r['run_s'])} | {steps} | {load} |")
    return "\n".join(out)


def _table_impacts(d) -> str:
    out = [_run(d["meta"]), "", "1000 impacts at rtol = atol = 1e-10, after compile (medians of interleaved rounds); "
           "errors on the fixed floor against the closed form, on the vibrating table (chaotic) of each flight "
           "against the exact parabola's root from the solver's own previous impact:", "",
           *_head("case", "method", "impacts", "impact-time error [s]", "velocity error [m/s]", "time")]
    for r in d["rows"]:
        out.append(f"| {r['case']} | {r['method']} | {r['impacts']} | {_g(r['impact_time_error'], 2)} "
                   f"| {_g(r['velocity_error'], 2)} | {_ms(r['seconds'])} |")
    out += ["", "A batch of bouncers on the vibrating table (Gamma in [1.5, 4], 20 table periods, at most 200 "
            "impacts each), `simulate_impacts_batch` on both cores after compile:", "",
            *_head("members", "lanes per chunk", "time", "members/s", "impacts/s", "impact-time error [s]",
                   "loop iterations min / median / max")]
    for r in d["batch"]:
        it = r["loop_iterations"]
        out.append(f"| {r['members']} | {r['lanes']} | {r['seconds']:.2f} s | {r['members_per_second']:.0f} "
                   f"| {r['impacts_per_second']:.0f} | {_g(r['impact_time_error'], 2)} "
                   f"| {it['min']} / {it['median']:g} / {it['max']} |")
    out += ["", "One impact solve (`jax.jit` of `solve_impacts`, 64 impacts), JAX's persistent cache off: " +
            "; ".join(f"{name} traced and lowered in {c['trace_lower']:.2f} s, compiled in {c['compile']:.2f} s"
                      for name, c in d["compile"].items()) + "."]
    return "\n".join(out)
