"""Heat maps of the keypoint UNet, in NumPy: targets, peaks, sub-pixel refinement.

The UNet (:mod:`magrun.tracking.unet`) gives one heat map per fiducial. Targets are
Gaussians of σ = :data:`HEATMAP_SIGMA` px with peak 1; :func:`peak_candidates` lists each
map's peaks with their heights (the points' confidence) and :func:`refine_peak` places one
to a fraction of a pixel with a Gaussian fit. Nothing here needs torch: tracking runs the
network in ONNX Runtime (:mod:`magrun.tracking.inference`).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

HEATMAP_SIGMA = 1.5  # px
N_KEYPOINTS = 3
#: input normalisation: uint8 RGB → roughly zero-mean, unit-range floats
MEAN, SCALE = 128.0, 1 / 64.0


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
