"""Munthe-Kaas solvers: states stay on the group, the tableau's order is kept,
dense output is on the group, and exact flows of constant velocity are exact."""

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.integrate import LieODETerm
from nhjax.lie import SE2Body, SO3Body, SO3Spatial, UnitQuaternionBody, Euclidean, se2, so3

INERTIA = jnp.array([1.0, 2.0, 3.5])


def euler_vf(t, y, args):
    R, W = y
    return (W, jnp.cross(INERTIA * W, W) / INERTIA)


def ambient_vf(t, y, args):
    R, W = y
    return (R @ so3.hat(W), jnp.cross(INERTIA * W, W) / INERTIA)


Y0 = (jnp.eye(3), jnp.array([0.3, 2.0, 0.1]))  # near the unstable middle axis: a hard tumble


@pytest.fixture(scope="module")
def reference():
    ts = jnp.linspace(0, 10, 41)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(ambient_vf), diffrax.Dopri8(), 0.0, 10.0, 0.01, Y0,
        saveat=diffrax.SaveAt(ts=ts),
        # steps end at the save times: diffrax's Dopri8 dense output is only 5th order
        # (test_rkmk87_dense_output_is_seventh_order), ~1e-10 off between steps here
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13, step_ts=ts), max_steps=100_000,
    )
    return ts, sol.ys


def test_rkmk4_is_fourth_order(reference):
    _, (Rref, _) = reference
    errs = []
    for n in (100, 200, 400):
        sol = diffrax.diffeqsolve(LieODETerm(euler_vf, (SO3Body(), Euclidean())), nhjax.RKMK4(), 0.0, 10.0, 10.0 / n, Y0, max_steps=1000)
        R = sol.ys[0][-1]
        errs.append(np.abs(R - Rref[-1]).max())
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 3.8), rates


def test_rkmk45_tolerance_proportionality_and_dense_output(reference):
    ts, (Rref, Wref) = reference
    prev = np.inf
    for tol in (1e-6, 1e-9, 1e-12):
        sol = diffrax.diffeqsolve(
            LieODETerm(euler_vf, (SO3Body(), Euclidean())), nhjax.RKMK45(), 0.0, 10.0, None, Y0,
            saveat=diffrax.SaveAt(ts=ts), stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            max_steps=100_000,
        )
        Rs = sol.ys[0]
        # every saved point, most of them interpolated, lies on SO(3)
        orth = np.abs(np.einsum("nji,njk->nik", Rs, Rs) - np.eye(3)).max()
        assert orth < 1e-14
        err = np.abs(Rs - Rref).max()
        assert err < 300 * tol and err < prev / 50, (tol, err)
        prev = err


def test_rkmk87_is_eighth_order(reference):
    """Fixed steps h, h/2, h/4 on the tumbling top: the error falls by 2^8."""
    import jax

    _, (Rref, Wref) = reference
    term = LieODETerm(euler_vf, (SO3Body(), Euclidean()))
    solve = jax.jit(lambda dt: diffrax.diffeqsolve(term, nhjax.RKMK87(), 0.0, 10.0, dt, Y0, max_steps=200).ys)
    errs = []
    for n in (30, 60, 120):  # errors ~8e-8, 2e-10, 6e-13: above the reference's ~1e-13
        R, W = (a[-1] for a in solve(10.0 / n))
        errs.append(max(np.abs(R - Rref[-1]).max(), np.abs(W - Wref[-1]).max()))
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    rates = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(rates > 7.5), (errs, rates)


def _max_diff(a, b):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(u - v)) for u, v in zip(a, b)]))


def test_rkmk87_dense_output_is_seventh_order():
    """RKMK87's dense output over one step of the tumbling top, at s = 0.3, 0.5, 0.9 of
    the step, against a step of that length (local error O(h^9)): error O(h^8), order 7
    (diffrax's Dopri8 interpolant bootstrapped twice). diffrax's own Dopri8 interpolant
    on the same step, in ambient coordinates: about O(h^6), order 5."""
    import jax

    from nhjax.integrate.rkmk import LieInterpolation

    term = LieODETerm(euler_vf, (SO3Body(), Euclidean()))
    solver, d8, d8term = nhjax.RKMK87(), diffrax.Dopri8(), diffrax.ODETerm(ambient_vf)
    plain = nhjax.RKMK87(bootstrap=False)  # diffrax's interpolant, in the algebra
    thetas = (0.3, 0.5, 0.9)

    @jax.jit
    def errors(h):
        f0 = solver.init(term, 0.0, h, Y0, None)
        y1, _, dense, _, _ = solver.step(term, 0.0, h, Y0, None, f0, False)
        y1p, _, dense_p, _, _ = plain.step(term, 0.0, h, Y0, None, f0, False)
        g0 = d8.init(d8term, 0.0, h, Y0, None)
        _, _, dense8, _, _ = d8.step(d8term, 0.0, h, Y0, None, g0, False)
        ours, theirs, plains = [], [], []
        for th in thetas:
            direct = solver.step(term, 0.0, th * h, Y0, None, f0, False)[0]
            ours.append(_max_diff(LieInterpolation(t0=0.0, t1=h, **dense).evaluate(th * h), direct))
            theirs.append(_max_diff(d8.interpolation_cls(t0=0.0, t1=h, **dense8).evaluate(th * h), direct))
            plains.append(_max_diff(LieInterpolation(t0=0.0, t1=h, **dense_p).evaluate(th * h), direct))
        return jnp.stack(ours), jnp.stack(theirs), jnp.stack(plains), _max_diff(y1, y1p)

    out = [errors(h) for h in (0.4, 0.2, 0.1)]  # ours: ~3e-10, ~1.6e-12, ~7e-15 (measured)
    ours, theirs, plains, steps = (np.array([np.asarray(o[k]) for o in out]) for k in range(4))
    rate_ours = np.log2(ours[:-1] / ours[1:])
    rate_theirs = np.log2(theirs[:-1] / theirs[1:])
    rate_plain = np.log2(plains[:-1] / plains[1:])
    assert np.all(rate_ours > 7.3), (ours, rate_ours)  # measured 7.7 .. 7.9
    # measured ~6 (6.8 at mid-step): order 5, and ~1e4 times ours at h = 0.1
    assert np.all(rate_theirs < 7.0) and np.all(theirs[-1] > 100 * ours[-1]), (theirs, rate_theirs)
    # bootstrap=False: the same steps, with diffrax's order-5 interpolant (in the algebra)
    assert np.all(steps == 0.0), steps
    assert np.all(rate_plain < 7.0) and np.all(plains[-1] > 100 * ours[-1]), (plains, rate_plain)


@pytest.mark.slow  # (RKMK87's order: test_rkmk87_is_eighth_order; its dense output: test_rkmk87_dense_output_is_seventh_order; make test-all)
def test_rkmk87_tolerance_proportionality_and_dense_output(reference):
    """Adaptive RKMK87: every saved state (most of them dense output) on SO(3) and within a
    few hundred tolerances of the reference, the error falling with the tolerance; far
    fewer steps than RKMK45 at 1e-12."""
    import jax

    ts, (Rref, Wref) = reference
    term = LieODETerm(euler_vf, (SO3Body(), Euclidean()))

    @jax.jit
    def solve(tol):
        sol = diffrax.diffeqsolve(
            term, nhjax.RKMK87(), 0.0, 10.0, None, Y0, saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol), max_steps=10_000,
        )
        return sol.ys, sol.stats["num_accepted_steps"]

    prev = np.inf
    for tol in (1e-6, 1e-9, 1e-12):
        (Rs, Ws), steps = solve(tol)
        orth = np.abs(np.einsum("nji,njk->nik", Rs, Rs) - np.eye(3)).max()
        assert orth < 1e-14
        err = max(np.abs(Rs - Rref).max(), np.abs(Ws - Wref).max())
        assert err < 300 * tol and err < prev / 50, (tol, err)
        prev = err
    assert int(steps) < 150  # measured 86 (RKMK45: 682)


def test_long_run_stays_on_group():
    sol = diffrax.diffeqsolve(
        LieODETerm(euler_vf, (SO3Body(), Euclidean())), nhjax.RKMK45(), 0.0, 2000.0, None, Y0,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6), max_steps=200_000,
    )
    R, W = sol.ys[0][-1], sol.ys[1][-1]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-13)
    # spatial angular momentum R I W is conserved by the free rigid body
    L0 = Y0[0] @ (INERTIA * Y0[1])
    np.testing.assert_allclose(R @ (INERTIA * W), L0, rtol=1e-3, atol=1e-3)
    # an ambient-coordinate solver at the same tolerance leaves SO(3)
    amb = diffrax.diffeqsolve(
        diffrax.ODETerm(ambient_vf), diffrax.Tsit5(), 0.0, 2000.0, None, Y0,
        stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6), max_steps=200_000,
    )
    Ra = amb.ys[0][-1]
    assert np.abs(Ra.T @ Ra - np.eye(3)).max() > 1e-6


# (RKMK87's steps on the group: test_rkmk87_is_eighth_order; make test-all)
@pytest.mark.parametrize("solver", [nhjax.RKMK4(), nhjax.RKMK45(), pytest.param(nhjax.RKMK87(), marks=pytest.mark.slow)])
def test_constant_velocity_flows_are_exact(solver):
    """For constant body velocity the exact flow is y0 exp(t v): RKMK reproduces it to round-off."""
    v3 = jnp.array([0.7, -1.3, 2.9])
    vse2 = jnp.array([1.0, 0.2, 2.5])
    q0 = so3.quat_exp(jnp.array([0.1, 0.2, -0.3]))
    R0 = so3.exp(jnp.array([0.4, 0.0, 1.0]))
    y0 = (R0, R0, q0, se2.from_xytheta(1.0, 2.0, 0.3))
    spaces = (SO3Body(), SO3Spatial(), UnitQuaternionBody(), SE2Body())
    term = LieODETerm(lambda t, y, a: (v3, v3, v3, vse2), spaces)
    kw = dict(dt0=0.37) if isinstance(solver, nhjax.RKMK4) else dict(
        dt0=None, stepsize_controller=diffrax.PIDController(rtol=1e-3, atol=1e-3))
    T = 3.7
    sol = diffrax.diffeqsolve(term, solver, 0.0, T, y0=y0, max_steps=1000, **kw)
    R_b, R_s, q, g = (a[-1] for a in sol.ys)
    np.testing.assert_allclose(R_b, R0 @ so3.exp(T * v3), atol=1e-13)
    np.testing.assert_allclose(R_s, so3.exp(T * v3) @ R0, atol=1e-13)
    np.testing.assert_allclose(so3.quat_to_matrix(q), so3.quat_to_matrix(q0) @ so3.exp(T * v3), atol=1e-13)
    np.testing.assert_allclose(g, y0[3] @ se2.exp(T * vse2), atol=1e-13)
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, atol=1e-15)


def test_quaternion_and_matrix_forms_agree():
    q0 = so3.quat_exp(jnp.array([0.2, -0.1, 0.4]))
    y0m = (so3.quat_to_matrix(q0), Y0[1])
    y0q = (q0, Y0[1])
    ctrl = diffrax.PIDController(rtol=1e-10, atol=1e-10)
    sm = diffrax.diffeqsolve(LieODETerm(euler_vf, (SO3Body(), Euclidean())), nhjax.RKMK45(), 0.0, 5.0, None, y0m, stepsize_controller=ctrl)
    sq = diffrax.diffeqsolve(LieODETerm(euler_vf, (UnitQuaternionBody(), Euclidean())), nhjax.RKMK45(), 0.0, 5.0, None, y0q, stepsize_controller=ctrl)
    np.testing.assert_allclose(so3.quat_to_matrix(sq.ys[0][-1]), sm.ys[0][-1], atol=1e-8)


def marked_euler_vf(t, y, args):
    """euler_vf with erf_inv(0) = 0 added: a primitive nothing else in a solve uses, so its
    count in the solve's jaxpr is the number of copies of the vector field."""
    import jax

    R, W = y
    return (W + jax.lax.erf_inv(jnp.zeros((), W.dtype)), jnp.cross(INERTIA * W, W) / INERTIA)


def _count(jaxpr, name) -> int:
    from jax.extend.core import jaxprs_in_params

    return sum((e.primitive.name == name) + sum(_count(s, name) for s in jaxprs_in_params(e.params))
               for e in jaxpr.eqns)


@pytest.mark.parametrize("vmapped", [False, pytest.param(True, marks=pytest.mark.slow)])  # (the batch: make test-all)
def test_first_stage_in_the_stage_scan_is_the_same_solve_with_one_copy_of_the_vector_field(reference, vmapped):
    """RKMK45(first_stage_in_scan=True) (simulate's single solves) evaluates the FSAL
    first stage of the first step inside its stage scan instead of in init: the same
    solution and step counts as the plain solver, alone and under jax.vmap, with one
    copy of the vector field in the program instead of three."""
    import jax

    ts, (Rref, _) = reference
    term = LieODETerm(marked_euler_vf, (SO3Body(), Euclidean()))

    def solve(solver, W0):
        sol = diffrax.diffeqsolve(term, solver, 0.0, 10.0, None, (jnp.eye(3), W0), saveat=diffrax.SaveAt(ts=ts),
                                  stepsize_controller=diffrax.PIDController(rtol=1e-10, atol=1e-10),
                                  max_steps=100_000)
        return sol.ys, sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"]

    W0 = jnp.stack([Y0[1], Y0[1] * 1.1, Y0[1][::-1]]) if vmapped else Y0[1]
    out, copies = {}, {}
    for flag in (False, True):
        fn = lambda w, s=nhjax.RKMK45(scan_stages=True, first_stage_in_scan=flag): solve(s, w)  # noqa: E731
        fn = jax.vmap(fn) if vmapped else fn
        out[flag] = jax.jit(fn)(W0)
        copies[flag] = _count(jax.make_jaxpr(fn)(W0).jaxpr, "erf_inv")
    # plain: init's f0, the recomputation after a jump (jumps=True) and the stage scan;
    # flagged: the stage scan's only
    assert copies == {False: 3, True: 1}
    (ys0, acc0, rej0), (ys1, acc1, rej1) = out[False], out[True]
    np.testing.assert_array_equal(np.asarray(acc0), np.asarray(acc1))
    np.testing.assert_array_equal(np.asarray(rej0), np.asarray(rej1))
    for a, b in zip(ys0, ys1):  # the same arithmetic, compiled apart: rounding, grown by the tumble
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-11)
    R = ys1[0][0] if vmapped else ys1[0]
    assert np.abs(np.asarray(R) - np.asarray(Rref)).max() < 300 * 1e-10  # and right


def test_a_solve_traces_the_step_once(monkeypatch):
    """diffrax traces a solver's step several times per solve (its loop body to see what
    stays static, the loop itself, dense output at an event); the step is a nested jit,
    so its body is traced once, and the solve is the same as with the step inlined."""
    import jax

    from nhjax import _programs
    from nhjax.integrate import rkmk
    from nhjax.scenes import BallInCone

    body, traces = rkmk._AbstractRKMK._step, []

    def counted(self, *args):
        traces.append(1)
        return body(self, *args)

    ball = BallInCone()  # projected steps and a guard event: every kind of step trace
    x0 = ball.initial_state(rho=3.0, rho_dot=0.5, alpha_dot=0.3, spin=1.0)
    monkeypatch.setattr(rkmk._AbstractRKMK, "_step", counted)
    # the solve traced here, not a stored program from another test or an earlier run
    monkeypatch.setenv("NHJAX_PROGRAM_CACHE", "0")
    monkeypatch.setattr(_programs, "_MEMORY", {})
    nested = jax.jit(lambda x: nhjax.simulate(ball, x, 4.0, saveat=2, diagnostics=False).xs[-1])(x0)
    assert len(traces) == 1
    monkeypatch.setattr(rkmk, "_nested_step", lambda solver, *args: solver._step(*args))
    # (another number of saved times: the solve's own jit would reuse its trace)
    inlined = jax.jit(lambda x: nhjax.simulate(ball, x, 4.0, saveat=3, diagnostics=False).xs[-1])(x0)
    assert len(traces) >= 4
    np.testing.assert_allclose(nested, inlined, rtol=0, atol=1e-13)


def _cat():
    from nhjax.scenes import FallingCat

    cat = FallingCat()
    ctrl = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])
    return cat, ctrl, cat.initial_state(0.8, chi_dot=0.5)


def test_rkmk87_simulate_falling_cat_agrees_with_rkmk45_in_fewer_steps():
    """simulate(..., solver=RKMK87()) on the falling cat over 10 s (vector state: Dopri8's
    steps): final and all 101 saved states agree with RKMK45 at 1e-12, and at 1e-10 it
    takes fewer accepted steps."""
    cat, ctrl, x0 = _cat()
    run = {}
    for name, solver in (("45", nhjax.RKMK45()), ("87", nhjax.RKMK87())):
        for tol in (1e-10, 1e-12):
            run[name, tol] = nhjax.simulate(cat, x0, 10.0, control=ctrl, solver=solver, rtol=tol, atol=tol,
                                            diagnostics=False)
    a, b = run["45", 1e-12], run["87", 1e-12]
    assert np.abs(np.asarray(a.xs) - np.asarray(b.xs)).max() < 1e-9
    assert int(run["87", 1e-10].num_accepted_steps) < int(run["45", 1e-10].num_accepted_steps)


# (~11 s cold; in the default run RKMK87 integrates the ShellWithTop steering's shooting
# solves, checked by tests/test_steering.py; make test-all)
@pytest.mark.slow
def test_rkmk87_simulate_shell_with_top_agrees_with_rkmk45_in_fewer_steps():
    """The spherical robot (R^2 x SO(3) x SO(3), nonholonomic rolling) over 3 s: RKMK87
    (stages in a scan, as simulate's default RKMK45 for this large vector field) agrees
    with RKMK45 at 1e-12 and takes fewer steps at 1e-10, attitudes on SO(3)."""
    from nhjax.scenes import ShellWithTop

    robot = ShellWithTop()
    x0 = robot.initial_state(top_omega=(0.0, 0.0, 3.0))
    ctrl = nhjax.Sinusoids(np.zeros(3), [0.02, -0.01, 0.015], [1.1, 0.7, 2.0], [0.0, 0.4, 1.0])
    run = {}
    for name, solver in (("45", nhjax.RKMK45(scan_stages=True)), ("87", nhjax.RKMK87(scan_stages=True))):
        for tol in (1e-10, 1e-12):
            run[name, tol] = nhjax.simulate(robot, x0, 3.0, control=ctrl, solver=solver, rtol=tol, atol=tol,
                                            saveat=11, diagnostics=False)
    a, b = run["45", 1e-12], run["87", 1e-12]
    for u, v in zip(jax_leaves(a.xs), jax_leaves(b.xs)):
        assert np.abs(np.asarray(u) - np.asarray(v)).max() < 1e-9
    for R in b.xs[0][1:]:  # both attitudes at every saved time
        R = np.asarray(R)
        assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < 1e-13
    assert int(run["87", 1e-10].num_accepted_steps) < int(run["45", 1e-10].num_accepted_steps)


def jax_leaves(tree):
    import jax

    return jax.tree_util.tree_leaves(tree)


# (make test-all: "vjp" ~18 s, its jitted gradient compiled on every run; "auto" ~13 s,
# and in the default run test_steering's shooting Jacobian, forward sensitivities
# through RKMK87 on SO(3) x SO(3), is checked against central differences)
@pytest.mark.parametrize("jacobians", [pytest.param("auto", marks=pytest.mark.slow),
                                       pytest.param("vjp", marks=pytest.mark.slow)])
def test_rkmk87_discrete_adjoint_agrees_with_central_differences(jacobians):
    """jax.grad through simulate with RKMK87 and DiscreteAdjoint ("auto": forward
    sensitivities for these D = 3 inputs; "vjp": the recorded steps backwards), through
    the saved states (dense output) and the final state, against central differences in the
    torque amplitudes and the inertia ratio lam (truncation ~h^2, error ~tol/h)."""
    import jax

    from nhjax.scenes import FallingCat

    _, ctrl, x0 = _cat()

    def loss(p, adjoint):
        amp, lam = p
        c = nhjax.Sinusoids(ctrl.offset, amp, ctrl.omega, ctrl.phase)
        tr = nhjax.simulate(FallingCat(lam=lam), x0, 4.0, control=c, solver=nhjax.RKMK87(), rtol=1e-11,
                            atol=1e-11, saveat=21, adjoint=adjoint, diagnostics=False, track_work=False)
        return tr.xs[-1, 2] ** 2 + 3.0 * tr.x_end[4] + jnp.sum(jnp.sin(tr.xs[:, 0]) * tr.xs[:, 3])

    p = (ctrl.amplitude, jnp.asarray(0.3157894736842105))
    g = jax.jit(jax.grad(lambda p: loss(p, nhjax.DiscreteAdjoint(jacobians=jacobians))))(p)
    f = jax.jit(lambda p: loss(p, None))
    amp, lam = p
    h = 1e-5
    fd = [(f((amp + h * e, lam)) - f((amp - h * e, lam))) / (2 * h) for e in np.eye(2)]
    fd.append((f((amp, lam + h)) - f((amp, lam - h))) / (2 * h))
    got = np.concatenate([np.asarray(g[0]), [float(g[1])]])
    np.testing.assert_allclose(got, np.asarray(fd), rtol=2e-5)
