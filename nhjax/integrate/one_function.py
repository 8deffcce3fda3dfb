"""Run a small program as one compiled function: a one-trip while loop XLA cannot remove.

Why. XLA's CPU runtime runs a program as a sequence of kernels ("thunks"). When a
sequence has more than 8 kernels and one of them touches a buffer over 512 bytes
(e.g. 101 saved states of a 5-state system), it runs them through a dataflow
executor that hands ready kernels to a thread pool. For a program of microseconds
that hand-off (waking a pool thread) can cost as much as the work: a jitted solve
with enough saved times to pass 512 bytes paid it on every call, whatever its
horizon (``benchmarks/batch_throughput.py`` times the cat's solve on defaults). The
thresholds are constants in XLA (``ThunkExecutor::Options``), with no flag.

What. ``xla_cpu_small_while_loop_byte_threshold`` (set by nhjax, see
``nhjax._xla_flags``) makes XLA compile a while loop whose body touches few bytes
into one function with no kernel dispatch inside. So the program is put in the body
of a while loop that runs once: its trip count is hidden from XLA behind an
optimization barrier (otherwise XLA unrolls a one-trip loop, or peels it), and the
body reads its inputs through the loop's carry behind a barrier too (otherwise XLA
hoists the loop-invariant body out of the loop).

Limits. XLA compiles such a loop as one function only without host callbacks
(equinox's runtime errors, progress bars), without LAPACK calls (``jnp.linalg``; see
``nhjax._linalg``) and below the byte threshold; otherwise the
loop is a while kernel around the same sequence (no gain, no loss). Reverse mode is
kept with a custom VJP that differentiates the unwrapped program (so whatever adjoint
the program uses, e.g. diffrax's checkpointed loops or ``DiscreteAdjoint``, does the
work); forward mode (``jax.jvp``) does not pass through a custom VJP, so callers
that need it (``diffrax.ForwardMode``) do not wrap.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.extend as jex
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax
from jax.custom_derivatives import SymbolicZero

__all__ = ["as_one_function", "under_differentiation"]

#: Substrings of the names of host-callback primitives (pure_callback, io_callback,
#: debug_callback, debug_print).
_CALLBACKS = ("callback", "debug_print")


def _has_callback(jaxpr) -> bool:
    """Whether ``jaxpr`` or any jaxpr nested in it calls back to the host."""
    for eqn in jaxpr.eqns:
        if any(c in eqn.primitive.name for c in _CALLBACKS):
            return True
        for sub in _subjaxprs(eqn.params):
            if _has_callback(sub):
                return True
    return False


def _subjaxprs(params):
    for v in params.values():
        for x in v if isinstance(v, (tuple, list)) else (v,):
            if isinstance(x, jex.core.ClosedJaxpr):
                yield x.jaxpr
            elif isinstance(x, jex.core.Jaxpr):
                yield x


def _zero(s):
    """The zero cotangent of an array of this shape and dtype."""
    if jnp.issubdtype(s.dtype, jnp.inexact):
        return jnp.zeros(s.shape, s.dtype)
    return np.zeros(s.shape, jax.dtypes.float0)


def under_differentiation(*trees) -> bool:
    """Whether a leaf of ``trees`` is a tracer of ``jax.jvp``, ``jax.vjp``, ``jax.grad``
    or ``jax.linearize`` (the outermost transformation at this point differentiates):
    then a solve gains nothing from ``as_one_function`` (its custom VJP's forward pass
    runs the unwrapped program, and forward mode does not pass through it), and
    wrapping it costs one more trace of the whole program."""
    return any(isinstance(x, _DIFF_TRACERS) for x in jtu.tree_leaves(trees))


try:  # JAX's tracer types of forward mode and of linearization (reverse mode)
    from jax._src.interpreters.ad import JVPTracer as _JVP
    from jax._src.interpreters.ad import LinearizeTracer as _LIN

    _DIFF_TRACERS: tuple = (_JVP, _LIN)
except ImportError:  # another JAX: always wrap, as before
    _DIFF_TRACERS = ()


def as_one_function(fn, *args):
    """``fn(*args)``, traced once, placed in a one-trip while loop (see the module
    docstring); differentiable in reverse mode. Arrays in ``args`` are the program's
    inputs, everything else is static. Returns what ``fn`` returns."""
    dyn, static = eqx.partition(args, eqx.is_array)
    flat_in, in_def = jtu.tree_flatten(dyn)

    def flat_fn(*flat):
        out = fn(*eqx.combine(jtu.tree_unflatten(in_def, flat), static))
        out_dyn, out_static = eqx.partition(out, eqx.is_array)
        flat_out, out_def = jtu.tree_flatten(out_dyn)
        box.append((out_def, out_static))
        return flat_out

    box = []
    closed, shapes = jax.make_jaxpr(flat_fn, return_shape=True)(*flat_in)
    out_def, out_static = box[0]
    # no gain with callbacks or effects; and a custom VJP cannot differentiate a traced
    # value the program closes over (a number in a user's lambda under an outer grad)
    if (closed.effects or _has_callback(closed.jaxpr)
            or any(isinstance(c, jax.core.Tracer) for c in closed.consts)):
        flat_out = jex.core.jaxpr_as_fun(closed)(*flat_in)
        return eqx.combine(jtu.tree_unflatten(out_def, flat_out), out_static)
    run = jex.core.jaxpr_as_fun(closed)
    shapes_in = [jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in flat_in]

    @jax.custom_vjp
    def once(flat):
        init = [jnp.zeros(s.shape, s.dtype) for s in shapes]
        trips = lax.optimization_barrier(jnp.int32(1))

        def body(carry):
            i, inputs, _ = carry
            i, inputs = lax.optimization_barrier((i, inputs))
            return i + 1, inputs, list(run(*inputs))

        return lax.while_loop(lambda c: c[0] < trips, body, (jnp.int32(0), flat, init))[2]

    def fwd(flat):
        # differentiate in the perturbed inputs only, as the unwrapped program would be
        # (custom VJPs inside it, e.g. DiscreteAdjoint's, refuse tangents elsewhere)
        values = [p.value for p in flat]
        which = [i for i, p in enumerate(flat) if p.perturbed]

        def of_perturbed(sub):
            full = list(values)
            for i, v in zip(which, sub):
                full[i] = v
            return list(run(*full))

        out, vjp = jax.vjp(of_perturbed, [values[i] for i in which])
        return out, (vjp, tuple(which))

    def bwd(res, cts):
        vjp, which = res
        cts = [_zero(s) if isinstance(c, SymbolicZero) else c for c, s in zip(cts, shapes)]
        (sub,) = vjp(cts)
        grads = [_zero(s) for s in shapes_in]
        for i, g in zip(which, sub):
            grads[i] = g
        return (grads,)

    once.defvjp(fwd, bwd, symbolic_zeros=True)
    flat_out = once(list(flat_in))
    return eqx.combine(jtu.tree_unflatten(out_def, flat_out), out_static)
