"""Checks of the CasADi steering peer (``casadi_steering.py``) against nhjax: the
CasADi and NumPy formulas equal ``ReducedSteering.vector_field`` /
``ReducedSteeringTarget`` at random points, the start is the OCP's, and the RK4
interval map converges to the continuous flow. Skipped without casadi.

Run with ``python -m pytest benchmarks/peers/test_casadi_steering.py``.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("casadi")

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import casadi_steering as cs  # noqa: E402

_spec = importlib.util.spec_from_file_location("steering_peer", HERE.parent / "steering_peer.py")
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_formulas_match_nhjax():
    worst, plane = bench.check_formulas(cs, n=40, seed=1)  # asserts < 1e-12 itself
    assert plane.shape == (3, 2)
    np.testing.assert_allclose(plane.T @ cs.initial_state()[6:9], 0.0, atol=1e-15)


def test_hanging_attitude_for_a_tilted_centre_of_mass():
    c = np.array([0.01, -0.02, 0.03])
    R = cs.hanging_attitude(c)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-15)
    np.testing.assert_allclose(R @ c, [0.0, 0.0, -np.linalg.norm(c)], atol=1e-15)


def test_rk4_interval_map_converges_to_the_flow():
    """One interval (h = 0.1 s) of a torque ramp from a moving state: the RK4 map's
    error falls like M^-4 against DOP853 at 1e-13 on the NumPy equations."""
    from scipy.integrate import solve_ivp

    f, _ = cs.steering_functions()
    rng = np.random.default_rng(3)
    x0 = cs.initial_state()
    x0[0:6] = rng.normal(size=6)
    ua, ub = rng.normal(size=3) * 0.2, rng.normal(size=3) * 0.2
    h = 0.1
    ref = solve_ivp(lambda t, x: cs.rhs_numpy(x, ua + (ub - ua) * t / h), (0.0, h), x0, method="DOP853",
                    rtol=1e-13, atol=1e-13).y[:, -1]
    errs = []
    for M in (4, 8):
        F = cs._interval_map(30, 3.0, "pl", M, f)
        errs.append(np.abs(np.asarray(F(x0, ua, ub)).ravel() - ref).max())
    assert errs[1] < 1e-5, errs
    assert 10 < errs[0] / errs[1] < 25, errs  # ~2^4
