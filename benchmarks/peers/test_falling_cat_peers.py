"""Checks of the falling-cat benchmark peers (``falling_cat.py``).

Run with ``python -m pytest benchmarks/peers/test_falling_cat_peers.py``.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location(
    "falling_cat_peers", Path(__file__).with_name("falling_cat.py")
)
fc = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fc)


@pytest.fixture(scope="module")
def default():
    case = fc.CAT_DEFAULT
    return {
        "p": fc.case_params(case),
        "y0": fc.case_y0(case),
        "t1": float(case["t1"]),
        "ref": fc.reference_solution(case),
    }


def test_numba_dp5_matches_scipy_reference(default):
    y1, n_acc, n_rej = fc.dp54_numba(default["y0"], default["t1"], 1e-10, 1e-10, default["p"])
    assert n_acc > 0 and n_rej >= 0
    np.testing.assert_allclose(y1, default["ref"], rtol=0, atol=1e-7)


def test_batch_equals_single_exactly(default):
    Y0 = fc.perturbed_y0s(8, seed=3)
    Y0[0] = default["y0"]
    for kw in ({}, {"dt0": fc.DIFFRAX_DT0, "diffrax_error": True}):
        Y1, steps = fc.dp54_numba_batch(Y0, default["t1"], 1e-8, 1e-8, default["p"], **kw)
        assert Y1.shape == Y0.shape and steps.shape == (Y0.shape[0],)
        for j in range(Y0.shape[0]):
            y1, n_acc, _ = fc.dp54_numba(Y0[j].copy(), default["t1"], 1e-8, 1e-8, default["p"], **kw)
            assert steps[j] == n_acc
            np.testing.assert_array_equal(Y1[j], y1)


def test_error_decreases_with_rtol(default):
    errs = {}
    for tol in (1e-4, 1e-8):
        y1, _, _ = fc.dp54_numba(default["y0"], default["t1"], tol, tol, default["p"])
        errs[tol] = np.max(np.abs(y1 - default["ref"]))
    assert errs[1e-8] < 1e-2 * errs[1e-4]


@pytest.mark.parametrize("tol, acc, rej", [(1e-4, 10, 2), (1e-8, 47, 6), (1e-10, 112, 7)])
def test_diffrax_mode_step_counts(default, tol, acc, rej):
    """Counts measured with diffrax 0.7.2: Dopri5(), PIDController(rtol=atol=tol), dt0=None."""
    _, n_acc, n_rej = fc.dp54_numba(
        default["y0"], default["t1"], tol, tol, default["p"], dt0=fc.DIFFRAX_DT0, diffrax_error=True
    )
    assert (n_acc, n_rej) == (acc, rej)


def test_max_steps_flag(default):
    _, _, _, exhausted = fc.dp54_solve(
        default["y0"], 0.0, default["t1"], 1e-10, 1e-10, default["p"], 5, 0.0, False
    )
    assert exhausted
    with pytest.raises(RuntimeError):
        fc.dp54_numba(default["y0"], default["t1"], 1e-10, 1e-10, default["p"], max_steps=5)
    Y1, steps = fc.dp54_numba_batch(
        default["y0"][None, :], default["t1"], 1e-10, 1e-10, default["p"], max_steps=5
    )
    assert steps[0] == -1 and np.isnan(Y1[0]).all()


def test_scipy_peer_close_to_reference(default):
    out = fc.solve_scipy("Radau", 1e-10, 1e-10)
    np.testing.assert_allclose(out["y1"], default["ref"], rtol=0, atol=1e-6)
    assert out["nfev"] > 0 and out["nsteps"] > 0 and out["seconds"] > 0
