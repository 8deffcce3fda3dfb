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


@pytest.mark.slow  # (shooting derivatives against differences: test_direct_jacobian_by_tangents_equals_the_reverse_passes_and_differences; make test-all)
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


@pytest.mark.parametrize("kind", [pytest.param("constant", marks=pytest.mark.slow), "linear"])
def test_shooting_jacobian_at_rest_is_the_exact_one(kind):
    """At zero inputs the double integrator stays at rest and the step control sees no
    error; the shooting solves' steps stop at the knots (controls.newton._step_controller),
    and the Jacobian of (J, q(T), v(T)) in the knot values is the exact one:
    q(T) = int_0^T (T - t) u dt, v(T) = int_0^T u dt, J = 0 (a step cap alone, with steps
    straddling the knots, gave 0.1214 and 0.1286 for dv(T)/du at the ends instead of 0.125)."""
    from controls import newton as nt

    T, n = 1.0, 8
    param = (controls.PiecewiseConstant if kind == "constant" else controls.PiecewiseLinear)(n, T, 1)
    sh = nt._Shooting(lq_problem(T), param, jnp.asarray(1e-10), jnp.asarray(1e-10))
    y, D = (np.asarray(a) for a in nt._values_and_jacobian(sh, np.zeros(param.size)))
    np.testing.assert_allclose(y, [0.0, -1.0, 0.0], atol=1e-15)
    h = T / n
    if kind == "constant":  # u = u_k on [k h, (k + 1) h]
        dq = h * (T - h * (np.arange(n) + 0.5))
        dv = np.full(n, h)
    else:  # hat functions phi_k: int phi_k = h (h/2 at the ends), int (T - t) phi_k = h (T - t_k)
        t = h * np.arange(n + 1)  # inside (symmetric hats), T h/2 - h^2/6 and h^2/6 at the ends
        dv = np.full(n + 1, h)
        dv[[0, -1]] = h / 2
        dq = dv * (T - t)
        dq[0] -= h**2 / 6
        dq[-1] += h**2 / 6
    np.testing.assert_allclose(D[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(D[1], dq, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(D[2], dv, rtol=1e-12, atol=1e-15)


def test_shooting_jacobian_at_rest_resolves_a_smooth_parametrization():
    """The same at zero inputs with Chebyshev(12): a smooth signal gets steps of at most
    T / 13 (controls.newton._step_controller), so the forward sensitivities integrate
    the basis polynomials T_k(2t/T - 1) to 1e-3 of the exact integrals (Gauss-Legendre,
    exact for these degrees). Left to the step control, which sees no error at rest,
    the solve took a few long steps and its Jacobian was off by 1.2 (the thruster
    chain's failed steering; tests/test_planar_chain.py has the whole task, in
    ``make test-all``)."""
    from controls import newton as nt

    T, n = 1.0, 12
    param = controls.Chebyshev(n, T, 1)
    sh = nt._Shooting(lq_problem(T), param, jnp.asarray(1e-10), jnp.asarray(1e-10))
    y, D = (np.asarray(a) for a in nt._values_and_jacobian(sh, np.zeros(param.size)))
    s, w = np.polynomial.legendre.leggauss(20)  # t = T (s + 1) / 2
    basis = np.polynomial.chebyshev.chebvander(s, n)
    dv = (T / 2) * w @ basis  # int_0^T T_k dt
    dq = (T**2 / 4) * (w * (1 - s)) @ basis  # int_0^T (T - t) T_k dt
    assert np.abs(dq).max() > 0.4 and np.abs(dv).max() > 0.9
    np.testing.assert_allclose(D[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(D[1], dq, rtol=0, atol=1e-3)
    np.testing.assert_allclose(D[2], dv, rtol=0, atol=1e-3)


def test_bad_problems_are_named():
    with pytest.raises(controls.ProblemError, match="scalar"):
        controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=lambda t, x, u: u)
    with pytest.raises(controls.ProblemError, match="does not fit"):
        controls.OCP(DoubleIntegrator(), jnp.zeros(3), 1.0, running_cost=HalfSquare())
    ocp = lq_problem()
    with pytest.raises(controls.ProblemError, match="^solve_direct: the parametrization has 2 inputs, DoubleIntegrator takes 1"):
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


def _hat_integrals(n, T):
    """For the n + 1 hat functions of PiecewiseLinear(n, T): the mass matrix int phi_j
    phi_k dt, int phi_k dt and int (T - t) phi_k dt, by 5-point Gauss-Legendre on each
    interval (exact: the integrands are polynomials of degree <= 2 there)."""
    xg, wg = np.polynomial.legendre.leggauss(5)
    knots = np.linspace(0.0, T, n + 1)
    M, w, r = np.zeros((n + 1, n + 1)), np.zeros(n + 1), np.zeros(n + 1)
    for i in range(n):
        a, b = knots[i], knots[i + 1]
        t = a + 0.5 * (b - a) * (xg + 1.0)
        q = 0.5 * (b - a) * wg
        phi = np.zeros((n + 1, t.size))
        phi[i], phi[i + 1] = (b - t) / (b - a), (t - a) / (b - a)
        M += (phi * q) @ phi.T
        w += phi @ q
        r += phi @ (q * (T - t))
    return M, w, r


def test_sqp_with_control_bounds_meets_the_kkt_conditions_of_the_discretized_problem():
    """Rest to x = 1 in 1 s with u <= 4 (the free optimum 6 - 12 t exceeds it early on),
    controls piecewise linear (exact here): the problem in the 9 parameters is the QP
    min p.M.p/2 s.t. int u = 0, int (T - t) u = 1, p <= 4. SQP (the default of
    solve_direct) must return its solution: taking the bounds SQP holds active, the
    equality-constrained QP solved in closed form gives the same parameters, nonnegative
    bound multipliers, and the other parameters strictly inside (KKT: the optimum)."""
    n, T, u_max = 8, 1.0, 4.0
    ocp = controls.OCP(DoubleIntegrator(), jnp.zeros(2), T, running_cost=HalfSquare(),
                       terminal_constraints=Target(jnp.array([1.0, 0.0])), u_lower=-10.0, u_upper=u_max)
    d = controls.solve_direct(ocp, controls.PiecewiseLinear(n, T, 1), progress=False)
    assert d.converged and d.violation < 1e-10, d.message
    p = np.asarray(d.params)
    assert p.max() <= u_max
    active = p >= u_max - 1e-9
    assert 0 < active.sum() < n  # the bound is active on some of the parameters
    M, w, r = _hat_integrals(n, T)
    E = np.vstack([w, r])
    S = np.eye(n + 1)[active]
    k, a = E.shape[0], S.shape[0]
    K = np.block([[M, E.T, S.T], [E, np.zeros((k, k + a))], [S, np.zeros((a, k + a))]])
    sol = np.linalg.solve(K, np.concatenate([np.zeros(n + 1), [0.0, 1.0], np.full(a, u_max)]))
    p_kkt, mult = sol[: n + 1], sol[n + 1 + k:]
    assert np.all(mult >= 0)  # M p + E^T nu + mu = 0, mu >= 0 for p <= u_max: the bounds push back
    assert np.all(p_kkt[~active] < u_max)
    np.testing.assert_allclose(p, p_kkt, atol=1e-8)
    np.testing.assert_allclose(d.cost, 0.5 * p_kkt @ M @ p_kkt, rtol=1e-10)
    assert d.cost > 6.0  # dearer than the unbounded optimum


class _Arctan(eqx.Module):
    """r(z) = atan(Q (z - z*)) componentwise, Q a rotation: one root z*."""

    root: jax.Array
    mix: jax.Array

    @property
    def residual_size(self):
        return self.root.shape[0]

    def residual(self, z):
        d = self.mix @ (z - self.root)
        return jnp.arctan(d)


class Pendulum(AbstractSystem):
    control_dim = 1
    state_names = ("q", "v")

    def vector_field(self, t, x, u):
        return jnp.stack([x[1], -jnp.sin(x[0]) + u[0]])


def test_the_returned_extremal_is_the_one_the_shooting_residual_comes_from():
    """solve_pontryagin's extremal, cost and residual (single shooting) belong to the
    returned solution: the trajectory starts at the returned p0, the residual
    recomputed from its end with the returned nu is the reported one, and the cost is
    the running cost's quadrature along it. Checked for Newton, and for
    Levenberg-Marquardt from a far guess stopped after every budget of 1-10 steps (its
    trials are rejected from the 2nd to the 9th: the answer is the last accepted point,
    not the trial), and from a nearer one to convergence. Both programs: the default
    (a solve of the extremal after the root find) and ``quick=True`` (the extremal
    from the root find's own last accepted solve)."""
    from controls.pontryagin import _terminal_residual

    # swing a pendulum from rest at the bottom to rest at q = 2 in T = 3 (nonlinear)
    ocp = controls.OCP(Pendulum(), jnp.zeros(2), 3.0, running_cost=HalfSquare(),
                       terminal_constraints=Target(jnp.array([2.0, 0.0])))
    runs = [("newton", None, 100)] + [("lm", np.array([200.0, 100.0]), k) for k in range(1, 11)]
    runs += [("lm", np.array([40.0, -30.0]), 100)]
    ref = None  # the default program's Newton solve (the first run)
    for quick, (solver, guess, budget) in [(q, run) for q in (False, True) for run in runs]:
        r = controls.solve_pontryagin(ocp, guess, solver=solver, max_steps=budget, progress=False, quick=quick)
        xs = np.asarray(r.trajectory.xs)
        np.testing.assert_array_equal(xs[0], np.concatenate([[0.0, 0.0], r.p0]))
        res = np.asarray(_terminal_residual(ocp, jnp.asarray(xs[-1, :2]), jnp.asarray(xs[-1, 2:]), jnp.asarray(r.nu)))
        assert np.max(np.abs(res)) == pytest.approx(r.residual, rel=1e-12, abs=1e-16)
        assert r.violation == pytest.approx(np.max(np.abs(xs[-1, :2] - [2.0, 0.0])), rel=1e-12, abs=1e-16)
        # trapezoid on 401 points: agrees with the integrated cost to its O(h^2) error
        trap = np.trapezoid(0.5 * r.controls[:, 0] ** 2, np.asarray(r.trajectory.ts))
        assert abs(trap - r.cost) < 1e-4 * r.cost
        if solver == "newton":
            if not quick:
                ref = r
            assert r.converged and r.iterations >= 3
            # the quick program's Newton solve ends at the default one's extremal
            np.testing.assert_allclose(r.p0, ref.p0, rtol=1e-9)
            np.testing.assert_allclose(r.cost, ref.cost, rtol=1e-11)
        if not r.converged:  # a stopped solve says where it stopped and what to try
            assert f"residual {r.residual:.2e} after {r.iterations} steps" in r.message
            assert "closer p0_guess" in r.message and "solver='lm'" not in r.message
        if budget == 100 and solver == "lm":
            # the damped iteration with the full budget ends at the same extremal
            assert r.converged
            np.testing.assert_allclose(r.p0, ref.p0, rtol=1e-8)
            np.testing.assert_allclose(r.cost, ref.cost, rtol=1e-10)


@pytest.mark.slow  # (the quick program's answers: test_somersault_ocp; make test-all)
def test_the_variational_jacobian_of_the_quick_program_is_the_forward_mode_one():
    """The quick Pontryagin program's residual Jacobian comes from the variational
    equations integrated beside the extremal (steps chosen on (x, p, J) alone); the
    forward-mode derivative of the same solve (step-size control included) is the
    reference. diffrax's step-size controller stops gradients through the step sizes,
    so both are the derivative of the discrete flow at the same steps: away from the
    root (the pendulum swing from two costate guesses, with nonzero multipliers) they
    agree to rounding, the residual and the extremal are the same solve's, and a wrong
    sign or transposition in the variational equations would be off by O(1)."""
    import diffrax

    from controls.pontryagin import (
        HamiltonianSystem,
        _extremal,
        _residual_and_extremal,
        _Shooting,
        _terminal_residual,
        _value_and_jacobian,
    )

    ocp = controls.OCP(Pendulum(), jnp.zeros(2), 3.0, running_cost=HalfSquare(),
                       terminal_constraints=Target(jnp.array([2.0, 0.0])))
    sh = _Shooting(HamiltonianSystem(ocp), jnp.asarray(1e-11), jnp.asarray(1e-11), 1)

    @eqx.filter_jit
    def forward_mode(sh, z):  # the residual of the extremal's solve, differentiated through it
        def evaluate(z):
            tr = _extremal(sh.ham, z[:2], sh.rtol, sh.atol, diffrax.ForwardMode())
            yT = tr.xs[-1]
            return _terminal_residual(ocp, yT[:2], yT[2:4], z[2:]), tr

        return _value_and_jacobian(z, evaluate)

    for z in (jnp.array([3.0, 2.0, 0.5, -0.2]), jnp.array([40.0, -30.0, 1.0, 2.0])):
        r, jac, tr = _residual_and_extremal(sh, z)
        r_fwd, jac_fwd, tr_fwd = forward_mode(sh, z)
        np.testing.assert_allclose(np.asarray(r), np.asarray(r_fwd), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(tr.xs), np.asarray(tr_fwd.xs), rtol=1e-12, atol=1e-12)
        assert int(tr.num_accepted_steps) == int(tr_fwd.num_accepted_steps)
        scale = np.max(np.abs(np.asarray(jac_fwd)))
        assert np.max(np.abs(np.asarray(jac) - np.asarray(jac_fwd))) < 1e-12 * scale
        assert np.max(np.abs(np.asarray(jac)[:, :2])) > 1e-2 * scale  # the ODE part is not trivially small
        assert tr.xs.shape[1] == 5  # (x, p, J): the sensitivities are not handed on


def test_shooting_root_finds_the_root_and_damping_rescues_a_diverging_newton():
    """The Pontryagin solver's root find (Newton and Levenberg-Marquardt on a residual
    and its forward-mode Jacobian): both reach the root of a smooth system to 1e-12
    from nearby; from far away (|d| = 8: atan's Newton steps overshoot further each
    time beyond |d| = 1.39) the undamped iteration fails and the damped one converges."""
    from controls.pontryagin import _shooting_root

    c, s = np.cos(0.3), np.sin(0.3)
    prob = _Arctan(jnp.array([0.4, -1.3]), jnp.array([[c, -s], [s, c]]))
    for damped in (False, True):
        z, r, steps, _ = _shooting_root(prob, jnp.array([0.9, -1.0]), 1e-13, 50, damped)
        np.testing.assert_allclose(np.asarray(z), [0.4, -1.3], atol=1e-12)
        assert np.max(np.abs(np.asarray(r))) <= 1e-12 and 1 <= int(steps) <= 30
    # a start where the undamped iteration does not converge within the budget
    far = jnp.array([0.4, -1.3]) + prob.mix.T @ jnp.array([8.0, -8.0])
    z, r, steps, _ = _shooting_root(prob, far, 1e-13, 100, True)
    np.testing.assert_allclose(np.asarray(z), [0.4, -1.3], atol=1e-12)
    zn, rn, _, _ = _shooting_root(prob, far, 1e-13, 100, False)
    assert not (np.max(np.abs(np.asarray(rn))) <= 1e-12)


def test_saved_path_is_the_rollout_and_a_failed_simulation_raises():
    """controls.problem.saved_path (the compiled re-simulation the costate check and
    somersault_free_winding's check use): on the LQ problem's optimal control the states
    are exact (q = 3t^2 - 2t^3, v = 6t - 6t^2) and equal the eager rollout's; a control
    that turns non-finite raises ProblemError instead of returning NaN states."""
    from controls.problem import ProblemError, rollout, saved_path

    ocp = lq_problem()

    def u(t, x):
        return jnp.stack([6.0 - 12.0 * t])

    ts, xs = saved_path(ocp, u, rtol=1e-10, atol=1e-10, n_points=11, owner="test")
    np.testing.assert_allclose(ts, np.linspace(0, 1, 11), atol=1e-15)
    np.testing.assert_allclose(xs, np.stack([3 * ts**2 - 2 * ts**3, 6 * ts - 6 * ts**2], 1), atol=1e-12)
    traj, _, _ = rollout(ocp, u, rtol=1e-10, atol=1e-10, saveat=11)
    np.testing.assert_allclose(xs, np.asarray(traj.xs[0]), rtol=0, atol=1e-14)

    def blows_up(t, x):
        return jnp.stack([1.0 / (0.5 - t)])

    with pytest.raises(ProblemError, match="test: the simulation of the control failed"):
        saved_path(ocp, blows_up, rtol=1e-10, atol=1e-10, n_points=11, owner="test")


def test_direct_jacobian_by_tangents_equals_the_reverse_passes_and_differences():
    """The direct methods' Jacobian of (J, psi) (controls.newton._values_and_jacobian:
    one solve carrying the P parameter tangents) against 1 + m reverse passes of the
    discrete adjoint and against central differences, on the LQ problem with Chebyshev
    controls (a curved case: the cost is quadratic in the parameters)."""
    from controls.newton import _Shooting, _values, _values_and_jacobian

    ocp, param = lq_problem(), controls.Chebyshev(4, 1.0, 1)
    sh = _Shooting(ocp, param, np.asarray(1e-12), np.asarray(1e-12))
    z = np.array([0.3, -1.2, 0.5, 0.8, -0.4])
    y, D = (np.asarray(a) for a in _values_and_jacobian(sh, z))
    y_rev, vjp = jax.vjp(lambda z: sh.values(z, tangents=False), jnp.asarray(z))
    D_rev = np.asarray(jax.vmap(vjp)(jnp.eye(y.shape[0]))[0])
    np.testing.assert_allclose(y, np.asarray(y_rev), rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(D, D_rev, rtol=1e-12, atol=1e-13)
    h = 1e-4
    D_fd = np.stack([(_values(sh, z + h * e) - _values(sh, z - h * e)) / (2 * h) for e in np.eye(z.size)], 1)
    np.testing.assert_allclose(D, D_fd, rtol=1e-7, atol=1e-8)
    assert np.abs(D[0]).max() > 0.1 and np.abs(D[1:]).max() > 0.1


def test_parametrization_edge_cases_are_named_or_answered():
    """A CubicSpline of one interval is the straight line between its knots (it raised a
    JAX shape error); fit of a function that returns NaN, and solve_direct_newton without a
    guess, are ProblemErrors naming the argument (a NaN fit, an IndexError before)."""
    spline = controls.CubicSpline(1, 2.0, 2)
    u = spline.signal(np.array([1.0, -1.0, 3.0, 1.0]))
    np.testing.assert_allclose(np.asarray(u(0.5)), [1.5, -0.5], rtol=0, atol=1e-14)
    with pytest.raises(controls.ProblemError, match="Chebyshev.fit: u_fn\\(t\\) returned NaN or inf at t = 0"):
        controls.Chebyshev(4, 1.0, 2).fit(lambda t: jnp.full(2, jnp.nan))
    ocp = controls.OCP(DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=HalfSquare(),
                       terminal_constraints=Target(jnp.array([1.0, 0.0])))
    with pytest.raises(controls.ProblemError, match="solve_direct_newton: guess must be the \\(5,\\) starting"):
        controls.solve_direct_newton(ocp, controls.Chebyshev(4, 1.0, 1), None)
