"""Two-layer baselines (paper, Section II-E): pose controller → force/torque → allocation.

- :class:`PIDPlanner` (Baseline 2): a PID on position and on orientation, with the reference
  velocity as feed-forward, scaled by the drag model (F = D(θ) v_cmd, τ = d_r ω_cmd), so the
  gains read as bandwidths in 1/s. The integrator only accumulates small errors (conditional
  integration) and is clamped: a drag-dominated robot integrates velocity already, and
  integrating a step's large initial error winds up into a slow overshoot.
- :class:`LinearMPCPlanner` (Baselines 3 and 4): an MPC on the rigid-body model linearised
  at the current heading (drag matrix D(θ₀) frozen over the horizon, exact zero-order-hold
  discretisation), inputs the force and torque within box limits. Its quadratic programme
  with box constraints is solved exactly as a bounded least-squares problem (condensed:
  the states are eliminated) by :class:`magrun.control.qp.BoxLeastSquares` (DAQP; scipy's
  BVLS is the reference; their times: BENCHMARKS.md).

Both hand the first wrench to :func:`magrun.control.allocation.allocate` with their field model
(lookup tables for B2 and B3, Zernike for B4). The predicted pose for the next tick is the
linear model driven by the wrench the allocated currents actually produce (per the
allocation's model); the PID makes no prediction (NaN), as it uses none.
"""

from __future__ import annotations

import math
import time
from abc import abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magrun.angles import angle_near, wrap_angle
from magrun.control.allocation import (
    AllocationConfig,
    allocate,
    background_wrench,
    wrench_matrix,
)
from magrun.control.base import Plan, Planner
from magrun.control.qp import BoxLeastSquares
from magrun.field.model import PlanarFieldModel
from magrun.records import ControllerStatus
from magrun.robot import RobotParams, drag_matrix

FloatArray = NDArray[np.float64]


def linear_model(robot: RobotParams, theta: float, dt: float) -> tuple[FloatArray, FloatArray]:
    """Exact ZOH discretisation ``(Ad (6, 6), Bd (6, 3))`` of the dynamics at heading θ.

    State ``[x, y, θ, vx, vy, ω]`` and input ``[Fx, Fy, τ]``, SI. In the body axes (along
    and across the moment) the drag is diagonal, so each axis is the scalar system
    ``ṗ = v, v̇ = −a v + f/m`` with ``a = d/m``, whose exact step is closed form
    (``e = exp(−a Δt)``)::

        p⁺ = p + v (1 − e)/a + f (Δt − (1 − e)/a)/(a m)       v⁺ = e v + f (1 − e)/(a m)

    rotated back to the workspace frame; the rotation is the same with ``a = d_r/J``.
    :func:`linear_model_expm` (the matrix exponential of the continuous system) is the
    reference it is tested against.
    """
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s], [s, c]])

    def axis(drag: float, mass: float) -> tuple[float, float, float, float]:
        a = drag / mass
        e = math.exp(-a * dt)
        g = -math.expm1(-a * dt) / a  # (1 − e)/a without cancellation
        return g, e, (dt - g) / drag, g / mass

    par = axis(robot.drag_parallel, robot.mass)
    perp = axis(robot.drag_perpendicular, robot.mass)
    rot = axis(robot.drag_rotation, robot.inertia)

    def rotated(i: int) -> FloatArray:
        out: FloatArray = (R * np.array([par[i], perp[i]])) @ R.T
        return out

    Ad = np.eye(6)
    Ad[0:2, 3:5], Ad[3:5, 3:5] = rotated(0), rotated(1)
    Ad[2, 5], Ad[5, 5] = rot[0], rot[1]
    Bd = np.zeros((6, 3))
    Bd[0:2, 0:2], Bd[3:5, 0:2] = rotated(2), rotated(3)
    Bd[2, 2], Bd[5, 2] = rot[2], rot[3]
    return Ad, Bd


def linear_model_expm(robot: RobotParams, theta: float, dt: float) -> tuple[FloatArray, FloatArray]:
    """:func:`linear_model` by the matrix exponential of the continuous system (reference)."""
    Ac = np.zeros((6, 6))
    Ac[0:3, 3:6] = np.eye(3)
    Ac[3:5, 3:5] = -drag_matrix(robot, theta) / robot.mass
    Ac[5, 5] = -robot.drag_rotation / robot.inertia
    Bc = np.zeros((6, 3))
    Bc[3:5, 0:2] = np.eye(2) / robot.mass
    Bc[5, 2] = 1 / robot.inertia
    aug = np.zeros((9, 9))
    aug[:6, :6], aug[:6, 6:] = Ac * dt, Bc * dt
    from scipy.linalg import expm  # the reference only: scipy.linalg when it is asked for

    E = expm(aug)
    return E[:6, :6], E[:6, 6:]


class TwoLayerPlanner(Planner):
    """Shared part of the two-layer planners: allocation, limits, prediction."""

    def __init__(
        self,
        field_model: PlanarFieldModel,
        robot: RobotParams,
        dt: float = 0.04,
        allocation: AllocationConfig | None = None,
    ) -> None:
        self.model = field_model
        self.robot = robot
        self.dt = dt
        self.allocation = allocation or AllocationConfig()
        coils = field_model.coils
        self.max_current = coils.max_current
        self.max_change = coils.max_slew_rate * dt

    @abstractmethod
    def desired_wrench(self, state: FloatArray, reference: FloatArray) -> FloatArray:
        """The high layer: force (N) and torque (N m) wanted at this tick, shape (3,)."""

    def plan(self, state: FloatArray, reference: FloatArray, previous: FloatArray) -> Plan:
        t0 = time.perf_counter()
        wrench = self.desired_wrench(state, reference)
        lower = np.maximum(-self.max_current, previous - self.max_change)
        upper = np.minimum(self.max_current, previous + self.max_change)
        currents, achieved = allocate(
            self.model,
            state[:2],
            float(state[2]),
            self.robot.moment,
            wrench,
            lower,
            upper,
            self.allocation,
            self.max_current,
        )
        predicted = self._predict_with_wrench(state, achieved)
        return Plan(currents, predicted, ControllerStatus(time.perf_counter() - t0))

    def predict(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        A, _ = wrench_matrix(self.model, state[:2], float(state[2]), self.robot.moment)
        w0, _ = background_wrench(self.model, state[:2], float(state[2]), self.robot.moment)
        return self._predict_with_wrench(state, A @ currents + w0)

    def _predict_with_wrench(self, state: FloatArray, wrench: FloatArray) -> FloatArray:
        Ad, Bd = linear_model(self.robot, float(state[2]), self.dt)
        return Ad @ state + Bd @ wrench


@dataclass(frozen=True)
class PIDConfig:
    """PID gains as bandwidths (1/s, 1/s², s) on position and orientation."""

    kp_position: float = 6.0
    ki_position: float = 1.0
    kd_position: float = 0.0
    kp_angle: float = 6.0
    ki_angle: float = 1.0
    kd_angle: float = 0.0
    integral_limit_position: float = 0.5e-3  # m s
    integral_limit_angle: float = 0.05  # rad s
    # conditional integration (anti-windup): integrate only errors smaller than these
    integrate_below_position: float = 1e-3  # m
    integrate_below_angle: float = math.radians(5.0)  # rad


class PIDPlanner(TwoLayerPlanner):
    """Baseline 2: PID on pose, with drag-scaled output and reference-velocity feed-forward."""

    def __init__(
        self,
        field_model: PlanarFieldModel,
        robot: RobotParams,
        dt: float = 0.04,
        config: PIDConfig | None = None,
        allocation: AllocationConfig | None = None,
    ) -> None:
        super().__init__(field_model, robot, dt, allocation)
        self.config = config or PIDConfig()
        self.reset()

    def reset(self) -> None:
        self._integral = np.zeros(3)
        self._last_error: FloatArray | None = None

    def desired_wrench(self, state: FloatArray, reference: FloatArray) -> FloatArray:
        cfg, dt = self.config, self.dt
        e = reference[0] - state[:3]
        e[2] = wrap_angle(e[2])
        small = np.abs(e) < [cfg.integrate_below_position] * 2 + [cfg.integrate_below_angle]
        self._integral += np.where(small, e * dt, 0.0)
        lim = np.array([cfg.integral_limit_position] * 2 + [cfg.integral_limit_angle])
        self._integral = np.clip(self._integral, -lim, lim)
        de = np.zeros(3) if self._last_error is None else (e - self._last_error) / dt
        self._last_error = e
        ff = (reference[1] - reference[0]) / dt
        kp = np.array([cfg.kp_position] * 2 + [cfg.kp_angle])
        ki = np.array([cfg.ki_position] * 2 + [cfg.ki_angle])
        kd = np.array([cfg.kd_position] * 2 + [cfg.kd_angle])
        v_cmd = ff + kp * e + ki * self._integral + kd * de
        D = drag_matrix(self.robot, float(state[2]))
        return np.concatenate([D @ v_cmd[:2], [self.robot.drag_rotation * v_cmd[2]]])

    def predict(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        return np.full(6, np.nan)

    def _predict_with_wrench(self, state: FloatArray, wrench: FloatArray) -> FloatArray:
        return np.full(6, np.nan)  # a PID makes no prediction


@dataclass(frozen=True)
class LinearMPCConfig:
    """Linear MPC horizon, wrench limits and weights (mm, rad, wrench / limit)."""

    horizon: int = 20
    max_force: float = 4e-4  # N, per axis
    max_torque: float = 4e-6  # N m
    q_position: float = 10.0  # per mm²
    q_angle: float = 100.0  # per rad²
    r_wrench: float = 1.0  # per (wrench / unit)²
    s_wrench_change: float = 0.5  # per (wrench change / unit)²
    #: the force (N) and torque (N m) the wrench weights are per: the paper rig's limits, so
    #: that a system's limits bound the wrench without changing what it costs
    force_unit: float = 4e-4
    torque_unit: float = 4e-6


class LinearMPCPlanner(TwoLayerPlanner):
    """Baselines 3 (lookup tables) and 4 (Zernike): linear MPC on force and torque."""

    def __init__(
        self,
        field_model: PlanarFieldModel,
        robot: RobotParams,
        dt: float = 0.04,
        config: LinearMPCConfig | None = None,
        allocation: AllocationConfig | None = None,
    ) -> None:
        super().__init__(field_model, robot, dt, allocation)
        self.config = cfg = config or LinearMPCConfig()
        N = cfg.horizon
        # constant parts of the condensed least squares: tracking weights, the block
        # lower-triangular pattern of the prediction matrix, and the rows below the tracking
        # ones (wrench size, wrench change) of M
        wq = np.sqrt(np.array([cfg.q_position / 1e-6, cfg.q_position / 1e-6, cfg.q_angle]))
        self._weights = np.tile(wq, N)
        k, j = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
        self._lag = np.where(j <= k, k - j, N)  # block (k, j) of Φ is Ad^(k−j) Bn, or 0
        diff = np.eye(3 * N) - np.eye(3 * N, k=-3)
        self._M = np.vstack(
            [
                np.zeros((3 * N, 3 * N)),
                np.sqrt(cfg.r_wrench) * np.eye(3 * N),
                np.sqrt(cfg.s_wrench_change) * diff,
            ]
        )
        self._unit = np.array([cfg.force_unit, cfg.force_unit, cfg.torque_unit])
        box = np.tile(np.array([cfg.max_force, cfg.max_force, cfg.max_torque]) / self._unit, N)
        self._lower, self._upper = -box, box  # the limits in units
        self._solve = BoxLeastSquares(3 * N)
        self.reset()

    def reset(self) -> None:
        self._last_wrench = np.zeros(3)

    def desired_wrench(self, state: FloatArray, reference: FloatArray) -> FloatArray:
        cfg, N = self.config, self.config.horizon
        Ad, Bd = linear_model(self.robot, float(state[2]), self.dt)
        unit = self._unit
        Bn = Bd * unit  # inputs in units of the weights
        # condensed prediction of the poses (rows 0:3 of the state), k = 1 … N:
        # X_k = Ad^k x0 + Σ_{j<k} Ad^(k−1−j) Bn u_j
        blocks = np.zeros((N + 1, 3, 3))  # Ad^i Bn, pose rows, i = 0 … N−1; block N is 0
        free = np.empty((N, 3))
        AiB, x = Bn, np.asarray(state, dtype=np.float64)
        for i in range(N):
            blocks[i] = AiB[:3]
            AiB = Ad @ AiB
            x = Ad @ x
            free[i] = x[:3]
        Phi = blocks[self._lag].transpose(0, 2, 1, 3).reshape(3 * N, 3 * N)
        ref = np.asarray(reference[1 : N + 1], dtype=np.float64).copy()
        th = float(state[2])
        for k in range(N):  # the reference angle nearest the running estimate
            ref[k, 2] = angle_near(ref[k, 2], th)
            th = ref[k, 2]
        Wq = self._weights
        M = self._M.copy()
        M[: 3 * N] = Wq[:, None] * Phi
        rhs = np.zeros(3 * 3 * N)
        rhs[: 3 * N] = Wq * (ref - free).ravel()
        rhs[6 * N : 6 * N + 3] = np.sqrt(cfg.s_wrench_change) * self._last_wrench / unit
        wrench = self._solve(M, rhs, self._lower, self._upper)[:3] * unit
        self._last_wrench = wrench
        return wrench
