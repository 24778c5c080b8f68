"""``magrun track``: the paper's S-trajectory closed loop, one trial per method, no recording.

The command line's condition becomes an in-memory protocol whose trials are assembled as
``magrun run`` assembles them (:mod:`magrun.trial`): the same condition gets the same rig,
controller tuning, feedback and safety layer.
"""

from __future__ import annotations

import json
import math
import time
from typing import Any

import click
import numpy as np

from magrun.cli.common import InputError, Latency, Progress
from magrun.protocol import DEFAULT_LATENCY_MS

#: the command's control rate, Hz
RATE_HZ = 25.0

#: the command-line options behind a protocol's fields, for error messages
OPTION_OF = {
    "robot": "--robot",
    "methods": "METHODS",
    "trajectory": "--speed-mm-s",
    "conditions": "--rate-hz / --sigma-mm",
    "duration_s": "--duration",
}


def track_protocol(
    methods: list[str],
    robot: str,
    duration: float | None,
    speed_mm_s: float,
    rate_hz: float,
    sigma_mm: float,
    camera: bool,
    latency_ms: float | str = DEFAULT_LATENCY_MS,
) -> Any:
    """The condition ``magrun track`` runs, as a protocol (an InputError when it is not one)."""
    from pydantic import ValidationError

    from magrun.protocol import Protocol

    try:
        return Protocol.model_validate(
            {
                "name": "track",
                "robot": robot,
                "trajectory": {"kind": "s_curve", "speed_mm_s": speed_mm_s},
                "methods": methods,
                "controller": {"rate_hz": RATE_HZ, "latency_ms": latency_ms},
                "conditions": {
                    "tracking_rate_hz": None if math.isinf(rate_hz) else rate_hz,
                    "noise_sigma_mm": sigma_mm,
                },
                "feedback": {"camera": camera},
                "duration_s": duration,
                "trials": 1,
            }
        )
    except ValidationError as exc:
        problems = [
            f"{OPTION_OF.get(str(e['loc'][0]), e['loc'][0]) if e['loc'] else 'track'}: "
            f"{e['msg'].removeprefix('Value error, ')}"
            for e in exc.errors()
        ]
        raise InputError("\n".join(problems)) from exc


@click.command("track")
@click.argument("methods", nargs=-1)
@click.option("--robot", default="magnet", show_default=True, help="Robot in robots.yaml.")
@click.option(
    "--seed", type=click.IntRange(min=0), default=0, show_default=True,
    help="Seeds the plant's parameter draw and the feedback noise.",
)  # fmt: skip
@click.option(
    "--duration", type=click.FloatRange(min=0, min_open=True), default=None,
    help="Seconds to run [default: the trajectory + 1 s].",
)  # fmt: skip
@click.option(
    "--speed-mm-s", type=click.FloatRange(min=0, min_open=True), default=3.0, show_default=True,
    help="Speed along the S, mm/s.",
)  # fmt: skip
@click.option(
    "--rate-hz",
    type=click.FloatRange(min=0, min_open=True),
    default=math.inf,
    help="Fluoroscopy rate of the feedback, Hz [default: every 25 Hz control tick].",
)
@click.option(
    "--sigma-mm", type=click.FloatRange(min=0), default=0.0, show_default=True,
    help="Feedback noise sigma on x and on y, mm.",
)  # fmt: skip
@click.option(
    "--camera",
    is_flag=True,
    help="Render camera frames and track them with the UNet (default: the exact pose).",
)
@click.option(
    "--latency-ms", type=Latency(), default=DEFAULT_LATENCY_MS, show_default=True,
    help="The simulated rig's latency per tick, ms (a protocol's controller.latency_ms):"
    " 'measured' charges the wall-clock compute instead (results then depend on the machine),"
    " 'none' is 0.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the results as one JSON object.")
def track(
    methods: tuple[str, ...],
    robot: str,
    seed: int,
    duration: float | None,
    speed_mm_s: float,
    rate_hz: float,
    sigma_mm: float,
    camera: bool,
    latency_ms: float | str,
    as_json: bool,
) -> None:
    """Track the paper's 43 x 43 mm S-trajectory on the simulated rig.

    Runs each METHOD (default: all six) closed loop at 25 Hz and prints RMS tracking and
    one-step prediction errors and solve times. The controller's feedback is the exact pose
    (or, with --camera, the UNet's pose on rendered frames), degraded to --rate-hz with
    N(0, --sigma-mm²) noise as the paper mimics fluoroscopy. Each trial is assembled as
    `magrun run` assembles a protocol's trial under the same condition.
    """
    from magrun.control import METHODS
    from magrun.trial import assemble, single_trial

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(
            f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}"
        )
    chosen = list(dict.fromkeys(methods)) or list(METHODS)
    protocol = track_protocol(
        chosen, robot, duration, speed_mm_s, rate_hz, sigma_mm, camera, latency_ms
    )
    results = []
    for method in chosen:
        parts = assemble(single_trial(protocol, method, seed))
        t0 = time.perf_counter()
        log = parts.run(progress=Progress(f"{method:>9}", not as_json))
        wall = time.perf_counter() - t0
        solve = log.solve_times
        row = {
            "method": method,
            "ticks": len(log.t),
            "rms_position_mm": log.rms_position_mm,
            "rms_orientation_deg": log.rms_orientation_deg,
            "rms_prediction_position_mm": log.rms_prediction_position_mm,
            "rms_prediction_orientation_deg": log.rms_prediction_orientation_deg,
            "median_solve_ms": float(np.median(solve) * 1e3),
            "p90_solve_ms": float(np.percentile(solve, 90) * 1e3),
            "failed_solves": sum(not s.success for s in log.status),
            "max_abs_current_a": float(np.abs(log.currents).max()),
            "measurements": int(np.isfinite(log.measured[:, 0]).sum()),
            # camera frames taken in which the tracker did not find the robot
            "tracking_lost": log.tracking_lost,
            "safety_stop": log.stop_reason,
            "wall_s": wall,
        }
        # NaN (no prediction: the PID) is written as JSON null, never as a bare NaN
        row = {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}
        results.append(row)
        if not as_json:
            click.echo(_line(row))
    if as_json:
        doc = {
            "robot": robot,
            "seed": seed,
            "speed_mm_s": speed_mm_s,
            "latency_ms": latency_ms,
            "feedback": {
                "source": "unet camera tracking" if camera else "exact pose",
                "rate_hz": None if math.isinf(rate_hz) else rate_hz,
                "sigma_mm": sigma_mm,
            },
        }
        click.echo(json.dumps({**doc, "results": results}))


def _line(row: dict[str, Any]) -> str:
    pred = (
        f"{row['rms_prediction_position_mm']:.3f} mm {row['rms_prediction_orientation_deg']:.2f}°"
        if row["rms_prediction_position_mm"] is not None
        else "none"
    )
    stop = f"  SAFETY STOP: {row['safety_stop']}" if row["safety_stop"] else ""
    return (
        f"{row['method']:>9}: RMS {row['rms_position_mm']:.3f} mm"
        f" {row['rms_orientation_deg']:.2f}°  prediction {pred}"
        f"  solve median {row['median_solve_ms']:.1f} ms"
        f"  failed {row['failed_solves']}/{row['ticks']}{stop}"
    )
