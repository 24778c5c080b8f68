"""System identification: the robot's and the coils' parameters fitted to recordings.

:func:`identify` adjusts a few factors on the nominal robot and coils so that the open-loop
predictions of :mod:`magrun.replay.model` (from each recorded actual pose, under the recorded
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

from magrun.recordings.reader import read_ticks
from magrun.replay.common import ReplayError, trial_of
from magrun.replay.model import (
    Segments,
    errors_of,
    field_function,
    held_substeps,
    recorded_system,
    rollout,
    segments_of,
    start_states,
)

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
    amplifier_tau: float | None = None,
) -> Identification:
    """Fit the factors of the module doc to the ``train`` recordings; report the prediction
    errors before and after on ``train`` and on the held-out ``test`` recordings.

    ``amplifier_tau`` (s; :func:`bench_timing` estimates it): predict with the currents the
    amplifiers drove (their slew ramps and this lag, :func:`driven_currents`) instead of the
    commanded ones held over each tick. On a bench whose amplifiers lag, the commanded
    currents make the robot look weaker than it is (a 15 ms lag halved the fitted force
    factor in a test), so give the lag where there is one.

    Raises :class:`~magrun.replay.common.ReplayError` when the recordings cannot be used together
    (different robots or coil channels) or have no ticks to predict from.
    """
    from scipy.optimize import least_squares

    from magrun.robot import load_robot

    if not train:
        raise ReplayError("identify needs at least one recording to fit to")
    recorded = {
        name: [(rec, trial_of(rec).protocol) for rec in map(read_ticks, paths)]
        for name, paths in (("train", train), ("test", test))
    }
    system = recorded_system([p for pairs in recorded.values() for _, p in pairs])
    coils = system.coils
    fld = field_function(model, system, compiled=True)
    sets: dict[str, list[Segments]] = {"train": [], "test": []}
    held: dict[int, HeldCurrents] = {}  # per segment, where the amplifiers' lag is given
    robots: set[tuple[str, str | None]] = set()
    for name, pairs in recorded.items():
        for rec, protocol in pairs:
            if rec.currents.shape[1] != coils.n_channels:
                raise ReplayError(f"{rec.path}: not {coils.n_channels} current channels")
            robots.add((protocol.robot, protocol.robots_file))
            seg = segments_of(rec, protocol, horizon)
            sets[name].append(seg)
            if amplifier_tau is not None:
                currents = driven_currents(
                    rec.currents, seg.length, seg.lag, coils.max_slew_rate, amplifier_tau
                )  # fmt: skip
                held[id(seg)] = held_currents(seg, currents)
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
        if id(seg) in held:
            return rollout_driven(seg, held[id(seg)], robot, fld, gains)
        return rollout(seg, robot, fld, gains, compiled=True)

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
    from magrun.robot import RobotsFile, robots_path
    from magrun.yamlio import load_yaml_model

    source = Path(result.robots_file) if result.robots_file else robots_path()
    doc = load_yaml_model(source, RobotsFile)  # read and checked when the trial ran
    spec = doc.root[result.robot].model_dump()
    spec["description"] = (
        f"{spec['description']}; identified from {len(result.train)} recording(s) "
        f"(magrun identify, {result.model} model)"
    )
    spec["moment_am2"] = float(f"{spec['moment_am2'] * result.force_factor:.6g}")
    return {name: spec}


# --------------------------------------------------------------------------------------------
# the bench's timing and tracking: what `magrun identify --plant` writes


@dataclass
class BenchTiming:
    """A bench's timing and tracking errors estimated from recordings (SI), with what each
    estimate rests on."""

    frame_age: float  # s: the measured poses show the robot this long before their tick
    frames: int  # measurements the frame age and tracker noise rest on
    tracker_position: float  # m, the measurements' own noise per axis (beyond the condition's)
    tracker_heading: float  # rad
    outlier_rate: float  # fraction of measurements further than 5 σ
    amplifier_tau: float  # s, the amplifiers' first-order lag
    lag_scan: dict[float, float] = field(default_factory=dict)  # τ (s) -> RMS error (mm)
    friction: float = 0.0  # m/s, the floor's kinetic friction as a drag speed
    moving_ticks: int = 0  # ticks the friction estimate rests on
    #: what the frame age rests on: "time stamps" (each measured pose's, its frame's time)
    #: or "time shift" (the measured poses against the actual ones; :func:`frame_age`)
    frame_age_from: str = "time shift"

    def plant_terms(self) -> dict[str, float]:
        """The plant file's settings (unit-suffixed, as ``simulation.plant: FILE`` reads)."""
        return {
            "frame_age_ms": round(float(self.frame_age) * 1e3, 2),
            "amplifier_tau_ms": round(self.amplifier_tau * 1e3, 2),
            "tracker_sigma_mm": round(self.tracker_position * 1e3, 4),
            "tracker_sigma_deg": round(math.degrees(self.tracker_heading), 3),
            "outlier_rate": round(self.outlier_rate, 4),
            "friction_mm_s": round(max(self.friction, 0.0) * 1e3, 3),
        }


#: frame ages scanned, s (every 0.5 ms up to 0.5 s), and amplifier lags, s
AGE_GRID = np.arange(0.0, 0.5, 5e-4)
LAG_GRID = (0.0, 0.0025, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03, 0.04, 0.06, 0.08)


def stamped(rec: Any) -> bool:
    """Whether a recording's measured poses carry their frames' times: some measurement
    stamped earlier than its tick (a recording whose frames were never late, or whose rig
    gave no frame times, has every stamp on its tick)."""
    ages = rec.measured_age
    return ages is not None and bool(np.any(np.nan_to_num(ages) > 0))


def frame_age(recordings: Sequence[Any]) -> tuple[float, int, FloatArray, FloatArray, str]:
    """How old the measured poses are when they arrive. Where every recording's measured
    poses carry their frames' times (:func:`stamped`), their mean age (arrival less the
    frame's time), the residuals taken at each frame's own time. Else the time shift between
    the measured poses and the actual ones: the age a that minimises
    Σ |measured(tₖ) − actual(tₖ − a)|² over every measurement (residuals beyond 5 × their
    median left out, as outliers), refined by a parabola through the best grid point and its
    neighbours. The actual poses are interpolated linearly between ticks. Returns the age
    (s), the number of measurements, their residuals (m, 3) at it, each measurement's own
    fluoroscopy noise σ (m,), m, from its recording's condition, and what the age rests on
    (``"time stamps"`` or ``"time shift"``)."""
    from_stamps = bool(recordings) and all(stamped(rec) for rec in recordings)

    def residuals(a: float) -> tuple[FloatArray, FloatArray]:
        parts, sigmas = [], []
        for rec in recordings:
            t = rec.t
            z = rec.poses["measured"]
            act = rec.poses["actual"]
            age = np.nan_to_num(rec.measured_age) if from_stamps else np.full(len(t), a)
            ok = np.all(np.isfinite(z), axis=1) & (t - age >= t[0])
            good = np.all(np.isfinite(act), axis=1)
            tt = t[ok] - age[ok]
            at = np.column_stack([np.interp(tt, t[good], act[good, i]) for i in range(3)])
            r = z[ok] - at
            r[:, 2] = (r[:, 2] + np.pi) % (2 * np.pi) - np.pi
            parts.append(r)
            noise = float(rec.trial.get("noise_sigma_mm", 0.0) or 0.0) * 1e-3
            sigmas.append(np.full(len(r), noise))
        if not parts:
            return np.empty((0, 3)), np.empty(0)
        return np.concatenate(parts), np.concatenate(sigmas)

    if from_stamps:
        r, sigma = residuals(0.0)
        ages = np.concatenate(
            [rec.measured_age[np.isfinite(rec.measured_age)] for rec in recordings]
        )
        if len(r) == 0:
            raise ReplayError("no measured poses with an actual pose to compare: no frame age")
        return float(np.mean(ages)), len(r), r, sigma, "time stamps"

    def cost(a: float) -> float:
        r, _ = residuals(a)
        d2 = np.sum(r[:, :2] ** 2, axis=1)
        if d2.size == 0:
            return math.inf
        keep = d2 <= 25 * np.median(d2)
        return float(np.mean(d2[keep]))

    costs = np.array([cost(float(a)) for a in AGE_GRID])
    i = int(np.argmin(costs))
    best = float(AGE_GRID[i])
    if 0 < i < len(AGE_GRID) - 1:
        c0, c1, c2 = costs[i - 1 : i + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best += 0.5 * (c0 - c2) / den * (AGE_GRID[1] - AGE_GRID[0])
    r, sigma = residuals(best)
    if len(r) == 0:
        raise ReplayError("no measured poses with an actual pose to compare: no frame age")
    return max(best, 0.0), len(r), r, sigma, "time shift"


def tracker_noise(residuals: FloatArray, condition: FloatArray) -> tuple[float, float, float]:
    """The tracker's own noise from the measurements' ``residuals`` (m, 3) against the
    actual poses and each one's fluoroscopy noise σ ``condition`` (m,), m: the position's
    σ per axis beyond the condition's (in quadrature, 0 where the residuals are no wider),
    the heading's σ (rad), and the share of outliers, measurements further than 5 σ of
    all the noise they carry, the condition's and the tracker's (residuals beyond 5 × their
    median square, and headings beyond 5 robust σ, left out of the σ's)."""
    d2 = np.sum(residuals[:, :2] ** 2, axis=1)
    keep = d2 <= 25 * np.median(d2)
    cond2 = float(np.mean(condition[keep] ** 2))
    per_axis = float(np.sqrt(max(np.mean(d2[keep]) / 2 - cond2, 0.0)))
    # the heading's outliers (a tracker that flips the robot end for end) left out alike
    th = np.abs(residuals[:, 2])
    heading = float(np.sqrt(np.mean(th[th <= 5 * 1.4826 * np.median(th)] ** 2)))
    total = np.sqrt(per_axis**2 + condition**2)  # each measurement's σ per axis
    outliers = float(np.mean(np.sqrt(d2) > 5 * np.maximum(total, 1e-9) * math.sqrt(2)))
    return per_axis, heading, outliers


def driven_currents(
    commanded: FloatArray, length: FloatArray, latency: FloatArray, slew: Any, tau: float,
    h: float = 1e-3,
) -> list[FloatArray]:  # fmt: skip
    """What the amplifiers drive, sub-step by sub-step of ``h``, for each tick: the
    commanded currents (n, C) apply ``latency`` (n,) after their tick's start (the previous
    ones until then) and the amplifiers follow them as a first-order lag ``tau`` within the
    slew limit (:func:`magrun.rigs.plant.amplifier_path`; ``tau`` 0: the slew ramp alone).
    Returns, per tick, the (m, C) currents at the middle of its m sub-steps (compiled:
    :func:`magrun.rigs.plant.driven_midpoints`)."""
    from magrun.rigs.kernel import driven_midpoints

    commanded = np.asarray(commanded, dtype=np.float64)
    counts = np.column_stack([np.round(latency / h), np.round((length - latency) / h)])
    counts = np.maximum(counts, 0).astype(np.int64)
    limit = np.ascontiguousarray(
        np.broadcast_to(np.asarray(slew, dtype=np.float64), commanded.shape[1:]) * h
    )
    decay = -math.expm1(-h / tau) if tau > 0 else 0.0
    flat = driven_midpoints(np.ascontiguousarray(commanded), counts, decay, limit, not tau > 0)
    ends = np.cumsum(counts.sum(axis=1))
    return np.split(flat, ends[:-1])


@dataclass(frozen=True)
class HeldCurrents:
    """What :func:`rollout_driven` holds over each part of each tick, from the driven
    currents (:func:`held_currents`): per horizon step, each start's sub-step (n,) s and,
    part by part, each start's mean driven current (n, C) A with the part's number of
    sub-steps. The same for every evaluation of a fit: computed once."""

    h: list[FloatArray]
    parts: list[list[tuple[FloatArray, int]]]


def held_currents(seg: Segments, driven: list[FloatArray], part: int = 5) -> HeldCurrents:
    """:class:`HeldCurrents` of ``seg``'s starts from :func:`driven_currents`' ``driven``:
    every ``part`` sub-steps of the shortest of the starts' ticks, the mean current of those
    sub-steps."""
    sizes = np.array([len(d) for d in driven])
    steps, held = [], []
    for j in range(seg.horizon):
        ks = seg.starts + j
        m = int(sizes[ks].min())
        steps.append(seg.length[ks] / sizes[ks])
        bounds = np.arange(0, m, part)
        means = None
        if m > 0 and np.all(sizes[ks] == m):  # every tick m sub-steps (a declared latency)
            stacked = np.stack([driven[k] for k in ks])  # (n, m, C): all parts' means at once
            counts = np.diff(np.append(bounds, m))[None, :, None]
            means = np.add.reduceat(stacked, bounds, axis=1) / counts
        parts = []
        for c, lo in enumerate(bounds.tolist()):
            hi = min(lo + part, m)
            if means is not None:
                parts.append((means[:, c], hi - lo))
            else:  # ticks of different lengths (a measured latency): the first m sub-steps
                parts.append((np.stack([driven[k][lo:hi].mean(axis=0) for k in ks]), hi - lo))
        held.append(parts)
    return HeldCurrents(steps, held)


def rollout_driven(
    seg: Segments, driven: list[FloatArray] | HeldCurrents, robot: Any, fld: Any,
    gains: FloatArray | None, part: int = 5,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """:func:`magrun.replay.model.rollout` with each tick's driven currents sub-step by
    sub-step (:func:`driven_currents`, or their :func:`held_currents` already): the field is
    read every ``part`` sub-steps at the mean current of those sub-steps."""
    held = driven if isinstance(driven, HeldCurrents) else held_currents(seg, driven, part)
    state = start_states(seg)
    positions = np.empty((seg.horizon, len(seg.starts), 2))
    headings = np.empty((seg.horizon, len(seg.starts)))
    for j in range(seg.horizon):
        for currents, count in held.parts[j]:
            if gains is not None:
                currents = currents * gains
            B, G = fld(np.column_stack(state[:2]), currents)
            state = held_substeps(state, B, G, robot, held.h[j], count)
        positions[j] = np.column_stack(state[:2])
        headings[j] = state[2]
    return positions, headings


def bench_timing(
    paths: Sequence[str | Path],
    model: str = "reference",
    gains: dict[str, float] | None = None,
    force_factor: float = 1.0,
    progress: Any = None,
) -> BenchTiming:
    """The frame age, the tracker's noise and the amplifiers' lag of the bench that made
    the recordings at ``paths``:

    - frame age and tracker noise: :func:`frame_age` (the measured poses' time stamps, else
      the measured poses against the actual ones); the noise is the residuals' spread less
      the fluoroscopy mimic's σ of each recording's condition (in quadrature), the outliers
      those beyond 5 σ;
    - amplifier lag: the τ of :data:`LAG_GRID` (refined by a parabola) whose driven currents
      (:func:`driven_currents`) give the least one-tick prediction error from the actual
      poses, with the fitted ``force_factor`` and ``gains``.

    On a simulated bench the actual pose is the plant's truth; on a real rig it is the
    camera's, so the age and noise are the fluoroscopy's relative to the camera.
    """
    recs = [read_ticks(p) for p in paths]
    if not recs:
        raise ReplayError("identify needs at least one recording")
    age, frames, r, sigma_cond, age_from = frame_age(recs)
    per_axis, heading, outliers = tracker_noise(r, sigma_cond)
    protocols = [trial_of(rec).protocol for rec in recs]
    system = recorded_system(protocols)
    coils = system.coils
    fld = field_function(model, system, compiled=True)
    robot = protocols[0].robot_params().scaled(moment=force_factor)
    g = None if gains is None else np.array([gains[c] for c in coils.channel_names])
    segs = [segments_of(rec, p, 1) for rec, p in zip(recs, protocols, strict=True)]
    scan: dict[float, float] = {}
    for tau in LAG_GRID:
        total, count = 0.0, 0
        for rec, seg in zip(recs, segs, strict=True):
            driven = driven_currents(
                rec.currents, seg.length, seg.lag, coils.max_slew_rate, tau
            )  # fmt: skip
            pos, _ang = errors_of(seg, *rollout_driven(seg, driven, robot, fld, g))
            n = len(seg.starts)
            total += float(pos[0]) ** 2 * n
            count += n
        scan[tau] = math.sqrt(total / count)
        if progress is not None:
            progress(len(scan))
    taus = np.array(list(scan))
    errs = np.array(list(scan.values()))
    i = int(np.argmin(errs))
    tau = float(taus[i])
    if 0 < i < len(taus) - 1:  # a parabola through the three points around the least
        x, y = taus[i - 1 : i + 2], errs[i - 1 : i + 2]
        a, b, _ = np.polyfit(x, y, 2)
        if a > 0:
            tau = float(np.clip(-b / (2 * a), x[0], x[2]))
    friction, moving = floor_friction(recs, segs, robot, fld, g, coils.max_slew_rate, tau)
    return BenchTiming(
        frame_age=age, frames=frames, tracker_position=per_axis, tracker_heading=heading,
        outlier_rate=outliers, amplifier_tau=tau, lag_scan=scan, friction=friction,
        moving_ticks=moving, frame_age_from=age_from,
    )  # fmt: skip


#: ticks slower than this (predicted, m/s) tell nothing of the kinetic friction
MOVING = 0.5e-3


def floor_friction(
    recs: Sequence[Any], segs: Sequence[Segments], robot: Any, fld: Any,
    gains: FloatArray | None, slew: Any, tau: float,
) -> tuple[float, int]:  # fmt: skip
    """The floor's kinetic friction f (m/s, as the drag speed it equals; the plant's
    ``friction_mm_s``) from the one-tick predictions without friction: on a moving
    drag-dominated body friction takes f d∥ against the velocity, which slows it by
    f (ûa² + ûb² d∥/d⊥) along its direction of motion û (body axes a, b). So each moving
    tick's shortfall along û, −r·û/Δt with r the actual end less the predicted one, is
    f times that factor: least squares over every tick predicted to move faster than
    :data:`MOVING`. Flow and the tracker's noise average out; a force factor off by k
    adds (k − 1) times the speed, so fit the robot on recordings where friction matters
    little, or take this as an upper bound. Returns f and the ticks it rests on."""
    num = den = 0.0
    count = 0
    for rec, seg in zip(recs, segs, strict=True):
        driven = driven_currents(rec.currents, seg.length, seg.lag, slew, tau)
        positions, _ = rollout_driven(seg, driven, robot, fld, gains)
        act = rec.poses["actual"]
        start, end = act[seg.starts], act[seg.starts + 1]
        dt = seg.length[seg.starts]
        step = positions[0] - start[:, :2]
        speed = np.hypot(step[:, 0], step[:, 1]) / dt
        finite = np.all(np.isfinite(end), axis=1) & np.all(np.isfinite(start), axis=1)
        ok = (speed > MOVING) & finite
        if not np.any(ok):
            continue
        u = step[ok] / (speed[ok] * dt[ok])[:, None]
        th = start[ok, 2]
        ua = np.cos(th) * u[:, 0] + np.sin(th) * u[:, 1]
        ub = -np.sin(th) * u[:, 0] + np.cos(th) * u[:, 1]
        factor = ua**2 + ub**2 * robot.drag_parallel / robot.drag_perpendicular
        shortfall = -np.sum((end[ok, :2] - positions[0][ok]) * u, axis=1) / dt[ok]
        num += float(np.sum(shortfall * factor))
        den += float(np.sum(factor**2))
        count += int(np.count_nonzero(ok))
    return (num / den if den > 0 else 0.0), count
