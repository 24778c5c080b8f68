"""The NMPC as a :class:`~magrun.control.base.Planner`: the tick's start, corridor and prediction;
the solver behind it (:mod:`.ipopt` or :mod:`.rti`)."""

from __future__ import annotations

import math
import time

import numpy as np
from numpy.typing import NDArray

from magrun.control.base import Plan, Planner
from magrun.control.nmpc.backend import Backend
from magrun.control.nmpc.config import N_PLANES, NX, OUTSIDE_START, STATE_SCALE, Iterate, NMPCConfig
from magrun.control.nmpc.ipopt import IpoptSolver
from magrun.control.nmpc.problem import OCP, channel_field_scale
from magrun.control.nmpc.rti import RTISolver
from magrun.field.model import PlanarFieldModel
from magrun.freespace import INACTIVE, FreeSpace
from magrun.records import ControllerStatus
from magrun.robot import RobotParams

FloatArray = NDArray[np.float64]


class NMPC(Planner):
    """The NMPC planner on a given field model (Zernike: proposed/B1; lookup table: B5)."""

    def __init__(
        self,
        field_model: PlanarFieldModel,
        robot: RobotParams,
        config: NMPCConfig | None = None,
        free_space: FreeSpace | None = None,
    ) -> None:
        self.config = cfg = config or NMPCConfig()
        if cfg.solver not in ("rti", "ipopt"):
            raise ValueError(f"unknown NMPC solver {cfg.solver!r}; choose rti or ipopt")
        if cfg.soft_constraints not in ("slack", "penalty"):
            raise ValueError(
                f"unknown soft_constraints {cfg.soft_constraints!r}; choose slack or penalty"
            )
        if not (math.isfinite(cfg.step_damping) and cfg.step_damping >= 0):
            raise ValueError(f"step_damping must be a number >= 0, got {cfg.step_damping}")
        self.model = field_model
        self.robot = robot
        coils = field_model.coils
        self.n_currents = coils.n_channels
        self.max_current = coils.max_current
        self.max_change = coils.max_slew_rate * cfg.dt
        margin = robot.length / 2 if cfg.workspace_margin is None else cfg.workspace_margin
        self.position_bound = coils.workspace_half_width - margin
        self.min_aligned_field = (
            robot.min_aligned_field if cfg.min_aligned_field is None else cfg.min_aligned_field
        )
        self.free_space = free_space
        #: each channel's field per ampere, RMS over the workspace, T/A (the field-model
        #: error's scale; module doc, "Field-model error")
        self.channel_field_scale = channel_field_scale(field_model)
        #: the estimate's position covariance (2×2, m²), for the corridor's chance margin
        self.position_covariance: FloatArray | None = None
        self.problem = OCP(self)
        self.backend: Backend = (
            RTISolver(self.problem) if cfg.solver == "rti" else IpoptSolver(self.problem)
        )
        self._predict = self.problem.maybe_compiled(self.problem.step_scaled)
        self.reset()

    # -- Planner API -----------------------------------------------------------------------------

    def reset(self) -> None:
        self.backend.reset()
        self.position_covariance = None
        self._expected_covariance: FloatArray | None = None
        #: the corridor's stages 1 … N as prepared: (reference, covariance, half-planes)
        self._ahead: tuple[FloatArray, FloatArray | None, FloatArray] | None = None
        self._prepare_time = 0.0

    @property
    def uses_uncertainty(self) -> bool:  # type: ignore[override]
        """The corridor's chance margins use the estimate's covariance (a phantom's)."""
        return self.problem.has_corridor

    def observe_uncertainty(self, covariance: FloatArray | None) -> None:
        """The estimate's covariance (3×3: x, y, θ) before this tick's frame (the filter's
        prediction), or None: tightens the corridor."""
        self.position_covariance = None if covariance is None else np.asarray(covariance)[:2, :2]

    def expect_uncertainty(self, covariance: FloatArray | None) -> None:
        """The next tick's :meth:`observe_uncertainty` (3×3), known a tick ahead: the
        prepared corridor's."""
        self._expected_covariance = (
            None if covariance is None else np.asarray(covariance)[:2, :2].copy()
        )

    def corridor(
        self, state: FloatArray, reference: FloatArray, covariance: FloatArray | None = None
    ) -> FloatArray:
        """The half-planes of each stage 0 … N, shape (N+1, N_PLANES, 3), in mm (scaled); the
        chance margins from ``covariance`` (2×2), else from :attr:`position_covariance`."""
        cov = self.position_covariance if covariance is None else covariance
        return self._with_start(self._corridor_ahead(reference, cov), state, cov)

    def _corridor_ahead(self, reference: FloatArray, cov: FloatArray | None) -> FloatArray:
        """:meth:`corridor`'s stages 1 … N (SI; stage 0 left inactive), which do not depend
        on the start: the half-planes at the last plan's states (the reference's before a
        plan), margins from ``cov``."""
        N = self.config.horizon
        planes = np.empty((N + 1, N_PLANES, 3))
        planes[:] = INACTIVE
        fs = self.free_space
        if fs is None:
            return planes
        plan = self.backend.states_plan()  # X_1 … X_N of the last plan, scaled
        if plan is None:
            positions = reference[1:, :2]
        else:
            positions = np.vstack([plan[1:, :2] * 1e-3, plan[-1:, :2] * 1e-3])
        cfg = self.config
        planes[1:, 0] = fs.corridor(
            positions, cov, cfg.corridor_margin, cfg.corridor_sigmas, cfg.corridor_share
        )
        return planes

    def _with_start(
        self, ahead: FloatArray, state: FloatArray, cov: FloatArray | None
    ) -> FloatArray:
        """The stages 1 … N of ``ahead`` (SI) with stage 0's half-plane, at the start
        ``state``, and the start's lead-out (module doc, "Corridor"): in mm (scaled)."""
        planes = ahead.copy()
        fs = self.free_space
        if fs is None:
            return planes
        cfg = self.config
        planes[0, 0] = fs.corridor(
            state[None, :2], cov, cfg.corridor_margin, cfg.corridor_sigmas, cfg.corridor_share
        )[0]
        if cfg.corridor_recovery > 0:
            # a start already inside the margin (an estimate that a frame moved toward the
            # wall) is led back out at corridor_recovery, not within one stage (module doc)
            n, c = planes[0, 0, :2], planes[0, 0, 2]
            axis = np.array([math.cos(state[2]), math.sin(state[2])]) * fs.half_axis
            inside = c - min(n @ (state[:2] + axis), n @ (state[:2] - axis))
            if inside > 0:
                k = np.arange(len(planes))
                planes[:, 0, 2] -= np.maximum(0.0, inside - k * cfg.dt * cfg.corridor_recovery)
        planes[:, :, 2] /= 1e-3  # c in mm, as the scaled positions
        return planes

    def predict(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        X, u = np.asarray(state) / STATE_SCALE, np.asarray(currents) / self.max_current
        kernel = getattr(self.backend, "kernel", None)
        if kernel is not None:  # the same compiled step, without CasADi's call overhead
            return kernel.predict(X, u) * STATE_SCALE
        return np.asarray(self._predict(X, u), dtype=np.float64).ravel() * STATE_SCALE

    def _start(
        self, state: FloatArray, reference: FloatArray, previous: FloatArray,
        covariance: FloatArray | None = None, preparation: bool = False,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:  # fmt: skip
        """(x0 SI, its position in the workspace box; u_prev scaled; stage parameters, the
        corridor's margins from ``covariance`` where given). A ``preparation`` keeps the
        corridor's stages 1 … N for the tick it prepares."""
        N = self.config.horizon
        x0 = np.asarray(state, dtype=np.float64).copy()
        x0[:2] = np.clip(x0[:2], -self.position_bound, self.position_bound)
        ref = np.asarray(reference, dtype=np.float64)
        if ref.shape != (N + 1, 3):
            raise ValueError(f"reference must have shape ({N + 1}, 3), got {ref.shape}")
        u_prev = np.asarray(previous, dtype=np.float64) / self.max_current
        cov = self.position_covariance if covariance is None else covariance
        ahead, self._ahead = self._ahead, None
        if ahead is None or not (
            np.array_equal(ahead[0], ref) and _same(ahead[1], cov)
        ):  # not prepared for this reference and covariance (the plan is the same)
            ahead = (ref, cov, self._corridor_ahead(ref, cov))
        if preparation:
            self._ahead = (ref.copy(), None if cov is None else cov.copy(), ahead[2])
        planes = self._with_start(ahead[2], x0, cov)
        return x0, u_prev, self.problem.stage_parameters(ref, planes)

    def _braking(self, x0: FloatArray, previous: FloatArray) -> Iterate:
        """A plan (S, V), scaled as the backends' iterates, that brakes: from ``x0`` (SI) the
        currents brought from ``previous`` (A) to zero as fast as the slew bound allows, the
        states the model gives for them, positions held within the bound."""
        N, bound = self.config.horizon, self.position_bound
        u, x = previous.copy(), x0.copy()
        S, V = np.empty((N, NX + self.n_currents)), np.empty((N, self.n_currents))
        for k in range(N):
            change = -np.clip(u, -self.max_change, self.max_change)
            u = u + change
            x = self.predict(x, u)
            if not np.all(np.isfinite(x)):
                x = x0.copy()
            x[:2] = np.clip(x[:2], -bound, bound)
            S[k] = np.concatenate([x / STATE_SCALE, u / self.max_current])
            V[k] = change / self.max_current
        return S, V

    def prepare(self, state: FloatArray, reference: FloatArray, previous: FloatArray) -> None:
        """The real-time iteration's preparation phase for the next tick (RTI solver): the
        plan moved on one stage and every stage linearised there, stage 0 at the predicted
        ``state``. The next :meth:`plan` then embeds its measured state into that QP and
        solves it (the feedback phase), where its parameters are the prepared ones: the
        same reference and previous currents, and corridor margins from the same
        covariance. With a phantom's corridor and a Kalman filter the margins follow the
        estimate's covariance before the tick's frame, the filter's prediction, which is
        known a tick ahead (:meth:`expect_uncertainty`): a frame's tick is prepared as any
        other. A tick whose start the corridor leads out of its margin (the lead-out follows
        the measured start) iterates in full."""
        covariance = None
        if self.problem.has_corridor and self.position_covariance is not None:
            covariance = self._expected_covariance
            if covariance is None:
                return  # the margins' covariance is not known ahead
        t0 = time.perf_counter()
        x0, u_prev, params = self._start(state, reference, previous, covariance, preparation=True)
        done = self.backend.prepare(np.concatenate([x0 / STATE_SCALE, u_prev]), params)
        self._prepare_time = time.perf_counter() - t0 if done else 0.0

    def plan(self, state: FloatArray, reference: FloatArray, previous: FloatArray) -> Plan:
        t0 = time.perf_counter()
        x0, u_prev, params = self._start(state, reference, previous)
        result = self.backend.solve(x0 / STATE_SCALE, u_prev, params)
        if not result.ok:
            # once more at rest, at least OUTSIDE_START inside the bound, from a plan that
            # brakes (module doc)
            inner = self.position_bound - OUTSIDE_START
            retry = np.concatenate([np.clip(x0[:2], -inner, inner), x0[2:3], np.zeros(3)])
            start = self._braking(retry, np.asarray(previous, dtype=np.float64))
            result = self.backend.solve(retry / STATE_SCALE, u_prev, params, start)
        elapsed = time.perf_counter() - t0
        prepared, self._prepare_time = self._prepare_time, 0.0
        if result.ok:
            currents = result.u0 * self.max_current
            predicted = self.predict(x0, currents)
            status = ControllerStatus(
                elapsed, result.iterations, True, "", result.message, prepared
            )
        else:
            shifted = self.backend.fallback()
            if shifted is not None:
                currents, fallback = shifted * self.max_current, "shifted"
            else:
                currents, fallback = np.zeros(self.n_currents), "zero"
            predicted = self.predict(x0, currents)
            status = ControllerStatus(
                elapsed, result.iterations, False, fallback, result.message, prepared
            )
        return Plan(currents, predicted, status)


def _same(a: FloatArray | None, b: FloatArray | None) -> bool:
    """Whether two covariances (or Nones) are the same, bit for bit."""
    return (a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))


# --------------------------------------------------------------------------------------------
# the problem, shared by both solvers
