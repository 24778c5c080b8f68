"""Pose estimators: the proposed Kalman filter and the baselines' simpler rules.

Kalman filter (paper, Section II-C)
-----------------------------------
The state is the pose ``p = (x, y, θ)``. The process model is the controller itself: the
prediction ``p̂ₖ⁻`` of this tick's pose was made by the NMPC at the previous tick, with the
currents it applied. With F = H = I::

    predict:  p̂ₖ⁻ = NMPC prediction,             Pₖ⁻ = Pₖ₋₁ + Q
    update:   Kₖ = Pₖ⁻ (Pₖ⁻ + R)⁻¹               (only when a measurement zₖ arrives)
              p̂ₖ = p̂ₖ⁻ + Kₖ (zₖ − p̂ₖ⁻),          Pₖ = (I − Kₖ) Pₖ⁻

With no measurement the prediction is the estimate (and P grows by Q). The angle innovation
is wrapped to (−π, π] by moving the measured θ next to the predicted one before the update.

With measurements every tick, P⁻ converges to the solution of the discrete Riccati equation
``P = P − P (P + R)⁻¹ P + Q`` (tests/test_estimation.py checks it).

Where the robot moves in a channel, its position across the channel is known to lie in the
body's free interval: :meth:`KalmanPoseFilter.truncate` conditions the Gaussian on it
(density truncation, D. Simon and D. L. Simon, "Constrained Kalman filtering via density
function truncation for turbofan engine health estimation", Int. J. Systems Science 41(2),
2010). With c = dᵀp the state along a unit direction d, its prior N(ĉ, σ²), σ² = dᵀPd,
restricted to ĉ + [lo, hi], has mean ĉ + δ and variance σ'² (the truncated normal's
moments); the whole state follows by the regression of p on c, exact for a Gaussian::

    p̂ ← p̂ + P d δ / σ²,      P ← P − P d dᵀ P (1 − σ'²/σ²) / σ²

A 2 mm measurement in a channel whose free width is 2 mm carries little across-channel
information that the walls do not; the truncated mean keeps the estimate off the edge of
that interval where the walls say the robot is unlikely to be.

Defaults (:class:`KalmanConfig`): measurement σ 1 mm and 3°, process σ 0.3 mm and 2° per
40 ms tick (the NMPC's one-step prediction error on the simulated plant is ~0.1 mm, plus the
model mismatch the per-trial perturbations add).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter
from numpy.typing import NDArray
from scipy.stats import truncnorm

from magrun.angles import angle_near
from magrun.control.base import Estimator

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class KalmanConfig:
    """Noise standard deviations of the pose Kalman filter (SI: m and rad)."""

    measurement_position: float = 1.0e-3
    measurement_angle: float = math.radians(3.0)
    process_position: float = 0.3e-3
    process_angle: float = math.radians(2.0)
    initial_position: float = 1.0e-3
    initial_angle: float = math.radians(5.0)

    def matrices(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(Q, R, P0)`` as 3×3 diagonal covariances."""

        def diag(pos: float, ang: float) -> FloatArray:
            return np.diag([pos**2, pos**2, ang**2])

        return (
            diag(self.process_position, self.process_angle),
            diag(self.measurement_position, self.measurement_angle),
            diag(self.initial_position, self.initial_angle),
        )


class KalmanPoseFilter(Estimator):
    """The proposed estimator: fuse each measurement with the controller's prediction."""

    def __init__(self, config: KalmanConfig | None = None) -> None:
        self.config = config or KalmanConfig()
        self.Q, self.R, self.P0 = self.config.matrices()
        self.kf = KalmanFilter(dim_x=3, dim_z=3)
        self.reset(np.zeros(3))

    def reset(self, pose: FloatArray) -> None:
        self.kf.x = np.asarray(pose, dtype=np.float64).reshape(3, 1).copy()
        self.kf.F = np.eye(3)
        self.kf.H = np.eye(3)
        self.kf.Q = self.Q.copy()
        self.kf.R = self.R.copy()
        self.kf.P = self.P0.copy()

    def update(self, measurement: FloatArray | None, prediction: FloatArray | None) -> FloatArray:
        if prediction is not None:
            self.kf.x = np.asarray(prediction, dtype=np.float64).reshape(3, 1).copy()
            self.kf.predict()
        if measurement is not None:
            z = np.asarray(measurement, dtype=np.float64).copy()
            z[2] = angle_near(z[2], float(self.kf.x[2, 0]))
            self.kf.update(z.reshape(3, 1))
        return self.kf.x.ravel().copy()

    @property
    def covariance(self) -> FloatArray:
        return np.asarray(self.kf.P, dtype=np.float64).copy()

    def constrain(self, pose: FloatArray) -> None:
        # projecting the estimate onto the free space (a state constraint): the mean moves,
        # the covariance is kept (a conservative choice: the projection only removes states)
        self.kf.x = np.asarray(pose, dtype=np.float64).reshape(3, 1).copy()

    def truncate(self, direction: FloatArray, lo: float, hi: float) -> FloatArray:
        """Condition the estimate on its component along ``direction`` lying within
        ``[lo, hi]`` of where it is now (module doc): the truncated normal's mean and variance
        along ``direction`` (a 3-vector of the state x, y, θ, unit length), the rest by
        regression. Returns the new estimate."""
        d = np.asarray(direction, dtype=np.float64).reshape(3, 1)
        P = np.asarray(self.kf.P, dtype=np.float64)
        var = (d.T @ P @ d).item()
        if not (var > 0 and lo <= 0 <= hi and hi > lo):
            return self.kf.x.ravel().copy()
        sigma = math.sqrt(var)
        # the truncated normal of the offset from the current mean, in units of sigma
        a, b = lo / sigma, hi / sigma
        mean, variance = truncnorm.stats(a, b, moments="mv")
        shift, ratio = float(mean) * sigma, float(variance)
        if not (math.isfinite(shift) and math.isfinite(ratio)):
            return self.kf.x.ravel().copy()
        gain = P @ d / var
        self.kf.x = self.kf.x + gain * shift
        self.kf.P = P - (P @ d @ d.T @ P) * (1.0 - ratio) / var
        return self.kf.x.ravel().copy()


class MeasurementOrPrediction(Estimator):
    """Baselines 1, 3, 4: the measurement when one arrives, else the controller's prediction.

    A measured θ is moved by a multiple of 2π next to the previous estimate.
    """

    use_prediction = True

    def reset(self, pose: FloatArray) -> None:
        self._last = np.asarray(pose, dtype=np.float64).copy()

    def update(self, measurement: FloatArray | None, prediction: FloatArray | None) -> FloatArray:
        if measurement is not None:
            z = np.asarray(measurement, dtype=np.float64).copy()
            # trackers report θ in (−π, π]; keep the estimate continuous, as the NMPC's warm
            # start and the reference are
            z[2] = angle_near(z[2], float(self._last[2]))
            self._last = z
        elif prediction is not None and self.use_prediction:
            self._last = np.asarray(prediction, dtype=np.float64).copy()
        return self._last.copy()

    def constrain(self, pose: FloatArray) -> None:
        self._last = np.asarray(pose, dtype=np.float64).copy()


class HoldLastMeasurement(MeasurementOrPrediction):
    """Baseline 2 (PID): the latest measurement, held until the next one (no prediction)."""

    use_prediction = False
