"""``magrun identify``: the robot's and the coils' parameters fitted to recordings."""

from __future__ import annotations

import json
import re
from pathlib import Path

import click

from magrun.cli.common import InputError, InputFile

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: what the plant file's frame age rests on (BenchTiming.frame_age_from), in words
AGE_FROM = {
    "time stamps": "the measured poses' time stamps (each frame's time) against their arrival",
    "time shift": "the measured poses against the actual ones, shifted in time (the "
    "recordings carry no frame times)",
}


@click.command("identify")
@click.argument(
    "recordings", nargs=-1, required=True,
    type=InputFile(),
)  # fmt: skip
@click.option(
    "--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
    help="The robots file to write (YAML, robots.yaml's format): the identified robot.",
)  # fmt: skip
@click.option(
    "--test", "test", multiple=True,
    type=InputFile(),
    help="A held-out recording: errors before and after, not fitted to (repeatable).",
)  # fmt: skip
@click.option(
    "--model", type=click.Choice(["reference", "zernike", "lut"]), default="reference",
    show_default=True, help="The field model the fit predicts with.",
)  # fmt: skip
@click.option(
    "--horizon", type=click.IntRange(1, 50), default=5, show_default=True,
    help="Fit the predictions 1 … K ticks ahead.",
)  # fmt: skip
@click.option(
    "--gains", "gains_out", type=click.Path(dir_okay=False, path_type=Path),
    help="Also write the coils' gains as a calibration file (YAML) for a protocol's "
    "controller.coil_gains.",
)  # fmt: skip
@click.option(
    "--plant", "plant_out", type=click.Path(dir_okay=False, path_type=Path),
    help="Also estimate the bench's frame age, tracker noise, amplifier lag and floor "
    "friction and write "
    "them as a plant file (YAML) for a protocol's simulation.plant.",
)  # fmt: skip
@click.option("--name", help="The identified robot's name  [default: ROBOT_identified].")
@click.option("--json", "as_json", is_flag=True, help="Print the result as one JSON object.")
def identify_cmd(
    recordings: tuple[Path, ...],
    out: Path,
    test: tuple[Path, ...],
    model: str,
    horizon: int,
    gains_out: Path | None,
    plant_out: Path | None,
    name: str | None,
    as_json: bool,
) -> None:
    """Fit the robot's force factor (moment over drag) and the coils' relative gains
    to RECORDINGS (one robot, one coil system) by least squares on open-loop predictions.

    Prints the prediction error before and after, on the recordings fitted to and on the
    --test recordings. Writes --out, a robots file with the identified robot (the nominal
    robot with the fitted moment); a protocol uses it with `robots_file: OUT` and
    `robot: NAME`. The coil gains are printed and in the file's header; --gains writes them
    as a calibration file, which a protocol uses with `controller.coil_gains: FILE`.

    --plant also estimates the bench's timing and tracking from the same recordings: the
    frame age (the measured poses against the actual ones, shifted in time), the tracker's
    noise and outliers, the amplifiers' lag (the lag whose driven currents predict the
    robot best) and the floor's kinetic friction (how far short of those predictions the
    robot falls along its motion), and writes them as a plant file: `simulation.plant: FILE`
    simulates that bench.
    """
    import yaml

    from magrun.calibration import gains_file_text
    from magrun.recordings.reader import RecordingReadError
    from magrun.replay.common import ReplayError
    from magrun.replay.identify import LAG_GRID, bench_timing, identify, robot_entry

    if out.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--out {out}: the robots file must be .yaml")
    if gains_out is not None and gains_out.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--gains {gains_out}: the calibration file must be .yaml")
    if gains_out is not None and gains_out.resolve() == out.resolve():
        raise InputError(f"--gains {gains_out}: the same file as --out")
    if plant_out is not None and plant_out.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--plant {plant_out}: the plant file must be .yaml")
    if plant_out is not None and plant_out.resolve() in {
        out.resolve(),
        gains_out.resolve() if gains_out else None,
    }:
        raise InputError(f"--plant {plant_out}: the same file as --out or --gains")
    if name is not None and not _NAME.fullmatch(name):
        raise InputError(f"--name {name!r}: a letter, then letters, digits or '_'")
    shared = set(recordings) & set(test)
    if shared:
        raise InputError(f"{', '.join(map(str, shared))}: both fitted to and held out")

    def progress(evaluations: int) -> None:
        if evaluations % 20 == 0:
            click.echo(f"fitting: {evaluations} evaluations of the predictions", err=True)

    try:
        timing = None
        if plant_out is not None:  # first: the fit then predicts with the lag
            click.echo("estimating the bench's timing and tracking", err=True)
            timing = bench_timing(
                list(recordings), model,
                progress=lambda n: click.echo(
                    f"amplifier lag: {n}/{len(LAG_GRID)} tried", err=True
                ),
            )  # fmt: skip
        result = identify(
            list(recordings), list(test), model, horizon, progress,
            amplifier_tau=timing.amplifier_tau if timing is not None else None,
        )  # fmt: skip
    except (ReplayError, RecordingReadError) as exc:
        raise InputError(str(exc)) from exc
    robot_name = name or f"{result.robot}_identified"
    try:  # the robots file the recordings name: changed or gone since they were made
        entry = robot_entry(result, robot_name)
    except (ValueError, KeyError) as exc:
        raise InputError(f"the recordings' robots file: {exc}") from exc
    header = [
        f"# {robot_name}: identified by magrun identify ({model} model, horizon {horizon})",
        f"# force factor (moment / drag vs nominal) {result.force_factor:.4f}",
        "# coil gains (field per ampere vs the model, geometric mean 1): "
        + ", ".join(f"{k} {v:.4f}" for k, v in result.coil_gains.items()),
    ]
    for key, err in result.errors.items():
        header.append(
            f"# {key.replace('_', ' ')}: RMS position {err['position_mm'][-1]:.4f} mm, "
            f"heading {err['heading_deg'][-1]:.3f} deg at {horizon} tick(s)"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(header) + "\n" + yaml.safe_dump(entry, sort_keys=False))
    if gains_out is not None:
        gains_out.parent.mkdir(parents=True, exist_ok=True)
        gains_out.write_text(
            gains_file_text(
                result.coil_gains,
                model,
                [
                    f"coil gains identified by magrun identify ({model} model, horizon "
                    f"{horizon}) from: {', '.join(p.name for p in recordings)}",
                    f"used with the robot {robot_name} of {out.name} (the gains' common "
                    "scale is in its moment)",
                ],
            )
        )
    plant_terms = timing.plant_terms() if timing is not None else None
    if plant_out is not None and timing is not None and plant_terms is not None:
        lines = [
            f"# a bench identified by magrun identify from {timing.frames} measurements in "
            f"{len(recordings)} recording(s): {', '.join(p.name for p in recordings)}",
            f"# frame age: {AGE_FROM[timing.frame_age_from]}; tracker noise: what is left beyond "
            "the condition's noise; amplifier lag: RMS one-tick prediction error (mm)",
            "# per lag tried: "
            + ", ".join(f"{k * 1e3:g} ms {v:.4f}" for k, v in timing.lag_scan.items()),
            f"# friction: the one-tick predictions' shortfall along the motion, over "
            f"{timing.moving_ticks} moving ticks (a kinetic friction; stiction not identified)",
            "# flow and the field's errors are not identified here: add them by hand",
        ]
        body = {"description": f"identified from {len(recordings)} recording(s)", **plant_terms}
        plant_out.parent.mkdir(parents=True, exist_ok=True)
        plant_out.write_text("\n".join(lines) + "\n" + yaml.safe_dump(body, sort_keys=False))
    if as_json:
        extra = {
            "out": str(out), "name": robot_name, "gains": gains_out and str(gains_out),
            "plant": plant_terms, "plant_file": plant_out and str(plant_out),
            "frame_age_from": timing and timing.frame_age_from,
        }  # fmt: skip
        click.echo(json.dumps({**result.summary(), **extra}))
        return
    for line in header:
        click.echo(line[2:])
    click.echo(f"wrote {out} (robot {robot_name})")
    if gains_out is not None:
        click.echo(f"wrote {gains_out} (coil gains)")
    if plant_out is not None and plant_terms is not None and timing is not None:
        click.echo(
            "bench: "
            + ", ".join(f"{k} {v:g}" for k, v in plant_terms.items())
            + f"\nframe age: {AGE_FROM[timing.frame_age_from]}"
            + f"\nwrote {plant_out} (plant file)"
        )
