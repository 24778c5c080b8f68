"""Nonlinear MPC that outputs coil currents directly (paper, Section II-C).

Over a horizon of N steps of Δt (defaults 20 and 40 ms), with decision variables the currents
I₀ … I_{N−1} and the predicted states X₁ … X_N (multiple shooting)::

    min   Σ_{k=0}^{N−1} [ e_{p,k}ᵀ Qp e_{p,k} + qθ e_{θ,k}² + I_kᵀ R I_k + ΔI_kᵀ S ΔI_k ]
          + e_{p,N}ᵀ P e_{p,N} + qθ,N e_{θ,N}²
    s.t.  X_{k+1} = f(X_k, I_k)                 robot.discrete_step with the field model
          |I_k| ≤ I_max,  |I_k − I_{k−1}| ≤ slew Δt   (I_{−1}: the currents applied last tick)
          |x_k|, |y_k| ≤ workspace half-width − margin   (k ≥ 1)

with e_{p,k} = (x_k, y_k) − (x_k^d, y_k^d) and e_{θ,k} the wrapped angle error, written
``atan2(sin Δ, cos Δ)`` (the paper's ``((Δ + π) mod 2π) − π``, smooth for the solver). X₀ is
the estimate (its position projected into the workspace box). IPOPT solves it, warm-started
from the previous solution shifted by one step.

Units inside the NLP are scaled for the solver: positions in mm, velocities in mm/s, and
currents as fractions of the limit, u = I / I_max. The weights are stated in those units:
Qp and P per mm², qθ and qθ,N per rad², R and S per u².

Default weights follow the paper's tuning note, ‖R‖ = 2‖S‖ and ‖Qp‖ = 10‖R‖, in these units
(R = I₈, S = 0.5 I₈, Qp = P = 10 I₂). The paper does not state its units, and the ratio only
means something with them: with currents in amperes instead (the same numbers per A², a
current penalty 900 times heavier) the robot lags the S-trajectory by 1.7–1.9 mm RMS on the
simulated rig; with normalised currents it tracks to a few hundredths of a millimetre.

On failure (no convergence, non-finite output) the plan falls back to the
previous plan's next currents ("shifted"), or to 0 A ("zero") when there is none; the
controller's safety clamp then bounds the change.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.control.base import ControllerStatus, Plan, Planner
from magrun.field.model import PlanarFieldModel
from magrun.robot import RobotParams, casadi_step_function

FloatArray = NDArray[np.float64]

#: NLP scaling of the state: mm, mm, rad, mm/s, mm/s, rad/s
STATE_SCALE = np.array([1e-3, 1e-3, 1.0, 1e-3, 1e-3, 1.0])
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


@dataclass(frozen=True)
class NMPCConfig:
    """NMPC horizon, weights (scaled units, see module doc) and solver options."""

    horizon: int = 20
    dt: float = 0.04
    q_position: float = 10.0  # Qp = q_position I₂, per mm²
    q_angle: float = 100.0  # qθ, per rad²
    r_current: float = 1.0  # R = r_current I₈, per (I / I_max)²
    s_current_change: float = 0.5  # S, per (I / I_max)²
    p_position: float = 10.0  # terminal P, per mm²
    q_angle_terminal: float = 100.0  # qθ,N, per rad²
    workspace_margin: float | None = None  # m; None: half the robot's length
    substeps: int = 2
    max_iter: int = 100
    tol: float = 1e-6
    expand: bool = True
    ipopt: dict[str, Any] = field(default_factory=dict)


class NMPC(Planner):
    """The NMPC planner on a given field model (Zernike: proposed/B1; lookup table: B5)."""

    def __init__(
        self,
        field_model: PlanarFieldModel,
        robot: RobotParams,
        config: NMPCConfig | None = None,
    ) -> None:
        self.config = cfg = config or NMPCConfig()
        self.model = field_model
        self.robot = robot
        coils = field_model.coils
        self.n_currents = nI = coils.n_channels
        self.max_current = coils.max_current
        self.max_change = coils.max_slew_rate * cfg.dt
        margin = robot.length / 2 if cfg.workspace_margin is None else cfg.workspace_margin
        self.position_bound = coils.workspace_half_width - margin
        self.step_function = casadi_step_function(
            robot, field_model.casadi_field_and_gradient, nI, cfg.dt, cfg.substeps
        )
        self._build()
        self.reset()

    # -- problem construction ------------------------------------------------------------------

    def _build(self) -> None:
        cfg, N, nI = self.config, self.config.horizon, self.n_currents
        scale = ca.DM(STATE_SCALE)
        x0 = ca.MX.sym("x0", 6)  # SI
        I_prev = ca.MX.sym("u_prev", nI)  # I / I_max
        ref = ca.MX.sym("ref", 3, N + 1)  # SI, columns k = 0 … N
        Is = [ca.MX.sym(f"u{k}", nI) for k in range(N)]  # I / I_max
        Xs = [ca.MX.sym(f"X{k + 1}", 6) for k in range(N)]  # scaled

        def pose_cost(X_scaled: Any, k: int, qp: float, qa: float) -> Any:
            ep = X_scaled[:2] - ref[:2, k] / 1e-3
            d = X_scaled[2] - ref[2, k]
            return qp * ca.sumsqr(ep) + qa * ca.atan2(ca.sin(d), ca.cos(d)) ** 2

        J: Any = 0
        g, lbg, ubg = [], [], []
        x_prev_si, I_before = x0, I_prev
        for k in range(N):
            if k > 0:
                J += pose_cost(Xs[k - 1], k, cfg.q_position, cfg.q_angle)
            dI = Is[k] - I_before
            J += cfg.r_current * ca.sumsqr(Is[k]) + cfg.s_current_change * ca.sumsqr(dI)
            g.append((self.step_function(x_prev_si, Is[k] * self.max_current) / scale) - Xs[k])
            lbg.append(np.zeros(6))
            ubg.append(np.zeros(6))
            g.append(dI)
            lbg.append(np.full(nI, -self.max_change / self.max_current))
            ubg.append(np.full(nI, self.max_change / self.max_current))
            x_prev_si, I_before = Xs[k] * scale, Is[k]
        J += pose_cost(Xs[-1], N, cfg.p_position, cfg.q_angle_terminal)

        w = ca.vertcat(*[ca.vertcat(Is[k], Xs[k]) for k in range(N)])
        p = ca.vertcat(x0, I_prev, ca.vec(ref))
        opts: dict[str, Any] = {
            "expand": cfg.expand,
            "print_time": False,
            "error_on_fail": False,
            "ipopt": {
                "print_level": 0,
                "sb": "yes",
                "max_iter": cfg.max_iter,
                "tol": cfg.tol,
                "acceptable_tol": 1e-4,
                "acceptable_iter": 5,
                **cfg.ipopt,
            },
        }
        self.solver = ca.nlpsol(
            "nmpc", "ipopt", {"x": w, "p": p, "f": J, "g": ca.vertcat(*g)}, opts
        )
        self._lbg = np.concatenate(lbg)
        self._ubg = np.concatenate(ubg)
        stage_lb = np.concatenate(
            [np.full(nI, -1.0), [-self.position_bound / 1e-3] * 2, [-np.inf] * 4]
        )
        stage_ub = -stage_lb
        self._lbx = np.tile(stage_lb, N)
        self._ubx = np.tile(stage_ub, N)
        self._stage = nI + 6

    # -- Planner API -----------------------------------------------------------------------------

    def reset(self) -> None:
        self._w: FloatArray | None = None

    def predict(self, state: FloatArray, currents: FloatArray) -> FloatArray:
        return np.asarray(self.step_function(state, currents), dtype=np.float64).ravel()

    def plan(self, state: FloatArray, reference: FloatArray, previous: FloatArray) -> Plan:
        N, nI, ns = self.config.horizon, self.n_currents, self._stage
        x0 = np.asarray(state, dtype=np.float64).copy()
        x0[:2] = np.clip(x0[:2], -self.position_bound, self.position_bound)
        ref = np.asarray(reference, dtype=np.float64)
        if ref.shape != (N + 1, 3):
            raise ValueError(f"reference must have shape ({N + 1}, 3), got {ref.shape}")
        w0 = self._initial_guess(x0, previous)
        args: dict[str, Any] = {
            "x0": w0,
            "p": np.concatenate([x0, previous / self.max_current, ref.ravel()]),
            "lbx": self._lbx,
            "ubx": self._ubx,
            "lbg": self._lbg,
            "ubg": self._ubg,
        }
        t0 = time.perf_counter()
        sol = self.solver(**args)
        elapsed = time.perf_counter() - t0
        stats = self.solver.stats()
        w = np.asarray(sol["x"], dtype=np.float64).ravel()
        message = str(stats.get("return_status", ""))
        ok = message in SUCCESS and bool(np.all(np.isfinite(w)))
        iterations = int(stats.get("iter_count", 0))
        if ok:
            self._w = w
            currents = w[:nI] * self.max_current
            predicted = w[nI : nI + 6] * STATE_SCALE
            status = ControllerStatus(elapsed, iterations, True, "", message)
        else:
            if self._w is not None:
                currents, fallback = self._w[ns : ns + nI] * self.max_current, "shifted"
                self._w = np.concatenate([self._w[ns:], self._w[-ns:]])
            else:
                currents, fallback = np.zeros(nI), "zero"
            predicted = self.predict(x0, currents)
            status = ControllerStatus(elapsed, iterations, False, fallback, message)
        return Plan(currents, predicted, status)

    def _initial_guess(self, x0: FloatArray, previous: FloatArray) -> FloatArray:
        """The previous solution shifted one step (last stage repeated); else hold and rest."""
        ns = self._stage
        if self._w is not None:
            return np.concatenate([self._w[ns:], self._w[-ns:]])
        stage = np.concatenate([previous / self.max_current, x0 / STATE_SCALE])
        return np.tile(stage, self.config.horizon)
