"""Nonlinear MPC that outputs coil currents directly (paper, Section II-C).

Over a horizon of N steps of Δt (defaults 20 and 40 ms), with decision variables the currents
I₀ … I_{N−1} and the predicted states X₁ … X_N (multiple shooting)::

    min   Σ_{k=0}^{N−1} [ e_{p,k}ᵀ Qp e_{p,k} + qθ e_{θ,k}² + I_kᵀ R I_k + ΔI_kᵀ S ΔI_k ]
          + e_{p,N}ᵀ P e_{p,N} + qθ,N e_{θ,N}²
    s.t.  X_{k+1} = f(X_k, I_k)                 robot.discrete_step (aligned sub-steps)
          |I_k| ≤ I_max,  |I_k − I_{k−1}| ≤ slew Δt   (I_{−1}: the currents applied last tick)
          |x_k|, |y_k| ≤ workspace half-width − margin   (k ≥ 1)
    soft: (m̂(θ_k) · B(p_k, I_k)) ≥ B_min           heading-stable fields   (k < N)
    soft: n_j,k · e ≥ c_j,k for both body ends e     corridor                (k ≥ 1)

with e_{p,k} = (x_k, y_k) − (x_k^d, y_k^d) and e_{θ,k} the wrapped angle error, written
``atan2(sin Δ, cos Δ)`` (the paper's ``((Δ + π) mod 2π) − π``, smooth for the solver). X₀ is
the estimate (its position projected into the workspace box).

Heading-stable fields
---------------------
The cost alone weighs pose and currents, and a field *against* the robot's moment holds a
heading as well as one along it: the torque m × B is zero both ways. But the anti-aligned
equilibrium is unstable: linearised, θ̇ = −(m B_∥ / d_r) δθ with B_∥ = m̂ · B the field along
the moment, so a tilt grows at m|B|/d_r (6–40 s⁻¹ for the drug-delivery capsule) where an
aligned field pulls it back at the same rate. Between fluoroscopy frames the plan's model says
the heading is held while the robot flips. Every plan therefore keeps B_∥ ≥ B_min, the robot's
``min_aligned_field`` (robots.yaml, where its derivation is written): at B_min a heading
error decays by a factor e within one frame period of the slowest fluoroscopy rate (3 Hz).

Field-model error
-----------------
B_min alone assumes the model's field is the coils' field. It is not quite: a coil a
millimetre from where the calibration put it, or a gain a few per cent off, makes each
channel's field wrong by a few per cent of itself, and the NMPC often holds the heading with
a small net field from large currents whose fields largely cancel (20–30 A per coil for
1–3 mT on the paper rig's spine delivery). The error then does not cancel: on the bench
preset (1 mm, 1° per coil, 2 % gains) the field the model predicts and the coils' differ by
7 % of the channels' fields in quadrature (median), which turned the field at the capsule by
20–90° where the aligned field was 1.2 mT. With ``field_error`` = ε > 0 (each channel's
field known to a fraction ε, independently) the field the model cannot vouch for has a
standard deviation of about ε s(I), with ``s(I)² = Σ_i (β_i I_i)²`` and β_i the channel's
field per ampere (RMS over the workspace, :func:`channel_field_scale`). It turns the robot
by about atan(ε s / B_∥), so the heading term asks for::

    B_∥ ≥ √(B_min² + (ε s(I) / tan δ)²)          δ = ``field_heading_error``

B_min where the currents are small, and where they are large a field along the moment that
dwarfs what the model does not know: the planner then prefers smaller currents, or a larger
aligned field, to a force bought with cancelling fields. With ε = 0 (the default) the term
is the plain B_∥ ≥ B_min.

Position uncertainty
--------------------
The model's field is evaluated at the estimate; the robot feels it where it is. A position
error e turns the field it feels by (m̂⊥ · G e) / B_∥ (G the field's gradient, m̂⊥ across
the moment) and changes its pull Gᵀm̂ by ∂(Gᵀm̂)/∂p e, so its velocity by |m|/d times that
(d the body's smaller drag). Little of either on a system whose field is uniform over
millimetres; but on three coils the NMPC holds headings with a field of about B_min whose
gradient turns it by 40° per 0.6 mm, and at 3 Hz with σ = 2 mm the robot then turned and
moved away from the model's prediction between frames, the filter followed the model, and
every trial lost the robot. With ``position_uncertainty`` = σ > 0 (per axis) each stage
adds to the cost what an error of σ would cost, to first order, weighed as qθ weighs a
heading error and Qp a position error over the frame interval T_f (``frame_interval``, the
time the estimate runs on the model alone)::

    σ √qθ Gᵀ m̂⊥ / b(B_∥)                        (two residuals, rad)
    σ √Qp |m|/d T_f vec ∂(Gᵀm̂)/∂p               (four residuals, mm)

with b(B_∥) = (B_∥ + √(B_∥² + B_min²)) / 2, a smooth one-sided floor: B_∥ where it is well
above B_min, toward 0 for a field against the moment, whose equilibrium any turn overturns
(with a floor symmetric in B_∥ a robot held against a background field rated as robust as
one held along it, and trials on ``three`` planned exactly that for their first 0.6 s).

so the plan prefers fields that are large against their gradient across the moment, and
pulls that change little over the estimate's error, where the estimate is uncertain. A
protocol's ``controller.position_uncertainty_mm: auto`` sets σ to twice the Kalman filter's
steady position σ just before a frame where the coils cannot hold the reference's heading
(:func:`magrun.trial.position_uncertainty`), 0 elsewhere, and T_f to the feedback's frame
interval. On ``tri`` (docs/systems.md) at 3 Hz with σ = 2 mm the proposed method lost the
robot in 3 of 3 trials without these terms; with the turn alone in 2 of 6 (4.7 mm RMS), with
both in none of the same 6 (1.8 mm; the filter without strong tracking, the soft
constraints as penalties).

Corridor
--------
With a :class:`~magrun.freespace.FreeSpace` that has a critical boundary (the protocol's
phantom), each stage k ≥ 1 has a half-plane from the critical boundary's point nearest to the
previous plan's state there (the reference on a trial's first tick;
:meth:`FreeSpace.corridor`). Both end points of the body's axis must lie on the free side,
the body's radius plus a margin away: ``corridor_margin`` + κ σ_n, where σ_n is the
estimate's standard deviation along the boundary's normal (the Kalman filter's covariance,
κ = ``corridor_sigmas``), at most ``corridor_share`` of the channel's free width: a chance
constraint, tightened by what the controller does not know. So the body's ends, and with them
its heading, are kept off the critical wall. The other boundaries get no constraint: contact
with them is allowed.

A frame can move the estimate into the margin (a 2 mm σ frame moves it by 0.5 mm on the bench
spine). The plan is then not asked to leave within one stage, which only a large lateral
force could do, bought with the heading: stage k's half-plane is moved back by what is left
of the start's intrusion after k stages at ``corridor_recovery`` (m/s), so the constraint
passes through the start's nearer end at stage 0 and is whole again once the intrusion is
recovered.

Soft constraints
----------------
Both are soft: a violation costs w · min(0, g)² (weights ``heading_weight`` per mT² and
``corridor_weight`` per mm² of violation), so every tick's problem stays feasible (a robot
pushed into a wall by a disturbance still gets the plan that leads it out), and their
weights make violations small against the tracking terms. The real-time iteration keeps
them in one of two ways (``soft_constraints``), with the same optimum:

- ``"penalty"`` (the default): residuals √w · min(0, g) in the least-squares cost. Their
  Gauss–Newton model is zero where a constraint is not violated at the linearisation, so
  one step can plan straight through a constraint it does not yet see and the next step
  back out of it; with one step a tick the field along the moment then alternates tick by
  tick. On the bench spine (heading weight 1000) the planned field turned 110–170° from the
  estimated heading on every other tick for 0.3 s, three iterations a tick, before a touch.
- ``"slack"``: each gap linearised as an inequality of the tick's QP with a slack that costs
  the same, g + G Δz + σ ≥ 0, σ ≥ 0, cost σ² (HPIPM's soft constraints; the kernel only,
  CasADi's QP keeps the residuals). Every step sees every constraint. On the bench spine
  (20 trials) 3 touched the anterior wall where 5 did with ``"penalty"``.

Units inside the problem are scaled for the solver: positions in mm, velocities in mm/s, and
currents as fractions of the limit, u = I / I_max. The weights are stated in those units:
Qp and P per mm², qθ and qθ,N per rad², R and S per u².

Default weights follow the paper's tuning note, ‖R‖ = 2‖S‖ and ‖Qp‖ = 10‖R‖, in these units
(R = I₈, S = 0.5 I₈, Qp = P = 10 I₂). They were set on the paper's rig, whose coils give its
references' velocities 5.9–8.1 times over (median over a reference; :func:`magrun.field.
capability.held_reference`). On a system f times stronger for its task the same force takes
currents f/8.2 times the fraction of the limit, and R and S per u² weigh them that much less:
a trial's R and S are scaled by max(1, (f / 8.2)²) (``controller.current_weight: auto``;
:func:`magrun.trial.nmpc_tuning`), so the paper rig keeps its weights and a system whose
coils could fling the robot gets currents weighed by what the task needs. On OctoMag
(f ≈ 47, weights × 33) the proposed method's 25.5 Hz, σ = 2 mm trials went from 0.76 mm, 7°
to 0.66 mm, 2°; on three coils (f ≈ 58 for a slow S) it lost the robot in 1 of 10 seeds
without the scaling, in none with it. The paper does not state its units, and the ratio only
means something with them: with currents in amperes instead (the same numbers per A², a
current penalty 900 times heavier) the robot lags the S-trajectory by 1.7–1.9 mm RMS on the
simulated rig; with normalised currents it tracks to a few hundredths of a millimetre.

Two solvers for the same problem (``NMPCConfig.solver``)
--------------------------------------------------------
``"rti"`` (default): a Gauss–Newton real-time iteration. The cost is a sum of squared
residuals, so its Gauss–Newton Hessian JᵀJ needs first derivatives only. Each tick linearises
the dynamics and residuals around the previous plan shifted by one step and solves one
structured QP with HPIPM (a Riccati-based interior point method for optimal control), with
the stage structure passed explicitly: stage states sₖ = (Xₖ, u_{k−1}) (14), stage controls
vₖ = uₖ − u_{k−1} (8), so the slew limit is a box on vₖ and every constraint is a box.
A trial's first tick (no previous plan) iterates to convergence instead. Iterated to
convergence on a fixed problem it reaches the same optimum as IPOPT (tests/test_nmpc.py).

Corrective iterations. Where a tick's step leaves the first currents' field along the moment
more than ``corrective_sag`` × B_min short of the heading term's bound, the tick iterates
again, at most ``corrective_iterations`` times, each step damped to ``corrective_step`` of
the QP's. Full Gauss–Newton steps can cycle: on the bench spine, where the capsule crosses
the channel's apex (x = 7.4 mm, y = 0), the currents that hold its heading while pushing it
along change from one family to another, and full steps from the old plan alternated between
two plans whose fields ran 4–7 mT against the moment on the next stages, at a cost 100–200 times
IPOPT's optimum for the same tick (tests/test_nmpc.py); the capsule turned and touched the
wall. Half steps reach IPOPT's currents within a few ticks. A tick whose heading holds takes
its one full step, as before.

Step damping. With ``step_damping`` = μ > 0 every QP's cost gains μ/2 |Δz|² on its step Δz
(states and currents, scaled units), a Levenberg–Marquardt term: the iteration's fixed points
(the optimum) stay where they are, each step is shorter. On a coil system that cannot hold the
reference's heading everywhere (three coils: :func:`magrun.field.capability.held_reference`)
the currents that give the force and hold a heading jump from one family to another, and full
steps alternated between them tick by tick: on the three-coil system of docs/systems.md the
proposed method lost the robot in every seed, its QPs failing from there on; with μ = 1 and
the held headings it tracked in all six. A protocol's ``controller.step_damping: auto`` gives
μ = 1 exactly there and 0 elsewhere (the paper rig's and OctoMag's trials are unchanged).

Checked steps. Gauss–Newton steps are not checked against anything, and a full step can raise
the objective it is meant to lower. Where the heading weights are light (held headings: the
paper's qθ × 0.01, :func:`magrun.trial.nmpc_tuning`) the heading swings freely and the force
with it, and plain steps diverged: on ``tri``, from a start turned 2 rad off the direction of
travel, the first tick's iterates ran to the position bound at 100–200 mm/s until HPIPM stopped
at its minimum step; forced through, the real-time ticks that followed drove the robot at
50 mm/s. With ``step_check`` each step is measured by the objective of its plan's currents
(:attr:`OCP.objective`: the states simulated from the start, held within the position bound).
The first tick keeps a step only where that falls, else takes it back and raises the step
damping tenfold (from max(10 μ, 1), at most 5 times) until one does, lowering it again after
each kept step: a Levenberg–Marquardt descent (:func:`descend`). A real-time tick's one step is
taken back where it more than doubles the objective of the plan it started from
(:data:`DIVERGING`), and that tick descends from the plan instead. Only a diverging step: a
new measurement moves the start, and the step that re-plans from it may well cost more than
the old plan did from there. On the turned start above the diverging steps multiplied the
objective 15–155 times; under σ = 2 mm noise at 3 Hz (Baseline 1 on ``tri``) 6 % of the
steps raised it, by 1.5 times (median), and taking all those back cost accuracy (2.4–2.6 mm
RMS became 2.2–10 mm, one robot of three lost), taking back the doubled ones did not. Where a
descent finds no better plan and a QP fails, the tick keeps its plain step (a first tick
fails, as before). Each checked tick evaluates the objective twice (its cost: BENCHMARKS.md);
``nmpc_tuning`` turns it on where the planner follows held headings, as the damping, and the
paper rig's trials are unchanged.

The tick splits in two (:meth:`NMPC.prepare`, called by the control loop after the currents
went out): the preparation linearises every stage around the shifted plan, stage 0 at the
state predicted for the next tick; the feedback (:meth:`NMPC.plan`) embeds the measured
state into that QP, exactly for the linearised model, and solves it. Both run in a compiled
kernel around HPIPM (:mod:`magrun.control.rti_kernel`); CasADi's HPIPM interface on the
same QP is the fallback without a C compiler (no split there).

``"ipopt"``: the reference: the multiple-shooting NLP above solved to convergence by IPOPT
with its exact Hessian, warm-started from the previous solution and multipliers shifted by
one step. ``magrun bench nmpc`` measures both side by side.

Both evaluate the field through the model's ``casadi_field_and_gradient`` (for the Zernike
model its monomial form, :mod:`magrun.field.polynomial`), and both run compiled C
(:mod:`magrun.compiled`: the RTI's per-stage functions, IPOPT's NLP callbacks),
cached on disk.

On failure (no convergence, non-finite output; after the retry below) the plan falls back
to the previous plan's next currents ("shifted"), or to 0 A ("zero") when there is none; the
controller's safety clamp then bounds the change. The tick after a failed one starts afresh,
as a trial's first tick does (currents held, iterated to convergence): the failed plan was
linearised where the robot no longer is, and continuing from it failed tick after tick
until its currents ran out (on a three-coil system under σ = 2 mm noise, 1018 of 1119 ticks,
the coils held at the plan's last currents while the robot drifted off). The position bound
is hard, and a start may leave no plan within it: one outside the box (clipped onto it) with
a push outward, or one moving toward the bound faster than the slew-limited currents can
stop it (the first tick of a ``tri`` trial at 3 Hz under σ = 2 mm: an estimate 1.6 mm inside
the bound moving toward it at 11 mm/s, from zero currents, failed for each NMPC method).
Baseline 1's starts carry velocities that are differences of noisy frames (on ``three``
under σ = 2 mm up to 140 mm/s and 80 rad/s), and its QP failed from some well inside the
bound too. A tick whose QP fails is solved once more from the same pose at rest, at least
:data:`OUTSIDE_START` inside the bound, cold from a plan that brakes
(:meth:`NMPC._braking`: the currents brought to zero at the slew bound, the model's states
for them, within the bound), so the first QP is linearised at a feasible plan. From the
held currents instead, a ``three`` start 1.5 mm outside the bound, a coil at its limit
pushing outward, failed the retry too (HPIPM at its iteration limit). Planned from inside
every time instead, the robot's estimate moved by a millimetre cost accuracy where the
first QP solves. A soft bound (an exact penalty in the
kernel's QP) made every tick's QP about 1.5–2 times slower on the paper's rig.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.compiled import compiled, shared_library
from magrun.control.base import Plan, Planner
from magrun.control.rti_kernel import RTIKernel, build_kernel
from magrun.control.symbolic import CASADI_OPS
from magrun.field.model import PlanarFieldModel
from magrun.freespace import INACTIVE, FreeSpace
from magrun.records import ControllerStatus
from magrun.robot import RobotParams, aligned_substep, discrete_step

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
        self.backend: _Backend = (
            RTISolver(self.problem) if cfg.solver == "rti" else IpoptSolver(self.problem)
        )
        self._predict = self.problem.maybe_compiled(self.problem.step_scaled)
        self.reset()

    # -- Planner API -----------------------------------------------------------------------------

    def reset(self) -> None:
        self.backend.reset()
        self.position_covariance = None
        self._prepare_time = 0.0

    def observe_uncertainty(self, covariance: FloatArray | None) -> None:
        """The estimate's covariance (3×3: x, y, θ), or None: tightens the corridor."""
        self.position_covariance = None if covariance is None else np.asarray(covariance)[:2, :2]

    def corridor(self, state: FloatArray, reference: FloatArray) -> FloatArray:
        """The half-planes of each stage 0 … N, shape (N+1, N_PLANES, 3), in mm (scaled)."""
        N = self.config.horizon
        planes = np.empty((N + 1, N_PLANES, 3))
        planes[:] = INACTIVE
        fs = self.free_space
        if fs is None:
            return planes
        plan = self.backend.states_plan()  # X_1 … X_N of the last plan, scaled
        if plan is None:
            positions = reference[:, :2]
        else:
            positions = np.vstack([state[:2], plan[1:, :2] * 1e-3, plan[-1:, :2] * 1e-3])
        cfg = self.config
        planes[:, 0] = fs.corridor(
            positions, self.position_covariance, cfg.corridor_margin, cfg.corridor_sigmas,
            cfg.corridor_share,
        )  # fmt: skip
        if cfg.corridor_recovery > 0:
            # a start already inside the margin (an estimate that a frame moved toward the
            # wall) is led back out at corridor_recovery, not within one stage (module doc)
            n, c = planes[0, 0, :2], planes[0, 0, 2]
            axis = np.array([math.cos(state[2]), math.sin(state[2])]) * fs.half_axis
            inside = c - min(n @ (state[:2] + axis), n @ (state[:2] - axis))
            if inside > 0:
                k = np.arange(N + 1)
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
        self, state: FloatArray, reference: FloatArray, previous: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(x0 SI, its position in the workspace box; u_prev scaled; stage parameters)."""
        N = self.config.horizon
        x0 = np.asarray(state, dtype=np.float64).copy()
        x0[:2] = np.clip(x0[:2], -self.position_bound, self.position_bound)
        ref = np.asarray(reference, dtype=np.float64)
        if ref.shape != (N + 1, 3):
            raise ValueError(f"reference must have shape ({N + 1}, 3), got {ref.shape}")
        u_prev = np.asarray(previous, dtype=np.float64) / self.max_current
        return x0, u_prev, self.problem.stage_parameters(ref, self.corridor(x0, ref))

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
        next estimate's covariance, so nothing is prepared and every tick iterates in full."""
        if self.problem.has_corridor and self.position_covariance is not None:
            return  # the margins follow the next estimate's covariance: nothing to prepare
        t0 = time.perf_counter()
        x0, u_prev, params = self._start(state, reference, previous)
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


# --------------------------------------------------------------------------------------------
# the problem, shared by both solvers


class OCP:
    """The optimal control problem in scaled units: dynamics, residuals, bounds."""

    def __init__(self, nmpc: NMPC) -> None:
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
        nmpc: NMPC, X: Any, u: Any, G: Any, along: Any, b_min: float
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
        # expanded to scalar operations and compiled (cached): about 5 times faster a call
        # than the MX graph, and the checked steps call it twice a tick
        return self.maybe_compiled(
            ca.Function("nmpc_objective", [x0, u_prev, par, U], [J]).expand()
        )


@dataclass(frozen=True)
class SolveResult:
    ok: bool
    u0: FloatArray  # first currents, I / I_max
    iterations: int
    message: str


class _Backend:
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


class IpoptSolver(_Backend):
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
        solver = ca.nlpsol("nmpc_ipopt", "ipopt", nlp, opts)
        library = self._compile(solver) if cfg.compile else None
        self.solver = (
            solver if library is None else ca.nlpsol("nmpc_ipopt", "ipopt", str(library), opts)
        )
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
    def _compile(solver: ca.Function) -> Path | None:
        def write(folder: Path) -> Path:
            cwd = os.getcwd()
            os.chdir(folder)  # generate_dependencies writes into the working directory
            try:
                return folder / solver.generate_dependencies("nmpc_ipopt.c")
            finally:
                os.chdir(cwd)

        return shared_library("nmpc_ipopt", write, optimisation="-O1")

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


class RTISolver(_Backend):
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
        # common subexpressions: the heading's derivatives repeat the field's derivatives the
        # dynamics' Jacobian already has
        kernel_stage = ca.Function(
            "rti_stage", [s, v, ref],
            [s_next, ca.jacobian(s_next, s), ca.jacobian(s_next, v), r, ca.jacobian(r, s),
             ca.jacobian(r, v), g, ca.jacobian(g, s), ca.jacobian(g, v)],
            {"cse": True},
        )  # fmt: skip
        kernel_terminal = ca.Function(
            "rti_terminal", [s, ref], [rN, ca.jacobian(rN, s), gN, ca.jacobian(gN, s)]
        )
        self.kernel = self._kernel(kernel_stage, kernel_terminal, r.shape[0], rN.shape[0],
                                   g.shape[0], gN.shape[0])  # fmt: skip
        self.robust_retries = 0
        self.relinearised = 0  # prepared ticks linearised again at the measurement
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
        self, stage: ca.Function, terminal: ca.Function, n_r: int, n_rt: int, n_g: int,
        n_gt: int,
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
        library = build_kernel(stage, terminal, heading, ocp.step_scaled, dims)
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


def channel_field_scale(model: PlanarFieldModel, n: int = 21) -> FloatArray:
    """Each channel's field per ampere, RMS over an n × n grid of the workspace box, T/A."""
    h = model.coils.workspace_half_width
    g = np.linspace(-h, h, n)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    unit = model.unit_field(grid)  # (n², channels, 2)
    return np.sqrt(np.mean(np.sum(unit**2, axis=-1), axis=0))


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


def _scale(limit: Any) -> Any:
    """The current scale in a CasADi product: a number, or a column of one per channel."""
    return float(limit) if np.ndim(limit) == 0 else ca.DM(np.asarray(limit, dtype=float))
