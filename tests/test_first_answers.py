"""First answers on every path (nhjax/_primitive.py): a function differentiated around
``simulate`` runs stored programs for the solve and its derivatives, so that

* forward mode (``jax.jvp``, ``jax.jacfwd``) works on simulate's defaults, as reverse
  mode (``jax.grad``, ``jax.jacrev``) does, with the same derivative;
* a second process neither traces nor compiles any of it.

Each derivative is checked against central differences of the solve itself and
against the other mode; the counts come from the tracing counter of the solve, the
program cache's statistics and JAX's own compile events."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import nhjax
from nhjax.scenes import FallingCat

CAT = FallingCat()
X0 = CAT.initial_state(0.8, chi_dot=0.5)
W = jnp.array([1.7, 0.9])
PHASE = jnp.array([0.0, np.pi / 2])


def _final_psi(p):
    """psi(5) of the cat under torques of amplitudes p[:2], from an initial bend rate p[2]."""
    u = nhjax.Sinusoids(jnp.zeros(2), p[:2], W, PHASE)
    x0 = X0.at[4].set(p[2])
    return nhjax.simulate(CAT, x0, 5.0, control=u).xs[-1, 2]


P = jnp.array([0.04, 0.02, 0.5])


_CHILD = """
import json, sys
import jax, jax.numpy as jnp, numpy as np
compiles, hit = [], [False]  # XLA compiles that no cache answered (a hit comes before its duration event)
jax.monitoring.register_event_listener(
    lambda name, **kw: hit.__setitem__(0, True) if name == "/jax/compilation_cache/cache_hits" else None)
def on_compile(name, secs, **kw):
    if name == "/jax/core/compile/backend_compile_duration":
        if not hit[0]:
            compiles.append(kw.get("fun_name", "?"))
        hit[0] = False
jax.monitoring.register_event_duration_secs_listener(on_compile)
sys.path.insert(0, {here!r})
import test_first_answers as t
from nhjax import _programs, _primitive
sim = sys.modules["nhjax.integrate.simulate"]
before = len(compiles)
out = dict(grad=np.asarray(jax.grad(t._final_psi)(t.P)).tolist(),
           jacfwd=np.asarray(jax.jacfwd(t._final_psi)(t.P)).tolist(),
           jacrev=np.asarray(jax.jacrev(t._final_psi)(t.P)).tolist())
out.update(traces=sum(sim.TRACES.values()), stats=dict(_programs.STATS), bound=dict(_primitive.BOUND),
           compiles=compiles[before:])
# the counter sees a compile that no cache can answer (a constant no program has)
jax.jit(lambda x: x * {salt!r})(1.0).block_until_ready()
out["counted"] = len(compiles) - before - len(out["compiles"])
if {checks!r}:  # after the counts: the first process's other modes and the differences
    _, jv = jax.jvp(t._final_psi, (t.P,), (jnp.array(t.V),))
    h = 1e-6
    out.update(jvp=float(jv), jit_grad=np.asarray(jax.jit(jax.grad(t._final_psi))(t.P)).tolist(),
               fd=[(float(t._final_psi(t.P + h * e)) - float(t._final_psi(t.P - h * e))) / (2 * h)
                   for e in np.eye(3)])
print(json.dumps(out))
"""

V = [1.0, -2.0, 0.5]


def test_both_modes_on_defaults_match_differences_and_a_second_process_neither_traces_nor_compiles(tmp_path):
    """A new process (empty cache) differentiates ``_final_psi`` by jax.grad, jacfwd and
    jacrev, then by jvp and under its own jax.jit: forward and reverse mode agree with
    each other and with central differences of the solve. A second process on the same
    cache gets the same derivatives with no trace and no compile, by nhjax or by JAX
    (whose compile counter is seen to work in both: a fresh constant is counted)."""
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")

    def run(checks):
        code = _CHILD.format(here=os.path.dirname(__file__), checks=checks, salt=float(np.random.default_rng().uniform(2, 3)))
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
        return json.loads(r.stdout.strip().splitlines()[-1])

    first, second = run(True), run(False)
    assert first["traces"] >= 2 and first["stats"]["stored"] >= 6  # solve, its fwd, bwd, jvp, ...
    assert first["compiles"] and first["counted"] == 1 and second["counted"] == 1
    assert first["bound"]["fwd"] >= 1 and first["bound"]["bwd"] >= 1 and first["bound"]["jvp"] >= 1
    assert second["traces"] == 0, second
    assert second["stats"]["stored"] == 0 and second["stats"]["compiled"] == 0, second
    assert second["compiles"] == [], second  # nor JAX: every program it ran came from a cache
    assert second["stats"]["executables"] >= 6
    for k in ("grad", "jacfwd", "jacrev"):
        assert second[k] == first[k]
    g = np.asarray(first["grad"])
    np.testing.assert_allclose(first["jacrev"], g, rtol=0, atol=1e-12)  # the batched backward pass
    np.testing.assert_allclose(first["jacfwd"], g, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(first["jvp"], g @ np.array(V), rtol=1e-10, atol=1e-10)
    # under the user's jit the stored programs are inlined: the same derivative
    np.testing.assert_allclose(first["jit_grad"], g, rtol=1e-12, atol=1e-14)
    fd = np.asarray(first["fd"])
    assert np.all(np.abs(fd) > 1e-2)  # every input moves psi: each entry could be wrong
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


def _first_impact(h, adjoint="forward"):
    """The first impact time [s] of a ball dropped from h [m] on the vibrating table."""
    from nhjax.scenes import BouncingBall

    ball = BouncingBall()
    return nhjax.simulate_impacts(ball, jnp.stack([h, 0.0]), 0.5, saveat=0, max_impacts=8,
                                  adjoint=adjoint).impact_times[0]


@pytest.mark.slow  # (impact-time derivatives against differences: test_impacts_grad, test_bouncing_ball; make test-all)
def test_impact_times_differentiate_in_both_modes_whatever_adjoint_was_asked():
    """The stored programs give each mode its own loop: grad of a solve set up for forward
    mode (adjoint="forward", the default) works, and agrees with jacfwd and differences."""
    h = 0.1
    g_rev = float(jax.grad(_first_impact)(h))  # a solve set up for forward mode, differentiated in reverse
    g_fwd = float(jax.jacfwd(_first_impact)(h))
    d = 1e-6
    fd = (float(_first_impact(h + d)) - float(_first_impact(h - d))) / (2 * d)
    assert abs(fd) > 0.1
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-10)
    np.testing.assert_allclose(g_rev, fd, rtol=1e-6)


def test_reduction_geometry_runs_as_stored_programs_equal_to_its_plain_functions():
    from nhjax import _primitive
    from nhjax.scenes import PlanarChain

    chain = PlanarChain()
    x = chain.initial_state(phi=[0.3, -0.2], phi_dot=[0.1, 0.4])
    r = jnp.array([0.3, -0.2])
    before = _primitive.BOUND["call"]
    for name, args in (("curvature", (r,)), ("body_states", (x,))):
        method = getattr(type(chain), name)
        stored, plain = method(chain, *args), jax.jit(method.plain)(chain, *args)
        for a, b in zip(jax.tree_util.tree_leaves(stored), jax.tree_util.tree_leaves(plain)):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-14)
    # under jax.grad the stored program is differentiated by its own stored derivatives
    g = jax.grad(lambda q: chain.connection(q)[2, 0])(r)
    d = 1e-6
    fd = [(float(chain.connection(r + d * e)[2, 0]) - float(chain.connection(r - d * e)[2, 0])) / (2 * d)
          for e in np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert _primitive.BOUND["call"] > before


_SCENES_CHILD = """
import json, sys
import jax, numpy as np
compiles = []  # every XLA compile of the process, by function name
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: compiles.append(kw.get("fun_name", "?"))
    if name == "/jax/core/compile/backend_compile_duration" else None)
sys.path.insert(0, {here!r})
import test_first_answers as t
import nhjax.scenes
del compiles[:]  # (the test module's own constants)
built = t._scene_states(np)
jax.jit(lambda x: x * {salt!r})(1.0).block_until_ready()  # the counter works: one compile seen
print(json.dumps(dict(compiles=compiles, built=[np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(v)]).tolist()
                                                for v in built])))
"""


def _scene_states(xp):
    """Scenes and start states as a user builds them, from numbers (``xp`` = numpy) or
    from traced values (``xp`` = jax.numpy, under jit): parameters derived in the
    constructors and the start states' arithmetic."""
    from nhjax.scenes import FallingCat, PlanarChain, RollingDisk, RollRing, Skate, SkateSE2, TwoWheeledCart

    a = xp.asarray([0.3, -0.2, 0.7, 1.1, 0.4])
    chain = PlanarChain(masses=xp.asarray([1.0, 2.0, 1.5]), lengths=xp.asarray([1.0, 0.8, 1.2]))
    thrusters = PlanarChain(thruster_axes=xp.asarray([[1.0, 1.0], [0.0, 2.0], [3.0, 0.0]]))
    cat = FallingCat.from_dimensions(a[4] + 0.6, a[2] + 0.3, a[3] / 4)
    return [Skate().initial_state(a[0], a[1], a[2], a[3], a[4]),
            SkateSE2().initial_state(a[0], a[1], a[2], a[3], a[4]),
            RollingDisk().initial_state(a[0], a[1], a[2], 0.2 * a[3], a[4], a[0], a[1], a[2]),
            TwoWheeledCart().initial_state(a[0], a[1], a[2], a[3], a[4], a[0], a[1]),
            chain.initial_state(phi=a[0], phi_dot=a[1:3]),
            (chain.bodies.inertias, chain.shape_map.hinge_out, chain.shape_map.hinge_in),
            thrusters.inputs.thruster_axes,
            (cat.I1, cat.lam, cat.B)]


def test_scenes_and_start_states_from_numbers_compile_no_eager_programs_and_equal_the_traced_ones(tmp_path):
    """Built from numbers in a new process, the scenes' derived parameters and start
    states cost no XLA program (each eager jnp operation would be one, compiled or
    looked up in every new process before the first answer): the arithmetic runs on
    the host. The same constructors on traced values (jit) give the same arrays, and a
    roll-ring start state (concrete only) satisfies its constraints."""
    env = dict(os.environ, NHJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    code = _SCENES_CHILD.format(here=os.path.dirname(__file__), salt=float(np.random.default_rng().uniform(2, 3)))
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert len(out["compiles"]) == 1, out["compiles"]  # the counter's own probe, nothing else
    traced = jax.jit(lambda: _scene_states(jnp))()
    assert len(traced) == len(out["built"])
    for host, jitted in zip(out["built"], traced):
        flat = np.concatenate([np.ravel(a) for a in jax.tree_util.tree_leaves(jitted)])
        np.testing.assert_allclose(host, flat, rtol=1e-14, atol=1e-15)
    from nhjax.scenes import RollRing

    ring = RollRing()
    x = ring.initial_state(u_r=0.1, beta=0.3, u_s=0.2, alpha1=0.4, alpha2=-0.5, beta_dot=0.7, u_s_dot=0.3,
                           alpha1_dot=-1.1, alpha2_dot=0.6)
    n = (x.shape[0] - 2) // 2
    q, qd = x[:n], x[n:2 * n]
    assert np.max(np.abs(ring.position_constraints(0.0, q))) < 1e-14
    assert np.max(np.abs(ring.velocity_constraints(0.0, q, qd))) < 1e-14


def _newton_sqrt(a, x0):
    """sqrt(a) by Newton's iteration in a while loop (stops on its own residual, as a
    solve does), with a second output that depends on x0 only."""
    def body(c):
        x, k = c
        return 0.5 * (x + a / x), k + 1

    x, k = jax.lax.while_loop(lambda c: (jnp.abs(c[0] ** 2 - a) > 1e-14 * a) & (c[1] < 50), body, (x0, 0))
    return {"root": x * jnp.ones(3), "iterations": k, "start": 2.0 * x0}


def test_a_batch_of_one_runs_the_program_itself_with_the_batched_programs_answer(monkeypatch, tmp_path):
    """jax.jacfwd in one number vmaps the stored JVP program over a basis of one vector;
    that batch of one is the JVP program on the squeezed inputs, not the vmap of its
    loop: jacfwd, vmap over one and over two members all equal the plain function's,
    and d sqrt(a)/da = 1 / (2 sqrt(a)), a derivative the loop's tangents must carry."""
    from nhjax import _primitive, _programs

    monkeypatch.setattr(_programs, "directory", lambda: tmp_path)
    monkeypatch.setattr(_programs, "_MEMORY", {})
    monkeypatch.setattr(_primitive, "_SPECS", {})

    def stored(a, x0):
        return _primitive.call("newton-sqrt", _newton_sqrt, (a, x0))

    a, x0 = jnp.asarray(2.0), jnp.asarray(1.0)
    before = dict(_primitive.BOUND)
    d = jax.jacfwd(lambda a: stored(a, x0)["root"])(a)
    assert _primitive.BOUND["jvp"] > before["jvp"] and _primitive.BOUND["vmap"] > before["vmap"]
    np.testing.assert_allclose(d, jax.jacfwd(lambda a: _newton_sqrt(a, x0)["root"])(a), rtol=1e-14)
    np.testing.assert_allclose(d, np.full(3, 0.5 / np.sqrt(2.0)), rtol=1e-12)
    for batch in (jnp.asarray([3.0]), jnp.asarray([3.0, 5.0])):
        got = jax.vmap(stored, in_axes=(0, None))(batch, x0)
        want = jax.vmap(_newton_sqrt, in_axes=(0, None))(batch, x0)
        for key in want:
            assert got[key].shape == want[key].shape, key
            np.testing.assert_allclose(got[key], want[key], rtol=1e-15)
    np.testing.assert_allclose(got["root"][:, 0], np.sqrt([3.0, 5.0]), rtol=1e-14)
