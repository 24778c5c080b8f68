"""The :class:`Rig` interface shared by the simulated plant and the real coil rig.

A rig has a lifecycle (``connect`` / ``disconnect``, or a ``with`` block) and a tick API the
runner drives at the control period::

    with SimRig(...) as rig:
        rig.reset(start_pose)
        for k in range(n_ticks):
            obs = rig.observe()                   # time, actual pose, camera frame
            applied = rig.apply(currents)         # what the amplifiers will actually drive
            rig.advance(dt)                       # simulate (or wait) one control period

``apply`` is the safety layer every rig shares: non-finite requests become zero, then
:func:`magrun.safety.clamp_currents` enforces the per-coil current limit and the slew limit,
and the rig returns the currents it will really drive (as lerobot's ``send_action`` does).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from types import TracebackType
from typing import TYPE_CHECKING, Literal, Protocol, Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from magrun.robot import RobotParams
    from magrun.tracking.camera import Camera

FloatArray = NDArray[np.float64]


class PoseTracker(Protocol):
    """What the loop needs of a camera tracker (:class:`magrun.tracking.tracker.Tracker`)."""

    def reset(self) -> None: ...

    def __call__(self, frame: NDArray[np.uint8]) -> FloatArray | None: ...


@dataclass(frozen=True)
class Observation:
    """What the rig reports at one tick.

    Attributes
    ----------
    t : float
        Rig time, s, from the trial start.
    pose : ndarray, shape (3,)
        The actual pose ``(x, y, θ)``, m and rad: simulator truth, or high-rate camera tracking
        on the hardware rig.
    in_contact : bool
        Whether the robot touched a wall since the previous observation (simulation only).
    frame : ndarray, shape (H, W, 3), uint8, or None
        The camera frame (RGB), when the rig has a camera: taken at ``frame_time``.
    camera_pose : ndarray, shape (3,), or None
        What the camera pipeline reports, where it differs from ``pose`` (a simulated bench:
        the pose at ``frame_time``, with the tracking errors where no frame is rendered; NaN:
        a dropped frame). None: ``pose`` is what the camera reports.
    frame_time : float or None
        Rig time, s, at which the camera saw the robot (``t`` less the frame's age); None:
        ``t``.
    """

    t: float
    pose: FloatArray
    in_contact: bool = False
    frame: NDArray[np.uint8] | None = None
    camera_pose: FloatArray | None = None
    frame_time: float | None = None


class Rig(ABC):
    """A coil rig: drives currents, reports the robot's pose.

    What the assembly, the loop and the runner read of a rig is declared here; a simulated
    rig adds its plant (:class:`~magrun.rigs.sim.SimRig`), a real one its link's statistics.
    """

    #: channel names in current-vector order
    channel_names: tuple[str, ...]
    max_current: float | FloatArray  # A: one for every channel, or one per channel
    max_slew_rate: float | FloatArray  # A/s
    #: s from the last observation to the rig's acknowledgement of the currents applied after
    #: it (a hardware rig measures it; NaN in simulation)
    last_latency: float = float("nan")
    #: the robot as magrun knows it (robots.yaml): what the controller and the tracker assume
    nominal_robot: RobotParams
    #: the camera whose frames :meth:`observe` returns, with its calibration; None: no frames
    camera: Camera | None = None
    #: whether the plant is simulated: the loop then emulates the declared compute latency
    #: (:meth:`emulated_latency`) and the recording holds the plant (:meth:`plant_record`)
    simulated: bool = False

    def emulated_latency(
        self, declared: float | Literal["measured"]
    ) -> float | Literal["measured"]:
        """The compute latency the loop emulates (:func:`magrun.loop.run_trial`): a simulated
        rig's, the protocol's ``declared`` one; a real rig has its own, so 0."""
        return declared if self.simulated else 0.0

    def frame_tracker(self) -> PoseTracker | None:
        """The tracker the loop runs on this rig's camera frames; None where the rig reports
        tracked poses itself (a real rig tracks its camera in :meth:`observe`) or has no
        camera."""
        return None

    def plant_record(self) -> dict[str, str]:
        """The recording's ``plant`` record (values JSON): a simulated plant's draws; a real
        rig has none to give."""
        return {}

    def report(self) -> dict[str, float | int]:
        """The rig's statistics for the manifest (a real rig: its link's latency, overruns,
        dropped frames); none in simulation."""
        return {}

    def connect(self) -> None:  # noqa: B027 - optional hook, a no-op in simulation
        """Acquire the hardware (no-op in simulation)."""

    def disconnect(self) -> None:  # noqa: B027 - optional hook, a no-op in simulation
        """Drive zero currents and release the hardware (no-op in simulation)."""

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.disconnect()

    @abstractmethod
    def reset(self, pose: ArrayLike) -> None:
        """Start a trial with the robot at rest at ``pose`` (x, y, θ) and all currents at 0 A."""

    @abstractmethod
    def observe(self, frame: bool = True) -> Observation:
        """The rig's time and the robot's actual pose now, with a camera frame if it has a
        camera and ``frame`` is true (a simulated camera then renders only frames asked for)."""

    @abstractmethod
    def apply(self, currents: ArrayLike) -> FloatArray:
        """Command currents (A, one per channel); returns those that will be driven."""

    @abstractmethod
    def advance(self, duration: float) -> None:
        """Let ``duration`` seconds pass with the applied currents (simulate, or wait)."""
