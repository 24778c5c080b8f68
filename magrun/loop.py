"""One closed-loop trial: rig, feedback, controller, reference, at the control period.

    >>> from magrun.loop import run_trial
    >>> log = run_trial(controller, rig, s_trajectory())       # doctest: +SKIP
    >>> log.rms_position_mm, log.rms_orientation_deg           # doctest: +SKIP

One tick::

    rig.observe() ──► actual pose (+ camera frame)
    tracker(frame) ──► tracked pose, or None when lost       (no tracker: the actual pose)
    feedback(t, tracked) ──► measured pose, or None          (e.g. FluoroscopyMimic)
    controller.step(measured, reference window) ──► currents ──► rig.apply ──► rig.advance

``feedback(t, pose)`` turns the camera pose into the controller's measurement, or ``None``
when no fluoroscopy frame arrives at this tick; :func:`perfect_feedback` passes every pose
through. The runner (protocols, recording) builds on this loop; it records everything
:class:`TrialLog` holds.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from magrun.control.base import Controller, ControllerStatus
from magrun.rigs.base import Rig
from magrun.robot import wrap_angle
from magrun.scene import Trajectory

FloatArray = NDArray[np.float64]
Feedback = Callable[[float, FloatArray | None], FloatArray | None]


class PoseTracker(Protocol):
    """What the loop needs of a camera tracker (:class:`magrun.tracking.tracker.Tracker`)."""

    def reset(self) -> None: ...

    def __call__(self, frame: NDArray[np.uint8]) -> FloatArray | None: ...


def perfect_feedback(t: float, pose: FloatArray | None) -> FloatArray | None:
    """Every tick gets the camera pose as it is."""
    return pose


@dataclass
class TrialLog:
    """Per-tick arrays of one trial (SI units); row k is tick k at time ``t[k]``."""

    t: FloatArray  # (n,)
    actual: FloatArray  # (n, 3)
    tracked: FloatArray  # (n, 3), the camera pose; NaN where the tracker lost the robot
    desired: FloatArray  # (n, 3)
    measured: FloatArray  # (n, 3), NaN where no measurement arrived
    estimated: FloatArray  # (n, 3)
    predicted: FloatArray  # (n, 3), the previous tick's prediction of this tick; NaN at k = 0
    currents: FloatArray  # (n, n_channels), as applied
    status: list[ControllerStatus]

    @property
    def position_error(self) -> FloatArray:
        return np.hypot(*(self.actual[:, :2] - self.desired[:, :2]).T)

    @property
    def orientation_error(self) -> FloatArray:
        return np.abs(wrap_angle(self.actual[:, 2] - self.desired[:, 2]))

    @property
    def rms_position_mm(self) -> float:
        return float(np.sqrt(np.mean(self.position_error**2)) * 1e3)

    @property
    def rms_orientation_deg(self) -> float:
        return float(np.degrees(np.sqrt(np.mean(self.orientation_error**2))))

    @property
    def rms_prediction_position_mm(self) -> float:
        d = self.actual[1:, :2] - self.predicted[1:, :2]
        return float(np.sqrt(np.mean(np.sum(d**2, axis=1))) * 1e3)

    @property
    def rms_prediction_orientation_deg(self) -> float:
        d = wrap_angle(self.actual[1:, 2] - self.predicted[1:, 2])
        return float(np.degrees(np.sqrt(np.mean(d**2))))

    @property
    def solve_times(self) -> FloatArray:
        return np.array([s.solve_time for s in self.status])


def run_trial(
    controller: Controller,
    rig: Rig,
    reference: Trajectory,
    feedback: Feedback = perfect_feedback,
    horizon: int = 20,
    duration: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    tracker: PoseTracker | None = None,
) -> TrialLog:
    """Run ``reference`` (plus 1 s of hold) closed loop; the robot starts at its first pose.

    With a ``tracker``, the controller's feedback comes from the rig's camera frames (the rig
    must have a camera); without one, from the actual pose. Give a fresh ``feedback`` per
    trial (a :class:`~magrun.tracking.fluoroscopy.FluoroscopyMimic` keeps its schedule).
    """
    dt = controller.dt
    total = reference.duration + 1.0 if duration is None else duration
    n = math.floor(total / dt + 1e-9) + 1
    start = reference.pose(0.0)
    rig.reset(start)
    controller.reset(start)
    if tracker is not None:
        tracker.reset()
    n_ch = controller.n_channels
    log = TrialLog(
        t=np.zeros(n),
        actual=np.zeros((n, 3)),
        tracked=np.full((n, 3), np.nan),
        desired=np.zeros((n, 3)),
        measured=np.full((n, 3), np.nan),
        estimated=np.zeros((n, 3)),
        predicted=np.full((n, 3), np.nan),
        currents=np.zeros((n, n_ch)),
        status=[],
    )
    prediction = np.full(3, np.nan)
    offsets = np.arange(horizon + 1) * dt
    for k in range(n):
        obs = rig.observe()
        if tracker is None:
            camera_pose: FloatArray | None = obs.pose
        elif obs.frame is None:
            raise ValueError("a tracker needs camera frames: give the rig a camera")
        else:
            camera_pose = tracker(obs.frame)
        z = feedback(obs.t, camera_pose)
        window = reference.pose(obs.t + offsets)
        out = controller.step(z, window)
        applied = rig.apply(out.currents)
        log.t[k] = obs.t
        log.actual[k] = obs.pose
        if camera_pose is not None:
            log.tracked[k] = camera_pose
        log.desired[k] = window[0]
        if z is not None:
            log.measured[k] = z
        log.estimated[k] = out.estimate
        log.predicted[k] = prediction
        log.currents[k] = applied
        log.status.append(out.status)
        prediction = out.predicted
        rig.advance(dt)
        if progress is not None:
            progress(k + 1, n)
    return log
