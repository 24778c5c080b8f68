"""The reference solver: the whole NLP by IPOPT every tick (multiple shooting)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.compiled import fingerprint, shared_library
from magrun.control.nmpc.backend import Backend, SolveResult
from magrun.control.nmpc.config import NP, NX, SUCCESS, Iterate
from magrun.control.nmpc.problem import OCP

FloatArray = NDArray[np.float64]


class IpoptSolver(Backend):
    """The multiple-shooting NLP to convergence with IPOPT, exact Hessian, warm-started.

    Decision vector: stage by stage (u_k, X_{k+1}), k = 0 … N−1. The NLP is built in MX with
    the stage function as a call node, so CasADi's generated callbacks (objective, gradient,
    constraint Jacobian, Lagrangian Hessian) hold each stage's derivative code once; they are
    compiled to one shared library (:mod:`magrun.compiled`) and IPOPT loads it.
    """

    def __init__(self, ocp: OCP) -> None:
        self.ocp = ocp
        cfg, N, nu = ocp.config, ocp.N, ocp.nu
        x0 = ca.MX.sym("x0", NX)  # scaled
        u_prev = ca.MX.sym("u_prev", nu)
        ref = ca.MX.sym("par", NP, N + 1)  # scaled stage parameters
        us = [ca.MX.sym(f"u{k}", nu) for k in range(N)]
        Xs = [ca.MX.sym(f"X{k + 1}", NX) for k in range(N)]
        J: Any = 0
        g, lbg, ubg = [], [], []
        slacks: list[Any] = []
        soft_g: list[Any] = []  # after every stage's rows, so warm starts shift stage-wise
        X_before, u_before = x0, u_prev
        stage_r, term_r = ocp.pose_residual["stage"], ocp.pose_residual["terminal"]

        def soften(gap: Any, name: str) -> Any:
            """s ≥ 0 with gap + s ≥ 0; returns Σ s² (the soft constraints, see soft_gaps)."""
            if gap.shape[0] == 0:
                return 0
            s = ca.MX.sym(name, gap.shape[0])
            slacks.append(s)
            soft_g.append(gap + s)
            return ca.sumsqr(s)

        for k in range(N):
            if k > 0:
                J += ca.sumsqr(stage_r(X_before, ref[:, k]))
                J += soften(ocp.soft_gaps(X_before, us[k], ref[:, k]), f"s{k}")
            else:  # X₀ is given: only the heading is the plan's to keep
                J += soften(ocp.soft_gaps(X_before, us[k], ref[:, k])[: int(ocp.has_heading)],
                            "s0")  # fmt: skip
            du = us[k] - u_before
            J += cfg.r_current * ca.sumsqr(us[k]) + cfg.s_current_change * ca.sumsqr(du)
            J += ca.sumsqr(ocp.uncertainty(X_before, us[k]))
            g += [ocp.step_scaled(X_before, us[k]) - Xs[k], du]
            lbg += [np.zeros(NX), np.full(nu, -ocp.du_max)]
            ubg += [np.zeros(NX), np.full(nu, ocp.du_max)]
            X_before, u_before = Xs[k], us[k]
        J += ca.sumsqr(term_r(X_before, ref[:, N]))
        J += soften(ocp.soft_gaps(X_before, None, ref[:, N]), "sN")
        slack = ca.vertcat(*slacks) if slacks else ca.MX(0, 1)
        g += soft_g
        lbg.append(np.zeros(slack.shape[0]))
        ubg.append(np.full(slack.shape[0], np.inf))
        w = ca.vertcat(*[ca.vertcat(us[k], Xs[k]) for k in range(N)], slack)
        p = ca.vertcat(x0, u_prev, ca.vec(ref))
        self._lbg, self._ubg = np.concatenate(lbg), np.concatenate(ubg)
        stage_lb = np.concatenate([np.full(nu, -1.0), [-ocp.pos_max] * 2, [-np.inf] * 4])
        n_slack = slack.shape[0]
        self._lbx = np.concatenate([np.tile(stage_lb, N), np.zeros(n_slack)])
        self._ubx = np.concatenate([np.tile(-stage_lb, N), np.full(n_slack, np.inf)])
        self._n_main = N * (nu + NX)
        self._stage = nu + NX
        opts: dict[str, Any] = {
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
        nlp = {"x": w, "p": p, "f": J, "g": ca.vertcat(*g)}
        library = self._compile(nlp, opts) if cfg.compile else None
        self.solver = ca.nlpsol("nmpc_ipopt", "ipopt", nlp if library is None else str(library),
                                opts)  # fmt: skip
        warm = {
            "warm_start_init_point": "yes",
            "warm_start_bound_push": 1e-9,
            "warm_start_bound_frac": 1e-9,
            "warm_start_slack_bound_frac": 1e-9,
            "warm_start_slack_bound_push": 1e-9,
            "warm_start_mult_bound_push": 1e-9,
            "mu_init": 1e-4,
        }
        warm_opts = {**opts, "ipopt": {**opts["ipopt"], **warm, **cfg.ipopt}}
        self.warm_solver = (
            ca.nlpsol("nmpc_ipopt", "ipopt", nlp, warm_opts)
            if library is None
            else ca.nlpsol("nmpc_ipopt", "ipopt", str(library), warm_opts)
        )
        self.reset()

    @staticmethod
    def _compile(nlp: dict[str, Any], opts: dict[str, Any]) -> Path | None:
        """IPOPT's NLP callbacks compiled (cached; found by the NLP's graph where the cache
        knows it, without building the solver's derivatives: :mod:`magrun.compiled`)."""

        def write(folder: Path) -> Path:
            solver = ca.nlpsol("nmpc_ipopt", "ipopt", nlp, opts)
            cwd = os.getcwd()
            os.chdir(folder)  # generate_dependencies writes into the working directory
            try:
                return folder / solver.generate_dependencies("nmpc_ipopt.c")
            finally:
                os.chdir(cwd)

        graph = fingerprint(ca.Function("nmpc_nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]]))
        return shared_library(
            "nmpc_ipopt", write, optimisation="-O1",
            fingerprint=None if graph is None else graph + repr(opts).encode(),
        )  # fmt: skip

    def reset(self) -> None:
        self._w: FloatArray | None = None
        self._lam_g: FloatArray | None = None
        self._lam_x: FloatArray | None = None

    def _shift(self, v: FloatArray, width: int) -> FloatArray:
        """The stage-wise part moved one stage on (the last repeated); slacks zero."""
        main = v[: self._n_main]
        return np.concatenate([main[width:], main[-width:], np.zeros(v.size - self._n_main)])

    def solve(
        self, x0: FloatArray, u_prev: FloatArray, par: FloatArray, start: Iterate | None = None
    ) -> SolveResult:
        ns, nu = self._stage, self.ocp.nu
        p = np.concatenate([x0, u_prev, par.ravel(order="F")])
        args: dict[str, Any] = {
            "p": p, "lbx": self._lbx, "ubx": self._ubx, "lbg": self._lbg, "ubg": self._ubg,
        }  # fmt: skip
        if self._w is None or start is not None:
            if start is None:
                cold = np.tile(np.concatenate([u_prev, x0]), self.ocp.N)
            else:  # (u_k, X_{k+1}) stage by stage from s_{k+1} = (X_{k+1}, u_k)
                cold = np.concatenate([start[0][:, NX:], start[0][:, :NX]], axis=1).ravel()
            args["x0"] = np.concatenate([cold, np.zeros(self._lbx.size - cold.size)])
            solver = self.solver
        else:
            assert self._lam_g is not None
            assert self._lam_x is not None
            args["x0"] = self._shift(self._w, ns)
            args["lam_x0"] = self._shift(self._lam_x, ns)
            args["lam_g0"] = self._shift(self._lam_g, ns)
            solver = self.warm_solver
        sol = solver(**args)
        stats = solver.stats()
        w = np.asarray(sol["x"], dtype=np.float64).ravel()
        message = str(stats.get("return_status", ""))
        ok = message in SUCCESS and bool(np.all(np.isfinite(w)))
        if ok:
            self._w = w
            self._lam_x = np.asarray(sol["lam_x"]).ravel()
            self._lam_g = np.asarray(sol["lam_g"]).ravel()
        return SolveResult(ok, w[:nu], int(stats.get("iter_count", 0)), message)

    def fallback(self) -> FloatArray | None:
        if self._w is None:
            return None
        ns, nu = self._stage, self.ocp.nu
        self._w = self._shift(self._w, ns)
        return self._w[:nu].copy()

    def currents_plan(self) -> FloatArray | None:
        if self._w is None:
            return None
        return self._w[: self._n_main].reshape(self.ocp.N, self._stage)[:, : self.ocp.nu].copy()

    def states_plan(self) -> FloatArray | None:
        if self._w is None:
            return None
        return self._w[: self._n_main].reshape(self.ocp.N, self._stage)[:, self.ocp.nu :].copy()


# --------------------------------------------------------------------------------------------
# Gauss–Newton real-time iteration with HPIPM
