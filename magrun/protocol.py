"""Declarative experiment protocols: the YAML schema, validation, and expansion into trials.

A protocol names a robot, a workspace, a reference trajectory, the methods to compare, the
conditions to sweep and those to hold fixed, and how many trials to run of each::

    name: rate_under_noise
    robot: magnet
    workspace: {kind: open}
    trajectory: {kind: s_curve, size_mm: 43, speed_mm_s: 3}
    methods: [proposed, baseline1, baseline2, baseline3, baseline4]
    sweep: {tracking_rate_hz: [3, 5, 7.5, 10, 15, 25.5]}
    conditions: {noise_sigma_mm: 2.0}
    trials: 3

    >>> from magrun.protocol import load_protocol
    >>> protocol = load_protocol("protocols/rate.yaml")          # doctest: +SKIP
    >>> trials = protocol.expand()                                # method × sweep × trials

Every model forbids unknown keys; :func:`load_protocol` raises
:class:`~magrun.yamlio.YamlModelError` naming the file, the YAML line and the field of every
problem. ``magrun protocol schema`` prints :func:`json_schema` for editors.

Conditions (:class:`Conditions`) are what a sweep may vary: the fluoroscopy rate and the
feedback noise. A trial's seed depends on the protocol seed, the index of its swept
condition (not the method) and its repeat index, so every method meets the same plant
perturbations, lighting and noise draws in the same condition and repeat (paired
comparisons), and the same protocol and seed give the same trials whatever runs them.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from magrun.control import METHODS
from magrun.rigs.plant import Imperfections
from magrun.scene import distinct_places

if TYPE_CHECKING:
    from magrun.robot import RobotParams
from magrun.yamlio import load_yaml_model, safe_json, validate_data

#: most trials one protocol file may expand to: a sweep beyond it is refused before anything
#: runs (10,000 trials of the paper's 52 s is six days of rig time)
MAX_TRIALS = 10_000

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# --------------------------------------------------------------------------------------------
# conditions


#: the bounds of a protocol's rates and noise: beyond them a trial is no experiment, and a
#: control rate of 1e9 Hz or a latency of a day would run (or wait) for ever
MAX_RATE_HZ = 1000.0  # control and feedback rates, Hz (coil amplifiers: a few kHz at most)
MIN_CONTROL_RATE_HZ = 1.0
MAX_LATENCY_MS = 10_000.0
MAX_INTEGRAL_TIME_S = 3600.0  # an integral action slower than an hour is none
MAX_NOISE_MM = 1000.0  # a protocol's workspace is at most a metre across
MAX_NOISE_DEG = 360.0
Rate = Annotated[float, Field(gt=0, le=MAX_RATE_HZ, allow_inf_nan=False)]
NoiseMm = Annotated[float, Field(ge=0, le=MAX_NOISE_MM, allow_inf_nan=False)]
NoiseDeg = Annotated[float, Field(ge=0, le=MAX_NOISE_DEG, allow_inf_nan=False)]
#: a factor on a derived tuning value, or "auto" (derived from the system, robot and task)
AutoFactor = Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] | Literal["auto"]


class Conditions(_Strict):
    """Feedback conditions of one trial: unit-suffixed as written, in SI as properties."""

    tracking_rate_hz: Rate | None = Field(
        None, description="Fluoroscopy (feedback) frame rate, Hz; default: every control tick."
    )
    noise_sigma_mm: NoiseMm = Field(
        0.0, description="Gaussian feedback noise, standard deviation on x and on y, mm."
    )
    noise_sigma_deg: NoiseDeg = Field(
        0.0, description="Gaussian feedback noise on the heading, standard deviation, degrees."
    )

    @property
    def rate_hz(self) -> float:
        """Feedback frames per second (infinite: one every control tick)."""
        return self.tracking_rate_hz or math.inf

    @property
    def noise_position_m(self) -> float:
        """Feedback noise on x and on y, standard deviation, m."""
        return self.noise_sigma_mm * 1e-3

    @property
    def noise_heading_rad(self) -> float:
        """Feedback noise on the heading, standard deviation, rad."""
        return math.radians(self.noise_sigma_deg)


#: how each condition is written in a condition slug (``rate-3hz``) and in results
CONDITION_SLUGS = {
    "tracking_rate_hz": ("rate", "hz"),
    "noise_sigma_mm": ("sigma", "mm"),
    "noise_sigma_deg": ("sigmatheta", "deg"),
}


class Sweep(_Strict):
    """Conditions to vary: each key lists its values; trials cover every combination."""

    tracking_rate_hz: Annotated[list[Rate], Field(min_length=1)] | None = None
    noise_sigma_mm: Annotated[list[NoiseMm], Field(min_length=1)] | None = None
    noise_sigma_deg: Annotated[list[NoiseDeg], Field(min_length=1)] | None = None

    @field_validator("*")
    @classmethod
    def _distinct(cls, values: list[float] | None) -> list[float] | None:
        if values is not None and len(set(values)) != len(values):
            raise ValueError("sweep values must be distinct")
        return values

    def items(self) -> list[tuple[str, list[float]]]:
        return [(k, v) for k, v in self.model_dump().items() if v is not None]


# --------------------------------------------------------------------------------------------
# workspace and trajectory


class OpenWorkspace(_Strict):
    """The open fluid container: the coil workspace's square walls."""

    kind: Literal["open"]


class PhantomWorkspace(_Strict):
    """A phantom whose boundaries are a polygon file (:mod:`magrun.phantom`); ``phantom`` and
    ``spine_phantom`` (the paper's) are the same kind."""

    kind: Literal["phantom", "spine_phantom"]
    phantom: str = Field(
        description="Phantom polygon file (YAML), relative to the protocol file's folder."
    )

    @field_validator("phantom")
    @classmethod
    def _load(cls, value: str, info: ValidationInfo) -> str:
        from magrun.phantom import load_phantom

        return _checked_file(value, info, load_phantom)


#: a trajectory's speed, mm/s: a robot slower than 1 µm/s would take days for a path; one
#: faster than 1 m/s leaves any coil system's workspace within a tick
Speed = Annotated[float, Field(ge=1e-3, le=1000)]
#: the longest time a trajectory may hold or a trial may last, s (a day)
MAX_TRIAL_S = 86_400.0


class SCurve(_Strict):
    """The paper's S-shaped path in a square (Section III-A), heading along the path."""

    kind: Literal["s_curve"]
    size_mm: Annotated[float, Field(gt=0, le=1000)] = 43.0
    speed_mm_s: Speed = 3.0


class OutAndBack(_Strict):
    """Along a path, hold, turn round in place, and back to the start (the spine experiment).

    The path is the phantom's ``path`` (``path: phantom``) or explicit points in mm.
    """

    kind: Literal["out_and_back"]
    path: Literal["phantom"] | Annotated[list[tuple[float, float]], Field(min_length=2)]
    speed_mm_s: Speed = 3.0
    hold_s: Annotated[float, Field(ge=0, le=MAX_TRIAL_S)] = Field(
        5.0, description="Station-keeping at the far end, s."
    )
    flip_s: Annotated[float, Field(gt=0, le=MAX_TRIAL_S)] = Field(
        3.0, description="Time to turn round (180°) in place, s."
    )

    @field_validator("path")
    @classmethod
    def _two_places(cls, path: Any) -> Any:
        """A path goes somewhere: at least 2 distinct points (a point repeated counts once)."""
        # the places scene.out_and_back keeps (mm here, m there)
        if isinstance(path, list) and np.count_nonzero(distinct_places(np.array(path) * 1e-3)) < 2:
            raise ValueError(
                f"a path needs at least 2 distinct points; these {len(path)} are one place"
            )
        return path


Workspace = Annotated[OpenWorkspace | PhantomWorkspace, Field(discriminator="kind")]
TrajectorySpec = Annotated[SCurve | OutAndBack, Field(discriminator="kind")]


# --------------------------------------------------------------------------------------------
# controller, feedback, recording, quick


class KalmanSettings(_Strict):
    """Kalman filter noise; ``measurement_sigma_mm: condition`` follows the trial's noise."""

    measurement_sigma_mm: Annotated[float, Field(gt=0, le=MAX_NOISE_MM)] | Literal["condition"] = (
        Field(
            "condition",
            description=(
                "Measurement noise assumed by the filter, mm; 'condition': the trial's "
                "noise_sigma_mm, floored at tracker_sigma_mm."
            ),
        )
    )
    tracker_sigma_mm: Annotated[float, Field(gt=0, le=MAX_NOISE_MM)] = Field(
        0.1, description="The camera tracker's own noise, mm (the floor of the above)."
    )
    measurement_sigma_deg: Annotated[float, Field(gt=0, le=MAX_NOISE_DEG)] = 3.0
    process_sigma_mm: Annotated[float, Field(gt=0, le=MAX_NOISE_MM)] | Literal["robot"] = Field(
        0.3,
        description=(
            "Process noise per control tick and axis, mm; 'robot': the robot's measured "
            "prediction error (robots.yaml prediction_sigma_mm)."
        ),
    )
    process_sigma_deg: Annotated[float, Field(gt=0, le=MAX_NOISE_DEG)] | Literal["robot"] = Field(
        2.0,
        description=(
            "Process noise of the heading per control tick, degrees; 'robot': robots.yaml "
            "prediction_sigma_deg."
        ),
    )
    heading_bias_sigma_deg: NoiseDeg = Field(
        0.0,
        description=(
            "The filter's heading bias (the model's heading drift per tick, learnt from the "
            "measured headings): its random walk per control tick, degrees; 0: no bias state."
        ),
    )
    mobility_sigma: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = Field(
        0.0,
        description=(
            "The filter's mobility scale (the robot's step over the model's, learnt from the "
            "measured positions): its random walk per control tick, at most 1; 0: no "
            "mobility state."
        ),
    )
    outlier_gate_sigma: Annotated[float, Field(ge=0, le=1000)] = Field(
        0.0,
        description=(
            "Reject a measurement whose pose lies more than this many standard deviations "
            "of its innovation from the filter's prediction (after 3 rejections in a row the "
            "next one is taken); 0: take every measurement."
        ),
    )
    strong_tracking: bool | Literal["auto"] = Field(
        "auto",
        description=(
            "Scale the filter's position variance up at a frame whose innovations are "
            "larger than it predicts (the strong tracking filter's fading factor; with the "
            "linearised filter only where they are ten times larger: a divergence guard); "
            "'auto': on with the linearised filter, and with the paper's where the coils "
            "cannot hold the reference's heading along the trajectory."
        ),
    )
    linearised: bool = Field(
        True,
        description=(
            "Propagate the filter's covariance through the model's Jacobian (an extended "
            "Kalman filter: P = F P F' + Q, F the one-tick prediction's derivative by the "
            "pose, under the currents applied); false: F = I, the paper's filter."
        ),
    )


#: the simulated rig's default latency per tick, ms: a camera tick's compute for the proposed
#: method (UNet tracking ~1.9 ms + Kalman filter and NMPC ~1.8 ms, medians of `magrun bench
#: tick` on a 2-core 2026 server), rounded up to leave room for a slower processor
DEFAULT_LATENCY_MS = 5.0


class ControllerSettings(_Strict):
    rate_hz: Annotated[float, Field(ge=MIN_CONTROL_RATE_HZ, le=MAX_RATE_HZ)] = Field(
        25.5, description="Control rate, Hz."
    )
    horizon: Annotated[int, Field(ge=1, le=100)] = Field(20, description="NMPC horizon, ticks.")
    step_damping: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] | Literal["auto"] = (
        Field(
            "auto",
            description=(
                "The NMPC's step damping (a Levenberg-Marquardt term on each real-time "
                "iteration's step, per (I/I_max)^2); 'auto': 1 where the coils cannot hold the "
                "reference's heading along the trajectory (the planner then follows headings "
                "they can), else 0."
            ),
        )
    )
    step_check: bool | Literal["auto"] = Field(
        "auto",
        description=(
            "Measure each NMPC step by the plan's objective: the first tick keeps only steps "
            "that lower it (raising the damping until one does), and a real-time step that "
            "more than doubles it is taken back; 'auto': on where the coils cannot hold the "
            "reference's heading along the trajectory (the planner then follows headings "
            "they can, lightly weighted), else off."
        ),
    )
    current_weight: AutoFactor = Field(
        "auto",
        description=(
            "A factor on the NMPC's current and current-change weights; 'auto': 1 on a "
            "system about as strong for the task as the paper's rig, (f/8.2)^2 where the "
            "coils give the reference's velocity f > 8.2 times over (median)."
        ),
    )
    angle_weight: AutoFactor = Field(
        "auto",
        description=(
            "A factor on the NMPC's heading-error weights; 'auto': 1 where the planner "
            "follows the reference's own headings, 0.01 where it follows headings the "
            "coils can hold (headings of the planner's choosing, not the task's)."
        ),
    )
    wrench_scale: AutoFactor = Field(
        "auto",
        description=(
            "A factor on the two-layer baselines' (2 to 4) wrench: the paper rig's force "
            "and torque limits and allocation references, set for its magnet robot; "
            "'auto': scaled by the robot's drags over the magnet robot's, the limits "
            "kept within what the coils typically give the robot."
        ),
    )
    position_uncertainty_mm: (
        Annotated[float, Field(ge=0, le=MAX_NOISE_MM, allow_inf_nan=False)] | Literal["auto"]
    ) = Field(
        "auto",
        description=(
            "The position error, mm, that the NMPC's heading-stable field withstands: the "
            "field along the moment is kept at least this times the field's gradient across "
            "the moment over tan(field_heading_error_deg); 'auto': twice the Kalman filter's "
            "steady position sigma before a frame where the coils cannot hold the reference's "
            "heading along the trajectory, else 0."
        ),
    )
    integral_time_s: (
        Annotated[float, Field(ge=0, le=MAX_INTEGRAL_TIME_S, allow_inf_nan=False)] | Literal["auto"]
    ) = Field(
        "auto",
        description=(
            "Integral action of the methods with a Kalman filter (proposed, baseline5): the "
            "reference's positions move by the integrated position error, with this time "
            "constant, s, where the estimate is certain, slower where it is not; 0: off. "
            "'auto': 0.1 s where the current weights are raised above the paper rig's and "
            "the coils hold the reference's own headings, else off (docs: Control)."
        ),
    )
    latency_ms: Annotated[float, Field(ge=0, le=MAX_LATENCY_MS)] | Literal["measured", "none"] = (
        Field(
            DEFAULT_LATENCY_MS,
            description=(
                "Simulated rig: the time between a tick's observation and its new currents, ms, "
                "during which the plant runs on the previous currents. A number is declared: the "
                "same protocol and seed give the same trial on any machine, under any load. "
                "'measured': the tick's wall-clock compute instead, and a tick that overruns the "
                "period stretches (timing studies; results then depend on the machine). 'none': 0. "
                "The measured compute time is recorded in every case, and ticks whose compute "
                "overran the control period are counted."
            ),
        )
    )
    plan_across_latency: bool = Field(
        False,
        description=(
            "Plan from the state predicted for when the tick's currents reach the coils, "
            "latency_ms after its observation (the previous currents act meanwhile), for a "
            "reference window that starts then. Off by default: on the simulated plants it "
            "did not reduce the tracking error (docs: Control)."
        ),
    )
    field_error_percent: Annotated[float, Field(ge=0, le=100)] = Field(
        0.0,
        description=(
            "The NMPC's trust in the coils' field model: each channel's field is taken as "
            "known to this percentage (1 sigma), and the field along the robot's moment is "
            "kept large enough that the field the model cannot vouch for turns the robot by "
            "at most field_heading_error_deg. 0: the model is trusted exactly (docs: Control)."
        ),
    )
    field_heading_error_deg: Annotated[float, Field(gt=0, lt=90)] = Field(
        20.0,
        description="The heading error, deg, that field_error_percent may cause (see there).",
    )
    heading_lead_mm: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = Field(
        0.0,
        description=(
            "In a phantom, mm: where the path bends away from the critical wall, the NMPC "
            "holds the heading the path has this far further on, so that a robot that far "
            "ahead of its estimate is not turned into that wall (about 1.5 sigma of the "
            "Kalman filter's position at the protocol's frame rate and noise). 0: the path's "
            "own headings (docs: Control)."
        ),
    )
    soft_constraints: Literal["slack", "penalty", "auto"] = Field(
        "auto",
        description=(
            "How the NMPC's real-time iteration keeps its soft constraints (the heading-stable "
            "field, a phantom's corridor): 'slack', as linearised inequalities with slacks in "
            "each tick's QP; 'penalty', as penalty residuals in the least-squares cost, which "
            "one step cannot see where they are not yet violated. The same optimum; 'slack' "
            "holds them tick by tick (docs: Control). 'auto': 'slack' where the coils cannot "
            "hold the reference's heading along the trajectory, else 'penalty'."
        ),
    )
    corrective_iterations: Annotated[int, Field(ge=0, le=50)] = Field(
        2,
        description=(
            "The NMPC's real-time iteration: extra iterations, at most, in a tick whose step "
            "left the field along the robot's moment short of the heading term's bound "
            "(docs: Control)."
        ),
    )
    corrective_step: Annotated[float, Field(gt=0, le=1)] = Field(
        1.0,
        description=(
            "The corrective iterations' step, as a fraction of the QP's (1: full "
            "Gauss-Newton steps; 0.5: half steps, which leave a cycle that full steps keep; "
            "docs: Control)."
        ),
    )
    charge_compute_time: bool | None = Field(
        None,
        description=(
            "Older name: true is latency_ms: measured, false is latency_ms: none. "
            "Give one of the two."
        ),
    )
    kalman: KalmanSettings = KalmanSettings()
    coil_gains: str | None = Field(
        None,
        description=(
            "A coil calibration file (what magrun identify --gains writes), relative to the "
            "protocol file's folder: the controllers' field models scale each channel by its "
            "gain. Default: none, the models as fitted."
        ),
    )

    @field_validator("latency_ms", mode="before")
    @classmethod
    def _latency_range(cls, value: Any) -> Any:
        # a number out of range is said so (the union would only name the words it takes)
        number = value
        if isinstance(value, str) and value not in ("measured", "none"):
            try:
                number = float(value)
            except ValueError:
                return value
        numeric = isinstance(number, int | float) and not isinstance(number, bool)
        if numeric and not 0 <= number <= MAX_LATENCY_MS:
            raise ValueError(
                f"{value} ms: a latency is from 0 to {MAX_LATENCY_MS:g} ms, or measured, or none"
            )
        return value

    @field_validator("coil_gains")
    @classmethod
    def _gains_file(cls, value: str | None, info: ValidationInfo) -> str | None:
        from magrun.calibration import load_coil_gains

        return None if value is None else _checked_file(value, info, load_coil_gains)

    @model_validator(mode="after")
    def _one_latency(self) -> ControllerSettings:
        if self.charge_compute_time is not None and "latency_ms" in self.model_fields_set:
            raise ValueError("give latency_ms or the older charge_compute_time, not both")
        return self

    @property
    def latency(self) -> float | Literal["measured"]:
        """The simulated rig's latency per tick: seconds, or ``"measured"``."""
        if self.charge_compute_time is not None:
            return "measured" if self.charge_compute_time else 0.0
        if self.latency_ms == "measured":
            return "measured"
        return 0.0 if self.latency_ms == "none" else self.latency_ms * 1e-3


class FeedbackSettings(_Strict):
    camera: bool = Field(
        True,
        description=(
            "Track rendered camera frames with the UNet (frames are recorded); false: the "
            "simulator's true pose feeds the fluoroscopy mimic, and no frames are recorded."
        ),
    )
    camera_frames: Literal["fluoroscopy", "every_tick"] = Field(
        "fluoroscopy",
        description=(
            "Simulated rig: at which ticks the camera takes (renders, tracks, records) a frame. "
            "'fluoroscopy': only when the fluoroscopy mimic takes one, the only frames the "
            "controller sees (the simulator's truth is the actual pose, which is what the real "
            "rig's high-rate camera is for). 'every_tick': at the control rate, as the real "
            "rig's camera, /robot/pose/tracked then at the control rate (slower)."
        ),
    )


class RecordingSettings(_Strict):
    image_every: Annotated[int, Field(ge=0)] = Field(
        1, description="Record every n-th camera frame (0: none)."
    )
    jpeg_quality: Annotated[int, Field(ge=10, le=100)] = 90
    image_format: Literal["jpeg", "raw"] = Field(
        "jpeg",
        description=(
            "MCAP camera frames as JPEG (foxglove.CompressedImage) or uncompressed "
            "(foxglove.RawImage, mono8/rgb8): raw keeps every pixel and sustains high frame rates."
        ),
    )
    rerun_image_every: Annotated[int, Field(ge=1)] = Field(
        1,
        description=(
            "Of the recorded frames, put every n-th in the .rrd too (raw frames at a high rate "
            "would swamp it; the MCAP keeps them all)."
        ),
    )
    compression: Literal["zstd", "lz4", "none"] = Field(
        "zstd", description="MCAP chunk compression (lz4: cheapest on CPU for raw frames)."
    )
    writer: Literal["auto", "thread", "process"] = Field(
        "auto",
        description=(
            "Where the recording is written: 'process' (a child process fed through shared "
            "memory: logging costs the control loop a copy, and the files are finished even "
            "if the loop's process is killed), 'thread' (a thread of the loop's process, "
            "whose Python work competes with the loop for the GIL: cheaper in CPU), or "
            "'auto': process on the hardware rig, thread in simulation (no clock to keep)."
        ),
    )


class SafetySettings(_Strict):
    """When a trial stops safely (magrun.safety): the currents ramp to zero at the slew
    limit, the trial ends, and the manifest and recording say why (status "stopped")."""

    lost_timeout_s: Annotated[float, Field(gt=0, le=MAX_TRIAL_S)] | None = Field(
        1.0,
        description=(
            "Stop when the camera tracker has lost the robot for longer than this, s "
            "(null: never; only with camera feedback)."
        ),
    )
    workspace_margin_mm: Annotated[float, Field(ge=0, le=1000)] | None = Field(
        5.0,
        description=(
            "Stop when the robot is further than this outside the workspace square, mm "
            "(null: never)."
        ),
    )
    stall_timeout_ms: Annotated[float, Field(gt=0, le=10_000)] = Field(
        100.0,
        description=(
            "Hardware rig: the driver ramps the currents to zero when no command arrived "
            "for this long, ms (at most 10 s, the rig protocol's longest watchdog)."
        ),
    )


def _bounded(upper: float, description: str) -> Any:
    """An optional non-negative setting up to ``upper`` (None: the preset's value)."""
    return Field(None, ge=0, le=upper, allow_inf_nan=False, description=description)


def _fraction(description: str) -> Any:
    """An optional fraction in [0, 1) (None: the preset's value)."""
    return Field(None, ge=0, lt=1, allow_inf_nan=False, description=description)


class PlantTerms(_Strict):
    """A real bench's imperfections (:mod:`magrun.rigs.plant`), unit-suffixed. In a plant file
    (and a preset) a key left out is off; in a protocol's ``simulation`` it is the plant's."""

    frame_age_ms: float | None = _bounded(
        2000, "Mean age of a camera or fluoroscopy frame: it shows the robot this long ago, ms."
    )
    frame_age_jitter_ms: float | None = _bounded(
        500, "σ of a frame's age about its mean, per frame (truncated at 0), ms."
    )
    amplifier_tau_ms: float | None = _bounded(
        1000,
        "Time constant of each amplifier's first-order current lag (on top of the slew limit), ms.",
    )
    coil_offset_mm: float | None = _bounded(
        20, "σ of each coil's in-plane placement error, per axis, mm (drawn per plant)."
    )
    coil_rotation_deg: float | None = _bounded(
        30, "σ of each coil's in-plane rotation error about its centre, degrees (per plant)."
    )
    residual_field_mt: float | None = _bounded(
        50,
        "RMS over the workspace of each coil's unmodelled smooth field at its current limit, mT.",
    )
    moment_misalignment_deg: float | None = _bounded(
        45, "σ of the magnetic moment's angle off the body axis, degrees (per plant)."
    )
    friction_mm_s: float | None = _bounded(
        100,
        "Kinetic Coulomb friction on the floor, as the drag speed it equals "
        "(force = drag_parallel × this), mm/s.",
    )
    stiction_mm_s: float | None = _bounded(
        100,
        "Static friction threshold, as a drag speed (below friction_mm_s: friction_mm_s), mm/s.",
    )
    rotational_friction_deg_s: float | None = _bounded(
        3600, "Kinetic friction torque, as the turning rate whose drag it equals, deg/s."
    )
    rotational_stiction_deg_s: float | None = _bounded(
        3600, "Static friction torque threshold, as a turning rate's drag, deg/s."
    )
    wall_friction: float | None = _bounded(
        2,
        "Kinetic Coulomb friction coefficient where the body touches a wall (its slide along "
        "the wall is slowed by this times the force pressing it in); dimensionless.",
    )
    wall_stiction: float | None = _bounded(
        2,
        "Static friction coefficient at the walls: the body sticks while the force along the "
        "wall is at most this times the force pressing it in; dimensionless.",
    )
    flow_sigma_mm_s: float | None = _bounded(
        100,
        "σ of the fluid's Ornstein–Uhlenbeck velocity, mm/s (along the channel in a phantom "
        "with a path, per axis in the open workspace).",
    )
    flow_time_s: float | None = Field(
        None, gt=0, le=3600, allow_inf_nan=False,
        description="Correlation time of the flow, s (default 1).",
    )  # fmt: skip
    tracker_sigma_mm: float | None = _bounded(
        20, "The camera pipeline's own white noise on each frame's position, per axis, mm."
    )
    tracker_sigma_deg: float | None = _bounded(
        90, "The camera pipeline's own white noise on each frame's heading, degrees."
    )
    outlier_rate: float | None = _fraction("Fraction of frames whose position is an outlier.")
    outlier_mm: float | None = _bounded(100, "σ of an outlier's displacement, per axis, mm.")
    drop_rate: float | None = _fraction("Fraction of frames dropped (nothing delivered).")

    exposure_ms: float | None = _bounded(
        200,
        "The camera's exposure, ms: a frame shows the robot blurred over the exposure that "
        "ends at the frame's time (the mean of 4 images along its path).",
    )
    glare_rate: float | None = _fraction(
        "Fraction of camera frames with a specular glint near the robot."
    )
    occlusion_rate: float | None = _fraction(
        "Fraction of camera frames with a bubble or debris over or near the robot."
    )

    def terms(self) -> dict[str, float]:
        """The settings given (not None), unit-suffixed as written."""
        return {k: v for k, v in self.model_dump().items() if k in PLANT_KEYS and v is not None}


#: the keys of a plant's imperfections (:class:`PlantTerms`)
PLANT_KEYS = tuple(PlantTerms.model_fields)

#: presets shipped with magrun (``magrun/data/plants/<name>.yaml``)
PLANT_PRESETS = ("ideal", "bench", "clinical")


class PlantFile(PlantTerms):
    """A plant file (``simulation.plant: FILE``; the presets are plant files too)."""

    description: str = ""


def plant_file_path(name: str) -> Path:
    """A preset's plant file."""
    from importlib import resources

    return Path(str(resources.files("magrun") / "data" / "plants" / f"{name}.yaml"))


def load_plant_file(path: str | Path) -> PlantFile:
    """Read and validate a plant file (raises :class:`~magrun.yamlio.YamlModelError`)."""
    return load_yaml_model(path, PlantFile)


#: a log-normal factor's σ: at 2 a factor is beyond e² (7.4×) one time in 20
Sigma = Annotated[float, Field(ge=0, le=2, allow_inf_nan=False)]


class SimulationSettings(PlantTerms):
    """The simulated rig's plant: how far each trial's robot and coils are from the models'
    nominal ones, and which real bench's imperfections it has.

    The robot and coil factors are log-normal, exp(N(0, σ²)), drawn per trial from its seed
    (or once, from ``plant_seed``); the draw is recorded (MCAP metadata record ``plant``).
    ``plant`` picks a preset (``ideal``: none of the imperfections; ``bench``: the paper's
    bench; ``clinical``: a C-arm) or a plant file; any imperfection given here overrides it."""

    plant: str = Field(
        "ideal",
        description=(
            "The plant's imperfections: ideal, bench, clinical, or a plant file (YAML, "
            "relative to the protocol file's folder); settings given here override it."
        ),
    )
    mass_sigma: Sigma = Field(0.1, description="σ of the mass (and inertia) factor.")
    drag_sigma: Sigma = Field(0.1, description="σ of the drag coefficients' factor.")
    moment_sigma: Sigma = Field(0.05, description="σ of the magnetic moment's factor.")
    coil_gain_sigma: Sigma = Field(
        0.02, description="σ of each coil's gain (field per ampere), one draw per coil."
    )
    plant_seed: Annotated[int, Field(ge=0, lt=2**63)] | None = Field(
        None,
        description=(
            "Draw the plant from this seed instead of each trial's: every trial then runs on "
            "the same robot and coils, as on one real rig (the feedback noise and camera still "
            "follow the trial's seed). Calibrate that rig with magrun identify."
        ),
    )

    @field_validator("plant")
    @classmethod
    def _plant(cls, value: str, info: ValidationInfo) -> str:
        if value in PLANT_PRESETS:
            return value
        return _checked_file(value, info, load_plant_file)

    def plant_terms(self) -> dict[str, float]:
        """Every imperfection, unit-suffixed: the preset's or plant file's, overridden by
        those given here; 0 where neither gives one (``flow_time_s``: 1)."""
        path = plant_file_path(self.plant) if self.plant in PLANT_PRESETS else Path(self.plant)
        merged = dict.fromkeys(PLANT_KEYS, 0.0) | {"flow_time_s": 1.0}
        merged |= load_plant_file(path).terms()
        return merged | self.terms()

    def imperfections(self) -> Imperfections:
        """:meth:`plant_terms` in SI, as the simulated rig takes them."""
        return imperfections_from_terms(self.plant_terms())


def imperfections_from_terms(t: dict[str, float]) -> Imperfections:
    """Unit-suffixed plant terms (:class:`PlantTerms`) as :class:`Imperfections` (SI)."""
    deg = math.radians
    return Imperfections(
        frame_age=t["frame_age_ms"] * 1e-3,
        frame_age_jitter=t["frame_age_jitter_ms"] * 1e-3,
        amplifier_tau=t["amplifier_tau_ms"] * 1e-3,
        coil_offset=t["coil_offset_mm"] * 1e-3,
        coil_rotation=deg(t["coil_rotation_deg"]),
        residual_field=t["residual_field_mt"] * 1e-3,
        moment_misalignment=deg(t["moment_misalignment_deg"]),
        friction=t["friction_mm_s"] * 1e-3,
        stiction=t["stiction_mm_s"] * 1e-3,
        rotational_friction=deg(t["rotational_friction_deg_s"]),
        rotational_stiction=deg(t["rotational_stiction_deg_s"]),
        wall_friction=t["wall_friction"],
        wall_stiction=t["wall_stiction"],
        flow_sigma=t["flow_sigma_mm_s"] * 1e-3,
        flow_time=t["flow_time_s"],
        tracker_position=t["tracker_sigma_mm"] * 1e-3,
        tracker_heading=deg(t["tracker_sigma_deg"]),
        outlier_rate=t["outlier_rate"],
        outlier_size=t["outlier_mm"] * 1e-3,
        drop_rate=t["drop_rate"],
        exposure=t["exposure_ms"] * 1e-3,
        glare_rate=t["glare_rate"],
        occlusion_rate=t["occlusion_rate"],
    )


class QuickSettings(_Strict):
    """What ``--quick`` runs: one trial of fewer conditions over a shorter time."""

    methods: Annotated[list[str], Field(min_length=1)] | None = None
    sweep: Sweep | None = None
    duration_s: PositiveFloat | None = Field(
        10.0, description="Trial length, s; null: the whole trajectory (as a full run)."
    )

    @field_validator("methods")
    @classmethod
    def _known(cls, methods: list[str] | None) -> list[str] | None:
        return None if methods is None else _check_methods(methods)


# --------------------------------------------------------------------------------------------
# the protocol


class Protocol(_Strict):
    """One experiment: every trial it runs follows from this and its seed."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", max_length=80)
    description: str = ""
    robots_file: str | None = Field(
        None,
        description=(
            "A robots file (robots.yaml's format, e.g. what magrun identify writes), relative "
            "to the protocol file's folder; default: magrun's robots.yaml."
        ),
    )
    robot: str = Field("magnet", description="A robot of the robots file.")
    system: str | None = Field(
        None,
        description=(
            "A coil-system folder (magrun field import-mpem writes one), relative to the "
            "protocol file's folder; default: the paper's rig."
        ),
    )
    workspace: Workspace = Field(default_factory=lambda: OpenWorkspace(kind="open"))
    trajectory: TrajectorySpec
    methods: Annotated[list[str], Field(min_length=1)]
    controller: ControllerSettings = ControllerSettings()
    sweep: Sweep = Sweep()
    conditions: Conditions = Conditions()
    trials: Annotated[int, Field(ge=1, le=1000)] = 3
    seed: Annotated[int, Field(ge=0, lt=2**63)] = 0
    feedback: FeedbackSettings = FeedbackSettings()
    recording: RecordingSettings = RecordingSettings()
    safety: SafetySettings = SafetySettings()
    simulation: SimulationSettings = SimulationSettings()
    duration_s: Annotated[float, Field(gt=0, le=MAX_TRIAL_S)] | None = Field(
        None, description="Trial length, s; default: the trajectory plus 1 s of hold."
    )
    quick: QuickSettings = QuickSettings()

    @field_validator("methods")
    @classmethod
    def _known_methods(cls, methods: list[str]) -> list[str]:
        return _check_methods(methods)

    @field_validator("robots_file")
    @classmethod
    def _robots_file(cls, value: str | None, info: ValidationInfo) -> str | None:
        from magrun.robot import load_robots

        return None if value is None else _checked_file(value, info, load_robots)

    @field_validator("system")
    @classmethod
    def _system_folder(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is None:
            return None
        path = _resolve(value, info)
        missing = [f for f in ("system.yaml", "reference_maps.npz") if not (path / f).is_file()]
        if missing:
            raise ValueError(
                f"{path}: not a coil-system folder (no {' or '.join(missing)}; "
                "magrun field import-mpem writes one)"
            )
        return str(path)

    @field_validator("robot")
    @classmethod
    def _known_robot(cls, robot: str, info: ValidationInfo) -> str:
        from magrun.robot import load_robots

        robots_file = info.data.get("robots_file")
        names = sorted(load_robots(robots_file))
        if robot not in names:
            where = robots_file or "robots.yaml"
            raise ValueError(f"unknown robot {robot!r}; {where} has {', '.join(names)}")
        return robot

    # fields are validated in order; these checks see the fields declared above them

    @field_validator("trajectory")
    @classmethod
    def _path_needs_phantom(cls, traj: SCurve | OutAndBack, info: ValidationInfo) -> Any:
        ws = info.data.get("workspace")
        phantom_path = isinstance(traj, OutAndBack) and traj.path == "phantom"
        if phantom_path and ws is not None and ws.kind == "open":
            raise ValueError("path 'phantom' needs a phantom workspace")
        return traj

    @field_validator("sweep")
    @classmethod
    def _sweep_rates(cls, sweep: Sweep, info: ValidationInfo) -> Sweep:
        _check_rates(sweep.tracking_rate_hz or [], info)
        return sweep

    @field_validator("conditions")
    @classmethod
    def _fixed(cls, conditions: Conditions, info: ValidationInfo) -> Conditions:
        sweep = info.data.get("sweep")
        both = conditions.model_fields_set & {k for k, _ in sweep.items()} if sweep else set()
        if both:
            raise ValueError(f"{', '.join(sorted(both))}: both swept and fixed; choose one")
        if conditions.tracking_rate_hz is not None:
            _check_rates([conditions.tracking_rate_hz], info)
        return conditions

    @model_validator(mode="after")
    def _robot_has_measured_noise(self) -> Protocol:
        k = self.controller.kalman
        if "robot" in (k.process_sigma_mm, k.process_sigma_deg):
            from magrun.robot import load_robots

            robot = load_robots(self.robots_file).get(self.robot)
            if robot is not None and robot.prediction_sigma is None:
                raise ValueError(
                    "controller.kalman.process_sigma_*: 'robot', but robot "
                    f"{self.robot!r} has no prediction_sigma_mm / prediction_sigma_deg "
                    "in robots.yaml; give the numbers instead"
                )
        return self

    @model_validator(mode="after")
    def _not_too_many_trials(self) -> Protocol:
        n = self.n_trials()
        if n > MAX_TRIALS:
            sizes = " × ".join(str(len(v)) for _, v in self.sweep.items()) or "1"
            raise ValueError(
                f"{n:,} trials (sweep {sizes} conditions × {len(self.methods)} methods × "
                f"{self.trials} trials): more than the {MAX_TRIALS:,} one protocol may run; "
                "split it into several protocol files"
            )
        return self

    def robot_params(self) -> RobotParams:
        """The protocol's robot, from its robots file."""
        from magrun.robot import load_robot

        return load_robot(self.robot, self.robots_file)

    # ---- expansion ---------------------------------------------------------------------

    def n_trials(self, quick: bool = False) -> int:
        """How many trials :meth:`expand` gives, without building them."""
        if quick:
            return len(self.expand(quick=True))
        return math.prod(len(v) for _, v in self.sweep.items()) * len(self.methods) * self.trials

    def expand(self, quick: bool = False, seed: int | None = None) -> list[Trial]:
        """Every trial, in a fixed order: condition, then method, then repeat."""
        methods = (self.quick.methods or self.methods) if quick else self.methods
        sweep = self.sweep
        if quick:
            sweep = self.quick.sweep or Sweep(
                **{k: sorted({v[0], v[-1]}) for k, v in self.sweep.items()}
            )
        items = sweep.items()
        names = [k for k, _ in items]
        base = self.conditions.model_dump()
        repeats = 1 if quick else self.trials
        root = self.seed if seed is None else seed
        trials = []
        for c_index, values in enumerate(itertools.product(*(v for _, v in items))):
            condition = Conditions(**{**base, **dict(zip(names, values, strict=True))})
            for method in methods:
                slug = condition_slug(method, dict(zip(names, values, strict=True)))
                for k in range(repeats):
                    trial_seed = int(
                        np.random.SeedSequence([root, c_index, k]).generate_state(1)[0]
                    )
                    trials.append(
                        Trial(
                            protocol=self,
                            method=method,
                            condition=condition,
                            swept=tuple(names),
                            index=k,
                            seed=trial_seed,
                            slug=slug,
                            quick=quick,
                        )
                    )
        return trials

    def trial_duration(self, quick: bool = False) -> float | None:
        """Seconds per trial, or None for the trajectory's own length plus 1 s."""
        if quick and self.quick.duration_s is not None:
            return min(self.quick.duration_s, self.duration_s or math.inf)
        return self.duration_s


class Trial(BaseModel):
    """One run: a method under one condition, repeat ``index``, with its own ``seed``."""

    model_config = ConfigDict(frozen=True)

    protocol: Protocol
    method: str
    condition: Conditions
    swept: tuple[str, ...]
    index: int
    seed: int
    slug: str
    quick: bool = False

    @property
    def relpath(self) -> str:
        """``<protocol>/<condition slug>/trial-<k>`` (add ``.mcap`` / ``.rrd``)."""
        return f"{self.protocol.name}/{self.slug}/trial-{self.index}"

    def describe(self) -> dict[str, Any]:
        """Protocol, method, every condition value, seed, index: the recording's metadata."""
        return {
            "protocol": self.protocol.name,
            "method": self.method,
            **self.condition.model_dump(),
            "trial": self.index,
            "seed": self.seed,
            "quick": self.quick,
        }


def condition_slug(method: str, swept: dict[str, float | None]) -> str:
    """``proposed_rate-3hz_sigma-2mm``: the method and the swept values, filesystem-safe."""
    parts = [method]
    for key, value in swept.items():
        prefix, unit = CONDITION_SLUGS[key]
        parts.append(f"{prefix}-{_number(value)}{unit}")
    return "_".join(parts)


def _number(value: float | None) -> str:
    if value is None:
        return "none"
    return f"{value:g}"


def _check_rates(rates: list[float], info: ValidationInfo) -> None:
    controller = info.data.get("controller")
    limit = controller.rate_hz if controller is not None else math.inf
    fast = [r for r in rates if r > limit * (1 + 1e-9)]
    if fast:
        raise ValueError(
            f"tracking rate {fast[0]:g} Hz is above the control rate {limit:g} Hz "
            "(controller.rate_hz); feedback cannot arrive faster than the loop runs"
        )


def _check_methods(methods: list[str]) -> list[str]:
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r}; choose from {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise ValueError("methods must be distinct")
    return methods


def _resolve(value: str, info: ValidationInfo) -> Path:
    base = (info.context or {}).get("base_dir")
    path = Path(value)
    return path if path.is_absolute() or base is None else Path(base) / path


def _checked_file(value: str, info: ValidationInfo, load: Callable[[Path], object]) -> str:
    """A file setting resolved against the protocol's folder and loaded once, so that a
    bad file fails validation (``load``'s own errors name the file and line)."""
    path = _resolve(value, info)
    load(path)
    return str(path)


def load_protocol(path: str | Path, overrides: Sequence[str] = ()) -> Protocol:
    """Read and validate a protocol file (raises :class:`~magrun.yamlio.YamlModelError`).

    ``overrides``: ``KEY=VALUE`` settings with dotted keys (``controller.rate_hz=20``),
    applied to the file before it is validated (``magrun run --set``).
    """
    return load_yaml_model(
        path, Protocol, context={"base_dir": str(Path(path).parent)}, overrides=overrides
    )


def protocol_from_json(text: str, source: str, overrides: Sequence[str] = ()) -> Protocol:
    """A recorded protocol (the MCAP ``protocol`` record's JSON) with ``overrides`` applied,
    validated again; ``source`` names it in errors."""
    data = safe_json(text, source)
    if isinstance(data, dict) and isinstance(data.get("conditions"), dict):
        # a dump lists every condition, the swept ones too (as their default): as written,
        # a swept quantity is not also fixed
        swept = {k for k, v in (data.get("sweep") or {}).items() if v is not None}
        data["conditions"] = {k: v for k, v in data["conditions"].items() if k not in swept}
    return validate_data(data, Protocol, source, overrides=overrides)


def json_schema() -> str:
    """The protocol JSON Schema (for editors' completion and checking), as text."""
    schema = Protocol.model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "magrun protocol"
    return json.dumps(schema, indent=2) + "\n"
