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
from typing import Self

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


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
    """A coil rig: drives currents, reports the robot's pose."""

    #: channel names in current-vector order
    channel_names: tuple[str, ...]
    max_current: float | FloatArray  # A: one for every channel, or one per channel
    max_slew_rate: float | FloatArray  # A/s
    #: s from the last observation to the rig's acknowledgement of the currents applied after
    #: it (a hardware rig measures it; NaN in simulation)
    last_latency: float = float("nan")

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
