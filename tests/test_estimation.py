"""Pose estimators: Kalman filter against Riccati theory and hand computation, baseline rules."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.linalg import solve_discrete_are

from magrun.estimation import (
    HoldLastMeasurement,
    KalmanConfig,
    KalmanPoseFilter,
    MeasurementOrPrediction,
)


def test_covariance_reaches_the_riccati_steady_state() -> None:
    """With a measurement every tick, P⁻ → the DARE solution for F = H = I (rtol 1e-9)."""
    kf = KalmanPoseFilter()
    Q, R = kf.Q, kf.R
    rng = np.random.default_rng(1)
    pose = np.zeros(3)
    for _ in range(400):
        kf.update(pose + rng.normal(0, 1e-3, 3), pose)
    prior = solve_discrete_are(np.eye(3), np.eye(3), Q, R)
    posterior = prior - prior @ np.linalg.solve(prior + R, prior)
    assert_allclose(kf.covariance, posterior, rtol=1e-9)


def test_update_is_the_variance_weighted_mean() -> None:
    """Diagonal P and R: each coordinate fuses as (R p + P z) / (P + R), P = P0 + Q."""
    cfg = KalmanConfig()
    kf = KalmanPoseFilter(cfg)
    kf.reset(np.zeros(3))
    prediction = np.array([1e-3, -2e-3, 0.1])
    z = np.array([2e-3, 0.0, 0.2])
    est = kf.update(z, prediction)
    Q, R, P0 = cfg.matrices()
    P = np.diag(P0 + Q)
    r = np.diag(R)
    assert_allclose(est, (r * prediction + P * z) / (P + r), rtol=1e-12)


def test_no_measurement_means_the_prediction_and_growing_covariance() -> None:
    kf = KalmanPoseFilter()
    kf.reset(np.zeros(3))
    P_before = kf.covariance
    prediction = np.array([0.01, 0.02, 1.0])
    assert_allclose(kf.update(None, prediction), prediction, rtol=0, atol=0)
    assert_allclose(kf.covariance, P_before + kf.Q, rtol=1e-12)


def test_angle_innovation_is_wrapped() -> None:
    """A measurement just across ±π from the prediction pulls the estimate across, not through 0."""
    kf = KalmanPoseFilter()
    kf.reset(np.array([0.0, 0.0, math.pi - 0.01]))
    est = kf.update(np.array([0.0, 0.0, -math.pi + 0.01]), np.array([0.0, 0.0, math.pi - 0.01]))
    assert math.pi - 0.01 < est[2] < math.pi + 0.01


@pytest.mark.parametrize("cls", [MeasurementOrPrediction, HoldLastMeasurement])
def test_baseline_estimators(cls: type) -> None:
    est = cls()
    est.reset(np.zeros(3))
    z = np.array([1.0, 2.0, 3.0])
    p = np.array([4.0, 5.0, 6.0])
    assert_allclose(est.update(z, p), z)
    expected_gap = p if cls is MeasurementOrPrediction else z
    assert_allclose(est.update(None, p), expected_gap)


@pytest.mark.parametrize("cls", [MeasurementOrPrediction, HoldLastMeasurement])
def test_baseline_estimates_stay_continuous_across_pi(cls: type) -> None:
    """Tracked θ wraps at ±π; the estimate follows the heading continuously (θ + 2πk)."""
    est = cls()
    est.reset(np.array([0.0, 0.0, math.pi - 0.2]))
    headings = math.pi - 0.2 + 0.1 * np.arange(1, 8)  # turning through π
    for th in headings:
        got = est.update(np.array([0.0, 0.0, math.atan2(math.sin(th), math.cos(th))]), None)
        assert got[2] == pytest.approx(th, abs=1e-12)
