"""User-defined Lagrangians as first-class as shipped scenes: named states
(``traj["r"]``), declared invariants with units in ``summary()``, and consistent
initial states from chosen coordinates (``project(t, x, fixed=...)``)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.errors import ParameterError
from nhjax.mechanics.lagrangian import Lagrangian

# ---------------------------------------------------------------- a bicycle-like system
# q = (x, y, z, yaw, lean, steer, th_r, th_f): rear contact (x, y), a frame point at
# height z = h cos(lean) (holonomic), rolling rear wheel of radius R (fwd = R th_r'),
# no side slip, the kinematic-bicycle yaw rate L cos(lean) yaw' = tan(steer) fwd and a
# rolling front wheel R th_f' cos(steer) = fwd: 8 coordinates, 4 + 1 constraints.
R, WHEELBASE, H = 0.35, 1.0, 0.6
NAMES = ("x", "y", "z", "yaw", "lean", "steer", "th_r", "th_f")


def _vel_c(t, q, qd):
    _, _, _, yaw, lean, steer, _, _ = q
    xd, yd, _, yawd, _, _, thrd, thfd = qd
    fwd = xd * jnp.cos(yaw) + yd * jnp.sin(yaw)
    return jnp.stack([fwd - R * thrd, -xd * jnp.sin(yaw) + yd * jnp.cos(yaw),
                      WHEELBASE * jnp.cos(lean) * yawd - jnp.tan(steer) * fwd, R * thfd * jnp.cos(steer) - fwd])


def _bike():
    m = jnp.array([80.0, 80, 80, 10, 20, 1, 0.5, 0.5])
    return Lagrangian(8, T=lambda q, qd: 0.5 * jnp.sum(m * qd**2), V=lambda q: 80 * 9.81 * q[2],
                      velocity_constraints=_vel_c,
                      position_constraints=lambda t, q: jnp.atleast_1d(q[2] - H * jnp.cos(q[4])),
                      state_names=NAMES)


def _forward_speed(x):
    return float(x[8] * jnp.cos(x[3]) + x[9] * jnp.sin(x[3]))


GIVEN = ("x", "y", "yaw", "lean", "steer", "th_r", "th_f", "lean_dot", "steer_dot", "th_r_dot")


def test_bicycle_keeps_chosen_coordinates_and_solves_the_rest():
    bike = _bike()
    # lean 0.1 rad, steer 0.2 rad, lean rate 0.3 rad/s, forward speed 4 m/s (th_r' = 4/R);
    # z, and the velocities x', y', z', yaw', th_f' deliberately wrong
    x = jnp.zeros(16).at[2].set(0.5).at[4].set(0.1).at[5].set(0.2).at[12].set(0.3).at[14].set(4 / R)
    x = x.at[8].set(1.0).at[11].set(-2.0)
    x1 = eqx.filter_jit(lambda b, x: b.project(0.0, x, fixed=GIVEN))(bike, x)
    idx = [bike.state_names.index(n) for n in GIVEN]
    np.testing.assert_array_equal(np.asarray(x1)[idx], np.asarray(x)[idx])  # exactly as given
    for k, r in bike.constraints(0.0, x1).items():
        assert float(jnp.max(jnp.abs(r))) < 1e-12, (k, r)
    assert abs(_forward_speed(x1) - 4.0) < 1e-12
    # the dependent values are the closed-form ones
    assert abs(float(x1[2]) - H * np.cos(0.1)) < 1e-14
    assert abs(float(x1[11]) - np.tan(0.2) * 4.0 / (WHEELBASE * np.cos(0.1))) < 1e-12
    assert abs(float(x1[10]) + H * np.sin(0.1) * 0.3) < 1e-14  # z' = -h sin(lean) lean'
    # the unrestricted projection is free to move the speed (the 4 -> 0.05 m/s)
    assert abs(_forward_speed(eqx.filter_jit(lambda b, x: b.project(0.0, x))(bike, x)) - 4.0) > 1.0


def test_project_fixed_by_index_equals_by_name():
    bike = _bike()
    x = jnp.zeros(16).at[4].set(0.05).at[5].set(-0.1).at[14].set(2.0)
    index = tuple(NAMES.index(n) if n in NAMES else 8 + NAMES.index(n[:-4]) for n in GIVEN)
    proj = eqx.filter_jit(lambda b, x, fixed: b.project(0.0, x, fixed=fixed))
    by_name, by_index = proj(bike, x, GIVEN), proj(bike, x, index)
    np.testing.assert_array_equal(np.asarray(by_name), np.asarray(by_index))


def test_project_fixed_bad_input_names_the_argument():
    bike = _bike()
    x = jnp.zeros(16)
    with pytest.raises(ParameterError, match="fixed=.*'speed'"):
        bike.project(0.0, x, fixed=("speed",))
    with pytest.raises(ParameterError, match="free velocities"):
        bike.project(0.0, x, fixed=tuple(f"{n}_dot" for n in NAMES[:5]))
    with pytest.raises(ParameterError, match="state_names has 3 entries"):
        Lagrangian(8, T=lambda q, qd: qd @ qd, state_names=("a", "b", "c"))
    with pytest.raises(ParameterError, match="invariants"):
        Lagrangian(2, T=lambda q, qd: qd @ qd, invariants={"L": 3.0})


# ---------------------------------------------------------------- named states, invariants
def test_named_states_and_invariants_with_units_reach_the_trajectory():
    """A particle in the central potential -k/r, polar coordinates: the angular
    momentum m r^2 th' is declared as an invariant with its unit and must be conserved
    to the tolerance; traj["r"] is the radius, checked against the energy of the orbit."""
    m, k = 2.0, 3.0
    pol = Lagrangian(2, T=lambda q, qd: 0.5 * m * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2), V=lambda q: -k / q[0],
                     state_names=("r", "th"),
                     invariants={"angular momentum": (lambda q, qd: m * q[0] ** 2 * qd[1], "kg m^2/s")})
    assert pol.state_names == ("r", "th", "r_dot", "th_dot")
    x0 = jnp.array([1.0, 0.0, 0.0, 1.0])  # at periapsis/apoapsis: r' = 0
    traj = nhjax.simulate(pol, x0, 5.0, rtol=1e-11, atol=1e-11, saveat=51)
    key = "angular momentum [kg m^2/s]"
    assert key in traj.invariants and key in traj.summary()
    assert float(traj.invariant_drift[key]) < 1e-9
    assert float(traj.invariants[key][0]) == pytest.approx(m * 1.0)
    # radial energy balance: E = m r'^2/2 + L^2/(2 m r^2) - k/r at every saved time
    r, rd, L = traj["r"], traj["r_dot"], traj.invariants[key]
    E = 0.5 * m * rd**2 + L**2 / (2 * m * r**2) - k / r
    np.testing.assert_allclose(np.asarray(E), float(E[0]), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(traj["th"]), np.asarray(traj.xs[:, 1]))
