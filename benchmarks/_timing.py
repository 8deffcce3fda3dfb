"""The one timing loop of the benchmarks (median wall time of a jax call), and the wait
for nhjax's background compiles before timing calls "after compile"."""

import time

import jax
import numpy as np


def median_time(fn, repeats=5, min_total=0.3, max_repeats=200):
    """Median seconds of ``fn()`` (waited for with ``jax.block_until_ready``) over at
    least ``repeats`` calls, more while they add up to less than ``min_total`` seconds,
    at most ``max_repeats``."""
    ts, start = [], time.perf_counter()
    while len(ts) < repeats or (time.perf_counter() - start < min_total and len(ts) < max_repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def settle():
    """Wait for nhjax's background work on programs (``nhjax._programs.settle``), so that
    calls timed after a first one measure the solver with all its programs (a first
    ``solve_direct_newton`` leaves its Hessian's program to a background thread)."""
    from nhjax import _programs

    _programs.settle()
