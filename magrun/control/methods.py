"""The six control methods of the paper, built by name behind one :class:`Controller` interface.

===========  ============================  =====================  ===========================
method       planner                       field model            estimator
===========  ============================  =====================  ===========================
proposed     NMPC on currents              Zernike                Kalman filter
baseline1    NMPC on currents              Zernike                measurement, else prediction
baseline2    PID → force/torque → alloc.   lookup table           last measurement (held)
baseline3    linear MPC → alloc.           lookup table           measurement, else prediction
baseline4    linear MPC → alloc.           Zernike                measurement, else prediction
baseline5    NMPC on currents              lookup table           Kalman filter
===========  ============================  =====================  ===========================

    >>> from magrun.control.methods import make_controller
    >>> controller = make_controller("proposed", robot="magnet")   # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from numpy.typing import ArrayLike

from magrun.control import METHODS, NMPC_METHODS
from magrun.control.allocation import AllocationConfig
from magrun.control.base import Controller, Estimator, Planner
from magrun.control.estimation import (
    HoldLastMeasurement,
    KalmanConfig,
    KalmanPoseFilter,
    MeasurementOrPrediction,
)
from magrun.control.nmpc import NMPC, NMPCConfig
from magrun.control.two_layer import LinearMPCConfig, LinearMPCPlanner, PIDConfig, PIDPlanner
from magrun.field.model import CalibratedFieldModel, PlanarFieldModel
from magrun.field.system import shipped_models
from magrun.freespace import FreeSpace
from magrun.robot import RobotParams, load_robot


@dataclass(frozen=True)
class ControlConfig:
    """Every tunable of every method; defaults are the documented ones."""

    dt: float = 0.04
    nmpc: NMPCConfig = field(default_factory=NMPCConfig)
    kalman: KalmanConfig = field(default_factory=KalmanConfig)
    pid: PIDConfig = field(default_factory=PIDConfig)
    linear_mpc: LinearMPCConfig = field(default_factory=LinearMPCConfig)
    allocation: AllocationConfig = field(default_factory=AllocationConfig)
    #: expected time, s, from a tick's observation to its currents reaching the coils: the
    #: controller plans across it (:class:`~magrun.control.base.Controller`)
    latency: float = 0.0
    #: s: the integral action's time constant (:class:`~magrun.control.base.Controller`), for
    #: the methods with a Kalman filter (it slows down with the filter's uncertainty); 0: off
    integral_time: float = 0.0


def make_controller(
    method: str,
    robot: RobotParams | str = "magnet",
    config: ControlConfig | None = None,
    zernike: PlanarFieldModel | None = None,
    lut: PlanarFieldModel | None = None,
    free_space: FreeSpace | None = None,
    coil_gains: ArrayLike | None = None,
) -> Controller:
    """Build one of :data:`METHODS` for ``robot`` (default models: the shipped ones).

    ``coil_gains``: each channel's field per ampere relative to the models (a coil
    calibration, :mod:`magrun.calibration`); both models are scaled by them. Default: none.

    ``free_space``: the workspace or phantom the robot moves in; every method's estimate is
    kept inside it, and the NMPC methods plan with its corridor. Default: the coil
    workspace's square.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    cfg = config or ControlConfig()
    params = load_robot(robot) if isinstance(robot, str) else robot
    if zernike is None or lut is None:
        z0, l0 = shipped_models()
        zernike, lut = zernike or z0, lut or l0
    if coil_gains is not None:
        zernike = CalibratedFieldModel(zernike, coil_gains)
        lut = CalibratedFieldModel(lut, coil_gains)
    nmpc_cfg = replace(cfg.nmpc, dt=cfg.dt)
    if free_space is None:
        free_space = FreeSpace.square(
            zernike.coils.workspace_half_width, params.length, params.diameter
        )
    planner: Planner
    estimator: Estimator
    if method in NMPC_METHODS:
        model = lut if method == "baseline5" else zernike
        planner = NMPC(model, params, nmpc_cfg, free_space)
        estimator = (
            MeasurementOrPrediction() if method == "baseline1" else KalmanPoseFilter(cfg.kalman)
        )
    elif method == "baseline2":
        planner = PIDPlanner(lut, params, cfg.dt, cfg.pid, cfg.allocation)
        estimator = HoldLastMeasurement()
    else:
        model = lut if method == "baseline3" else zernike
        planner = LinearMPCPlanner(model, params, cfg.dt, cfg.linear_mpc, cfg.allocation)
        estimator = MeasurementOrPrediction()
    coils = zernike.coils
    filtered = isinstance(estimator, KalmanPoseFilter)
    return Controller(
        method, estimator, planner, cfg.dt, coils.max_current, coils.max_slew_rate,
        coils.n_channels, free_space,
        velocity="model" if filtered else "difference", latency=cfg.latency,
        integral_time=cfg.integral_time if filtered else 0.0,
    )  # fmt: skip
