"""Optimal control: a linear-quadratic problem with a known optimum solved by both
methods; optimality residuals; gradients of the shooting cost; clear errors for bad
problems. (The somersault tasks are in test_somersault_ocp.py.)"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import controls
from nhjax.mechanics import AbstractSystem


class DoubleIntegrator(AbstractSystem):
    control_dim = 1
    state_names = ("q", "v")

    def vector_field(self, t, x, u):
        return jnp.stack([x[1], u[0]])


class HalfSquare(eqx.Module):
    def __call__(self, t, x, u):
        return 0.5 * u @ u


class Target(eqx.Module):
    x: jax.Array

    def __call__(self, x):
        return x - self.x


def lq_problem(T=1.0):
    # rest at 0 -> rest at 1: u* = 6/T^2 - 12 t/T^3, cost 6/T^3
    return controls.OCP(DoubleIntegrator(), jnp.zeros(2), T, running_cost=HalfSquare(),
                        terminal_constraints=Target(jnp.array([1.0, 0.0])))


def test_lq_both_methods_reach_the_analytic_optimum():
    ocp = lq_problem()
    ind = controls.solve_pontryagin(ocp)
    assert ind.converged
    np.testing.assert_allclose(ind.cost, 6.0, rtol=1e-12)
    np.testing.assert_allclose(ind.p0, [-12.0, -6.0], atol=1e-9)  # p = dH/dx costates
    ts = np.asarray(ind.trajectory.ts)
    np.testing.assert_allclose(ind.controls[:, 0], 6 - 12 * ts, atol=1e-8)
    # direct: u* is linear in t, so piecewise-linear controls contain it exactly
    d = controls.solve_direct(ocp, controls.PiecewiseLinear(4, 1.0, 1))
    assert d.converged and d.violation < 1e-8
    np.testing.assert_allclose(d.cost, 6.0, rtol=1e-8)
    np.testing.assert_allclose(d.params, 6 - 12 * np.linspace(0, 1, 5), atol=1e-4)
    # the direct optimum satisfies Pontryagin's conditions (costates from its multipliers)
    res = controls.pmp_residual(ocp, d.control, d.multipliers)
    assert res["stationarity"] < 1e-4 and res["hamiltonian_variation"] < 1e-4


def test_lq_feasible_path_newton_reaches_the_analytic_optimum():
    """solve_direct_newton on the LQ problem: u* = 6 - 12 t lies in the piecewise-linear
    space, so the optimum is exact; its multipliers make the direct optimum satisfy
    Pontryagin's conditions as solve_direct's do."""
    ocp = lq_problem()
    param = controls.PiecewiseLinear(4, 1.0, 1)
    d = controls.solve_direct_newton(ocp, param, jnp.zeros(param.size), rtol=1e-12, atol=1e-12)
    assert d.converged, d.message
    assert d.violation < 1e-10 and d.iterations <= 3  # a quadratic problem: one Newton step
    np.testing.assert_allclose(d.cost, 6.0, rtol=1e-10)
    np.testing.assert_allclose(d.params, 6 - 12 * np.linspace(0, 1, 5), atol=1e-7)
    res = controls.pmp_residual(ocp, d.control, d.multipliers)
    assert res["stationarity"] < 1e-6 and res["hamiltonian_variation"] < 1e-6
    with pytest.raises(controls.ProblemError, match="bounds"):
        bounded = controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=HalfSquare(),
                               terminal_constraints=Target(jnp.array([1.0, 0.0])), u_lower=-1.0, u_upper=1.0)
        controls.solve_direct_newton(bounded, param, jnp.zeros(param.size))


@pytest.mark.slow
def test_lq_multiple_shooting():
    ocp = lq_problem()
    ind = controls.solve_pontryagin(ocp, shooting="multiple", segments=3)
    assert ind.converged
    np.testing.assert_allclose(ind.cost, 6.0, rtol=1e-12)
    dm = controls.solve_direct(ocp, controls.PiecewiseLinear(4, 1.0, 1), shooting="multiple", segments=3)
    assert dm.converged
    np.testing.assert_allclose(dm.cost, 6.0, rtol=1e-8)


def test_gradient_of_shooting_cost_matches_fd():
    ocp = lq_problem(T=2.0)
    param = controls.Fourier(3, 2.0, 1)
    p = jnp.asarray(np.random.default_rng(3).normal(size=param.size))

    def J(p):
        _, cost, psi = controls.rollout(ocp, param.signal(p), rtol=1e-12, atol=1e-12)
        return cost + psi @ psi

    g = jax.grad(J)(p)
    h = 1e-6
    fd = np.array([(J(p + h * e) - J(p - h * e)) / (2 * h) for e in np.eye(param.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)


def test_bad_problems_are_named():
    with pytest.raises(controls.ProblemError, match="scalar"):
        controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=lambda t, x, u: u)
    with pytest.raises(controls.ProblemError, match="does not fit"):
        controls.OCP(DoubleIntegrator(), jnp.zeros(3), 1.0, running_cost=HalfSquare())
    ocp = lq_problem()
    with pytest.raises(controls.ProblemError, match="2 inputs|takes 1"):
        controls.solve_direct(ocp, controls.PiecewiseLinear(4, 1.0, 2))
    with pytest.raises(controls.ProblemError, match="not differentiable|zero gradient"):
        flat = controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0,
                            running_cost=lambda t, x, u: jnp.round(u[0]) ** 2)
        controls.solve_direct(flat, controls.PiecewiseLinear(4, 1.0, 1))
    # unreachable within the bounds: |u| <= 1 cannot bring the double integrator to 1 in 1 s
    bounded = controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=HalfSquare(),
                           terminal_constraints=Target(jnp.array([1.0, 0.0])), u_lower=-1.0, u_upper=1.0)
    d = controls.solve_direct(bounded, controls.PiecewiseConstant(8, 1.0, 1), max_outer=8)
    assert not d.converged and "unreachable" in d.message
