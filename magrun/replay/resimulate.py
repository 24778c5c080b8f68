"""Counterfactual re-simulation: a recorded simulated trial run again from its own protocol
and seed, as recorded or with another method or settings.

A simulated trial is a function of its protocol and its seed: the seed draws the plant (the
robot's parameters, the coils' gains), the camera's lighting and the feedback noise, and with
a declared latency (``controller.latency_ms`` a number or ``none``) nothing else enters, so
the same trial run again gives the same pose and current messages, byte for byte
(:func:`same_messages` checks it). With another ``method`` or ``--set`` overrides the new
controller meets the same plant draw, lighting and noise sequence: a paired comparison, one
trial against its counterfactual. With ``latency_ms: measured`` the plant is charged each
tick's measured compute time, so a rerun differs a little: :class:`Resimulation` says so.

The run is :func:`magrun.runner.execute_trial`, the one every ``magrun run`` trial goes
through; its files are moved to the requested name afterwards.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magrun.control import METHODS
from magrun.protocol import condition_slug
from magrun.recordings.reader import read_ticks
from magrun.replay.common import ReplayError, rms_errors, trial_of
from magrun.runner import execute_trial

#: the topics whose messages a faithful rerun reproduces exactly
COMPARED_TOPICS = (
    "/robot/pose/actual",
    "/robot/pose/tracked",
    "/robot/pose/measured",
    "/robot/pose/estimated",
    "/robot/pose/predicted",
    "/robot/pose/desired",
    "/coils/currents",
)


@dataclass
class Resimulation:
    """What :func:`resimulate` ran and found (RMS errors: actual against desired pose)."""

    source: Path
    mcap: Path
    rrd: Path
    method: str
    recorded_method: str
    overrides: tuple[str, ...]
    entry: dict[str, Any]  # the rerun's manifest entry (magrun.runner.execute_trial)
    recorded_rms: tuple[float, float]  # mm, degrees
    deterministic: bool  # the protocol declares its latency: a rerun is reproducible
    #: unchanged reruns only: whether every compared message equals the recording's
    identical: bool | None = None
    notes: list[str] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        e = self.entry
        return {
            "source": str(self.source),
            "mcap": str(self.mcap),
            "rrd": str(self.rrd),
            "recorded_method": self.recorded_method,
            "method": self.method,
            "overrides": list(self.overrides),
            "deterministic": self.deterministic,
            "identical_messages": self.identical,
            "recorded_rms_position_mm": self.recorded_rms[0],
            "recorded_rms_orientation_deg": self.recorded_rms[1],
            "rms_position_mm": e.get("rms_position_mm"),
            "rms_orientation_deg": e.get("rms_orientation_deg"),
            "status": e.get("status"),
            "failed_solves": e.get("failed_solves"),
            "critical_contact_s": e.get("critical_contact_s"),
            "warnings": e.get("warnings", []),
            "wall_s": e.get("wall_s"),
            "notes": self.notes,
        }


def resimulate(
    recording: str | Path,
    method: str | None = None,
    overrides: tuple[str, ...] = (),
    out: str | Path | None = None,
    view: str = "",
) -> Resimulation:
    """Run ``recording``'s simulated trial again (module doc) and record it to ``out``
    (default: beside the recording, ``<name>.resim.mcap``) with its ``.rrd`` beside it;
    ``view``, a Rerun viewer's gRPC URL, gets it live as well.

    Raises
    ------
    ReplayError
        A recording from hardware, an unknown method, a protocol the overrides break, an
        output that would overwrite the recording, or a rerun that failed.
    magrun.recordings.reader.RecordingReadError
        The file is not a readable magrun recording.
    """
    source = Path(recording)
    out = Path(out) if out is not None else source.with_name(f"{source.stem}.resim.mcap")
    if out.resolve() == source.resolve():
        raise ReplayError(f"--out {out}: a re-simulation is written beside the recording, "
                          "never over it")  # fmt: skip
    rec = read_ticks(source)
    meta = rec.trial
    if str(meta.get("rig", "sim")) != "sim":
        raise ReplayError(
            f"{source}: recorded on the {meta.get('rig')} rig; only a simulated trial can be "
            "re-simulated (its plant is the recorded seed's draw)"
        )
    trial = trial_of(rec, overrides)
    recorded_method = trial.method
    if method is not None and method != trial.method:
        if method not in METHODS:
            raise ReplayError(f"--method {method!r}: one of {', '.join(METHODS)}")
        trial = trial.model_copy(update={"method": method, "slug": condition_slug(method, {})})
    latency = trial.protocol.controller.latency
    result = Resimulation(
        source=source, mcap=out, rrd=out.with_suffix(".rrd"), method=trial.method,
        recorded_method=recorded_method, overrides=tuple(overrides), entry={},
        recorded_rms=rms_errors(rec.poses["actual"], rec.poses["desired"]),
        deterministic=latency != "measured",
    )  # fmt: skip
    if not result.deterministic:
        result.notes.append(
            "the protocol charges the measured compute time (latency_ms: measured): the "
            "rerun's plant saw this machine's timings, so it differs from the recording"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    # the trial is recorded in a hidden folder named after the output and moved out when
    # whole; one a killed re-simulation left is removed by the next into the same output
    # (the command line holds the output's lock meanwhile: magrun.atomic.OutputLock)
    tmp = out.parent / f".{out.name}.part"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        entry = execute_trial(trial, tmp, view=view)
        if entry.get("status") != "ok":
            raise ReplayError(
                f"{source}: the re-simulated trial ended {entry.get('status')}: "
                f"{entry.get('error') or 'no reason given'}"
            )
        base = tmp / trial.relpath
        shutil.move(base.with_suffix(".mcap"), out)
        shutil.move(base.with_suffix(".rrd"), result.rrd)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    result.entry = entry
    if result.method == recorded_method and not overrides:
        result.identical = same_messages(source, out)
        if not result.identical and result.deterministic:
            result.notes.append(
                "the rerun's messages differ from the recording's: was it recorded by "
                "another magrun version? (the recording's `software` metadata says which)"
            )
    return result


def same_messages(a: str | Path, b: str | Path, topics: tuple[str, ...] = COMPARED_TOPICS) -> bool:
    """Whether two recordings hold the same messages on ``topics``: topic, log time and the
    serialised bytes, in order."""
    from magrun.recordings.reader import raw_messages

    return raw_messages(a, topics) == raw_messages(b, topics)
