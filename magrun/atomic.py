"""Atomic file writes: a reader (or a crash) never sees a half-written data file.

Each writer writes ``NAME.part`` beside the target and renames it over the target, which is
atomic on POSIX file systems.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


def _part(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.with_name(path.name + ".part")


def write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 text to ``path`` atomically."""
    path = Path(path)
    tmp = _part(path)
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def write_npz(path: str | Path, arrays: Mapping[str, NDArray[Any]]) -> None:
    """Write a compressed ``.npz`` of named arrays to ``path`` atomically (no pickles)."""
    path = Path(path)
    tmp = _part(path)
    with tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]  # numpy stubs mistype **kwds
    tmp.replace(path)
