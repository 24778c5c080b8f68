"""The tracker's weights file, read and checked without torch.

``magrun tracker train`` writes the UNet's parameters as an ``.npz`` archive (one array per
parameter plus a JSON ``meta`` entry: the levels' ``widths``, the scale ``px_per_mm`` the
model was trained at, how it was trained), not as a pickle, so reading one runs no code.
Beside it, with the same name and the suffix ``.onnx``, lies the network's ONNX graph, which
tracking runs (:mod:`magrun.tracking.inference`); the graph names the weights it was exported
from by :meth:`WeightsFile.digest`, so a graph left beside retrained weights is noticed.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.yamlio import read_npz, safe_json

#: the most levels and channels per level a weights file may declare (the shipped UNet has
#: 4 levels of 8–64): a bound on what a hostile file can make magrun allocate
MAX_LEVELS, MAX_WIDTH = 8, 1024
#: the scale of the shipped model's training frames, px per mm (older files do not say)
DEFAULT_PX_PER_MM = 2.5


def graph_path_of(weights: Path) -> Path:
    """Where the ONNX graph of the weights file ``weights`` lies: beside it, suffix ``.onnx``."""
    return weights.with_suffix(".onnx")


@dataclass(frozen=True)
class WeightsFile:
    """A weights file's arrays (parameter name → array, ``meta`` left out) and metadata."""

    path: Path
    arrays: dict[str, NDArray[Any]]
    meta: dict[str, Any]

    @property
    def widths(self) -> tuple[int, ...]:
        """Channels per level of the UNet."""
        return tuple(self.meta["widths"])

    @property
    def stride(self) -> int:
        """The network's input sides must be multiples of this."""
        return 2 ** (len(self.widths) - 1)

    @property
    def px_per_mm(self) -> float:
        """The scale the model was trained at, px per mm."""
        return float(self.meta.get("px_per_mm", DEFAULT_PX_PER_MM))

    @property
    def graph_path(self) -> Path:
        """Where the ONNX graph of these weights lies (:func:`graph_path_of`)."""
        return graph_path_of(self.path)

    def digest(self) -> str:
        """SHA-256 of the parameters (names, dtypes, shapes and values, by name)."""
        h = hashlib.sha256()
        for name in sorted(self.arrays):
            a = np.ascontiguousarray(self.arrays[name])
            h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
            h.update(a.tobytes())
        return h.hexdigest()


def read_weights(path: str | Path) -> WeightsFile:
    """The arrays and metadata of a file written by ``magrun tracker train``.

    Raises ``ValueError`` naming what is wrong for anything else: not an ``.npz`` archive,
    pickled arrays, metadata that is not a JSON object with ``widths`` (1 to
    :data:`MAX_LEVELS` integers in 1 … :data:`MAX_WIDTH`), NaN or infinite values. Whether
    the arrays fit a UNet of those widths is checked where the network is built
    (:func:`magrun.tracking.unet.load_weights`) or run (its ONNX graph)."""
    try:
        data = read_npz(path, "magrun tracker train")
    except ValueError as exc:
        raise ValueError(f"not a readable weights file: {exc}") from exc
    if "meta" not in data:
        raise ValueError("no `meta` array (magrun tracker train writes one)")
    meta = safe_json(str(data.pop("meta")), "its metadata")
    widths = meta.get("widths") if isinstance(meta, dict) else None
    if not (
        isinstance(widths, list)
        and 1 <= len(widths) <= MAX_LEVELS
        and all(type(w) is int and 1 <= w <= MAX_WIDTH for w in widths)
    ):
        raise ValueError(
            f"its metadata's `widths` must be 1 to {MAX_LEVELS} integers in 1 … {MAX_WIDTH}"
        )
    px = meta.get("px_per_mm", DEFAULT_PX_PER_MM)
    if not (isinstance(px, int | float) and not isinstance(px, bool) and 0 < px < 1e4):
        raise ValueError("its metadata's `px_per_mm` must be a positive number")
    for name, array in data.items():
        if array.dtype.kind not in "fiu":
            raise ValueError(f"array {name!r} is not numeric ({array.dtype})")
        if not np.all(np.isfinite(array)):
            raise ValueError(f"array {name!r} holds NaN or infinite values")
    return WeightsFile(Path(path), data, meta)
