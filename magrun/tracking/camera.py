"""The top-view camera: image size, scale, and the world ↔ pixel mapping.

The camera looks straight down the −z axis at the workspace plane (z up toward the camera),
so the mapping is a scaled, y-flipped translation::

    u = u₀ + x · s,   v = v₀ − y · s        s = px_per_mm · 1000 (px per m)

with ``(u₀, v₀)`` the pixel the world point ``center`` falls on: the image centre
``((W − 1)/2, (H − 1)/2)``. Pixel ``(u, v)`` is column ``u``, row ``v``; integer coordinates
are pixel centres (OpenCV's convention). A crop of a frame is the same camera with another
size and centre, which is how the tracker and its training data see the workspace.

    >>> cam = Camera(CameraConfig(width_px=256, height_px=256, px_per_mm=2.5))
    >>> cam.to_pixel([[0.0, 0.0], [0.01, 0.01]]).tolist()
    [[127.5, 127.5], [152.5, 102.5]]
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CameraConfig:
    """Camera model of the simulated rig (and the scale the tracker works at on a real one).

    Attributes
    ----------
    width_px, height_px : int
        Frame size. The default 256 × 256 px at 2.5 px/mm sees 102.4 mm, the whole 100 mm
        workspace; rendering one frame takes about a millisecond.
    px_per_mm : float
        Scale on the workspace plane.
    blur_px : float
        σ of the Gaussian point-spread function (optics, focus, motion), px.
    noise : float
        σ of the sensor noise, a fraction of full scale (0.02 ≈ 5 grey levels of 255).
    lighting : float
        Amplitude of the lighting variation: per trial a gain and white balance within
        ±``lighting``, an illumination gradient and vignetting of up to ``lighting`` across
        the frame, and a flicker of ``lighting``/5 from frame to frame.
    """

    width_px: int = 256
    height_px: int = 256
    px_per_mm: float = 2.5
    blur_px: float = 0.8
    noise: float = 0.02
    lighting: float = 0.15

    def __post_init__(self) -> None:
        if self.width_px < 16 or self.height_px < 16:
            raise ValueError("camera frames must be at least 16 x 16 px")
        if not self.px_per_mm > 0:
            raise ValueError("px_per_mm must be positive")
        if self.blur_px < 0 or self.noise < 0 or not 0 <= self.lighting < 1:
            raise ValueError("blur_px and noise must be ≥ 0, lighting in [0, 1)")


DEFAULT_CAMERA = CameraConfig()


@dataclass(frozen=True)
class Camera:
    """A :class:`CameraConfig` placed over the workspace: its centre sees world ``center``."""

    config: CameraConfig = DEFAULT_CAMERA
    center: tuple[float, float] = (0.0, 0.0)  # m

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` in px, NumPy's order."""
        return self.config.height_px, self.config.width_px

    @property
    def scale(self) -> float:
        """Pixels per metre."""
        return self.config.px_per_mm * 1e3

    @property
    def principal(self) -> tuple[float, float]:
        """Pixel ``(u₀, v₀)`` of the world point ``center``."""
        return (self.config.width_px - 1) / 2, (self.config.height_px - 1) / 2

    def to_pixel(self, xy: ArrayLike) -> FloatArray:
        """World points, shape (..., 2), m → pixels ``(u, v)``, shape (..., 2)."""
        p = np.asarray(xy, dtype=np.float64)
        u0, v0 = self.principal
        u = u0 + (p[..., 0] - self.center[0]) * self.scale
        v = v0 - (p[..., 1] - self.center[1]) * self.scale
        return np.stack([u, v], axis=-1)

    def to_world(self, uv: ArrayLike) -> FloatArray:
        """Pixels ``(u, v)``, shape (..., 2) → world points, m, shape (..., 2)."""
        q = np.asarray(uv, dtype=np.float64)
        u0, v0 = self.principal
        x = self.center[0] + (q[..., 0] - u0) / self.scale
        y = self.center[1] - (q[..., 1] - v0) / self.scale
        return np.stack([x, y], axis=-1)

    def crop(self, origin: tuple[int, int], size: tuple[int, int]) -> Camera:
        """The camera that sees the pixel window at column/row ``origin``, ``size`` (w, h)."""
        u, v = origin
        w, h = size
        centre_px = (u + (w - 1) / 2, v + (h - 1) / 2)
        cx, cy = self.to_world(centre_px)
        return Camera(replace(self.config, width_px=w, height_px=h), (float(cx), float(cy)))
