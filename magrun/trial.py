"""What a trial's parts are built from, shared by every entry point (``magrun run``, ``magrun
track``, the benchmarks), so that one condition always gets one controller tuning.

:func:`control_config` turns a protocol's ``controller`` section, the robot and the trial's
condition into the methods' :class:`~magrun.control.methods.ControlConfig`: the control
period, the horizons and the Kalman filter's noise (the measurement noise follows the
condition's ``noise_sigma_mm`` unless the protocol fixes it; the process noise is the robot's
measured prediction error where the protocol says ``robot``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from magrun.control.estimation import KalmanConfig
from magrun.control.methods import ControlConfig
from magrun.control.nmpc import NMPCConfig
from magrun.control.two_layer import LinearMPCConfig
from magrun.protocol import ControllerSettings
from magrun.robot import load_robot


def control_config(
    settings: ControllerSettings, robot: str, condition: Mapping[str, float | None]
) -> ControlConfig:
    """The controller tuning for ``robot`` under ``condition`` (``noise_sigma_mm``,
    ``noise_sigma_deg``: the feedback's noise, mm and degrees; missing or None: none)."""
    k = settings.kalman
    if k.measurement_sigma_mm == "condition":
        sigma_mm = max(float(condition.get("noise_sigma_mm") or 0.0), k.tracker_sigma_mm)
    else:
        sigma_mm = k.measurement_sigma_mm
    sigma_deg = max(k.measurement_sigma_deg, float(condition.get("noise_sigma_deg") or 0.0))
    measured = load_robot(robot).prediction_sigma  # a protocol checks it exists where it asks
    process_m = (
        measured[0] if measured and k.process_sigma_mm == "robot"
        else float(k.process_sigma_mm) * 1e-3
    )  # fmt: skip
    process_rad = (
        measured[1] if measured and k.process_sigma_deg == "robot"
        else math.radians(float(k.process_sigma_deg))
    )  # fmt: skip
    return ControlConfig(
        dt=1.0 / settings.rate_hz,
        nmpc=NMPCConfig(horizon=settings.horizon),
        linear_mpc=LinearMPCConfig(horizon=settings.horizon),
        kalman=KalmanConfig(
            measurement_position=sigma_mm * 1e-3,
            measurement_angle=math.radians(sigma_deg),
            process_position=process_m,
            process_angle=process_rad,
        ),
    )
