"""The fluoroscopy mimic: camera poses degraded to fluoroscopy's rate and noise (Section II-F).

The paper could not fit a C-arm around its coils, so it degraded its camera tracking instead:
fewer frames, plus Gaussian noise, before the pose reached the controller, while the raw
high-rate camera pose stayed the "actual" pose for the errors. :class:`FluoroscopyMimic` does
the same to the camera pose stream of a trial:

- **rate**: a fluoroscopy frame is due every 1/rate s from the trial start (t = 0, 1/f,
  2/f, …). The camera frame at or after each due time is delivered, the others return
  ``None``. Due times advance on a fixed grid, never from the delivery time, so with a
  25 Hz camera a 7.5 Hz mimic delivers every 3rd or 4th frame and averages 7.5 Hz exactly;
  a rate at or above the camera's delivers every frame.
- **noise**: each delivered pose gets independent N(0, σ²) added to x and to y (σ per axis,
  as in the paper's "σ = 2 mm") and N(0, σ_θ²) to θ (0 by default), from a generator seeded
  per trial, so a trial's measurements are reproducible.
- a frame on which the camera tracker lost the robot (``None``) is a lost fluoroscopy frame:
  nothing is delivered and the next frame is due on the grid as usual.

    >>> mimic = FluoroscopyMimic(rate_hz=7.5, sigma_position=0.0, seed=0)
    >>> [mimic(k * 0.04, np.zeros(3)) is not None for k in range(8)]
    [True, False, False, False, True, False, False, True]
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.angles import wrap_angle

FloatArray = NDArray[np.float64]

#: the paper's tracking rates, Hz (fluoroscopy's 3 to 15 fps, and the fastest control rate)
PAPER_RATES_HZ = (3.0, 7.5, 15.0, 25.5)


class FluoroscopyMimic:
    """Rate- and noise-degraded pose feedback; a ``feedback(t, pose)`` for the trial loop.

    Parameters
    ----------
    rate_hz : float
        Fluoroscopy frame rate, Hz (> 0; ``math.inf`` passes every camera frame).
    sigma_position : float
        σ of the Gaussian noise on x and on y, m.
    sigma_orientation : float
        σ of the Gaussian noise on θ, rad.
    seed : int
        Seeds the noise; the same seed gives the same measurements.
    """

    def __init__(
        self,
        rate_hz: float,
        sigma_position: float = 0.0,
        sigma_orientation: float = 0.0,
        seed: int = 0,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        if sigma_position < 0 or sigma_orientation < 0:
            raise ValueError("noise sigma must be >= 0")
        self.rate_hz = float(rate_hz)
        self.sigma_position = float(sigma_position)
        self.sigma_orientation = float(sigma_orientation)
        self.seed = seed
        self.reset()

    @property
    def period(self) -> float:
        """Seconds between fluoroscopy frames (0 for an infinite rate)."""
        return 1.0 / self.rate_hz

    def reset(self) -> None:
        """Start a new trial: first frame due at t = 0, the noise sequence from the seed."""
        self._rng = np.random.default_rng(self.seed)
        self._frame = 0  # index of the next due frame on the grid k / rate

    def due(self, t: float) -> bool:
        """Whether a fluoroscopy frame is due at camera time ``t`` (s); changes nothing.

        The trial loop asks this before rendering a simulated frame, so the camera renders
        and tracks only the frames the mimic will take.
        """
        return t + 1e-9 >= self._frame * self.period

    def __call__(self, t: float, pose: ArrayLike | None) -> FloatArray | None:
        """The measurement delivered at camera time ``t`` (s), or ``None`` if none is due."""
        # small tolerance: t = k·dt accumulates rounding, and a due time must not slip a frame
        if not self.due(t):
            return None
        self._frame = math.floor((t + 1e-9) * self.rate_hz) + 1 if self.period else 0
        if pose is None:
            return None
        p = np.array(pose, dtype=np.float64)
        noise = self._rng.standard_normal(3)
        p[:2] += self.sigma_position * noise[:2]
        if self.sigma_orientation > 0:
            p[2] = float(wrap_angle(p[2] + self.sigma_orientation * noise[2]))
        return p
