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
estimate's standard deviation along the boundary's normal (κ = ``corridor_sigmas``), at
most ``corridor_share`` of the channel's free width: a chance constraint, tightened by what
the controller does not know. The covariance is the Kalman filter's before the tick's frame
(its prediction from the last tick): the same with a frame or without, so known a tick
ahead and the tick's corridor prepared with the rest of it (:meth:`NMPC.prepare`); a
frame's tick keeps the wider margin of the covariance the frame is about to shrink. So the
body's ends, and with them its heading, are kept off the critical wall. The other
boundaries get no constraint: contact with them is allowed.

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

from magrun.control.nmpc.backend import SolveResult, descend
from magrun.control.nmpc.config import N_PLANES, NP, NX, STATE_SCALE, NMPCConfig
from magrun.control.nmpc.ipopt import IpoptSolver
from magrun.control.nmpc.planner import NMPC
from magrun.control.nmpc.problem import OCP, channel_field_scale
from magrun.control.nmpc.rti import RTISolver

__all__ = [
    "NMPC",
    "NP",
    "NX",
    "N_PLANES",
    "OCP",
    "STATE_SCALE",
    "IpoptSolver",
    "NMPCConfig",
    "RTISolver",
    "SolveResult",
    "channel_field_scale",
    "descend",
]  # fmt: skip
