"""System identification: the robot's and the coils' parameters fitted to recordings.

:func:`identify` adjusts a few factors on the nominal robot and coils so that the open-loop
predictions of :mod:`magrun.prediction` (from each recorded actual pose, under the recorded
currents, 1 … K ticks ahead) match the recorded poses, by nonlinear least squares
(``scipy.optimize.least_squares``). Residuals are position errors in mm and heading errors
as the displacement of the robot's end (θ × half its length), in mm.

What recordings can tell apart, and so what is fitted:

- ``force_factor``: the magnetic moment over the drag, relative to the nominal robot. The
  robot is heavily damped (it reaches its drift speed in a few ms, against a 39 ms tick), so
  its motion follows moment × field / drag: a moment 5 % larger and a drag 5 % larger give the
  same path. The fit puts the factor on the moment and keeps the nominal drag.
- ``coil_gains``: each channel's field per ampere relative to the model, normalised to a
  geometric mean of 1. A common scale of all coils acts as a stronger moment and is part of
  ``force_factor``.
The mass is not fitted: it shows only in the first milliseconds after a current change, and
a fit of it to four 52 s recordings came out 3× off while everything else was within 1 %; it
stays nominal.

Against a simulated plant with known draws (the recordings' ``plant`` record) these compare
as: ``force_factor`` with (moment factor × geometric-mean gain) / drag factor, and each gain
with the drawn gain over the drawn gains' geometric mean (tests/test_identify.py).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.prediction import Segments, errors_of, field_function, rollout, segments_of
from magrun.recorded import read_ticks
from magrun.replay import ReplayError, trial_of

FloatArray = NDArray[np.float64]


@dataclass
class Identification:
    """The fitted factors and the prediction errors before and after."""

    robot: str  # the nominal robot's name
    robots_file: str | None  # its robots file (None: magrun's robots.yaml)
    model: str
    horizon: int
    force_factor: float
    coil_gains: dict[str, float]
    train: list[str]
    test: list[str]
    errors: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    cost_evaluations: int = 0
    wall_s: float = 0.0

    def summary(self) -> dict[str, Any]:
        """What ``magrun identify --json`` prints."""
        return {
            "robot": self.robot, "model": self.model, "horizon": self.horizon,
            "force_factor": self.force_factor,
            "coil_gains": self.coil_gains, "train": self.train, "test": self.test,
            "errors": self.errors, "cost_evaluations": self.cost_evaluations,
            "wall_s": self.wall_s,
        }  # fmt: skip


def _unpack(p: FloatArray) -> tuple[float, FloatArray]:
    z = p[1:]
    return math.exp(p[0]), np.exp(z - z.mean())


def identify(
    train: Sequence[str | Path],
    test: Sequence[str | Path] = (),
    model: str = "reference",
    horizon: int = 1,
    progress: Any = None,
) -> Identification:
    """Fit the factors of the module doc to the ``train`` recordings; report the prediction
    errors before and after on ``train`` and on the held-out ``test`` recordings.

    Raises :class:`~magrun.replay.ReplayError` when the recordings cannot be used together
    (different robots or coil channels) or have no ticks to predict from.
    """
    from scipy.optimize import least_squares

    from magrun.field.coils import CoilSystem
    from magrun.robot import load_robot

    if not train:
        raise ReplayError("identify needs at least one recording to fit to")
    coils = CoilSystem.load()
    fld = field_function(model, coils)
    sets: dict[str, list[Segments]] = {"train": [], "test": []}
    robots: set[tuple[str, str | None]] = set()
    for name, paths in (("train", train), ("test", test)):
        for path in paths:
            rec = read_ticks(path)
            if rec.currents.shape[1] != coils.n_channels:
                raise ReplayError(f"{rec.path}: not {coils.n_channels} current channels")
            protocol = trial_of(rec).protocol
            robots.add((protocol.robot, protocol.robots_file))
            sets[name].append(segments_of(rec, protocol, horizon))
    if len(robots) != 1:
        names = ", ".join(sorted(name for name, _ in robots))
        raise ReplayError(f"the recordings are of different robots: {names}")
    ((robot_name, robots_file),) = robots
    nominal = load_robot(robot_name, robots_file)
    half = nominal.length / 2
    t0 = time.perf_counter()
    evaluations = 0

    def predict(p: FloatArray, seg: Segments) -> tuple[FloatArray, FloatArray]:
        force, gains = _unpack(p)
        robot = nominal.scaled(moment=force)
        return rollout(seg, robot, fld, gains)

    targets = [seg.targets for seg in sets["train"]]

    def residuals(p: FloatArray) -> FloatArray:
        nonlocal evaluations
        evaluations += 1
        parts = []
        for seg, target in zip(sets["train"], targets, strict=True):
            positions, headings = predict(p, seg)
            parts.append(((positions - target[..., :2]) * 1e3).ravel())
            turn = (headings - target[..., 2] + np.pi) % (2 * np.pi) - np.pi
            parts.append((turn * half * 1e3).ravel())
        if progress is not None:
            progress(evaluations)
        return np.concatenate(parts)

    p0 = np.zeros(1 + coils.n_channels)
    fit = least_squares(residuals, p0, method="trf", x_scale=0.05, diff_step=1e-4, xtol=1e-10)
    force, gains = _unpack(fit.x)
    result = Identification(
        robot=robot_name, robots_file=robots_file, model=model, horizon=horizon,
        force_factor=force,
        coil_gains=dict(zip(coils.channel_names, gains.tolist(), strict=True)),
        train=[str(p) for p in train], test=[str(p) for p in test],
    )  # fmt: skip
    for name, segs in sets.items():
        if not segs:
            continue
        for label, p in (("before", p0), ("after", fit.x)):
            pos, ang = zip(*(errors_of(seg, *predict(p, seg)) for seg in segs), strict=True)
            n = np.array([len(seg.starts) for seg in segs], dtype=float)
            # RMS over every start of every recording, at each horizon
            rms_pos = np.sqrt(np.sum(np.square(pos) * n[:, None], axis=0) / n.sum())
            rms_ang = np.sqrt(np.sum(np.square(ang) * n[:, None], axis=0) / n.sum())
            result.errors[f"{name}_{label}"] = {
                "position_mm": rms_pos.round(6).tolist(), "heading_deg": rms_ang.round(6).tolist(),
            }  # fmt: skip
    result.cost_evaluations = evaluations
    result.wall_s = time.perf_counter() - t0
    return result


def robot_entry(result: Identification, name: str) -> dict[str, Any]:
    """A ``robots.yaml`` entry for the identified robot: the nominal one with the fitted
    moment (force factor); its drag and mass stay nominal (module doc)."""
    import yaml

    from magrun.robot import RobotsFile, robots_path

    source = Path(result.robots_file) if result.robots_file else robots_path()
    doc = RobotsFile.model_validate(yaml.safe_load(source.read_text(encoding="utf-8")))
    spec = doc.root[result.robot].model_dump()
    spec["description"] = (
        f"{spec['description']}; identified from {len(result.train)} recording(s) "
        f"(magrun identify, {result.model} model)"
    )
    spec["moment_am2"] = float(f"{spec['moment_am2'] * result.force_factor:.6g}")
    return {name: spec}
