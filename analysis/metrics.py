"""Per-sample and per-trial metrics: pose errors, clearance, controller statistics.

Pure functions on arrays (SI in, SI out) and one :func:`trial_metrics` that names the
results with their units. Definitions:

- position error: ``|p_actual − p_desired|`` (m); orientation error: ``|wrap(θ_a − θ_d)|``
  with ``wrap`` to (−π, π]; RMS over the trial's ticks, NaN samples (a stream missing at a
  tick) left out.
- clearance of the robot's body from a boundary: the body is a capsule (a segment of length
  ``L − D`` along the heading, radius ``D/2``); clearance is the distance from that segment to
  the boundary polyline minus ``D/2``, negative when the body overlaps the boundary.
- contact: clearance at or below :data:`CONTACT_MM`; ``contact_time_s`` with any boundary,
  ``contact_time_s[name]`` per boundary.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    import pandas as pd

FloatArray = NDArray[np.float64]


class TrialRecord(Protocol):
    """What :func:`trial_metrics` reads of a trial besides its samples (an
    :class:`analysis.load.Recording` is one)."""

    @property
    def boundaries(self) -> dict[str, np.ndarray]: ...  # name -> (n, 2) polyline, m

    @property
    def critical(self) -> str | None: ...

    @property
    def robot_length(self) -> float | None: ...  # m

    @property
    def robot_diameter(self) -> float | None: ...  # m

    @property
    def status(self) -> pd.DataFrame: ...  # the controller status per tick

    @property
    def recorder(self) -> dict[str, str]: ...  # the recorder's summary (dropped_ticks)

    @property
    def currents(self) -> pd.DataFrame: ...  # t (s), then one column per coil, A

    @property
    def trial(self) -> dict[str, Any]: ...  # the trial's metadata (max_current_a)

    def control_period(self) -> float: ...  # s


#: clearance, mm, at or below which the body counts as touching a boundary
CONTACT_MM = 0.05
#: the clearance percentile reported beside the minimum
CLEARANCE_PERCENTILE = 5.0


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Angles wrapped to (−π, π]."""
    a = np.asarray(a, dtype=np.float64)
    return np.pi - np.mod(np.pi - a, 2 * np.pi)


def pose_errors(actual: ArrayLike, reference: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Position error (m) and absolute wrapped orientation error (rad) of (n, 3) poses."""
    a = np.asarray(actual, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    pos = np.hypot(a[:, 0] - r[:, 0], a[:, 1] - r[:, 1])
    return pos, np.abs(wrap_angle(a[:, 2] - r[:, 2]))


def rms(values: ArrayLike) -> float:
    """Root mean square of the finite values; NaN if there are none."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else math.nan


def _point_segment_distance(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances from points ``p`` (..., 2) to segments ``a``–``b`` (..., 2), broadcast."""
    ab = b - a
    denom = np.maximum(np.sum(ab * ab, axis=-1), 1e-300)
    s = np.clip(np.sum((p - a) * ab, axis=-1) / denom, 0.0, 1.0)
    d = p - (a + s[..., None] * ab)
    return np.hypot(d[..., 0], d[..., 1])


def segment_segment_distance(
    p0: FloatArray, p1: FloatArray, a: FloatArray, b: FloatArray
) -> FloatArray:
    """Distances between 2-D segments ``p0``–``p1`` and ``a``–``b`` (arrays broadcast).

    Zero where they cross; otherwise the least of the four endpoint-to-segment distances.
    """

    def cross(o: FloatArray, u: FloatArray, v: FloatArray) -> FloatArray:
        return (u[..., 0] - o[..., 0]) * (v[..., 1] - o[..., 1]) - (u[..., 1] - o[..., 1]) * (
            v[..., 0] - o[..., 0]
        )

    d1, d2 = cross(a, b, p0), cross(a, b, p1)
    d3, d4 = cross(p0, p1, a), cross(p0, p1, b)
    crossing = (d1 * d2 < 0) & (d3 * d4 < 0)
    d = np.minimum.reduce(
        [
            _point_segment_distance(p0, a, b),
            _point_segment_distance(p1, a, b),
            _point_segment_distance(a, p0, p1),
            _point_segment_distance(b, p0, p1),
        ]
    )
    return np.where(crossing, 0.0, d)


def capsule_clearance(
    poses: ArrayLike, length: float, diameter: float, boundary: ArrayLike
) -> FloatArray:
    """Clearance, m, of a capsule body at each pose (n, 3) from a boundary polyline (m, 2).

    NaN for poses with NaN entries. Negative when the body overlaps the boundary (down to
    −D/2, when the body's axis touches it).
    """
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    line = np.asarray(boundary, dtype=np.float64).reshape(-1, 2)
    half = max(length / 2 - diameter / 2, 0.0)
    axis = np.stack([np.cos(p[:, 2]), np.sin(p[:, 2])], axis=1) * half
    p0, p1 = (p[:, :2] - axis)[:, None, :], (p[:, :2] + axis)[:, None, :]
    a, b = line[None, :-1], line[None, 1:]
    out = np.full(len(p), np.nan)
    good = np.flatnonzero(np.all(np.isfinite(p), axis=1))
    for start in range(0, good.size, 2048):  # bounded memory: 2048 poses × segments at a time
        i = good[start : start + 2048]
        out[i] = segment_segment_distance(p0[i], p1[i], a, b).min(axis=1) - diameter / 2
    return out


def time_in(mask: ArrayLike, t: ArrayLike) -> float:
    """Time, s, during which ``mask`` holds: each sample counts until the next one."""
    m = np.asarray(mask, dtype=bool)
    tt = np.asarray(t, dtype=np.float64)
    if tt.size < 2:
        return 0.0
    dt = np.diff(tt, append=tt[-1] + np.median(np.diff(tt)))
    return float(np.sum(dt[m]))


def _q(values: ArrayLike, q: float) -> float:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(np.percentile(v, q)) if v.size else math.nan


def trial_metrics(
    rec: TrialRecord, samples: pd.DataFrame, contact_mm: float = CONTACT_MM
) -> dict[str, Any]:
    """One trial's metrics, named with units; NaN where a recording has nothing to say.

    ``samples`` is :func:`analysis.load.samples_of` of ``rec``.
    """
    out: dict[str, Any] = {
        "duration_s": float(samples["t"].iloc[-1] - samples["t"].iloc[0]) if len(samples) else 0.0,
        "ticks": len(samples),
        "rms_position_mm": rms(samples["position_error_mm"]),
        "rms_orientation_deg": rms(samples["orientation_error_deg"]),
        "max_position_mm": _q(samples["position_error_mm"], 100),
        "rms_prediction_position_mm": rms(samples["prediction_position_error_mm"]),
        "rms_prediction_orientation_deg": rms(samples["prediction_orientation_error_deg"]),
        "rms_prediction_measured_position_mm": rms(
            samples["prediction_measured_position_error_mm"]
        ),
        "rms_prediction_measured_orientation_deg": rms(
            samples["prediction_measured_orientation_error_deg"]
        ),
    }
    out.update(coil_effort(rec.currents, rec.trial.get("max_current_a")))
    # clearance from every boundary, and contact with any
    t = samples["t"].to_numpy()
    actual = samples[["x", "y", "theta"]].to_numpy()
    length, diameter = rec.robot_length, rec.robot_diameter
    touching = np.zeros(len(samples), dtype=bool)
    out["min_clearance_mm"] = math.nan
    out["p5_clearance_mm"] = math.nan
    out["contact_time_s"] = math.nan
    if rec.boundaries and length is not None:
        for name, line in rec.boundaries.items():
            c = 1e3 * capsule_clearance(actual, length, diameter or 0.0, line)
            out[f"min_clearance_mm[{name}]"] = _q(c, 0)
            out[f"p5_clearance_mm[{name}]"] = _q(c, CLEARANCE_PERCENTILE)
            touching |= c <= contact_mm
            out[f"contact_time_s[{name}]"] = time_in(c <= contact_mm, t)
            if name == rec.critical:
                out["min_clearance_mm"] = _q(c, 0)
                out["p5_clearance_mm"] = _q(c, CLEARANCE_PERCENTILE)
        out["contact_time_s"] = time_in(touching, t)
    # controller statistics
    st = rec.status
    period = rec.control_period()
    ct = st["compute_time"].to_numpy(dtype=np.float64)
    out.update(
        {
            "solve_ms_median": _q(st["solve_time"] * 1e3, 50),
            "solve_ms_p99": _q(st["solve_time"] * 1e3, 99),
            "prepare_ms_median": _q(st["prepare_time"] * 1e3, 50),
            "compute_ms_median": _q(ct * 1e3, 50),
            "compute_ms_p99": _q(ct * 1e3, 99),
            "iterations_median": _q(st["iterations"], 50),
            "control_rate_hz": (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0]
            else math.nan,
            "overrun_fraction": float(np.mean(ct > period)) if ct.size and math.isfinite(period)
            else math.nan,
            "fallbacks": int((st["fallback"].astype(str) != "").sum()),
            "solve_failures": int((~st["success"].astype(bool)).sum()),
            "measurements": int(st["measurement"].astype(bool).sum()),
            "tracking_lost": int(st["tracking_lost"].astype(bool).sum()),
            "dropped_ticks": _int_or_nan(rec.recorder.get("dropped_ticks")),
        }
    )  # fmt: skip
    return out


#: a current within this fraction of its limit counts as at the limit
AT_LIMIT = 0.995


def coil_effort(currents: pd.DataFrame, limits: Any = None) -> dict[str, float]:
    """The coils' effort over a trial from its applied currents (``t`` in s, then one column
    per coil in A; each value holds until the next sample):

    - ``rms_current_a[<coil>]`` per coil and ``rms_current_a`` over all coils;
    - ``current_squared_integral_a2s``: ∫ Σₖ Iₖ² dt, A² s (the coils' heat, per ohm);
    - ``current_variation_a``: the currents' total variation Σₖ Σ |ΔIₖ|, A (chatter);
    - ``time_at_limit_s``: time during which any coil is within 0.5 % of its limit, s, where
      the recording states its limits (``max_current_a``: one number, or one per coil);
      NaN where it does not.
    """
    coils = [c for c in currents.columns if c not in ("t", "t_ns")]
    out: dict[str, float] = {}
    if not coils or len(currents) == 0:
        return {"rms_current_a": math.nan, "current_squared_integral_a2s": math.nan,
                "current_variation_a": math.nan, "time_at_limit_s": math.nan}  # fmt: skip
    I = currents[coils].to_numpy(dtype=np.float64)
    t = currents["t"].to_numpy(dtype=np.float64)
    dt = np.diff(t, append=t[-1] + (np.median(np.diff(t)) if t.size > 1 else 0.0))
    for k, name in enumerate(coils):
        out[f"rms_current_a[{name}]"] = rms(I[:, k])
    out["rms_current_a"] = rms(I)
    out["current_squared_integral_a2s"] = float(np.sum(np.sum(I * I, axis=1) * dt))
    out["current_variation_a"] = float(np.sum(np.abs(np.diff(I, axis=0))))
    try:
        lim = np.broadcast_to(np.asarray(limits, dtype=np.float64), (len(coils),))
    except (TypeError, ValueError):
        lim = None
    if lim is None or not np.all(np.isfinite(lim) & (lim > 0)):
        out["time_at_limit_s"] = math.nan
    else:
        at = np.any(np.abs(I) >= AT_LIMIT * lim, axis=1)
        out["time_at_limit_s"] = float(np.sum(dt[at]))
    return out


def _int_or_nan(value: Any) -> float:
    try:
        return float(int(value))
    except (TypeError, ValueError):
        return math.nan
