"""Roll-ring transmission (seed 002, 9.8-9.13): the energy balance with the damper's
dissipation integrated (checked against an independent quadrature of the saved
velocities), the drive's work, the exact tilt beta(t) (J_r beta'' = N(t)) and the
travel of the ring body u_r = int c tan(beta), and the five constraints."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import simpson

import nhjax
from nhjax import errors as E
from nhjax.scenes.roll_ring import RollRing, drive_profile

# one compiled program for every solve below (steps land on the kinks of the drive moment)
SOLVE = dict(saveat=4001, rtol=1e-10, atol=1e-10, jump_ts=RollRing.kink_times())


def test_initial_state_is_consistent(rng):
    rr = RollRing(drive_speed=0.7)
    for _ in range(4):
        x0 = rr.initial_state(u_r=rng.normal(), beta=rng.uniform(-1, 1), u_s=rng.normal(), alpha1=rng.normal(),
                              alpha2=rng.normal(), beta_dot=rng.normal(), u_s_dot=rng.normal(),
                              alpha1_dot=rng.normal(), alpha2_dot=rng.normal())
        assert float(rr.constraint_residual(0.0, x0)) < 1e-15
        assert float(x0[18]) == 0.0 and float(x0[19]) == 0.0
        assert float(rr.energy_balance(x0)) == pytest.approx(float(rr.mechanical_energy(x0)))


def test_energy_plus_dissipated_equals_initial_energy():
    """Shaft at rest, no moment: E(t) + D(t) = E(0), and D(t) is the integral of
    delta (u_s' - u_r')^2 over the saved velocities (Simpson), not only the ledger."""
    rr = RollRing(drive_speed=0.0, moment_scale=0.0)
    x0 = rr.initial_state(u_s=0.1, alpha1=0.5, alpha2=-0.3, u_s_dot=0.2)
    tr = nhjax.simulate(rr, x0, 10.0, **SOLVE)
    ts, xs = np.asarray(tr.ts), np.asarray(tr.xs)
    E = np.asarray([float(rr.mechanical_energy(x)) for x in xs[::100]])
    D, W = xs[::100, 18], xs[::100, 19]
    assert D[-1] > 0.1 * abs(E[0] - rr.mechanical_energy(rr.initial_state())) > 0  # the damper does take energy
    np.testing.assert_allclose(E + D, E[0], atol=1e-8)
    assert np.abs(W).max() < 1e-9  # no work in: the pivots' constraint forces do none
    rate = float(rr.delta) * (xs[:, 11] - xs[:, 9]) ** 2
    quad = np.array([simpson(rate[: i + 1], x=ts[: i + 1]) for i in range(100, 4001, 100)])
    np.testing.assert_allclose(quad, D[1:], atol=1e-7)
    assert float(tr.invariant_drift["energy_balance"]) < 1e-8
    assert max(float(v) for v in tr.constraint_drift.values()) < 1e-12


def test_driven_transmission_balance_and_exact_tilt():
    """The seed's run: the moment tilts the rings, the shaft drives the ring body, the absorber
    and the pendulum follow. E + D - W stays constant; beta(t) is the double integral of
    N / J_r; u_r(t) = int c tan(beta) (the nonholonomic drive (9.8))."""
    rr = RollRing()
    tr = nhjax.simulate(rr, rr.initial_state(), 10.0, **SOLVE)
    assert not tr.guard
    ts, xs = np.asarray(tr.ts), np.asarray(tr.xs)
    assert float(tr.invariant_drift["energy_balance"]) < 1e-9
    assert max(float(v) for v in tr.constraint_drift.values()) < 1e-12
    assert xs[-1, 19] > 5e-4 and xs[-1, 18] > 1e-5  # the drive supplied work, the damper took some
    # exact tilt: beta(t) = int_0^t (t - s) N(s) / J_r ds (N from the profile, fine Simpson)
    s = np.linspace(0.0, 10.0, 200001)
    N = float(rr.moment_scale) * np.asarray(drive_profile(jnp.asarray(s)))
    for t in (1.0, 2.5, 6.25, 10.0):
        k = s <= t
        beta = simpson((t - s[k]) * N[k], x=s[k]) / float(rr.J_r)
        # steps land on the kinks of N (jump_ts); without them the error is 3e-9 .. 2e-8 here
        assert float(np.interp(t, ts, xs[:, 1])) == pytest.approx(beta, abs=1e-9)
    assert xs[:, 1].max() == pytest.approx(0.1, abs=1e-6)  # held at a = 1e-3 * 0.5 s * ... / J_r = 0.1 rad
    # travel of the ring body: u_r(t) = c int tan(beta)
    travel = simpson(float(rr.drive_speed) * np.tan(xs[:, 1]), x=ts)
    assert xs[-1, 0] == pytest.approx(travel, abs=1e-8)
    assert xs[-1, 0] > 0.3 and abs(xs[-1, 2] - xs[-1, 0]) < 0.05  # the absorber follows the ring body


def test_tilt_guard_and_bad_input():
    with pytest.raises(E.OutsideChartError, match="set by beta"):
        RollRing().initial_state(beta=2.0)
    with pytest.raises(E.ParameterError, match="m_r"):
        RollRing(m_r=0.0)
    with pytest.raises(E.ParameterError, match="delta"):
        RollRing(delta=-1.0)
    rr = RollRing(moment_scale=0.05)  # 50 x the seed's moment: tilts past pi/2
    tr = nhjax.simulate(rr, rr.initial_state(), 10.0, on_guard="stop", **SOLVE)
    assert tr.guard == "tilt" and float(tr.ts[-1]) < 10.0
