"""The records a trial produces, shared by the loop that makes them and the recorder that
writes them: small dataclasses, NumPy only (no control, rig or solver imports), so the
recorder's writer process stays light. Also what a recording needs besides its ticks
(:class:`RecordingSetup`) and the pose streams it records.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ControllerStatus:
    """How one tick's plan was obtained.

    Attributes
    ----------
    solve_time : float
        Wall time of the planner, s.
    iterations : int
        Solver iterations (0 for closed-form planners).
    success : bool
        Whether the solver converged (always true for closed-form planners).
    fallback : str
        ``""`` when the plan was used, else what replaced it: ``"shifted"`` (the previous
        plan's next currents) or ``"zero"``.
    message : str
        The solver's return status.
    prepare_time : float
        Wall time, s, of the planner's preparation for this tick, done before the tick's
        measurement (:meth:`Planner.prepare`; 0 where there was none). ``solve_time`` is then
        the feedback phase alone: the planner's share of the delay from measurement to
        currents.
    """

    solve_time: float
    iterations: int = 0
    success: bool = True
    fallback: str = ""
    message: str = ""
    prepare_time: float = 0.0


@dataclass(frozen=True)
class Tick:
    """Everything one control tick saw and did (SI units), as handed to ``on_tick``."""

    k: int
    t: float  # s from the trial start
    actual: FloatArray  # (3,)
    tracked: FloatArray | None  # camera pose, None when no tracker or the tracker lost it
    measured: FloatArray | None  # the feedback, None when no fluoroscopy frame arrived
    estimated: FloatArray
    predicted: FloatArray | None  # the previous tick's prediction of this tick
    desired: FloatArray
    currents: FloatArray  # as applied, A
    status: ControllerStatus
    compute_time: float  # s: tracking + feedback + controller, wall clock
    frame: NDArray[np.uint8] | None = None
    latency: float = math.nan  # s, the tick's frame to the rig's ack (hardware rigs)
    safety_stop: str = ""  # the safety layer's reason, once it has tripped
    measured_age: float = 0.0  # s: how long before ``t`` the measurement's frame was taken


#: the recorded pose streams, each an MCAP topic ``/robot/pose/<stream>``
POSE_STREAMS = ("actual", "tracked", "measured", "estimated", "predicted", "desired")


def yaw_of(qz: float, qw: float) -> float:
    """θ of a yaw quaternion (z, w components), in (−π, π]."""
    return math.atan2(2 * qw * qz, 1 - 2 * qz * qz)


def pose_of(msg: Any) -> FloatArray:
    """(x, y, θ) of a decoded ``foxglove.PoseInFrame`` as the recorder writes it."""
    p, q = msg.pose.position, msg.pose.orientation
    return np.array([p.x, p.y, yaw_of(q.z, q.w)])


def metadata_text(value: Any) -> str:
    """A metadata value as MCAP stores it: strings as they are, the rest as JSON."""
    return value if isinstance(value, str) else json.dumps(value)


def metadata_value(text: str) -> Any:
    """The inverse of :func:`metadata_text` (text that is not JSON, or nested too deeply to
    decode, stays text)."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError):
        return text


@dataclass
class RecordingSetup:
    """Static facts a recording needs besides its ticks."""

    trial: dict[str, Any]  # the ``trial`` metadata (JSON-able values)
    channel_names: tuple[str, ...]
    protocol_json: str = "{}"
    boundaries: dict[str, FloatArray] = field(default_factory=dict)  # name -> (n, 2), m
    workspace_half_width: float | None = None  # m, the square the robot may use
    reference: FloatArray | None = None  # (n, 3) the desired path, for the views
    camera: Any = None  # magrun.tracking.camera.Camera, for the pixel overlay
    image_every: int = 1  # record every n-th camera frame (0: none)
    jpeg_quality: int = 90
    recording_id: str = ""
    name: str = ""  # the recording's name in the viewer ("": from the trial metadata)
    image_format: str = "jpeg"  # or "raw": foxglove.RawImage, every pixel
    rerun_image_every: int = 1  # of the recorded frames, every n-th also into the .rrd
    compression: str = "zstd"  # MCAP chunk compression: zstd, lz4 or none
    extra_metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # more records
    live_view: str = ""  # a Rerun viewer's gRPC URL to stream to as well ("": none)
