"""diffrax's end-of-interval threshold without a 100-link chain in every compiled solve.

Before its stepping loop, ``diffrax.diffeqsolve`` computes the time within which a
step is rounded to the end of the interval, t1 stepped 100 floats down, by calling
``equinox.internal.prevbefore`` 100 times in sequence (diffrax/_integrate.py,
``loop``). t1 is an argument of nhjax's programs (a new horizon does not compile
again), so the chain is not folded: each link is a bitwise nextafter of about 17
operations, and XLA compiles all of them as one long straight-line kernel for every
diffrax loop in a program (a first ``simulate()`` holds one such loop, a
Pontryagin solve two); the README's ``compile_times`` section has the measured cost.

``collapsed_prevbefore()`` (entered around nhjax's ``diffeqsolve`` calls while
they are traced) puts in its place a function with the same values that
remembers which of its results came from which start: called on its own k-th
result it returns the (k+1)-th float below the start in one closed form
(``prev_floats``). The 99 intermediate results are then unused and dropped from
the program, and the threshold is a handful of integer operations. Every value
is equinox's, including its rules at zero (``-tiny``), for subnormals (XLA's CPU
treats them as zero) and at -inf, so the solves take exactly the same steps
(``tests/test_clip_floor.py`` compares the two bit for bit and the solves'
results).
"""

from __future__ import annotations

import contextlib
import threading

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["prev_floats", "collapsed_prevbefore"]


def _int_type(dtype):
    return {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[np.dtype(dtype).itemsize]


@jax.custom_jvp
def prev_floats(x, n):
    """``n`` successive ``equinox.internal.prevbefore`` of ``x`` (n >= 1, an integer):
    x stepped n floats towards -inf, where zero and the subnormals (zero on XLA's CPU)
    step to -tiny, the smallest normal number below zero, and -inf stays -inf. The
    derivative is 1, as equinox's."""
    x = jnp.asarray(x)
    itype = _int_type(x.dtype)
    info = jnp.finfo(x.dtype)

    def bits(v):
        return jax.lax.bitcast_convert_type(jnp.asarray(v, x.dtype), itype)

    b = bits(x)
    n = jnp.asarray(n, itype)
    tiny, neg_tiny, neg_inf = bits(info.tiny), bits(-info.tiny), bits(-jnp.inf)
    # (signed integers: a negative float's bits grow, and its magnitude with them, by one
    # per step away from zero, up to -inf's)
    # from zero or a subnormal: -tiny, then n - 1 floats further down
    from_zero = jnp.minimum(neg_tiny + (n - 1), neg_inf)
    # positive normal: down to the largest subnormal in j steps, then as from zero
    j = b - tiny + 1
    positive = jnp.where(n <= j, b - n, jnp.minimum(neg_tiny + (n - j - 1), neg_inf))
    negative = jnp.minimum(b + n, neg_inf)
    out = jnp.where(x >= info.tiny, positive, jnp.where(x <= -info.tiny, negative, from_zero))
    out = jax.lax.bitcast_convert_type(out, x.dtype)
    return jnp.where(jnp.isnan(x), jnp.nan, out)  # (a NaN comes back as the quiet NaN, as from equinox)


@prev_floats.defjvp
def _prev_floats_jvp(primals, tangents):
    x, n = primals
    return prev_floats(x, n), tangents[0]


# a nested jit with the count an argument: the 100 links of a chain are traced once
# (not 100 times) and XLA inlines the calls, then drops the 99 unused ones
_prev_floats_nested = jax.jit(prev_floats)

_RESULTS: dict = {}  # id(result) -> (result, start, k): result = prev_floats(start, k)
_LOCK = threading.Lock()
_DEPTH = 0
_EQUINOX = eqxi.prevbefore


def _prevbefore(x):
    """``equinox.internal.prevbefore(x)``, by ``prev_floats`` from the chain's start when
    ``x`` is one of this function's own results."""
    known = _RESULTS.get(id(x))
    start, k = (known[1], known[2] + 1) if known is not None and known[0] is x else (x, 1)
    out = _prev_floats_nested(start, k)
    _RESULTS[id(out)] = (out, start, k)
    return out


@contextlib.contextmanager
def collapsed_prevbefore():
    """``equinox.internal.prevbefore`` replaced by ``_prevbefore`` (same values) for the
    duration: for tracing ``diffrax.diffeqsolve``. Nested and concurrent uses (solves
    traced in several threads) share one replacement, put back by the last to leave;
    a trace in another thread meanwhile gets the same values from it."""
    global _DEPTH
    with _LOCK:
        _DEPTH += 1
        if _DEPTH == 1:
            eqxi.prevbefore = _prevbefore
    try:
        yield
    finally:
        with _LOCK:
            _DEPTH -= 1
            if _DEPTH == 0:
                eqxi.prevbefore = _EQUINOX
                _RESULTS.clear()
