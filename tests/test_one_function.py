"""A solve's program as one compiled function (nhjax/integrate/one_function.py): the same
numbers and derivatives as the unwrapped program, and the structure XLA needs to run it
without its thread-pool hand-offs (no host callback in the solve, few top-level kernels)."""

import dataclasses

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
import sys
from nhjax.integrate.one_function import as_one_function
from nhjax.scenes import FallingCat

S = sys.modules["nhjax.integrate.simulate"]  # the module (nhjax.integrate.simulate is the function)
CAT = FallingCat(lam=0.4)
CTRL = nhjax.Sinusoids([0.0, 0.0], [0.3, 0.2], [2.0, 3.0], [0.0, np.pi / 2])


def _toy(x, k, scale):
    """Floats and integers in and out, a loop inside (what a solve looks like)."""
    y = jax.lax.fori_loop(0, 5, lambda i, v: jnp.sin(v) * scale + i, x) + k
    return {"y": y, "n": k * 2, "tag": "static"}


def test_values_and_reverse_derivatives_equal_the_unwrapped_program():
    x, k, scale = jnp.linspace(0.1, 1.0, 80), jnp.int32(5), jnp.asarray(1.3)
    out = eqx.filter_jit(lambda *a: as_one_function(_toy, *a))(x, k, scale)
    ref = eqx.filter_jit(_toy)(x, k, scale)
    assert out["tag"] == "static" and int(out["n"]) == 10
    np.testing.assert_array_equal(out["y"], ref["y"])

    def loss(f, x, scale):
        return jnp.sum(f(x, k, scale)["y"] ** 2)

    wrapped = jax.grad(lambda x, s: loss(lambda *a: as_one_function(_toy, *a), x, s), argnums=(0, 1))(x, scale)
    plain = jax.grad(lambda x, s: loss(_toy, x, s), argnums=(0, 1))(x, scale)
    np.testing.assert_allclose(wrapped[0], plain[0], rtol=1e-14)
    np.testing.assert_allclose(wrapped[1], plain[1], rtol=1e-14)
    # only the scale perturbed: x and k get no tangent inside (custom VJPs that refuse
    # tangents on some inputs, as DiscreteAdjoint's does, keep working)
    g = jax.grad(lambda s: loss(lambda *a: as_one_function(_toy, *a), x, s))(scale)
    assert float(g) == pytest.approx(float(plain[1]), rel=1e-14)
    # central differences
    h = 1e-6
    fd = (loss(_toy, x, scale + h) - loss(_toy, x, scale - h)) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=1e-7)


def _jitted(saveat, **kw):
    return jax.jit(lambda x: nhjax.simulate(CAT, x, 3.0, control=CTRL, rtol=1e-8, atol=1e-8, saveat=saveat,
                                            **kw).xs)


def test_a_jitted_solve_is_one_function_with_the_numbers_of_the_kernel_sequence():
    x0 = jnp.asarray(CAT.initial_state(1.0, chi_dot=0.3))
    xs = _jitted(101)(x0)
    # the same solve, unwrapped (diffrax's program kernel by kernel)
    _, guards, _ = S._check_inputs(CAT, CTRL, x0, 0.0, 1e-8, False)
    solver, controller, adjoint, dt0, static, ts = S._configure(
        CAT, CTRL, x0, 0.0, 3.0, guards, saveat=101, solver=None, rtol=1e-8, atol=1e-8, dt0=None,
        max_steps=None, stepsize_controller=None, jump_ts=None, adjoint=None, project_steps=False,
        track_work=None, progress=False)
    static = dataclasses.replace(static, runtime_checks=False)
    plain = eqx.filter_jit(S._solve_body)(CAT, CTRL, x0, jnp.asarray(0.0), jnp.asarray(3.0), ts, solver,
                                          controller, adjoint, dt0, static)
    np.testing.assert_allclose(xs, plain.xs, rtol=0, atol=1e-15)

    # XLA runs a program's kernels through its thread pool when there are more than 8 and
    # one touches over 512 bytes (101 saved states are 4 KB), which for a program of
    # microseconds costs more than the program. So the whole of diffrax's solve must be
    # one call at the top level (XLA's one-function loop), with no kernel of diffrax's
    # around it (the set-up, the save buffers, the post-loop bookkeeping)
    text = _jitted(101, track_work=False, diagnostics=False).lower(x0).compile().as_text()
    entry = text.split("\nENTRY ")[1].split("\n}")[0].splitlines()[1:]
    calls = [ln for ln in entry if " call(" in ln and "xla_cpu_small_call" in ln]
    assert len(calls) == 1, "\n".join(entry)
    outside = [ln for ln in entry if ln not in calls and "diffeqsolve" in ln]
    assert not outside, "\n".join(outside)


def test_forward_mode_adjoints_are_not_wrapped():
    """jax.jvp does not pass a custom VJP: with diffrax.ForwardMode the solve stays as it
    was, and jacfwd through it agrees with central differences."""
    x0 = jnp.asarray(CAT.initial_state(1.0, chi_dot=0.3))

    def final_psi(a):
        ctrl = nhjax.Sinusoids(jnp.zeros(2), a, jnp.array([2.0, 3.0]), jnp.array([0.0, np.pi / 2]))
        return nhjax.simulate(CAT, x0, 2.0, control=ctrl, rtol=1e-10, atol=1e-10, saveat=2,
                              adjoint=diffrax.ForwardMode(), diagnostics=False).xs[-1, 2]

    a = jnp.array([0.3, 0.2])
    J = jax.jacfwd(final_psi)(a)
    h = 1e-6
    fd = [(final_psi(a.at[i].add(h)) - final_psi(a.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(J, fd, rtol=1e-6)


def test_a_solve_differentiated_inside_a_stored_trace_is_traced_once(monkeypatch):
    """Inside a stored program's trace (the optimal-control solvers' Jacobians and
    Hessians are such programs), a solve under jax.grad is traced once: its discrete
    adjoint's forward pass; no primal trace before it (a nested jit, the one-function
    wrapper) and no shape-only trace in its backward pass for the saved states the loss
    does not read. The gradient is central differences'."""
    from nhjax import _programs

    x0 = jnp.asarray(CAT.initial_state(1.0, chi_dot=0.3))

    def loss(a):
        ctrl = nhjax.Sinusoids(jnp.zeros(2), a, jnp.array([2.0, 3.0]), jnp.array([0.0, np.pi / 2]))
        return nhjax.simulate(CAT, x0, 2.0, control=ctrl, rtol=1e-10, atol=1e-10, saveat=5,
                              adjoint=nhjax.DiscreteAdjoint()).xs[-1, 2]

    solves = []
    plain = diffrax.diffeqsolve
    monkeypatch.setattr(diffrax, "diffeqsolve", lambda *a, **k: solves.append(1) or plain(*a, **k))
    a = jnp.array([0.3, 0.2])
    with _programs.stored_trace():
        g = jax.jit(jax.grad(loss))(a)
    assert len(solves) == 1
    h = 1e-6
    fd = [(loss(a.at[i].add(h)) - loss(a.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)
