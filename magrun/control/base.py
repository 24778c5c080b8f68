"""The interface the six control methods share.

A :class:`Controller` is an estimator and a planner behind one ``step``::

    measured pose or None ─► Estimator(measured, last prediction) ─► pose estimate
        estimate ─► FreeSpace.project (the workspace or phantom the protocol declares)
        at a measurement, in a phantom: Estimator.truncate to the body's free interval
            across the critical boundary (FreeSpace.across)
        velocity = the prediction's (model velocity), or (estimate − previous estimate) / Δt
    [estimate, velocity], reference window, previous currents ─► Planner ─► currents, prediction
        safety: clamp_currents (|I| ≤ I_max, |ΔI| ≤ slew Δt, non-finite → 0) on every tick

Velocity: the planner's own prediction of this tick's velocity (``velocity="model"``, the
methods with a Kalman filter), or the finite difference of the estimates (``"difference"``,
the paper's rule, kept by the baselines). With a filter, the estimate jumps by the innovation
at every fluoroscopy frame, so the difference spikes there (~20 mm/s at 3 Hz and σ = 2 mm);
the drag-dominated robot's velocity is set by the field within a few ms, and the model's
prediction of it is what the plan needs.

An estimator that propagates its covariance through the model (:attr:`Estimator.uses_jacobian`,
the linearised Kalman filter) gets with each prediction its Jacobian by the pose, by central
differences of the same one-tick prediction (:data:`JACOBIAN_STEPS`); others get none and
cost nothing.

A measurement may describe the robot as it was some time ago (``step(..., age=s)``: a
camera's or C-arm's frame age, known from the frame's time stamp). The controller then fuses
it at the tick it was taken, nearest ``age``: it goes back to its state at the start of that
tick (it keeps the last :data:`MEMORY` ticks: the estimator's state, the measurements fused
and the currents applied), fuses the measurement there with those of that tick, and runs
the estimation and the model's prediction forward again with the currents applied since, to
this tick. With every measurement on time this is the usual tick; with every measurement
late it gives the estimate a filter fed in time order would (tests/test_control.py).

The new currents reach the coils some time after the tick's observation (``latency``: the
tick's compute). Meanwhile the previous currents act, so with ``latency`` > 0 the planner
plans from the state predicted for then (the model's one-tick prediction under the previous
currents, interpolated to the fraction ``latency/Δt`` of the period; drag-dominated motion is
near uniform within a period), for a reference window that starts then (the loop shifts it),
and the prediction handed to the next tick is taken back from ``Δt + latency`` to ``Δt``
the same way.

Integral action (``integral_time`` T > 0): the planner gets the reference window with its
positions moved by an offset b, which grows after each tick's plan by g (r₀ − x₀), the
position error at the plan's start, with g = Δt/T · σ₀² / (σ₀² + σ²): σ² the estimate's
position variance per axis (the estimator's covariance; σ₀ = :data:`INTEGRAL_SIGMA`), so
the offset follows a bias the measurements show and ignores the noise they carry. Without a
covariance g = Δt/T. The offset stops growing while a coil is at its limit and its length is
held to :data:`INTEGRAL_LIMIT` (anti-windup). A planner whose weights let the robot lag
behind by what its model does not know of it (the robot's mobility, a coil's gain) then
tracks without that offset: on OctoMag with exact feedback at 25.5 Hz the proposed method's
RMS went from 12 µm to 3 µm (docs: Control).

After the currents went out, ``prepare(next reference window)`` lets the planner do the next
tick's work that needs no measurement (the NMPC linearises around its prediction); ``step``
then only finishes it, so the delay from measurement to currents is the feedback phase.

``step`` returns a :class:`ControlOutput`: the currents to apply, the estimate it used, its
prediction of the pose at the next tick, and a :class:`ControllerStatus` (solve time,
iterations, success, fallback). Planners differ (NMPC, PID + allocation, linear MPC +
allocation); estimators differ (Kalman filter, measurement-or-prediction, hold-last); the loop
around them is this one class.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.angles import wrap_angle
from magrun.freespace import FreeSpace
from magrun.records import ControllerStatus
from magrun.safety import Limit, clamp_currents

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Plan:
    """A planner's answer: currents (A) and the state it predicts one tick ahead."""

    currents: FloatArray
    predicted_state: FloatArray  # (6,) x, y, θ, vx, vy, ω
    status: ControllerStatus


@dataclass(frozen=True)
class ControlOutput:
    """What a controller hands to the rig and the recorder at one tick."""

    currents: FloatArray  # (n_channels,) A, within limits
    estimate: FloatArray  # (3,) the pose the plan started from
    predicted: FloatArray  # (3,) predicted pose at the next tick
    status: ControllerStatus
    fault: str = ""  # a planner output the clamp had to repair (the safety layer stops on it)


#: ticks a controller remembers for late measurements (1 s at the paper's 25.5 Hz)
MEMORY = 26

#: m: the integral action's offset is held to this length (anti-windup)
INTEGRAL_LIMIT = 1e-3
#: a coil's current at this fraction of its limit or more stops the integral action
SATURATED = 0.98
#: m: the estimate's position σ at which the integral action is half as fast
INTEGRAL_SIGMA = 0.2e-3
#: the central differences' steps of the prediction's Jacobian (x, y in m, θ in rad)
JACOBIAN_STEPS = (1e-5, 1e-5, 1e-4)


class Estimator(ABC):
    """Turns the (possibly missing) measurement and the last prediction into a pose."""

    @abstractmethod
    def reset(self, pose: FloatArray) -> None: ...

    def snapshot(self) -> object:
        """The estimator's state, for :meth:`restore` (a late measurement's re-run)."""
        return copy.deepcopy(self.__dict__)

    def restore(self, state: object) -> None:
        """Go back to a :meth:`snapshot`."""
        self.__dict__.update(copy.deepcopy(state))  # type: ignore[call-overload]

    def fuse_more(self, measurement: FloatArray) -> FloatArray:
        """Fuse a further measurement of the same tick, after :meth:`update` (a late one
        that belongs here); the new pose. By default the latest measurement wins."""
        return self.update(measurement, None)

    #: whether :meth:`update` uses the prediction's Jacobian (the controller computes it only
    #: for an estimator that does)
    uses_jacobian = False

    @abstractmethod
    def update(
        self,
        measurement: FloatArray | None,
        prediction: FloatArray | None,
        jacobian: FloatArray | None = None,
    ) -> FloatArray:
        """The pose estimate (3,) at this tick; ``jacobian`` (3×3): the prediction's
        derivative by the last tick's pose, where :attr:`uses_jacobian`."""

    @property
    def covariance(self) -> FloatArray | None:
        """The estimate's covariance (3×3, SI), where the estimator keeps one."""
        return None

    def predicted_covariance(
        self, prediction: FloatArray | None, jacobian: FloatArray | None = None
    ) -> FloatArray | None:
        """The covariance (3×3) that :meth:`update` without a measurement, from this
        ``prediction`` and ``jacobian``, would leave, the estimator left as it is; None
        where it keeps none."""
        if self.covariance is None:
            return None
        before = self.snapshot()
        self.update(None, prediction, jacobian)
        covariance = self.covariance
        self.restore(before)
        return covariance

    def constrain(self, pose: FloatArray) -> None:  # noqa: B027 (optional hook)
        """The estimate was moved to ``pose`` (into the free space): start from there."""

    def truncate(self, direction: FloatArray, lo: float, hi: float) -> FloatArray | None:
        """Condition the estimate on its component along ``direction`` (3,) lying within
        ``[lo, hi]`` of where it is; the new estimate, or None where the estimator keeps no
        distribution to condition (the default)."""
        return None


class Planner(ABC):
    """Turns a state estimate and a reference window into currents."""

    @abstractmethod
    def reset(self) -> None:
        """Forget warm starts and integrators (a new trial)."""

    @abstractmethod
    def plan(self, state: FloatArray, reference: FloatArray, previous: FloatArray) -> Plan:
        """Currents for this tick.

        Parameters
        ----------
        state : ndarray, shape (6,)
            Estimated ``[x, y, θ, vx, vy, ω]``, SI.
        reference : ndarray, shape (horizon + 1, 3)
            Desired poses at this tick and the next ``horizon`` ticks.
        previous : ndarray, shape (n_channels,)
            Currents applied at the previous tick, A.
        """

    @abstractmethod
    def predict(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        """The planner's model of the state one tick after applying ``currents``."""

    #: whether :meth:`observe_uncertainty` and :meth:`expect_uncertainty` use what they are
    #: given (the controller computes the covariance before the frame only then)
    uses_uncertainty = False

    def observe_uncertainty(self, covariance: FloatArray | None) -> None:  # noqa: B027 (hook)
        """The estimate's covariance (3×3) at this tick before its frame (the filter's
        prediction), before :meth:`plan`; planners that use it (the NMPC's corridor)
        override this."""

    def expect_uncertainty(self, covariance: FloatArray | None) -> None:  # noqa: B027 (hook)
        """What :meth:`observe_uncertainty` will be given at the next tick (the filter's
        prediction, :meth:`Estimator.predicted_covariance`, known a tick ahead), before
        :meth:`prepare`; planners whose preparation depends on it (the NMPC's corridor)
        override this."""

    def prepare(  # noqa: B027 (optional hook)
        self, state: FloatArray, reference: FloatArray, previous: FloatArray
    ) -> None:
        """Work for the next tick that needs no measurement, done after this tick's currents
        went out: ``state`` is the predicted state at the next tick (6,), ``reference`` the
        next tick's window and ``previous`` the currents just applied. :meth:`plan` then
        does only what the measurement changes (the NMPC's real-time iteration: linearise
        before, solve after). Planners without such a split ignore it."""


class Controller:
    """Estimator + planner + safety clamp: one tick of any control method.

    Parameters
    ----------
    name : str
        Method name as recordings state it (``proposed``, ``baseline1`` …).
    estimator, planner
        The method's parts.
    dt : float
        Control period, s.
    max_current, max_slew_rate : float or ndarray
        A and A/s: one value for every channel, or one per channel.
        Limits, A and A/s; every output obeys them.
    free_space : FreeSpace, optional
        Where the robot's body can be: every estimate is projected into it.
    velocity : {"difference", "model"}
        The velocity handed to the planner (module doc).
    latency : float
        Expected time, s, from a tick's observation to its currents reaching the coils; the
        planner plans across it (module doc). 0: the currents apply at once.
    """

    def __init__(
        self,
        name: str,
        estimator: Estimator,
        planner: Planner,
        dt: float,
        max_current: Limit,
        max_slew_rate: Limit,
        n_channels: int,
        free_space: FreeSpace | None = None,
        velocity: str = "difference",
        latency: float = 0.0,
        integral_time: float = 0.0,
    ) -> None:
        if velocity not in ("difference", "model"):
            raise ValueError(f"velocity must be 'difference' or 'model', not {velocity!r}")
        if not (math.isfinite(latency) and latency >= 0):
            raise ValueError(f"latency must be finite and >= 0, got {latency!r}")
        if not (math.isfinite(integral_time) and integral_time >= 0):
            raise ValueError(f"integral_time must be finite and >= 0, got {integral_time!r}")
        self.latency = float(latency)
        self.integral_time = float(integral_time)
        self.name = name
        self.estimator = estimator
        self.planner = planner
        self.free_space = free_space
        self.velocity = velocity
        self.dt = dt
        self.max_current = max_current
        self.max_change = max_slew_rate * dt
        self.n_channels = n_channels
        self.reset(np.zeros(3))

    def reset(self, pose: ArrayLike) -> None:
        """Start a trial: the robot at rest at ``pose``, all currents 0 A."""
        p = np.asarray(pose, dtype=np.float64).copy()
        self.estimator.reset(p)
        self.planner.reset()
        self._previous_estimate = p
        self._prediction: FloatArray | None = None
        self._jacobian: FloatArray | None = None
        self._prior: FloatArray | None = None  # the coming tick's covariance before its frame
        #: the state and currents of the last prediction, until its Jacobian is computed
        self._linearise_at: tuple[FloatArray, FloatArray] | None = None
        self._predicted_state: FloatArray | None = None
        self._predicted_velocity: FloatArray | None = None
        self.currents = np.zeros(self.n_channels)
        #: m: the integral action's offset of the reference's positions (module doc)
        self.reference_offset = np.zeros(2)
        self._memory: deque[_TickMemory] = deque(maxlen=MEMORY)
        #: late measurements fused at their tick, and those older than the memory (dropped)
        self.late_fused = 0
        self.late_dropped = 0

    def _state(self) -> tuple[object, ...]:
        """What a tick starts from (the estimator's state and the last tick's outcome)."""
        return (
            self.estimator.snapshot(), self._previous_estimate, self._prediction,
            self._predicted_state, self._predicted_velocity, self.currents, self._jacobian,
            self._linearise_at,
        )  # fmt: skip

    def _restore(self, state: tuple[object, ...]) -> None:
        self.estimator.restore(state[0])
        (
            self._previous_estimate, self._prediction, self._predicted_state,
            self._predicted_velocity, self.currents, self._jacobian, self._linearise_at,
        ) = state[1:]  # type: ignore[assignment]  # fmt: skip

    def _ahead(self, state: FloatArray) -> FloatArray:
        """The state when this tick's currents apply, ``latency`` after ``state`` (the
        previous currents act meanwhile; module doc); ``state`` itself without latency."""
        if self.latency <= 0:
            return state
        f = min(self.latency / self.dt, 1.0)
        p = self.planner.predict(state, self.currents)
        out = state.copy()
        out[:3] = state[:3] + f * (p[:3] - state[:3])
        if p.size >= 6:
            out[3:6] = p[3:6]
        return out

    def _back(self, start: FloatArray, predicted: FloatArray) -> FloatArray:
        """A plan's prediction from ``start`` (``Δt`` after the currents applied) taken
        back to the next tick's observation time, ``latency`` earlier."""
        if self.latency <= 0:
            return predicted
        f = min(self.latency / self.dt, 1.0)
        out = predicted.copy()
        out[:3] = start[:3] + (1.0 - f) * (predicted[:3] - start[:3])
        return out

    def _next(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        """The model's prediction of the next tick's state from this tick's ``state``
        with ``currents`` applied after the latency."""
        start = self._ahead(state)
        return self._back(start, self.planner.predict(start, currents))

    def _fuse_late(self, z: FloatArray, lag: int) -> None:
        """Fuse ``z``, taken ``lag`` ticks ago, at that tick, and run the estimation forward
        again to the start of this tick (module doc)."""
        ticks = list(self._memory)[-lag:]
        ticks[0].measurements.append(z)
        self._restore(ticks[0].start)
        for i, tick in enumerate(ticks):
            if i > 0:
                tick.start = self._state()
            state = self._estimate_with(tick.measurements)
            predicted = self._next(state, tick.currents)
            self._advance(state[:3].copy(), predicted, tick.currents, state)
        self.late_fused += 1

    def _begin(self, measurement: ArrayLike | None, age: float) -> FloatArray:
        """A tick's estimation: a late measurement is fused at its tick first (module
        doc); returns the state the planner sees."""
        z = None if measurement is None else np.asarray(measurement, dtype=np.float64)
        lag = round(age / self.dt) if z is not None and age > 0 else 0
        if z is not None and lag > 0:
            if lag <= len(self._memory):
                self._fuse_late(z, lag)
            else:
                self.late_dropped += 1
            z = None
        self._memory.append(_TickMemory(self._state(), [] if z is None else [z]))
        return self._estimate_with(self._memory[-1].measurements)

    def _estimate_with(self, measurements: list[FloatArray]) -> FloatArray:
        """The estimation half of a tick with these measurements (none, one, or a late one
        beside the tick's own)."""
        state = self._estimate(measurements[0] if measurements else None)
        for z in measurements[1:]:
            estimate = self.estimator.fuse_more(z)
            if self.free_space is not None:
                estimate = self._into_free_space(estimate, self.free_space, True)
            state = np.concatenate([estimate, state[3:]])
        return state

    def _into_free_space(self, estimate: FloatArray, fs: FreeSpace, measured: bool) -> FloatArray:
        """The estimate projected into the free space; at a measurement, also conditioned on
        the body's free interval across the critical boundary (where the estimator keeps a
        distribution: :meth:`Estimator.truncate`)."""
        inside = fs.project(estimate)
        if not np.array_equal(inside, estimate):
            estimate = inside
            self.estimator.constrain(estimate)
        if not measured or self.estimator.covariance is None:
            return estimate  # nothing to condition
        across = fs.across(estimate)
        if across is None:
            return estimate
        n, lo, hi = across
        truncated = self.estimator.truncate(np.array([n[0], n[1], 0.0]), lo, hi)
        if truncated is None:
            return estimate
        inside = fs.project(truncated)
        if not np.array_equal(inside, truncated):
            self.estimator.constrain(inside)
        return inside

    def _estimate(self, measurement: ArrayLike | None) -> FloatArray:
        """The estimation half of a tick: the state ``[x, y, θ, vx, vy, ω]`` the planner sees."""
        z = None if measurement is None else np.asarray(measurement, dtype=np.float64)
        self._linearise()
        estimate = self.estimator.update(z, self._prediction, self._jacobian)
        if self.free_space is not None:
            estimate = self._into_free_space(estimate, self.free_space, z is not None)
        if self.velocity == "model" and self._predicted_velocity is not None:
            velocity = self._predicted_velocity
        else:
            delta = estimate - self._previous_estimate
            delta[2] = wrap_angle(delta[2])
            velocity = delta / self.dt
        return np.concatenate([estimate, velocity])

    def _linearise(self) -> None:
        """The last prediction's Jacobian, if it is still to compute (:meth:`prepare`
        computes it off the feedback path; a replay or a late measurement's re-run here)."""
        if self._linearise_at is not None:
            self._jacobian = self._transition(*self._linearise_at)
            self._linearise_at = None

    def _transition(self, state: FloatArray, currents: FloatArray) -> FloatArray | None:
        """∂ :meth:`_next` (pose) / ∂ ``state``'s pose, by central differences (the model's
        linearisation: an extended Kalman filter's F); None where it is not finite."""
        J = np.empty((3, 3))
        for j, h in enumerate(JACOBIAN_STEPS):
            up, down = state.copy(), state.copy()
            up[j] += h
            down[j] -= h
            J[:, j] = (self._next(up, currents)[:3] - self._next(down, currents)[:3]) / (2 * h)
        return J if np.all(np.isfinite(J)) else None

    def _advance(
        self, estimate: FloatArray, predicted: FloatArray, currents: FloatArray,
        state: FloatArray,
    ) -> None:  # fmt: skip
        self._jacobian = None
        self._prior = None
        uses = self.estimator.uses_jacobian
        self._linearise_at = (state.copy(), currents.copy()) if uses else None
        self._previous_estimate = estimate
        self._prediction = predicted[:3].copy()
        self._predicted_state = predicted.copy() if predicted.size >= 6 else None
        self._predicted_velocity = predicted[3:6].copy() if predicted.size >= 6 else None
        self.currents = currents

    def prepare(self, reference: FloatArray) -> None:
        """The planner's preparation for the next tick (:meth:`Planner.prepare`), from the
        prediction of this tick's plan: call it after the currents went out, before the next
        measurement. ``reference``: the next tick's window."""
        self._linearise()  # the estimator's Jacobian of the prediction, off the feedback path
        if self._predicted_state is not None:
            state = self._predicted_state
            if self.latency > 0:  # the next plan starts when its currents apply
                state = self._ahead(state)
            if self.planner.uses_uncertainty:  # the next tick's before its frame, as in step
                self.planner.expect_uncertainty(self._prior_covariance())
            self.planner.prepare(state, self._offset(reference), self.currents)

    def _prior_covariance(self) -> FloatArray | None:
        """The covariance the estimate has at the coming tick before its frame (the filter's
        prediction from this tick; :meth:`Estimator.predicted_covariance`), as the planner
        sees it (module doc); the estimator's own before its first prediction."""
        if self._prediction is None:
            return self.estimator.covariance
        if self._prior is None:
            self._linearise()
            self._prior = self.estimator.predicted_covariance(self._prediction, self._jacobian)
        return self._prior

    def _offset(self, reference: FloatArray) -> FloatArray:
        """``reference`` with its positions moved by the integral action's offset."""
        if not self.reference_offset.any():
            return reference
        shifted = np.array(reference, dtype=np.float64)
        shifted[:, :2] += self.reference_offset
        return shifted

    def _integrate(self, reference: FloatArray, start: FloatArray, currents: FloatArray) -> None:
        """The integral action (module doc): the offset grows by g times the position error
        at the plan's start (g = Δt/T, less where the estimate is uncertain), its length
        held to :data:`INTEGRAL_LIMIT`; not while a coil of ``currents`` is at its limit."""
        if self.integral_time <= 0:
            return
        if np.any(np.abs(currents) >= SATURATED * np.asarray(self.max_current)):
            return  # anti-windup
        error = np.asarray(reference[0, :2]) - start[:2]
        if not np.all(np.isfinite(error)):
            return
        gain = self.dt / self.integral_time
        covariance = self.estimator.covariance
        if covariance is not None:  # slower where the estimate is uncertain (module doc)
            variance = float(np.trace(np.asarray(covariance)[:2, :2])) / 2
            gain *= INTEGRAL_SIGMA**2 / (INTEGRAL_SIGMA**2 + variance)
        offset = self.reference_offset + error * gain
        norm = float(np.hypot(*offset))
        if norm > INTEGRAL_LIMIT:
            offset *= INTEGRAL_LIMIT / norm
        self.reference_offset = offset

    def replay_step(
        self, measurement: ArrayLike | None, currents: ArrayLike, age: float = 0.0
    ) -> tuple[FloatArray, FloatArray]:
        """One tick of estimation with the planner replaced by given ``currents`` (those a
        recording says were applied): the estimate, and the planner's model's prediction of
        the next tick's pose from it under those currents, which the next tick's estimator
        update uses as its prior. The estimator sees the consequences of its own estimates,
        not of the recorded ones. ``age``: as for :meth:`step`."""
        state = self._begin(measurement, age)
        applied = np.asarray(currents, dtype=np.float64)
        self._memory[-1].currents = applied
        predicted = self._next(state, applied)
        estimate = state[:3].copy()
        self._advance(estimate, predicted, applied, state)
        return estimate, predicted[:3].copy()

    def step(
        self, measurement: ArrayLike | None, reference: FloatArray, age: float = 0.0
    ) -> ControlOutput:
        """One tick: ``measurement`` is a pose (x, y, θ) or ``None`` when no frame arrived;
        ``age`` (s) how long before this tick the measurement's frame was taken (module doc)."""
        uses = self.planner.uses_uncertainty
        prior = self._prior_covariance() if uses else None  # before this tick's frame
        state = self._begin(measurement, age)
        estimate = state[:3].copy()
        start = self._ahead(state)  # where the robot is when these currents apply
        if uses:
            self.planner.observe_uncertainty(prior)
        plan = self.planner.plan(start, self._offset(reference), self.currents)
        fault = ""
        if not np.all(np.isfinite(plan.currents)):
            fault = f"the {self.name} planner returned non-finite currents"
        currents = clamp_currents(plan.currents, self.currents, self.max_current, self.max_change)
        self._integrate(reference, start, currents)
        predicted = plan.predicted_state
        if not np.allclose(currents, plan.currents, atol=1e-6, rtol=0) or not np.all(
            np.isfinite(predicted)
        ):
            predicted = self.planner.predict(start, currents)
        predicted = self._back(start, predicted)
        self._memory[-1].currents = currents
        self._advance(estimate, predicted, currents, state)
        return ControlOutput(currents, estimate, predicted[:3].copy(), plan.status, fault)


@dataclass
class _TickMemory:
    """One remembered tick: the controller's state at its start, the measurements fused in
    it (late ones added), and the currents applied after it."""

    start: tuple[object, ...]
    measurements: list[FloatArray]
    currents: FloatArray = field(default_factory=lambda: np.zeros(0))
