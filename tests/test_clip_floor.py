"""diffrax's end-of-interval threshold in closed form (nhjax/integrate/clip_floor.py):
the same floats as equinox's chain of prevbefore calls, bit for bit, for every input;
the chain leaves compiled programs; a solve takes the same steps with or without it."""

import contextlib
import threading

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

import nhjax
from nhjax.integrate import adjoint, clip_floor
from nhjax.scenes import FallingCat

N = 100
_EQUINOX = eqxi.prevbefore


@jax.jit
def _equinox_chain(x):
    """Equinox's prevbefore applied 1 .. N times: (N, len(x)). A scan: the same calls
    one after the other, without the unrolled chain's compile (tens of seconds)."""
    def step(x, _):
        x = _EQUINOX(x)
        return x, x

    return jax.lax.scan(step, x, None, length=N)[1]


@jax.jit
def _closed_form(x):
    return clip_floor.prev_floats(x[None, :], jnp.arange(1, N + 1)[:, None])


def _bits(a):
    return np.asarray(a).view(np.int64)


TINY, MAX = np.finfo(float).tiny, np.finfo(float).max
SPECIAL = [0.0, -0.0, 5e-324, -5e-324, 1e-310, TINY, -TINY, np.nextafter(TINY, 1), TINY * (1 + 50 * 2**-52),
           np.inf, -np.inf, np.nan, 1.0, -1.0, MAX, -MAX, np.nextafter(-MAX, 0), -np.nextafter(-MAX, 0) * 1]


def test_special_values_bit_for_bit():
    # zero and the subnormals step to -tiny (XLA's CPU reads subnormals as zero); a
    # positive number near tiny passes through the subnormals to -tiny; -inf stays
    x = np.array(SPECIAL, float)
    np.testing.assert_array_equal(_bits(_closed_form(x)), _bits(_equinox_chain(x)))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, allow_subnormal=True), min_size=len(SPECIAL), max_size=len(SPECIAL)))  # one compile for both tests
def test_any_float_bit_for_bit(values):
    x = np.array(values, float)
    np.testing.assert_array_equal(_bits(_closed_form(x)), _bits(_equinox_chain(x)))


def test_derivative_is_one_as_equinox():
    assert jax.grad(lambda t: clip_floor.prev_floats(t, 100))(2.0) == 1.0
    with clip_floor.collapsed_prevbefore():
        assert jax.grad(lambda t: eqxi.prevbefore(eqxi.prevbefore(t)))(2.0) == 1.0


def _chain(t):
    for _ in range(N):
        t = eqxi.prevbefore(t)
    return t


def _instructions(fn, *args):
    # (a new function each time: jax.jit would reuse an earlier trace of fn)
    text = jax.jit(lambda *a: fn(*a)).lower(*args).compile().as_text()
    return sum(" = " in line for line in text.splitlines())


def test_the_chain_leaves_the_compiled_program():
    long = _instructions(_chain, 3.0)
    with clip_floor.collapsed_prevbefore():
        short = _instructions(_chain, 3.0)
        value = jax.jit(lambda t: _chain(t))(3.0)
    assert short < 60 < 10 * 60 < long, (short, long)
    assert _bits(value) == _bits(jax.jit(_chain)(3.0)) == _bits(3.0) - N
    assert eqxi.prevbefore is _EQUINOX  # put back


def test_the_chain_is_traced_once(monkeypatch):
    """The 100 links are calls of one nested jit: prev_floats's body is traced once, not
    100 times (a solve's tracing, which no compilation cache stores, is part of the
    time to a first answer)."""
    body, traces = clip_floor.prev_floats.fun, []
    monkeypatch.setattr(clip_floor.prev_floats, "fun", lambda *a: traces.append(1) or body(*a))
    with clip_floor.collapsed_prevbefore():
        out = jax.jit(_chain)(jnp.full((7,), 3.0))  # a shape no other test traces
    assert len(traces) == 1
    assert (_bits(out) == _bits(3.0) - N).all()


def test_nested_and_concurrent_uses_put_equinox_back_once_all_leave():
    inside = threading.Event()
    leave = threading.Event()

    def other():
        with clip_floor.collapsed_prevbefore():
            inside.set()
            leave.wait(10)

    th = threading.Thread(target=other)
    th.start()
    inside.wait(10)
    with clip_floor.collapsed_prevbefore():
        with clip_floor.collapsed_prevbefore():
            assert eqxi.prevbefore is clip_floor._prevbefore
        assert eqxi.prevbefore is clip_floor._prevbefore
    assert eqxi.prevbefore is clip_floor._prevbefore  # the other thread is still inside
    leave.set()
    th.join()
    assert eqxi.prevbefore is _EQUINOX
    assert not clip_floor._RESULTS


def test_a_solve_takes_the_same_steps_without_the_chain(monkeypatch):
    # the cat under torques to t1 = 7.3 with 53 saved times; then the same solve with
    # equinox's chain traced as diffrax wrote it: every float of the results agrees
    cat = FallingCat()
    x0 = cat.initial_state(1.0, chi=0.2, theta_dot=0.3, chi_dot=-0.4)

    def u(t, x):
        return jnp.stack([0.3 * jnp.sin(2 * t), 0.2 * jnp.cos(3 * t)])

    def run():
        tr = jax.jit(lambda x: nhjax.simulate(cat, x, 7.3, control=u, rtol=1e-9, atol=1e-9, saveat=53,
                                              diagnostics=False))(x0)
        return np.asarray(tr.xs), np.asarray(tr.ts), int(tr.num_steps)

    xs, ts, steps = run()
    monkeypatch.setattr(adjoint, "collapsed_prevbefore", contextlib.nullcontext)
    xs0, ts0, steps0 = run()
    assert steps == steps0 > 20
    np.testing.assert_array_equal(xs, xs0)
    np.testing.assert_array_equal(ts, ts0)
