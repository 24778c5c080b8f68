"""Replay: a recorded trial's estimator run again, offline, with other settings.

:func:`replay_estimator` rebuilds the trial's controller from the recording's own protocol
(with ``--set`` overrides), then walks the recorded ticks: at each, the estimator gets the
recorded measurement (or none, between fluoroscopy frames) and, as its prior, the prediction
the controller's model made at the previous tick *from the replayed estimate* under the
currents the recording says were applied (:meth:`~magrun.control.base.Controller.replay_step`).
A changed filter therefore sees the consequences of its own estimates; only the plan is taken
from the recording, since the robot really moved under those currents. A late frame is fused
at the tick it was taken, as live: its age is the measured pose's log time less its time stamp
(:attr:`~magrun.recordings.reader.RecordedTrial.measured_age`).

:func:`write_replay` writes the result: a copy of the recording's channels and metadata with
``/replay/<label>/robot/pose/estimated`` and ``…/predicted`` added, a ``replay`` metadata
record saying what was changed, and an ``.rrd`` beside it
(:mod:`magrun.recordings.rerun_log`), where the replayed streams are drawn over the recorded
ones.

Why replaying the recording's own settings is not exact: in the live loop the next tick's
prior is the NMPC's own predicted state from its solve; the replay predicts with the model
alone (:meth:`~magrun.control.base.Planner.predict`) from the replayed state. The two
integrate the same model, so they agree to the solver's tolerance, not to the last bit.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.recordings.reader import RecordedTrial, read_ticks
from magrun.replay.common import ReplayError, rms_errors, trial_of

FloatArray = NDArray[np.float64]

#: ``--estimator`` names and what they build
ESTIMATORS = ("kalman", "measurement", "hold")


@dataclass
class EstimatorReplay:
    """What :func:`replay_estimator` gives: the replayed streams and their errors."""

    label: str
    method: str
    estimator: str  # the estimator's class name
    settings: tuple[str, ...]  # the --set overrides
    t: FloatArray  # (n,) s
    estimated: FloatArray  # (n, 3)
    predicted: FloatArray  # (n, 3): the previous tick's prediction of this one (NaN at 0)
    recorded_estimated: FloatArray  # (n, 3)
    actual: FloatArray  # (n, 3)
    wall_s: float
    errors: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """The figures ``magrun replay --json`` prints."""
        return {
            "label": self.label,
            "method": self.method,
            "estimator": self.estimator,
            "settings": list(self.settings),
            "ticks": len(self.t),
            "duration_s": float(self.t[-1]) if len(self.t) else 0.0,
            "wall_s": self.wall_s,
            **self.errors,
        }


def replay_estimator(
    path: str | Path,
    overrides: tuple[str, ...] = (),
    estimator: str | None = None,
    label: str = "replay",
) -> tuple[RecordedTrial, EstimatorReplay]:
    """Replay the estimator of the recording at ``path`` (module doc).

    ``overrides``: ``KEY=VALUE`` protocol settings (dotted keys), e.g.
    ``controller.kalman.measurement_sigma_mm=0.5``. ``estimator``: replace the method's own
    estimator by ``kalman`` (the proposed method's filter, tuned by the protocol),
    ``measurement`` (the measurement, else the prediction) or ``hold`` (the last
    measurement). Raises :class:`ReplayError` (or
    :class:`~magrun.recordings.reader.RecordingReadError`) on a recording or settings it cannot
    use.
    """
    from magrun.control.estimation import (
        HoldLastMeasurement,
        KalmanPoseFilter,
        MeasurementOrPrediction,
    )
    from magrun.trial import RunError, build_controller

    if estimator is not None and estimator not in ESTIMATORS:
        raise ReplayError(f"unknown estimator {estimator!r}; one of {', '.join(ESTIMATORS)}")
    rec = read_ticks(path)
    trial = trial_of(rec, overrides)
    try:
        parts = build_controller(trial)
    except (OSError, ValueError, RunError) as exc:
        raise ReplayError(f"{rec.path}: cannot rebuild the trial's controller: {exc}") from exc
    controller = parts.controller
    if estimator is not None:
        controller.estimator = {
            "kalman": lambda: KalmanPoseFilter(parts.config.kalman),
            "measurement": MeasurementOrPrediction,
            "hold": HoldLastMeasurement,
        }[estimator]()
        controller.velocity = "model" if estimator == "kalman" else "difference"
    if rec.currents.shape[1] != controller.n_channels:
        raise ReplayError(
            f"{rec.path}: {rec.currents.shape[1]} current channels recorded, the controller "
            f"has {controller.n_channels}"
        )
    start = rec.poses["desired"][0]
    if not np.all(np.isfinite(start)):
        raise ReplayError(f"{rec.path}: no desired pose at the first tick to start from")
    t0 = time.perf_counter()
    controller.reset(start)
    n = len(rec.t)
    estimated = np.empty((n, 3))
    predicted = np.full((n, 3), np.nan)
    for k in range(n):
        estimated[k], prediction = controller.replay_step(
            rec.measured(k), rec.currents[k], rec.age(k)
        )
        if k + 1 < n:
            predicted[k + 1] = prediction
    result = EstimatorReplay(
        label=label, method=trial.method, estimator=type(controller.estimator).__name__,
        settings=tuple(overrides), t=rec.t, estimated=estimated, predicted=predicted,
        recorded_estimated=rec.poses["estimated"], actual=rec.poses["actual"],
        wall_s=time.perf_counter() - t0,
    )  # fmt: skip
    rec_pos, rec_deg = rms_errors(result.recorded_estimated, result.actual)
    new_pos, new_deg = rms_errors(estimated, result.actual)
    diff_pos, diff_deg = rms_errors(estimated, result.recorded_estimated)
    result.errors = {
        "rms_estimation_error_recorded_mm": rec_pos,
        "rms_estimation_error_recorded_deg": rec_deg,
        "rms_estimation_error_replayed_mm": new_pos,
        "rms_estimation_error_replayed_deg": new_deg,
        "rms_replayed_vs_recorded_mm": diff_pos,
        "rms_replayed_vs_recorded_deg": diff_deg,
    }
    return rec, result


def replay_topic(label: str, stream: str) -> str:
    """``/replay/<label>/robot/pose/<stream>``."""
    return f"/replay/{label}/robot/pose/{stream}"


def write_replay(
    rec: RecordedTrial, result: EstimatorReplay, out: str | Path, view: str = ""
) -> Path:
    """Copy ``rec``'s file to ``out`` (.mcap) with the replayed streams and a ``replay``
    metadata record added, written to a temporary name and renamed when complete; then its
    ``.rrd`` beside it, streamed to the Rerun viewer at the gRPC URL ``view`` as well if one
    is given. Returns the ``.rrd``'s path."""
    from magrun.recordings.rerun_log import rrd_from_mcap
    from magrun.recordings.writer import copy_with_poses

    out = Path(out)
    if out.resolve() == rec.path.resolve():
        raise ReplayError(f"{out}: write the replay elsewhere, never over the recording")
    out.parent.mkdir(parents=True, exist_ok=True)
    extra: list[tuple[int, str, FloatArray]] = []  # (log time, topic, pose) in time order
    for k, t_ns in enumerate(rec.t_ns.tolist()):
        extra.append((t_ns, replay_topic(result.label, "estimated"), result.estimated[k]))
        if np.all(np.isfinite(result.predicted[k])):
            extra.append((t_ns, replay_topic(result.label, "predicted"), result.predicted[k]))
    record = {
        "source": rec.path.name,
        "kind": "estimator",
        "label": result.label,
        "estimator": result.estimator,
        "settings": json.dumps(list(result.settings)),
        **{k: json.dumps(v) for k, v in result.errors.items()},
    }
    # a replay of a replay keeps only its own "replay" record (the copy drops the source's)
    copy_with_poses(rec.path, out, extra, "replay", record)
    rrd = out.with_suffix(".rrd")
    rrd_from_mcap(out, rrd, live_view=view)
    return rrd
