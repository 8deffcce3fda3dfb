"""simulate(): clear errors for bad input, failures reported with their time,
the same answers eagerly and under jit, and honest diagnostics."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.mechanics import Lagrangian
from nhjax.scenes import FallingCat, FallingCatAttitudes

OSC = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 0.5 * 4.0 * q @ q)  # omega = 2


def test_harmonic_oscillator_exact_and_diagnostics():
    tr = nhjax.simulate(OSC, jnp.array([1.0, 0.0]), 3.0, rtol=1e-11, atol=1e-11, saveat=31)
    np.testing.assert_allclose(tr.xs[:, 0], np.cos(2 * tr.ts), atol=1e-9)
    assert tr.xs.shape == (31, 2) and tr.us is None and tr.work is None
    assert float(tr.invariant_drift["energy"]) < 1e-9
    assert int(tr.num_accepted_steps) > 10
    assert "energy" in tr.summary()
    ts = jnp.array([0.0, 0.5, 2.5])
    tr2 = nhjax.simulate(OSC, jnp.array([1.0, 0.0]), 3.0, saveat=ts, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(tr2.ts, ts)
    np.testing.assert_allclose(tr2.xs[:, 0], np.cos(2 * ts), atol=1e-9)


def test_bad_inputs_are_named():
    cat = FallingCat()
    x0 = cat.initial_state(0.8)
    with pytest.raises(ValueError, match="expects 5 components"):
        nhjax.simulate(cat, jnp.zeros(4), 1.0)
    with pytest.raises(ValueError, match="NaN"):
        nhjax.simulate(cat, x0.at[1].set(jnp.nan), 1.0)
    with pytest.raises(ValueError, match="2 inputs"):
        nhjax.simulate(cat, x0, 1.0, control=lambda t, x: jnp.zeros(3))
    with pytest.raises(TypeError, match="callable"):
        nhjax.simulate(cat, x0, 1.0, control=jnp.zeros(2))
    with pytest.raises(ValueError, match="takes no control"):
        nhjax.simulate(OSC, jnp.array([1.0, 0.0]), 1.0, control=lambda t, x: jnp.zeros(1))
    with pytest.raises(ValueError, match="greater than t0"):
        nhjax.simulate(cat, x0, 0.0)
    with pytest.raises(ValueError, match="sorted"):
        nhjax.simulate(cat, x0, 1.0, saveat=jnp.array([0.5, 0.2]))
    with pytest.raises(ValueError, match="fixed-step"):
        nhjax.simulate(cat, x0, 1.0, solver=diffrax.Euler())
    with pytest.raises(ValueError, match="on_guard"):
        nhjax.simulate(cat, x0, 1.0, on_guard="ignore")
    att = FallingCatAttitudes(0.1, 0.3, 2.0)
    with pytest.raises(nhjax.SystemKindError, match="drift off the group"):
        nhjax.simulate(att, att.initial_state(0.8), 1.0, solver=diffrax.Tsit5())


def test_max_steps_exhaustion_reports_time():
    with pytest.raises(nhjax.IntegrationError, match="max_steps=5 exhausted") as err:
        nhjax.simulate(OSC, jnp.array([1.0, 0.0]), 100.0, max_steps=5)
    assert 0 < err.value.t < 100.0
    assert err.value.trajectory.ts[-1] == pytest.approx(err.value.t)


def test_nan_in_vector_field_reports_time():
    """q'' = 1/(2 sqrt(1 - q)) reaches q = 1 (where it turns NaN) at a finite time."""
    sys = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: jnp.sqrt(1.0 - q[0]))
    with pytest.raises(nhjax.IntegrationError, match="NaN") as err:
        nhjax.simulate(sys, jnp.array([0.0, 0.5]), 5.0, max_steps=2000)
    # energy: v^2/2 + sqrt(1 - q) = 1.125, so q reaches 1 with speed 1.5; it started at speed 0.5
    assert 0.5 < err.value.t < 1.5
    # with a fixed step the state itself turns NaN: reported between two saved times
    with pytest.raises(nhjax.IntegrationError, match="state became NaN") as err:
        nhjax.simulate(sys, jnp.array([0.0, 0.5]), 5.0, solver=diffrax.Euler(), dt0=0.01)
    assert 0.5 < err.value.t < 1.6


class Gain(eqx.Module):
    k: jax.Array

    def __call__(self, t, x):
        return jnp.stack([-self.k * x[3], -self.k * x[4]])


def test_same_result_under_jit_and_runtime_errors():
    cat = FallingCat()
    x0 = cat.initial_state(0.8, theta_dot=0.3, chi_dot=0.5)
    eager = nhjax.simulate(cat, x0, 2.0, control=Gain(jnp.asarray(0.05)), saveat=5)
    run = jax.jit(lambda x, k: nhjax.simulate(cat, x, 2.0, control=Gain(k), saveat=5).xs)
    np.testing.assert_allclose(run(x0, jnp.asarray(0.05)), eager.xs, atol=1e-14)
    # the damping gain removes energy: the work is negative and balances the energy change
    assert float(eager.work[-1]) < 0 and float(eager.invariant_drift["energy - work"]) < 1e-7
    # tolerances as traced arguments (one compiled sweep over rtol), x0 a closed-over constant
    by_tol = jax.jit(lambda tol: nhjax.simulate(cat, x0, 2.0, control=Gain(jnp.asarray(0.05)), saveat=5,
                                                rtol=tol, atol=tol).xs)
    np.testing.assert_allclose(by_tol(1e-8), eager.xs, atol=1e-14)
    assert float(jnp.max(jnp.abs(by_tol(1e-4) - eager.xs))) > 1e-9  # the tolerance does reach the solve
    bad = jax.jit(lambda x: nhjax.simulate(cat, x, 2.0, max_steps=3).xs)
    with pytest.raises(Exception, match="max_steps exhausted, or NaN"):
        jax.block_until_ready(bad(x0))
    toward_zero = jax.jit(lambda x: nhjax.simulate(cat, x, 2.0).xs)
    with pytest.raises(Exception, match="chart guard"):
        jax.block_until_ready(toward_zero(cat.initial_state(0.3, theta_dot=-1.0)))


@pytest.mark.slow  # (20-50 s; make test-all)
def test_a_projected_solve_saves_the_same_states_eager_and_under_jit():
    """A projected solve's saved states (dense output between projected steps) are
    projected onto the constraints: in an eager call by its diagnostics program (with or
    without diagnostics), under jit inside the caller's program. Both give the same
    states, on the constraints to round-off, where the unprojected dense output is off
    them by the integration error."""
    disk = nhjax.scenes.RollingDisk()
    system = disk.quaternion_model()
    x0 = disk.to_quaternion_state(disk.initial_state(theta=0.3, phi_dot=0.4, theta_dot=0.2, psi_dot=1.5))
    eager = nhjax.simulate(system, x0, 4.0, saveat=41, rtol=1e-6, atol=1e-6)
    lean = nhjax.simulate(system, x0, 4.0, saveat=41, rtol=1e-6, atol=1e-6, diagnostics=False)
    jitted = jax.jit(lambda x: nhjax.simulate(system, x, 4.0, saveat=41, rtol=1e-6, atol=1e-6).xs)(x0)
    raw = nhjax.simulate(system, x0, 4.0, saveat=41, rtol=1e-6, atol=1e-6, project_steps=False)

    def worst(xs):
        return max(float(np.max(np.abs(np.asarray(v))))
                   for v in jax.vmap(lambda x: system.constraints(0.0, x))(jnp.asarray(xs)).values())

    np.testing.assert_allclose(eager.xs, jitted, atol=1e-13)
    np.testing.assert_allclose(lean.xs, eager.xs, atol=1e-14)
    assert worst(eager.xs) < 1e-13 and worst(jitted) < 1e-13
    assert worst(raw.xs) > 1e-9  # (without projection the saved states drift off)


class _WholeProjection(nhjax.scenes.ThreeCylinders):
    """ThreeCylinders whose steps end with the whole projection: redefining ``project``
    turns the split off (``splits_projection``)."""

    def project(self, t, x, fixed=None):
        return super().project(t, x, fixed)


class _WholeProjectionCat(nhjax.scenes.FallingCatLagrangian):
    def project(self, t, x, fixed=None):
        return super().project(t, x, fixed)


@pytest.mark.slow  # (20-50 s; make test-all)
def test_the_split_projection_takes_the_steps_of_the_whole_one():
    """A projected solve of a constrained Lagrangian projects the positions after each
    step and the velocities with the next step's first stage (one evaluation of M and A
    for both). The states it steps from are those of the whole projection after each
    step: same steps, same saved and final states to round-off, eagerly, under jit and
    with the work of an input tracked; the final state, whose velocities no next step
    projects, is on the constraints. Without the velocity half the states part by the
    integration error."""
    split_sys, whole_sys = nhjax.scenes.ThreeCylinders(), _WholeProjection()
    assert split_sys.splits_projection and not whole_sys.splits_projection
    x0 = split_sys.initial_state()
    split = nhjax.simulate(split_sys, x0, 6.0, saveat=31)
    whole = nhjax.simulate(whole_sys, x0, 6.0, saveat=31)
    assert int(split.num_accepted_steps) == int(whole.num_accepted_steps) > 20
    assert int(split.num_rejected_steps) == int(whole.num_rejected_steps)
    np.testing.assert_allclose(split.xs, whole.xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(split.x_end, whole.x_end, rtol=0, atol=1e-12)
    assert float(split_sys.constraint_residual(split.t_final, split.x_end)) < 1e-13
    jitted = jax.jit(lambda x: nhjax.simulate(split_sys, x, 6.0, saveat=31).x_end)(x0)
    np.testing.assert_allclose(jitted, whole.x_end, rtol=0, atol=1e-12)

    # positions only (the velocity half left out): the solve drifts off the whole one
    class _PositionsOnly(nhjax.scenes.ThreeCylinders):
        def projected_field(self, t, x, apply, control=None):
            return super().projected_field(t, x, False, control)

    drift = nhjax.simulate(_PositionsOnly(), x0, 6.0, saveat=31)
    assert float(np.max(np.abs(np.asarray(drift.xs) - np.asarray(whole.xs)))) > 1e-10

    # an input acting, its work tracked (the work rides in the state)
    cat, whole_cat = nhjax.scenes.FallingCatLagrangian(), _WholeProjectionCat()
    xc = jnp.array([1.0, 0.0, 0.0, 0.1, 0.3, 0.0])
    xc = cat.project(0.0, xc)
    u = nhjax.Sinusoids([0.0, 0.0], [0.3, 0.2], [2.0, 3.0], [0.0, np.pi / 2])
    a = nhjax.simulate(cat, xc, 3.0, control=u, track_work=True, saveat=11)
    b = nhjax.simulate(whole_cat, xc, 3.0, control=u, track_work=True, saveat=11)
    assert int(a.num_accepted_steps) == int(b.num_accepted_steps)
    np.testing.assert_allclose(a.xs, b.xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.work, b.work, rtol=0, atol=1e-12)
    assert float(np.max(np.abs(a.work))) > 1e-3


def test_signals():
    pl = nhjax.PiecewiseLinear([0.0, 1.0, 3.0], [[0.0, 1.0], [2.0, 1.0], [2.0, -1.0]])
    np.testing.assert_allclose(pl(0.5), [1.0, 1.0])
    np.testing.assert_allclose(pl(2.0), [2.0, 0.0])
    np.testing.assert_allclose(pl.breakpoints, [1.0])
    pc = nhjax.PiecewiseConstant([0.0, 1.0, 3.0], [[1.0], [5.0]])
    np.testing.assert_allclose([pc(0.2)[0], pc(1.0)[0], pc(2.9)[0]], [1.0, 5.0, 5.0])
    with pytest.raises(ValueError, match="one value row per interval"):
        nhjax.PiecewiseConstant([0.0, 1.0], [[1.0], [2.0]])
    with pytest.raises(ValueError, match="share one shape"):
        nhjax.Sinusoids([0.0, 1.0], [1.0], [2.0, 3.0])
    # a kinked force: x'' = u(t), exact double integral of a piecewise-linear signal
    sys = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, force=lambda t, q, qd, u: u, control_dim=1)
    u = nhjax.PiecewiseLinear([0.0, 1.0, 2.0], [0.0, 1.0, 0.0])
    tr = nhjax.simulate(sys, jnp.zeros(2), 2.0, control=u, saveat=2, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tr.xs[-1], [1.0, 1.0], atol=1e-12)  # x(2) = 1, v(2) = 1


def test_new_values_of_the_same_structure_do_not_trace_again(capsys):
    """simulate() with another initial state, horizon, tolerances or control coefficients
    reuses the traced and compiled solve (traces counted); the progress bar counts
    simulated seconds and changes the result only by round-off (a program of its own)."""
    import importlib

    sim = importlib.import_module("nhjax.integrate.simulate")
    cat = FallingCat()
    ctrl = nhjax.Sinusoids([0.0, 0.0], [0.02, 0.01], [1.0, 2.0], [0.0, 0.5])
    nhjax.simulate(cat, cat.initial_state(0.8, chi_dot=0.5), 2.0, control=ctrl, rtol=1e-8, atol=1e-8)
    before = sim.TRACES["solve"]
    other = nhjax.Sinusoids([0.01, 0.0], [0.03, 0.02], [1.5, 0.5], [0.1, 0.2])
    x0 = cat.initial_state(0.9, chi_dot=0.7)
    tr = nhjax.simulate(cat, x0, 3.0, control=other, rtol=1e-9, atol=1e-9)
    assert sim.TRACES["solve"] == before
    ref = nhjax.simulate(cat, x0, 3.0, control=other, rtol=1e-9, atol=1e-9, saveat=jnp.linspace(0.0, 3.0, 101))
    np.testing.assert_allclose(tr.xs, ref.xs, rtol=1e-13, atol=1e-13)
    bar = nhjax.simulate(cat, x0, 3.0, control=other, rtol=1e-9, atol=1e-9, progress=True)
    np.testing.assert_allclose(bar.xs, tr.xs, rtol=1e-13, atol=1e-14)  # another program: round-off apart
    assert int(bar.num_steps) == int(tr.num_steps)
    err = capsys.readouterr().err
    assert "t = 3 of 3 s" in err
