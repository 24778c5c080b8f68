"""Synthetic top-view camera frames of the workspace (OpenCV), with exact keypoint labels.

What a frame shows, back to front:

- the fluid in the container, a light blue-grey;
- walls (the container's, the spine phantom's channel) as 1 mm agarose-coloured bands;
- the robot, as the paper describes it: the **magnet robot** is a 16 × 2.8 mm cylinder painted
  pink on its front (north-pole) half and yellow on its rear half, lit along its axis; the
  **drug-delivery robot** is a translucent 7.4 × 2.8 mm resin capsule with its dark disk
  magnet in the front cap and the blue drug in the rest.

Then the camera model: Gaussian blur (``blur_px``), lighting (a per-trial gain, white balance,
illumination gradient and vignetting, plus frame-to-frame flicker) and Gaussian sensor noise.
Shapes are drawn by exact area coverage (8 × 8 supersampling), so a label sits on the drawn
robot to well under the tracker's error. Frames are ``uint8`` RGB arrays, shape (H, W, 3).

    >>> from magrun.robot import load_robot
    >>> r = Renderer(Camera(), load_robot("magnet"), seed=0)
    >>> r.render([0.0, 0.0, 0.5]).shape
    (256, 256, 3)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.robot import RobotParams
from magrun.scene import Walls
from magrun.tracking.camera import Camera

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

_SHIFT = 4  # OpenCV fixed-point bits: coordinates at 1/16 px
_ONE = 1 << _SHIFT
_SUPERSAMPLE = 8  # shapes are rasterised at 8 × 8 samples per pixel
_ARC = 16  # polygon edges per half-circle

FLUID = (0.74, 0.79, 0.82)
AGAROSE = (0.93, 0.88, 0.74)
PINK = (0.94, 0.42, 0.64)
YELLOW = (0.96, 0.84, 0.22)
SHELL_EDGE = (0.55, 0.58, 0.60)
SHELL = (0.97, 0.97, 0.96)
DRUG = (0.22, 0.42, 0.86)
MAGNET = (0.20, 0.20, 0.23)
WALL_THICKNESS = 1e-3  # m, the band painted for a wall segment


@dataclass(frozen=True)
class Lighting:
    """One trial's lighting: ``image = gain · illumination(u, v) · scene``.

    ``gain`` (3,) is exposure times white balance per RGB channel; the illumination is
    ``1 + gradient · q − vignette · |q|²`` over normalised image coordinates q ∈ [−1, 1]².
    """

    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    gradient: tuple[float, float] = (0.0, 0.0)
    vignette: float = 0.0
    flicker: float = 0.0  # σ of the per-frame relative gain change

    @classmethod
    def draw(cls, rng: np.random.Generator, amount: float) -> Lighting:
        """Random lighting with variation ``amount`` (see :class:`CameraConfig`)."""
        exposure = 1.0 + rng.uniform(-amount, amount)
        balance = 1.0 + rng.uniform(-amount / 3, amount / 3, 3)
        g = exposure * balance
        angle = rng.uniform(0, 2 * np.pi)
        slope = rng.uniform(0, amount / 2)
        return cls(
            gain=(float(g[0]), float(g[1]), float(g[2])),
            gradient=(float(slope * np.cos(angle)), float(slope * np.sin(angle))),
            vignette=float(rng.uniform(0, amount)),
            flicker=amount / 5,
        )

    def field(self, shape: tuple[int, int]) -> F32:
        """Illumination times gain, shape (H, W, 3), float32."""
        h, w = shape
        qy, qx = np.meshgrid(
            np.linspace(-1, 1, h, dtype=np.float32),
            np.linspace(-1, 1, w, dtype=np.float32),
            indexing="ij",
        )
        illum = 1 + self.gradient[0] * qx - self.gradient[1] * qy
        illum -= self.vignette * (qx**2 + qy**2) / 2
        return illum[..., None] * np.asarray(self.gain, dtype=np.float32)


def _fixed(uv: FloatArray) -> NDArray[np.int32]:
    return np.round(uv * _ONE).astype(np.int32)


def inset(polygon: FloatArray, delta: float) -> FloatArray:
    """The convex ``polygon`` (n, 2) with every edge moved inward by ``delta``; polygons of
    one vertex count stacked as (..., n, 2) are each moved alike, to the same last bit."""
    p = np.asarray(polygon, dtype=np.float64)
    # each vertex's successor (np.roll, without its overhead)
    nxt = np.concatenate([p[..., 1:, :], p[..., :1, :]], axis=-2)
    edge = nxt - p
    area2 = np.sum(p[..., 0] * nxt[..., 1] - nxt[..., 0] * p[..., 1], axis=-1)
    # counter-clockwise (in u, v): the inside is to the left
    sign = np.where(area2 > 0, 1.0, -1.0)[..., None, None]
    normal = sign * np.stack([-edge[..., 1], edge[..., 0]], axis=-1)
    normal /= np.maximum(np.hypot(normal[..., 0], normal[..., 1]), 1e-12)[..., None]
    # the normal of the edge ending at each vertex
    before = np.concatenate([normal[..., -1:, :], normal[..., :-1, :]], axis=-2)
    # offset lines meet at v + δ (n₁ + n₂) / (1 + n₁·n₂)
    denom = np.maximum(1.0 + np.sum(before * normal, axis=-1), 1e-6)
    return p + delta * (before + normal) / denom[..., None]


#: a shape to paint: a convex outline (n, 2) in frame px, its colour (RGB, 0–1) and opacity
Shape = tuple[FloatArray, tuple[float, float, float], float]
#: a shape rasterised for a canvas: the box it covers (rows, columns) and its inset outline
#: on the box's fine grid, in OpenCV's fixed point; None where it misses the canvas
_Raster = tuple[tuple[slice, slice], NDArray[np.int32]] | None
#: a half-circle's angles, rad
_HALF_TURN = np.arange(_ARC + 1) / _ARC * math.pi


def _rasterise(
    outlines: list[FloatArray], origin: FloatArray, shape: tuple[int, int]
) -> list[_Raster]:
    """Where each convex outline (frame px) lands on a canvas of ``shape`` (h, w) whose
    top-left pixel is ``origin``: the pixels it can touch, and its outline on their fine grid
    (×:data:`_SUPERSAMPLE`). Outlines with as many vertices are worked out together, each to
    the same last bit as alone."""
    h, w = shape
    out: list[_Raster] = [None] * len(outlines)
    groups: dict[int, list[int]] = {}
    for i, uv in enumerate(outlines):
        groups.setdefault(len(uv), []).append(i)
    for members in groups.values():
        local = np.stack([outlines[i] for i in members]) - origin
        # every pixel the polygon (or OpenCV's ½ fine-px overshoot) can touch
        lo = np.maximum(np.floor(local.min(axis=1)).astype(int) - 1, 0)
        hi = np.minimum(np.ceil(local.max(axis=1)).astype(int) + 2, [w, h])
        # fine pixel j's centre is at coarse coordinate (j + 0.5)/S − 0.5
        fine = (local - lo[:, None, :] + 0.5) * _SUPERSAMPLE - 0.5
        # OpenCV fills every pixel the outline touches, ~½ px beyond it: inset by the 0.45
        # fine px that makes the filled area match the polygon's over random shapes
        fixed = _fixed(inset(fine, 0.45))
        for j, i in enumerate(members):
            (u0, v0), (u1, v1) = lo[j], hi[j]
            if u1 > u0 and v1 > v0:
                out[i] = (slice(v0, v1), slice(u0, u1)), fixed[j]
    return out


def _stadium(a: FloatArray, b: FloatArray, radius: float) -> FloatArray:
    """The set of points within ``radius`` px of segment a–b as one convex outline: two
    half-circles of :data:`_ARC` edges each, the radius scaled so the polygon's area is the
    round shape's (OpenCV's filled circles cover ~π(r + ½)²)."""
    return _stadiums(np.asarray(a)[None], np.asarray(b)[None], radius)[0]


def _stadiums(a: FloatArray, b: FloatArray, radius: float) -> FloatArray:
    """:func:`_stadium` of each segment a[i]–b[i] ((k, 2) each), (k, 2 (ARC + 1), 2), each
    the same numbers as alone."""
    d = b - a
    angle = np.array([math.atan2(dy, dx) for dx, dy in d])[:, None]
    r = radius * math.sqrt(math.pi / (_ARC * math.sin(math.pi / _ARC)))
    arc_b = angle - math.pi / 2 + _HALF_TURN
    arc_a = angle + math.pi / 2 + _HALF_TURN
    return np.concatenate(
        [b[:, None] + r * np.stack([np.cos(arc_b), np.sin(arc_b)], axis=-1),
         a[:, None] + r * np.stack([np.cos(arc_a), np.sin(arc_a)], axis=-1)], axis=1,
    )  # fmt: skip


class _Canvas:
    """An RGB float image that takes shapes with an opacity, in pixel coordinates.

    Each shape is rasterised on a ×:data:`_SUPERSAMPLE` grid (pixel centres inside the shape)
    and box-filtered down, so a pixel gets the fraction of it the shape covers: outlines and
    centroids land within ~0.05 px (tests/test_tracking.py allows 0.1). OpenCV's own anti-aliasing
    dilates a filled shape by about half a pixel, unevenly, which put the labels off the
    drawn robot by up to 0.4 px.
    ``image`` may be a window of the frame whose top-left pixel is ``origin``; each shape is
    rasterised over its own bounding box only, so the cost follows the shape's size.
    """

    def __init__(self, image: F32, origin: tuple[int, int] = (0, 0)) -> None:
        self.image = image
        self.origin = np.array(origin, dtype=np.float64)

    def rasterise(self, outlines: list[FloatArray]) -> list[_Raster]:
        return _rasterise(outlines, self.origin, self.image.shape[:2])

    def paint(self, raster: _Raster, colour: tuple[float, float, float], opacity: float) -> None:
        """Blend a rasterised shape (:meth:`rasterise`) in, ``opacity`` of it over its cover."""
        if raster is None:
            return
        box, outline = raster
        target = self.image[box]
        h, w = target.shape[:2]
        mask = np.zeros((h * _SUPERSAMPLE, w * _SUPERSAMPLE), np.uint8)
        cv2.fillConvexPoly(mask, outline, 255, cv2.LINE_8, _SHIFT)
        cover = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA)
        a = cover.astype(np.float32) * np.float32(opacity / 255.0)
        target += a[..., None] * (np.asarray(colour, dtype=np.float32) - target)

    def shapes(self, shapes: list[Shape]) -> None:
        """Paint ``shapes`` in order, back to front."""
        for raster, (_, colour, opacity) in zip(
            self.rasterise([uv for uv, _, _ in shapes]), shapes, strict=True
        ):
            self.paint(raster, colour, opacity)

    def polygon(self, uv: FloatArray, colour: tuple[float, float, float], opacity: float) -> None:
        self.shapes([(np.asarray(uv, dtype=np.float64), colour, opacity)])

    def capsule(
        self,
        a: FloatArray,
        b: FloatArray,
        radius: float,
        colour: tuple[float, float, float],
        opacity: float,
    ) -> None:
        """The set of points within ``radius`` px of segment a–b (a stadium)."""
        self.polygon(_stadium(a, b, radius), colour, opacity)


def draw_walls(image: F32, camera: Camera, walls: Walls) -> None:
    """Paint every wall segment as a band of :data:`WALL_THICKNESS` (in place)."""
    canvas = _Canvas(image)
    half = WALL_THICKNESS / 2 * camera.scale
    for seg in walls.segments:
        a, b = camera.to_pixel(seg)
        canvas.capsule(a, b, half, AGAROSE, 1.0)


def robot_reach_px(camera: Camera, robot: RobotParams) -> float:
    """Farthest a drawn robot pixel can be from the robot's centre, px (plus anti-aliasing)."""
    return (robot.length / 2 + robot.diameter / 2) * camera.scale + 2


def robot_shapes(camera: Camera, pose: ArrayLike, robot: RobotParams) -> list[Shape]:
    """The robot at ``pose`` (x, y, θ; m, rad) as the convex shapes it is painted with, back to
    front, outlines in frame px."""
    return robot_shapes_at(camera, np.asarray(pose, dtype=np.float64)[None], robot)[0]


def robot_shapes_at(camera: Camera, poses: FloatArray, robot: RobotParams) -> list[list[Shape]]:
    """:func:`robot_shapes` of each of ``poses`` (k, 3), worked out together (a motion-blurred
    frame paints the robot at several poses): each outline the same to the last bit as alone,
    every number the same element-wise operation."""
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    s = camera.scale
    half_l, radius = robot.length / 2 * s, robot.diameter / 2 * s
    c = camera.to_pixel(poses[:, :2])  # (k, 2)
    th = poses[:, 2]
    u = np.stack([np.cos(th), -np.sin(th)], axis=-1)  # image v points down: world +y is −v
    n = np.stack([-u[:, 1], u[:, 0]], axis=-1)

    def rect(s0: float, s1: float, half_width: float) -> FloatArray:
        # corners c + s·u ± w·n, in the order s0 + w, s1 + w, s1 − w, s0 − w; (k, 4, 2)
        along = np.array((s0, s1, s1, s0))[None, :, None] * u[:, None, :]
        across = np.array((half_width, half_width, -half_width, -half_width))
        return c[:, None, :] + along + across[None, :, None] * n[:, None, :]

    if robot.appearance == "capsule":
        cap = half_l - radius
        inner = max(radius - 0.3e-3 * s, 0.5)
        magnet_at = half_l - radius * 0.9
        shapes = [
            (_stadiums(c - cap * u, c + cap * u, radius), SHELL_EDGE, 0.75),
            (_stadiums(c - cap * u, c + cap * u, inner), SHELL, 0.8),
            (rect(-cap, 0.25 * half_l, 0.8 * inner), DRUG, 0.65),
            (rect(magnet_at - 0.5e-3 * s, magnet_at + 0.5e-3 * s, 0.85 * inner), MAGNET, 0.95),
        ]
    else:
        shapes = [
            (rect(-half_l, 0.0, radius), YELLOW, 1.0),
            (rect(0.0, half_l, radius), PINK, 1.0),
            (rect(-half_l, half_l, radius / 3), (1.0, 1.0, 1.0), 0.3),  # specular line
        ]
    return [[(uv[i], colour, opacity) for uv, colour, opacity in shapes] for i in range(len(c))]


def _in_view(centre: FloatArray, reach: float, image: F32, origin: tuple[int, int]) -> bool:
    """Whether a robot centred at ``centre`` (frame px) that reaches ``reach`` px from it can
    touch ``image``, a window of the frame whose top-left pixel is ``origin``."""
    local = centre - origin
    h, w = image.shape[:2]
    return not (np.any(local + reach < 0) or np.any(local - reach > (w, h)))


def draw_robot(
    image: F32,
    camera: Camera,
    pose: ArrayLike,
    robot: RobotParams,
    origin: tuple[int, int] = (0, 0),
) -> None:
    """Paint the robot at ``pose`` (x, y, θ; m, rad) onto ``image`` (in place).

    ``image`` is the frame, or a window of it whose top-left pixel is ``origin`` (u, v).
    """
    centre = camera.to_pixel(np.asarray(pose, dtype=np.float64)[:2])
    if _in_view(centre, robot_reach_px(camera, robot), image, origin):
        _Canvas(image, origin).shapes(robot_shapes(camera, pose, robot))


def finish(
    image: F32, camera: Camera, lighting: Lighting, illumination: F32, rng: np.random.Generator
) -> NDArray[np.uint8]:
    """Camera model on a rendered scene: blur, lighting with flicker, sensor noise → uint8."""
    cfg = camera.config
    if cfg.blur_px > 0:
        image = np.asarray(cv2.GaussianBlur(image, (0, 0), cfg.blur_px), dtype=np.float32)
    flicker = np.float32(1.0 + lighting.flicker * rng.standard_normal())
    out = image * illumination * flicker
    if cfg.noise > 0:
        # OpenCV's generator, seeded per frame from ``rng``: 3× faster than NumPy's here,
        # and a trial's frames stay reproducible from its seed
        noise = np.empty_like(out)
        cv2.setRNGSeed(int(rng.integers(2**31)))
        cv2.randn(noise, np.zeros(1), np.full(1, cfg.noise))
        out += noise
    return np.clip(out * 255.0 + 0.5, 0, 255).astype(np.uint8)


def blur_radius_px(sigma: float) -> int:
    """Half the kernel OpenCV's ``GaussianBlur`` uses on float images for ``sigma``, px."""
    return (round(sigma * 8 + 1) | 1) // 2 if sigma > 0 else 0


class Renderer:
    """Frames of one trial: fixed camera, robot and walls, lighting drawn once from ``seed``.

    A frame is the same camera model as :func:`finish` applied to the scene, computed the
    cheap way a trial can afford (~0.5 ms instead of ~2 ms for 256²):

    - the background (fluid, walls) is blurred and lit once; the blur is linear, so a frame is
      that plus the blurred, lit difference the robot makes, computed in a window around the
      robot only (exact up to float rounding; tests/test_tracking.py compares with
      :func:`finish`);
    - sensor noise is a window, at a random offset drawn per frame, into a bank of
      (2H, 2W, 3) i.i.d. Gaussian samples drawn once per trial: within a frame every pixel's
      noise is independent N(0, σ²), and at any one pixel successive frames read different
      samples. Drawing 196k fresh normals per frame cost more than the rest of the frame.

    Parameters
    ----------
    camera : Camera
        What the frame covers, and the camera model.
    robot : RobotParams
        Size and ``appearance`` of the robot.
    walls : Walls, optional
        Wall segments to paint (the container, a phantom channel).
    seed : int
        Seeds the lighting and the per-frame noise, so a trial's frames are reproducible.
    """

    def __init__(
        self, camera: Camera, robot: RobotParams, walls: Walls | None = None, seed: int = 0
    ) -> None:
        self.camera = camera
        self.robot = robot
        self.rng = np.random.default_rng(seed)
        cfg = camera.config
        self.lighting = Lighting.draw(self.rng, cfg.lighting)
        self._illumination = self.lighting.field(camera.shape)
        self._background = np.empty((*camera.shape, 3), dtype=np.float32)
        self._background[:] = np.asarray(FLUID, dtype=np.float32)
        if walls is not None:
            draw_walls(self._background, camera, walls)
        # in grey levels (0–255): the lit, blurred background and the per-pixel light
        self._light = self._illumination * np.float32(255.0)
        blurred = self._background
        if cfg.blur_px > 0:
            blurred = np.asarray(cv2.GaussianBlur(blurred, (0, 0), cfg.blur_px), np.float32)
        self._lit = blurred * self._light
        self._margin = robot_reach_px(camera, robot) + blur_radius_px(cfg.blur_px) + 1
        h, w = camera.shape
        self._noise: F32 | None = None
        if cfg.noise > 0:
            self._noise = self.rng.standard_normal((2 * h, 2 * w, 3), dtype=np.float32)
            self._noise *= np.float32(cfg.noise * 255.0)

    def render(self, pose: ArrayLike, exposure: ArrayLike | None = None) -> NDArray[np.uint8]:
        """The frame with the robot at ``pose`` (x, y, θ; m, rad): uint8 RGB, shape (H, W, 3).

        ``exposure`` (k, 3): the robot's poses over the exposure instead; the robot is then the
        mean of its k images (motion blur), the camera model applied once."""
        cfg = self.camera.config
        h, w = self.camera.shape
        image = self._lit.copy()
        poses = np.atleast_2d(np.asarray(pose if exposure is None else exposure, np.float64))
        c = self.camera.to_pixel(poses[:, :2])
        lo = np.clip(np.floor(c.min(axis=0) - self._margin), 0, (w, h)).astype(int)
        hi = np.clip(np.ceil(c.max(axis=0) + self._margin) + 1, 0, (w, h)).astype(int)
        if np.all(hi > lo):
            box = (slice(lo[1], hi[1]), slice(lo[0], hi[0]))
            base = self._background[box]
            patch = np.zeros_like(base)
            origin = (int(lo[0]), int(lo[1]))
            # each pose's robot drawn on the background alone; the shapes of all of them
            # rasterised together (each the same as alone, the pass cheaper)
            reach = robot_reach_px(self.camera, self.robot)
            shapes = [
                one if _in_view(centre, reach, base, origin) else []
                for one, centre in zip(
                    robot_shapes_at(self.camera, poses, self.robot), c, strict=True
                )
            ]  # fmt: skip
            outlines = [uv for one in shapes for uv, _, _ in one]
            rasters = iter(_rasterise(outlines, np.array(origin, np.float64), base.shape[:2]))
            for one in shapes:
                drawn = _Canvas(base.copy(), origin)
                for _, colour, opacity in one:
                    drawn.paint(next(rasters), colour, opacity)
                patch += drawn.image - base  # zero within `margin` of the window's inner sides
            if len(poses) > 1:
                patch /= np.float32(len(poses))
            if cfg.blur_px > 0:  # so the reflected border equals the whole frame's blur
                patch = np.asarray(cv2.GaussianBlur(patch, (0, 0), cfg.blur_px), np.float32)
            image[box] += patch * self._light[box]
        image *= np.float32(1.0 + self.lighting.flicker * self.rng.standard_normal())
        if self._noise is not None:
            dv, du = int(self.rng.integers(h)), int(self.rng.integers(w))
            image += self._noise[dv : dv + h, du : du + w]
        image += np.float32(0.5)
        np.clip(image, 0, 255, out=image)
        return image.astype(np.uint8)
