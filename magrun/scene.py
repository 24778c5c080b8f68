"""Reference trajectories and workspace walls (SI units: m, s, rad).

A :class:`Trajectory` is a densely sampled, timed pose path ``(t, x, y, θ)`` with θ unwrapped;
:meth:`Trajectory.pose` interpolates it at any times and holds the end pose afterwards.
Builders make the paper's paths:

    >>> from magrun.scene import s_trajectory
    >>> ref = s_trajectory()                      # 43 x 43 mm S, 3 mm/s, heading along the path
    >>> round(ref.duration, 1)
    51.2

:class:`Walls` are line segments the robot's body cannot cross (the container, the spine
phantom's channel); the simulated rig resolves contact against them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Trajectory:
    """A timed reference path.

    Attributes
    ----------
    t : ndarray, shape (n,)
        Increasing times, s, from 0.
    poses : ndarray, shape (n, 3)
        ``(x, y, θ)`` in m and rad, θ continuous (unwrapped) along the path.
    """

    t: FloatArray
    poses: FloatArray

    def __post_init__(self) -> None:
        if self.t.ndim != 1 or self.poses.shape != (self.t.size, 3) or self.t.size < 2:
            raise ValueError("Trajectory needs t (n,) and poses (n, 3) with n >= 2")
        if np.any(np.diff(self.t) <= 0):
            raise ValueError("Trajectory times must increase")

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def pose(self, t: ArrayLike) -> FloatArray:
        """Reference pose(s) at time(s) ``t``, shape (..., 3); the end pose is held after."""
        tq = np.asarray(t, dtype=np.float64)
        return np.stack([np.interp(tq, self.t, self.poses[:, k]) for k in range(3)], axis=-1)


def distinct_places(points: ArrayLike) -> NDArray[np.bool_]:
    """Which of a polyline's points (n, 2), m, to keep: each one more than 1e-12 m (a
    rounding error) from the one before it; a repeated point is one place."""
    p = np.asarray(points, dtype=np.float64)
    return np.concatenate([[True], np.hypot(*np.diff(p, axis=0).T) > 1e-12])


def _path_to_trajectory(points: FloatArray, headings: FloatArray, speed: float) -> Trajectory:
    seg = np.hypot(*np.diff(points, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return Trajectory(t=s / speed, poses=np.column_stack([points, np.unwrap(headings)]))


def s_trajectory(
    size: float = 0.043, speed: float = 0.003, center: tuple[float, float] = (0.0, 0.0)
) -> Trajectory:
    """The paper's S-shaped trajectory inside a ``size`` × ``size`` square (Section III-A).

    Three horizontal legs joined by two half-circles of radius ``size``/4, traversed at
    constant ``speed`` (m/s) from the top-right corner, the robot's axis along the path::

        ◄──────────┐ start
        (             top leg, leftwards, then a left half-circle down
        └─────────►
                  )   middle leg, rightwards, then a right half-circle down
        ◄─────────┘   bottom leg, leftwards, to the bottom-left corner
    """
    a, r = size / 2, size / 4
    cx, cy = center
    pts: list[FloatArray] = []
    hdg: list[FloatArray] = []

    def line(p0: tuple[float, float], p1: tuple[float, float]) -> None:
        n = max(2, math.ceil(math.dist(p0, p1) / 2e-4))
        u = np.linspace(0, 1, n)[:, None]
        pts.append(np.asarray(p0) + u * (np.asarray(p1) - np.asarray(p0)))
        hdg.append(np.full(n, math.atan2(p1[1] - p0[1], p1[0] - p0[0])))

    def half_circle(c: tuple[float, float], start_angle: float, direction: int) -> None:
        n = max(3, math.ceil(math.pi * r / 2e-4))
        phi = start_angle + direction * np.linspace(0, math.pi, n)
        pts.append(np.column_stack([c[0] + r * np.cos(phi), c[1] + r * np.sin(phi)]))
        hdg.append(phi + direction * math.pi / 2)

    line((a, a), (-a + r, a))
    half_circle((-a + r, a - r), math.pi / 2, +1)  # counter-clockwise on the left
    line((-a + r, 0.0), (a - r, 0.0))
    half_circle((a - r, -r), math.pi / 2, -1)  # clockwise on the right
    line((a - r, -a), (-a, -a))
    points = np.concatenate(pts) + np.array([cx, cy])
    headings = np.concatenate(hdg)
    # drop the duplicated joints so that time stays strictly increasing
    keep = distinct_places(points)
    return _path_to_trajectory(points[keep], headings[keep], speed)


def out_and_back(
    points: ArrayLike, speed: float = 0.003, hold: float = 5.0, flip: float = 3.0
) -> Trajectory:
    """Along a polyline, hold, turn round in place, and back (the spine experiment).

    The robot's axis follows the path out at ``speed`` (m/s), station-keeps ``hold`` s at the
    far end, turns by +180° in place over ``flip`` s (uniformly), and comes back along the
    same path, heading home, to the start. ``points`` (n, 2) in m.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise ValueError("out_and_back needs a path of at least 2 points (n, 2)")
    pts = pts[distinct_places(pts)]
    d = np.diff(pts, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    heading = np.append(heading, heading[-1])  # vertex i takes segment i's direction
    out = _path_to_trajectory(pts, heading, speed)
    t_far = out.duration
    theta_far = float(out.poses[-1, 2])
    n_flip = 25
    flip_t = t_far + hold + np.linspace(0.0, flip, n_flip)
    flip_theta = theta_far + np.linspace(0.0, math.pi, n_flip)
    back = _path_to_trajectory(pts[::-1], heading[::-1] + math.pi, speed)
    t0_back = t_far + hold + flip
    t = np.concatenate(
        [out.t, [t_far + hold] if hold > 0 else [], flip_t[1:], back.t[1:] + t0_back]
    )
    far = pts[-1]
    poses = np.concatenate(
        [
            out.poses,
            np.array([[far[0], far[1], theta_far]])[: 1 if hold > 0 else 0],
            np.column_stack(
                [np.full(n_flip - 1, far[0]), np.full(n_flip - 1, far[1]), flip_theta[1:]]
            ),
            back.poses[1:],
        ]
    )
    return Trajectory(t=t, poses=poses)


def lead_headings(reference: Trajectory, boundary: ArrayLike, lead: float) -> Trajectory:
    """``reference`` with the heading of each pose on the move replaced by the path's heading
    ``lead`` (m) further along it where that heading points further from ``boundary`` (a
    polyline (n, 2), m: a phantom's critical wall); ``reference`` itself where no heading
    changes.

    In a bend whose outer wall is ``boundary`` the heading is then the one the robot needs
    ``lead`` further on: a robot that far ahead of its estimate along the bend is still
    turned along the channel, not into that wall. Along a straight run, in a bend that
    turns toward ``boundary``, and where the robot holds or turns in place, the headings stay
    as they are. "Further from" compares each heading's unit vector with the normal from
    ``boundary``'s nearest point to the pose. A leg (a run of poses on the move) takes
    headings from itself only, its last heading beyond its end.
    """
    poses = reference.poses
    xy = poses[:, :2]
    step = np.hypot(*np.diff(xy, axis=0).T)
    wall = np.asarray(boundary, dtype=np.float64).reshape(-1, 2)
    if lead <= 0 or len(wall) < 2 or not np.any(step > 0):
        return reference
    normal = _normals_from(wall, xy)
    theta = poses[:, 2].copy()
    # legs: the runs of consecutive poses joined by a move
    breaks = np.flatnonzero(step <= 0)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [len(xy) - 1]])
    for i0, i1 in zip(starts, ends, strict=True):
        if i1 <= i0:
            continue
        s = np.concatenate([[0.0], np.cumsum(step[i0:i1])])
        leg = poses[i0 : i1 + 1, 2]
        ahead = np.interp(s + lead, s, leg)
        n = normal[i0 : i1 + 1]
        here = np.cos(leg) * n[:, 0] + np.sin(leg) * n[:, 1]
        there = np.cos(ahead) * n[:, 0] + np.sin(ahead) * n[:, 1]
        better = there > here + 1e-12
        theta[i0 : i1 + 1] = np.where(better, ahead, leg)
    if np.array_equal(theta, poses[:, 2]):
        return reference
    return Trajectory(reference.t, np.column_stack([xy, theta]))


def _normals_from(wall: FloatArray, points: FloatArray) -> FloatArray:
    """The unit vectors (m, 2) from the polyline ``wall``'s nearest point to each of
    ``points`` (m, 2), in blocks of about a million point-segment pairs (a dense outline and
    a long path need no more memory than that)."""
    a, ab = wall[:-1], np.diff(wall, axis=0)
    length2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-300)
    out = np.empty_like(points)
    block = max(1, 1_000_000 // len(a))
    for k in range(0, len(points), block):
        rel = points[k : k + block, None, :] - a[None]  # (points, segments, 2)
        u = np.clip(np.einsum("pij,ij->pi", rel, ab) / length2, 0.0, 1.0)
        gap = rel - u[..., None] * ab
        dist = np.hypot(gap[..., 0], gap[..., 1])
        nearest = np.argmin(dist, axis=1)
        rows = np.arange(len(rel))
        out[k : k + block] = gap[rows, nearest] / np.maximum(dist[rows, nearest], 1e-300)[:, None]
    return out


def capsule_disks(half_axis: float, radius: float) -> FloatArray:
    """Offsets (m) along a capsule's axis of the disks :meth:`Walls.resolve_capsule` tests."""
    n_disk = math.ceil(2 * half_axis / (radius / 2)) + 1 if half_axis > 0 else 1
    return np.linspace(-half_axis, half_axis, n_disk) if n_disk > 1 else np.zeros(1)


@dataclass(frozen=True)
class Walls:
    """Straight wall segments, shape (n, 2, 2): ``segments[i] = [[x0, y0], [x1, y1]]`` in m."""

    segments: FloatArray

    @classmethod
    def box(cls, half_width: float) -> Walls:
        """The four walls of the square |x|, |y| ≤ half_width."""
        h = half_width
        c = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        return cls(np.stack([c, np.roll(c, -1, axis=0)], axis=1))

    def __add__(self, other: Walls) -> Walls:
        return Walls(np.concatenate([self.segments, other.segments]))

    def distances(self, p: ArrayLike) -> FloatArray:
        """Distance from point ``p`` (2,) to every segment, m, shape (n,)."""
        return np.hypot(*(np.asarray(p, dtype=np.float64) - self._closest(p)).T)

    def _closest(self, p: ArrayLike) -> FloatArray:
        a, b = self.segments[:, 0], self.segments[:, 1]
        ab = b - a
        u = np.clip(
            np.einsum("ij,ij->i", np.asarray(p) - a, ab) / np.einsum("ij,ij->i", ab, ab), 0, 1
        )
        return a + u[:, None] * ab

    def resolve(
        self, p: FloatArray, v: FloatArray, radius: float
    ) -> tuple[FloatArray, FloatArray, bool]:
        """Push a disk of ``radius`` at ``p`` out of every wall it penetrates.

        Contact is inelastic and frictionless: the position moves back to touching distance
        and the velocity loses its component into the wall. Returns ``(p, v, touched)``.
        """
        if self.segments.size == 0:
            return p, v, False
        touched = False
        for _ in range(3):  # corners: a push out of one wall can press into its neighbour
            q = self._closest(p)
            d = p - q
            dist = np.hypot(d[:, 0], d[:, 1])
            i = int(np.argmin(dist))
            if dist[i] >= radius:
                break
            touched = True
            n = d[i] / dist[i] if dist[i] > 1e-12 else np.array([0.0, 0.0])
            p = q[i] + radius * n
            vn = float(v @ n)
            if vn < 0:
                v = v - vn * n
        return p, v, touched

    def resolve_capsule(
        self,
        state: tuple[float, ...],
        half_axis: float,
        radius: float,
        translational_drag: float,
        rotational_drag: float,
        iterations: int = 16,
        wall_friction: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[tuple[float, ...], bool]:
        """:meth:`resolve` for a capsule body, translating and turning it out of the walls.

        The body is disks of ``radius`` along its axis, at most ``radius``/2 apart over
        ±``half_axis`` (a wall slips between two by under 3 % of the radius). For the deepest
        penetration, of depth δ along the wall normal n at arm r from the centre, the body
        moves as a drag-dominated body would under a contact force along n: with mobilities
        1/c_t (translation) and 1/c_r (rotation) and w = 1/c_t + (r × n)²/c_r,

            Δp = n δ / (c_t w),   Δθ = (r × n) δ / (c_r w),

        and the contact point's velocity into the wall is removed the same way (inelastic,
        frictionless). Repeated up to ``iterations`` times, for corners and for a body jammed
        across a channel (the plant's 1 ms steps leave µm penetrations: a pass or two). A flat
        side resting on a wall is pushed at the middle of its equally deep disks (no turn).
        ``state`` is ``(x, y, θ, vx, vy, ω)``; returns the new state and whether it touched.

        ``wall_friction`` = (μ_k, μ_s, h): Coulomb friction at the contact (0: frictionless),
        for a plant stepped by h s. A drag-dominated body pressed into a wall by a force F_n
        sinks δ = F_n h / c_t into it in a step, and its contact point moves s = v_t h along
        it: the contact point's slide is cut by μ_k δ (kinetic), or to nothing where
        |s| ≤ μ_s δ (it sticks), which is |F_t| reduced by μ_k F_n, or held while
        |F_t| ≤ μ_s F_n (the same mobilities as the push; the tangential velocity with it).
        """
        x, y, th, vx, vy, om = state
        if self.segments.size == 0:
            return state, False
        s = capsule_disks(half_axis, radius)
        a, b = self.segments[:, 0], self.segments[:, 1]
        ab = b - a
        den = np.einsum("ij,ij->i", ab, ab)
        touched = False
        for _ in range(iterations):
            axis = np.array([math.cos(th), math.sin(th)])
            pts = np.array([x, y]) + s[:, None] * axis  # (m, 2)
            rel = pts[:, None, :] - a[None]  # (m, n, 2)
            u = np.clip(np.einsum("mnk,nk->mn", rel, ab) / den, 0.0, 1.0)
            d = rel - u[..., None] * ab[None]
            dist = np.hypot(d[..., 0], d[..., 1])
            i, j = np.unravel_index(int(np.argmin(dist)), dist.shape)
            if dist[i, j] >= radius * (1 - 1e-9):
                break
            touched = True
            if dist[i, j] > 1e-12:
                n = d[i, j] / dist[i, j]
            else:  # centre on the wall line: push along the wall's normal toward the body
                n = np.array([-ab[j, 1], ab[j, 0]]) / math.sqrt(den[j])
            # a flat side resting on the wall: act at the middle of the equally deep disks
            level = dist[:, j] <= dist[i, j] + 1e-3 * radius
            r = float(np.mean(s[level])) * axis
            rxn = float(r[0] * n[1] - r[1] * n[0])
            w = 1.0 / translational_drag + rxn * rxn / rotational_drag
            depth = radius - float(dist[i, j])
            x += n[0] * depth / (translational_drag * w)
            y += n[1] * depth / (translational_drag * w)
            th += rxn * depth / (rotational_drag * w)
            # velocity of the contact point along n
            vc = vx * n[0] + vy * n[1] + om * rxn
            if vc < 0:
                impulse = -vc / w
                vx += n[0] * impulse / translational_drag
                vy += n[1] * impulse / translational_drag
                om += rxn * impulse / rotational_drag
            if wall_friction[0] > 0 or wall_friction[1] > 0:
                x, y, th, vx, vy, om = _wall_friction(
                    (x, y, th, vx, vy, om), n, r, depth, translational_drag, rotational_drag,
                    wall_friction,
                )  # fmt: skip
        return (x, y, th, vx, vy, om), touched


def _wall_friction(
    state: tuple[float, ...],
    n: FloatArray,
    r: FloatArray,
    depth: float,
    translational_drag: float,
    rotational_drag: float,
    friction: tuple[float, float, float],
) -> tuple[float, ...]:
    """Coulomb friction at a wall contact (:meth:`Walls.resolve_capsule`): the contact point
    at arm ``r`` slides v_t h along the wall (tangent t = n rotated by +90°); cut it by
    μ_k ``depth``, or to nothing where it is at most μ_s ``depth``."""
    x, y, th, vx, vy, om = state
    mu_k, mu_s, h = friction
    tx, ty = -float(n[1]), float(n[0])
    rxt = float(r[0] * ty - r[1] * tx)
    vt = vx * tx + vy * ty + om * rxt
    slide = vt * h
    if abs(slide) <= mu_s * depth:
        cut = -slide
    else:
        cut = -math.copysign(min(mu_k * depth, abs(slide)), slide)
    if cut == 0.0:
        return state
    wt = 1.0 / translational_drag + rxt * rxt / rotational_drag
    x += tx * cut / (translational_drag * wt)
    y += ty * cut / (translational_drag * wt)
    th += rxt * cut / (rotational_drag * wt)
    dv = cut / (h * wt)  # the same impulse on the velocities
    vx += tx * dv / translational_drag
    vy += ty * dv / translational_drag
    om += rxt * dv / rotational_drag
    return x, y, th, vx, vy, om
