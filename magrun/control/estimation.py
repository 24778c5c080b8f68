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

Linearised filter (``linearised``, the protocols' default)
----------------------------------------------------------
F = I says an error of the estimate stays the same size over a tick. Where the coils' pull
depends on where the robot is, it does not: a robot 1 mm off the estimate feels another
gradient, so it moves another way than the model's prediction, and the error grows (or
shrinks) by the model's own derivative. With ``linearised`` the covariance goes through it,
an extended Kalman filter's prediction step::

    p̂ₖ⁻ = NMPC prediction,    Pₖ⁻ = F Pₖ₋₁ Fᵀ + Q,    F = ∂(prediction)/∂(pose)

with F computed by the controller (central differences of its model's one-tick prediction
under the currents it applied, across the latency: :meth:`Controller._transition`). The
update is unchanged. Where the pull grows away from the estimate the filter knows its
position is less certain than F = I says and weighs the next frame more; where the pull
holds the robot it weighs it less. On a three-coil system with a background field at 3 Hz
and σ = 2 mm the proposed method's RMS error went from 3.2 to 1.7 mm (6 trials); the
paper's rig at 3 Hz from 1.89 to 1.70 mm (docs: Control, "Linearised filter").

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

Heading bias (optional)
-----------------------
Where the coils' field is off in direction (their gains are off by a few per cent and the
NMPC keeps the field near its least aligned value, so a small absolute error turns it by
degrees), the robot settles at another heading than the model's: between two frames the
model's heading drifts from the robot's by the same amount every tick, and the filter, which
trusts the model between frames, follows the model. With ``heading_bias`` > 0 the state
gains that drift, b (rad per tick), as a random walk (σ = ``heading_bias`` per tick)::

    state (x, y, θ, b):   θₖ⁻ = NMPC prediction of θ + b,     bₖ = bₖ₋₁ + w,  w ~ N(0, σ_b²)

so F is I with F[θ, b] = 1, H measures (x, y, θ). The heading measurements, which the camera
gives to a degree or two, then estimate b frame by frame (a constant drift is followed with
no lasting error: tests/test_estimation.py), and the heading between frames follows the
robot instead of the model. An additive velocity bias for the position did not help ("Mobility"
below says why); the position gets a scale instead.

Mobility (optional)
-------------------
A robot whose force factor (moment over drag) is off, or that loses speed to friction,
moves a fraction of the model's step every tick, and the filter, trusting the model between
frames, puts it ahead of where it is: at 3 Hz, σ = 2 mm and a robot at 0.7 of the model's
speed, by about a millimetre. An additive bias (a velocity the robot lacks) is cancelled by
the controller: behind the path it pushes harder, its model moves the estimate on by as
much as the bias holds it back, while the robot, short of force, does not follow. With
``mobility`` > 0 the state gains the scale k of the model's step δ = prediction − x̂, a random
walk (σ = ``mobility`` per tick) starting at 1::

    state (x, y, …, k):   (x, y)⁻ = (x, y) + k δ,     kₖ = kₖ₋₁ + w,  w ~ N(0, σ_k²)

linear in the state for the known δ, so F is I with F[(x, y), k] = δ this tick and the
filter stays an exact Kalman filter. A harder push now moves the estimate k times as far.
The measured positions estimate k (a constant scale is followed with no lasting error, its
estimate unbiased under noise: tests/test_estimation.py); without motion it learns nothing
and the filter is the plain one.

Outlier gate (optional)
-----------------------
A tracker that takes a glint, a bubble or another object for the robot reports a pose far
from it, or turned end for end, and one such frame at σ = 1 mm moves the estimate most of
the way there. With ``outlier_gate`` = g > 0 a measurement whose innovation y (the pose,
covariance S = P⁻ + R) has yᵀS⁻¹y > g² is not fused (the χ² test of y; with three degrees
of freedom g = 4 rejects 1 in 1000 good measurements). Where the robot has really moved
away from the estimate every measurement is far: after :data:`GATE_PATIENCE` rejections in
a row the next one is taken whatever it says. ``rejected`` counts the rejections.

The patience is for positions. A measured heading more than 90° from the estimate's is a
tracker that took the robot end for end (an occluded fiducial in an X-ray), not a robot
that turned half round between two frames the model followed: with the gate on, such a
measurement's position is fused alone, its heading not, until :data:`FLIP_PATIENCE` of
them in a row say so (then the estimate's heading is what is wrong, and the next one is
taken whole). A real half turn that the estimate missed would not last in any case: the
field the planner sets along the estimated heading turns the robot's moment toward it.
``reversed`` counts them. Without this, three rejections of a tracker's flip
let the fourth into the estimate, and the planner turned the capsule round to match it
(the spine on the C-arm plant at 25.5 Hz, with a filter trusting the tracker more than it
deserved: one trial in 20 touched the critical wall that way).

Strong tracking (optional)
--------------------------
Between frames the filter trusts the model. Where the model's field is least trustworthy
(a three-coil system holds the heading with a field of about B_min whose gradient turns
it) the robot can move away from the prediction for several frames, and a filter that
weighs each frame by its fixed P⁻ follows the model while the robot goes elsewhere. With
``strong_tracking`` on, the filter measures its own consistency (the strong tracking
filter's fading factor; Q. Ge, T. Shao, C. Wen, R. Sun, "Analysis on strong tracking
filtering for linear dynamic systems", Mathematical Problems in Engineering 2015, 648125):
at each frame, with y the position innovation, ρ the forgetting and β the weakening
factor::

    V = (ρ V + y yᵀ) / (1 + ρ)                     (the first frame: V = y yᵀ)
    λ = max(1, tr(V − β R_p) / tr(P⁻_p))           (p: the position block)
    P⁻ ← D P⁻ D,   D = diag(√λ, √λ, 1, …)

so where the innovations are larger than the filter predicts, its position variance (and
with it the weight of the frame) grows by λ before the update; where they are not, λ = 1
and the filter is the plain one. The heading's own variance is left as it is. With a large
β (10: :data:`magrun.trial.GUARD_WEAKENING`) it acts only where the innovations are far
larger than the measurement noise and the prior together, as a guard against the linearised
filter's divergence where its model is wrong: there it trusts the model more than F = I,
and a model far off can hold it off for seconds.

Defaults (:class:`KalmanConfig`): measurement σ 1 mm and 3°, process σ 0.3 mm and 2° per
40 ms tick (the NMPC's one-step prediction error on the simulated plant is ~0.1 mm, plus the
model mismatch the per-trial perturbations add), no heading bias, no mobility state, no
strong tracking (ρ = 0.95 and β = 1.5 where it is on), F = I (the paper's filter; a
protocol's ``controller.kalman.linearised`` defaults to the linearised one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray

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
    #: the heading bias's random walk per tick, rad per tick (module doc; 0: no bias state)
    heading_bias: float = 0.0
    #: the heading bias's initial standard deviation, rad per tick
    initial_heading_bias: float = math.radians(0.4)
    #: the mobility scale's random walk per tick (module doc; 0: no mobility state)
    mobility: float = 0.0
    #: the mobility scale's initial standard deviation (about its nominal 1)
    initial_mobility: float = 0.2
    #: reject a measurement whose pose lies more than this many standard deviations of
    #: its innovation from the prediction (Mahalanobis; module doc; 0: take every one)
    outlier_gate: float = 0.0
    #: scale the position's prior covariance by the strong tracking fading factor (module
    #: doc), with this forgetting factor ρ of the innovations' covariance and weakening
    #: factor β of the measurement noise
    strong_tracking: bool = False
    #: propagate the covariance through the prediction's Jacobian, which :meth:`update` is
    #: then given (module doc, "Linearised filter"); False: F = I
    linearised: bool = False
    forgetting: float = 0.95
    weakening: float = 1.5

    def matrices(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(Q, R, P0)`` as 3×3 diagonal covariances."""

        def diag(pos: float, ang: float) -> FloatArray:
            return np.diag([pos**2, pos**2, ang**2])

        return (
            diag(self.process_position, self.process_angle),
            diag(self.measurement_position, self.measurement_angle),
            diag(self.initial_position, self.initial_angle),
        )


def steady_position_sigma(config: KalmanConfig, frame_ticks: int = 1) -> float:
    """The filter's steady position standard deviation just before a frame, m, with a
    measurement every ``frame_ticks`` ticks: per axis, P⁻ = P + n q² between frames and
    P = P⁻ r² / (P⁻ + r²) at each, so P⁻ is the positive root of
    P⁻² − n q² P⁻ − n q² r² = 0 (q, r: process and measurement σ, n = ``frame_ticks``)."""
    if frame_ticks < 1:
        raise ValueError(f"frame_ticks must be >= 1, got {frame_ticks}")
    a = frame_ticks * config.process_position**2
    r2 = config.measurement_position**2
    return math.sqrt((a + math.sqrt(a * a + 4 * a * r2)) / 2)


#: measurements in a row the outlier gate rejects before it takes the next one anyway
GATE_PATIENCE = 3
#: measured headings more than 90° from the estimate's in a row whose headings the gate
#: leaves out (their positions fused) before it takes the next one whole
FLIP_PATIENCE = 10


class KalmanPoseFilter(Estimator):
    """The proposed estimator: fuse each measurement with the controller's prediction."""

    def __init__(self, config: KalmanConfig | None = None) -> None:
        self.config = config or KalmanConfig()
        c = self.config
        if not c.heading_bias >= 0:
            raise ValueError(f"heading_bias must be >= 0, got {c.heading_bias}")
        if not c.outlier_gate >= 0:
            raise ValueError(f"outlier_gate must be >= 0, got {c.outlier_gate}")
        if not all(math.isfinite(v) and v >= 0 for v in (c.mobility, c.initial_mobility)):
            raise ValueError(
                f"mobility and initial_mobility must be >= 0, got {c.mobility}, "
                f"{c.initial_mobility}"
            )
        if not (0.0 <= c.forgetting < 1.0 and c.weakening >= 1.0):
            raise ValueError(
                f"forgetting must be in [0, 1) and weakening >= 1, got {c.forgetting}, "
                f"{c.weakening}"
            )
        #: measurements the gate rejected, and the current run of them
        self.rejected = 0
        self._run = 0
        #: measurements whose reversed heading the gate left out, and the current run of them
        self.reversed = 0
        self._flips = 0
        #: the strong tracking filter's innovation covariance (module doc) and last factor
        self._innovations: FloatArray | None = None
        self.fading = 1.0
        Q, R, P0 = c.matrices()
        #: where the heading bias and the mobility scale (module doc) sit in the state
        self._bias = 3 if c.heading_bias > 0 else None
        self._mobility = (3 if self._bias is None else 4) if c.mobility > 0 else None
        #: state size: the pose (3), the heading bias and the mobility where they are on
        self.n = 3 + (self._bias is not None) + (self._mobility is not None)
        n = self.n
        self.Q, self.P0, self.R = np.zeros((n, n)), np.zeros((n, n)), R
        self.Q[:3, :3], self.P0[:3, :3] = Q, P0
        self.F, self.H = np.eye(n), np.eye(3, n)
        if (b := self._bias) is not None:
            self.Q[b, b] = c.heading_bias**2
            self.P0[b, b] = c.initial_heading_bias**2
            self.F[2, b] = 1.0  # θ⁻ = prediction + b
        if (m := self._mobility) is not None:
            self.Q[m, m] = c.mobility**2
            self.P0[m, m] = c.initial_mobility**2
        # imported here: filterpy's package imports scipy.stats (about a second of a fresh
        # process's start-up), which a process running no Kalman filter never needs; with the
        # filter, scipy.stats is then in memory before any tick (:meth:`truncate` uses it)
        from filterpy.kalman import KalmanFilter
        from scipy.stats import truncnorm

        self._truncnorm = truncnorm

        self.kf = KalmanFilter(dim_x=n, dim_z=3)
        self.reset(np.zeros(3))

    def reset(self, pose: FloatArray) -> None:
        self.kf.x = np.zeros((self.n, 1))
        self.kf.x[:3, 0] = np.asarray(pose, dtype=np.float64)
        if self._mobility is not None:
            self.kf.x[self._mobility, 0] = 1.0
        self.kf.F = self.F.copy()
        self.kf.H = self.H.copy()
        self.kf.Q = self.Q.copy()
        self.kf.R = self.R.copy()
        self.kf.P = self.P0.copy()
        self._innovations, self.fading = None, 1.0

    def update(
        self,
        measurement: FloatArray | None,
        prediction: FloatArray | None,
        jacobian: FloatArray | None = None,
    ) -> FloatArray:
        if prediction is not None:
            p = np.asarray(prediction, dtype=np.float64)
            if (m := self._mobility) is not None:
                # x⁻ = x + k δ, δ = prediction − x the model's step (known): F[:2, k] = δ
                self.kf.F[0, m], self.kf.F[1, m] = p[:2] - self.kf.x[:2, 0]
                self.kf.x[2, 0] = p[2]
            else:
                self.kf.x[:3, 0] = p
            before = np.asarray(self.kf.P, dtype=np.float64)
            self.kf.predict()
            if jacobian is not None and self.config.linearised:
                F = self.kf.F.copy()
                F[:3, :3] = jacobian  # P⁻ = F P Fᵀ + Q with the model's linearisation
                self.kf.P = F @ before @ F.T + self.kf.Q
        if measurement is not None:
            z = np.asarray(measurement, dtype=np.float64).copy()
            z[2] = angle_near(z[2], float(self.kf.x[2, 0]))
            if self._gated(z):
                return self.pose
            if self.config.strong_tracking:
                self._fade(z)
            if self._reversed(z):  # its position alone (module doc, "Outlier gate")
                self.kf.update(z[:2].reshape(2, 1), R=self.kf.R[:2, :2], H=self.kf.H[:2])
            else:
                self.kf.update(z.reshape(3, 1))
        return self.pose

    def _reversed(self, z: FloatArray) -> bool:
        """Whether, with the gate on, ``z``'s heading (already next to the estimate's) is
        more than 90° from the estimate's and fewer than :data:`FLIP_PATIENCE` such
        measurements came in a row before it: its heading is then left out."""
        if self.config.outlier_gate <= 0:
            return False
        if abs(z[2] - float(self.kf.x[2, 0])) <= math.pi / 2:
            self._flips = 0
            return False
        if self._flips < FLIP_PATIENCE:
            self._flips += 1
            self.reversed += 1
            return True
        self._flips = 0
        return False

    def _fade(self, z: FloatArray) -> None:
        """Scale the position's prior covariance by the fading factor λ (module doc)."""
        c = self.config
        y = z[:2] - self.kf.x[:2, 0]
        V = np.outer(y, y)
        if self._innovations is not None:
            V = (c.forgetting * self._innovations + V) / (1.0 + c.forgetting)
        self._innovations = V
        P = np.asarray(self.kf.P, dtype=np.float64)
        spread = float(np.trace(P[:2, :2]))
        excess = float(np.trace(V) - c.weakening * np.trace(self.R[:2, :2]))
        self.fading = max(1.0, excess / spread) if spread > 0 else 1.0
        D = np.ones(self.n)
        D[:2] = math.sqrt(self.fading)
        self.kf.P = P * np.outer(D, D)

    def _gated(self, z: FloatArray) -> bool:
        """Whether the gate rejects ``z``: its innovation y (pose), covariance
        S = P⁻ + R, is beyond ``outlier_gate`` σ (yᵀS⁻¹y > gate²), and
        fewer than :data:`GATE_PATIENCE` measurements in a row were rejected before it
        (then the robot has moved where the estimate did not follow: take it)."""
        gate = self.config.outlier_gate
        if gate <= 0:
            return False
        y = z - self.kf.x[:3, 0]  # θ already next to the prediction (update)
        S = np.asarray(self.kf.P[:3, :3] + self.R, dtype=np.float64)
        far = float(y @ np.linalg.solve(S, y)) > gate**2
        if far and self._run < GATE_PATIENCE:
            self._run += 1
            self.rejected += 1
            return True
        self._run = 0
        return False

    @property
    def uses_jacobian(self) -> bool:  # type: ignore[override]
        """Whether :meth:`update` propagates the covariance through the given Jacobian."""
        return self.config.linearised

    @property
    def pose(self) -> FloatArray:
        """The pose estimate (x, y, θ), SI."""
        return np.asarray(self.kf.x[:3, 0], dtype=np.float64).copy()

    def snapshot(self) -> object:
        innovations = None if self._innovations is None else self._innovations.copy()
        return self.kf.x.copy(), self.kf.P.copy(), self._run, self.rejected, innovations

    def restore(self, state: object) -> None:
        saved = cast(tuple[FloatArray, FloatArray, int, int, FloatArray | None], state)
        self.kf.x = saved[0].copy()
        self.kf.P = saved[1].copy()
        self._run, self.rejected = saved[2], saved[3]
        self._innovations = None if saved[4] is None else saved[4].copy()

    @property
    def heading_bias(self) -> float:
        """The estimated heading drift of the model, rad per tick (0 without the state)."""
        return 0.0 if self._bias is None else float(self.kf.x[self._bias, 0])

    @property
    def mobility(self) -> float:
        """The estimated mobility scale: the robot's step over the model's (1 without it)."""
        return 1.0 if self._mobility is None else float(self.kf.x[self._mobility, 0])

    @property
    def covariance(self) -> FloatArray:
        """The pose's covariance (3×3, SI)."""
        return np.asarray(self.kf.P[:3, :3], dtype=np.float64).copy()

    def constrain(self, pose: FloatArray) -> None:
        # projecting the estimate onto the free space (a state constraint): the mean moves,
        # the covariance is kept (a conservative choice: the projection only removes states)
        self.kf.x[:3, 0] = np.asarray(pose, dtype=np.float64)

    def truncate(self, direction: FloatArray, lo: float, hi: float) -> FloatArray:
        """Condition the estimate on its component along ``direction`` lying within
        ``[lo, hi]`` of where it is now (module doc): the truncated normal's mean and variance
        along ``direction`` (a 3-vector of the pose x, y, θ, unit length), the rest of the
        state (the heading bias too) by regression. Returns the new pose estimate."""
        d = np.zeros((self.n, 1))
        d[:3, 0] = np.asarray(direction, dtype=np.float64)
        P = np.asarray(self.kf.P, dtype=np.float64)
        var = (d.T @ P @ d).item()
        if not (var > 0 and lo <= 0 <= hi and hi > lo):
            return self.pose
        sigma = math.sqrt(var)
        # the truncated normal of the offset from the current mean, in units of sigma
        a, b = lo / sigma, hi / sigma
        mean, variance = self._truncnorm.stats(a, b, moments="mv")
        shift, ratio = float(mean) * sigma, float(variance)
        if not (math.isfinite(shift) and math.isfinite(ratio)):
            return self.pose
        gain = P @ d / var
        self.kf.x = self.kf.x + gain * shift
        self.kf.P = P - (P @ d @ d.T @ P) * (1.0 - ratio) / var
        return self.pose


class MeasurementOrPrediction(Estimator):
    """Baselines 1, 3, 4: the measurement when one arrives, else the controller's prediction.

    A measured θ is moved by a multiple of 2π next to the previous estimate.
    """

    use_prediction = True

    def reset(self, pose: FloatArray) -> None:
        self._last = np.asarray(pose, dtype=np.float64).copy()

    def update(
        self,
        measurement: FloatArray | None,
        prediction: FloatArray | None,
        jacobian: FloatArray | None = None,
    ) -> FloatArray:
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

    def snapshot(self) -> object:
        return self._last.copy()

    def restore(self, state: object) -> None:
        self._last = np.array(state, dtype=np.float64)


class HoldLastMeasurement(MeasurementOrPrediction):
    """Baseline 2 (PID): the latest measurement, held until the next one (no prediction)."""

    use_prediction = False
