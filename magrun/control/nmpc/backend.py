"""What the two solvers share: their result, their interface, and the checked descent (module doc
of :mod:`magrun.control.nmpc`, "Checked steps")."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magrun.control.nmpc.config import (
    DAMPING_LEVELS,
    DESCENT_SLACK,
    NON_FINITE,
    Iterate,
    NMPCConfig,
)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SolveResult:
    ok: bool
    u0: FloatArray  # first currents, I / I_max
    iterations: int
    message: str


class Backend:
    def reset(self) -> None:
        raise NotImplementedError

    def prepare(self, s_lin: FloatArray, par: FloatArray) -> bool:
        """Work for the coming tick before its measurement; whether any was done."""
        return False

    def solve(
        self, x0: FloatArray, u_prev: FloatArray, par: FloatArray, start: Iterate | None = None
    ) -> SolveResult:
        """One tick's plan from scaled x0, the previous currents and the (NP, N+1) stage
        parameters (:meth:`OCP.stage_parameters`). With ``start`` (states s₁ … s_N and
        current steps v₀ … v_{N−1}, scaled) the solve starts cold from that plan instead of
        the last one."""
        raise NotImplementedError

    def fallback(self) -> FloatArray | None:
        """The previous plan's next currents (and shift that plan), or None without one."""
        raise NotImplementedError

    def currents_plan(self) -> FloatArray | None:
        """The last accepted plan's currents, shape (N, nu), scaled; None without one."""
        raise NotImplementedError

    def states_plan(self) -> FloatArray | None:
        """The last accepted plan's states X_1 … X_N, shape (N, 6), scaled; None without one."""
        raise NotImplementedError


# --------------------------------------------------------------------------------------------
# IPOPT reference


def descend(
    objective: Callable[[FloatArray], float],
    iterate: Callable[[], Iterate],
    restore: Callable[[FloatArray, FloatArray], None],
    step: Callable[[float], tuple[str, float]],
    config: NMPCConfig,
) -> tuple[int, int, int, str]:
    """Gauss–Newton steps from a plan toward convergence, each kept only where it lowers
    ``objective`` of the plan's current steps V (N, nu), else taken back (``restore(S, V)``)
    and the step damping raised tenfold, lowered again after each kept step (module doc,
    "Checked steps"). ``iterate()``: the plan (S, V); ``step(μ)``: one step with damping μ,
    returning '' or why it failed (the plan then unchanged), and the step's size (∞-norm).
    Up to ``first_tick_iterations`` steps, fewer where one at the configured damping is
    below ``step_tolerance``, or until a QP fails at the highest damping. Returns (steps,
    steps taken back, steps kept, '' or why the last step failed); the plan is the last
    kept one."""
    base = config.step_damping
    S, V = iterate()
    value, level, iterations, back, kept = objective(V), 0, 0, 0, 0
    while iterations < max(config.first_tick_iterations, config.iterations):
        error, size = step(_damping(base, level))
        iterations += 1
        if error == NON_FINITE:  # the plan itself: no damping mends that
            return iterations, back, kept, error
        if not error:
            S1, V1 = iterate()
            after = objective(V1)
            if after <= value + DESCENT_SLACK * abs(value):
                S, V, value, kept = S1, V1, after, kept + 1
                if level == 0 and size < config.step_tolerance:
                    break
                level = max(level - 1, 0)
                continue
            restore(S, V)  # taken back
        if level == DAMPING_LEVELS:  # no shorter step left to try
            return iterations, back, kept, error
        level += 1
        back += 1
    return iterations, back, kept, ""


def _damping(base: float, level: int) -> float:
    """The first tick's step damping at a level: the configured one at 0, then tenfold from
    max(10 × it, 1) (scaled units: the tracking weights are of order 1–10)."""
    return base if level == 0 else max(10.0 * base, 1.0) * 10.0 ** (level - 1)
