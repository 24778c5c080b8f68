"""Was a trial healthy? Warnings that a trial which ran to its end still deserves.

A trial whose controller saturated every coil for seconds, whose solver kept failing, whose
estimate lost the robot, or whose robot touched the critical boundary has not failed (the
safety layer had no reason to stop it, and its recording is complete), but it is not simply
``ok`` either. :func:`trial_health` measures those conditions on a :class:`~magrun.loop.TrialLog`;
the runner writes the figures and the warnings into the trial's manifest entry
(``warnings``, a list of sentences), ``magrun run`` prints them, and ``magrun figures``'
report lists the trials that have them.

Thresholds (:class:`HealthLimits`) are deliberately loose: a warning means "look at this
trial", not "discard it".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.freespace import FreeSpace

FloatArray = NDArray[np.float64]

#: clearance, m, at or below which the body counts as touching a boundary (as the analysis)
CONTACT = 0.05e-3


@dataclass(frozen=True)
class HealthLimits:
    """When a trial gets a warning (SI units)."""

    #: a coil at its current limit (≥ 99 %) for longer than this, uninterrupted, s
    saturation_s: float = 1.0
    #: more solver failures (fallbacks) than this share of the ticks
    failed_solves: float = 0.01
    #: the estimate further than this from the actual pose, m (the estimate lost the robot)
    estimate_error: float = 5e-3
    #: more ticks than this share whose measured compute exceeded the control period (the
    #: controller, with tracking, is too slow for the rig at this rate)
    overruns: float = 0.01
    #: the robot counts as lost when it is further from the reference than ``lost_extent``
    #: of the reference's extent (the diagonal of its bounding box; at least ``lost_floor``,
    #: m) in at least ``lost_share`` of the ticks: not a large error, the task given up
    lost_extent: float = 0.25
    lost_floor: float = 2e-3
    lost_share: float = 0.25


def longest_run(mask: NDArray[np.bool_]) -> int:
    """Length of the longest run of consecutive True values."""
    best = run = 0
    for v in mask:
        run = run + 1 if v else 0
        best = max(best, run)
    return best


def prediction_error(
    log: Any,
    dt: float,
    predict: Callable[[FloatArray, FloatArray], FloatArray],
    steps: int = 1,
) -> tuple[float, float]:
    """The controller model's prediction error over ``steps`` ticks from the *actual* state,
    as per-tick process noise: (per-axis position σ, m; heading σ, rad), each the RMS error of
    the ``steps``-tick prediction divided by √steps.

    The prediction starts at tick k from the actual pose and its finite-difference velocity
    and applies the recorded currents of ticks k … k + steps − 1; it is compared with the
    actual pose at k + steps. A pose Kalman filter whose prediction is the model's adds its
    process noise Q every tick and is corrected once per fluoroscopy frame: with ``steps`` the
    ticks between frames, Q = σ² is what makes the filter's spread at a frame match the
    model's real error there. (The model's errors are correlated from tick to tick, a
    parameter bias above all, so the one-tick error, ``steps`` = 1, understates it: on the
    simulated rig by about √steps.) robots.yaml's ``prediction_sigma_mm`` / ``_deg`` are trial
    means of this at 3 Hz.
    """
    a, I = log.actual, log.currents
    pos, ang = [], []
    for k in range(1, len(a) - steps):
        velocity = (a[k] - a[k - 1]) / dt
        velocity[2] = ((a[k, 2] - a[k - 1, 2] + math.pi) % (2 * math.pi) - math.pi) / dt
        x = np.concatenate([a[k], velocity])
        if not np.all(np.isfinite(x)) or not np.all(np.isfinite(a[k + steps])):
            continue
        for j in range(steps):
            x = predict(x, I[k + j])
        pos.append(float(np.sum((x[:2] - a[k + steps, :2]) ** 2)))
        ang.append(float(((x[2] - a[k + steps, 2] + math.pi) % (2 * math.pi) - math.pi) ** 2))
    if not pos:
        return math.nan, math.nan
    return math.sqrt(np.mean(pos) / 2 / steps), math.sqrt(np.mean(ang) / steps)


def trial_health(
    log: Any,
    dt: float,
    max_current: float | FloatArray,
    free_space: FreeSpace | None = None,
    limits: HealthLimits | None = None,
    predict: Callable[[FloatArray, FloatArray], FloatArray] | None = None,
    frame_ticks: int = 1,
) -> tuple[dict[str, Any], list[str]]:
    """Health figures of one trial and the warnings they raise.

    Parameters
    ----------
    log : magrun.loop.TrialLog
        The trial's ticks.
    dt : float
        Control period, s.
    max_current : float
        The coils' current limit, A.
    free_space : FreeSpace, optional
        With a critical boundary: the time the actual body touched it is measured.
    predict : callable, optional
        The controller's model, ``predict(state (6,), currents) -> state``: its prediction
        error from the actual state over ``frame_ticks`` ticks (the ticks between two
        fluoroscopy frames), as per-tick process noise, is measured
        (:func:`prediction_error`).

    Returns
    -------
    figures : dict
        ``failed_solves`` (count), ``longest_saturation_s``, ``max_estimate_error_mm``,
        ``lost`` (the robot lost: :class:`HealthLimits`) and ``lost_share`` (the share of
        ticks beyond the loss distance); with
        a critical boundary, ``critical_contact_s``; with ``predict``,
        ``prediction_sigma_mm`` and ``prediction_sigma_deg``.
    warnings : list of str
        One sentence per condition beyond :class:`HealthLimits`.
    """
    lim = limits or HealthLimits()
    n = len(log.t)
    failed = sum(not s.success for s in log.status)
    saturated = np.any(np.abs(log.currents) >= 0.99 * max_current, axis=1)
    longest = longest_run(saturated) * dt
    err = np.hypot(*(log.estimated[:, :2] - log.actual[:, :2]).T)
    finite = err[np.isfinite(err)]
    worst = float(finite.max()) if finite.size else math.nan
    desired = log.desired[:, :2]
    extent = float(np.hypot(*np.ptp(desired, axis=0))) if n else 0.0
    far = max(lim.lost_extent * extent, lim.lost_floor)
    error = np.hypot(*(log.actual[:, :2] - desired).T)
    # a NaN pose (a rig's tracking that lost the robot) is as far as any
    beyond = float(np.mean(~(error <= far))) if n else 0.0
    lost = beyond >= lim.lost_share
    figures: dict[str, Any] = {
        "failed_solves": int(failed),
        "longest_saturation_s": float(longest),
        "max_estimate_error_mm": worst * 1e3,
        "lost": bool(lost),
        "lost_share": beyond,
    }
    if predict is not None:
        sigma, sigma_angle = prediction_error(log, dt, predict, frame_ticks)
        figures["prediction_sigma_mm"] = sigma * 1e3
        figures["prediction_sigma_deg"] = math.degrees(sigma_angle)
    warnings: list[str] = []
    if lost:
        warnings.append(
            f"the robot was lost: more than {far * 1e3:.1f} mm from the reference in "
            f"{beyond:.0%} of the ticks"
        )
    if n and failed > lim.failed_solves * n:
        warnings.append(f"{failed} failed solves in {n} ticks (the previous plan was used)")
    if longest > lim.saturation_s:
        warnings.append(f"a coil at its current limit for {longest:.1f} s without a break")
    over = log.compute_time > dt
    if n and np.count_nonzero(over) > lim.overruns * n:
        warnings.append(
            f"{np.count_nonzero(over)} of {n} ticks' compute exceeded the {dt * 1e3:.1f} ms"
            f" control period (longest {log.compute_time.max() * 1e3:.1f} ms): too slow for"
            " the rig at this rate"
        )
    if worst > lim.estimate_error:
        i = int(np.nanargmax(err))
        warnings.append(
            f"the estimate was {worst * 1e3:.1f} mm from the robot at t = {log.t[i]:.1f} s"
        )
    if free_space is not None and free_space.critical is not None:
        touching = np.array(
            [free_space.clearance(p, [free_space.critical]) <= CONTACT for p in log.actual]
        )
        contact = float(np.count_nonzero(touching) * dt)
        figures["critical_contact_s"] = contact
        if contact > 0:
            first = float(log.t[int(np.argmax(touching))])
            warnings.append(
                f"the body touched the critical boundary ({free_space.critical}) for "
                f"{contact:.2f} s, first at t = {first:.1f} s"
            )
    return figures, warnings
