"""magrun's NMPC problem formulated in acados, as a magrun Planner (a peer for benchmarks).

acados is not a dependency of magrun: this file needs an acados build and its Python
interface (README.md beside it). The problem is magrun's RTI problem
(magrun/control/nmpc/problem.py, scaled units), built from magrun's own CasADi functions:

  state     s_k = (X_k scaled [mm, mm, rad, mm/s, mm/s, rad/s], u_{k-1} = I / I_max)   (14)
  input     v_k = u_k - u_{k-1}                                                         (8)
  dynamics  s_{k+1} = (step_scaled(X_k, u_{k-1} + v_k), u_{k-1} + v_k)   DISCRETE model
  cost      NONLINEAR_LS, the same residuals as magrun's Gauss-Newton cost: stage 0
            [heading, sqrt(R) u, sqrt(S) v]; stages 1..N-1 the pose residual in front; the
            terminal pose residual. The heading-stable field's residual is magrun's own
            min(0, sqrt(w) (B_par - B_min)). acados halves a least-squares cost, so W = 2 I
            on the residuals (the weights are inside them) gives magrun's objective.
  bounds    |v| <= du_max; |x|, |y| <= pos_max and |u_prev| <= 1 on stages 1..N; s_0 fixed.

The reference pose per stage is the stage parameter. No corridor (the benchmark's S runs in
the open workspace), and no corrective iterations (magrun's RTI may add up to two when the
heading residual was missed by the linearisation; acados' SQP_RTI takes one QP a tick).

With ``split=True`` the planner runs acados' real-time split in the closed loop as magrun
does: ``prepare`` (rti_phase 1: the shifted plan linearised, x_0's guess the predicted
state) after the currents went out, and ``plan`` embeds the measured s_0 and solves
(rti_phase 2). Solve times are then the feedback phase; ``prepare_time`` the preparation.
"""

from __future__ import annotations

import os
import time
from typing import Any

import acados_template.utils
import casadi as ca
import numpy as np
from acados_template import AcadosModel, AcadosOcp, AcadosOcpSolver

from magrun.control.base import Plan, Planner
from magrun.control.nmpc import NMPC, NP, NX, STATE_SCALE
from magrun.records import ControllerStatus

# the t_renderer built offline (README.md) reports this version
acados_template.utils.TERA_DEFAULT_VERSION = os.environ.get("TERA_VERSION", "0.2.0")


def build_ocp(
    nmpc: NMPC, mode: str, name: str, hpipm_mode: str = "SPEED", cond_n: int | None = None
) -> AcadosOcp:
    prob, cfg = nmpc.problem, nmpc.config
    N, nu = prob.N, prob.nu
    X = ca.SX.sym("X", NX)
    up = ca.SX.sym("u_prev", nu)
    v = ca.SX.sym("v", nu)
    ref = ca.SX.sym("ref", 3)
    u = up + v
    model = AcadosModel()
    model.name = name
    model.x = ca.vertcat(X, up)
    model.u = v
    model.p = ref
    model.disc_dyn_expr = ca.vertcat(prob.step_scaled(X, u), u)
    par = ca.vertcat(ref, ca.DM.zeros(NP - 3))  # no corridor half-planes
    pose = prob.pose_residual["stage"](X, par)
    heading = prob.heading(X, u)
    currents = ca.vertcat(np.sqrt(cfg.r_current) * u, np.sqrt(cfg.s_current_change) * v)
    model.cost_y_expr_0 = ca.vertcat(heading, currents)
    model.cost_y_expr = ca.vertcat(pose, heading, currents)
    model.cost_y_expr_e = prob.pose_residual["terminal"](X, par)
    ny0, ny, nye = (int(e.shape[0]) for e in (model.cost_y_expr_0, model.cost_y_expr,
                                               model.cost_y_expr_e))  # fmt: skip

    ocp = AcadosOcp()
    ocp.model = model
    ocp.cost.cost_type_0 = ocp.cost.cost_type = ocp.cost.cost_type_e = "NONLINEAR_LS"
    ocp.cost.W_0, ocp.cost.W, ocp.cost.W_e = 2 * np.eye(ny0), 2 * np.eye(ny), 2 * np.eye(nye)
    ocp.cost.yref_0, ocp.cost.yref, ocp.cost.yref_e = np.zeros(ny0), np.zeros(ny), np.zeros(nye)
    ocp.parameter_values = np.zeros(3)

    c = ocp.constraints
    c.x0 = np.zeros(NX + nu)
    c.idxbu = np.arange(nu)
    du = np.broadcast_to(prob.du_max, (nu,))
    c.lbu, c.ubu = -du, du.copy()
    idx = np.concatenate([[0, 1], NX + np.arange(nu)])
    lb = np.concatenate([[-prob.pos_max] * 2, np.full(nu, -1.0)])
    c.idxbx, c.lbx, c.ubx = idx, lb, -lb
    c.idxbx_e, c.lbx_e, c.ubx_e = idx, lb, -lb

    o = ocp.solver_options
    o.N_horizon = N
    o.tf = N * cfg.dt
    o.integrator_type = "DISCRETE"
    o.hessian_approx = "GAUSS_NEWTON"
    o.qp_solver = "PARTIAL_CONDENSING_HPIPM"
    if cond_n is not None:
        o.qp_solver_cond_N = cond_n
    o.hpipm_mode = hpipm_mode
    o.cost_scaling = np.ones(N + 1)
    o.qp_solver_iter_max = 50
    o.qp_tol = 1e-8
    o.print_level = 0
    if mode == "rti":
        o.nlp_solver_type = "SQP_RTI"
    else:
        o.nlp_solver_type = "SQP"
        o.nlp_solver_max_iter = 100
        o.nlp_solver_tol_stat = 1e-6
        o.nlp_solver_tol_eq = 1e-8
        o.nlp_solver_tol_ineq = 1e-8
        o.nlp_solver_tol_comp = 1e-8
    return ocp


class AcadosPlanner(Planner):
    """acados on magrun's problem; magrun's NMPC gives the model, the scalings and predict."""

    def __init__(
        self, nmpc: NMPC, mode: str = "rti", build_dir: str = "acados_build",
        hpipm_mode: str = "SPEED", cond_n: int | None = None, tag: str = "",
        split: bool = False,
    ) -> None:  # fmt: skip
        self.nmpc, self.mode, self.split = nmpc, mode, split
        self.N, self.nu = nmpc.problem.N, nmpc.problem.nu
        name = f"magrun_{mode}{tag}"
        ocp = build_ocp(nmpc, mode, name, hpipm_mode, cond_n)
        folder = os.path.join(build_dir, name)
        ocp.code_export_directory = os.path.join(folder, "c_generated_code")
        self.solver = AcadosOcpSolver(
            ocp, json_file=os.path.join(folder, "ocp.json"), verbose=False
        )
        self.reset()

    def reset(self) -> None:
        self._warm = False
        self._prepared: np.ndarray | None = None
        self._prepare_time = 0.0
        self.internal_times: list[float] = []  # acados' own time_tot per solve, s
        self.solver.reset()

    def predict(self, state: Any, currents: Any) -> Any:
        return self.nmpc.predict(state, currents)

    def _scaled(self, state: Any, previous: Any) -> np.ndarray:
        nm = self.nmpc
        x0 = np.asarray(state, dtype=np.float64).copy()
        x0[:2] = np.clip(x0[:2], -nm.position_bound, nm.position_bound)
        u_prev = np.asarray(previous, dtype=np.float64) / nm.max_current
        return np.concatenate([x0 / STATE_SCALE, u_prev])

    def _parameters(self, reference: Any) -> None:
        refs = np.asarray(reference, dtype=np.float64).T.copy()
        refs[:2] /= 1e-3  # mm
        self.solver.set_flat("p", refs.ravel(order="F"))

    def _shift(self, s_first: np.ndarray) -> None:
        S, nu, ns = self.solver, self.nu, NX + self.nu
        xs, us = S.get_flat("x"), S.get_flat("u")
        S.set_flat("x", np.concatenate([s_first, xs[2 * ns :], xs[-ns:]]))
        S.set_flat("u", np.concatenate([us[nu:], np.zeros(nu)]))

    def prepare(self, state: Any, reference: Any, previous: Any) -> None:
        if not (self.split and self._warm and self.mode == "rti"):
            return
        t0 = time.perf_counter()
        s_pred = self._scaled(state, previous)
        self._parameters(reference)
        self._shift(s_pred)  # x_0's guess: the predicted state (initial-value embedding)
        self.solver.options_set("rti_phase", 1)
        self.solver.solve()
        self._prepared = np.asarray(reference, dtype=np.float64).copy()
        self._prepare_time = time.perf_counter() - t0

    def plan(self, state: Any, reference: Any, previous: Any) -> Plan:
        nm, S = self.nmpc, self.solver
        t0 = time.perf_counter()
        s0 = self._scaled(state, previous)
        prepared, prepare_time = self._prepared, self._prepare_time
        self._prepared, self._prepare_time = None, 0.0
        iters = 1
        if prepared is not None and np.array_equal(prepared, reference):
            S.constraints_set(0, "lbx", s0)
            S.constraints_set(0, "ubx", s0)
            S.options_set("rti_phase", 2)
            status = S.solve()
            S.options_set("rti_phase", 0)
        else:
            prepare_time = 0.0
            self._parameters(reference)
            S.constraints_set(0, "lbx", s0)
            S.constraints_set(0, "ubx", s0)
            if not self._warm:  # like magrun: hold the currents, rest at s0, iterate
                N, nu = self.N, self.nu
                S.set_flat("x", np.tile(s0, N + 1))
                S.set_flat("u", np.zeros(N * nu))
                last = None
                for iters in range(1, (30 if self.mode == "rti" else 1) + 1):  # noqa: B007
                    status = S.solve()
                    u = S.get_flat("u")
                    if status != 0 or (last is not None and np.max(np.abs(u - last)) < 1e-8):
                        break
                    last = u
                self._warm = status == 0
            else:  # stage 0 linearised at the measured s0, as magrun's unsplit tick
                self._shift(s0)
                status = S.solve()
            if self.mode != "rti":
                iters = int(S.get_stats("sqp_iter"))
        self.internal_times.append(float(S.get_stats("time_tot")))
        v0 = S.get(0, "u")
        elapsed = time.perf_counter() - t0
        ok = status == 0 and bool(np.all(np.isfinite(v0)))
        u0 = s0[NX:] + v0
        currents = u0 * nm.max_current if ok else np.asarray(previous, dtype=np.float64)
        predicted = nm.predict(s0[:NX] * STATE_SCALE, currents)
        fallback = "" if ok else "previous"
        status_ = ControllerStatus(elapsed, iters, ok, fallback, f"acados status {status}",
                                   prepare_time)  # fmt: skip
        return Plan(currents, predicted, status_)
