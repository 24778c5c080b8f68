"""The keypoint UNet: an RGB crop in, one heat map per fiducial out (torch).

A small UNet (Ronneberger et al. 2015; the paper adapts the one of Pryor et al. 2021): four
levels of two 3×3 convolutions with batch norm and ReLU, max-pool down, nearest-neighbour
upsampling and skip concatenation up, and a 1×1 head with one channel per fiducial
(:data:`magrun.tracking.keypoints.NAMES`). It is fully convolutional: it runs on the 96 px
crops it was trained on and on whole frames (sides multiples of 8). Its targets and the
peaks of its heat maps: :mod:`magrun.tracking.heatmaps`.

Weights are stored as ``.npz`` (:mod:`magrun.tracking.weights`), not as a pickle, so
loading them runs no code. Only training, evaluation against torch and the ONNX export
(:mod:`magrun.tracking.export`) build this module's network; tracking runs its ONNX graph.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from magrun.tracking.heatmaps import MEAN, SCALE
from magrun.tracking.weights import WeightsFile, read_weights


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1, bias=False),
        nn.BatchNorm2d(c_out),
        nn.ReLU(inplace=True),
    )


class KeypointUNet(nn.Module):
    """UNet with ``widths`` channels per level; input (B, 3, H, W), output (B, K, H, W)."""

    def __init__(self, widths: tuple[int, ...] = (8, 16, 32, 64), n_keypoints: int = 3):
        super().__init__()
        self.widths = tuple(widths)
        self.encoders = nn.ModuleList()
        c = 3
        for w in widths:
            self.encoders.append(_block(c, w))
            c = w
        self.decoders = nn.ModuleList()
        for w in reversed(widths[:-1]):
            self.decoders.append(_block(c + w, w))
            c = w
        self.head = nn.Conv2d(c, n_keypoints, 1)

    @property
    def stride(self) -> int:
        """Input sides must be multiples of this."""
        return 2 ** (len(self.widths) - 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for level, enc in enumerate(self.encoders):
            if level:
                x = nn.functional.max_pool2d(x, 2)
            x = enc(x)
            skips.append(x)
        for dec, skip in zip(self.decoders, reversed(skips[:-1]), strict=True):
            x = nn.functional.interpolate(x, scale_factor=2.0, mode="nearest")
            x = dec(torch.cat([x, skip], dim=1))
        out: torch.Tensor = self.head(x)
        return out


def to_input(images: NDArray[np.uint8]) -> torch.Tensor:
    """uint8 RGB images (B, H, W, 3) or one (H, W, 3) → normalised float tensor (B, 3, H, W)."""
    a = images[None] if images.ndim == 3 else images
    t = torch.from_numpy(np.ascontiguousarray(a)).permute(0, 3, 1, 2).float()
    return ((t - MEAN) * SCALE).contiguous(memory_format=torch.channels_last)


def save_weights(model: KeypointUNet, path: str | Path, meta: dict[str, Any]) -> None:
    """Write ``model``'s state and ``meta`` (JSON-able) to ``path`` (.npz)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    info = {"widths": list(model.widths), **meta}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, meta=np.array(json.dumps(info)), **arrays)
    tmp.replace(path)


def load_weights(path: str | Path) -> tuple[KeypointUNet, dict[str, Any]]:
    """A model (eval mode) and its metadata from a file written by :func:`save_weights`.

    Raises ``ValueError`` naming what is wrong (:func:`magrun.tracking.weights.read_weights`),
    or which array does not fit a UNet of the file's widths."""
    weights = read_weights(path)
    return model_of(weights), weights.meta


def model_of(weights: WeightsFile) -> KeypointUNet:
    """The model (eval mode) of a weights file already read; ``ValueError`` naming an array
    that does not fit a UNet of its widths."""
    model = KeypointUNet(weights.widths)
    want = model.state_dict()
    state = {}
    for name, array in weights.arrays.items():
        if name not in want or array.shape != tuple(want[name].shape):
            raise ValueError(f"array {name!r} does not fit a UNet of {list(weights.widths)}")
        state[name] = torch.from_numpy(array.copy())
    missing = sorted(set(want) - set(state))
    if missing:
        raise ValueError(f"arrays missing: {', '.join(missing[:5])}")
    model.load_state_dict(state)
    return model.eval()
