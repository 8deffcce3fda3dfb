"""The batch path's vectorizable float64 sin/cos (nhjax/integrate/fast_trig.py): accuracy
against the C library, the worst cases of the argument reduction, special values, and
the jaxpr rewrite that puts them in place (and flags arguments beyond its exact range)."""

import jax
import jax.numpy as jnp
import numpy as np

from nhjax.integrate import fast_trig as ft

SIN, COS = jax.jit(ft.sin), jax.jit(ft.cos)


def _ulps(a, ref):
    return np.max(np.abs(a - ref) / np.spacing(np.maximum(np.abs(ref), np.finfo(float).tiny)))


def test_within_one_ulp_of_libm_over_the_exact_range():
    rng = np.random.default_rng(0)
    for scale in (1e-5, 1.0, 4.0, 100.0, 1e4, ft.LIMIT):
        x = rng.uniform(-scale, scale, 100_000)
        assert _ulps(np.asarray(SIN(x)), np.sin(x)) <= 1.0, scale
        assert _ulps(np.asarray(COS(x)), np.cos(x)) <= 1.0, scale


def test_worst_cases_of_the_reduction():
    # the doubles nearest to multiples of pi/2, where x - k pi/2 cancels most
    k = np.arange(-(2**19), 2**19, 5, dtype=float)
    near = k * (np.pi / 2)
    for x in (near, np.nextafter(near, np.inf), np.nextafter(near, -np.inf)):
        assert _ulps(np.asarray(SIN(x)), np.sin(x)) <= 1.0
        assert _ulps(np.asarray(COS(x)), np.cos(x)) <= 1.0


def test_special_values():
    x = jnp.array([0.0, -0.0, 5e-324, -1e-300, np.nan, np.inf, -np.inf])
    s, c = np.asarray(SIN(x)), np.asarray(COS(x))
    np.testing.assert_array_equal(s[:4], np.sin(np.asarray(x[:4])))
    assert np.signbit(s[1]) and not np.signbit(s[0])
    np.testing.assert_array_equal(c[:4], 1.0)
    assert np.all(np.isnan(s[4:])) and np.all(np.isnan(c[4:]))


def test_rewrite_replaces_nested_calls_and_flags_large_arguments():
    @jax.jit
    def inner(x):
        return jnp.sin(x) * jnp.cos(2 * x)

    def f(x, y, w):
        z = inner(x) + jax.nn.softplus(jnp.sin(y))  # custom_jvp inside
        scanned = jax.lax.scan(lambda c, a: (c + jnp.cos(a * c), jnp.sin(c)), w, x[:8])  # replaced
        looped = jax.lax.while_loop(lambda a: a[0] < 3, lambda a: (a[0] + 1, a[1] + jnp.sin(a[1])), (0, y))[1]
        return z, scanned, looped  # the while loop's sin is left to libm

    x, y, w = jnp.linspace(-3.0, 3.0, 64), jnp.linspace(0.1, 2.0, 64), jnp.linspace(-1.0, 1.0, 64)
    g = jax.jit(with_fast := ft.with_fast_trig(f, x, y, w))
    out, bad = g(x, y, w)
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(f(x, y, w))):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14)
    assert not bool(bad)
    jaxpr = str(jax.make_jaxpr(with_fast)(x, y, w))
    assert jaxpr.count(" sin ") == 1  # only the one inside the while loop is left
    assert " cos " not in jaxpr
    for big in (ft.LIMIT * 1.01, np.inf, -1e9):
        assert bool(g(x.at[5].set(big), y, w)[1])
    assert bool(g(x, y, w.at[3].set(1e9))[1])  # beyond the range inside the scan body only
    assert not bool(g(x.at[5].set(np.nan), y, w)[1])  # NaN stays NaN, no re-run needed
