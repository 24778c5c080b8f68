"""The keypoint UNet: an RGB crop in, one heat map per fiducial out (torch).

A small UNet (Ronneberger et al. 2015; the paper adapts the one of Pryor et al. 2021): four
levels of two 3×3 convolutions with batch norm and ReLU, max-pool down, nearest-neighbour
upsampling and skip concatenation up, and a 1×1 head with one channel per fiducial
(:data:`magrun.tracking.keypoints.NAMES`). It is fully convolutional: it runs on the 96 px
crops it was trained on and on whole frames (sides multiples of 8). Targets are Gaussians of
σ = :data:`HEATMAP_SIGMA` px with peak 1; :func:`peak_candidates` lists each map's peaks
with their heights (the points' confidence) and :func:`refine_peak` places one to a
fraction of a pixel with a Gaussian fit.

Weights are stored as ``.npz`` (one array per parameter plus a JSON ``meta`` entry), not as
a pickle, so loading them runs no code.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn

from magrun.yamlio import read_npz, safe_json

FloatArray = NDArray[np.float64]

HEATMAP_SIGMA = 1.5  # px
N_KEYPOINTS = 3
#: input normalisation: uint8 RGB → roughly zero-mean, unit-range floats
MEAN, SCALE = 128.0, 1 / 64.0


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


def gaussian_heatmaps(points: FloatArray, shape: tuple[int, int]) -> NDArray[np.float32]:
    """Target maps, shape (K, H, W), peak 1 at each point (u, v) in px; NaN points give 0."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    out = np.zeros((len(points), h, w), dtype=np.float32)
    for k, (u, v) in enumerate(points):
        if np.isfinite(u) and np.isfinite(v):
            out[k] = np.exp(-((uu - u) ** 2 + (vv - v) ** 2) / (2 * HEATMAP_SIGMA**2))
    return out


def refine_peak(heatmap: NDArray[np.float32], u: int, v: int) -> tuple[float, float]:
    """Sub-pixel position of the peak at pixel (u, v) of one map.

    A Gaussian (log-parabola) through the peak and its two neighbours along each axis, exact
    for a sampled Gaussian peak; at the border the pixel position is kept.
    """
    h, w = heatmap.shape
    out = [float(u), float(v)]
    for axis, (coord, size) in enumerate(((u, w), (v, h))):
        if 0 < coord < size - 1:
            if axis == 0:
                a, b, c = heatmap[v, u - 1], heatmap[v, u], heatmap[v, u + 1]
            else:
                a, b, c = heatmap[v - 1, u], heatmap[v, u], heatmap[v + 1, u]
            la, lb, lc = np.log(np.maximum([a, b, c], 1e-4))
            den = la - 2 * lb + lc
            if den < 0:
                out[axis] += float(np.clip(0.5 * (la - lc) / den, -0.5, 0.5))
    return out[0], out[1]


def peak_candidates(
    heatmaps: NDArray[np.float32], max_peaks: int = 3, min_height: float = 0.2
) -> list[tuple[NDArray[np.intp], FloatArray]]:
    """Up to ``max_peaks`` local maxima (5 × 5 neighbourhood) of each map, highest first.

    Returns, per map, ``(pixels (n, 2) integer (u, v), heights (n,))``; a map with no peak
    above ``min_height`` gives its highest pixel alone. Refine the ones you keep with
    :func:`refine_peak`.
    """
    out = []
    for hm in heatmaps:
        local = cv2.dilate(hm, np.ones((5, 5), np.uint8))
        vs, us = np.nonzero((hm >= local) & (hm >= min_height))
        if vs.size == 0:
            v, u = np.unravel_index(int(np.argmax(hm)), hm.shape)
            vs, us = np.array([v]), np.array([u])
        heights = hm[vs, us].astype(np.float64)
        keep: list[int] = []
        for i in np.argsort(-heights, kind="stable"):
            # equal neighbours (a peak midway between pixels) are one peak
            if all(abs(us[i] - us[j]) > 2 or abs(vs[i] - vs[j]) > 2 for j in keep):
                keep.append(int(i))
            if len(keep) == max_peaks:
                break
        out.append((np.column_stack([us[keep], vs[keep]]), heights[keep]))
    return out


def save_weights(model: KeypointUNet, path: str | Path, meta: dict[str, Any]) -> None:
    """Write ``model``'s state and ``meta`` (JSON-able) to ``path`` (.npz)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in model.state_dict().items()}
    info = {"widths": list(model.widths), **meta}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, meta=np.array(json.dumps(info)), **arrays)
    tmp.replace(path)


#: the most levels and channels per level a weights file may declare (the shipped UNet has
#: 4 levels of 8–64): a bound on what a hostile file can make magrun allocate
MAX_LEVELS, MAX_WIDTH = 8, 1024


def load_weights(path: str | Path) -> tuple[KeypointUNet, dict[str, Any]]:
    """A model (eval mode) and its metadata from a file written by :func:`save_weights`.

    Raises ``ValueError`` naming what is wrong for anything else: not an ``.npz`` archive,
    pickled arrays, metadata that is not a JSON object with ``widths`` (1 to
    :data:`MAX_LEVELS` integers in 1 … :data:`MAX_WIDTH`), arrays that do not fit the model."""
    try:
        data = read_npz(path, "magrun tracker train")
    except ValueError as exc:
        raise ValueError(f"not a readable weights file: {exc}") from exc
    if "meta" not in data:
        raise ValueError("no `meta` array (magrun tracker train writes one)")
    meta = safe_json(str(data["meta"]), "its metadata")
    widths = meta.get("widths") if isinstance(meta, dict) else None
    if not (
        isinstance(widths, list)
        and 1 <= len(widths) <= MAX_LEVELS
        and all(type(w) is int and 1 <= w <= MAX_WIDTH for w in widths)
    ):
        raise ValueError(
            f"its metadata's `widths` must be 1 to {MAX_LEVELS} integers in 1 … {MAX_WIDTH}"
        )
    model = KeypointUNet(tuple(widths))
    want = model.state_dict()
    state = {}
    for name, array in data.items():
        if name == "meta":
            continue
        if name not in want or array.shape != tuple(want[name].shape):
            raise ValueError(f"array {name!r} does not fit a UNet of {widths}")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"array {name!r} holds NaN or infinite values")
        state[name] = torch.from_numpy(array.copy())
    missing = sorted(set(want) - set(state))
    if missing:
        raise ValueError(f"arrays missing: {', '.join(missing[:5])}")
    model.load_state_dict(state)
    return model.eval(), meta
