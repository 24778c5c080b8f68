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
    keep = np.concatenate([[True], np.hypot(*np.diff(points, axis=0).T) > 1e-12])
    return _path_to_trajectory(points[keep], headings[keep], speed)


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
