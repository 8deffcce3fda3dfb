"""simulate_batch: per member the same result as simulate(), also for members
that need very different numbers of steps; batched parameters and controls;
bad members named."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.mechanics import Lagrangian
from nhjax.scenes import BouncingBall, FallingCat

CTRL = nhjax.Sinusoids([-0.015, 0.0], [0.04, 0.02], [1.7, 0.9], [0.0, np.pi / 2])


@pytest.mark.slow  # (members of very different lengths equal their own solves: test_refilled_lanes_give_each_member_its_own_solve; tracked work: test_diagnostics_honest; make test-all)
def test_batch_equals_single_including_very_different_step_counts():
    cat = FallingCat()
    # calm members and one with a fast twist (many more steps)
    X = jnp.array([[0.8, 0, 0, 0, 0.5], [0.9, 0, 0, 0.1, 0.3], [0.7, 0, 0, 0, 6.0], [1.0, 1.0, 0, -0.2, 0.5]])
    tr = nhjax.simulate_batch(cat, X, 10.0, control=CTRL, rtol=1e-9, atol=1e-9, saveat=5, chunk_size=3,
                              track_work=True)
    steps = np.asarray(tr.num_accepted_steps)
    assert steps.max() > 3 * steps.min()
    for i in range(X.shape[0]):
        one = nhjax.simulate(cat, X[i], 10.0, control=CTRL, rtol=1e-9, atol=1e-9, saveat=5)
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)
        assert int(tr.num_accepted_steps[i]) == int(one.num_accepted_steps)
        np.testing.assert_allclose(tr.invariant_drift["energy - work"][i], one.invariant_drift["energy - work"], atol=1e-13)


def test_batched_parameters_and_controls():
    # a batch of cats with different inertia ratios, each under its own torque amplitude
    lams = jnp.array([0.2, 0.5, 1.5])
    cats = nhjax.stack([FallingCat(lam=lam) for lam in lams])
    ctrls = nhjax.Sinusoids(jnp.zeros((3, 2)), jnp.array([[0.01, 0.0], [0.02, 0.0], [0.03, 0.01]]),
                            jnp.ones((3, 2)))
    x0 = FallingCat().initial_state(0.8, chi_dot=0.5)
    tr = nhjax.simulate_batch(cats, x0, 5.0, control=ctrls, in_axes={"system": 0, "control": 0},
                              rtol=1e-10, atol=1e-10)
    for i in range(3):
        one = nhjax.simulate(FallingCat(lam=lams[i]), x0, 5.0, rtol=1e-10, atol=1e-10, saveat=2,
                             control=nhjax.Sinusoids(ctrls.offset[i], ctrls.amplitude[i], ctrls.omega[i]))
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="nhjax.stack"):
        nhjax.simulate_batch(FallingCat(lam=lams), x0, 1.0, in_axes={"system": 0})


@pytest.mark.slow  # (bad members named: test_sweep_mode_returns_every_members_status; make test-all)
def test_bad_members_are_named():
    cat = FallingCat()
    X = jnp.tile(cat.initial_state(0.8, chi_dot=0.5), (6, 1))
    X = X.at[2, 1].set(jnp.nan).at[4, 0].set(0.0)
    with pytest.raises(nhjax.BatchError, match=r"member 2: x0 contains NaN.*member 4: outside the chart") as e:
        nhjax.simulate_batch(cat, X, 1.0)
    assert e.value.members == [2, 4]
    # member 3 heads for the singular chart, member 5 runs out of steps
    X = jnp.tile(cat.initial_state(0.8, chi_dot=0.5), (6, 1))
    X = X.at[3].set(cat.initial_state(0.3, theta_dot=-1.0))
    with pytest.raises(nhjax.BatchError, match="member 3") as e:
        nhjax.simulate_batch(cat, X, 2.0)
    assert e.value.members == [3] and 0.25 < e.value.times[0] < 0.32
    tr = nhjax.simulate_batch(cat, X, 2.0, on_guard="stop")
    assert float(tr.t_final[3]) == pytest.approx(e.value.times[0]) and float(tr.t_final[0]) == 2.0
    fast = X.at[5, 4].set(50.0)
    with pytest.raises(nhjax.BatchError, match="member 5: max_steps exhausted"):
        nhjax.simulate_batch(cat, fast.at[3].set(X[0]), 2.0, max_steps=200)


def test_input_errors():
    """Bad batch arguments are named errors of simulate_batch (both paths: the cat's
    lock-step chunks and the impact batch), raised before any numerics."""
    cat = FallingCat()
    X = jnp.tile(cat.initial_state(0.8), (4, 1))
    with pytest.raises(nhjax.ParameterError, match="simulate_batch: batched arguments disagree on the batch size"):
        nhjax.simulate_batch(nhjax.stack([cat, cat]), X, 1.0, in_axes={"system": 0, "x0": 0})
    with pytest.raises(nhjax.ParameterError, match="simulate_batch: in_axes keys"):
        nhjax.simulate_batch(cat, X, 1.0, in_axes={"params": 0})
    with pytest.raises(nhjax.ParameterError, match=r"in_axes\['x0'\] must be 0 .* or None"):
        nhjax.simulate_batch(cat, X, 1.0, in_axes={"x0": 1})
    with pytest.raises(nhjax.ParameterError, match="the batch has no members"):
        nhjax.simulate_batch(cat, X[:0], 1.0)
    # one state where a batch is expected: its 5 numbers are not 5 members
    with pytest.raises(nhjax.StateError, match=r"x0 \(shape \(5,\)\) is one state of FallingCat, not a batch"):
        nhjax.simulate_batch(cat, X[0], 1.0)
    for bad in (0, 1.5):
        with pytest.raises(nhjax.ParameterError, match="workers must be"):
            nhjax.simulate_batch(cat, X, 1.0, workers=bad)
    ball = BouncingBall()
    B = np.stack([ball.initial_state(h) for h in (0.1, 0.2)])
    with pytest.raises(nhjax.ParameterError, match="the batch has no members"):
        nhjax.simulate_batch(ball, B[:0], 1.0)
    with pytest.raises(nhjax.ParameterError, match="workers must be at least 1"):
        nhjax.simulate_impacts_batch(ball, B, 1.0, workers=0)
    with pytest.raises(MemoryError, match="save fewer times"):
        nhjax.simulate_batch(cat, jnp.tile(X, (250_000, 1)), 1.0, saveat=10_000)


@pytest.mark.slow  # (subprocesses, 30-40 s; make test-all)
def test_split_batch_on_two_workers_equals_one_chunk():
    """A batch big enough to be split across workers (2 x 300 members, threads) gives per
    member the result of one chunk on one thread and of a single simulate(), and keeps
    the members in order; a bad member in the second chunk is named by its batch index."""
    cat = FallingCat()
    rng = np.random.default_rng(3)
    X = jnp.tile(cat.initial_state(0.8, chi_dot=0.5), (600, 1))
    X = X.at[:, 0].add(rng.uniform(-0.3, 0.3, 600)).at[:, 4].add(rng.uniform(-0.4, 2.0, 600))
    kw = dict(control=CTRL, rtol=1e-9, atol=1e-9, track_work=False, diagnostics=False)
    split = nhjax.simulate_batch(cat, X, 3.0, workers=2, **kw)
    whole = nhjax.simulate_batch(cat, X, 3.0, workers=1, chunk_size=600, **kw)
    np.testing.assert_allclose(split.xs, whole.xs, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(split.num_accepted_steps, whole.num_accepted_steps)
    for i in (0, 299, 300, 599):  # both sides of the chunk boundary
        one = nhjax.simulate(cat, X[i], 3.0, saveat=2, **kw)
        np.testing.assert_allclose(split.xs[i], one.xs, rtol=1e-12, atol=1e-12)
    with pytest.raises(nhjax.BatchError, match="member 457: x0 contains NaN"):
        nhjax.simulate_batch(cat, X.at[457, 2].set(jnp.nan), 3.0, workers=2, **kw)


@pytest.mark.slow(reason="compiles vmapped diffeqsolve besides the lock-step batch (~22 s on an empty cache); "
                         "the default run checks lock-step members against their own simulate() in "
                         "test_refilled_lanes_give_each_member_its_own_solve[8-times]; make test-all")
def test_lockstep_equals_vmapped_diffrax_and_saves_up_to_a_guard():
    """Two independent batch paths agree member by member: the lock-step integrator and
    vmapped diffeqsolve (taken when an adjoint is given), with uneven save times and a
    member stopped by the chart guard (nothing saved after its event time)."""
    cat = FallingCat()
    X = jnp.stack([cat.initial_state(0.8, chi_dot=0.5), cat.initial_state(0.3, theta_dot=-1.0),
                   cat.initial_state(1.0, chi_dot=4.0)])
    ts = jnp.array([0.0, 0.05, 0.3, 0.31, 1.2, 2.0])
    kw = dict(rtol=1e-9, atol=1e-9, saveat=ts, on_guard="stop")
    lock = nhjax.simulate_batch(cat, X, 2.0, **kw)
    vm = nhjax.simulate_batch(cat, X, 2.0, adjoint=diffrax.RecursiveCheckpointAdjoint(), **kw)
    np.testing.assert_array_equal(lock.num_accepted_steps, vm.num_accepted_steps)
    np.testing.assert_allclose(lock.t_final, vm.t_final, rtol=1e-12)
    assert 0.25 < float(lock.t_final[1]) < 0.31  # member 1 reaches the guard
    np.testing.assert_array_equal(np.isfinite(lock.ts), np.isfinite(vm.ts))
    assert not np.isfinite(lock.ts[1, 3:]).any() and np.isfinite(lock.ts[0]).all()
    ok = np.isfinite(np.asarray(vm.xs))
    np.testing.assert_allclose(np.asarray(lock.xs)[ok], np.asarray(vm.xs)[ok], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lock.x_end, vm.x_end, rtol=1e-11, atol=1e-12)


# slow (~45 s on 2 cores); the default run keeps group-valued batch members through
# test_members_off_their_group_are_named_and_not_solved
@pytest.mark.slow
def test_group_valued_states_projection_jumps_and_other_solvers():
    """Per member the single result, where the lock-step path does something different:
    group-valued state parts (vmapped exp maps), a projection after every step, a
    piecewise-constant control (jump times restart the FSAL stage of some members),
    and a diffrax solver stepped member by member."""
    att = FallingCat().attitude_model()  # SO(3) x SO(3) x R^4
    X = nhjax.stack([att.initial_state(0.8, chi_dot=c) for c in (0.5, 1.5)])
    tr = nhjax.simulate_batch(att, X, 3.0, control=CTRL, saveat=4)
    for i, c in enumerate((0.5, 1.5)):
        one = nhjax.simulate(att, att.initial_state(0.8, chi_dot=c), 3.0, control=CTRL, saveat=4)
        for a, b in zip(jax.tree_util.tree_leaves(tr.xs), jax.tree_util.tree_leaves(one.xs)):
            np.testing.assert_allclose(a[i], b, rtol=1e-12, atol=1e-12)

    pend = Lagrangian(2, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 9.81 * q[1],
                      position_constraints=lambda t, q: jnp.atleast_1d(q @ q - 1.0))
    X = jnp.array([[np.sin(a), -np.cos(a), w * np.cos(a), w * np.sin(a)] for a, w in ((0.4, 1.5), (1.0, -2.0))])
    tr = nhjax.simulate_batch(pend, X, 3.0, project_steps=True, saveat=5)
    for i in range(2):
        one = nhjax.simulate(pend, X[i], 3.0, project_steps=True, saveat=5)
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)
        assert float(tr.constraint_drift["position"][i]) < 1e-12

    cat = FallingCat()
    steps = nhjax.PiecewiseConstant(jnp.array([0.0, 0.7, 1.9, 3.0]), jnp.array([[0.02, 0.0], [-0.01, 0.01], [0.0, 0.0]]))
    X = jnp.stack([cat.initial_state(0.8, chi_dot=c) for c in (0.5, 2.5)])
    tr = nhjax.simulate_batch(cat, X, 3.0, control=steps, rtol=1e-9, atol=1e-9)
    for i in range(2):
        one = nhjax.simulate(cat, X[i], 3.0, control=steps, rtol=1e-9, atol=1e-9, saveat=2)
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)
        assert int(tr.num_accepted_steps[i]) == int(one.num_accepted_steps)
    # Dopri8 with jump times: the step counts of this case depend on rounding (vmapped
    # diffrax takes 6 and 10 steps, simulate() one by one 6 and 17), so a chunk stepping
    # both members in two lanes is compared with vmapped diffrax exactly, and one lane at
    # a time (the second member refills the first's lane) with simulate() exactly
    kw = dict(control=steps, solver=diffrax.Dopri8(), rtol=1e-9, atol=1e-9)
    tr = nhjax.simulate_batch(cat, X, 3.0, lanes=2, **kw)
    vm = nhjax.simulate_batch(cat, X, 3.0, adjoint=diffrax.RecursiveCheckpointAdjoint(), **kw)
    np.testing.assert_allclose(tr.xs, vm.xs, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(tr.num_steps, vm.num_steps)
    tr = nhjax.simulate_batch(cat, X, 3.0, lanes=1, **kw)
    for i in range(2):
        one = nhjax.simulate(cat, X[i], 3.0, saveat=2, **kw)
        # the same steps (below); the values to 1e-12 as above: the chunk and simulate()'s
        # solve are programs compiled apart, whose last bits differ (8.8e-13 under the
        # tests' unoptimized LLVM pipeline, conftest.py)
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)
        assert int(tr.num_steps[i]) == int(one.num_steps)


@pytest.mark.slow  # (large arguments flagged: test_fast_trig.py::test_rewrite_replaces_nested_calls_and_flags_large_arguments; make test-all)
def test_angles_beyond_the_fast_sine_range_rerun_with_the_library_sine():
    """A control phase of 1e7 rad puts sin/cos arguments beyond fast_trig.LIMIT: the
    chunk reports it and is solved again with libm's functions, matching simulate()."""
    from nhjax.integrate import _local_batch as batch

    cat = FallingCat()
    X = jnp.stack([cat.initial_state(0.8, chi_dot=0.5), cat.initial_state(0.9, chi_dot=1.0)])
    t0, t1 = jnp.asarray(0.0), jnp.asarray(4.0)
    for phase, expect_bad in ((0.3, False), (1.0e7, True)):
        ctrl = nhjax.Sinusoids([0.0, 0.0], [0.04, 0.02], [1.7, 0.9], [phase, phase])
        options = dict(saveat=2, solver=None, rtol=1e-9, atol=1e-9, dt0=None, max_steps=None,
                       stepsize_controller=None, jump_ts=None, adjoint=None, project_steps=False,
                       track_work=False, progress=False, diagnostics=False)
        _, _, bad = batch._lockstep_chunk(cat, X, ctrl, 2, t0, t1, 1e-8, False, options, (None, 0, None), True)
        assert bool(bad) == expect_bad
        tr = nhjax.simulate_batch(cat, X, 4.0, control=ctrl, rtol=1e-9, atol=1e-9)
        vm = nhjax.simulate_batch(cat, X, 4.0, control=ctrl, rtol=1e-9, atol=1e-9,
                                  adjoint=diffrax.RecursiveCheckpointAdjoint())
        # sin(w t + 1e7) itself is only defined to ulp(1e7) = 2e-9: compiled programs that
        # round w t + phase differently (fused or not) differ by that much (the lock-step
        # and the vmapped program did so once the lock-step loop refilled its lanes)
        tol = 1e-12 if phase < 1 else 5e-9
        np.testing.assert_allclose(tr.xs, vm.xs, rtol=tol, atol=tol)
        for i in range(2):
            one = nhjax.simulate(cat, X[i], 4.0, control=ctrl, rtol=1e-9, atol=1e-9, saveat=2)
            np.testing.assert_allclose(tr.xs[i], one.xs, rtol=tol, atol=tol)


def test_compiled_chunks_are_reused_only_for_the_same_configuration():
    """simulate_batch keeps compiled chunk programs by argument structure: a second call
    with other tolerances or another control must not reuse the first program."""
    cat = FallingCat()
    X = jnp.stack([cat.initial_state(0.8, chi_dot=0.5), cat.initial_state(0.9, chi_dot=1.5)])
    other = nhjax.Sinusoids([0.0, 0.0], [0.05, 0.0], [1.0, 1.0])
    for rtol, ctrl in ((1e-6, CTRL), (1e-10, CTRL), (1e-6, CTRL), (1e-6, other)):
        tr = nhjax.simulate_batch(cat, X, 3.0, control=ctrl, rtol=rtol, atol=rtol)
        for i in range(2):
            one = nhjax.simulate(cat, X[i], 3.0, control=ctrl, rtol=rtol, atol=rtol, saveat=2)
            assert int(tr.num_accepted_steps[i]) == int(one.num_accepted_steps)
            np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # (subprocesses, 30-40 s; make test-all)
def test_several_local_devices(tmp_path):
    """With two CPU devices (a fresh process with XLA's host device count set) the chunks
    run on both and the result is gathered in member order (this used to fail when the
    chunks were concatenated across devices); a second such process loads the stored
    one-device programs onto the one device they were compiled for (loaded onto every
    local device they refused one-device inputs)."""
    import os
    import subprocess
    import sys

    script = tmp_path / "two_devices.py"
    script.write_text(
        "import jax, jax.numpy as jnp, numpy as np, nhjax\n"
        "from nhjax.scenes import FallingCat\n"
        "assert len(jax.local_devices()) == 2\n"
        "cat = FallingCat()\n"
        "X = jnp.tile(cat.initial_state(0.8, chi_dot=0.5), (600, 1))\n"
        "X = X.at[:, 0].add(np.linspace(-0.3, 0.3, 600))\n"
        "tr = nhjax.simulate_batch(cat, X, 2.0, rtol=1e-9, atol=1e-9, saveat=3, diagnostics=False)\n"
        "for i in (0, 299, 300, 599):\n"
        "    one = nhjax.simulate(cat, X[i], 2.0, rtol=1e-9, atol=1e-9, saveat=3, diagnostics=False)\n"
        "    np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)\n"
        "from nhjax import _programs\n"
        "print(_programs.STATS['executables'], 'ok')\n"
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", NHJAX_CACHE_DIR=str(tmp_path))
    loaded = []
    for _ in range(2):
        out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=600)
        assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]
        loaded.append(int(out.stdout.strip().split()[-2]))
    assert loaded[0] == 0 and loaded[1] >= 2  # the second process ran stored executables


@pytest.mark.slow  # (subprocesses, 30-40 s; make test-all)
def test_two_workers_running_a_projected_batch_at_once_finish(tmp_path):
    """Two worker threads each running a chunk of a projected batch (the quaternion disk,
    128 members on 2 workers) finish, and every member's saved states are on S^3 and
    satisfy the rolling constraints. With the saved states projected by vmap (batched
    LAPACK solves over members x saved times) this hung on the 2-core development
    machine: both executions waited, at ~2 % CPU, in a fresh process each time; hence a
    child process with a time limit."""
    import os
    import subprocess
    import sys

    script = tmp_path / "projected_batch.py"
    script.write_text(
        "import numpy as np, nhjax\n"
        "from nhjax.scenes import RollingDisk\n"
        "disk = RollingDisk(); quat = disk.quaternion_model()\n"
        "rng = np.random.default_rng(0)\n"
        "X = np.stack([np.asarray(disk.to_quaternion_state(disk.initial_state(theta=th, phi_dot=0.4,\n"
        "    theta_dot=0.2, psi_dot=pd))) for th, pd in zip(rng.uniform(0.1, 0.5, 128), rng.uniform(1, 2, 128))])\n"
        "tr = nhjax.simulate_batch(quat, X, 1.0, workers=2, saveat=11)\n"
        "norms = np.linalg.norm(np.asarray(tr.xs)[:, :, 3:7], axis=-1)\n"
        "worst = max(float(np.max(v)) for v in tr.constraint_drift.values())\n"
        "steps = np.asarray(tr.num_accepted_steps)\n"
        "print(float(np.max(np.abs(norms - 1.0))), worst, int(steps.min()), int(steps.max()))\n"
    )
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path))
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    norm_err, drift, fewest, most = (float(v) for v in out.stdout.split()[-4:])
    assert norm_err < 1e-13 and drift < 1e-12
    assert most > fewest  # members of different lengths


# (3 lanes: refilled more often; 8 lanes over 20 members refill too, and finish one lane at a time)
@pytest.mark.parametrize("lanes, saveat", [pytest.param(3, "times", marks=pytest.mark.slow), (8, "times"),
                                           pytest.param(8, "many", marks=pytest.mark.slow),
                                           pytest.param(8, 2, marks=pytest.mark.slow)])
def test_refilled_lanes_give_each_member_its_own_solve(lanes, saveat):
    """Members whose step counts differ more than 10x, fewer lanes than members (each lane
    is refilled several times), saved times in between and a member stopped by the chart
    guard: every member equals its own simulate() to 1e-12 with the same step counts.
    With 8 lanes the last members are finished one lane at a time (lockstep.py's tail);
    with 400 saved times the lanes write them into the members' slots directly instead
    of keeping their own (lockstep.py's lane_saves)."""
    cat = FallingCat()
    chi_dots = [0.5, 9.0, 0.3, 0.6, 5.0, 0.4, 0.7, 30.0, 0.2, 0.5]
    if lanes == 8:
        chi_dots += [0.45, 12.0, 0.35, 2.0, 0.25, 20.0, 0.55, 0.65, 1.0, 0.3]
    X = jnp.stack([cat.initial_state(0.8, chi_dot=c) for c in chi_dots])
    X = X.at[5].set(cat.initial_state(0.3, theta_dot=-1.0))  # reaches sin(theta) = 0
    ts = {"times": jnp.array([0.0, 0.1, 0.27, 1.3, 3.0]), "many": jnp.linspace(0.0, 3.0, 400)}.get(saveat, saveat)
    kw = dict(rtol=1e-9, atol=1e-9, saveat=ts, on_guard="stop")
    tr = nhjax.simulate_batch(cat, X, 3.0, lanes=lanes, **kw)
    steps = np.asarray(tr.num_accepted_steps)
    assert steps.max() > 10 * steps.min()
    assert tr.status_names()[5] == "guard" and tr.guard == "sin_theta"
    for i in range(len(chi_dots)):
        one = nhjax.simulate(cat, X[i], 3.0, **kw)
        assert int(tr.num_accepted_steps[i]) == int(one.num_accepted_steps)
        assert int(tr.num_rejected_steps[i]) == int(one.num_rejected_steps)
        np.testing.assert_allclose(tr.t_final[i], one.t_final, rtol=1e-12)
        n = one.ts.shape[0] - (i == 5)  # simulate() appends the state at the event time
        np.testing.assert_allclose(tr.xs[i, :n], one.xs[:n], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(tr.x_end[i], one.x_end, rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(tr.invariant_drift["energy"][i], one.invariant_drift["energy"], atol=1e-12)
        if i == 5 and saveat in ("times", "many"):  # nothing saved after the event time
            assert n < len(ts) and not np.isfinite(tr.ts[5, n:]).any()


def test_sweep_mode_returns_every_members_status():
    """on_error='return': bad initial states, a guard stop and an exhausted step budget
    are reported per member with their times; the other members are intact; the batch
    result behaves as a batch (final states per member, masks, a summary)."""
    cat = FallingCat()
    X = jnp.tile(cat.initial_state(0.8, chi_dot=0.5), (7, 1)).at[:, 4].add(jnp.linspace(0, 0.6, 7))
    X = X.at[1, 1].set(jnp.nan)  # bad x0
    X = X.at[3].set(cat.initial_state(0.3, theta_dot=-1.0))  # guard at t ~ 0.29
    X = X.at[4, 0].set(-0.2)  # outside the chart
    X = X.at[6, 4].set(60.0)  # needs more than max_steps
    tr = nhjax.simulate_batch(cat, X, 2.0, max_steps=300, on_error="return")
    assert tr.status_names() == ["ok", "bad x0", "ok", "guard", "bad x0", "ok", "max_steps"]
    assert "NaN" in tr.reasons[1] and "chart" in tr.reasons[4] and "max_steps" in tr.reasons[6]
    assert 0.25 < float(tr.t_final[3]) < 0.32 and float(tr.t_final[1]) == 0.0
    assert float(tr.t_final[6]) < 2.0
    np.testing.assert_array_equal(tr.ok, [True, False, True, False, False, True, False])
    assert tr.x_final.shape == (7, 5) and tr.x_end.shape == (7, 5)
    for i in (0, 2, 5):
        one = nhjax.simulate(cat, X[i], 2.0, saveat=2)
        np.testing.assert_allclose(tr.x_final[i], one.xs[-1], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tr.x_end[3], nhjax.simulate(cat, X[3], 2.0, on_guard="stop").x_end,
                               rtol=1e-10, atol=1e-12)
    assert tr.valid.shape == (7, 2) and tr.valid[0].all() and not tr.valid[1, 1]
    text = tr.summary()
    assert text.startswith("7 members: ok 3, guard 1, max_steps 1, bad x0 2") and "member 3:" in text
    assert tr.counts() == {"ok": 3, "guard": 1, "max_steps": 1, "bad x0": 2}
    with pytest.raises(nhjax.BatchError, match="bad initial states in 2 member"):
        nhjax.simulate_batch(cat, X, 2.0, max_steps=300)


def test_new_values_of_the_same_structure_do_not_trace_again():
    """A batch with other initial states, system parameters, control coefficients,
    tolerances, horizon or number of members (within a chunk's capacity) reuses the
    compiled chunk: no new trace and no new compile (counted), and the results are the
    new ones."""
    from nhjax.integrate import _local_batch as batch

    compiles = []

    def counting(real):
        def fn(*a, **k):
            compiles.append(1)
            return real(*a, **k)
        return fn

    cats = nhjax.stack([FallingCat(lam=lam) for lam in (0.3, 0.4, 0.5)])
    X = jnp.stack([FallingCat().initial_state(0.8, chi_dot=c) for c in (0.3, 0.5, 0.9, 1.2)])
    kw = dict(in_axes={"system": 0, "x0": 0}, lanes=2)
    nhjax.simulate_batch(cats, X[:3], 2.0, control=CTRL, rtol=1e-8, atol=1e-8, **kw)
    before = dict(batch.TRACES)
    # 4 members: the same chunk capacity (batch sizes share a program up to the next power of 2)
    lams = (0.35, 0.6, 0.45, 0.5)
    other = nhjax.Sinusoids([0.01, 0.0], [0.03, 0.05], [1.1, 0.7], [0.2, 0.1])
    cats2 = nhjax.stack([FallingCat(lam=lam) for lam in lams])
    X2 = X + 0.01
    real = batch._cached_lockstep, batch._compile
    batch._cached_lockstep, batch._compile = counting(real[0]), counting(real[1])
    try:
        tr = nhjax.simulate_batch(cats2, X2, 2.5, control=other, rtol=1e-9, atol=1e-9, **kw)
    finally:
        batch._cached_lockstep, batch._compile = real
    assert dict(batch.TRACES) == before
    assert not compiles  # the compiled chunk is kept, not compiled again per call
    for i, lam in enumerate(lams):
        one = nhjax.simulate(FallingCat(lam=lam), X2[i], 2.5, control=other, rtol=1e-9, atol=1e-9,
                             saveat=2)
        np.testing.assert_allclose(tr.xs[i], one.xs, rtol=1e-12, atol=1e-12)


@pytest.mark.slow  # (the work itself: test_diagnostics_honest; make test-all)
def test_work_tracking_leaves_the_steps_alone_and_is_on_where_it_is_the_only_report():
    """The work of the inputs stays out of the error norm: the same states and steps with
    and without it. A batch tracks it by default only for a system with no invariant or
    constraint of its own (the cat reports its angular momentum; a forced oscillator
    reports nothing else)."""
    cat = FallingCat()
    x0 = cat.initial_state(0.8, chi_dot=0.5)
    on = nhjax.simulate(cat, x0, 5.0, control=CTRL, track_work=True, saveat=7)
    off = nhjax.simulate(cat, x0, 5.0, control=CTRL, track_work=False, saveat=7)
    np.testing.assert_array_equal(on.xs, off.xs)
    assert int(on.num_steps) == int(off.num_steps)
    assert float(on.invariant_drift["energy - work"]) < 1e-8  # the work is still accurate
    X = jnp.stack([x0, cat.initial_state(0.9, chi_dot=0.3)])
    assert "energy - work" not in nhjax.simulate_batch(cat, X, 2.0, control=CTRL).invariant_drift
    osc = Lagrangian(1, T=lambda q, qd: 0.5 * qd @ qd, V=lambda q: 0.5 * q @ q,
                     force=lambda t, q, qd, u: u, control_dim=1)
    push = nhjax.Sinusoids([0.0], [0.3], [1.3])
    tr = nhjax.simulate_batch(osc, jnp.array([[1.0, 0.0], [0.0, 2.0]]), 6.0, control=push)
    one = nhjax.simulate(osc, jnp.array([0.0, 2.0]), 6.0, control=push, saveat=2)
    np.testing.assert_allclose(tr.invariant_drift["energy - work"][1], one.invariant_drift["energy - work"],
                               atol=1e-13)
    assert float(tr.invariant_drift["energy - work"].max()) < 1e-6  # energies ~1-2 J, rtol 1e-8


@pytest.mark.slow  # (group checks of x0: test_validation; per-member reports: test_sweep_mode_returns_every_members_status; make test-all)
def test_members_off_their_group_are_named_and_not_solved():
    """Each member's attitude is checked for membership of SO(3) (the validation layer's
    member report, vmapped in the chunk): a scaled rotation is a bad x0; with
    project=True it is projected onto the group and solved like simulate(project=True)."""
    att = FallingCat().attitude_model()
    X = nhjax.stack([att.initial_state(0.8, chi_dot=c) for c in (0.5, 1.5)])
    X = jax.tree_util.tree_map(lambda a: a, X)
    bad = (X[0].at[1].multiply(2.0),) + tuple(X[1:])
    tr = nhjax.simulate_batch(att, bad, 1.0, on_error="return")
    assert tr.status_names() == ["ok", "bad x0"] and "not on its group" in tr.reasons[1]
    with pytest.raises(nhjax.BatchError, match="member 1: .*not on its group"):
        nhjax.simulate_batch(att, bad, 1.0)
    fixed = nhjax.simulate_batch(att, bad, 1.0, project=True)
    one = nhjax.simulate(att, jax.tree_util.tree_map(lambda a: a[1], bad), 1.0, project=True, saveat=2)
    for a, b in zip(jax.tree_util.tree_leaves(fixed.xs), jax.tree_util.tree_leaves(one.xs)):
        np.testing.assert_allclose(a[1], b, rtol=1e-12, atol=1e-12)


_TWO_CHUNKS_CHILD = """
import numpy as np, jax.tree_util as jtu
import nhjax
from nhjax.scenes import BallOnPlatter

system = BallOnPlatter()
x0 = system.initial_state()
X = jtu.tree_map(lambda a: np.stack([np.asarray(a)] * 512), x0)
alone = nhjax.simulate_batch(system, X, 1.0, progress=False, workers=1)
for _ in range(3):
    bt = nhjax.simulate_batch(system, X, 1.0, progress=False)  # two chunks, two threads
    for a, b in zip(jtu.tree_leaves(bt.x_final), jtu.tree_leaves(alone.x_final)):
        assert np.array_equal(np.asarray(a), np.asarray(b))
print("done")
"""


@pytest.mark.slow(reason="compiles the ball-on-platter chunk of 256 lanes in a child process (~25 s); make test-all")
def test_two_chunks_with_batched_lapack_calls_at_once_finish(tmp_path):
    """simulate_batch of 512 balls on a platter (a constrained scene: its lock-step chunk
    solves 128 KKT systems per stage by one batched LAPACK call) in two chunks on the
    default two threads, three times: it finishes, each time equal to the batch run on
    one thread. Before nhjax ran such programs one at a time, the first such batch
    hung (jaxlib 0.10's batched kernels wait on XLA's thread pool from a thread of it).
    The child is killed after 300 s, so a hang fails the test."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    try:
        r = subprocess.run([sys.executable, "-c", _TWO_CHUNKS_CHILD], capture_output=True, text=True, env=env,
                           timeout=300)
    except subprocess.TimeoutExpired:
        pytest.fail("two chunks with batched LAPACK calls did not finish in 300 s (hung)")
    assert r.returncode == 0 and r.stdout.strip().endswith("done"), r.stderr[-3000:]
