"""Grids of optimal-control problems in one call (controls.solve_pontryagin_batch and
controls.solve_direct_batch).

On the chart somersault (controls.tasks.velocity_somersault_chart): each member of a
batch is the same solve as alone, the members on the fixed-theta loop's holonomy
meet the loop's closed-form extremal, members that differ in structure are refused
before any numerics, and a member that fails (or holds NaN) does not spoil the others.
"""

import equinox as eqx
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
    # by default the members run as two shares of one program (two members each) in two
    # threads: the first two members alone in one program (of that shape: no new compile)
    # give the same bits, and so do three members (the second share padded with a copy of
    # its first member)
    fields = ("p0", "nu", "cost", "violation", "residual", "iterations", "xs", "ts", "controls")
    two = controls.solve_pontryagin_batch(ocps[:2], z[:2, :3], z[:2, 3:], progress=False, workers=1)
    three = controls.solve_pontryagin_batch(ocps[:3], z[:3, :3], z[:3, 3:], progress=False, workers=2)
    for f in fields:
        np.testing.assert_array_equal(getattr(two, f), getattr(r, f)[:2], err_msg=f)
        np.testing.assert_array_equal(getattr(three, f), getattr(r, f)[:3], err_msg=f)
    assert list(three.status) == list(r.status[:3])
    # the same grid as one stack of problems gives the same answers; a field set for the
    # whole stack at once (members 1 and 2 back on their loops' holonomy) gives each
    # member its new problem's answer: the loop's closed form; member 0 is untouched
    stack = controls.stack_members(ocps)
    again = controls.solve_pontryagin_batch(stack, z[:, :3], z[:, 3:], progress=False)
    np.testing.assert_array_equal(again.cost, r.cost)
    np.testing.assert_array_equal(again.p0, r.p0)
    targets = np.array(stack.terminal_constraints.target)
    targets[1:3, 2] = [_holonomy(cat, 0.6), _holonomy(cat, 0.7)]
    on_loops = controls.solve_pontryagin_batch(eqx.tree_at(lambda g: g.terminal_constraints.target, stack, targets),
                                               z[:, :3], z[:, 3:], progress=False)
    assert on_loops.converged.all() and on_loops.cost[0] == r.cost[0]
    for k, th in ((1, 0.6), (2, 0.7)):
        assert abs(on_loops.cost[k] - _loop_cost(cat, th)) < 1e-10 * _loop_cost(cat, th)
        assert abs(on_loops.cost[k] - r.cost[k]) > 1e-3 * r.cost[k]  # (a new problem, not the old answer)


def test_members_that_differ_in_structure_are_refused_by_name():
    """Another system (a torque-driven cat: another class and state size) or another type
    is a GridError naming the member and the field whose class differs, raised before
    anything is traced."""
    cat = FallingCatKinematic()
    chart = velocity_somersault_chart(cat, 0.6, -np.pi, T)
    torque = torque_somersault(FallingCat(), 0.6, -np.pi, T)
    with pytest.raises(controls.GridError, match=r"problem 1's \.system is a FallingCat, problem 0's a "
                                                 r"FallingCatKinematic"):
        controls.solve_pontryagin_batch([chart, torque], progress=False)
    with pytest.raises(controls.ProblemError, match="member 1 is a str"):
        controls.solve_pontryagin_batch([chart, "not a problem"], progress=False)
    with pytest.raises(controls.ProblemError, match=r"shape \(3,\).*\(2, 3\)"):
        controls.solve_pontryagin_batch([chart, chart], np.zeros((3, 3)), progress=False)
    with pytest.raises(controls.ProblemError, match="non-empty"):
        controls.solve_pontryagin_batch([], progress=False)
    for bad in (0, 1.5, "two", True):  # the thread count, checked before any numerics
        with pytest.raises(controls.ProblemError, match="workers"):
            controls.solve_pontryagin_batch([chart, chart], progress=False, workers=bad)
    # a stack whose horizon was set without the members' axis
    bad = eqx.tree_at(lambda g: g.T, controls.stack_members([chart, chart]), np.asarray(T))
    with pytest.raises(controls.GridError, match=r"\.T of shape \(\)"):
        controls.solve_pontryagin_batch(bad, progress=False)


def test_a_failing_member_does_not_spoil_the_others():
    """A member far from its start (bend 1.0 asked to turn by -4 rad straight from its
    loop) fails, a member with a NaN guess is flagged and not run; the others converge
    to what they reach alone (solve_pontryagin), and a budget of one step reports
    max_iterations for every member it stops."""
    cat = FallingCatKinematic()
    good, zg = _members(cat, [0.5, 0.6], [-0.2, 0.1])
    far = velocity_somersault_chart(cat, 1.0, -4.0, T)
    zf = np.concatenate(fixed_theta_costates(cat, 1.0, T))
    znan = zg[0].copy()
    znan[1] = np.nan
    ocps, z = good + [far, good[0]], np.vstack([zg, zf, znan])
    # (four members: the program of the first test's batch)
    r = controls.solve_pontryagin_batch(ocps, z[:, :3], z[:, 3:], progress=False)
    assert list(r.status[:2]) == ["converged", "converged"]
    assert r.status[2] in ("non_finite", "stalled", "max_iterations") and r.reasons[2]
    assert r.status[3] == "non_finite_input" and "NaN" in r.reasons[3] and np.isnan(r.cost[3])
    for i in range(2):
        alone = controls.solve_pontryagin(good[i], zg[i, :3], zg[i, 3:], progress=False)
        assert abs(alone.cost - r.cost[i]) <= 1e-12 * abs(alone.cost)
        np.testing.assert_allclose(r.p0[i], alone.p0, rtol=0, atol=1e-9)
    assert r.counts()["converged"] == 2
    short = controls.solve_pontryagin_batch(ocps, z[:, :3], z[:, 3:], max_steps=1, progress=False)
    assert list(short.status[:2]) == ["max_iterations"] * 2 and "1 steps" in short.reasons[0]
    with pytest.raises(controls.ProblemError, match="every member"):
        controls.solve_pontryagin_batch([good[0]], znan[:3], znan[3:], progress=False)


def test_continuation_along_the_grid_converges_a_member_from_its_neighbour():
    """Four turns of the bent cat (bend 1.0) from its loop's holonomy to -4 rad, all from
    the loop's costates (four members: the first test's program): the farthest fails
    from there; with grid=(4,) it is solved again
    from its converged neighbour's solution and converges, to an extremal that
    solve_pontryagin confirms (converged at once from it, the same cost to 1e-12); the
    grid's shape is checked before any numerics."""
    cat = FallingCatKinematic()
    turns = _holonomy(cat, 1.0) + np.linspace(0.0, -4.0 - _holonomy(cat, 1.0), 4)
    ocps = [velocity_somersault_chart(cat, 1.0, t, T) for t in turns]
    z = np.concatenate(fixed_theta_costates(cat, 1.0, T))
    plain = controls.solve_pontryagin_batch(ocps, z[:3], z[3:], progress=False)
    assert not plain.converged[-1] and (plain.started_from == -1).all()
    r = controls.solve_pontryagin_batch(ocps, z[:3], z[3:], grid=(4,), progress=False)
    assert r.converged.all() and r.started_from[-1] >= 0
    np.testing.assert_array_equal(r.cost[plain.converged], plain.cost[plain.converged])
    alone = controls.solve_pontryagin(ocps[-1], r.p0[-1], r.nu[-1], progress=False)
    assert alone.converged and alone.iterations <= 2
    assert abs(alone.cost - r.cost[-1]) <= 1e-12 * abs(alone.cost)
    with pytest.raises(controls.ProblemError, match=r"grid \(2, 3\) does not hold the 4"):
        controls.solve_pontryagin_batch(ocps, z[:3], z[3:], grid=(2, 3), progress=False)


# ------------------------------------------------------------------ the direct method
def _loop_controls(param):
    """The fixed-theta loop's inputs (theta', chi') = (0, 2 pi / T) in ``param`` (exact:
    they are constant)."""
    import jax.numpy as jnp

    return np.asarray(param.fit(lambda t: jnp.array([0.0, 2 * np.pi / T])))


@pytest.mark.slow(reason="compiles the batched SQP; the default run solves a direct batch in docs/guides/optimal-control.md and checks Pontryagin batches member by member here; make test-all")
def test_direct_batch_members_are_their_own_sqp_solves_and_failures_stay_apart():
    """solve_direct_batch on the chart somersault, one call: members on their loop's
    holonomy, off it, on a cat of other inertia, with control bounds that the turn
    cannot be made within (infeasible), and with a NaN guess (not run). Each solved
    member is solve_direct_sqp's solve on it alone (the same iterations; cost to 1e-12
    relative, parameters to 1e-8), so the failures spoil nothing; the loop member's
    cost is the loop's closed form; the failures have their statuses and reasons, and
    NaN rows where nothing was solved."""
    cat, other = FallingCatKinematic(), FallingCatKinematic(I1=0.12, lam=0.4, B=2.0)
    param = controls.PiecewiseLinear(10, T, 2)

    def bounded(o, b):  # the problem with |u_i| <= b [rad/s]
        return controls.OCP(o.system, o.x0, T, o.running_cost, terminal_constraints=o.terminal_constraints,
                            u_lower=-b, u_upper=b)

    ocps, _ = _members(cat, [0.5, 0.6, 0.7], [0.0, -0.2, 0.15])
    ocps.append(velocity_somersault_chart(other, 0.8, _holonomy(other, 0.8) - 0.1, T))
    # |u| <= 10 is inactive at these optima; |u| <= 1 cannot wind chi = int u2 dt once in 2 s
    ocps = [bounded(o, 10.0) for o in ocps] + [bounded(ocps[1], 1.0), bounded(ocps[0], 10.0)]
    guess = _loop_controls(param)
    guesses = np.stack([guess] * 6)
    guesses[5, 3] = np.nan
    r = controls.solve_direct_batch(ocps, param, guesses, lanes=3, progress=False)  # (two groups: one program body)
    assert list(r.status) == ["converged"] * 4 + ["infeasible", "non_finite_input"]
    assert r.reasons[:4] == [""] * 4 and "control bounds" in r.reasons[4] and "NaN" in r.reasons[5]
    assert r.counts() == {"converged": 4, "infeasible": 1, "non_finite_input": 1}
    assert np.isnan(r.cost[5]) and np.isnan(r.params[5]).all() and r.results[5] is None
    assert r.violation[:4].max() < 1e-8 and r.rounds >= r.iterations.max() + 1
    for i, ocp in enumerate(ocps[:5]):
        alone = controls.solve_direct_sqp(ocp, param, guess, progress=False)
        assert alone.converged == (i < 4) and alone.iterations == r.iterations[i]
        assert alone.message == r.results[i].message
        if i < 4:
            assert abs(alone.cost - r.cost[i]) <= 1e-12 * abs(alone.cost)
            np.testing.assert_allclose(r.params[i], np.asarray(alone.params), rtol=0, atol=1e-8)
            assert r.results[i].cost == r.cost[i]
    assert abs(r.cost[0] - _loop_cost(cat, 0.5)) < 1e-9 * _loop_cost(cat, 0.5)
    # a member's control is its parametrization's signal: re-simulated, it meets the target
    _, J, psi = controls.rollout(ocps[1], r.results[1].control, rtol=1e-10, atol=1e-10)
    assert abs(float(J) - r.cost[1]) < 1e-8 and np.abs(np.asarray(psi)).max() < 1e-7


def test_direct_batch_refuses_members_of_other_structure_by_name():
    """Another state size, another parametrization degree, a count of parametrizations
    that does not match the problems, a guess of the wrong shape: named errors, before
    anything is traced."""
    cat = FallingCatKinematic()
    chart = velocity_somersault_chart(cat, 0.6, -np.pi, T)
    torque = torque_somersault(FallingCat(), 0.6, -np.pi, T)
    param = controls.Chebyshev(10, T, 2)
    with pytest.raises(controls.GridError, match="problem 1"):
        controls.solve_direct_batch([chart, torque], param, progress=False)
    with pytest.raises(controls.GridError, match=r"parametrization 1 .*\(Chebyshev\.n: 8 against 10\)"):
        controls.solve_direct_batch([chart, chart], [param, controls.Chebyshev(8, T, 2)], progress=False)
    with pytest.raises(controls.ProblemError, match="3 parametrizations for 2 problems"):
        controls.solve_direct_batch([chart, chart], [param] * 3, progress=False)
    with pytest.raises(controls.ProblemError, match=r"shape \(22,\).*\(2, 22\)"):
        controls.solve_direct_batch([chart, chart], param, np.zeros((3, 22)), progress=False)
    with pytest.raises(controls.ProblemError, match="is for solve_pontryagin_batch"):
        controls.solve_direct_batch(controls.stack_members([chart, chart]), param, progress=False)


def test_batch_arguments_of_the_wrong_kind_are_named():
    """Problems that are not a list, guesses that are not numbers (a string, ragged
    rows) and a grid shape that is not integers are refused by name before any numerics."""
    cat = FallingCatKinematic()
    ocps = [velocity_somersault_chart(cat, th, -0.3, T) for th in (0.5, 0.6)]
    for solve in (controls.solve_pontryagin_batch, lambda o: controls.solve_direct_batch(o, controls.Chebyshev(4, T, 2))):
        for bad in (None, 5):
            with pytest.raises(controls.ProblemError, match="must be a list of controls.OCP"):
                solve(bad)
    with pytest.raises(controls.ProblemError, match="p0_guess must be a real number"):
        controls.solve_pontryagin_batch(ocps, "abc", progress=False)
    with pytest.raises(controls.ProblemError, match=r"nu_guess must have shape \(3,\).*\(2, 3\) \(one row per "
                       r"member\); got a list of rows of shapes \(3,\), \(2,\)"):
        controls.solve_pontryagin_batch(ocps, np.zeros(3), [[1.0, 2.0, 3.0], [1.0, 2.0]], progress=False)
    with pytest.raises(controls.ProblemError, match=r"solve_direct_batch: guess must .* got a list of rows of "
                       r"shapes \(10,\), \(3,\)"):
        controls.solve_direct_batch(ocps, controls.Chebyshev(4, T, 2), [np.zeros(10), np.zeros(3)], progress=False)
    with pytest.raises(controls.ProblemError, match="guess must be a real number"):
        controls.solve_direct_batch(ocps, controls.Chebyshev(4, T, 2), "g", progress=False)
    for grid in ("2", (2.7,), (0,)):
        with pytest.raises(controls.ProblemError, match="solve_pontryagin_batch: grid must be"):
            controls.solve_pontryagin_batch(ocps, grid=grid, progress=False)
