"""The two-layer baselines' box-constrained least squares: DAQP against scipy's BVLS and KKT."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from magrun.control.qp import BoxLeastSquares, bvls
from magrun.control.two_layer import linear_model, linear_model_expm
from magrun.robot import load_robots


def _problem(seed: int, n: int, rows: int, reg: float) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    M = np.vstack([rng.normal(size=(rows, n)), np.sqrt(reg) * np.eye(n)])
    r = np.concatenate([rng.normal(scale=3.0, size=rows), np.zeros(n)])
    lo = -rng.uniform(0.1, 1.0, n)
    hi = rng.uniform(0.1, 1.0, n)
    return M, r, lo, hi


def _kkt_residual(M, r, x, lo, hi) -> float:
    """Largest violation of the optimality conditions, relative to the gradient's scale."""
    g = M.T @ (M @ x - r)  # gradient of ½‖Mx − r‖²
    scale = np.abs(M.T @ r).max() + 1e-300
    at_lo, at_hi = np.isclose(x, lo, atol=1e-9), np.isclose(x, hi, atol=1e-9)
    free = ~(at_lo | at_hi)
    viol = np.concatenate([np.abs(g[free]), np.maximum(-g[at_lo], 0), np.maximum(g[at_hi], 0)])
    return float(viol.max(initial=0.0) / scale)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    shape=st.sampled_from([(8, 4), (8, 12), (60, 120), (60, 20)]),
    reg=st.sampled_from([1e-4, 1e-2, 1.0]),
)
@example(seed=1441, shape=(60, 20), reg=1e-4)  # DAQP at its default primal tolerance
@example(seed=1819, shape=(60, 20), reg=1e-4)  # stopped short of the optimum on these
def test_daqp_finds_the_bvls_optimum(seed: int, shape: tuple[int, int], reg: float) -> None:
    """Same feasible point, same objective (1e-9 relative), first-order optimal (KKT 1e-7)."""
    n, rows = shape
    M, r, lo, hi = _problem(seed, n, rows, reg)
    solve = BoxLeastSquares(n)
    x, ref = solve(M, r, lo, hi), bvls(M, r, lo, hi)
    assert np.all(lo <= x)
    assert np.all(x <= hi)
    f, f_ref = np.sum((M @ x - r) ** 2), np.sum((M @ ref - r) ** 2)
    assert f == pytest.approx(f_ref, rel=1e-9)
    assert_allclose(x, ref, atol=1e-6 * (hi - lo).max())
    assert _kkt_residual(M, r, x, lo, hi) < 1e-7
    assert solve.fallbacks == 0


def test_unconstrained_optimum_is_the_normal_equations() -> None:
    M, r, _, _ = _problem(1, 8, 12, 1e-2)
    x = BoxLeastSquares(8)(M, r, -1e6, 1e6)
    assert_allclose(x, np.linalg.lstsq(M, r, rcond=None)[0], rtol=1e-9)


def test_a_solve_daqp_does_not_finish_is_answered_by_bvls(monkeypatch: pytest.MonkeyPatch) -> None:
    """DAQP's iteration limit (exit flag -4) stands in for any flag but optimal: the answer is
    BVLS's, and the solve is counted."""
    import magrun.control.qp as qp

    M, r, lo, hi = _problem(3, 8, 12, 1e-2)
    solve = BoxLeastSquares(8)
    daqp_x = solve(M, r, lo, hi)
    monkeypatch.setattr(qp.daqp, "solve", lambda *a, **k: (np.zeros(8), 0.0, -4, {}))
    x = solve(M, r, lo, hi)
    assert solve.fallbacks == 1
    assert_allclose(x, bvls(M, r, lo, hi), rtol=0, atol=0)
    assert_allclose(x, daqp_x, atol=1e-6 * (hi - lo).max())


def test_wrong_size_is_refused() -> None:
    with pytest.raises(ValueError, match="columns"):
        BoxLeastSquares(8)(np.eye(4), np.zeros(4), -1, 1)


@pytest.mark.parametrize("name", sorted(load_robots()))
def test_closed_form_zoh_equals_the_matrix_exponential(name: str) -> None:
    """Every entry within 1e-9 relative of scipy's expm of the augmented system."""
    robot = load_robots()[name]
    for theta in np.linspace(-3.5, 3.5, 15):
        for dt in (1e-3, 0.04, 0.5):
            Ad, Bd = linear_model(robot, theta, dt)
            Ae, Be = linear_model_expm(robot, theta, dt)
            assert_allclose(Ad, Ae, rtol=1e-9, atol=1e-12 * np.abs(Ae).max())
            assert_allclose(Bd, Be, rtol=1e-9, atol=1e-12 * np.abs(Be).max())
