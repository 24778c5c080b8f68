"""A field and dynamics model's open-loop prediction error on a recording (model replay).

The paper's prediction-accuracy experiment (Section III-A) compares the pose the NMPC
predicted at the previous tick with the pose reached. :func:`prediction_errors` asks the same
of any model on any recording, further ahead: from the recorded actual pose at tick k (and
the velocity from the poses at k − 1 and k) it drives the planar dynamics
(:func:`magrun.robot.exponential_substep`) with the currents the recording says were applied
at ticks k … k + K − 1, and compares the pose after j ticks with the recorded one, for
j = 1 … K. Every tick of the recording is a start; the result is the RMS position (mm) and
heading (°) error at each horizon.

The field comes from one of the models (``--model``):

- ``zernike``: the shipped Zernike model (the proposed method's);
- ``lut``: the shipped lookup table (Baselines 2, 3 and 5);
- ``reference``: the reference maps on the plant's grid, the simulated rig's own field.

The robot is the protocol's, with its nominal parameters (a simulated rig draws each trial's
parameters and coil gains around them: that difference is part of the error, and what
``magrun identify`` estimates). Each tick's first ``latency`` (the protocol's declared
latency, or the recorded compute time where it was charged as measured) runs on the previous
tick's currents, as on the rig, and each tick lasts until the next recorded one. The
amplifiers' slew ramp and wall contacts are not modelled: in a phantom, ticks in contact
predict worse.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from magrun.field.system import System
from magrun.recordings.reader import read_ticks
from magrun.replay.common import ReplayError, trial_of
from magrun.robot import exponential_substep
from magrun.trial import RunError, coil_gains_of, system_of

if TYPE_CHECKING:
    from magrun.protocol import Protocol

FloatArray = NDArray[np.float64]
#: the field models a recording can be replayed with
MODELS = ("zernike", "lut", "reference")
#: integration sub-step, s (the tick is split into equal sub-steps no longer than this)
SUBSTEP = 2e-3


@dataclass
class PredictionErrors:
    """RMS open-loop prediction errors at horizons 1 … K (ticks)."""

    model: str
    robot: str
    dt: float  # s, the control period
    starts: int  # start ticks averaged over
    position_mm: FloatArray  # (K,) RMS position error after j ticks
    heading_deg: FloatArray  # (K,) RMS heading error after j ticks
    wall_s: float

    def summary(self) -> dict[str, Any]:
        """What ``magrun replay --model --json`` prints."""
        return {
            "model": self.model,
            "robot": self.robot,
            "dt_s": self.dt,
            "starts": self.starts,
            "horizon": len(self.position_mm),
            "rms_position_mm": [round(float(v), 6) for v in self.position_mm],
            "rms_heading_deg": [round(float(v), 6) for v in self.heading_deg],
            "wall_s": self.wall_s,
        }


def _wrap(a: Any) -> Any:
    return (a + np.pi) % (2 * np.pi) - np.pi


def field_function(model: str, system: System, compiled: bool = False) -> Any:
    """``f(positions (n, 2), currents (n, C)) -> (B, G)``, with ``B[k]`` and ``G[k][l]``
    arrays of n (T, T/m), for one of :data:`MODELS` of the coil system ``system``. With
    ``compiled``, the reference grid is read by the plant's compiled code
    (:func:`magrun.rigs.kernel.grid_rows`; equal to rounding): for a fit's many rollouts, not
    for one, where loading Numba (about a second) costs more than it saves."""
    if model in ("zernike", "lut"):
        zernike, lut = system.models
        planar = zernike if model == "zernike" else lut

        def analytic(positions: FloatArray, currents: FloatArray) -> tuple[Any, Any]:
            B, G = planar.field_and_gradient(positions, currents)
            return B.T, G.transpose(1, 2, 0)

        return analytic
    if model == "reference":
        grid = system.plant_maps
        table = np.ascontiguousarray(grid.table, dtype=np.float64)

        def gridded(positions: FloatArray, currents: FloatArray) -> tuple[Any, Any]:
            # the background's column (where the system has one) at an input of 1
            inputs = grid.inputs(currents)
            if compiled:  # the plant's own bilinear read
                from magrun.rigs.kernel import grid_rows

                rows = grid_rows(
                    np.ascontiguousarray(positions, dtype=np.float64),
                    np.ascontiguousarray(inputs), table, grid.x0, grid.y0, grid.step,
                )  # fmt: skip
            else:
                rows = np.einsum("nc,nck->nk", inputs, grid.units(positions))
            return rows[:, :2].T, rows[:, 2:].reshape(-1, 2, 2).transpose(1, 2, 0)

        return gridded
    raise ReplayError(f"unknown model {model!r}; one of {', '.join(MODELS)}")


@dataclass
class Segments:
    """What open-loop rollouts need from one recording: the actual poses (n, 3), the
    applied currents (n, C), each tick's latency and length (n,) s (a tick whose compute
    overran lasts longer than the period ``dt``), and the start ticks from which ``horizon``
    ticks of actual poses follow."""

    actual: FloatArray
    currents: FloatArray
    lag: FloatArray
    length: FloatArray
    dt: float
    starts: NDArray[np.int64]
    horizon: int

    @property
    def targets(self) -> FloatArray:
        """The recorded poses 1 … K ticks after each start, shape (K, n, 3)."""
        return np.stack([self.actual[self.starts + j + 1] for j in range(self.horizon)])


def segments_of(rec: Any, protocol: Any, horizon: int) -> Segments:
    """The :class:`Segments` of a recording (:class:`~magrun.recordings.reader.RecordedTrial`) made
    under ``protocol``; raises :class:`~magrun.replay.common.ReplayError` if it has none."""
    dt = 1.0 / protocol.controller.rate_hz
    latency = protocol.controller.latency
    lag = rec.compute_time if latency == "measured" else np.full(len(rec.t), float(latency))
    # to 0.1 ms: measured latencies differ at every tick, and the rollout integrates each
    # distinct length separately (the currents' switch moves by at most 0.05 ms)
    length = np.append(np.diff(rec.t), dt)  # each tick until the next one, s
    lag = np.round(np.clip(np.nan_to_num(lag, nan=0.0), 0.0, length), 4)
    actual = rec.poses["actual"]
    n = len(rec.t)
    ok = np.all(np.isfinite(actual), axis=1)
    starts = np.array(
        [k for k in range(1, n - horizon) if ok[k - 1 : k + horizon + 1].all()], dtype=np.int64
    )
    if len(starts) == 0:
        raise ReplayError(f"{rec.path}: too few ticks with an actual pose for --horizon {horizon}")
    return Segments(actual, rec.currents, lag, length, dt, starts, horizon)


def start_states(seg: Segments) -> tuple[Any, ...]:
    """Each start's state (x, y, θ, vx, vy, ω) as arrays over the starts: its actual pose,
    and the velocity of the tick before it (the pose difference over that tick)."""
    actual, starts = seg.actual, seg.starts
    d = actual[starts] - actual[starts - 1]
    d[:, 2] = _wrap(d[:, 2])
    v = d / seg.length[starts - 1][:, None]
    return (*actual[starts].T, *v.T)


def rollout(
    seg: Segments, robot: Any, field: Any, gains: FloatArray | None = None,
    compiled: bool = False,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """Open-loop predictions from every start: positions (K, n, 2) and headings (K, n) after
    1 … K ticks. ``gains`` scale each channel's field per ampere (default 1); ``compiled``:
    the sub-steps compiled (:func:`held_substeps`), for a fit's many rollouts."""
    currents, lag, starts = seg.currents, seg.lag, seg.starts
    if gains is not None:
        currents = currents * gains  # a coil's gain scales its field per ampere
    state = start_states(seg)
    positions = np.empty((seg.horizon, len(starts), 2))
    headings = np.empty((seg.horizon, len(starts)))
    for j in range(seg.horizon):
        k = starts + j
        # the tick's first lag runs on the previous currents, the rest on this tick's
        for held, duration in ((currents[k - 1], lag[k]), (currents[k], seg.length[k] - lag[k])):
            B, G = field(np.column_stack(state[:2]), held)
            m = max(1, math.ceil(float(np.max(duration)) / SUBSTEP))
            state = held_substeps(state, B, G, robot, duration / m, m, compiled)
        positions[j] = np.column_stack(state[:2])
        headings[j] = state[2]
    return positions, headings


def errors_of(seg: Segments, positions: FloatArray, headings: FloatArray) -> tuple[Any, Any]:
    """RMS position (mm) and heading (°) error at each horizon, shape (K,) each."""
    target = seg.targets
    dp = positions - target[..., :2]
    pos = np.sqrt(np.mean(np.sum(dp**2, axis=-1), axis=1)) * 1e3
    ang = np.degrees(np.sqrt(np.mean(_wrap(headings - target[..., 2]) ** 2, axis=1)))
    return pos, ang


def recorded_system(protocols: Sequence[Protocol]) -> System:
    """The coil system the recordings of ``protocols`` were made on (their ``system``: a
    folder, or the paper's rig) with its models; a :class:`~magrun.replay.common.ReplayError` where
    they name different systems or the folder's description is bad."""
    systems = sorted({p.system or "the paper's rig" for p in protocols})
    if len(systems) != 1:
        raise ReplayError(f"the recordings are of different coil systems: {', '.join(systems)}")
    try:
        return system_of(protocols[0])
    except RunError as exc:
        raise ReplayError(str(exc)) from exc


def prediction_errors(
    path: str | Path, model: str = "zernike", horizon: int = 1, overrides: tuple[str, ...] = ()
) -> PredictionErrors:
    """The open-loop prediction error of ``model`` on the recording at ``path`` (module doc)
    at horizons 1 … ``horizon`` ticks. ``overrides``: ``--set`` protocol settings (e.g. the
    robot, or ``controller.coil_gains``: the model with a coil calibration). Raises
    :class:`~magrun.replay.common.ReplayError` on what it cannot use."""
    if horizon < 1:
        raise ReplayError(f"--horizon must be at least 1, got {horizon}")
    rec = read_ticks(path)
    protocol = trial_of(rec, overrides).protocol
    system = recorded_system([protocol])
    coils = system.coils
    if rec.currents.shape[1] != coils.n_channels:
        raise ReplayError(
            f"{rec.path}: {rec.currents.shape[1]} current channels recorded, the coil system "
            f"has {coils.n_channels}"
        )
    try:
        gains = coil_gains_of(protocol, coils)  # a calibration given with --set
    except RunError as exc:
        raise ReplayError(str(exc)) from exc
    seg = segments_of(rec, protocol, horizon)
    t0 = time.perf_counter()
    fld = field_function(model, system)
    positions, headings = rollout(seg, protocol.robot_params(), fld, gains)
    pos, ang = errors_of(seg, positions, headings)
    return PredictionErrors(
        model=model, robot=protocol.robot, dt=seg.dt, starts=len(seg.starts), position_mm=pos,
        heading_deg=ang, wall_s=time.perf_counter() - t0,
    )  # fmt: skip


def held_substeps(
    state: tuple[Any, ...], B: Any, G: Any, robot: Any, h: FloatArray, count: int,
    compiled: bool = True,
) -> tuple[Any, ...]:  # fmt: skip
    """:func:`substep_each` ``count`` times with (B, G) held; ``compiled``
    (:func:`magrun.rigs.kernel.held_substeps`, the same sub-step to rounding, tested against
    it) where a fit runs the rollouts many times: NumPy's per-call overhead on arrays of a few
    hundred starts is then most of the time."""
    if count <= 0:
        return state
    if not compiled:
        for _ in range(count):
            state = substep_each(state, B, G, robot, h)
        return state
    from magrun.rigs.kernel import ROBOT_FIELDS
    from magrun.rigs.kernel import held_substeps as loop

    n = len(state[0])
    vector = np.array([getattr(robot, f) for f in ROBOT_FIELDS], dtype=np.float64)
    out = np.array(state, dtype=np.float64).reshape(6, n)
    loop(
        out,
        np.ascontiguousarray(np.broadcast_to(B, (2, n)), dtype=np.float64),
        np.ascontiguousarray(np.broadcast_to(G, (2, 2, n)), dtype=np.float64),
        vector,
        np.ascontiguousarray(np.broadcast_to(h, (n,)), dtype=np.float64),
        count,
    )
    return tuple(out)


def substep_each(
    state: tuple[Any, ...], B: Any, G: Any, robot: Any, h: FloatArray
) -> tuple[Any, ...]:
    """One sub-step of length ``h`` (an array: each start's own) for every start at once; a
    start with ``h`` ≤ 0 keeps its state."""
    if np.all(h == h.flat[0]):
        h0 = float(h.flat[0])
        return state if h0 <= 0 else tuple(exponential_substep(state, B, G, robot, h0))
    # different lengths (ticks of measured length or latency): each start its own constants
    moved = exponential_substep(state, B, G, robot, np.maximum(h, 0.0))
    return tuple(np.where(h > 0, new, old) for new, old in zip(moved, state, strict=True))
