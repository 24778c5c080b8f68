"""Where the robot's body can be: the workspace square, or a phantom's channel inside it.

The controllers are given the workspace geometry the protocol declares, as a
:class:`FreeSpace`: the boundary polylines (a phantom's, in file order closing its outline;
for the open workspace the square's four walls), which of them is ``critical``, and the
robot's body, a capsule of length L and diameter D (a segment of length L − D, radius D/2).
Three things are built on it:

- :meth:`FreeSpace.project`: a pose moved into the space the body can occupy (inside the
  outline, the body clear of every boundary). The controller passes every estimate through
  it, so an estimate cannot leave the channel, whatever the measurements or the planner do.
- :meth:`FreeSpace.across`: at a pose, the critical boundary's normal and how far the body
  can move along it each way before it meets a wall (:meth:`FreeSpace.play`): the free
  interval the Kalman filter conditions its estimate on at each measurement
  (:meth:`magrun.control.estimation.KalmanPoseFilter.truncate`).
- :meth:`FreeSpace.corridor`: at given positions, the critical boundary's nearest point as
  a half-plane ``n·p ≥ c`` that the body's two end points must satisfy, its margin
  tightened by the estimate's uncertainty: the NMPC's corridor constraint
  (:mod:`magrun.control.nmpc`). With the body's ends on the free side, its heading is limited
  where the channel is narrow.

All lengths in metres.

    >>> fs = FreeSpace.square(0.05, length=0.016, diameter=0.0028)
    >>> fs.project([0.06, 0.0, 0.0])[0].round(4)          # pushed back inside the square
    np.float64(0.0486)
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.phantom import point_to_segments, segment_distances
from magrun.scene import Walls, capsule_disks

FloatArray = NDArray[np.float64]

#: a half-plane that never binds: n = 0, c = −∞ (as finite numbers for the solver), m
INACTIVE = (0.0, 0.0, -1.0)


@dataclass(frozen=True)
class FreeSpace:
    """A closed outline of named boundaries and the capsule body that moves inside it.

    Parameters
    ----------
    boundaries : dict of str to ndarray, shape (n, 2)
        Polylines, m, that in this order close the outline.
    critical : str or None
        The boundary whose clearance matters (its margin is tightened by the estimate's
        uncertainty), or None.
    length, diameter : float
        The robot's body, m.
    """

    boundaries: dict[str, FloatArray]
    critical: str | None
    length: float
    diameter: float
    _segments: dict[str, tuple[FloatArray, FloatArray]] = field(
        init=False, repr=False, compare=False
    )
    _fitting: FloatArray | None = field(init=False, repr=False, compare=False, default=None)
    _groups: dict[tuple[str, ...], tuple[FloatArray, ...]] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )
    _column_groups: dict[tuple[str, ...], tuple[FloatArray, ...]] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )
    #: :meth:`_fits`' shortcut: the grid's origin (x, y), pitch, and which of its cells hold
    #: only centres at which the body fits at every heading (:meth:`_sure_cells`)
    _sure: tuple[float, float, float, NDArray[np.bool_]] | None = field(
        init=False, repr=False, compare=False, default=None
    )

    def __post_init__(self) -> None:
        outline = np.concatenate(list(self.boundaries.values()))
        x, y = outline[:, 0], outline[:, 1]
        area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
        side = 1.0 if area > 0 else -1.0  # counter-clockwise: the interior is on the left
        segs: dict[str, tuple[FloatArray, FloatArray]] = {}
        for name, line in self.boundaries.items():
            s = np.stack([line[:-1], line[1:]], axis=1)
            d = s[:, 1] - s[:, 0]
            keep = np.hypot(d[:, 0], d[:, 1]) > 1e-12
            s, d = s[keep], d[keep]
            inward = (
                side * np.column_stack([-d[:, 1], d[:, 0]]) / np.hypot(d[:, 0], d[:, 1])[:, None]
            )
            segs[name] = (s, inward)
        object.__setattr__(self, "_segments", segs)
        object.__setattr__(self, "_fitting", self._fitting_poses())
        object.__setattr__(self, "_sure", self._sure_cells())

    @classmethod
    def square(cls, half_width: float, length: float, diameter: float) -> FreeSpace:
        """The open workspace: the square |x|, |y| ≤ ``half_width``, no critical boundary."""
        h = half_width
        corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h], [-h, -h]])
        return cls({"workspace": corners}, None, length, diameter)

    @property
    def radius(self) -> float:
        return self.diameter / 2

    @property
    def half_axis(self) -> float:
        """Half the length of the body's axis segment (the capsule's end-cap centres), m."""
        return max(self.length / 2 - self.diameter / 2, 0.0)

    def walls(self) -> Walls:
        return Walls(np.concatenate([s for s, _ in self._segments.values()]))

    def nearest(self, points: ArrayLike, names: list[str]) -> tuple[FloatArray, FloatArray]:
        """Nearest point of the named boundaries to each point, and the normal into the free
        side there. ``points`` (m, 2); returns ``(q, n)``, each (m, 2)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if len(p) == 1:  # the NMPC's start, every tick: as floats (the same numbers)
            q0x, q0y, n0x, n0y = self._nearest_xy(float(p[0, 0]), float(p[0, 1]), tuple(names))
            return np.array([[q0x, q0y]]), np.array([[n0x, n0y]])
        a, ab, ab2, inward = self._group(tuple(names))
        px, py = p[:, :1], p[:, 1:]
        u = np.clip(((px - a[:, 0]) * ab[:, 0] + (py - a[:, 1]) * ab[:, 1]) / ab2, 0.0, 1.0)
        qx, qy = a[:, 0] + u * ab[:, 0], a[:, 1] + u * ab[:, 1]  # (m, n)
        d2 = (px - qx) ** 2 + (py - qy) ** 2
        j = np.argmin(d2, axis=1)
        rows = np.arange(len(p))
        qj = np.column_stack([qx[rows, j], qy[rows, j]])
        dj, nj = np.sqrt(d2[rows, j]), inward[j]
        # off a vertex the direction to the point is the smooth normal; its sign is the side
        r = p - qj
        with np.errstate(invalid="ignore", divide="ignore"):
            radial = r / dj[:, None]
        sign = np.where(np.sum(r * nj, axis=1) >= 0, 1.0, -1.0)
        n = np.where((dj > 1e-9)[:, None], sign[:, None] * radial, nj)
        return qj, n

    def _nearest_xy(
        self, px: float, py: float, names: tuple[str, ...]
    ) -> tuple[float, float, float, float]:
        """:meth:`nearest` for one point, as floats: the nearest point (qx, qy) and the
        normal (nx, ny). The vectorised path's operations, element by element in the same
        order, on contiguous columns and in place: the same numbers to the last bit, in
        under half the time."""
        ax, ay, bx, by, ab2, inward = self._columns(names)
        u = px - ax
        u *= bx
        t = py - ay
        t *= by
        u += t
        u /= ab2
        np.clip(u, 0.0, 1.0, out=u)
        qx = u * bx
        qx += ax
        qy = u * by
        qy += ay
        d2 = px - qx
        d2 *= d2
        t = py - qy
        t *= t
        d2 += t
        j = int(np.argmin(d2))
        qjx, qjy = float(qx[j]), float(qy[j])
        dj = math.sqrt(d2[j])
        rx, ry = px - qjx, py - qjy
        if dj > 1e-9:  # off a vertex the direction to the point; its sign is the side
            njx, njy = float(inward[j, 0]), float(inward[j, 1])
            sign = 1.0 if rx * njx + ry * njy >= 0 else -1.0
            return qjx, qjy, sign * (rx / dj), sign * (ry / dj)
        return qjx, qjy, float(inward[j, 0]), float(inward[j, 1])

    def _columns(self, names: tuple[str, ...]) -> tuple[FloatArray, ...]:
        """:meth:`_group`'s segment starts and directions as contiguous columns (x, y),
        with the squared lengths and inward normals (cached)."""
        if names not in self._column_groups:
            a, ab, ab2, inward = self._group(names)
            columns = (np.ascontiguousarray(c) for c in (a[:, 0], a[:, 1], ab[:, 0], ab[:, 1]))
            self._column_groups[names] = (*columns, ab2, inward)
        return self._column_groups[names]

    def _group(self, names: tuple[str, ...]) -> tuple[FloatArray, ...]:
        """Segment starts, directions, squared lengths and inward normals of the named
        boundaries, joined (cached: the corridor asks for them every control tick)."""
        if names not in self._groups:
            segs = np.concatenate([self._segments[k][0] for k in names])
            inward = np.concatenate([self._segments[k][1] for k in names])
            ab = segs[:, 1] - segs[:, 0]
            self._groups[names] = (segs[:, 0], ab, np.sum(ab * ab, axis=1), inward)
        return self._groups[names]

    def corridor(
        self,
        positions: ArrayLike,
        covariance: FloatArray | None,
        margin: float,
        sigmas: float,
        share: float,
    ) -> FloatArray:
        """The NMPC's corridor at each position: half-planes ``(nx, ny, c)``, shape (m, 3),
        from the critical boundary's nearest point q and its normal n into the free side: the
        body's end points e must satisfy ``n·e ≥ c = n·q + D/2 + margin'``, with the margin
        ``margin + min(sigmas · σ_n, share · free width)`` (σ_n: the position ``covariance``'s
        standard deviation along the boundary's normal; free width: :meth:`free_width` less
        the body's diameter and twice ``margin``); :data:`INACTIVE` rows without a critical
        boundary."""
        p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        out = np.empty((len(p), 3))
        out[:] = INACTIVE
        if self.critical is None:
            return out
        if len(p) == 1:
            out[0] = self._corridor_one(float(p[0, 0]), float(p[0, 1]), covariance, margin,
                                        sigmas, share)  # fmt: skip
            return out
        return self._corridor_many(p, out, covariance, margin, sigmas, share)

    def _corridor_many(
        self, p: FloatArray, out: FloatArray, covariance: FloatArray | None, margin: float,
        sigmas: float, share: float,
    ) -> FloatArray:  # fmt: skip
        """:meth:`corridor` at the points ``p`` (m, 2), vectorised, into ``out`` (m, 3)."""
        assert self.critical is not None
        q1, n1 = self.nearest(p, [self.critical])
        extra = np.zeros(len(p))
        if covariance is not None:
            var = np.einsum("ki,ij,kj->k", n1, covariance, n1)
            free = self._width(p, q1, n1) - self.diameter - 2 * margin
            extra = np.minimum(sigmas * np.sqrt(np.maximum(var, 0.0)), share * np.maximum(free, 0))
        out[:, :2] = n1
        out[:, 2] = np.sum(n1 * q1, axis=1) + self.radius + margin + extra
        return out

    def _corridor_one(
        self, px: float, py: float, covariance: FloatArray | None, margin: float,
        sigmas: float, share: float,
    ) -> tuple[float, float, float]:  # fmt: skip
        """:meth:`corridor` for one point (the NMPC's start, every tick): the vectorised
        path's arithmetic on floats, in its order (the variance as its einsum sums one row),
        so the same half-plane to the last bit (NaN where it gives NaN), in under half the
        time."""
        assert self.critical is not None
        q1x, q1y, n1x, n1y = self._nearest_xy(px, py, (self.critical,))
        extra = 0.0
        if covariance is not None:
            c = covariance  # n·C·n, summed as einsum sums one row
            var = (n1x * c[0, 0] * n1x + n1x * c[0, 1] * n1y) + (
                n1y * c[1, 0] * n1x + n1y * c[1, 1] * n1y
            )
            width = math.inf
            others = self._others
            if others:
                q2x, q2y, n2x, n2y = self._nearest_xy(px, py, others)
                facing = -(n1x * n2x + n1y * n2y)
                across = n2x * (q2x - q1x) + n2y * (q2y - q1y)
                if facing > 0.1:
                    width = -across / facing
            free = width - self.diameter - 2 * margin
            chance, cap = sigmas * math.sqrt(max(var, 0.0)), share * max(free, 0.0)
            # np.minimum's NaN: either NaN gives NaN (0 · ∞ where a share of 0 meets an
            # unbounded width, a NaN covariance)
            extra = math.nan if math.isnan(chance) or math.isnan(cap) else min(chance, cap)
        return n1x, n1y, (n1x * q1x + n1y * q1y) + self.radius + margin + extra

    @functools.cached_property
    def _others(self) -> tuple[str, ...]:
        """The boundaries other than the critical one, in their order."""
        return tuple(k for k in self.boundaries if k != self.critical)

    def free_width(self, positions: ArrayLike) -> FloatArray:
        """Width, m, of the free space across the critical boundary at each position: from
        its nearest point, along its normal, to the nearest other boundary's half-plane
        (∞ without a critical boundary or where the other boundary faces away)."""
        p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        if self.critical is None:
            return np.full(len(p), np.inf)
        q1, n1 = self.nearest(p, [self.critical])
        return self._width(p, q1, n1)

    def _width(self, p: FloatArray, q1: FloatArray, n1: FloatArray) -> FloatArray:
        if not self._others:
            return np.full(len(p), np.inf)
        q2, n2 = self.nearest(p, list(self._others))
        facing = -np.sum(n1 * n2, axis=1)  # 1 when the other wall is straight across
        across = np.sum(n2 * (q2 - q1), axis=1)  # the other wall's distance along its normal
        with np.errstate(divide="ignore", invalid="ignore"):
            width = np.where(facing > 0.1, -across / facing, np.inf)
        return width

    def contains(self, point: ArrayLike) -> bool:
        """Whether a point lies inside the outline (even-odd rule)."""
        return bool(self.inside(np.asarray(point, dtype=np.float64)[None, :2])[0])

    def inside(self, points: ArrayLike) -> NDArray[np.bool_]:
        """:meth:`contains` for many points (m, 2) at once."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        poly = np.concatenate([s[:, 0] for s, _ in self._segments.values()])
        a, b = poly[None], np.roll(poly, -1, axis=0)[None]
        x, y = p[:, :1], p[:, 1:]
        cross = (a[..., 1] > y) != (b[..., 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xi = a[..., 0] + (y - a[..., 1]) * (b[..., 0] - a[..., 0]) / (b[..., 1] - a[..., 1])
        return np.count_nonzero(cross & (x < xi), axis=1) % 2 == 1

    def project(self, pose: ArrayLike) -> FloatArray:
        """``pose`` (x, y, θ) moved into the free space: the centre inside the outline and the
        body clear of every boundary.

        A centre outside goes to the nearest boundary point, a body radius in; a body through
        a wall turns along it (to the nearer of the wall's two directions); then it is pushed
        and turned out as :meth:`Walls.resolve_capsule` does (translation and rotation of the
        tip equally cheap), up to three rounds. Where that does not settle (a body jammed in a
        corner), the nearest of a grid of poses that fit (0.5 mm or 1/60 of the
        outline, 11.25°; built with the free space, so that no control tick waits for it) is
        taken. A pose already in the free space is returned unchanged; a non-finite one as it
        is."""
        p = np.asarray(pose, dtype=np.float64).copy()
        if not np.all(np.isfinite(p)):
            return p
        if self._fits(p):
            return p
        names = list(self.boundaries)
        for _ in range(3):
            if self.contains(p[:2]) and self.clearance(p) >= -1e-7:
                return p
            if not self.contains(p[:2]):
                q, n = self.nearest(p[:2], names)
                p[:2] = q[0] + n[0] * self.radius * 1.001
            if self.clearance(p) < -self.radius / 2:  # an end cap's centre through a wall
                _, n = self.nearest(p[:2], names)
                along = math.atan2(n[0, 0], -n[0, 1])  # the wall's direction
                p[2] = along + round((p[2] - along) / math.pi) * math.pi
            state = (float(p[0]), float(p[1]), float(p[2]), 0.0, 0.0, 0.0)
            tip = max(self.length / 2, 1e-6)
            moved, _ = self.walls().resolve_capsule(
                state, self.half_axis, self.radius * 1.002, 1.0, tip * tip, iterations=64
            )
            p[:3] = moved[:3]
        if self.contains(p[:2]) and self.clearance(p) >= -1e-7:
            return p
        return self._nearest_fitting(np.asarray(pose, dtype=np.float64))

    def _fits(self, pose: FloatArray) -> bool:
        """A quick sufficient test that the body fits at ``pose``: centre inside, and every
        disk of the body (radius D/2, at most D/4 apart along the axis) clear of every wall
        by 5 % of the radius (the disks' outline dips under the capsule's by at most 3 %).

        A centre in one of :meth:`_sure_cells` passes at once (the estimate is there on most
        control ticks of an open workspace); the others are measured."""
        return self._in_sure_cell(pose) or self._fits_measured(pose)

    def _in_sure_cell(self, pose: FloatArray) -> bool:
        """Whether the centre of ``pose`` lies in one of :meth:`_sure_cells` (finite poses)."""
        assert self._sure is not None
        x0, y0, pitch, sure = self._sure
        i, j = math.floor((pose[0] - x0) / pitch), math.floor((pose[1] - y0) / pitch)
        return bool(0 <= i < sure.shape[0] and 0 <= j < sure.shape[1] and sure[i, j])

    def _fits_measured(self, pose: FloatArray) -> bool:
        """:meth:`_fits`' test measured: the centre inside, the body's disks clear."""
        if not self.contains(pose[:2]):
            return False
        a, ab, ab2, _ = self._group(tuple(self.boundaries))
        s = capsule_disks(self.half_axis, self.radius)
        px = pose[0] + s[:, None] * math.cos(pose[2])
        py = pose[1] + s[:, None] * math.sin(pose[2])
        u = np.clip(((px - a[:, 0]) * ab[:, 0] + (py - a[:, 1]) * ab[:, 1]) / ab2, 0.0, 1.0)
        d2 = (px - a[:, 0] - u * ab[:, 0]) ** 2 + (py - a[:, 1] - u * ab[:, 1]) ** 2
        return bool(d2.min() >= (1.05 * self.radius) ** 2)

    def _sure_cells(self) -> tuple[float, float, float, NDArray[np.bool_]]:
        """A grid over the outline's box (pitch 0.5 mm, or 1/60 of the box) and, per cell,
        whether every centre in it passes :meth:`_fits`' measured test at every heading: the
        cell's centre inside and at least ``half axis + 1.05 D/2 + half the cell's diagonal``
        (and a nanometre for rounding) from every wall. Then every point of the cell is inside
        (no wall within its reach) and every disk of a body centred there, at most the half axis
        from its centre, is 1.05 D/2 clear of every wall. Cells the body cannot be sure of (all,
        in a channel narrower than the body is long) are measured as before."""
        lo, hi, pitch = self._grid_box()
        n = np.maximum(np.ceil((hi - lo) / pitch).astype(int), 1)
        ii, jj = np.meshgrid(np.arange(n[0]), np.arange(n[1]), indexing="ij")
        centres = np.stack([lo[0] + (ii + 0.5) * pitch, lo[1] + (jj + 0.5) * pitch], axis=-1)
        flat = centres.reshape(-1, 2)
        segs = np.concatenate([s for s, _ in self._segments.values()])
        dist = point_to_segments(flat[:, None], segs[None, :, 0], segs[None, :, 1]).min(axis=1)
        need = self.half_axis + 1.05 * self.radius + pitch * math.sqrt(0.5) + 1e-9
        sure = (self.inside(flat) & (dist >= need)).reshape(ii.shape)
        return float(lo[0]), float(lo[1]), pitch, sure

    def _nearest_fitting(self, pose: FloatArray) -> FloatArray:
        """The grid pose that fits nearest to ``pose`` (heading compared modulo π, the
        capsule being symmetric, then turned to the nearer of θ, θ + π)."""
        grid = self._fitting
        assert grid is not None
        dth = (grid[:, 2] - pose[2] + math.pi / 2) % math.pi - math.pi / 2
        cost = np.hypot(grid[:, 0] - pose[0], grid[:, 1] - pose[1]) + self.half_axis * np.abs(dth)
        best = grid[int(np.argmin(cost))].copy()
        best[2] = pose[2] + float(dth[int(np.argmin(cost))])
        return best

    def _grid_box(self) -> tuple[FloatArray, FloatArray, float]:
        """The outline's bounding box (lower and upper corners, m) and the pitch of the grids
        laid over it (:meth:`_fitting_poses`, :meth:`_sure_cells`): 0.5 mm, or 1/60 of the
        box where that is coarser."""
        outline = np.concatenate([s[:, 0] for s, _ in self._segments.values()])
        lo, hi = outline.min(axis=0), outline.max(axis=0)
        return lo, hi, max(0.5e-3, float(np.max(hi - lo)) / 60)

    def _fitting_poses(self, headings: int = 16) -> FloatArray:
        lo, hi, pitch = self._grid_box()
        xs = np.arange(lo[0], hi[0] + pitch, pitch)
        ys = np.arange(lo[1], hi[1] + pitch, pitch)
        grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
        segs = np.concatenate([s for s, _ in self._segments.values()])
        # centres inside, at least a radius from every wall: the only ones a body can have
        centres = grid[self.inside(grid)]
        dist = point_to_segments(centres[:, None], segs[None, :, 0], segs[None, :, 1])
        clear = dist.min(axis=1) >= self.radius
        centres, dist = centres[clear], dist[clear]
        # a wall farther from a centre than the body reaches (its half axis and a radius, and
        # a nanometre for rounding) is farther than a radius from its axis at any heading:
        # only the (centre, wall) pairs within reach are measured
        limit = self.radius * 1.001
        pair, wall = np.nonzero(dist <= limit + self.half_axis + 1e-9)
        a, b = segs[wall, 0], segs[wall, 1]
        out = []
        for th in np.arange(headings) * math.pi / headings:
            axis = np.array([math.cos(th), math.sin(th)]) * self.half_axis
            p0, p1 = centres[pair] - axis, centres[pair] + axis
            d = segment_distances(p0, p1, a, b)
            touching = np.zeros(len(centres), dtype=bool)
            touching[pair[d < limit]] = True
            ok = ~touching
            out.append(np.column_stack([centres[ok], np.full(int(ok.sum()), th)]))
        grid = np.concatenate(out)
        if not len(grid):
            raise ValueError("the robot's body fits nowhere in this free space")
        return grid

    def across(self, pose: ArrayLike) -> tuple[FloatArray, float, float] | None:
        """The critical boundary's normal at the body and how far the body can move along it.

        Returns ``(n, lo, hi)``: ``n`` (2,) the unit normal into the free side at the critical
        boundary's point nearest the body's centre, and ``lo ≤ 0 ≤ hi``, m, the translations
        along ``n`` within which the body at ``pose`` still fits (:meth:`play`): ``lo`` toward
        the critical boundary, ``hi`` toward the other side. None without a critical boundary.
        """
        if self.critical is None:
            return None
        p = np.asarray(pose, dtype=np.float64)
        _, n = self.nearest(p[:2], [self.critical])
        lo, hi = self.play(p, n[0])
        return n[0], lo, hi

    def play(
        self, pose: ArrayLike, direction: ArrayLike, reach: float = 4e-3
    ) -> tuple[float, float]:
        """How far the body at ``pose`` can translate along ``direction`` (a unit 2-vector)
        each way before it meets a wall, m: ``(lo ≤ 0, hi ≥ 0)``, each at most ``reach``.

        Each disk of the body (radius r = D/2, :func:`~magrun.scene.capsule_disks`) moving as
        ``c + s·direction`` meets a wall segment where it enters the segment inflated by r, a
        convex set, so over one interval of s: the hull of where the line crosses the
        segment's slab and its two end circles. ``lo`` and ``hi`` are the nearest such
        intervals' ends on either side of 0. A pose that does not fit (a disk on a wall)
        gets ``(0, 0)``.
        """
        p = np.asarray(pose, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        r = self.radius
        axis = np.array([math.cos(p[2]), math.sin(p[2])])
        c = p[:2] + capsule_disks(self.half_axis, r)[:, None] * axis  # (m, 2)
        a, ab, ab2, _ = self._group(tuple(self.boundaries))
        near = point_to_segments(p[:2], a, a + ab) <= self.half_axis + r + reach
        a, ab, ab2 = a[near], ab[near], ab2[near]
        if not len(a):
            return -reach, reach
        length = np.sqrt(ab2)
        t = ab / length[:, None]  # along each segment
        m = np.column_stack([-t[:, 1], t[:, 0]])  # across it
        w = c[:, None, :] - a[None, :, :]  # (m, n, 2)
        lo_all, hi_all = np.full(w.shape[:2], np.inf), np.full(w.shape[:2], -np.inf)

        def hull(s0: FloatArray, s1: FloatArray) -> None:
            ok = s0 <= s1
            lo_all[:] = np.where(ok, np.minimum(lo_all, s0), lo_all)
            hi_all[:] = np.where(ok, np.maximum(hi_all, s1), hi_all)

        with np.errstate(divide="ignore", invalid="ignore"):
            # the slab: |m·(x − a)| < r and 0 ≤ t·(x − a) ≤ |ab|, x = c + s d
            md, td = m @ d, t @ d
            wm, wt = np.sum(w * m, axis=-1), np.sum(w * t, axis=-1)
            slab = np.sort(np.stack([(-r - wm) / md, (r - wm) / md]), axis=0)
            along = np.sort(np.stack([-wt / td, (length - wt) / td]), axis=0)
            inside_m = np.abs(wm) < r  # direction parallel to the segment: s unbounded
            inside_t = (wt >= 0) & (wt <= length)
            a0 = np.where(np.abs(md) > 1e-12, slab[0], np.where(inside_m, -np.inf, np.inf))
            a1 = np.where(np.abs(md) > 1e-12, slab[1], np.where(inside_m, np.inf, -np.inf))
            b0 = np.where(np.abs(td) > 1e-12, along[0], np.where(inside_t, -np.inf, np.inf))
            b1 = np.where(np.abs(td) > 1e-12, along[1], np.where(inside_t, np.inf, -np.inf))
            hull(np.maximum(a0, b0), np.minimum(a1, b1))
            # the end circles: |w − e + s d|² = r², e = 0 (a) or ab (b)
            for e in (np.zeros_like(ab), ab):
                we = w - e[None]
                half_b = we @ d
                disc = half_b**2 - (np.sum(we * we, axis=-1) - r * r)
                root = np.sqrt(np.maximum(disc, 0.0))
                hit = disc >= 0
                hull(np.where(hit, -half_b - root, np.inf), np.where(hit, -half_b + root, -np.inf))
        if np.any((lo_all < 0) & (hi_all > 0)):
            return 0.0, 0.0
        ahead = lo_all[lo_all >= 0]
        behind = hi_all[hi_all <= 0]
        hi = min(float(ahead.min()) if ahead.size else reach, reach)
        lo = max(float(behind.max()) if behind.size else -reach, -reach)
        return lo, hi

    def clearances(
        self, poses: ArrayLike, names: list[str] | None = None, pairs: int = 1_000_000
    ) -> FloatArray:
        """:meth:`clearance` at each of ``poses`` (m, 3), m: every wall segment against every
        pose, vectorised in blocks of about ``pairs`` pose-segment pairs (a long path's check
        before a run)."""
        p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        axis = np.column_stack([np.cos(p[:, 2]), np.sin(p[:, 2])]) * self.half_axis
        e0, e1 = p[:, :2] - axis, p[:, :2] + axis
        a, ab, _, _ = self._group(tuple(names or list(self.boundaries)))
        b = a + ab
        out = np.empty(len(p))
        step = max(1, pairs // len(a))
        for i in range(0, len(p), step):
            s0, s1 = e0[i : i + step, None], e1[i : i + step, None]  # (k, 1, 2)
            out[i : i + step] = segment_distances(s0, s1, a, b).min(axis=1) - self.radius
        return out

    def clearance(self, pose: ArrayLike, names: list[str] | None = None) -> float:
        """Least distance, m, from the body at ``pose`` to the named boundaries (default:
        all); negative when it overlaps one."""
        p = np.asarray(pose, dtype=np.float64)
        axis = np.array([math.cos(p[2]), math.sin(p[2])]) * self.half_axis
        ends = np.stack([p[:2] - axis, p[:2] + axis])
        key = tuple(names or list(self.boundaries))
        a, ab, ab2, _ = self._group(key)
        # only walls within reach of the body's axis can be nearest to it
        u = np.clip(((p[0] - a[:, 0]) * ab[:, 0] + (p[1] - a[:, 1]) * ab[:, 1]) / ab2, 0, 1)
        centre = np.hypot(p[0] - a[:, 0] - u * ab[:, 0], p[1] - a[:, 1] - u * ab[:, 1])
        near = centre <= centre.min() + 2 * self.half_axis + 1e-12
        d = segment_distances(ends[0], ends[1], a[near], a[near] + ab[near])
        return float(d.min() - self.radius)
