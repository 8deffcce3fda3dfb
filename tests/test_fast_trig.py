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


def test_minor_axis_concatenations_of_a_vmapped_field_are_joined_along_the_major_axis():
    """A vector field vmapped over lanes joins its [lanes, k] pieces along the last axis;
    the rewrite joins them along the first instead (lock-step layout) with the same
    values, with and without the sine replacement, also inside a scan body."""

    def field(x):
        s = jnp.sin(x[0])
        return jnp.concatenate([x[2:], jnp.stack([s * x[1], jnp.cos(x[1]) - x[0]])])

    def f(X):  # X [4, L]: lanes last, as in the lock-step loop
        out = jax.vmap(field, in_axes=1, out_axes=1)(X)
        scanned = jax.lax.scan(lambda c, _: (jax.vmap(field, in_axes=1, out_axes=1)(c), None), X, None, length=3)[0]
        return out, scanned

    X = jnp.stack([jnp.linspace(-2.0, 2.0, 16), jnp.linspace(0.5, 1.5, 16),
                   jnp.linspace(-1.0, 0.0, 16), jnp.linspace(3.0, 4.0, 16)])
    assert "dimension=1" in str(jax.make_jaxpr(f)(X))  # jax's batching rule: the minor axis
    for trig in (False, True):
        g = ft.with_fast_trig(f, X, trig=trig)
        jaxpr = str(jax.make_jaxpr(g)(X))
        assert "concatenate[dimension=1]" not in jaxpr and "concatenate[dimension=0]" in jaxpr
        assert (" sin " in jaxpr) == (not trig)
        out, bad = jax.jit(g)(X)
        for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(f(X))):
            np.testing.assert_allclose(a, b, rtol=0 if not trig else 1e-14, atol=0 if not trig else 1e-14)
        assert not bool(bad)
