"""``magrun replay``: a recording's estimator run again with other settings."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import click

from magrun.cli.common import SET_HELP, InputError, InputFile, claimed_outputs
from magrun.cli.viewer import LiveView, live_view, live_view_options
from magrun.control import METHODS

_LABEL = re.compile(r"[A-Za-z0-9_.-]+")


@click.command("replay")
@click.argument("recording", type=InputFile())
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=SET_HELP)
@click.option(
    "--estimator", type=click.Choice(["kalman", "measurement", "hold"]),
    help="Replace the method's estimator: the Kalman filter (tuned by the protocol), the "
    "measurement else the prediction, or the last measurement held  [default: the method's].",
)  # fmt: skip
@click.option(
    "--label",
    help="Names the replayed streams: /replay/LABEL/robot/pose/{estimated,predicted}  "
    "[default: replay; with --resimulate: resim, naming only the output].",
)  # fmt: skip
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path),
    help="The output MCAP  [default: RECORDING's name + .LABEL.mcap, beside it].",
)  # fmt: skip
@click.option(
    "--overwrite", is_flag=True,
    help="Replace the output MCAP and its .rrd if they exist (never the recording itself).",
)  # fmt: skip
@click.option(
    "--resimulate", is_flag=True,
    help="Instead of the estimator: run the simulated trial again from its recorded protocol "
    "and seed (the same plant draw, lighting and noise), as recorded or with --method / "
    "--set; a whole new recording.",
)  # fmt: skip
@click.option(
    "--method", type=click.Choice(list(METHODS)),
    help="With --resimulate: the control method to run instead of the recorded one.",
)  # fmt: skip
@click.option(
    "--model", type=click.Choice(["zernike", "lut", "reference"]),
    help="Instead of the estimator: the open-loop prediction error of this field model with "
    "the robot's dynamics, from the recorded actual poses under the recorded currents.",
)  # fmt: skip
@click.option(
    "--horizon", type=click.IntRange(1, 200), default=10, show_default=True,
    help="With --model: predict 1 … K ticks ahead.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
@live_view_options
def replay(
    recording: Path,
    overrides: tuple[str, ...],
    estimator: str | None,
    label: str | None,
    out: Path | None,
    overwrite: bool,
    resimulate: bool,
    method: str | None,
    model: str | None,
    horizon: int,
    as_json: bool,
    open_view: bool,
    connect: str | None,
    web: bool,
    web_port: int,
) -> None:
    """Re-run a recorded trial's estimator offline, with changed settings.

    The estimator gets the recorded measurements and, as its prior at each tick, the
    controller's model's prediction from its own previous estimate under the currents the
    recording says were applied. With the recording's own settings it reproduces the
    recorded estimate. Writes OUT.mcap (the recording's channels plus the replayed estimate
    and prediction, and a `replay` metadata record) and OUT.rrd beside it, where the replay
    is drawn over the recording; prints the RMS estimation error (estimate against the
    actual pose) of the recorded and of the replayed estimator.

    With --model, replays a field model instead: from every tick's recorded actual pose it
    predicts 1 … --horizon ticks ahead under the recorded currents and prints the RMS
    position (mm) and heading (°) error at each horizon (the paper's prediction-accuracy
    test on any recording). Nothing is written.

    With --resimulate, runs a simulated trial again from its recorded protocol and seed and
    records it to OUT.mcap and OUT.rrd. Unchanged (and with a declared latency) it reproduces
    the recording's pose and current messages byte for byte, and says whether it did; with
    --method or --set the new controller meets the same plant, lighting and noise, a paired
    comparison. Prints both trials' RMS tracking errors.

    --view, --connect and --web show the output in a Rerun viewer as it is written (a
    re-simulation as it runs).
    """

    if recording.suffix.lower() != ".mcap":
        raise InputError(f"{recording}: replay reads a trial's .mcap recording")
    if method is not None and not resimulate:
        raise InputError("--method re-runs the trial's control: it needs --resimulate")
    if resimulate:
        if model is not None or estimator is not None:
            raise InputError(
                "--resimulate runs the whole trial: it takes no --model or --estimator"
            )
        with live_view(open_view, connect, web, web_port, f"{_again(recording)} --web") as lv:
            _resimulate(recording, method, overrides, label or "resim", out, overwrite, as_json, lv)
        return
    label = label or "replay"
    if model is not None:
        if estimator or out or open_view or connect or web or label != "replay":
            raise InputError(
                "--model writes nothing: it takes no --estimator, --label, --out, --view, "
                "--connect or --web"
            )
        _model_replay(recording, model, horizon, overrides, as_json)
        return
    if not _LABEL.fullmatch(label):
        raise InputError(f"--label {label!r}: use letters, digits, '_', '-' and '.' only")
    out = out or recording.with_name(f"{recording.stem}.{label}.mcap")
    if out.suffix.lower() != ".mcap":
        raise InputError(f"--out {out}: the output must be an .mcap file")
    # held while written: a second replay or recover into OUT is refused, not interleaved
    with claimed_outputs([out, out.with_suffix(".rrd")], [recording], overwrite):
        _estimator_replay(
            recording, overrides, estimator, label, out, open_view, connect, web, web_port,
            as_json,
        )  # fmt: skip


def _estimator_replay(
    recording: Path,
    overrides: tuple[str, ...],
    estimator: str | None,
    label: str,
    out: Path,
    open_view: bool,
    connect: str | None,
    web: bool,
    web_port: int,
    as_json: bool,
) -> None:
    from magrun.recordings.reader import RecordingReadError
    from magrun.replay.common import ReplayError
    from magrun.replay.estimator import replay_estimator, write_replay

    try:
        rec, result = replay_estimator(recording, overrides, estimator, label)
    except (ReplayError, RecordingReadError) as exc:
        raise InputError(str(exc)) from exc
    with live_view(open_view, connect, web, web_port, f"{_again(recording)} --web") as lv:
        try:  # the viewer gets the output as it is written
            rrd = write_replay(rec, result, out, view=lv.url if lv is not None else "")
        except ReplayError as exc:
            raise InputError(str(exc)) from exc
        _print_replay(recording, out, rrd, result, label, overrides, as_json)
        if lv is not None:
            lv.linger()


def _again(recording: Path) -> str:
    """The command, to suggest it with another option."""
    return f"magrun replay {recording}"


def _print_replay(
    recording: Path,
    out: Path,
    rrd: Path,
    result: Any,
    label: str,
    overrides: tuple[str, ...],
    as_json: bool,
) -> None:
    summary = {**result.summary(), "source": str(recording), "mcap": str(out), "rrd": str(rrd)}
    if as_json:
        click.echo(json.dumps(summary))
    else:
        e = result.errors
        click.echo(
            f"{recording.name}: {result.method}, {len(result.t)} ticks "
            f"({result.t[-1]:.1f} s) replayed in {result.wall_s:.2f} s"
        )
        click.echo(
            f"  RMS estimation error, recorded: {e['rms_estimation_error_recorded_mm']:.3f} mm, "
            f"{e['rms_estimation_error_recorded_deg']:.2f}°"
        )
        click.echo(
            f"  RMS estimation error, {label}: {e['rms_estimation_error_replayed_mm']:.3f} mm, "
            f"{e['rms_estimation_error_replayed_deg']:.2f}° "
            f"({result.estimator}{', ' + ', '.join(overrides) if overrides else ''})"
        )
        click.echo(f"wrote {out} and {rrd}")


def _model_replay(
    recording: Path, model: str, horizon: int, overrides: tuple[str, ...], as_json: bool
) -> None:
    from magrun.recordings.reader import RecordingReadError
    from magrun.replay.common import ReplayError
    from magrun.replay.model import prediction_errors

    try:
        result = prediction_errors(recording, model, horizon, overrides)
    except (ReplayError, RecordingReadError) as exc:
        raise InputError(str(exc)) from exc
    if as_json:
        click.echo(json.dumps({**result.summary(), "source": str(recording)}))
        return
    click.echo(
        f"{recording.name}: {model} model, {result.robot}, {result.starts} starts, "
        f"Δt {result.dt * 1e3:.1f} ms ({result.wall_s:.2f} s)"
    )
    click.echo("  ticks ahead   RMS position (mm)   RMS heading (°)")
    for j, (p, a) in enumerate(zip(result.position_mm, result.heading_deg, strict=True), 1):
        click.echo(f"  {j:>11}   {p:>17.4f}   {a:>15.3f}")


def _resimulate(
    recording: Path,
    method: str | None,
    overrides: tuple[str, ...],
    label: str,
    out: Path | None,
    overwrite: bool,
    as_json: bool,
    lv: LiveView | None,
) -> None:
    from magrun.recordings.reader import RecordingReadError
    from magrun.replay.common import ReplayError
    from magrun.replay.resimulate import resimulate

    if not _LABEL.fullmatch(label):
        raise InputError(f"--label {label!r}: use letters, digits, '_', '-' and '.' only")
    out = out or recording.with_name(f"{recording.stem}.{label}.mcap")
    if out.suffix.lower() != ".mcap":
        raise InputError(f"--out {out}: the output must be an .mcap file")
    with claimed_outputs([out, out.with_suffix(".rrd")], [recording], overwrite):
        if not as_json:
            click.echo(f"{recording.name}: re-simulating ...", err=True)
        try:
            result = resimulate(recording, method, overrides, out, view=lv.url if lv else "")
        except (ReplayError, RecordingReadError) as exc:
            raise InputError(str(exc)) from exc
    summary = result.summary()
    if as_json:
        click.echo(json.dumps(summary))
    else:
        changed = ", ".join(
            ([f"--method {result.method}"] if result.method != result.recorded_method else [])
            + [f"--set {o}" for o in result.overrides]
        )
        rms, deg = result.recorded_rms
        click.echo(f"  recorded ({result.recorded_method}): RMS {rms:.3f} mm, {deg:.2f}°")
        click.echo(
            f"  re-simulated ({changed or 'unchanged'}): RMS {summary['rms_position_mm']:.3f} mm, "
            f"{summary['rms_orientation_deg']:.2f}° in {summary['wall_s']:.1f} s"
        )
        if result.identical is not None:
            click.echo(
                "  pose and current messages: "
                + (
                    "identical to the recording's"
                    if result.identical
                    else "DIFFER from the recording's"
                )
            )
        for line in [*summary["warnings"], *result.notes]:
            click.echo(f"  note: {line}")
        click.echo(f"wrote {result.mcap} and {result.rrd}")
    if lv is not None:
        lv.linger()
