"""One closed-loop trial: rig, feedback, controller, reference, at the control period.

    >>> from magrun.loop import run_trial
    >>> log = run_trial(controller, rig, s_trajectory())       # doctest: +SKIP
    >>> log.rms_position_mm, log.rms_orientation_deg           # doctest: +SKIP

One tick::

    rig.observe() ──► actual pose (+ camera frame)
    tracker(frame) ──► tracked pose, or None when lost       (no tracker: the actual pose)
    feedback(t, tracked) ──► measured pose, or None          (e.g. FluoroscopyMimic)
    controller.step(measured, reference window) ──► currents ──► rig.apply
    controller.prepare(next reference window)                 (the plant runs on meanwhile)
    rig.advance (the rest of the period)

``feedback(t, pose)`` turns the camera pose into the controller's measurement, or ``None``
when no fluoroscopy frame arrives at this tick; :func:`perfect_feedback` passes every pose
through. The runner (protocols, recording) builds on this loop; it records everything
:class:`TrialLog` holds.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from magrun.angles import wrap_angle
from magrun.control.base import Controller
from magrun.records import ControllerStatus, Tick
from magrun.rigs.base import PoseTracker, Rig
from magrun.safety import SafetyConfig, SafetyLayer
from magrun.scene import Trajectory

FloatArray = NDArray[np.float64]
Feedback = Callable[[float, FloatArray | None], FloatArray | None]


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
    compute_time: FloatArray  # (n,) s, tracking + feedback + controller per tick
    interrupted: bool = False  # ended early by a stop request (currents ramped to zero)
    stop_reason: str = ""  # why the safety layer stopped the trial ("" : it ran to the end)
    #: (n,) whether the tick took a camera frame (always, without a tracker or frame_due)
    framed: NDArray[np.bool_] | None = None
    #: CPU seconds of the loop's thread in each stage (:data:`STAGES`), summed over the ticks
    stage_cpu_s: dict[str, float] | None = None

    @property
    def tracking_lost(self) -> int:
        """Frames taken in which the tracker did not find the robot."""
        taken = np.ones(len(self.t), bool) if self.framed is None else self.framed
        return int(np.count_nonzero(taken & ~np.isfinite(self.tracked[:, 0])))

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
    def rms_prediction_measured_position_mm(self) -> float:
        """RMS of the measured pose against the previous tick's prediction of it, over the
        ticks where a measurement arrived (what a real rig can compute; NaN: none)."""
        d = self.measured[1:, :2] - self.predicted[1:, :2]
        e = np.sum(d**2, axis=1)
        e = e[np.isfinite(e)]
        return float(np.sqrt(np.mean(e)) * 1e3) if e.size else math.nan

    @property
    def rms_prediction_measured_orientation_deg(self) -> float:
        d = wrap_angle(self.measured[1:, 2] - self.predicted[1:, 2])
        d = d[np.isfinite(d)]
        return float(np.degrees(np.sqrt(np.mean(d**2)))) if d.size else math.nan

    @property
    def solve_times(self) -> FloatArray:
        return np.array([s.solve_time for s in self.status])


#: the stages of a tick whose CPU time :func:`run_trial` adds up (``TrialLog.stage_cpu_s``):
#: the rig's observation (in simulation: rendering the camera frame), tracking the frame,
#: the feedback and the controller's step, the plant (the safety layer, applying the
#: currents, advancing the rig: in simulation the plant's integration), handing the tick
#: to the recorder, the controller's preparation of the next tick, and the rest of the loop
#: (its own bookkeeping)
STAGES = ("observe", "track", "control", "plant", "record", "prepare", "loop")


def run_trial(
    controller: Controller,
    rig: Rig,
    reference: Trajectory,
    feedback: Feedback = perfect_feedback,
    horizon: int = 20,
    duration: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    tracker: PoseTracker | None = None,
    frame_due: Callable[[float], bool] | None = None,
    on_tick: Callable[[Tick], None] | None = None,
    latency: float | Literal["measured"] = 0.0,
    clock: Callable[[], float] = time.perf_counter,
    stop: Callable[[], bool] | None = None,
    safety: SafetyLayer | None = None,
    planned: Trajectory | None = None,
) -> TrialLog:
    """Run ``reference`` (plus 1 s of hold) closed loop; the robot starts at its first pose.

    The controller follows ``planned`` (default: ``reference``), a reference of the same
    timing whose headings the coils can hold; the log's desired poses are ``reference``'s.

    With a ``tracker``, the controller's feedback comes from the rig's camera frames (the rig
    must have a camera); without one, from the actual pose. Give a fresh ``feedback`` per
    trial (a :class:`~magrun.tracking.fluoroscopy.FluoroscopyMimic` keeps its schedule).

    ``frame_due(t)`` (with a tracker; e.g. the mimic's ``due``) says at which ticks the camera
    takes a frame: on the others the rig renders none, nothing is tracked, and the feedback
    gets nothing (no frame was due). Without it every tick has a frame.

    ``latency`` (for simulated rigs) is the time, s, between a tick's observation and its
    new currents: it passes on the plant with the previous currents before the new ones
    apply, and a tick lasts ``max(Δt, latency)``. A number is declared and the trial stays
    independent of the machine (0: the plant waits for the controller). ``"measured"``
    charges the tick's wall-clock compute ``c`` (tracking, feedback, controller): a
    controller slower than the control rate then runs slower, as on hardware, and the trial
    depends on the machine's speed and load. The measured ``c`` is logged either way.

    ``on_tick`` receives a :class:`Tick` after each tick's currents are applied (the
    recorder's hook); it runs on the loop's thread, so it must be quick. Then the controller
    prepares the next tick (:meth:`Controller.prepare`: the NMPC linearises around its
    prediction), which is not part of the tick's measured compute ``c``: it happens while the
    plant runs on the new currents, before the next observation.

    Every tick's currents pass through ``safety`` (:class:`magrun.safety.SafetyLayer`;
    default: the controller's current and slew limits, a safe stop on non-finite currents,
    no tracking or workspace checks). When it trips, the currents ramp to zero at the slew
    limit, those ticks recorded like any other, and the trial ends (``TrialLog.stop_reason``).

    ``stop()`` is asked after every tick: when true, the safety layer trips ("interrupted"),
    the currents ramp to zero as above, and the trial ends early (``TrialLog.interrupted``;
    :mod:`magrun.interrupt`).

    The loop thread's CPU time in each of :data:`STAGES` is summed in
    ``TrialLog.stage_cpu_s`` (``time.thread_time``: what the stage cost, not what the
    machine's load made it wait).
    """
    dt = controller.dt
    if safety is None:
        safety = SafetyLayer(
            controller.n_channels, controller.max_current, controller.max_change / dt, dt,
            SafetyConfig(lost_timeout_s=None, workspace_margin_m=None),
        )  # fmt: skip
    safety.reset()
    total = reference.duration + 1.0 if duration is None else duration
    n_nominal = math.floor(total / dt + 1e-9) + 1
    plan = reference if planned is None else planned
    start = reference.pose(0.0)
    rig.reset(start)
    controller.reset(start)
    if tracker is not None:
        tracker.reset()
    rows: dict[str, list[FloatArray]] = {k: [] for k in _LOG_ARRAYS}
    statuses: list[ControllerStatus] = []
    compute: list[float] = []
    taken: list[bool] = []
    nan3 = np.full(3, np.nan)
    prediction: FloatArray | None = None
    offsets = np.arange(horizon + 1) * dt
    lead = controller.latency  # the controller plans across it (0: none)
    measured = latency == "measured"
    declared = 0.0 if measured else float(latency)
    k, t = 0, 0.0
    interrupted = False
    cpu = time.thread_time
    spent = dict.fromkeys(STAGES, 0.0)
    loop_start = cpu()
    while t <= total + 1e-9 or (safety.tripped and not safety.at_rest):
        take = tracker is None or frame_due is None or frame_due(t)
        c0 = cpu()
        obs = rig.observe(frame=take and tracker is not None)
        c1 = cpu()
        spent["observe"] += c1 - c0
        t0 = clock()
        camera_pose: FloatArray | None = None
        if tracker is None:  # the rig's pose (NaN: its own tracking lost the robot)
            seen = obs.pose if obs.camera_pose is None else obs.camera_pose
            camera_pose = seen if np.all(np.isfinite(seen)) else None
        elif not take:
            pass  # no frame due: nothing to track, nothing delivered
        elif obs.frame is None:
            raise ValueError("a tracker needs camera frames: give the rig a camera")
        else:
            camera_pose = tracker(obs.frame)
        c2 = cpu()
        spent["track"] += c2 - c1
        z = feedback(obs.t, camera_pose) if take else None
        # the plan starts when its currents apply, the controller's latency from now
        window = plan.pose(obs.t + lead + offsets)
        desired = reference.pose(obs.t) if lead or plan is not reference else window[0]
        # a frame's age (its time stamp): the controller fuses it where it was taken
        age = obs.t - obs.frame_time if z is not None and obs.frame_time is not None else 0.0
        out = controller.step(z, window, age)
        c = clock() - t0
        c3 = cpu()
        spent["control"] += c3 - c2
        charged = c if measured else declared
        period = max(dt, charged)
        if charged > 0:
            rig.advance(charged)  # the previous currents drive the plant meanwhile
        safety.check(obs.t, obs.pose, (camera_pose is not None) if take else None)
        applied = rig.apply(safety.limit(out.currents, out.fault, obs.t))
        c4 = cpu()
        spent["plant"] += c4 - c3
        tick = Tick(
            k=k, t=obs.t, actual=obs.pose, tracked=camera_pose if tracker is not None else None,
            measured=z, estimated=out.estimate, predicted=prediction, desired=desired,
            currents=applied, status=out.status, compute_time=c, frame=obs.frame,
            latency=rig.last_latency, safety_stop=safety.reason, measured_age=age,
        )  # fmt: skip
        for name, value in (
            ("t", np.array([obs.t])),
            ("actual", obs.pose),
            ("tracked", nan3 if camera_pose is None else camera_pose),
            ("desired", desired),
            ("measured", nan3 if z is None else z),
            ("estimated", out.estimate),
            ("predicted", nan3 if prediction is None else prediction),
            ("currents", applied),
        ):
            rows[name].append(np.asarray(value, dtype=np.float64))
        statuses.append(out.status)
        compute.append(c)
        taken.append(take)
        c5 = cpu()
        if on_tick is not None:
            on_tick(tick)
        c6 = cpu()
        spent["record"] += c6 - c5
        prediction = out.predicted
        rest = period - charged
        # the next tick's work that needs no measurement, while the plant runs on; its time
        # as a simulated rig's clock will read it (it adds each advance: the same sum, in the
        # same order), so that the next tick's window is the prepared one to the bit
        t_next = obs.t + charged + rest if charged > 0 and rest > 0 else obs.t + period
        controller.prepare(plan.pose(t_next + lead + offsets))
        c7 = cpu()
        spent["prepare"] += c7 - c6
        if rest > 0:
            rig.advance(rest)
        spent["plant"] += cpu() - c7
        t = obs.t + period
        k += 1
        if progress is not None:
            progress(min(k, n_nominal), n_nominal)
        if stop is not None and not interrupted and stop():
            interrupted = True
            safety.trip("interrupted", t)
        if safety.at_rest:
            break
    if progress is not None and k < n_nominal and not safety.tripped:
        progress(n_nominal, n_nominal)
    spent["loop"] = max(cpu() - loop_start - sum(spent.values()), 0.0)
    arrays = {name: np.stack(rows[name]) for name in _LOG_ARRAYS}
    return TrialLog(
        **{name: arrays[name] for name in _LOG_ARRAYS if name != "t"},
        t=arrays["t"][:, 0],
        status=statuses,
        compute_time=np.array(compute),
        interrupted=interrupted,
        stop_reason=safety.reason,
        framed=np.array(taken, dtype=bool),
        stage_cpu_s=spent,
    )


_LOG_ARRAYS = (
    "t", "actual", "tracked", "desired", "measured", "estimated", "predicted", "currents",
)  # fmt: skip
