"""Robot models and planar dynamics (paper, Section II-C, Eqs. (dynamics) and (magnetic_force)).

State ``x = [x, y, θ, vx, vy, ω]`` in m, rad, m/s, rad/s. The robot is a rigid cylinder whose
magnetic moment ``m = |m| (cos θ, sin θ)`` lies along its axis::

    m_r v̇ = F_mag − R(θ) diag(d∥, d⊥) R(θ)ᵀ v        F_mag = (m·∇)B,  F_l = Σ_k m_k ∂B_k/∂x_l
    J ω̇   = τ_mag − d_r ω                            τ_mag = m × B = m_x B_y − m_y B_x

Discretisation
--------------
The velocity time constants m_r/d (≈ 6 ms) and J/d_r (≈ 2 ms) are far below the NMPC's 40 ms
step: explicit Euler on these equations diverges. :func:`discrete_step` is an exponential
integrator: over a sub-step of length h, with force and torque held, the damped velocity
equations are linear and are solved exactly along the body axes,

    u(h) = u_ss + (u₀ − u_ss) e^{−h/τ},    s(h) = u_ss h + (u₀ − u_ss) τ (1 − e^{−h/τ}),

(u a body-axis velocity, u_ss = f/d its terminal value, τ = m_r/d, s the distance moved), so
the scheme is stable for any h. The field and its gradient are evaluated once per step at the
step's start position (the robot moves well under a millimetre in 40 ms); force and torque
are re-evaluated from them on ``substeps`` sub-steps, because orientation is the fast
variable (alignment rate |m||B|/d_r of tens to hundreds of 1/s: "The model's step" below).
tests/test_robot.py checks the step against an adaptive stiff integration (Radau) of the
continuous equations. The simulated plant takes 1 ms sub-steps of this scheme.

The model's step
----------------
The exponential sub-step holds the torque at the mid-step heading, which is right while the
heading's relaxation rate k|B| = m|B|/d_r times the sub-step h stays below about 1. A strong
coil system turns a light robot far faster: OctoMag, MiniMag or a three-coil system with
``micro_magnet`` reach k|B| of 400–800 1/s (k|B|·h of 8–16 at the NMPC's 20 ms sub-steps),
and the paper's rig with ``drug_delivery`` near 30 A about 400 1/s. There the exponential
sub-step's heading is tens of degrees off after one tick (on a three-coil system at 10 A,
62° median), the NMPC plans with a robot that does not exist, and under noisy feedback
it lost the robot. :func:`aligned_substep`, the NMPC's step, solves the heading's turn toward
the field instead: drag-dominated, δ = θ − φ (φ the field's direction) obeys
δ̇ = −k|B| sin δ, whose solution is tan(δ/2) = tan(δ₀/2) e^(−k|B|t), exact for any k|B|·h.
Inertia (J/d_r of 0.3–2 ms) enters twice: the relaxation rate on the slow manifold,
k|B| (1 + k|B| J/d_r cos δ₀), capped at the underdamped envelope 1/(2 J/d_r), and the start's
turn rate in excess of the quasi-steady −k|B| sin δ₀, which decays over J/d_r. The force,
linear in the heading's (cos θ, sin θ), is averaged over the turn by Simpson's rule. Against
Radau (tests/test_robot.py) its two 20 ms sub-steps stay within 0.4–2° and 12 µm per tick
for fields of 2–100 mT at up to 149° from the robot, where the exponential sub-step's error
reached 80–175° for the stiff robots.

The kernel is written once over an ``ops`` namespace (``sin``, ``cos``, ``exp``, ``atan2``,
``sqrt``, ``fmin``, ``fmax``), so NumPy floats, NumPy arrays and CasADi expressions
(:mod:`magrun.control.symbolic`) all run the same code.

    >>> from magrun.robot import load_robot
    >>> robot = load_robot("magnet")
    >>> round(robot.moment, 5), robot.name
    (0.00135, 'magnet')
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, RootModel

from magrun.yamlio import parse_yaml_model, read_text_file

FloatArray = NDArray[np.float64]
Expr = Any

NUMPY_OPS = SimpleNamespace(
    sin=np.sin,
    cos=np.cos,
    exp=np.exp,
    atan2=np.arctan2,
    sqrt=np.sqrt,
    fmin=np.minimum,
    fmax=np.maximum,
)
#: Python floats: fastest
MATH_OPS = SimpleNamespace(
    sin=math.sin, cos=math.cos, exp=math.exp, atan2=math.atan2, sqrt=math.sqrt, fmin=min, fmax=max
)
STATE_NAMES = ("x", "y", "theta", "vx", "vy", "omega")
#: T: a floor under the field's magnitude in :func:`aligned_substep` (its derivative at
#: zero field stays finite; far below any coil's field)
FIELD_FLOOR = 1e-12


class RobotSpec(BaseModel):
    """One robot in ``robots.yaml`` (YAML units as suffixed; see the file for the derivation)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    description: str
    length_mm: float = Field(gt=0)
    diameter_mm: float = Field(gt=0)
    moment_am2: float = Field(gt=0, description="Magnetic moment along the robot's axis, A m².")
    mass_g: float = Field(gt=0, description="Mass including added fluid mass.")
    viscosity_mpa_s: float = Field(gt=0, description="Fluid viscosity (drag derivation only).")
    contact_factor: float = Field(gt=0, description="Effective / free-fluid drag (derivation).")
    drag_parallel_n_s_per_m: float = Field(gt=0)
    drag_perpendicular_n_s_per_m: float = Field(gt=0)
    drag_rotation_n_m_s: float = Field(gt=0)
    appearance: Literal["two_tone", "capsule"] = Field(
        description="How the camera sees the robot (magrun.tracking.render)."
    )
    min_aligned_field_mt: float = Field(
        0.0,
        ge=0,
        description=(
            "Least field along the moment the NMPC keeps (heading-stable fields), mT; "
            "see robots.yaml for the derivation."
        ),
    )
    prediction_sigma_mm: float | None = Field(
        None,
        gt=0,
        description=(
            "RMS one-step prediction error of the controller's model, position, mm per tick: "
            "the Kalman filter's process noise (robots.yaml says how it was measured)."
        ),
    )
    prediction_sigma_deg: float | None = Field(
        None, gt=0, description="The same for the heading, degrees per tick."
    )


class RobotsFile(RootModel[dict[str, RobotSpec]]):
    pass


@dataclass(frozen=True)
class RobotParams:
    """Rigid-body parameters in SI units, as the dynamics use them."""

    name: str
    length: float  # m
    diameter: float  # m
    moment: float  # A m², along the body axis
    mass: float  # kg
    inertia: float  # kg m², about the vertical axis
    drag_parallel: float  # N s/m, along the body axis
    drag_perpendicular: float  # N s/m, across the body axis
    drag_rotation: float  # N m s
    appearance: str = "two_tone"  # camera look: "two_tone" (magnet robot) or "capsule"
    min_aligned_field: float = 0.0  # T, least field along the moment (heading-stable fields)
    prediction_sigma: tuple[float, float] | None = None  # m, rad: one-step prediction error

    @classmethod
    def from_spec(cls, name: str, spec: RobotSpec) -> RobotParams:
        length, diameter, mass = spec.length_mm * 1e-3, spec.diameter_mm * 1e-3, spec.mass_g * 1e-3
        return cls(
            name=name,
            length=length,
            diameter=diameter,
            moment=spec.moment_am2,
            mass=mass,
            inertia=mass * (length**2 / 12 + diameter**2 / 16),
            drag_parallel=spec.drag_parallel_n_s_per_m,
            drag_perpendicular=spec.drag_perpendicular_n_s_per_m,
            drag_rotation=spec.drag_rotation_n_m_s,
            appearance=spec.appearance,
            min_aligned_field=spec.min_aligned_field_mt * 1e-3,
            prediction_sigma=(
                (spec.prediction_sigma_mm * 1e-3, math.radians(spec.prediction_sigma_deg))
                if spec.prediction_sigma_mm is not None and spec.prediction_sigma_deg is not None
                else None
            ),
        )

    def scaled(self, *, mass: float = 1.0, drag: float = 1.0, moment: float = 1.0) -> RobotParams:
        """A copy with mass (and inertia), all drag coefficients and the moment multiplied."""
        return replace(
            self,
            mass=self.mass * mass,
            inertia=self.inertia * mass,
            drag_parallel=self.drag_parallel * drag,
            drag_perpendicular=self.drag_perpendicular * drag,
            drag_rotation=self.drag_rotation * drag,
            moment=self.moment * moment,
        )


def robots_path() -> Path:
    return Path(str(resources.files("magrun") / "data" / "robots.yaml"))


def load_robots(path: str | Path | None = None) -> dict[str, RobotParams]:
    """All robots of a robots file (default: the paper's two, ``magnet`` and ``drug_delivery``).

    Raises
    ------
    magrun.yamlio.YamlModelError
        If the file does not match the schema; the message names file, line and field.
    """
    path = Path(path) if path is not None else robots_path()
    doc = parse_yaml_model(read_text_file(path), RobotsFile, str(path))
    return {name: RobotParams.from_spec(name, spec) for name, spec in doc.root.items()}


def load_robot(name: str, path: str | Path | None = None) -> RobotParams:
    robots = load_robots(path)
    try:
        return robots[name]
    except KeyError:
        raise KeyError(f"unknown robot {name!r}; known: {', '.join(sorted(robots))}") from None


def slender_body_drag(
    length: float, diameter: float, viscosity: float
) -> tuple[float, float, float]:
    """Stokes drag of a cylinder in unbounded fluid (Tirado & García de la Torre, 1979/80).

    Parameters
    ----------
    length, diameter : float
        Cylinder size, m (valid for aspect ratios 2–30).
    viscosity : float
        Dynamic viscosity, Pa s.

    Returns
    -------
    (d_parallel, d_perpendicular, d_rotation) : N s/m, N s/m, N m s
        Translation along and across the axis, rotation about a transverse axis.
    """
    p = length / diameter
    lp = math.log(p)
    d_par = 2 * math.pi * viscosity * length / (lp - 0.207 + 0.980 / p - 0.133 / p**2)
    d_perp = 4 * math.pi * viscosity * length / (lp + 0.839 + 0.185 / p + 0.233 / p**2)
    d_rot = math.pi * viscosity * length**3 / (3 * (lp - 0.662 + 0.917 / p - 0.050 / p**2))
    return d_par, d_perp, d_rot


# -- kernels ------------------------------------------------------------------------------------


def magnetic_wrench(
    theta: Any, moment: Any, B: Any, G: Any, ops: SimpleNamespace = NUMPY_OPS
) -> tuple[tuple[Any, Any], Any]:
    """Force and torque on a moment ``moment`` (A m²) at angle ``theta``, Eq. (magnetic_force).

    ``B = (Bx, By)`` in T and ``G[k][l] = ∂B_k/∂x_l`` in T/m, as nested sequences (or arrays
    indexable that way). Returns ``((Fx, Fy), τ)`` in N and N m.
    """
    mx, my = moment * ops.cos(theta), moment * ops.sin(theta)
    fx = mx * G[0][0] + my * G[1][0]
    fy = mx * G[0][1] + my * G[1][1]
    return (fx, fy), mx * B[1] - my * B[0]


def relaxation(tau: float, h: float) -> tuple[float, float]:
    """The exact relaxation's constants over ``h`` for a time constant ``tau`` (s): the decay
    e^(−h/τ) and its integral τ(1 − e^(−h/τ)). The one definition of the plant sub-step's
    constants: :func:`_relax` here and the compiled plant (:mod:`magrun.rigs.kernel`) both
    use it, so the two integrate with the same numbers."""
    decay = math.exp(-h / tau)
    return decay, tau * (1.0 - decay)


def _relax(u0: Any, u_ss: Any, tau: float, h: Any) -> tuple[Any, Any]:
    """Exact solution of u̇ = (u_ss − u)/τ over h: (u(h), ∫₀ʰ u dt). ``h`` a float, or an
    array with each element's own length (the replay's rollouts from many starts at once)."""
    decay: Any
    integral: Any
    if isinstance(h, np.ndarray):
        decay = np.exp(-h / tau)
        integral = tau * (1.0 - decay)
    else:
        decay, integral = relaxation(tau, h)
    return u_ss + (u0 - u_ss) * decay, u_ss * h + (u0 - u_ss) * integral


def _substep_with_wrench(
    state: tuple[Any, ...],
    wrench: tuple[tuple[Any, Any], Any],
    params: RobotParams,
    h: float,
    ops: SimpleNamespace,
) -> tuple[Any, ...]:
    """Exact damped motion over ``h`` under a held force and torque (body axes of θ₀)."""
    x, y, th, vx, vy, om = state
    (fx, fy), tq = wrench
    x1, y1, vx1, vy1 = _translate(x, y, th, vx, vy, fx, fy, params, h, ops)
    om1, dth = _relax(om, tq / params.drag_rotation, params.inertia / params.drag_rotation, h)
    return x1, y1, th + dth, vx1, vy1, om1


def _translate(
    x: Any,
    y: Any,
    th: Any,
    vx: Any,
    vy: Any,
    fx: Any,
    fy: Any,
    params: RobotParams,
    h: float,
    ops: SimpleNamespace,
) -> tuple[Any, Any, Any, Any]:
    """Exact damped translation over ``h`` under a held force (body axes of ``th``):
    (x, y, vx, vy) after it."""
    c, s = ops.cos(th), ops.sin(th)
    # body axes: a along the moment, b across it
    ua, ub = c * vx + s * vy, -s * vx + c * vy
    fa, fb = c * fx + s * fy, -s * fx + c * fy
    ua1, sa = _relax(ua, fa / params.drag_parallel, params.mass / params.drag_parallel, h)
    ub1, sb = _relax(ub, fb / params.drag_perpendicular, params.mass / params.drag_perpendicular, h)
    return x + c * sa - s * sb, y + s * sa + c * sb, c * ua1 - s * ub1, s * ua1 + c * ub1


def exponential_substep(
    state: tuple[Any, ...],
    B: Any,
    G: Any,
    params: RobotParams,
    h: Any,
    ops: SimpleNamespace = NUMPY_OPS,
) -> tuple[Any, ...]:
    """One sub-step of length ``h`` (s; a float, or with NumPy an array of each element's own)
    with the field (B, G) held: the scheme of the module doc.

    Exponential midpoint rule: a half step under the start wrench predicts the mid-step
    orientation; the full step then uses the wrench at that orientation. The damping is exact
    either way; the midpoint makes the orientation coupling second order in ``h``.
    ``state`` is the 6-tuple ``(x, y, θ, vx, vy, ω)``; returns the next 6-tuple.
    """
    start = magnetic_wrench(state[2], params.moment, B, G, ops)
    half = _substep_with_wrench(state, start, params, h / 2, ops)
    mid = magnetic_wrench(half[2], params.moment, B, G, ops)
    return _substep_with_wrench(state, mid, params, h, ops)


def aligned_substep(
    state: tuple[Any, ...],
    B: Any,
    G: Any,
    params: RobotParams,
    h: float,
    ops: SimpleNamespace = NUMPY_OPS,
) -> tuple[Any, ...]:
    """One sub-step of length ``h`` (s) with the field (B, G) held, the heading's turn toward
    the field solved exactly (module doc, "The model's step"). Stable and accurate for any
    alignment rate k|B|·h, where :func:`exponential_substep` needs k|B|·h below about 1.
    ``state`` is the 6-tuple ``(x, y, θ, vx, vy, ω)``; returns the next 6-tuple."""
    x, y, th, vx, vy, om = state
    bx, by = B[0], B[1]
    c, s = ops.cos(th), ops.sin(th)
    norm = ops.sqrt(bx * bx + by * by + FIELD_FLOOR * FIELD_FLOOR)
    # δ = θ − φ, φ the field's direction: sin δ, cos δ (both 0 where there is no field)
    sd, cd = (s * bx - c * by) / norm, (c * bx + s * by) / norm
    k = params.moment / params.drag_rotation  # alignment rate per tesla, 1/(T s)
    tau = params.inertia / params.drag_rotation
    # the heading's relaxation rate: the slow root of J δ̈ + d_r δ̇ + m|B| δ = 0, k|B| where
    # inertia is negligible; past critical damping (4 k|B| J/d_r > 1), its envelope 1/(2 J/d_r)
    stiffness = k * norm * tau
    rate = ops.fmin(k * norm * (1.0 + stiffness * cd), 0.5 / tau)
    transient = om + k * norm * sd  # ω less its quasi-steady value τ/d_r = −k|B| sin δ

    def turned(t: float) -> Any:
        """θ(t) − θ₀: tan(δ/2) decays as e^(−rate·t) (the overdamped relaxation), plus the
        start's excess turn rate relaxing over J/d_r. The turn's sine and cosine, both times
        the same positive factor, with sin²δ₀ written (1 − cos δ₀)(1 + cos δ₀): smooth
        everywhere, 0 at zero field and at the anti-aligned rest."""
        e = ops.exp(-rate * t)
        sine = sd * (2.0 * e * cd - (1.0 + cd) + (1.0 - cd) * e * e)
        cosine = cd * (1.0 + cd) - cd * (1.0 - cd) * e * e + 2.0 * (1.0 - cd) * (1.0 + cd) * e
        return ops.atan2(sine, cosine) + transient * (tau * (1.0 - math.exp(-t / tau)))

    # the force, linear in the heading's (cos, sin), averaged over the turn (Simpson's rule)
    mid, th1 = th + turned(0.5 * h), th + turned(h)
    hx = (c + 4.0 * ops.cos(mid) + ops.cos(th1)) / 6.0
    hy = (s + 4.0 * ops.sin(mid) + ops.sin(th1)) / 6.0
    fx = params.moment * (hx * G[0][0] + hy * G[1][0])
    fy = params.moment * (hx * G[0][1] + hy * G[1][1])
    x1, y1, vx1, vy1 = _translate(x, y, mid, vx, vy, fx, fy, params, h, ops)
    S1 = ops.sin(th1) * bx - ops.cos(th1) * by
    return x1, y1, th1, vx1, vy1, -k * S1 + transient * math.exp(-h / tau)


def discrete_step(
    state: tuple[Any, ...],
    field: Callable[[Any, Any], tuple[Any, Any]],
    params: RobotParams,
    dt: float,
    substeps: int = 2,
    ops: SimpleNamespace = NUMPY_OPS,
    substep: Callable[..., tuple[Any, ...]] = exponential_substep,
) -> tuple[Any, ...]:
    """Advance ``state`` by ``dt`` (s) with the field evaluated once at the start position,
    in ``substeps`` sub-steps of ``substep`` (the plant's :func:`exponential_substep`, or the
    model's :func:`aligned_substep`).

    ``field(x, y) -> (B, G)`` gives the total field (T) and gradient (T/m) at a position for
    the currents held over the step.
    """
    B, G = field(state[0], state[1])
    h = dt / substeps
    for _ in range(substeps):
        state = substep(state, B, G, params, h, ops)
    return state


def drag_matrix(params: RobotParams, theta: float) -> FloatArray:
    """Translational drag in the workspace frame, R(θ) diag(d∥, d⊥) R(θ)ᵀ, N s/m, shape (2, 2)."""
    c, s = math.cos(theta), math.sin(theta)
    R = np.array([[c, -s], [s, c]])
    return R @ np.diag([params.drag_parallel, params.drag_perpendicular]) @ R.T


def state_derivative(
    state: ArrayLike, B: ArrayLike, G: ArrayLike, params: RobotParams
) -> FloatArray:
    """Right-hand side of the continuous equations, for reference integrations and tests.

    ``state`` (6,), ``B`` (2,) in T and ``G`` (2, 2) in T/m at the state's position.
    """
    x = np.asarray(state, dtype=np.float64)
    Bv, Gv = np.asarray(B, dtype=np.float64), np.asarray(G, dtype=np.float64)
    (fx, fy), tq = magnetic_wrench(x[2], params.moment, Bv, Gv)
    acc = (np.array([fx, fy]) - drag_matrix(params, float(x[2])) @ x[3:5]) / params.mass
    alpha = (tq - params.drag_rotation * x[5]) / params.inertia
    return np.array([x[3], x[4], x[5], acc[0], acc[1], alpha])


def heading_rate(params: RobotParams, field_along: float) -> float:
    """Rate, 1/s, at which a small heading error relaxes in a field whose component along the
    moment is ``field_along`` (T): the linearised, drag-dominated heading dynamics
    d_r δθ̇ = −m B_∥ δθ. Negative (the error grows) when the field is against the moment."""
    return params.moment * field_along / params.drag_rotation
