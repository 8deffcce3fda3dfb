"""Issue 14: every case a user met at the edges raises a named, documented error (or
works correctly), in the words the issue asked for. Property-based tests and the
coverage of every public entry point are in test_validation_properties.py."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import controls
import nhjax
from nhjax import errors as E
from nhjax.integrate.simulate import _check_inputs
from nhjax.lie import so3
from nhjax.mechanics import AbstractSystem, Lagrangian
from nhjax.scenes import (
    BallOnPlatter,
    FallingCat,
    FallingCatKinematic,
    ShellWithTop,
    SkateSE2,
)

OSC = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 0.5 * 4.0 * q @ q)  # omega = 2


def test_errors_are_named_and_keep_builtin_classes():
    for cls in (E.ParameterError, E.StateError, E.GroupMembershipError, E.ConstraintViolationError,
                E.ProjectionError, E.TimeSpanError, E.ProblemError):
        assert issubclass(cls, E.NhjaxError) and issubclass(cls, ValueError)
    assert issubclass(E.ControlError, ValueError) and issubclass(E.ControlError, TypeError)
    assert issubclass(E.SystemKindError, E.NhjaxError) and issubclass(E.SystemKindError, TypeError)
    assert issubclass(E.ResourceError, MemoryError)
    assert controls.ProblemError is E.ProblemError


def test_a_ragged_sequence_is_a_parameter_error():
    """A ragged list where numbers go (numpy's own ValueError from np.iscomplexobj before)."""
    from nhjax import _validate as V

    for check in (lambda v: V.real("x", v, owner="f"), lambda v: V.positive("x", v, owner="f")):
        with pytest.raises(E.ParameterError, match=r"f: x must be a real number, got \[\[1, 2\], \[1\]\]"):
            check([[1, 2], [1]])


def test_user_lagrangian_with_a_state_of_the_wrong_length():
    two = Lagrangian(n=2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 0.5 * q @ q)
    for bad in (jnp.ones(3), jnp.ones(5), jnp.ones((2, 2))):
        with pytest.raises(E.StateError, match=r"length 2 n = 4 .* n = 2 coordinates"):
            nhjax.simulate(two, bad, 1.0)
    with pytest.raises(E.ParameterError, match="n must be at least 1"):
        Lagrangian(n=0, T=lambda q, qd: qd @ qd)
    with pytest.raises(E.ParameterError, match="T must be a callable"):
        Lagrangian(n=1, T=3.0)
    with pytest.raises(E.ParameterError, match="no force"):
        Lagrangian(n=1, T=lambda q, qd: qd @ qd, control_dim=1)
    # outputs of the wrong shape, named at construction (autodiff would fail deep inside
    # the derivation of the equations with JAX's own words)
    with pytest.raises(E.ParameterError, match=r"T\(q, qd\) must return the kinetic energy, a scalar.*shape \(2,\)"):
        Lagrangian(n=2, T=lambda q, qd: 0.5 * qd**2)
    with pytest.raises(E.ParameterError, match=r"V\(q\) must return the potential energy"):
        Lagrangian(n=2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: q)
    with pytest.raises(E.ParameterError, match=r"force\(t, q, qd, u\) must return the generalized force, shape "
                                               r"\(2,\); it returns shape \(1,\)") as err:
        Lagrangian(n=2, T=lambda q, qd: 0.5 * qd @ qd, force=lambda t, q, qd, u: u, control_dim=1)
    assert err.value.name == "force"
    with pytest.raises(E.ParameterError, match="velocity_constraints.*a vector"):
        Lagrangian(n=2, T=lambda q, qd: 0.5 * qd @ qd, velocity_constraints=lambda t, q, qd: jnp.outer(qd, qd))
    with pytest.raises(E.ParameterError, match="invariant 'p'"):
        Lagrangian(n=2, T=lambda q, qd: 0.5 * qd @ qd, invariants={"p": lambda q, qd: qd})
    # a function abstract evaluation cannot read is left to the solve (not refused here)
    Lagrangian(n=1, T=lambda q, qd: 0.5 * float(qd[0]) ** 2)


def test_lie_lagrangian_velocity_of_the_wrong_length_and_off_group_poses():
    sk = SkateSE2()
    (g,), v = sk.initial_state(speed=1.0, phi_dot=0.5)
    for bad in (v[:2], jnp.ones(4)):
        with pytest.raises(E.StateError, match=r"velocity\) must have 3 entries for SkateSE2"):
            nhjax.simulate(sk, ((g,), bad), 1.0)
    with pytest.raises(E.StateError, match="structure of SkateSE2's state"):
        nhjax.simulate(sk, jnp.zeros(6), 1.0)
    scaled = g.at[:2, :2].multiply(2.0)
    with pytest.raises(E.GroupMembershipError, match=r"x0\[0\]\[0\] is not on SE\(2\).*3\.000e\+00") as err:
        nhjax.simulate(sk, ((scaled,), v), 1.0)
    assert err.value.name == "x0[0][0]" and err.value.residual == pytest.approx(3.0)
    flipped = g.at[:2, 0].multiply(-1.0)
    with pytest.raises(E.GroupMembershipError, match="det = -1"):
        nhjax.simulate(sk, ((flipped,), v), 1.0, project=True)


def test_falling_cat_parameters_named_by_the_argument_passed():
    with pytest.raises(E.ParameterError, match="mass must be positive, got 0") as err:
        FallingCat.from_dimensions(mass=0)
    assert err.value.name == "mass"
    with pytest.raises(E.ParameterError, match="mass must be positive, got -1"):
        FallingCat.from_dimensions(mass=-1)  # not "I1 must be positive" (a derived quantity)
    with pytest.raises(E.ParameterError, match="length must be positive, got -1"):
        FallingCat.from_dimensions(length=-1)
    with pytest.raises(E.ParameterError, match="radius must be positive, got -0.25"):
        FallingCat.from_dimensions(radius=-0.25)
    with pytest.raises(E.ParameterError, match="I1 must be positive, got -1"):
        FallingCatKinematic(I1=-1.0)
    with pytest.raises(E.ParameterError, match="lam must be finite and positive.*got nan"):
        FallingCatKinematic(lam=float("nan"))
    with pytest.raises(E.ParameterError, match=r"B must be positive, got -2.0 \(element \(3,\)"):
        FallingCat(B=np.array([1.0, 2.0, 3.0, -2.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]))  # batched: the member
    with pytest.raises(E.ParameterError, match="theta must be finite"):
        FallingCat().initial_state(float("inf"))


def test_a_system_that_needs_a_control_says_so():
    cat = FallingCatKinematic()
    with pytest.raises(E.ControlError, match="FallingCatKinematic needs a control.*pass control="):
        nhjax.simulate(cat, cat.initial_state(0.5), 1.0)

    class NeedsInput(AbstractSystem):  # a user system that does not declare requires_control
        control_dim = 1
        state_names = ("x",)

        def vector_field(self, t, x, u):
            return u[:1] * x

    with pytest.raises(E.ControlError, match="NeedsInput needs a control"):
        nhjax.simulate(NeedsInput(), jnp.ones(1), 1.0)
    with pytest.raises(E.ControlError, match="returned NaN or inf"):
        nhjax.simulate(cat, cat.initial_state(0.5), 1.0, control=lambda t, x: jnp.full(2, jnp.nan))


def test_shell_with_top_attitudes_and_radius():
    robot = ShellWithTop()
    (xy, Rsh, Rt), v = robot.initial_state(shell_omega=(1.0, 0.0, 0.0))
    with pytest.raises(E.GroupMembershipError, match=r"x0\[0\]\[2\] is not on SO\(3\)"):
        nhjax.simulate(robot, ((xy, Rsh, 2.0 * Rt), v), 0.1)
    with pytest.raises(E.GroupMembershipError, match="shell_attitude is not on SO"):
        robot.initial_state(shell_attitude=2.0 * np.eye(3))
    with pytest.raises(E.ParameterError, match="Rs must be finite and positive.*got inf"):
        ShellWithTop(Rs=float("inf"))
    with pytest.raises(E.ParameterError, match=r"It must be symmetric positive definite"):
        ShellWithTop(It=np.diag([1e-2, -1e-2, 1e-2]))
    # project=True replaces R^T R = 4 I by the nearest rotation (R itself) and the run goes on
    R = so3.exp(jnp.array([0.3, -0.2, 0.5]))
    x0 = robot.initial_state(top_attitude=R)
    (xy, Rsh, Rt), v = x0
    checked, _, _ = _check_inputs(robot, None, ((xy, Rsh, 2.0 * Rt), v), 0.0, 1e-8, True)
    np.testing.assert_allclose(checked[0][2], R, atol=1e-14)


def test_project_true_brings_a_norm_two_quaternion_onto_s3():
    ball = BallOnPlatter()
    x = ball.initial_state(u1=1.0, u2=0.5, u1_dot=0.2, u2_dot=1.0, spin=0.3)
    bad = x.at[3:7].multiply(2.0)
    with pytest.raises(E.ConstraintViolationError, match="position.*Pass project=True"):
        nhjax.simulate(ball, bad, 1.0)
    xp, _, _ = _check_inputs(ball, None, bad, 0.0, 1e-8, True)
    assert abs(float(jnp.linalg.norm(xp[3:7])) - 1.0) < 1e-14  # on S^3 (four Newton steps left 1e-7)
    res = ball.constraints(0.0, xp)
    assert max(float(jnp.max(jnp.abs(r))) for r in res.values()) < 1e-12
    np.testing.assert_allclose(xp[:3], x[:3], atol=1e-14)  # the contact and centre are untouched
    # a state the projection cannot reach: the error does not ask for project=True again
    class Stubborn(AbstractSystem):
        state_names = ("a", "b")

        def vector_field(self, t, x, u):
            return jnp.zeros(2)

        def constraints(self, t, x):
            return {"circle": (x @ x - 1.0)[None]}

    with pytest.raises(E.ProjectionError, match="did not converge.*defines no project") as err:
        nhjax.simulate(Stubborn(), jnp.array([2.0, 0.0]), 1.0, project=True)
    assert "Pass project=True" not in str(err.value)


def test_project_converged_reports_the_residual_reached():
    ball = BallOnPlatter()
    bad = ball.initial_state().at[3:7].multiply(2.0)
    one_round = eqx.filter_jit(lambda b, x: b.project(0.0, x))(ball, bad)  # four Newton steps: not yet on S^3
    assert abs(float(jnp.linalg.norm(one_round[3:7])) - 1.0) > 1e-9
    xp, res, rounds = eqx.filter_jit(lambda b, x: b.project_converged(0.0, x))(ball, bad)
    assert float(res) < 1e-13 and 1 < int(rounds) < 10
    assert float(res) == pytest.approx(float(ball.constraint_residual(0.0, xp)))


def test_traced_checks_are_runtime_errors_with_the_same_words():
    cat = FallingCat()
    x0 = cat.initial_state(0.8)
    run = jax.jit(lambda x: nhjax.simulate(cat, x, 1.0, saveat=2).xs)
    with pytest.raises(Exception, match="initial state x0 contains NaN or inf"):
        jax.block_until_ready(run(x0.at[1].set(jnp.nan)))
    # the checks of x0 are one runtime check (first_error_if): each condition still
    # raises its own words, and the first failing one is the one reported
    ctl = jax.jit(lambda x, a: nhjax.simulate(cat, x, 1.0, saveat=2, control=nhjax.Sinusoids(
        jnp.stack([a, 0.0]), jnp.zeros(2), jnp.ones(2), jnp.zeros(2))).xs)
    assert np.all(np.isfinite(np.asarray(ctl(x0, 0.01))))
    with pytest.raises(Exception, match="control\\(t0, x0\\) returned NaN or inf"):
        jax.block_until_ready(ctl(x0, jnp.nan))
    with pytest.raises(Exception, match="initial state x0 contains NaN or inf"):
        jax.block_until_ready(ctl(x0.at[1].set(jnp.nan), jnp.nan))
    ball = BallOnPlatter()
    xb = ball.initial_state()
    check = jax.jit(lambda x: _check_inputs(ball, None, x, 0.0, 1e-8, False)[0])
    np.testing.assert_allclose(check(xb), xb)
    with pytest.raises(Exception, match="violates constraint 'position'.*project=True"):
        jax.block_until_ready(check(xb.at[3:7].multiply(2.0)))
    span = jax.jit(lambda t1: nhjax.simulate(OSC, jnp.array([1.0, 0.0]), t1, saveat=2).xs)
    np.testing.assert_allclose(span(jnp.pi)[-1], [1.0, 0.0], atol=1e-6)  # a period of omega = 2
    with pytest.raises(Exception, match="t1 must be greater than t0"):
        jax.block_until_ready(span(-1.0))
    # traced save times and steps: checked before the solve, whose program has no checks
    times = jax.jit(lambda ts: nhjax.simulate(OSC, jnp.array([1.0, 0.0]), jnp.pi, saveat=ts).xs)
    np.testing.assert_allclose(times(jnp.array([0.0, 1.0, jnp.pi]))[-1], [1.0, 0.0], atol=1e-6)
    for bad in ([0.0, 2.0, 1.0], [0.0, 1.0, 4.0], [-0.5, 1.0, 2.0]):
        with pytest.raises(Exception, match="saveat times must be sorted and lie in"):
            jax.block_until_ready(times(jnp.array(bad)))
    fixed = jax.jit(lambda h: nhjax.simulate(OSC, jnp.array([1.0, 0.0]), jnp.pi, saveat=2, solver=nhjax.RKMK4(),
                                             dt0=h, diagnostics=False).xs)
    np.testing.assert_allclose(fixed(jnp.pi / 200)[-1], [1.0, 0.0], atol=1e-6)
    with pytest.raises(Exception, match="dt0 must be positive"):
        jax.block_until_ready(fixed(-0.01))


def test_time_spans_and_saved_times():
    x0 = jnp.array([1.0, 0.0])
    for t1, words in ((np.inf, "finite time, got inf"), (np.nan, "finite time, got nan"),
                      (0.0, "empty time span"), (-1.0, "reversed time span")):
        with pytest.raises(E.TimeSpanError, match=words):
            nhjax.simulate(OSC, x0, t1)
    with pytest.raises(E.TimeSpanError, match="at least 2"):
        nhjax.simulate(OSC, x0, 1.0, saveat=1)
    with pytest.raises(E.TimeSpanError, match="float"):
        nhjax.simulate(OSC, x0, 1.0, saveat=11.0)
    with pytest.raises(E.TimeSpanError, match="NaN or inf"):
        nhjax.simulate(OSC, x0, 1.0, saveat=jnp.array([0.0, jnp.nan]))
    with pytest.raises(E.TimeSpanError, match="non-empty"):
        nhjax.simulate(OSC, x0, 1.0, saveat=jnp.zeros(0))
    with pytest.raises(E.ParameterError, match="rtol must be positive"):
        nhjax.simulate(OSC, x0, 1.0, rtol=0.0)
    with pytest.raises(E.ParameterError, match="max_steps must be at least 1"):
        nhjax.simulate(OSC, x0, 1.0, max_steps=0)


def test_memory_is_checked_before_allocating():
    x0 = jnp.array([1.0, 0.0])
    with pytest.raises(E.ResourceError, match="saving 100000000000 times.*save fewer times") as err:
        nhjax.simulate(OSC, x0, 1.0, saveat=10**11)
    assert err.value.need > err.value.available > 0
    loss = lambda x: nhjax.simulate(OSC, x, 1.0, saveat=2, adjoint=nhjax.DiscreteAdjoint(max_steps=10**11)).xs[-1, 0]  # noqa: E731
    with pytest.raises(E.ResourceError, match="differentiated solve recording max_steps=100000000000"):
        jax.grad(loss)(x0)


class _DoubleIntegrator(AbstractSystem):
    control_dim = 1
    state_names = ("q", "v")

    def vector_field(self, t, x, u):
        return jnp.stack([x[1], u[0]])


def _effort(t, x, u):
    return 0.5 * u @ u


def test_ocp_refuses_bad_problems_at_construction():
    di = _DoubleIntegrator()
    for T in (np.inf, 0.0, -1.0, np.nan):
        with pytest.raises(controls.ProblemError, match="T (must be a finite time|= .* must be positive)"):
            controls.OCP(di, jnp.zeros(2), T, running_cost=_effort)
    with pytest.raises(controls.ProblemError, match="does not fit"):
        controls.OCP(di, jnp.zeros(3), 1.0, running_cost=_effort)
    with pytest.raises(controls.ProblemError, match="x0 contains NaN or inf at 'v'"):
        controls.OCP(di, jnp.array([0.0, jnp.inf]), 1.0, running_cost=_effort)
    with pytest.raises(controls.ProblemError, match=r"input 0 has u_lower = 1 >= u_upper = -1"):
        controls.OCP(di, jnp.zeros(2), 1.0, running_cost=_effort, u_lower=1.0, u_upper=-1.0)
    with pytest.raises(controls.ProblemError, match="u_lower contains NaN"):
        controls.OCP(di, jnp.zeros(2), 1.0, running_cost=_effort, u_lower=jnp.nan, u_upper=1.0)
    with pytest.raises(controls.ProblemError, match="running_cost must be a callable"):
        controls.OCP(di, jnp.zeros(2), 1.0, running_cost=2.0)
    with pytest.raises(controls.ProblemError, match="outside the chart") as err:
        controls.OCP(FallingCatKinematic(), jnp.zeros(3), 1.0, running_cost=_effort)
    assert isinstance(err.value, E.OutsideChartError) and err.value.guard == "sin_theta"
    ocp = controls.OCP(di, jnp.zeros(2), 1.0, running_cost=_effort)
    with pytest.raises(controls.ProblemError, match=r"covers \[0, 0.5\] but the problem's horizon is \[0, 1\]"):
        controls.solve_direct(ocp, controls.PiecewiseLinear(4, 0.5, 1))
    with pytest.raises(controls.ProblemError, match="rtol must be positive"):
        controls.solve_direct(ocp, controls.PiecewiseLinear(4, 1.0, 1), rtol=-1.0)
    with pytest.raises(controls.ProblemError, match="guess must be finite"):
        controls.solve_direct(ocp, controls.PiecewiseLinear(4, 1.0, 1), guess=jnp.full(5, jnp.nan))


def test_pontryagin_names_a_terminal_constraint_that_is_nan_at_the_start():
    """psi(x) = sqrt(x_q - 5) is undefined where the initial guess's extremal ends (x_q = 0):
    the error blames the terminal constraint, not the vector field."""
    ocp = controls.OCP(_DoubleIntegrator(), jnp.zeros(2), 1.0, running_cost=_effort,
                       terminal_constraints=lambda x: jnp.sqrt(x[:1] - 5.0))
    with pytest.raises(controls.ProblemError, match=r"terminal_constraints\(x\(T\)\) is NaN/inf at the start") as err:
        controls.solve_pontryagin(ocp)
    assert "vector field" not in str(err.value)
    with pytest.raises(controls.ProblemError, match="p0_guess must be finite"):
        controls.solve_pontryagin(ocp, p0_guess=jnp.array([jnp.nan, 0.0]))
    with pytest.raises(controls.ProblemError, match="solver must be one of"):
        controls.solve_pontryagin(ocp, solver="bfgs")


def test_eager_checks_raise_before_the_solve_runs_and_the_projected_start_is_solved(tmp_path, monkeypatch):
    """An eager simulate() traces its checks, its solve and its diagnostics before it runs
    any of them (each compiles in the background as soon as it is traced); the checks
    still run first: a start off the constraints raises without the solve's program ever
    being called, and with project=True the solve starts from the projected state (its
    first saved state is on S^3 to rounding, not at |p| = 2)."""
    from nhjax import _programs

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    called = []
    real_call = _programs.call

    def recording(name, *args, **kwargs):
        called.append(name)
        return real_call(name, *args, **kwargs)

    ball = BallOnPlatter()
    x = ball.initial_state(u1=1.0, u2=0.5, u1_dot=0.2, u2_dot=1.0, spin=0.3)  # a program of its own
    bad = x.at[3:7].multiply(2.0)
    monkeypatch.setattr(_programs, "call", recording)
    with pytest.raises(E.ConstraintViolationError, match="position.*Pass project=True"):
        nhjax.simulate(ball, bad, 0.5)
    assert called == ["report"]
    called.clear()
    tr = nhjax.simulate(ball, bad, 0.5, project=True)
    assert called == ["report", "simulate", "diagnose"]
    assert abs(float(jnp.linalg.norm(tr.xs[0, 3:7])) - 1.0) < 1e-14
    assert float(tr.constraint_drift["position"]) < 1e-12


@pytest.mark.slow(reason="compiles simulate's stages again as plain jitted programs (~10 s); the default "
                         "run checks the cache's route (test_first_answers, test_programs); make test-all")
def test_with_the_program_cache_off_gradients_and_checks_take_the_same_route(monkeypatch):
    """NHJAX_PROGRAM_CACHE=0: simulate() runs the same stages with plain jitted programs.
    A NaN start raises the named error before any solve; ``jax.grad`` of a final
    position (whose diagnostics program is not compiled in a thread: the tracers of the
    gradient cannot cross into one) is the exact one of the harmonic oscillator,
    q(T) = q0 cos(2T) (T = q'^2/2, V = 2q^2: omega = 2), to the solve's tolerance, and
    so is ``jax.jacfwd`` with ``adjoint=diffrax.ForwardMode()`` (docs/guides/cache.md)."""
    from nhjax import _programs

    monkeypatch.setenv("NHJAX_PROGRAM_CACHE", "0")
    assert _programs.directory() is None
    osc = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 2.0 * q @ q)
    with pytest.raises(E.StateError, match="NaN or inf"):
        nhjax.simulate(osc, jnp.array([jnp.nan, 0.0]), 1.0)

    def q_end(q0, adjoint=None):
        tr = nhjax.simulate(osc, jnp.stack([q0, 0.0]), 1.0, saveat=3, rtol=1e-10, atol=1e-10, adjoint=adjoint)
        assert "energy" in tr.invariant_drift  # the diagnostics program ran
        return tr.x_end[0]

    assert abs(float(jax.grad(q_end)(0.3)) - np.cos(2.0)) < 1e-8
    # forward mode, as the cache guide says: with diffrax's ForwardMode
    assert abs(float(jax.jacfwd(lambda q: q_end(q, diffrax.ForwardMode()))(0.3)) - np.cos(2.0)) < 1e-8


def test_checks_that_show_no_message_do_not_format_the_stack(monkeypatch):
    """equinox formats every frame of the Python stack for each check it traces, for the
    message of the "raise" mode. In the "nan" mode (controls' programs) and the "off"
    mode (a solve's own diffrax checks) nothing shows it: a simulate() traced inside
    ``controls.problem.nan_errors`` reads no stack. The checks still act: a NaN start
    gives NaN outputs, a good one the eager solve's state."""
    import traceback

    from controls.problem import nan_errors
    from nhjax import _programs

    def _clear_error_traces():  # (equinox caches its traced checks; a cached one reads no stack either)
        _programs._EQX_JIT_CHECK._cached.clear_cache()

    _clear_error_traces()
    walks = []
    real_walk = traceback.walk_stack
    monkeypatch.setattr(traceback, "walk_stack", lambda f: (walks.append(1), real_walk(f))[1])
    cat = FallingCat()
    x0 = cat.initial_state(0.8, chi_dot=0.5)
    with nan_errors():
        end = jax.jit(lambda x: nhjax.simulate(cat, x, 2.0, saveat=2).xs[-1])
        good, bad = end(x0), end(x0.at[2].set(jnp.nan))
    _clear_error_traces()
    assert walks == []
    assert bool(jnp.all(jnp.isnan(bad)))
    np.testing.assert_allclose(np.asarray(good), np.asarray(nhjax.simulate(cat, x0, 2.0, saveat=2).xs[-1]),
                               rtol=1e-12, atol=1e-12)


def test_physically_impossible_bodies_are_refused_at_the_edge_of_what_bodies_can_be():
    """Issue 40: inertias a body cannot have. Each rule is met with equality by a body
    that exists (accepted) and broken by one part in 1e9 beyond it (refused, naming every
    argument of the relation)."""
    from nhjax import mechanics
    from nhjax.scenes import RollingDisk, RollingSphereWall, ShellWithSuslovHinge, SuslovBundle, ThreeCylinders

    def refused(make, names, match):
        with pytest.raises(E.ParameterError, match=match) as err:
            make()
        assert set(names) <= set(err.value.names), err.value.names
        assert isinstance(err.value, ValueError)

    m, r, over = 2.0, 0.5, 1 + 1e-9
    shell = 2.0 / 3.0 * m * r**2  # a thin spherical shell: the largest J of a ball of mass m, radius r
    BallOnPlatter(m=m, r=r, J=shell)
    refused(lambda: BallOnPlatter(m=m, r=r, J=shell * over), ("J", "m", "r"), "thin spherical shell")
    refused(lambda: nhjax.scenes.BallInCone(m=m, r=r, J=shell * over), ("J", "m", "r"), "2/3 m r\\^2")
    RollingSphereWall(r=r, m=m, k=np.sqrt(2 / 3) * r)  # k: radius of gyration, J = m k^2
    refused(lambda: RollingSphereWall(r=r, m=m, k=np.sqrt(2 / 3) * r * over), ("k", "m", "r"), "m k\\^2")
    ShellWithSuslovHinge(ms=m, Rs=r, Is=shell)
    refused(lambda: ShellWithTop(ms=m, Rs=r, Is=shell * over), ("Is", "ms", "Rs"), "2/3 ms Rs\\^2")
    # a thin disk: axial moment exactly twice the transverse (cylinder_inertia at length -> 0)
    I_t, I_a = mechanics.cylinder_inertia(m, 1e-300, r)
    assert I_a == 2 * I_t
    RollingDisk(m=m, r=r, J1=I_a, J2=I_t)
    refused(lambda: RollingDisk(m=m, r=r, J1=I_a, J2=I_t / over), ("J1", "J2"), "at most twice")
    RollingDisk(m=m, r=r, J1=m * r**2, J2=m * r**2 / 2)  # a ring: all the mass on the rim
    refused(lambda: RollingDisk(m=m, r=r, J1=m * r**2 * over, J2=m * r**2), ("J1", "m", "r"), "rim")
    refused(lambda: ThreeCylinders(J_a=2.0 * over, J_t=1.0, m=100.0), ("J_a", "J_t"), "at most twice")
    refused(lambda: ThreeCylinders(J_l=1.0, J_lt=1.0, m_l=1.0, r1=1.0 / np.sqrt(over)), ("J_l", "m_l", "r1"), "rim")
    refused(lambda: FallingCat(lam=2.0 * over), ("lam",), "at most twice")
    FallingCat.from_dimensions(mass=1.0, length=1e-3, radius=0.5)  # a disk-like cylinder: lam -> 2
    # triangle inequality of principal moments: a flat lamina sits on the edge
    SuslovBundle(inertia=(1.0, 2.0, 3.0))
    refused(lambda: SuslovBundle(inertia=(1.0, 2.0, 3.0 * over)), ("inertia",), "exceeds the sum")
    refused(lambda: ShellWithSuslovHinge(inertia=(1e-3, 2e-3, 3e-3 * over)), ("inertia",), "exceeds the sum")
    R = np.asarray(so3.exp(jnp.array([0.3, -0.5, 0.2])))
    refused(lambda: ShellWithTop(It=R @ np.diag([0.01, 0.01, 0.02 * over]) @ R.T), ("It",), "exceeds the sum")
    # batched bodies: every member checked at once, the member named
    Is = np.stack([np.diag([1.0, 2.0, 3.0])] * 5)
    mechanics.RigidBody(jnp.ones(5), jnp.asarray(Is))
    Is[3] = np.diag([1.0, 1.0, 2.5])
    refused(lambda: mechanics.RigidBody(jnp.ones(5), jnp.asarray(Is)), ("inertia",), "member 3")
    refused(lambda: mechanics.Bodies([1.0, 1.0], np.stack([np.eye(3), np.diag([0.0, 1.0, 1.5])])), ("inertias",),
            "exceeds the sum")
    mechanics.Bodies([1.0, 1.0], np.stack([np.eye(3), np.diag([0.0, 1.0, 1.0])]))  # a rod: (0, I, I)


def test_a_start_outside_the_chart_is_one_error_wherever_it_is_found():
    """Issue 40: initial_state, simulate and an OCP refuse the same start with the same
    error, OutsideChartError (a ValueError, and the ChartSingularityError a solve raises
    at the chart's edge), naming the guard, its value and the argument; a scene that holds
    a batch of parameter sets refuses to build one state by name."""
    from nhjax.scenes import BallInCone, RollingDisk

    cat = FallingCat(chart_eps=1e-3)
    theta = 0.5e-3  # sin(theta) - chart_eps = -0.5e-3: just outside
    x0 = jnp.array([theta, 0.0, 0.0, 0.0, 0.0])
    errors = []
    for call in (lambda: cat.initial_state(theta), lambda: nhjax.simulate(cat, x0, 1.0),
                 lambda: nhjax.simulate(cat, x0, 1.0, on_guard="stop"),
                 lambda: controls.OCP(FallingCatKinematic(chart_eps=1e-3), x0[:3], 1.0,
                                      running_cost=lambda t, x, u: u @ u)):
        with pytest.raises(E.OutsideChartError) as err:
            call()
        errors.append(err.value)
    for e in errors:
        assert isinstance(e, ValueError) and isinstance(e, E.ChartSingularityError) and e.t == 0.0
        assert e.guard == "sin_theta" and "-0.0005 <= 0" in str(e) and "already outside the chart" in str(e)
    assert [e.name for e in errors] == ["theta", "x0", "x0", "x0"]
    cat.initial_state(1.5e-3)  # just inside: accepted
    with pytest.raises(E.OutsideChartError, match="set by theta") as err:
        RollingDisk().initial_state(theta=np.pi / 2 - 1e-4)
    assert err.value.guard == "tilt"
    with pytest.raises(E.OutsideChartError, match="rho = 0.5 puts the ball's centre") as err:
        BallInCone().initial_state(rho=0.5)
    assert err.value.name == "rho"
    # one state is one member's: a batched parameter is named, not a numpy error
    with pytest.raises(E.ParameterError, match="holds a batch of 2 parameter sets \\(lam has shape \\(2,\\)\\)"):
        FallingCat(lam=np.array([0.3, 0.4])).initial_state(0.5)
    with pytest.raises(E.ParameterError, match="gamma has shape"):
        BallInCone(gamma=np.array([0.9, 1.0])).initial_state()


def test_control_parametrizations_and_horizons_follow_simulates_rules():
    """Issue 40: parametrizations check n, T, dim on construction, T (and an OCP's
    horizon) by the rules simulate applies to t1, with the same words; plain lists are
    states wherever simulate takes one."""
    for kind in (controls.Chebyshev, controls.Fourier, controls.PiecewiseConstant, controls.PiecewiseLinear,
                 controls.CubicSpline):
        with pytest.raises(controls.ProblemError, match=f"{kind.__name__}: n must be at least"):
            kind(-3, 2.0, 2)
        with pytest.raises(controls.ProblemError, match="T = -2.0 must be positive"):
            kind(10, -2.0, 2)
        with pytest.raises(controls.ProblemError, match="dim must be at least 1"):
            kind(10, 2.0, 0)
    controls.Chebyshev(0, 2.0, 1)  # degree 0: a constant control
    with pytest.raises(E.TimeSpanError) as sim:
        nhjax.simulate(FallingCat(), FallingCat().initial_state(0.6), "2.0")
    words = str(sim.value).split("t1 ", 1)[1]  # "must be a time in seconds (a real number), got '2.0'"
    for make in (lambda: controls.Chebyshev(10, "2.0", 2),
                 lambda: controls.OCP(FallingCatKinematic(), [0.6, 0.0, 0.0], "2.0", running_cost=_effort)):
        with pytest.raises(controls.ProblemError) as err:
            make()
        assert str(err.value).endswith("T " + words)
    with pytest.raises(controls.ProblemError, match="T must be a finite time"):
        controls.OCP(FallingCatKinematic(), [0.6, 0.0, 0.0], np.inf, running_cost=_effort)
    cheb = controls.Chebyshev(3, 2.0, 2)
    with pytest.raises(controls.ProblemError, match="u_fn\\(t\\) must return the 2 inputs, shape \\(2,\\), got \\(3,\\)"):
        cheb.fit(lambda t: jnp.stack([t, t, t]))
    # an exact fit: (t, t^2) on [0, 2] is 1 + s and 3/2 + 2 s + T_2(s) / 2 with s = t - 1
    np.testing.assert_allclose(cheb.fit(lambda t: jnp.stack([t, t * t])).reshape(4, 2),
                               [[1.0, 1.5], [1.0, 2.0], [0.0, 0.5], [0.0, 0.0]], atol=1e-13)
    with pytest.raises(controls.ProblemError, match="takes 8 parameters, got shape \\(3,\\)"):
        cheb.signal(np.zeros(3))
    # a concrete parameter array closed over by the caller's jax.jit is checked on the
    # host, not traced (benchmarks/steering_peer.py's warm start did this)
    p = jnp.arange(8.0) / 10
    np.testing.assert_allclose(jax.jit(lambda t: cheb.signal(p)(t, None))(0.7), cheb.signal(p)(0.7, None),
                               rtol=1e-15, atol=0)
    # a plain list is a state: the same numbers as the array; refused by name if not numbers
    cat = FallingCatKinematic()
    ocp = controls.OCP(cat, [0.6, 0.0, 0.0], 2.0, running_cost=_effort)
    assert isinstance(ocp.x0, jax.Array) and ocp.x0.shape == (3,)
    osc_list = nhjax.simulate(OSC, [1.0, 0.0], 1.0, saveat=2, rtol=1e-10, atol=1e-10)
    osc_array = nhjax.simulate(OSC, jnp.array([1.0, 0.0]), 1.0, saveat=2, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(osc_list.xs, osc_array.xs)
    np.testing.assert_allclose(osc_list.xs[-1, 0], np.cos(2.0), atol=1e-8)
    with pytest.raises(E.StateError, match="x0 must be an array of real numbers") as err:
        nhjax.simulate(OSC, [1.0, "a"], 1.0)
    assert err.value.name == "x0"
