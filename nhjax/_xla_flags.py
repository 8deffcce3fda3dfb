"""One XLA setting nhjax makes for the process: small while loops as one function.

XLA's CPU runtime runs a compiled program as a sequence of kernels ("thunks"),
and a ``while`` loop as that sequence once per iteration. A time-stepping loop
over a few numbers -- one trajectory of a small system, a per-step VJP of the
discrete adjoint, a lock-step batch step of some tens of lanes -- is then
~30-300 small kernels per step, each paying the runtime's dispatch (and, for
kernels that may run concurrently, a hand-off to its thread pool). XLA also has
a pass that compiles a whole while loop into one function when the bytes its body
reads and writes per iteration (XLA's cost analysis) are below
``xla_cpu_small_while_loop_byte_threshold`` (an ``xla_backend_extra_options``
entry; XLA's default is 1024 bytes, which almost no ODE loop meets; loops with a
scatter, sort or custom call are never hoisted). nhjax raises it to 1 MiB: a
single trajectory then runs as one compiled loop (about twice as fast as kernel by
kernel), and so does the lock-step batch's stepping loop up to ~128 lanes of a
small system (the batch's default lane counts stay there; this needs its vector
fields in lanes-last layout, see fast_trig.py: with component-by-component
concatenations the one-function loop ran slower than the kernels).

XLA reads XLA_FLAGS once, when JAX initialises its CPU backend, so the setting only
takes effect if ``import nhjax`` comes before the first JAX computation of the
process; otherwise a warning says so. Set ``NHJAX_SMALL_LOOP_BYTES=0`` to leave
XLA's default alone, or another number of bytes; an
``xla_cpu_small_while_loop_byte_threshold`` already in XLA_FLAGS is kept as it is.
"""

from __future__ import annotations

import os
import warnings

KEY = "xla_cpu_small_while_loop_byte_threshold"
DEFAULT_BYTES = 1 << 20
_OPTION = "--xla_backend_extra_options="


def merged_flags(flags: str, nbytes: int) -> str:
    """XLA_FLAGS ``flags`` with ``KEY=nbytes`` added to its xla_backend_extra_options
    (created if absent; a KEY already there is left as it is)."""
    if KEY in flags:
        return flags
    tokens = flags.split()
    for i, tok in enumerate(tokens):
        if tok.startswith(_OPTION):
            rest = tok[len(_OPTION):]
            tokens[i] = f"{_OPTION}{rest},{KEY}={nbytes}" if rest else f"{_OPTION}{KEY}={nbytes}"
            return " ".join(tokens)
    return " ".join(tokens + [f"{_OPTION}{KEY}={nbytes}"])


def configure(environ=os.environ) -> str:
    """Add the small-loop threshold to ``environ["XLA_FLAGS"]``. Returns what was done:
    "set", "off" (NHJAX_SMALL_LOOP_BYTES=0), "user" (already in XLA_FLAGS) or "late"
    (JAX's backend was already running: the setting cannot apply, a warning is given)."""
    raw = environ.get("NHJAX_SMALL_LOOP_BYTES", str(DEFAULT_BYTES)).strip()
    try:
        nbytes = int(raw)
    except ValueError:
        raise ValueError(f"NHJAX_SMALL_LOOP_BYTES must be a number of bytes (0 = off), got {raw!r}") from None
    if nbytes <= 0:
        return "off"
    flags = environ.get("XLA_FLAGS", "")
    if KEY in flags:
        return "user"
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        warnings.warn(
            "nhjax was imported after JAX's backend started, so XLA keeps compiling small "
            "time-stepping loops kernel by kernel (single trajectories and batches run slower "
            "on the CPU). "
            "Import nhjax before the first JAX computation, or set "
            f"XLA_FLAGS='{_OPTION}{KEY}={nbytes}' before starting Python.",
            stacklevel=3,
        )
        return "late"
    environ["XLA_FLAGS"] = merged_flags(flags, nbytes)
    return "set"
