"""The fluoroscopy mimic: delivered rate and noise statistics match the request."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from magrun.tracking.fluoroscopy import PAPER_RATES_HZ, FluoroscopyMimic

CAMERA_DT = 0.04  # s, the 25 Hz control and camera rate


def deliveries(
    mimic: FluoroscopyMimic, seconds: float, pose=None
) -> list[tuple[float, np.ndarray]]:
    pose = np.array([0.01, -0.02, 0.5]) if pose is None else pose
    out = []
    for k in range(round(seconds / CAMERA_DT) + 1):
        z = mimic(k * CAMERA_DT, pose)
        if z is not None:
            out.append((k * CAMERA_DT, z))
    return out


@pytest.mark.parametrize("rate", [*PAPER_RATES_HZ, 1.0, 10.0, 12.5])
def test_delivered_rate_matches_request(rate: float) -> None:
    """Over 60 s, frames on the grid k/rate: count within 1 of 60·min(rate, 25) + 1."""
    got = deliveries(FluoroscopyMimic(rate), 60.0)
    expected = 60.0 * min(rate, 1 / CAMERA_DT) + 1
    assert abs(len(got) - expected) <= 1
    times = np.array([t for t, _ in got])
    # each delivery is the first camera frame at or after its due time: never early, late by
    # less than one camera period
    due = np.arange(len(times)) / min(rate, 1 / CAMERA_DT)
    assert np.all(times >= due - 1e-9)
    assert np.all(times < due + CAMERA_DT - 1e-9)


def test_infinite_rate_passes_every_frame() -> None:
    assert len(deliveries(FluoroscopyMimic(math.inf), 2.0)) == 51


def test_noise_statistics_match_sigma() -> None:
    """20 000 deliveries: sample σ within 3 % of the request (its standard error is 0.5 %),
    means within 4 standard errors of zero, x and y uncorrelated."""
    sigma, sigma_th = 2e-3, math.radians(3)
    mimic = FluoroscopyMimic(math.inf, sigma, sigma_th, seed=7)
    pose = np.array([0.01, -0.02, 0.5])
    z = np.array([mimic(k * CAMERA_DT, pose) for k in range(20_000)])
    err = z - pose
    n = len(err)
    assert_allclose(err[:, :2].std(axis=0), sigma, rtol=0.03)
    assert_allclose(err[:, 2].std(), sigma_th, rtol=0.03)
    assert np.all(np.abs(err.mean(axis=0)) < 4 * np.array([sigma, sigma, sigma_th]) / math.sqrt(n))
    assert abs(np.corrcoef(err[:, 0], err[:, 1])[0, 1]) < 4 / math.sqrt(n)


def test_zero_sigma_passes_the_pose_exactly_and_wraps_the_angle() -> None:
    mimic = FluoroscopyMimic(7.5, 0.0, 0.0)
    pose = np.array([0.003, 0.004, 3.1])
    assert_array_equal(mimic(0.0, pose), pose)
    noisy = FluoroscopyMimic(math.inf, 0.0, 1.0, seed=1)
    angles = np.array([noisy(k * CAMERA_DT, pose)[2] for k in range(200)])
    assert np.all((angles > -math.pi) & (angles <= math.pi))


def test_seeded_trials_are_reproducible_and_reset_restarts() -> None:
    a = deliveries(FluoroscopyMimic(7.5, 2e-3, seed=3), 5.0)
    b = deliveries(FluoroscopyMimic(7.5, 2e-3, seed=3), 5.0)
    c = deliveries(FluoroscopyMimic(7.5, 2e-3, seed=4), 5.0)
    assert_array_equal(np.array([z for _, z in a]), np.array([z for _, z in b]))
    assert not np.allclose(np.array([z for _, z in a]), np.array([z for _, z in c]))
    m = FluoroscopyMimic(7.5, 2e-3, seed=3)
    deliveries(m, 5.0)
    m.reset()
    assert_array_equal(np.array([z for _, z in deliveries(m, 5.0)]), np.array([z for _, z in a]))


def test_lost_camera_frame_is_a_lost_fluoroscopy_frame() -> None:
    """A frame due while the tracker has no pose is dropped; the schedule stays on its grid."""
    m = FluoroscopyMimic(5.0)  # due at 0, 0.2, 0.4, ...
    pose = np.zeros(3)
    assert m(0.0, pose) is not None
    assert m(0.2, None) is None  # due, but lost
    assert m(0.24, pose) is None  # not due again before 0.4
    assert m(0.4, pose) is not None


@pytest.mark.parametrize(("rate", "sigma"), [(0.0, 0.0), (-1.0, 0.0), (5.0, -1.0)])
def test_bad_arguments_are_rejected(rate: float, sigma: float) -> None:
    with pytest.raises(ValueError, match="must be"):
        FluoroscopyMimic(rate, sigma)
