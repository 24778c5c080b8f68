"""The NMPC's configuration and constants (the module doc of :mod:`magrun.control.nmpc`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
#: a plan as the RTI iterates it: states s₁ … s_N (N, ns) and current steps v₀ … v_{N−1}
#: (N, nu), scaled
Iterate = tuple[FloatArray, FloatArray]


#: NLP scaling of the state: mm, mm, rad, mm/s, mm/s, rad/s
STATE_SCALE = np.array([1e-3, 1e-3, 1.0, 1e-3, 1e-3, 1.0])
SUCCESS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")
NX = 6
#: the kernel's fast HPIPM mode's initial barrier parameter (HPIPM's "speed_abs" default: 10).
#: The RTI's QPs are in steps from a plan shifted from the last, small and mostly inactive;
#: from 1e-2 HPIPM takes 3 interior-point iterations on the S (median) where it took 5
#: (docs/benchmarks.md); the robust mode, the retry, keeps its default
KERNEL_MU0 = 1e-2
NON_FINITE = "non-finite QP"
#: a step whose objective rises by at most this share is kept (rounding; "Checked steps")
DESCENT_SLACK = 1e-9
#: a real-time step that multiplies the objective of the plan it started from more than this
#: is diverging ("Checked steps")
DIVERGING = 2.0
#: the damping is raised at most this many times (up to 1e4 × the first; "Checked steps")
DAMPING_LEVELS = 5
#: m: how far inside the position bound a start outside it is planned from (:meth:`NMPC._start`)
OUTSIDE_START = 1e-3
#: corridor half-planes per stage (the critical boundary's; FreeSpace.corridor)
N_PLANES = 1
#: per-stage parameters: the reference pose (3, scaled) and the half-planes (nx, ny, c mm)
NP = 3 + 3 * N_PLANES


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
    # heading-stable fields: field along the moment ≥ B_min (T; None: the robot's own)
    min_aligned_field: float | None = None
    heading_weight: float = 100.0  # per mT² below B_min; 0 switches the term off
    # the coils' field-model error (module doc, "Field-model error"): each channel's field
    # is trusted to this fraction (1 σ, relative; 0: exactly) and the field along the moment
    # is kept ≥ field_error · s(I) / tan(field_heading_error), s the channels' fields' norm
    field_error: float = 0.0
    field_heading_error: float = math.radians(20.0)  # rad
    # the estimate's position error per axis, m (module doc, "Position uncertainty"): each
    # stage pays for the turn of the field and the change of the robot's velocity an error
    # of this size would cause; 0: the estimate's position is taken as exact
    position_uncertainty: float = 0.0
    # s: how long the estimate runs on the model between two measurements (the feedback's
    # frame interval; module doc, "Position uncertainty")
    frame_interval: float = 0.04
    # corridor (with a FreeSpace): the body's ends clear of the boundaries
    # per mm² of violation, critical boundary (the others get none: contact with them is
    # allowed, and resting on the far wall keeps the body off the critical one)
    corridor_weight: float = 100.0
    # m, from the critical boundary before the chance term: on the spine at 3 Hz, 2 mm, seeds
    # 1–3: 0.2 mm touched the anterior wall in 3 of 3 trials, 0.5 mm in none (1 of 7 with
    # seeds 4–7 too), 0.7 mm in 3 of 4 (pressing the body into the posterior wall)
    corridor_margin: float = 0.5e-3
    corridor_sigmas: float = 1.0  # κ: the critical margin grows by κ σ of the estimate ...
    corridor_share: float = 1.0  # ... by at most this share of the channel's free width
    # m/s: a start inside the margin is led out this fast (module doc, "Corridor"); bench
    # spine, 40 trials with the rest as shipped: least clearance 0.15 mm without, 0.43 with
    corridor_recovery: float = 2e-3
    substeps: int = 2
    solver: Literal["rti", "ipopt"] = "rti"
    compile: bool = True  # compile the stage functions / NLP callbacks to C (cached)
    # RTI: SQP iterations per tick (1 = real-time iteration) and on a trial's first tick
    iterations: int = 1
    first_tick_iterations: int = 30
    step_tolerance: float = 1e-8  # stop the first tick's iterations below this step (∞-norm)
    # RTI: extra iterations (at most) when the first currents leave the field along the moment
    # more than corrective_sag × B_min short of the heading term's bound, each a damped step
    # of corrective_step times the QP's (module doc, "Corrective iterations")
    corrective_iterations: int = 2
    corrective_sag: float = 0.1
    corrective_step: float = 1.0
    # RTI with a preparation: a measurement that the model linearised at the prediction maps
    # more than this far from the model itself (one step, ∞-norm in the scaled units: mm,
    # rad, mm/s, rad/s, I/I_max) is linearised afresh. On the paper rig's S it stays below
    # 1e-3 with exact feedback and below 0.12 (p99) under 2 mm noise at 3 and 25.5 Hz; a
    # three-coil system wobbling about its heading went to 1e3
    max_embedding_defect: float = 1.0
    # RTI: a Levenberg–Marquardt term μ/2 |step|² on every QP's step (scaled units; module
    # doc, "Step damping"); 0: full Gauss–Newton steps
    step_damping: float = 0.0
    # RTI: steps checked against the objective of the plan's currents (module doc, "Checked
    # steps"): the first tick keeps only steps that lower it, raising the damping where one
    # does not; a real-time step that more than doubles it over the plan it started from is
    # taken back and the tick descends as the first does. Two evaluations of the objective
    # a tick
    step_check: bool = False
    hpipm: dict[str, Any] = field(default_factory=dict)
    # RTI: the QP through magrun's compiled kernel around HPIPM ("direct", falling back to
    # "casadi" where it cannot be built) or through CasADi's HPIPM interface ("casadi")
    rti_qp: Literal["direct", "casadi"] = "direct"
    # RTI kernel: the soft constraints (heading-stable field, corridor) as linearised
    # inequalities with slacks in the QP ("slack"), or as residuals min(0, g) in the
    # Gauss–Newton cost ("penalty"; CasADi's QP always). The same optimum; one step of
    # "penalty" does not see a constraint inactive where it linearises and can plan straight
    # through it (module doc, "Soft constraints")
    soft_constraints: Literal["slack", "penalty"] = "penalty"
    # IPOPT
    max_iter: int = 100
    tol: float = 1e-6
    ipopt: dict[str, Any] = field(default_factory=dict)
