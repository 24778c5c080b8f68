"""Three fiducial points on the robot's axis, and the pose they determine.

The tracker locates three points per robot, as the paper's annotators marked three points
per robot mask (Section II-F). Ours lie on the body axis at signed distances ``s`` from the
centre: the tail tip, the centre and the head tip (the head is where the magnetic moment
points), ``s = (−L/2, 0, +L/2)``.

The pose follows by a weighted rigid fit of those body coordinates to the located points
``p_i`` (no scale): minimise Σ wᵢ |c + sᵢ u(θ) − pᵢ|² over the centre ``c`` and the axis
``u = (cos θ, sin θ)``. With p̄, s̄ the weighted means, the solution is closed-form::

    u ∝ Σ wᵢ (sᵢ − s̄)(pᵢ − p̄),     c = p̄ − s̄ u

so three exact points give the exact pose, and noisy ones their least-squares pose.

    >>> pts = fiducials([0.01, -0.002, 0.3], length=0.016)
    >>> np.round(pose_from_keypoints(pts, length=0.016).pose, 9).tolist()
    [0.01, -0.002, 0.3]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: fiducial names, in the order of the model's heat-map channels
NAMES = ("tail", "centre", "head")
#: positions along the axis in units of the robot's length
AXIAL_FRACTIONS = np.array([-0.5, 0.0, 0.5])


def axial_offsets(length: float) -> FloatArray:
    """Signed distances of the fiducials from the centre along the axis, m, shape (3,)."""
    return AXIAL_FRACTIONS * length


def fiducials(pose: ArrayLike, length: float) -> FloatArray:
    """World positions of the three fiducials of a robot at ``pose`` (x, y, θ), shape (3, 2)."""
    x, y, th = np.asarray(pose, dtype=np.float64)
    s = axial_offsets(length)
    return np.column_stack([x + s * np.cos(th), y + s * np.sin(th)])


@dataclass(frozen=True)
class KeypointFit:
    """Result of :func:`pose_from_keypoints`.

    Attributes
    ----------
    pose : ndarray, shape (3,)
        ``(x, y, θ)``, m and rad, θ in (−π, π].
    residual : float
        Weighted RMS distance of the points from the fitted ones, m.
    span : float
        Distance between the first and last point, m (the apparent length).
    """

    pose: FloatArray
    residual: float
    span: float


def pose_from_keypoints(
    points: ArrayLike, length: float, weights: ArrayLike | None = None
) -> KeypointFit:
    """Least-squares rigid pose of the fiducials ``points`` (3, 2), m; see the module docs.

    ``weights`` (3,) default to equal; non-positive weights drop a point (at least two must
    remain, and they must not coincide).
    """
    p = np.asarray(points, dtype=np.float64)
    s = axial_offsets(length)
    if p.shape != (s.size, 2):
        raise ValueError(f"expected points of shape ({s.size}, 2), got {p.shape}")
    w = np.ones(s.size) if weights is None else np.clip(np.asarray(weights, float), 0.0, None)
    if np.count_nonzero(w) < 2:
        raise ValueError("need at least two points with positive weight")
    w = w / w.sum()
    p_bar, s_bar = w @ p, w @ s
    direction = (w * (s - s_bar)) @ (p - p_bar)
    norm = float(np.hypot(*direction))
    if norm == 0.0:
        raise ValueError("the points do not determine an axis")
    u = direction / norm
    c = p_bar - s_bar * u
    fitted = c + s[:, None] * u
    residual = float(np.sqrt(w @ np.sum((fitted - p) ** 2, axis=1)))
    theta = float(np.arctan2(u[1], u[0]))
    return KeypointFit(np.array([c[0], c[1], theta]), residual, float(np.hypot(*(p[-1] - p[0]))))
