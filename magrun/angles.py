"""Planar angles: wrapping to one turn and unwrapping next to a reference (radians)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def wrap_angle(a: Any) -> Any:
    """Angle(s) wrapped to [−π, π)."""
    return (np.asarray(a) + math.pi) % (2 * math.pi) - math.pi


def angle_near(angle: float, ref: float) -> float:
    """``angle`` shifted by a multiple of 2π to lie within π of ``ref``."""
    return ref + float(wrap_angle(angle - ref)) if math.isfinite(angle) else angle
