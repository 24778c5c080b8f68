"""The real-time iteration: one Gauss–Newton SQP step a tick, its QP by magrun's compiled kernel
around HPIPM or by CasADi's HPIPM interface, with the preparation split and the corrective and
checked steps."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.control.nmpc.backend import Backend, SolveResult, descend
from magrun.control.nmpc.config import DIVERGING, KERNEL_MU0, NON_FINITE, NP, NX, Iterate
from magrun.control.nmpc.problem import OCP
from magrun.control.rti_kernel import RTIKernel, build_kernel

FloatArray = NDArray[np.float64]


class RTISolver(Backend):
    """Gauss–Newton SQP on the stage-wise problem, one structured QP (HPIPM) per tick.

    QP variables, in HPIPM's order: [v₀, s₁, v₁, s₂, …, v_{N−1}, s_N] (s₀ is fixed, so stage 0
    has no state), with sₖ = (Xₖ, u_{k−1}) and vₖ = uₖ − u_{k−1}; constraints: the
    linearised dynamics gaps only; the cost's Gauss–Newton Hessian JᵀJ and gradient Jᵀr.

    Two ways to the same QP (``NMPCConfig.rti_qp``): the compiled kernel
    (:mod:`magrun.control.rti_kernel`; default) linearises every stage and fills HPIPM's
    stage structures in C, and splits a tick into :meth:`prepare` (before the measurement,
    stage 0 linearised at the predicted start) and the feedback in :meth:`solve` (the
    measured start embedded, the QP solved). Without it, one compiled CasADi function
    assembles the whole sparse QP around the iterate and CasADi's HPIPM interface solves it,
    everything at the measurement.
    """

    def __init__(self, ocp: OCP) -> None:
        self.ocp = ocp
        cfg, N, nu = ocp.config, ocp.N, ocp.nu
        ns = NX + nu
        self.ns, self.nz = ns, nu + (N - 1) * (ns + nu) + ns
        # one stage: s = (X, u_prev), v = Δu; next state, its Jacobians, residuals, Jacobians
        s = ca.SX.sym("s", ns)
        v = ca.SX.sym("v", nu)
        ref = ca.SX.sym("par", NP)
        X, up = s[:NX], s[NX:]
        u = up + v
        s_next = ca.vertcat(ocp.step_scaled(X, u), u)
        # the tracking residuals, and the soft constraints' weighted gaps g ≥ 0: with
        # soft_constraints="slack" the kernel puts the gaps in the QP as linearised
        # inequalities with slacks; with "penalty" (and in CasADi's QP) they are residuals
        # min(0, g) in the cost, the same optimum (rti_hpipm.c says how the two differ)
        pose = ocp.pose_residual["stage"](X, ref)
        soft = ca.vertcat(ocp.corridor(X, ref), ocp.heading(X, u))
        currents = ca.vertcat(
            np.sqrt(cfg.r_current) * u, np.sqrt(cfg.s_current_change) * v, ocp.uncertainty(X, u)
        )
        r_all = ca.vertcat(pose, soft, currents)
        rN_all = ca.vertcat(ocp.pose_residual["terminal"](X, ref), ocp.corridor(X, ref))
        if cfg.soft_constraints == "slack":
            r, rN = ca.vertcat(pose, currents), ocp.pose_residual["terminal"](X, ref)
            g, gN = ocp.soft_gaps(X, u, ref), ocp.soft_gaps(X, None, ref)
        else:
            r, rN, g, gN = r_all, rN_all, ca.SX(0, 1), ca.SX(0, 1)

        def kernel_functions() -> tuple[ca.Function, ca.Function]:
            # common subexpressions: the heading's derivatives repeat the field's derivatives
            # the dynamics' Jacobian already has. Built only where the compiled cache does
            # not know the kernel yet (0.1-1.3 s: magrun.compiled)
            stage = ca.Function(
                "rti_stage", [s, v, ref],
                [s_next, ca.jacobian(s_next, s), ca.jacobian(s_next, v), r, ca.jacobian(r, s),
                 ca.jacobian(r, v), g, ca.jacobian(g, s), ca.jacobian(g, v)],
                {"cse": True},
            )  # fmt: skip
            terminal = ca.Function(
                "rti_terminal", [s, ref], [rN, ca.jacobian(rN, s), gN, ca.jacobian(gN, s)]
            )
            return stage, terminal

        problem = ca.Function("rti_problem", [s, v, ref], [s_next, r, g, rN, gN])
        self.kernel = self._kernel(kernel_functions, problem, r.shape[0], rN.shape[0],
                                   g.shape[0], gN.shape[0])  # fmt: skip
        self.robust_retries = 0
        self.relinearised = 0  # prepared ticks linearised again at the measurement
        self.embedded = 0  # ticks whose feedback phase used the preparation
        self.reset()
        if self.kernel is not None:
            return

        stage = ca.Function(
            "rti_stage",
            [s, v, ref],
            [s_next, ca.jacobian(s_next, s), ca.jacobian(s_next, v), r_all,
             ca.jacobian(r_all, s), ca.jacobian(r_all, v)],
            {"cse": True},
        )  # fmt: skip
        terminal = ca.Function("rti_terminal", [s, ref], [rN_all, ca.jacobian(rN_all, s)])

        # the whole QP, in MX over the stage function mapped along the horizon
        z = ca.MX.sym("z", self.nz)
        s0 = ca.MX.sym("s0", ns)
        refs = ca.MX.sym("par", NP, N + 1)
        S, V = self._split(z)  # S: s₁ … s_N (ns × N), V: v₀ … v_{N−1} (nu × N)
        S_from = ca.horzcat(s0, S[:, : N - 1])
        fk, Ak, Bk, rk, Jsk, Jvk = stage.map(N)(S_from, V, refs[:, :N])
        gaps = fk - S  # dynamics defects, ns × N
        rT, JT = terminal(S[:, N - 1], refs[:, N])
        H_blocks, g_blocks, A_rows = [], [], []
        eye = ca.MX.eye(ns)
        # 1e-9 keeps H positive definite along the unweighted velocities; the step damping
        # adds its proximal term (module doc, "Step damping")
        reg = 1e-9 + cfg.step_damping
        for k in range(N):
            Jv = Jvk[:, k * nu : (k + 1) * nu]
            rr = rk[:, k]
            Jk = Jv if k == 0 else ca.horzcat(Jsk[:, k * ns : (k + 1) * ns], Jv)
            H_blocks.append(ca.mtimes(Jk.T, Jk) + reg * ca.MX.eye(Jk.shape[1]))
            g_blocks.append(ca.mtimes(Jk.T, rr))
        H_blocks.append(ca.mtimes(JT.T, JT) + reg * eye)
        g_blocks.append(ca.mtimes(JT.T, rT))
        # gap rows: [A_k B_k −I] on (s_k, v_k, s_{k+1}); stage 0 has only v₀
        col = 0
        for k in range(N):
            Bblock = Bk[:, k * nu : (k + 1) * nu]
            if k == 0:
                left = Bblock
                width = nu
            else:
                left = ca.horzcat(Ak[:, k * ns : (k + 1) * ns], Bblock)
                width = ns + nu
            row = [ca.MX(ns, col), left, -eye, ca.MX(ns, self.nz - col - width - ns)]
            A_rows.append(ca.horzcat(*[b for b in row if b.shape[1] > 0]))
            col += width
        H = ca.diagcat(*H_blocks)
        g = ca.vertcat(*g_blocks)
        A = ca.vertcat(*A_rows)
        b = -ca.vec(gaps)  # A Δz = −gap
        lb, ub = self._bounds()
        qp = ca.Function(
            "rti_qp", [z, s0, refs], [H, g, A, b, lb - z, ub - z],
            ["z", "s0", "ref"], ["H", "g", "A", "b", "lbx", "ubx"],
        )  # fmt: skip
        self.qp_data = ocp.maybe_compiled(qp)
        opts: dict[str, Any] = {
            "N": N,
            "nx": [0] + [ns] * N,
            "nu": [nu] * N + [0],
            "ng": [0] * (N + 1),
            "error_on_fail": False,
            # HPIPM bounds every variable; ±1e8 for "none" stalls its interior point method,
            # ±1e4 (mm/s, rad/s: far beyond anything reachable) converges in ~5 iterations
            "inf": 1e4,
            "hpipm": {"iter_max": 50, "res_g_max": 1e-8, "res_b_max": 1e-8, "res_d_max": 1e-8,
                      "res_m_max": 1e-8, **cfg.hpipm},
        }  # fmt: skip
        structure = {"h": H.sparsity(), "a": A.sparsity()}
        # HPIPM's "speed_abs" preset first (no iterative refinement, and no residuals
        # evaluated at each interior-point iteration): faster per QP than the default and
        # the "speed" presets with the same closed loop (BENCHMARKS.md); it can stop short
        # (minimum step length) where the default one does not, e.g. started on an active
        # wall bound, so a QP it fails is solved again with the default preset
        # (``robust_retries`` counts them)
        fast = {**opts, "hpipm": {"mode": "speed_abs", **opts["hpipm"]}}
        self.qp_solver = ca.conic("rti_hpipm", "hpipm", structure, fast)
        self.qp_robust = ca.conic("rti_hpipm_robust", "hpipm", structure, opts)

    #: HPIPM's options that the kernel takes from ``NMPCConfig.hpipm`` (CasADi's names), with
    #: ``iter_max`` and ``mu0``
    KERNEL_TOLERANCES = ("res_g_max", "res_b_max", "res_d_max", "res_m_max")

    def _kernel(
        self, functions: Callable[[], tuple[ca.Function, ca.Function]], problem: ca.Function,
        n_r: int, n_rt: int, n_g: int, n_gt: int,
    ) -> RTIKernel | None:  # fmt: skip
        """The compiled kernel (:mod:`magrun.control.rti_kernel`), or None for CasADi's QP."""
        ocp, cfg = self.ocp, self.ocp.config
        if cfg.rti_qp != "direct" or not cfg.compile:
            return None
        nu = ocp.nu
        dims = {"N": ocp.N, "NS": self.ns, "NU": nu, "NR": n_r, "NRT": n_rt, "NP": NP,
                "NB": 2 + nu, "NG": n_g, "NGT": n_gt,
                "NGH": int(ocp.has_heading and n_g > 0)}  # fmt: skip
        heading = ocp.heading_residual if ocp.has_heading else None
        library = build_kernel(functions, problem, heading, ocp.step_scaled, dims)
        if library is None:
            return None
        hp = {"iter_max": 50, **dict.fromkeys(self.KERNEL_TOLERANCES, 1e-08), "mu0": KERNEL_MU0,
              **cfg.hpipm}  # fmt: skip
        bounded = np.concatenate([[0, 1], NX + np.arange(nu)])
        upper = np.concatenate([[ocp.pos_max] * 2, np.ones(nu)])
        tolerances = tuple(float(hp[k]) for k in (*self.KERNEL_TOLERANCES, "mu0"))
        kernel = RTIKernel(
            library, dims, np.broadcast_to(ocp.du_max, (nu,)), bounded, -upper, upper,
            tolerances, int(hp["iter_max"]),
        )  # fmt: skip
        if cfg.step_damping:
            kernel.set_damping(cfg.step_damping)
        return kernel

    def _split(self, z: Any) -> tuple[Any, Any]:
        """(states s₁ … s_N as columns, controls v₀ … v_{N−1} as columns) of a QP vector."""
        N, nu, ns = self.ocp.N, self.ocp.nu, self.ns
        v0 = z[:nu]
        rest = z[nu : nu + (N - 1) * (ns + nu)]
        blocks = ca.reshape(rest, ns + nu, N - 1)
        S = ca.horzcat(blocks[:ns, :], z[-ns:])
        V = ca.horzcat(v0, blocks[ns:, :])
        return S, V

    def _bounds(self) -> tuple[FloatArray, FloatArray]:
        ocp, nu, N = self.ocp, self.ocp.nu, self.ocp.N
        v_lb = np.full(nu, -ocp.du_max)
        s_lb = np.concatenate([[-ocp.pos_max] * 2, [-np.inf] * 4, np.full(nu, -1.0)])
        lb = np.concatenate([v_lb] + [np.concatenate([s_lb, v_lb])] * (N - 1) + [s_lb])
        return lb, -lb

    # -- iterate layout helpers (NumPy) ----------------------------------------------------

    def _pack(self, S: FloatArray, V: FloatArray) -> FloatArray:
        """States (N, ns) and controls (N, nu) into the QP vector."""
        parts = [V[0]]
        for k in range(1, self.ocp.N):
            parts += [S[k - 1], V[k]]
        parts.append(S[-1])
        return np.concatenate(parts)

    def _unpack(self, z: FloatArray) -> Iterate:
        N, nu, ns = self.ocp.N, self.ocp.nu, self.ns
        mid = z[nu : nu + (N - 1) * (ns + nu)].reshape(N - 1, ns + nu)
        S = np.vstack([mid[:, :ns], z[-ns:]])
        V = np.vstack([z[:nu], mid[:, ns:]])
        return S, V

    def reset(self) -> None:
        self._z: FloatArray | None = None
        self._has_plan = False  # the kernel holds a plan
        self._restart = False  # the last tick failed: the next starts afresh (module doc)
        self._aligned = False  # ... already moved on to the coming tick
        self._prepared: tuple[FloatArray, FloatArray] | None = None  # (par, s_lin)
        self._plan: FloatArray | None = None  # the kernel's last plan s₁ … s_N

    def prepare(self, s_lin: FloatArray, par: FloatArray) -> bool:
        """The preparation phase for the coming tick (kernel only): the plan moved on one
        stage and linearised there, stage 0 at the predicted start ``s_lin`` = (x, u_prev),
        scaled. False where there is nothing to prepare (no plan yet, or CasADi's QP)."""
        k = self.kernel
        if k is None or not self._has_plan or self._restart:
            return False
        if not self._aligned:
            k.shift()
            self._aligned = True
        if not k.prepare(par, s_lin):
            self._prepared = None
            return False
        self._prepared = (par[:, 1:].copy(), np.array(s_lin, dtype=np.float64))
        return True

    def _solve_kernel(self, k: RTIKernel, x0: FloatArray, u_prev: FloatArray,
                      par: FloatArray, start: Iterate | None) -> SolveResult:  # fmt: skip
        cfg = self.ocp.config
        s0 = np.concatenate([x0, u_prev])
        prepared = self._prepared
        self._prepared = None
        # stage 0's parameters do not reach the QP (its residuals that use them depend on
        # X_0 alone, which is given), so a preparation holds when the others and u_prev agree
        ready = (
            prepared is not None
            and np.array_equal(prepared[1][NX:], u_prev)
            and np.array_equal(prepared[0], par[:, 1:])
        )
        if not self._has_plan or self._restart or start is not None:
            # cold: from start, or holding the currents at rest at x0; to convergence (after
            # a failed tick too: the plan it leaves was linearised where the robot no longer is)
            k.set_iterate(*(start if start is not None else self._held(s0)))
            if cfg.step_check:
                return self._descend_kernel(k, x0, u_prev, par)
            budget = max(cfg.first_tick_iterations, cfg.iterations)
            ready = False
        else:
            if not self._aligned:
                k.shift()
            budget = cfg.iterations
        self._aligned = True
        self.embedded += ready
        iterations, corrections = 0, cfg.corrective_iterations
        while iterations < budget:
            embedded = ready
            if not ready and not k.prepare(par, s0):
                return self._failed(iterations + 1, NON_FINITE)
            ready = False
            damped = corrections < cfg.corrective_iterations and cfg.corrective_step < 1.0
            if damped or cfg.step_check:
                before = k.iterate()
            fb = k.feedback(s0, cfg.max_embedding_defect if embedded else np.inf)
            if fb.status == -2:
                # the measurement is too far from the prediction for the linearisation there:
                # linearised at the measurement instead, as an unprepared tick
                self.relinearised += 1
                if not k.prepare(par, s0):
                    return self._failed(iterations + 1, NON_FINITE)
                fb = k.feedback(s0)
            iterations += 1
            if fb.status != 0:
                return self._failed(iterations, f"HPIPM status {fb.status}")
            if cfg.step_check and iterations == 1:
                objective, plain = self._objective(x0, u_prev, par), k.iterate()
                if objective(plain[1]) > DIVERGING * objective(before[1]):
                    k.set_iterate(*before)  # the step is diverging: descend instead
                    return self._descend_kernel(k, x0, u_prev, par, plain)
            if damped:  # a corrective iteration: a damped step (module doc)
                (S0, V0), (S1, V1) = before, k.iterate()
                a = cfg.corrective_step
                k.set_iterate(S0 + a * (S1 - S0), V0 + a * (V1 - V0))
                if self.ocp.has_heading:
                    u0 = u_prev + V0[0] + a * (V1[0] - V0[0])  # the damped first currents
                    fb = fb._replace(heading_residual=float(self.ocp.heading_check(x0, u0)))
            if fb.step < cfg.step_tolerance:
                break
            if (
                iterations == budget and corrections > 0 and self.ocp.has_heading
                and fb.heading_residual < -cfg.corrective_sag * self.ocp.heading_scale
            ):  # fmt: skip
                corrections -= 1
                budget += 1
        return self._solved(k, u_prev, iterations)

    def _held(self, s0: FloatArray) -> Iterate:
        """The plan that holds the currents with the robot at rest at ``s0``'s pose."""
        return np.tile(s0, (self.ocp.N, 1)), np.zeros((self.ocp.N, self.ocp.nu))

    def _objective(
        self, x0: FloatArray, u_prev: FloatArray, par: FloatArray
    ) -> Callable[[FloatArray], float]:
        """The objective of a plan's current steps V (N, nu) from this tick's start."""

        def objective(V: FloatArray) -> float:
            value = float(self.ocp.objective(x0, u_prev, par, (u_prev + np.cumsum(V, 0)).T))
            return value if math.isfinite(value) else math.inf  # NaN: no better than any

        return objective

    def _solved(self, k: RTIKernel, u_prev: FloatArray, iterations: int) -> SolveResult:
        self.robust_retries = k.retries
        self._has_plan, self._aligned, self._restart = True, False, False
        S, V = k.iterate()
        self._plan = S
        return SolveResult(True, u_prev + V[0], iterations, "SUCCESS")

    def _descend_kernel(
        self, k: RTIKernel, x0: FloatArray, u_prev: FloatArray, par: FloatArray,
        plain: Iterate | None = None,
    ) -> SolveResult:  # fmt: skip
        """The kernel's iterate descended (:func:`descend`). Where no step is kept and a QP
        fails, a real-time tick keeps its ``plain`` step (S, V) as the unchecked iteration
        would; a first tick fails."""
        s0 = np.concatenate([x0, u_prev])
        base = self.ocp.config.step_damping

        def step(mu: float) -> tuple[str, float]:
            k.set_damping(mu)
            if not k.prepare(par, s0):
                return NON_FINITE, math.inf
            fb = k.feedback(s0)
            return ("" if fb.status == 0 else f"HPIPM status {fb.status}"), fb.step

        try:
            iterations, _, kept, error = descend(
                self._objective(x0, u_prev, par), k.iterate, k.set_iterate, step, self.ocp.config
            )
        finally:
            k.set_damping(base)
        if error and not kept:
            if plain is None:
                return self._failed(iterations, error)
            k.set_iterate(*plain)
        return self._solved(k, u_prev, iterations)

    def _failed(self, iterations: int, message: str) -> SolveResult:
        """A kernel tick that failed. A trial's first tick leaves no plan; a later one leaves
        the plan moved on to this tick, whose next currents :meth:`fallback` returns."""
        self.robust_retries = self.kernel.retries if self.kernel is not None else 0
        self._restart = self._has_plan
        return SolveResult(False, np.zeros(self.ocp.nu), iterations, message)

    def solve(
        self, x0: FloatArray, u_prev: FloatArray, par: FloatArray, start: Iterate | None = None
    ) -> SolveResult:
        if self.kernel is not None:
            if start is None:
                return self._solve_kernel(self.kernel, x0, u_prev, par, None)
            kept = self.kernel.iterate()  # what fallback() moves on if this fails too
            result = self._solve_kernel(self.kernel, x0, u_prev, par, start)
            if not result.ok:
                self.kernel.set_iterate(*kept)
            return result
        cfg = self.ocp.config
        s0 = np.concatenate([x0, u_prev])
        if self._z is None or start is not None:
            # cold: from start, or holding the currents at rest at x0; to convergence
            z = self._pack(*(start if start is not None else self._held(s0)))
            if cfg.step_check:
                return self._descend_casadi(z, x0, u_prev, par)
            budget = max(cfg.first_tick_iterations, cfg.iterations)
        else:
            z = self._shifted(self._z)
            budget = cfg.iterations
        iterations, message = 0, ""
        corrections = cfg.corrective_iterations
        while iterations < budget:
            iterations += 1
            step, message = self._qp_step(z, s0, par, 0.0)
            if step is None:
                return SolveResult(False, np.zeros(self.ocp.nu), iterations, message)
            if cfg.step_check and iterations == 1:
                objective = self._objective(x0, u_prev, par)
                if objective(self._unpack(z + step)[1]) > DIVERGING * objective(
                    self._unpack(z)[1]
                ):  # the step is diverging: descend instead
                    return self._descend_casadi(z, x0, u_prev, par, z + step)
            if corrections < cfg.corrective_iterations:  # corrective: damped (module doc)
                step = cfg.corrective_step * step
            z = z + step
            if np.max(np.abs(step)) < cfg.step_tolerance:
                break
            if iterations == budget and corrections > 0 and self._heading_sagged(x0, z, u_prev):
                # the linearisation did not see the heading residual (it was inactive there)
                # and the step went well past it: once more, from where it is active
                corrections -= 1
                budget += 1
        self._z = z
        _, V = self._unpack(z)
        return SolveResult(True, u_prev + V[0], iterations, message)

    def _qp_step(
        self, z: FloatArray, s0: FloatArray, par: FloatArray, extra_damping: float
    ) -> tuple[FloatArray | None, str]:
        """CasADi's QP around ``z`` (its Hessian damped by ``extra_damping`` more than the
        configured μ) solved: (the step, HPIPM's message), or (None, why not)."""
        H, g, A, b, lbx, ubx = self.qp_data(z, s0, par)
        # a non-finite state or model reaches the gradient and the gaps (H alone cannot be)
        if not (np.all(np.isfinite(np.asarray(g))) and np.all(np.isfinite(np.asarray(b)))):
            return None, NON_FINITE
        if extra_damping:  # the diagonal is in H's pattern (the regularisation)
            H = H + extra_damping * ca.DM.eye(H.shape[0])
        qp = {"h": H, "g": g, "a": A, "lba": b, "uba": b, "lbx": lbx, "ubx": ubx}
        try:
            sol = self.qp_solver(**qp)
            stats = self.qp_solver.stats()
            if not stats.get("success", False):
                self.robust_retries += 1
                sol = self.qp_robust(**qp)
                stats = self.qp_robust.stats()
        except RuntimeError as exc:  # an ill-posed QP (CasADi's checks)
            return None, str(exc)[-200:]
        message = str(stats.get("return_status", ""))
        step = np.asarray(sol["x"], dtype=np.float64).ravel()
        if not stats.get("success", False) or not np.all(np.isfinite(step)):
            return None, message or "failed"
        return step, message

    def _descend_casadi(
        self, z: FloatArray, x0: FloatArray, u_prev: FloatArray, par: FloatArray,
        plain: FloatArray | None = None,
    ) -> SolveResult:  # fmt: skip
        """The plan ``z`` descended (:func:`descend`) with CasADi's QP; ``plain``: as in
        :meth:`_descend_kernel`."""
        s0 = np.concatenate([x0, u_prev])
        base = self.ocp.config.step_damping
        work = [z]

        def step(mu: float) -> tuple[str, float]:
            dz, message = self._qp_step(work[0], s0, par, mu - base)
            if dz is None:
                return message, math.inf
            work[0] = work[0] + dz
            return "", float(np.max(np.abs(dz)))

        def restore(S: FloatArray, V: FloatArray) -> None:
            work[0] = self._pack(S, V)

        iterations, _, kept, error = descend(
            self._objective(x0, u_prev, par), lambda: self._unpack(work[0]), restore, step,
            self.ocp.config,
        )  # fmt: skip
        if error and not kept:
            if plain is None:
                return SolveResult(False, np.zeros(self.ocp.nu), iterations, error)
            work[0] = plain
        self._z = work[0]
        _, V = self._unpack(work[0])
        return SolveResult(True, u_prev + V[0], iterations, "SUCCESS")

    def _heading_sagged(self, x0: FloatArray, z: FloatArray, u_prev: FloatArray) -> bool:
        """Whether the first currents of plan ``z`` put the field along the moment at the
        start state more than ``corrective_sag`` × B_min below B_min."""
        if not self.ocp.has_heading:
            return False
        _, V = self._unpack(z)
        r = float(self.ocp.heading_check(x0, u_prev + V[0]))
        return r < -self.ocp.config.corrective_sag * self.ocp.heading_scale

    def _shifted(self, z: FloatArray) -> FloatArray:
        S, V = self._unpack(z)
        return self._pack(np.vstack([S[1:], S[-1:]]), np.vstack([V[1:], np.zeros_like(V[:1])]))

    def fallback(self) -> FloatArray | None:
        if self.kernel is not None:
            if not self._has_plan:
                return None
            # the failed tick moved the plan on already (or a preparation did)
            if not self._aligned:
                self.kernel.shift()
            self._aligned = False
            S, _ = self.kernel.iterate()
            self._plan = S
            return S[0, NX:].copy()
        if self._z is None:
            return None
        self._z = self._shifted(self._z)
        S, _ = self._unpack(self._z)
        return S[0, NX:].copy()  # u₀ of the shifted plan = u₁ of the old one

    def _plan_states(self) -> FloatArray | None:
        """s₁ … s_N of the last plan, (N, ns)."""
        if self.kernel is not None:  # as planned (a preparation may have moved the iterate on)
            return self._plan if self._has_plan else None
        return None if self._z is None else self._unpack(self._z)[0]

    def currents_plan(self) -> FloatArray | None:
        S = self._plan_states()
        return None if S is None else S[:, NX:].copy()  # s_{k+1} holds u_k

    def states_plan(self) -> FloatArray | None:
        S = self._plan_states()
        return None if S is None else S[:, :NX].copy()
