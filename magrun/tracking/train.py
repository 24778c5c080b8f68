"""Training the keypoint UNet on rendered crops (and optionally a lab's annotated frames).

    magrun tracker train --out weights.npz           # from scratch on rendered crops, CPU
    magrun tracker train --images DIR --labels labels.csv --px-per-mm 4.1 \\
        --init magrun/tracking/data/unet.npz --steps 1000 --out lab.npz     # fine-tune

Every step draws a fresh batch from the renderer (an endless, exactly labelled data set, so
there is no over-fitting to a fixed set); with real frames, half of each batch is crops of
them. The loss is the mean squared heat-map error, weighted up (×10) under the targets'
peaks so that the few foreground pixels are not drowned by the background. AdamW with a
one-cycle learning-rate schedule.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from numpy.typing import NDArray

from magrun.robot import RobotParams
from magrun.tracking.camera import DEFAULT_CAMERA, CameraConfig
from magrun.tracking.dataset import CROP, Sample, crop_sample, synthetic_sample
from magrun.tracking.heatmaps import gaussian_heatmaps
from magrun.tracking.unet import KeypointUNet, to_input

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings; the defaults train the shipped model in a few CPU minutes."""

    steps: int = 3000
    batch: int = 24
    lr: float = 3e-3
    weight_decay: float = 1e-4
    foreground_weight: float = 10.0
    seed: int = 0
    widths: tuple[int, ...] = (8, 16, 32, 64)


def heatmap_loss(pred: torch.Tensor, target: torch.Tensor, foreground: float) -> torch.Tensor:
    """Mean of (1 + foreground · target) · (pred − target)²."""
    return torch.mean((1 + foreground * target) * (pred - target) ** 2)


def make_batch(samples: Sequence[Sample]) -> tuple[torch.Tensor, torch.Tensor]:
    images = np.stack([s.image for s in samples])
    shape = images.shape[1:3]
    targets = np.stack([gaussian_heatmaps(s.keypoints, shape) for s in samples])
    return to_input(images), torch.from_numpy(targets)


def train(
    robots: Sequence[RobotParams],
    config: TrainConfig = TrainConfig(),
    camera: CameraConfig = DEFAULT_CAMERA,
    model: KeypointUNet | None = None,
    real: Sequence[tuple[NDArray[np.uint8], FloatArray]] = (),
    progress: Callable[[int, int, float], None] | None = None,
) -> KeypointUNet:
    """Train (or fine-tune ``model``) and return it in eval mode.

    ``real`` holds (image, keypoints px) pairs at the tracker's scale; ``progress(step,
    steps, loss)`` is called every step.
    """
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    net = model if model is not None else KeypointUNet(config.widths)
    net = net.to(memory_format=torch.channels_last).train()
    opt = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=config.lr, total_steps=config.steps, pct_start=0.1
    )
    smoothed = float("nan")
    for step in range(config.steps):
        samples: list[Sample] = []
        n_real = config.batch // 2 if real else 0
        for _ in range(n_real):
            img, pts = real[int(rng.integers(len(real)))]
            samples.append(crop_sample(rng, img, pts, CROP, 24.0))
        samples += [synthetic_sample(rng, robots, camera) for _ in range(config.batch - n_real)]
        x, y = make_batch(samples)
        loss = heatmap_loss(net(x), y, config.foreground_weight)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        value = float(loss.detach())
        smoothed = value if step == 0 else 0.98 * smoothed + 0.02 * value
        if progress is not None:
            progress(step + 1, config.steps, smoothed)
    return net.eval()
