"""The records a trial produces, shared by the loop that makes them and the recorder that
writes them: small dataclasses, NumPy only (no control, rig or solver imports), so the
recorder's writer process stays light.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
    """

    solve_time: float
    iterations: int = 0
    success: bool = True
    fallback: str = ""
    message: str = ""


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
