"""What a coil system can do with a robot: force, torque, held field and sustainable speed.

A magnet robot of moment m along its heading h = (cos θ, sin θ) in the field B(I) and
gradient G(I) of currents I (both linear in I, plus a background where the system has one)
feels (:func:`magrun.robot.magnetic_wrench`)::

    F = m Gᵀ h,        τ = m (h × B) = m h⊥ · B,        h⊥ = (−sin θ, cos θ)

and, drag-dominated, moves at v = D(θ)⁻¹ F with D(θ) the drag matrix. To move at velocity v
while turning at ω it needs F = D(θ) v and τ = d_r ω, and to keep its heading stable a
field along its moment of at least B_min (the robot's ``min_aligned_field``). Each of these
is linear in the currents, so for a pose, a velocity and a turn rate the largest speed factor
s for which the currents can give ``F = s D(θ) v``, the torque and ``h · B ≥ B_min`` within
each channel's limit is a linear program (scipy's HiGHS, :mod:`magrun.field.lp`)::

    max s   s.t.  m Gᵀ(I) h − s D(θ) v = −m G₀ᵀ h,     m h⊥ · B(I) = d_r ω − m h⊥ · B₀,
                  h · B(I) ≥ B_min − h · B₀,           |I_k| ≤ I_max,k,    0 ≤ s ≤ s_cap

The pose can be held at speed s |v| (s ≥ 1: the velocity is reachable). Three equalities
in the currents: a three-coil system has no freedom left, and whether its one solution lies
within the limits is exactly the question. No solution at all (s infeasible) means the
system cannot even hold that pose and heading there.

:func:`workspace_capability` maps this over a grid of positions and headings (the robot
moving along its axis); :func:`trajectory_capability` checks a reference trajectory pose by
pose (``magrun run`` refuses a trajectory the coils cannot follow); ``magrun field check``
prints both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.lp import solve_lp
from magrun.field.model import PlanarFieldModel
from magrun.robot import RobotParams, drag_matrix
from magrun.scene import Trajectory

FloatArray = NDArray[np.float64]

#: the largest speed factor an LP reports (a velocity of 0 needs none; "unbounded")
SPEED_CAP = 1e6
#: heading offsets (rad) tried, in this order, where the reference's own heading cannot be
#: held at the asked velocity: the robot may point elsewhere and still follow the path
HEADING_OFFSETS = np.radians([0.0, *(d * s for d in range(15, 181, 15) for s in (1, -1))][:-1])
#: a velocity reached to this fraction counts as reached: short of it by 1 % at a pose, the
#: robot falls behind by 1 % of its speed there, well below any tracking error; refusing a
#: run for that would refuse trajectories at exactly the coils' limit
REACHED = 0.99
#: directions sampled for the largest field magnitude (the torque's bound)
FIELD_DIRECTIONS = 72


@dataclass(frozen=True)
class PoseCapability:
    """What the coils can do at one pose, for one velocity and turn rate."""

    #: largest factor on the asked velocity (NaN: the pose and heading cannot be held at all)
    speed_factor: float
    #: the currents that give it (A), or None
    currents: FloatArray | None


def _limits(max_current: float | ArrayLike, n: int) -> FloatArray:
    limits = np.broadcast_to(np.asarray(max_current, dtype=np.float64), (n,)).copy()
    if not np.all(np.isfinite(limits) & (limits > 0)):
        raise ValueError("every channel's current limit must be a positive number of amperes")
    return limits


@dataclass(frozen=True)
class Site:
    """What the coils give at one position: the channels' unit fields ``B`` (n, 2) T/A and
    gradients ``G`` (n, 2, 2) T/(m A), the background's ``B0`` (2,) T and ``G0`` (2, 2) T/m,
    each channel's current limit (n,) A, and the robot they act on."""

    B: FloatArray
    G: FloatArray
    B0: FloatArray
    G0: FloatArray
    limits: FloatArray
    robot: RobotParams


def _sites(
    model: PlanarFieldModel, robot: RobotParams, limits: FloatArray, positions: FloatArray
) -> list[Site]:
    """A :class:`Site` for each of ``positions`` (..., 2), m, flattened."""
    flat = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    B, G = model.unit_field_and_gradient(flat)
    B0, G0 = model.background_field_and_gradient(flat)
    return [Site(B[k], G[k], B0[k], G0[k], limits, robot) for k in range(len(flat))]


def largest_field(site: Site) -> float:
    """The largest field magnitude, T, the currents make at ``site``: over directions d, the
    largest Σ_c |d·B_c| I_max,c + d·B₀ (:data:`FIELD_DIRECTIONS` of them)."""
    angles = np.arange(FIELD_DIRECTIONS) * (2 * math.pi / FIELD_DIRECTIONS)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (nd, 2)
    return float((np.abs(d @ site.B.T) @ site.limits + d @ site.B0).max())


def pose_capability(
    site: Site, theta: float, velocity: ArrayLike, turn_rate: float = 0.0
) -> PoseCapability:
    """The LP of the module doc at ``site`` for heading ``theta`` (rad), ``velocity`` (2,)
    m/s and ``turn_rate`` rad/s asked."""
    B, G, limits, robot = site.B, site.G, site.limits, site.robot
    B0, G0 = site.B0, site.G0
    n = B.shape[0]
    m = robot.moment
    h = np.array([math.cos(theta), math.sin(theta)])
    hp = np.array([-h[1], h[0]])
    F_req = drag_matrix(robot, theta) @ np.asarray(velocity, dtype=np.float64)
    # force per ampere: F_l = m Σ_j h_j G[j, l]
    force = m * np.einsum("j,cjl->lc", h, G)  # (2, n)
    f0 = m * (h @ G0)
    a_eq = np.zeros((3, n + 1))
    a_eq[:2, :n], a_eq[:2, n] = force, -F_req
    a_eq[2, :n] = m * (B @ hp)
    b_eq = np.array([-f0[0], -f0[1], robot.drag_rotation * turn_rate - m * (hp @ B0)])
    a_ub = np.zeros((1, n + 1))
    a_ub[0, :n] = -(B @ h)
    b_ub = np.array([float(h @ B0) - robot.min_aligned_field])
    # scale the rows to order one (newtons, newton-metres and teslas are far apart) by what
    # the coils can give at all, not by the row's own projection: a projection that is zero
    # up to rounding must stay negligible, not become a constraint
    field_scale = float(np.abs(B).max(axis=1) @ limits) or 1.0  # T
    force_scale = max(float(np.abs(force).max(axis=0) @ limits), float(np.abs(F_req).max()))
    norm = np.array([force_scale or 1.0, force_scale or 1.0, m * field_scale])
    a_eq /= norm[:, None]
    b_eq /= norm
    a_ub /= field_scale
    b_ub /= field_scale
    cost = np.zeros(n + 1)
    cost[n] = -1.0
    x = solve_lp(
        cost,
        np.vstack([a_ub, a_eq]),
        np.concatenate(([-np.inf], b_eq)),
        np.concatenate((b_ub, b_eq)),
        np.concatenate((-limits, [0.0])),
        np.concatenate((limits, [SPEED_CAP])),
    )
    if x is None:
        return PoseCapability(math.nan, None)
    return PoseCapability(float(x[n]), x[:n])


def reachable(
    site: Site,
    theta: float,
    velocity: ArrayLike,
    turn_rate: float = 0.0,
    offsets: ArrayLike = HEADING_OFFSETS,
    enough: float = REACHED,
) -> tuple[float, float]:
    """:func:`pose_capability` at the headings ``offsets`` away from ``theta`` (rad, in
    order; default: its own first, then :data:`HEADING_OFFSETS`), until one gives the asked
    velocity ``enough`` times over: the factor (the first such one found, else the best; NaN
    where no heading can be held) and its offset."""
    best, at = math.nan, 0.0
    for delta in np.asarray(offsets, dtype=np.float64):
        cap = pose_capability(site, theta + delta, velocity, turn_rate)
        if cap.speed_factor > best or math.isnan(best):
            best, at = cap.speed_factor, float(delta)
        if best >= enough:
            break
    return best, at


@dataclass(frozen=True)
class WorkspaceCapability:
    """:func:`workspace_capability`'s maps, per position (ny, nx) and heading (nθ)."""

    x: FloatArray  # m, (nx,)
    y: FloatArray  # m, (ny,)
    headings: FloatArray  # rad, (nθ,)
    #: the speed the robot can hold moving along its axis, m/s (0: it cannot move; NaN: it
    #: cannot even hold the heading there), (ny, nx, nθ)
    speed: FloatArray
    #: the largest field the coils make there, T (any direction), (ny, nx)
    field: FloatArray
    drag: float  # N s/m, the robot's along its axis
    moment: float  # A m², the robot's

    #: with a speed asked: per position and direction of travel (the headings' directions),
    #: whether some heading lets the robot move that way at that speed, (ny, nx, nθ)
    reaches: NDArray[np.bool_] | None = None
    #: the speed asked, m/s
    asked: float | None = None

    @property
    def force(self) -> FloatArray:
        """The largest force along the heading while holding it, N, (ny, nx, nθ): the drag
        at the speed it holds."""
        return self.speed * self.drag

    @property
    def torque(self) -> FloatArray:
        """The largest torque on the robot, N m, (ny, nx): its moment in the largest field."""
        return self.field * self.moment

    @property
    def typical_force(self) -> float:
        """The median force along the heading, N, over the poses whose heading the coils can
        hold and move along it (the force such a robot typically gets); 0 where none. A pose
        "moves" where its force exceeds a millionth of the largest (a linear program's
        rounding is not a force)."""
        force = np.where(np.isfinite(self.force), self.force, 0.0)
        moving = force[force > 1e-6 * force.max()] if force.size else force
        return float(np.median(moving)) if moving.size else 0.0

    @property
    def typical_field(self) -> float:
        """The median over positions of the largest field the coils make, T."""
        return float(np.median(self.field))

    def summary(self) -> dict[str, Any]:
        """The figures ``magrun field check`` prints (SI in, the units named in the keys)."""
        held = np.isfinite(self.speed)
        along = np.where(held, self.speed, 0.0)
        worst = along.min(axis=2)  # the worst heading per position
        out: dict[str, Any] = {
            "positions": int(worst.size),
            "headings": int(self.headings.size),
            "largest_force_uN": float(np.nanmax(self.force) * 1e6) if held.any() else 0.0,
            "largest_torque_uNm": float(self.torque.max() * 1e6),
            "largest_field_mT": float(self.field.max() * 1e3),
            "poses_held_share": float(held.mean()),
            "speed_along_axis_mm_s": {
                "worst": float(worst.min() * 1e3),
                "median": float(np.median(worst) * 1e3),
                "best": float(along.max() * 1e3),
            },
        }
        if self.reaches is not None and self.asked is not None:
            out["speed_asked_mm_s"] = self.asked * 1e3
            out["feasible_share"] = float(self.reaches.mean())
            out["feasible"] = bool(self.reaches.all())
        return out


def workspace_capability(
    model: PlanarFieldModel,
    robot: RobotParams,
    max_current: float | ArrayLike,
    half_width: float,
    points: int = 11,
    headings: int = 8,
    speed: float | None = None,
) -> WorkspaceCapability:
    """The module doc's figures on a ``points`` × ``points`` grid over the square
    ±``half_width`` (m) and ``headings`` headings, the robot moving along its axis; with a
    ``speed`` (m/s), also whether it can move at that speed in each of the headings'
    directions with some heading (:func:`reachable`)."""
    n = model.coils.n_channels
    limits = _limits(max_current, n)
    axis = np.linspace(-half_width, half_width, points)
    thetas = np.arange(headings) * (2 * math.pi / headings)
    grid = np.stack(np.meshgrid(axis, axis), axis=-1)  # (ny, nx, 2): [i, j] = (x_j, y_i)
    sites = _sites(model, robot, limits, grid)  # row-major: site i·points + j
    speed_here = np.full((points, points, headings), math.nan)
    field = np.array([largest_field(site) for site in sites]).reshape(points, points)
    reaches = None if speed is None else np.zeros((points, points, headings), dtype=bool)
    for i in range(points):
        for j in range(points):
            here = sites[i * points + j]
            for k, theta in enumerate(thetas):
                h = np.array([math.cos(theta), math.sin(theta)])
                # at a unit speed (1 m/s) along the axis, the factor is the speed itself
                cap = pose_capability(here, float(theta), h)
                speed_here[i, j, k] = cap.speed_factor
                if reaches is not None and speed is not None:
                    reaches[i, j, k] = (
                        cap.speed_factor >= REACHED * speed
                        or reachable(here, float(theta), speed * h)[0] >= REACHED
                    )
    return WorkspaceCapability(
        axis, axis, thetas.astype(np.float64), speed_here, field, robot.drag_parallel,
        robot.moment, reaches, speed,
    )  # fmt: skip


@dataclass(frozen=True)
class TrajectoryCapability:
    """:func:`trajectory_capability`'s verdict on a reference trajectory."""

    t: FloatArray  # s, the poses checked
    poses: FloatArray  # (n, 3), m and rad
    #: per pose, the largest factor on the reference's velocity (NaN: not holdable)
    factor: FloatArray
    speed: FloatArray  # m/s, the reference's speed at each pose
    #: rad, the heading offset from the reference's at which ``factor`` holds (0: its own)
    heading_offset: FloatArray
    turn_rate: FloatArray  # rad/s, the reference's at each pose

    @property
    def feasible(self) -> bool:
        """Whether every pose's velocity is reached (to :data:`REACHED`)."""
        return bool(np.all(self.factor >= REACHED))

    def worst(self) -> int:
        """Index of the pose with the least factor (an unholdable one first)."""
        f = np.where(np.isfinite(self.factor), self.factor, -1.0)
        return int(np.argmin(f))


def trajectory_capability(
    model: PlanarFieldModel,
    robot: RobotParams,
    max_current: float | ArrayLike,
    reference: Trajectory,
    samples: int = 400,
    first: bool = False,
) -> TrajectoryCapability:
    """Check ``reference`` at ``samples`` evenly spaced times: at each, can the coils give
    the velocity and turn rate it asks (central differences) while holding the heading's
    field (module doc)? With ``first``, stop at the first pose they cannot (the result then
    ends there)."""
    n = model.coils.n_channels
    limits = _limits(max_current, n)
    t = np.linspace(0.0, reference.duration, samples)
    poses = reference.pose(t)
    rates = np.gradient(poses, t, axis=0)  # (samples, 3): vx, vy, ω
    sites = _sites(model, robot, limits, poses[:, :2])
    factor = np.full(samples, math.nan)
    offset = np.zeros(samples)
    for k, site in enumerate(sites):
        factor[k], offset[k] = reachable(site, float(poses[k, 2]), rates[k, :2], float(rates[k, 2]))
        if first and not factor[k] >= REACHED:
            samples = k + 1
            break
    speed = np.hypot(rates[:, 0], rates[:, 1])
    cut = slice(0, samples)
    return TrajectoryCapability(
        t[cut], poses[cut], factor[cut], speed[cut], offset[cut], rates[cut, 2]
    )


#: the speed factor a planned heading keeps in hand where the reference's own heading cannot
#: be held somewhere along it: on the three-coil system of docs/systems.md (S at 1 mm/s,
#: 6 seeds) 1.5 and 2 each lost the robot in a trial, 2.5 in none
HELD_SPARE = 2.5
#: heading offsets tried, rad: 5° apart up to a half turn either way
HELD_OFFSETS = np.radians(np.arange(5.0, 180.1, 5.0))
#: poses checked along the reference, and the offsets' moving average (in poses, odd): a
#: heading planned to swing as fast as the check's pose spacing would be a new task
HELD_SAMPLES = 400
HELD_SMOOTHING = 9


@dataclass(frozen=True)
class HeldReference:
    """:func:`held_reference`'s result."""

    #: the reference with held headings (the reference object itself where its own holds)
    trajectory: Trajectory
    #: rad, per checked pose: the heading offset chosen there (before smoothing)
    offsets: FloatArray
    #: per checked pose, the speed factor at that heading (NaN: no heading holds there)
    factor: FloatArray

    @property
    def median_factor(self) -> float:
        """How many times over the coils give the reference's velocity, median over its
        poses (NaN-free ones): how strong the system is for this task."""
        finite = self.factor[np.isfinite(self.factor)]
        return float(np.median(finite)) if finite.size else math.nan


def held_reference(
    model: PlanarFieldModel,
    robot: RobotParams,
    max_current: float | ArrayLike,
    reference: Trajectory,
) -> HeldReference:
    """The reference with the headings the coils can hold.

    ``reference`` itself, and zero offsets, where :func:`pose_capability` reaches its
    velocity and turn rate at its own heading (to :data:`REACHED`) at each of
    :data:`HELD_SAMPLES` poses. Else, at each pose, its own heading where the coils give
    that velocity :data:`HELD_SPARE` times over, or the nearest heading that they do (5°
    steps, the side of the previous pose's offset first), or the previous pose's offset
    where none does; the offsets are smoothed (a moving average over :data:`HELD_SMOOTHING`
    poses) and added to the reference's headings, on the reference's times and the
    samples' together."""
    n = model.coils.n_channels
    limits = _limits(max_current, n)
    t = np.linspace(0.0, reference.duration, HELD_SAMPLES)
    poses = reference.pose(t)
    rates = np.gradient(poses, t, axis=0)
    sites = _sites(model, robot, limits, poses[:, :2])

    def factor(k: int, offset: float) -> float:
        cap = pose_capability(sites[k], float(poses[k, 2]) + offset, rates[k, :2], rates[k, 2])
        return cap.speed_factor

    factors = np.array([factor(k, 0.0) for k in range(HELD_SAMPLES)])
    offsets = np.zeros(HELD_SAMPLES)
    if np.all(factors >= REACHED):
        return HeldReference(reference, offsets, factors)
    previous = 0.0
    for k in range(HELD_SAMPLES):
        if factors[k] >= HELD_SPARE:
            previous = 0.0
        else:
            side = -1.0 if previous < 0 else 1.0
            tries = np.ravel(np.column_stack([side * HELD_OFFSETS, -side * HELD_OFFSETS]))
            best, at = reachable(
                sites[k], float(poses[k, 2]), rates[k, :2], rates[k, 2], tries, HELD_SPARE
            )  # fmt: skip
            if best >= HELD_SPARE:
                previous, factors[k] = at, best
            else:
                factors[k] = factor(k, previous)
        offsets[k] = previous
    return HeldReference(held_trajectory(reference, offsets), offsets, factors)


def held_trajectory(reference: Trajectory, offsets: FloatArray) -> Trajectory:
    """``reference`` with :func:`held_reference`'s heading ``offsets`` (rad, one per checked
    pose) smoothed and added to its headings."""
    t = np.linspace(0.0, reference.duration, HELD_SAMPLES)
    half = HELD_SMOOTHING // 2
    padded = np.pad(offsets, half, mode="edge")
    smooth = np.convolve(padded, np.ones(HELD_SMOOTHING) / HELD_SMOOTHING, mode="valid")
    # on the reference's own times and the samples': a reference of a few knots (a polyline
    # drawn by hand) would otherwise keep the offsets only where its knots fall
    t_out = np.union1d(reference.t, t)
    poses_out = reference.pose(t_out)
    poses_out[:, 2] += np.interp(t_out, t, smooth)
    return Trajectory(t_out, poses_out)
