"""Training and evaluation samples for the keypoint UNet.

**Synthetic** samples come from the renderer with exact labels: a crop of ``size`` px around
a robot (either robot, any heading), its centre up to ``max_offset`` px from the crop's centre
(the tracker centres its crop on the previous pose, so the robot is near the middle), with
per-sample lighting, blur, noise and scale drawn around the camera defaults, and wall bands
crossing the crop half of the time (container walls, the phantom channel). A few samples
show no robot at all, so the model learns to stay quiet on an empty frame.

**Real** samples come from a lab's own annotated frames, for fine-tuning (see
:func:`load_annotations` for the format).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from magrun.robot import RobotParams
from magrun.scene import Walls
from magrun.tracking.camera import DEFAULT_CAMERA, Camera, CameraConfig
from magrun.tracking.keypoints import NAMES, fiducials
from magrun.tracking.render import FLUID, Lighting, draw_robot, draw_walls, finish

FloatArray = NDArray[np.float64]
U8 = NDArray[np.uint8]

CROP = 96  # px, the tracker's input window


#: the robots the tracker learns and is evaluated on: the paper's two, which the default
#: camera frames (robots.yaml's others, e.g. micro_magnet for small workspaces, it does not)
TRACKED_ROBOTS = ("magnet", "drug_delivery")


def tracked_robots() -> list[RobotParams]:
    """:data:`TRACKED_ROBOTS` from robots.yaml."""
    from magrun.robot import load_robot

    return [load_robot(name) for name in TRACKED_ROBOTS]


@dataclass(frozen=True)
class Sample:
    """One labelled image: ``keypoints`` (3, 2) in px (u, v), NaN when no robot is shown."""

    image: U8
    keypoints: FloatArray
    robot: str


def synthetic_sample(
    rng: np.random.Generator,
    robots: Sequence[RobotParams],
    camera: CameraConfig = DEFAULT_CAMERA,
    size: int = CROP,
    max_offset: float = 24.0,
    empty_fraction: float = 0.05,
) -> Sample:
    """A rendered crop with exact keypoints (see the module docs for the distribution)."""
    cfg = replace(
        camera,
        width_px=size,
        height_px=size,
        px_per_mm=camera.px_per_mm * rng.uniform(0.95, 1.05),
        blur_px=rng.uniform(0.5, 1.3) * camera.blur_px,
        noise=rng.uniform(0.5, 2.0) * camera.noise,
    )
    robot = robots[int(rng.integers(len(robots)))]
    pose = np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    offset = rng.uniform(-max_offset, max_offset, 2) / (cfg.px_per_mm * 1e3)
    cam = Camera(cfg, (float(pose[0] + offset[0]), float(pose[1] + offset[1])))
    image = np.empty((size, size, 3), dtype=np.float32)
    image[:] = np.asarray(FLUID, dtype=np.float32) * np.float32(rng.uniform(0.92, 1.08, 3))
    if rng.random() < 0.5:
        walls = _random_walls(rng, cam) if rng.random() < 0.5 else channel_walls(rng, pose, robot)
        draw_walls(image, cam, walls)
    empty = rng.random() < empty_fraction
    if not empty:
        draw_robot(image, cam, pose, robot)
    lighting = Lighting.draw(rng, camera.lighting)
    frame = finish(image, cam, lighting, lighting.field(cam.shape), rng)
    points = (
        np.full((len(NAMES), 2), np.nan) if empty else cam.to_pixel(fiducials(pose, robot.length))
    )
    return Sample(frame, points, robot.name)


def channel_walls(rng: np.random.Generator, pose: FloatArray, robot: RobotParams) -> Walls:
    """Two walls along the robot, as in the phantom's channel: 0–4 mm clear of its sides."""
    x, y, th = pose
    u = np.array([np.cos(th), np.sin(th)])
    segs = []
    for side in (-1.0, 1.0):
        angle = th + rng.normal(0.0, 0.1)
        d = np.array([np.cos(angle), np.sin(angle)])
        n = np.array([-d[1], d[0]])
        gap = robot.diameter / 2 + rng.uniform(0.0, 4e-3)
        mid = np.array([x, y]) + u * rng.uniform(-robot.length, robot.length) + side * gap * n
        segs.append([mid - 0.05 * d, mid + 0.05 * d])
    return Walls(np.asarray(segs, dtype=np.float64))


def _random_walls(rng: np.random.Generator, cam: Camera) -> Walls:
    """One or two long wall segments crossing the crop, clear of its centre most of the time."""
    half = cam.config.width_px / cam.scale / 2
    segs = []
    for _ in range(rng.integers(1, 3)):
        angle = rng.uniform(0, np.pi)
        d = np.array([np.cos(angle), np.sin(angle)])
        normal = np.array([-d[1], d[0]])
        dist = rng.uniform(0.004, half)  # ≥ 4 mm from the crop centre
        mid = np.asarray(cam.center) + normal * dist * rng.choice([-1, 1])
        segs.append([mid - 2 * half * d, mid + 2 * half * d])
    return Walls(np.asarray(segs, dtype=np.float64))


# -- real images ------------------------------------------------------------------------------

ANNOTATION_COLUMNS = ("image", "tail_u", "tail_v", "centre_u", "centre_v", "head_u", "head_v")


def load_annotations(path: str | Path) -> list[tuple[str, FloatArray]]:
    """Read a keypoint annotation file.

    The format is a CSV file with the header ``image,tail_u,tail_v,centre_u,centre_v,head_u,
    head_v``: one row per annotated frame, ``image`` a file name relative to the image folder
    (or, for a video, the 0-based frame index), the others the pixel coordinates (column u,
    row v; origin at the top-left pixel's centre) of the robot's tail tip, centre and head tip
    (the head is the end the magnetic moment points to). Extra columns are ignored.

    Raises
    ------
    ValueError
        Naming the file, line and column of the first bad row.
    """
    path = Path(path)
    rows: list[tuple[str, FloatArray]] = []
    line = 1
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            missing = [c for c in ANNOTATION_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise ValueError(f"{path}:1: missing column(s) {', '.join(missing)}")
            for row in reader:
                line = reader.line_num
                values = []
                for col in ANNOTATION_COLUMNS[1:]:
                    try:
                        value = float(row[col])
                    except (TypeError, ValueError):
                        raise ValueError(f"{path}:{line}: column {col!r}: not a number") from None
                    if not math.isfinite(value):
                        raise ValueError(f"{path}:{line}: column {col!r}: not a finite number")
                    values.append(value)
                rows.append((row["image"], np.asarray(values).reshape(3, 2)))
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except csv.Error as exc:
        raise ValueError(f"{path}:{line}: not readable as CSV: {exc}") from None
    except OSError as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None
    if not rows:
        raise ValueError(f"{path}: no annotated frames")
    return rows


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def _rgb(bgr: NDArray[Any]) -> U8:
    return np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)


@contextmanager
def _video(source: Path) -> Iterator[cv2.VideoCapture]:
    cap = cv2.VideoCapture(str(source))
    if not cap.isOpened():
        raise ValueError(f"{source}: not an image folder or a readable video")
    try:
        yield cap
    finally:
        cap.release()


def read_frames(source: str | Path, names: Sequence[str]) -> Iterator[U8]:
    """RGB frames named in an annotation file, from a folder of images or a video file."""
    source = Path(source)
    if source.is_dir():
        for name in names:
            bgr = cv2.imread(str(source / name), cv2.IMREAD_COLOR)
            if bgr is None:
                raise ValueError(f"{source / name}: cannot read image")
            yield _rgb(bgr)
        return
    with _video(source) as cap:
        for name in names:
            try:
                index = int(name)
            except ValueError:
                raise ValueError(
                    f"{source}: video frames are named by index, got {name!r}"
                ) from None
            cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            ok, bgr = cap.read()
            if not ok:
                raise ValueError(f"{source}: cannot read frame {index}")
            yield _rgb(bgr)


def iter_frames(source: str | Path) -> Iterator[tuple[str, U8]]:
    """Every frame of a folder of images (sorted by name) or of a video: (name, RGB) pairs.

    A video's frames are named by their 0-based index, as in the annotation format.
    """
    source = Path(source)
    if source.is_dir():
        names = sorted(p.name for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not names:
            raise ValueError(f"{source}: no images ({', '.join(IMAGE_SUFFIXES)})")
        yield from zip(names, read_frames(source, names), strict=True)
        return
    with _video(source) as cap:
        index = 0
        while True:
            ok, bgr = cap.read()
            if not ok:
                break
            yield str(index), _rgb(bgr)
            index += 1


def real_samples(
    source: str | Path, annotations: str | Path, px_per_mm: float, target_px_per_mm: float
) -> list[tuple[U8, FloatArray]]:
    """Annotated real frames rescaled to the tracker's scale: (image, keypoints px) pairs."""
    rows = load_annotations(annotations)
    f = target_px_per_mm / px_per_mm
    out = []
    for (_, pts), rgb in zip(rows, read_frames(source, [r[0] for r in rows]), strict=True):
        img = rgb if f == 1 else cv2.resize(rgb, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)
        img = np.asarray(img, dtype=np.uint8)
        # pixel centres: u' + 0.5 = f (u + 0.5)
        out.append((img, (pts + 0.5) * f - 0.5))
    return out


def crop_sample(
    rng: np.random.Generator, image: U8, keypoints: FloatArray, size: int, max_offset: float
) -> Sample:
    """A ``size`` crop of a real frame around its robot, edge-padded, with shifted labels."""
    centre = np.nanmean(keypoints, axis=0) + rng.uniform(-max_offset, max_offset, 2)
    u0, v0 = (np.round(centre) - size // 2).astype(int)
    pad = size
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    u0c = int(np.clip(u0, -pad, image.shape[1] + pad - size))
    v0c = int(np.clip(v0, -pad, image.shape[0] + pad - size))
    crop = padded[v0c + pad : v0c + pad + size, u0c + pad : u0c + pad + size]
    return Sample(np.ascontiguousarray(crop), keypoints - [u0c, v0c], "real")
