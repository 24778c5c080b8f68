"""Held-out accuracy and speed of a tracker on rendered frames (``magrun tracker eval``).

Frames are whole default-camera frames of the workspace, drawn from a seed the training never
uses: each robot in turn at a uniformly random pose inside the container (clear of its walls),
and in half of them inside a channel (two walls along the robot, 0–4 mm from its sides, as in
the spine phantom), with a fresh lighting, blur and noise per frame.

- **tracking** frames are tracked as in a trial: the window is placed at the previous pose,
  taken as the true pose plus N(0, (1 mm)²) per axis (the robot moves ≲ 1 mm per frame);
- **search** frames have no previous pose: the tracker searches the whole frame first.

A frame *fails* when the tracker reports no pose or one more than 1 mm off (a gross error);
the RMS errors are over the frames that did not fail. Inference time is the wall time of
``Tracker.track`` (crop, network, decoding, fit) per frame.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from magrun.angles import wrap_angle
from magrun.robot import RobotParams
from magrun.scene import Walls
from magrun.tracking.camera import DEFAULT_CAMERA, Camera, CameraConfig
from magrun.tracking.dataset import channel_walls
from magrun.tracking.inference import UNetNet
from magrun.tracking.render import Renderer
from magrun.tracking.tracker import Tracker

if TYPE_CHECKING:
    from magrun.tracking.unet import KeypointUNet

GROSS_ERROR = 1e-3  # m
EVAL_SEED = 10_000  # training draws from small seeds; evaluation from here on


def evaluate(
    model: UNetNet | KeypointUNet,
    robots: Sequence[RobotParams],
    frames: int = 1000,
    search_frames: int = 100,
    camera: CameraConfig = DEFAULT_CAMERA,
    seed: int = EVAL_SEED,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Accuracy (mm, degrees), failure rate and time per frame (ms), overall and per robot,
    of the network ``model`` (a weights file's graph, or a torch model: run by ONNX Runtime)."""
    rng = np.random.default_rng(seed)
    cam = Camera(camera)
    trackers = {r.name: Tracker(model, cam, r) for r in robots}
    box = Walls.box(0.05)
    rows: list[dict[str, Any]] = []
    total = frames + search_frames
    for i in range(total):
        robot = robots[i % len(robots)]
        reach = 0.05 - robot.length / 2 - 1e-3
        pose = np.array([*rng.uniform(-reach, reach, 2), rng.uniform(-np.pi, np.pi)])
        walls = box + channel_walls(rng, pose, robot) if rng.random() < 0.5 else box
        jitter = replace(
            camera,
            blur_px=camera.blur_px * rng.uniform(0.5, 1.3),
            noise=camera.noise * rng.uniform(0.5, 2.0),
        )
        frame = Renderer(Camera(jitter), robot, walls, seed=int(rng.integers(2**31))).render(pose)
        search = i >= frames
        prior = None if search else pose + np.array([*rng.normal(0, 1e-3, 2), 0.0])
        tracker = trackers[robot.name]
        tracker.reset()
        t0 = time.perf_counter()
        result = tracker.track(frame, prior)
        elapsed = time.perf_counter() - t0
        row: dict[str, Any] = {"robot": robot.name, "search": search, "time": elapsed}
        if result.pose is None:
            row.update(position=np.nan, orientation=np.nan, failed=True)
        else:
            dp = float(np.hypot(*(result.pose[:2] - pose[:2])))
            da = abs(float(wrap_angle(result.pose[2] - pose[2])))
            row.update(position=dp, orientation=da, failed=dp > GROSS_ERROR)
        rows.append(row)
        if progress is not None:
            progress(i + 1, total)

    def summary(sel: list[dict[str, Any]]) -> dict[str, Any]:
        ok = [r for r in sel if not r["failed"]]
        pos = np.array([r["position"] for r in ok])
        ang = np.array([r["orientation"] for r in ok])
        times = np.array([r["time"] for r in sel]) * 1e3
        return {
            "frames": len(sel),
            "rms_position_mm": float(np.sqrt(np.mean(pos**2)) * 1e3) if ok else None,
            "rms_orientation_deg": float(np.degrees(np.sqrt(np.mean(ang**2)))) if ok else None,
            "max_position_mm": float(pos.max() * 1e3) if ok else None,
            "failure_rate": 1 - len(ok) / len(sel),
            "median_ms": float(np.median(times)),
            "p95_ms": float(np.percentile(times, 95)),
        }

    tracking = [r for r in rows if not r["search"]]
    searching = [r for r in rows if r["search"]]
    return {
        "camera": {"width_px": camera.width_px, "height_px": camera.height_px,
                   "px_per_mm": camera.px_per_mm},
        "tracking": summary(tracking),
        "per_robot": {
            r.name: summary([x for x in tracking if x["robot"] == r.name]) for r in robots
        },
        "search": summary(searching) if searching else None,
        "backend": next(iter(trackers.values())).backend,
    }  # fmt: skip
