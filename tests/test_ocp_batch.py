"""Grids of optimal-control problems in one call (controls.solve_pontryagin_batch).

On the chart somersault (controls.tasks.velocity_somersault_chart): each member of a
batch is the same solve as alone, the members on the fixed-theta loop's holonomy
meet the loop's closed-form extremal, members that differ in structure are refused
before any numerics, and a member that fails (or holds NaN) does not spoil the others.
"""

import numpy as np
import pytest

import controls
from controls.tasks import fixed_theta_costates, torque_somersault, velocity_somersault_chart
from nhjax.scenes import FallingCat, FallingCatKinematic

T = 2.0


def _holonomy(cat, th):
    c, s = np.cos(th), np.sin(th)
    return -2 * np.pi * cat.lam * c / (s * s + cat.lam * c * c)


def _loop_cost(cat, th):
    """Vibrational energy of the fixed-theta loop: I1 lam s^2/D (2 pi/T)^2 T (theta' = 0)."""
    s, c = np.sin(th), np.cos(th)
    return cat.I1 * cat.lam * s * s / (s * s + cat.lam * c * c) * (2 * np.pi / T) ** 2 * T


def _members(cat, bends, offsets):
    ocps = [velocity_somersault_chart(cat, th, _holonomy(cat, th) + d, T) for th, d in zip(bends, offsets)]
    z = np.stack([np.concatenate(fixed_theta_costates(cat, th, T)) for th in bends])
    return ocps, z


def test_each_member_is_its_own_solve_and_the_loop_members_are_exact():
    """Four members (two bends on their loop's holonomy, two turned 0.15-0.2 rad off
    it, one on a cat of other inertia): the batch's cost, costates and residual are
    solve_pontryagin's on each alone (to rounding), and on the holonomy the cost is the
    loop's closed form and p0 the loop's exact costates."""
    cat, other = FallingCatKinematic(), FallingCatKinematic(I1=0.12, lam=0.4, B=2.0)
    ocps, z = _members(cat, [0.5, 0.6, 0.7], [0.0, -0.2, 0.15])
    ocps.append(velocity_somersault_chart(other, 0.8, _holonomy(other, 0.8), T))
    z = np.vstack([z, np.concatenate(fixed_theta_costates(other, 0.8, T))])
    r = controls.solve_pontryagin_batch(ocps, z[:, :3], z[:, 3:], progress=False)
    assert list(r.status) == ["converged"] * 4 and r.converged.all() and r.reasons == [""] * 4
    assert r.residual.max() < 1e-9 and r.violation.max() < 1e-9
    for i, ocp in enumerate(ocps):
        # the violation reported is the extremal's own end against the target
        target = np.asarray(ocp.terminal_constraints.target)
        assert abs(r.violation[i] - np.abs(r.xs[i, -1, :3] - target).max()) < 1e-15
        alone = controls.solve_pontryagin(ocp, z[i, :3], z[i, 3:], progress=False)
        assert abs(alone.cost - r.cost[i]) <= 1e-12 * abs(alone.cost)
        np.testing.assert_allclose(r.p0[i], alone.p0, rtol=0, atol=1e-9)
        np.testing.assert_allclose(r.xs[i], np.asarray(alone.trajectory.xs), rtol=0, atol=1e-9)
    for i, (c, th) in enumerate(((cat, 0.5), (other, 0.8))):
        k = 0 if i == 0 else 3
        assert abs(r.cost[k] - _loop_cost(c, th)) < 1e-10 * _loop_cost(c, th)
        np.testing.assert_allclose(r.p0[k], np.asarray(fixed_theta_costates(c, th, T)[0]), rtol=0, atol=1e-9)
    # the controls returned are u* along each extremal: theta' = u1 integrates to theta
    ts, xs, us = r.ts[1], r.xs[1], r.controls[1]
    theta = xs[0, 0] + np.concatenate([[0.0], np.cumsum(0.5 * (us[1:, 0] + us[:-1, 0]) * np.diff(ts))])
    assert np.abs(theta - xs[:, 0]).max() < 1e-4


def test_members_that_differ_in_structure_are_refused_by_name():
    """Another state size (a torque-driven cat) or another type is a GridError naming
    the member, raised before anything is traced."""
    cat = FallingCatKinematic()
    chart = velocity_somersault_chart(cat, 0.6, -np.pi, T)
    torque = torque_somersault(FallingCat(), 0.6, -np.pi, T)
    with pytest.raises(controls.GridError, match="problem 1"):
        controls.solve_pontryagin_batch([chart, torque], progress=False)
    with pytest.raises(controls.ProblemError, match="member 1 is a str"):
        controls.solve_pontryagin_batch([chart, "not a problem"], progress=False)
    with pytest.raises(controls.ProblemError, match=r"shape \(3,\).*\(2, 3\)"):
        controls.solve_pontryagin_batch([chart, chart], np.zeros((3, 3)), progress=False)
    with pytest.raises(controls.ProblemError, match="non-empty"):
        controls.solve_pontryagin_batch([], progress=False)


def test_a_failing_member_does_not_spoil_the_others():
    """A member far from its start (bend 1.0 asked to turn by -4 rad straight from its
    loop) fails, a member with a NaN guess is flagged and not run; the others converge
    to exactly what they reach in a batch without them, and a budget of one step
    reports max_iterations for every member it stops."""
    cat = FallingCatKinematic()
    good, zg = _members(cat, [0.5, 0.6], [-0.2, 0.1])
    far = velocity_somersault_chart(cat, 1.0, -4.0, T)
    zf = np.concatenate(fixed_theta_costates(cat, 1.0, T))
    znan = zg[0].copy()
    znan[1] = np.nan
    ocps, z = good + [far, good[0]], np.vstack([zg, zf, znan])
    # (lanes=2: groups of two and a remainder of one, the good pair a group of its own as in
    # the batch without the others)
    r = controls.solve_pontryagin_batch(ocps, z[:, :3], z[:, 3:], lanes=2, progress=False)
    clean = controls.solve_pontryagin_batch(good, zg[:, :3], zg[:, 3:], progress=False)
    assert list(r.status[:2]) == ["converged", "converged"]
    assert r.status[2] in ("non_finite", "stalled", "max_iterations") and r.reasons[2]
    assert r.status[3] == "non_finite_input" and "NaN" in r.reasons[3] and np.isnan(r.cost[3])
    np.testing.assert_array_equal(r.cost[:2], clean.cost)
    np.testing.assert_array_equal(r.p0[:2], clean.p0)
    assert r.counts()["converged"] == 2
    short = controls.solve_pontryagin_batch(good, zg[:, :3], zg[:, 3:], max_steps=1, progress=False)
    assert list(short.status) == ["max_iterations"] * 2 and "1 steps" in short.reasons[0]
    with pytest.raises(controls.ProblemError, match="every member"):
        controls.solve_pontryagin_batch([good[0]], znan[:3], znan[3:], progress=False)


def test_continuation_along_the_grid_converges_a_member_from_its_neighbour():
    """Six turns of the bent cat (bend 1.0) from its loop's holonomy to -4 rad, all from
    the loop's costates: the farthest fails from there; with grid=(6,) it is solved again
    from its converged neighbour's solution and converges, to an extremal that
    solve_pontryagin confirms (converged at once from it, the same cost to 1e-12); the
    grid's shape is checked before any numerics."""
    cat = FallingCatKinematic()
    turns = _holonomy(cat, 1.0) + np.linspace(0.0, -4.0 - _holonomy(cat, 1.0), 6)
    ocps = [velocity_somersault_chart(cat, 1.0, t, T) for t in turns]
    z = np.concatenate(fixed_theta_costates(cat, 1.0, T))
    plain = controls.solve_pontryagin_batch(ocps, z[:3], z[3:], progress=False)
    assert not plain.converged[-1] and (plain.started_from == -1).all()
    r = controls.solve_pontryagin_batch(ocps, z[:3], z[3:], grid=(6,), progress=False)
    assert r.converged.all() and r.started_from[-1] >= 0
    np.testing.assert_array_equal(r.cost[plain.converged], plain.cost[plain.converged])
    alone = controls.solve_pontryagin(ocps[-1], r.p0[-1], r.nu[-1], progress=False)
    assert alone.converged and alone.iterations <= 2
    assert abs(alone.cost - r.cost[-1]) <= 1e-12 * abs(alone.cost)
    with pytest.raises(controls.ProblemError, match=r"grid \(2, 2\) does not hold the 6"):
        controls.solve_pontryagin_batch(ocps, z[:3], z[3:], grid=(2, 2), progress=False)
