"""What the replay's modes share: their error, the recorded trial rebuilt from its own
protocol, and the RMS error of one pose stream against another."""

from __future__ import annotations

import math
import re

import numpy as np
from numpy.typing import NDArray

from magrun.protocol import Conditions, Trial, protocol_from_json
from magrun.recordings.reader import RecordedTrial

FloatArray = NDArray[np.float64]


class ReplayError(ValueError):
    """A recording that cannot be replayed, or settings that do not apply to it."""


def rms_errors(estimate: FloatArray, truth: FloatArray) -> tuple[float, float]:
    """RMS position (mm) and heading (°, wrapped) error of ``estimate`` against ``truth``
    over the rows where both are finite."""
    ok = np.all(np.isfinite(estimate), axis=1) & np.all(np.isfinite(truth), axis=1)
    if not ok.any():
        return math.nan, math.nan
    d = estimate[ok] - truth[ok]
    pos = float(np.sqrt(np.mean(d[:, 0] ** 2 + d[:, 1] ** 2))) * 1e3
    ang = (d[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return pos, float(np.degrees(np.sqrt(np.mean(ang**2))))


def trial_of(rec: RecordedTrial, overrides: tuple[str, ...] = ()) -> Trial:
    """The recorded trial, its protocol rebuilt from the recording with ``overrides``."""
    from magrun.yamlio import YamlModelError

    meta = rec.trial
    if not rec.protocol_json:
        raise ReplayError(f"{rec.path}: no `protocol` metadata record to rebuild the trial from")
    source = f"{rec.path} (recorded protocol)"
    try:
        protocol = protocol_from_json(rec.protocol_json, source, overrides)
    except YamlModelError as exc:
        # files the protocol named, recorded as paths on the machine that ran it
        hints = [
            f"\n(a {what} recorded elsewhere: give its path, --set {key}=PATH)"
            for key, what in _RECORDED_FILES.items()
            if _names_setting(str(exc), key)
        ]
        raise ReplayError(f"{exc}{''.join(hints)}") from exc
    try:
        condition = Conditions(**{k: meta[k] for k in Conditions.model_fields if k in meta})
        return Trial(
            protocol=protocol, method=str(meta["method"]), condition=condition, swept=(),
            index=int(meta.get("trial", 0)), seed=int(meta["seed"]),
            slug=rec.path.parent.name, quick=bool(meta.get("quick", False)),
        )  # fmt: skip
    except (KeyError, ValueError, TypeError) as exc:
        raise ReplayError(f"{rec.path}: the `trial` metadata record is incomplete: {exc}") from exc


def _names_setting(message: str, key: str) -> bool:
    """Whether an error ``message`` names the dotted setting ``key`` (as written: the
    validation's errors drop a union's tags, :func:`magrun.yamlio.validate_data`)."""
    return re.search(rf"(?<![\w.]){re.escape(key)}(?![\w])", message) is not None


#: protocol settings that name files, as replay's errors hint at them
_RECORDED_FILES = {
    "workspace.phantom": "phantom",
    "robots_file": "robots file",
    "controller.coil_gains": "coil calibration",
    "simulation.plant": "plant file",
    "system": "coil-system folder",
}
