"""Vectorizable float64 sine and cosine for the batch path.

Why: XLA's CPU backend lowers a float64 ``sin``/``cos`` to a call of the C
library's scalar routine for every element. A call inside a fused loop keeps
LLVM from vectorizing the whole loop, and the calls themselves cost 10-20 ns
each: profiled on the falling cat batch (perf, 4096 members), ``__sin_fma`` and
``__sincos_fma`` took 40 % of the time. The same functions written with
elementwise arithmetic fuse and vectorize with everything around them.

How (the fdlibm method, Sun Microsystems 1993): reduce x to r = x - k pi/2 with
k = round(2x/pi), pi/2 split into three 33-bit pieces and a tail (Cody & Waite),
so that k * piece is exact for |k| < 2^20; then the fdlibm kernel polynomials
for sin r and cos r on |r| <= pi/4, and the quadrant k mod 4 picks the result.
Accuracy: within 1 ulp of glibc for |x| <= ``LIMIT`` (tests/test_fast_trig.py).

Beyond ``LIMIT`` = 2^19 pi/2 (about 8.2e5 rad) the reduction is no longer exact,
so ``with_fast_trig`` reports it: the function it returns gives a flag that is
True when any argument of a replaced sin/cos exceeded ``LIMIT`` (or was inf), and
the caller re-runs with the library functions.

The same rewrite of the lock-step body also turns every concatenation along the
last axis of arrays of two or more axes into one along the first: a vector field
vmapped over the lanes builds its state derivative as ``[lanes, n]`` pieces joined
along n (jax's concatenate batching rule puts the batch axis first), which XLA's
CPU loop emitter computes component by component across the short minor axis;
joined along the first axis (``[n, lanes]``, the lock-step layout) each component
is one contiguous vector over the lanes (same values: a pure rearrangement).
"""

from __future__ import annotations

import jax
import jax.extend.core as jex
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax

__all__ = ["LIMIT", "cos", "sin", "with_fast_trig"]

_INVPIO2 = 6.36619772367581382433e-01
_PIO2_1 = 1.57079632673412561417e00  # first 33 bits of pi/2
_PIO2_2 = 6.07710050630396597660e-11  # next 33 bits
_PIO2_3 = 2.02226624871116645580e-21  # next 33 bits
_PIO2_3T = 8.47842766036889956997e-32  # pi/2 - (PIO2_1 + PIO2_2 + PIO2_3)
_S = (-1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04,
      2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10)
_C = (4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05,
      -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11)

#: Largest |x| for which the reduction is exact (|k| < 2^20 with margin).
LIMIT = float(2**19 * np.pi / 2)


def _reduce(x):
    """k mod 4 and r = rhi + rlo = x - k pi/2 (|r| <= pi/4, error ~ 2^-100 |x|)."""
    k = jnp.round(x * _INVPIO2)
    r = x - k * _PIO2_1  # exact (Sterbenz)
    r = r - k * _PIO2_2
    w = k * _PIO2_3
    rhi = r - w
    rlo = ((r - rhi) - w) - k * _PIO2_3T
    q = jnp.where(jnp.isfinite(k), k, 0.0).astype(jnp.int64) & 3
    return q, rhi, rlo


def _kernels(rhi, rlo):
    """fdlibm __kernel_sin and __kernel_cos of rhi + rlo."""
    z = rhi * rhi
    ps = _S[5]
    for c in _S[4::-1][:-1]:
        ps = ps * z + c
    v = z * rhi
    s = rhi - ((z * (0.5 * rlo - v * ps) - rlo) - v * _S[0])
    pc = _C[5]
    for c in _C[4::-1]:
        pc = pc * z + c
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + (z * z * pc - rhi * rlo))
    return s, c


def sin(x):
    """sin x for float64 x, elementwise, vectorizable; exact reduction for |x| <= LIMIT."""
    q, rhi, rlo = _reduce(x)
    s, c = _kernels(rhi, rlo)
    out = jnp.where(q == 0, s, jnp.where(q == 1, c, jnp.where(q == 2, -s, -c)))
    return jnp.where(x == 0, x, out)  # keeps the sign of -0.0


def cos(x):
    """cos x for float64 x, elementwise, vectorizable; exact reduction for |x| <= LIMIT."""
    q, rhi, rlo = _reduce(x)
    s, c = _kernels(rhi, rlo)
    return jnp.where(q == 0, c, jnp.where(q == 1, -s, jnp.where(q == 2, -c, s)))


_REPLACE = {lax.sin_p: sin, lax.cos_p: cos}
# Call-like primitives whose body is inlined (their custom derivative rules are not
# needed: the batch path runs forward only).
_INLINE = {"jit": "jaxpr", "pjit": "jaxpr", "closed_call": "call_jaxpr", "core_call": "call_jaxpr",
           "custom_jvp_call": "call_jaxpr", "custom_vjp_call": "call_jaxpr", "remat": "jaxpr",
           "checkpoint": "jaxpr"}


def _merge(acc, new):
    """Running maxima of |sin/cos arguments| by argument shape: acc and new combined."""
    acc = dict(acc)
    for shape, m in new.items():
        acc[shape] = jnp.maximum(acc[shape], m) if shape in acc else m
    return acc


def _eval(jaxpr, consts, args, acc, trig=True):
    """Evaluate ``jaxpr`` with sin/cos replaced (if ``trig``) and minor-axis concatenations
    done along the major axis; ``acc`` maps an argument shape to the running elementwise
    max of |argument| (NaN counted as 0): an elementwise update that fuses with the
    computation, reduced once at the end."""
    env = {}

    def read(v):
        return v.val if isinstance(v, jex.Literal) else env[v]

    def write(v, val):
        if not isinstance(v, jex.DropVar):
            env[v] = val

    for v, c in zip(jaxpr.constvars, consts):
        write(v, c)
    for v, a in zip(jaxpr.invars, args):
        write(v, a)
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        prim = eqn.primitive
        key = _INLINE.get(prim.name)
        if trig and prim in _REPLACE and eqn.outvars[0].aval.dtype == jnp.float64:
            x = invals[0]
            acc = _merge(acc, {jnp.shape(x): jnp.where(jnp.isnan(x), 0.0, jnp.abs(x))})
            outs = [_REPLACE[prim](x)]
        elif prim.name == "scan":
            outs, acc = _eval_scan(eqn, invals, acc, trig)
        elif (prim.name == "concatenate" and len(invals) > 1 and jnp.ndim(invals[0]) >= 2
              and eqn.params["dimension"] == jnp.ndim(invals[0]) - 1):
            joined = jnp.concatenate([jnp.moveaxis(x, -1, 0) for x in invals], axis=0)
            outs = [jnp.moveaxis(joined, 0, -1)]
        elif key is not None and key in eqn.params:
            inner = eqn.params[key]
            if isinstance(inner, jex.ClosedJaxpr):
                outs, acc = _eval(inner.jaxpr, inner.consts, invals, acc, trig)
            else:
                outs, acc = _eval(inner, (), invals, acc, trig)
        else:
            params = prim.get_bind_params(eqn.params)
            with eqn.ctx.manager:
                outs = prim.bind(*invals, **params)
            if not prim.multiple_results:
                outs = [outs]
        for v, o in zip(eqn.outvars, outs):
            write(v, o)
    return [read(v) for v in jaxpr.outvars], acc


def _eval_scan(eqn, invals, acc, trig=True):
    """A lax.scan whose body has sin/cos replaced; the running maxima of their
    arguments travel through the loop as extra carries (an RKMK stage scan holds the
    vector field of large systems)."""
    p = eqn.params
    body, nc, ncarry = p["jaxpr"], p["num_consts"], p["num_carry"]
    consts, init, xs = invals[:nc], invals[nc:nc + ncarry], invals[nc + ncarry:]

    def run(carry, x, acc_in):
        outs, acc_new = _eval(body.jaxpr, body.consts, [*consts, *carry, *(x or ())], {}, trig)
        return outs[:ncarry], outs[ncarry:], _merge(acc_in, acc_new)

    x_struct = [jax.ShapeDtypeStruct(a.shape[1:], a.dtype) for a in xs]
    c_struct = [jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)) for a in init]
    acc_shapes = jax.eval_shape(lambda c, x: run(c, x, {})[2], c_struct, x_struct)
    acc0 = {k: jnp.zeros(v.shape, v.dtype) for k, v in acc_shapes.items()}

    def f(carry_acc, x):
        carry, acc_in = carry_acc
        c, y, acc_out = run(carry, x, acc_in)
        return (c, acc_out), y

    (carry, acc_scan), ys = jax.lax.scan(f, (list(init), acc0), list(xs) if xs else None,
                                         length=p["length"], reverse=p["reverse"], unroll=p["unroll"])
    return [*carry, *ys], _merge(acc, acc_scan)


def with_fast_trig(fn, *example_args, trig=True):
    """``fn`` with every float64 sin/cos outside while loops and conditionals replaced by the
    vectorizable versions above (also inside lax.scan bodies; ``trig=False``: not
    replaced), and minor-axis concatenations done along the major axis (module
    docstring). Returns ``g`` with ``g(*args) == (fn(*args), bad)``;
    ``bad`` is True when some replaced call had an argument beyond ``LIMIT`` or infinite
    (then the outputs are inaccurate: run ``fn`` instead). sin/cos inside while loops
    and conditionals are left alone. Forward use only (derivatives are not defined)."""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example_args)
    out_tree = jtu.tree_structure(out_shape)

    def g(*args):
        outs, acc = _eval(closed.jaxpr, closed.consts, jtu.tree_leaves(args), {}, trig)
        bad = jnp.zeros((), bool)
        for m in acc.values():
            bad = bad | jnp.any(~(m <= LIMIT))
        return jtu.tree_unflatten(out_tree, outs), bad

    return g
