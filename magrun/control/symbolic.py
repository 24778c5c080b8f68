"""The robot's dynamics as CasADi expressions, for the NMPC: :func:`magrun.robot.discrete_step`
run over CasADi's ``sin``/``cos``/``exp`` (the kernel is written once over an ``ops``
namespace, see :mod:`magrun.robot`). Kept out of :mod:`magrun.robot` so that loading robots
(protocol validation, the simulated rig, the recorder) never imports CasADi.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import casadi as ca

from magrun.robot import RobotParams, aligned_substep, discrete_step

Expr = Any

CASADI_OPS = SimpleNamespace(
    sin=ca.sin, cos=ca.cos, exp=ca.exp, atan2=ca.atan2, sqrt=ca.sqrt, fmin=ca.fmin, fmax=ca.fmax
)


def casadi_step_function(
    params: RobotParams,
    field_and_gradient: Callable[[Expr, Expr], tuple[Expr, Expr]],
    n_currents: int,
    dt: float,
    substeps: int = 2,
    name: str = "step",
    substep: Callable[..., tuple[Any, ...]] = aligned_substep,
) -> ca.Function:
    """``name(x[6], I[n]) -> x_next[6]``: :func:`discrete_step` as an SX CasADi function.

    ``field_and_gradient(p, I)`` is a field model's ``casadi_field_and_gradient``.
    """
    x = ca.SX.sym("x", 6)
    I = ca.SX.sym("I", n_currents)

    def field(px: Expr, py: Expr) -> tuple[Expr, Expr]:
        B, G = field_and_gradient(ca.vertcat(px, py), I)
        return [B[0], B[1]], [[G[0, 0], G[0, 1]], [G[1, 0], G[1, 1]]]

    nxt = discrete_step(
        tuple(x[i] for i in range(6)), field, params, dt, substeps, CASADI_OPS, substep
    )
    return ca.Function(name, [x, I], [ca.vertcat(*nxt)], ["x", "I"], ["x_next"])
