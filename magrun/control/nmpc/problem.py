"""The optimal control problem, described once: the scaled dynamics, the costs' residuals and the
soft constraints (heading-stable field, corridor) as CasADi functions, shared by both solvers."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any, Protocol

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.compiled import compiled
from magrun.control.nmpc.config import N_PLANES, NP, NX, STATE_SCALE
from magrun.control.symbolic import CASADI_OPS
from magrun.field.model import PlanarFieldModel
from magrun.freespace import INACTIVE
from magrun.robot import aligned_substep, discrete_step

if TYPE_CHECKING:
    from magrun.control.nmpc.config import NMPCConfig
    from magrun.freespace import FreeSpace
    from magrun.robot import RobotParams

FloatArray = NDArray[np.float64]


class Description(Protocol):
    """What the problem is built from: the planner's settings, coils, robot and free space
    (:class:`~magrun.control.nmpc.planner.NMPC` holds them)."""

    config: NMPCConfig
    model: PlanarFieldModel
    robot: RobotParams
    free_space: FreeSpace | None
    n_currents: int
    max_current: float | FloatArray  # A
    max_change: float | FloatArray  # A per control period
    position_bound: float  # m
    min_aligned_field: float  # T
    channel_field_scale: FloatArray  # T/A per channel


class OCP:
    """The optimal control problem in scaled units: dynamics, residuals, bounds."""

    def __init__(self, nmpc: Description) -> None:
        cfg = nmpc.config
        self.config = cfg
        self.N = cfg.horizon
        self.nu = nu = nmpc.n_currents
        self.max_current = nmpc.max_current
        self.du_max = nmpc.max_change / nmpc.max_current  # slew bound on u per step
        self.pos_max = nmpc.position_bound / 1e-3  # mm
        scale = ca.DM(STATE_SCALE)
        X = ca.SX.sym("X", NX)  # scaled
        u = ca.SX.sym("u", nu)  # I / I_max
        # the field at the stage's start, shared by the dynamics and the heading residual
        B, G = nmpc.model.casadi_field_and_gradient(X[:2] * 1e-3, u * _scale(nmpc.max_current))
        Bl, Gl = [B[0], B[1]], [[G[0, 0], G[0, 1]], [G[1, 0], G[1, 1]]]
        X_si = X * scale
        nxt = discrete_step(
            tuple(X_si[i] for i in range(NX)), lambda _x, _y: (Bl, Gl), nmpc.robot, cfg.dt,
            cfg.substeps, CASADI_OPS, aligned_substep,
        )  # fmt: skip
        X_next = ca.vertcat(*nxt) / scale
        #: X_{k+1}(X_k, u_k), scaled
        self.step_scaled = ca.Function("nmpc_step", [X, u], [X_next], ["X", "u"], ["X_next"])
        # residuals, the cost is Σ |r|²: r = [√q (p − p_ref), √qθ wrap(θ − θ_ref)] for the
        # pose, [√R u, √S (u − u_prev)] for the currents, and the soft constraints'
        # √w min(0, g): the heading's on (X_k, u_k), the corridor's on X_k
        par = ca.SX.sym("par", NP)  # reference (mm, mm, rad), half-planes (nx, ny, c mm)
        self.pose_residual = {
            "stage": self._pose_residual(X, par, cfg.q_position, cfg.q_angle),
            "terminal": self._pose_residual(X, par, cfg.p_position, cfg.q_angle_terminal),
        }
        along = (ca.cos(X[2]) * B[0] + ca.sin(X[2]) * B[1]) * 1e3  # mT
        b_min = nmpc.min_aligned_field * 1e3
        required: Any = b_min
        if cfg.field_error > 0:
            # the field the model cannot vouch for: each channel's |b_i| I_i (mT) times the
            # error, in quadrature; the aligned field must dwarf it (module doc)
            limits = np.broadcast_to(np.asarray(nmpc.max_current, float), (nu,))
            per_channel = ca.DM(nmpc.channel_field_scale * 1e3 * limits)  # mT at u = 1
            spread = ca.sumsqr(u * per_channel)
            ratio = cfg.field_error / math.tan(cfg.field_heading_error)
            required = ca.sqrt(b_min**2 + ratio**2 * spread)
        # the weighted gaps √w g (≥ 0 where satisfied); the residuals are min(0, ·) of them
        self.heading_gap = ca.Function(
            "heading_gap", [X, u], [np.sqrt(cfg.heading_weight) * (along - required)]
        )
        self.heading_residual = ca.Function(
            "heading_residual", [X, u], [ca.fmin(0, self.heading_gap(X, u))]
        )
        self.has_heading = cfg.heading_weight > 0
        self.has_uncertainty = cfg.position_uncertainty > 0
        if self.has_uncertainty:
            self.uncertainty_residual = self._uncertainty_residual(nmpc, X, u, G, along, b_min)
        #: the heading residual at B_∥ = 0 (a violation of B_min)
        self.heading_scale = np.sqrt(cfg.heading_weight) * b_min
        self.heading_check = self.maybe_compiled(self.heading_residual)
        fs = nmpc.free_space
        half_axis = (fs.half_axis if fs is not None else 0.0) / 1e-3  # mm
        ends = [X[:2] + e * ca.vertcat(ca.cos(X[2]), ca.sin(X[2])) for e in (-half_axis, half_axis)]
        gaps = [
            np.sqrt(cfg.corridor_weight)
            * (par[3 + 3 * j] * e[0] + par[4 + 3 * j] * e[1] - par[5 + 3 * j])
            for j in range(N_PLANES)
            for e in ends
        ]
        self.corridor_gap = ca.Function("corridor_gap", [X, par], [ca.vertcat(*gaps)])
        self.corridor_residual = ca.Function(
            "corridor_residual", [X, par], [ca.fmin(0, ca.vertcat(*gaps))]
        )
        self.has_corridor = fs is not None and fs.critical is not None and cfg.corridor_weight > 0

    @staticmethod
    def _pose_residual(X: Any, par: Any, qp: float, qa: float) -> ca.Function:
        d = X[2] - par[2]
        r = ca.vertcat(
            np.sqrt(qp) * (X[:2] - par[:2]), np.sqrt(qa) * ca.atan2(ca.sin(d), ca.cos(d))
        )
        return ca.Function("pose_residual", [X, par], [r])

    @staticmethod
    def _uncertainty_residual(
        nmpc: Description, X: Any, u: Any, G: Any, along: Any, b_min: float
    ) -> ca.Function:
        """What the estimate's position error costs (module doc, "Position uncertainty"): an
        error e turns the field the robot feels by (m̂⊥ · G e) / b(B_∥) and changes the pull
        on it, Gᵀm̂, by ∂(Gᵀm̂)/∂p e, its velocity by |m|/d times that over the frame interval
        T_f; for e of σ per axis, weighed as qθ and Qp weigh a heading and a position error."""
        cfg = nmpc.config
        sigma_mm = cfg.position_uncertainty / 1e-3
        heading = ca.vertcat(ca.cos(X[2]), ca.sin(X[2]))
        across = ca.vertcat(-ca.sin(X[2]), ca.cos(X[2]))
        # B_∥ floored smoothly and one-sided: → B_∥ above B_min, → 0 for a field against the
        # moment (whose equilibrium a turn of any size overturns)
        floor = (along + ca.sqrt(along**2 + b_min**2)) / 2
        turn = ca.mtimes(G[:2, :2].T, across) / floor  # rad per mm
        stiffness = ca.jacobian(ca.mtimes(G[:2, :2].T, heading), X[:2]) * 1e3  # T/m² (X: mm)
        robot = nmpc.robot
        mobility = robot.moment / min(robot.drag_parallel, robot.drag_perpendicular)  # m²/(T s)
        drift = mobility * cfg.frame_interval * ca.vec(stiffness)  # mm per mm of error
        return ca.Function(
            "uncertainty_residual", [X, u],
            [sigma_mm * ca.vertcat(np.sqrt(cfg.q_angle) * turn, np.sqrt(cfg.q_position) * drift)],
        )  # fmt: skip

    def uncertainty(self, X: Any, u: Any) -> Any:
        """The position uncertainty's residuals of X and u, the field's turn (2) and the
        velocity's change (4); empty without it (``position_uncertainty`` = 0)."""
        return self.uncertainty_residual(X, u) if self.has_uncertainty else ca.DM.zeros(0, 1)

    def corridor(self, X: Any, par: Any) -> Any:
        """The corridor's residuals at state X (empty without a free space)."""
        return self.corridor_residual(X, par) if self.has_corridor else ca.DM.zeros(0, 1)

    def heading(self, X: Any, u: Any) -> Any:
        """The heading-stable field's residual of X and u (empty when switched off)."""
        return self.heading_residual(X, u) if self.has_heading else ca.DM.zeros(0, 1)

    def soft_gaps(self, X: Any, u: Any | None, par: Any) -> Any:
        """The weighted gaps of a stage's soft constraints (heading when ``u`` is given, first;
        the corridor), in X's symbolic type (SX or MX): a slack s ≥ 0 per row, gap + s ≥ 0
        and cost s², is the same penalty as the residuals min(0, gap) and smooth for an
        exact Hessian (IPOPT; the RTI kernel's QP with soft_constraints="slack")."""
        parts = []
        if u is not None and self.has_heading:
            parts.append(self.heading_gap(X, u))
        if self.has_corridor:
            parts.append(self.corridor_gap(X, par))
        return ca.vertcat(*parts) if parts else type(X)(0, 1)

    def maybe_compiled(self, function: ca.Function) -> ca.Function:
        return compiled(function) if self.config.compile else function

    def stage_parameters(self, ref: FloatArray, planes: FloatArray | None = None) -> FloatArray:
        """(N+1, 3) SI reference poses and (N+1, N_PLANES, 3) half-planes (mm; default: none)
        to the (NP, N+1) scaled parameter columns."""
        out = np.empty((NP, self.N + 1))
        out[:3] = ref.T
        out[:2] /= 1e-3
        if planes is None:
            planes = np.empty((self.N + 1, N_PLANES, 3))
            planes[:] = INACTIVE
        out[3:] = planes.reshape(self.N + 1, -1).T
        return out

    def cost(self, x0: FloatArray, u_prev: FloatArray, par: FloatArray, u: FloatArray) -> float:
        """The objective for currents u (N, nu), states simulated from x0 (scaled), stage
        parameters ``par`` (:meth:`stage_parameters`)."""
        return float(self.objective(x0, u_prev, par, np.asarray(u, dtype=np.float64).T))

    @functools.cached_property
    def objective(self) -> ca.Function:
        """The problem's objective as one function of the currents,
        ``objective(x0, u_prev, par, U)`` with U (nu, N) scaled: every stage's and the
        terminal residuals squared, the states simulated from x0 under U (single shooting),
        each position held within the position bound.
        The checked steps' merit (module doc, "Checked steps")."""
        cfg, N = self.config, self.N
        x0, u_prev = ca.MX.sym("x0", NX), ca.MX.sym("u_prev", self.nu)
        par, U = ca.MX.sym("par", NP, N + 1), ca.MX.sym("u", self.nu, N)
        J: Any = 0
        X, before = x0, u_prev
        for k in range(N):
            u = U[:, k]
            if k > 0:
                J += ca.sumsqr(self.pose_residual["stage"](X, par[:, k]))
                J += ca.sumsqr(self.corridor(X, par[:, k]))
            J += ca.sumsqr(self.heading(X, u)) + ca.sumsqr(self.uncertainty(X, u))
            J += cfg.r_current * ca.sumsqr(u) + cfg.s_current_change * ca.sumsqr(u - before)
            X = self.step_scaled(X, u)
            # the plan's positions are bounded (a hard constraint); a simulated state past
            # the bound is held on it, where the field model is still defined
            X = ca.vertcat(ca.fmin(ca.fmax(X[:2], -self.pos_max), self.pos_max), X[2:])
            before = u
        J += ca.sumsqr(self.corridor(X, par[:, N]))
        J += ca.sumsqr(self.pose_residual["terminal"](X, par[:, N]))
        # the checked steps call it twice a tick. Compiled (cached), the MX graph's C calls
        # the stage functions' and runs as fast as the graph expanded to scalar operations
        # (82 against 84 us a call on the spine's problem) but compiles in 0.6 s, not 13 s
        # (gcc spends them allocating registers in one huge function); uncompiled, the
        # expanded graph is the faster (84 against 455 us in CasADi's virtual machine)
        objective = ca.Function("nmpc_objective", [x0, u_prev, par, U], [J])
        built = self.maybe_compiled(objective)
        return objective.expand() if built is objective else built


def channel_field_scale(model: PlanarFieldModel, n: int = 21) -> FloatArray:
    """Each channel's field per ampere, RMS over an n × n grid of the workspace box, T/A."""
    h = model.coils.workspace_half_width
    g = np.linspace(-h, h, n)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    unit = model.unit_field(grid)  # (n², channels, 2)
    return np.sqrt(np.mean(np.sum(unit**2, axis=-1), axis=0))


def _scale(limit: Any) -> Any:
    """The current scale in a CasADi product: a number, or a column of one per channel."""
    return float(limit) if np.ndim(limit) == 0 else ca.DM(np.asarray(limit, dtype=float))
