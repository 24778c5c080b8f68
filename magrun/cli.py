"""The ``magrun`` command line. One small function per verb; the work lives in the library.

    magrun field reference --out recordings/field/reference_maps.npz
    magrun field fit --out recordings/field --json
    magrun field import-comsol --small s.txt --medium m.txt --large l.txt --out maps.npz
    magrun track proposed baseline2 --json         # S-trajectory, perfect feedback, simulated rig
    magrun track proposed --rate-hz 3 --sigma-mm 2 --camera   # UNet tracking + fluoroscopy mimic
    magrun tracker train --out recordings/tracker/unet.npz     # train the keypoint UNet (CPU)
    magrun tracker eval --json                     # held-out tracker accuracy and speed
    magrun tracker run clip.mp4 --px-per-mm 4.2 --out poses.csv    # track a lab's footage
    magrun bench nmpc --json                       # NMPC solve times, Zernike vs lookup table
    magrun validate protocols/*.yaml               # check protocols before running anything
    magrun run protocols/rate.yaml --jobs 2        # run, record MCAP + Rerun, manifest
    magrun view recordings/rate/proposed_rate-3hz/trial-0.rrd      # open in the Rerun viewer
    magrun figures recordings --out figures        # paper figures, results.csv, report.md

Bad input (a malformed file, an unknown option value) exits with status 2 and one message
naming the file (and line where there is one); it never prints a traceback.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from magrun import __version__

INPUT_ERROR = 2


class InputError(click.ClickException):
    """User input we cannot use: exit status 2, message only."""

    exit_code = INPUT_ERROR


def _load_coils(path: Path | None) -> Any:
    from magrun.field.coils import CoilFileError, CoilSystem

    try:
        return CoilSystem.load(path)
    except CoilFileError as exc:
        raise InputError(str(exc)) from exc


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="magrun")
def cli() -> None:
    """Run, record and analyse magnetic-robot control experiments."""


@cli.group()
def field() -> None:
    """Coil field models: reference maps, Zernike fit, COMSOL import."""


COILS_OPTION = click.option(
    "--coils",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Coil-system YAML (default: the paper's rig shipped with magrun).",
)


@field.command("reference")
@COILS_OPTION
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("recordings/field/reference_maps.npz"),
    show_default=True,
    help="Output .npz file.",
)
@click.option(
    "--pitch-mm",
    type=click.FloatRange(min=0.05, max=10.0),
    default=1.0,
    show_default=True,
    help="Grid spacing in mm.",
)
@click.option(
    "--sheets",
    type=click.IntRange(min=1, max=200),
    default=12,
    show_default=True,
    help="Radial current sheets per winding.",
)
def field_reference(coils: Path | None, out: Path, pitch_mm: float, sheets: int) -> None:
    """Compute unit-current reference maps of every coil type with magpylib.

    To refresh the maps shipped with magrun, run from a source checkout with
    --out magrun/field/data/reference_maps.npz (see README, "Data files").
    """
    from magrun.field.reference import compute_reference_maps

    system = _load_coils(coils)
    start = time.perf_counter()
    maps = compute_reference_maps(system, pitch=pitch_mm * 1e-3, sheets=sheets)
    maps.save(out)
    grid = next(iter(maps.maps.values()))
    click.echo(
        f"wrote {out}: {len(maps.maps)} coil types on a {grid.x.size} x {grid.y.size} grid "
        f"({pitch_mm:g} mm) in {time.perf_counter() - start:.1f} s"
    )


@field.command("fit")
@COILS_OPTION
@click.option(
    "--reference",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Reference maps .npz (default: the maps shipped with magrun).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("recordings/field"),
    show_default=True,
    help="Folder for zernike_model.json, zernike_fit.json and zernike_figure.npz.",
)
@click.option(
    "--max-order",
    type=click.IntRange(min=1, max=20),
    default=10,
    show_default=True,
    help="Highest radial degree scored.",
)
@click.option(
    "--r2-saturation",
    type=click.FloatRange(min=0.0, max=1.0),
    default=0.01,
    show_default=True,
    help="Keep the smallest order after which one more order gains less R² than this.",
)
@click.option(
    "--order",
    "orders",
    multiple=True,
    metavar="TYPE=N",
    help="Fix the order of a coil type instead of selecting it (repeatable), e.g. small=4.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the fit report as one JSON object.")
def field_fit(
    coils: Path | None,
    reference: Path | None,
    out: Path,
    max_order: int,
    r2_saturation: float,
    orders: tuple[str, ...],
    as_json: bool,
) -> None:
    """Fit the Zernike model to reference maps and report MAE and R² per coil type and order."""
    from magrun.field.fitting import fit_reference, parse_orders
    from magrun.field.reference import ReferenceMaps

    system = _load_coils(coils)
    try:
        fixed = parse_orders(list(orders))
        maps = ReferenceMaps.load(reference)
        result = fit_reference(
            system, maps, max_order=max_order, r2_saturation=r2_saturation, fixed_orders=fixed
        )
    except (ValueError, KeyError) as exc:
        raise InputError(str(exc).strip("'\"")) from exc
    paths = result.save(out)
    if as_json:
        click.echo(json.dumps({**result.report, "files": {k: str(v) for k, v in paths.items()}}))
        return
    for coil_type, rep in result.report["coil_types"].items():
        click.echo(f"{coil_type}: selected order {rep['selected_order']} ({rep['selected_by']})")
        click.echo("  order  terms   MAE [mT/A]       R²   max err [mT/A]")
        for s in rep["orders"]:
            mark = "*" if s["order"] == rep["selected_order"] else " "
            click.echo(
                f" {mark}{s['order']:>5} {s['n_terms']:>6} {s['mae_mT']:>12.4f} "
                f"{s['r2']:>8.5f} {s['max_error_mT']:>16.4f}"
            )
        below = rep["fraction_below_4mT"]
        click.echo(
            "  error below 4 mT on "
            + ", ".join(
                f"{v:.1%} of the workspace {k.replace('at_', 'at ')}" for k, v in below.items()
            )
        )
    click.echo("wrote " + ", ".join(str(p) for p in paths.values()))


@field.command("import-comsol")
@COILS_OPTION
@click.option(
    "--small",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Small-coil export.",
)
@click.option(
    "--medium",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Medium-coil export.",
)
@click.option(
    "--large",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Large-coil export.",
)
@click.option(
    "--current-a",
    type=float,
    default=1.0,
    show_default=True,
    help="Coil current (A) the exports were computed at.",
)
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    required=True,
    help="Output reference-map .npz, usable with 'magrun field fit --reference'.",
)
def field_import_comsol(
    coils: Path | None,
    small: Path | None,
    medium: Path | None,
    large: Path | None,
    current_a: float,
    out: Path,
) -> None:
    """Build reference maps from COMSOL plain-text exports, one per coil type."""
    from magrun.field.comsol import import_comsol

    system = _load_coils(coils)
    files = {
        k: v for k, v in (("small", small), ("medium", medium), ("large", large)) if v is not None
    }
    missing = sorted({ch.coil_type for ch in system.channels} - set(files))
    if missing:
        raise InputError(f"the driven coil types need exports too: --{' --'.join(missing)}")
    try:
        maps = import_comsol(files, current_a, coils_meta=system.spec.model_dump(mode="json"))
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    maps.save(out)
    click.echo(
        f"wrote {out}: " + ", ".join(f"{k} {m.x.size} x {m.y.size}" for k, m in maps.maps.items())
    )


class _Progress:
    """Per-tick progress on stderr while a trial runs (nothing with --json or off a terminal)."""

    def __init__(self, label: str, enabled: bool) -> None:
        self.label, self.enabled = label, enabled and sys.stderr.isatty()
        self._bar: Any = None

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        if self._bar is None:
            self._bar = click.progressbar(
                length=total, label=self.label, file=sys.stderr, show_eta=True
            )
            self._bar.__enter__()
        self._bar.update(1)
        if done == total:
            self._bar.__exit__(None, None, None)


@cli.command("track")
@click.argument("methods", nargs=-1)
@click.option("--robot", default="magnet", show_default=True, help="Robot in robots.yaml.")
@click.option("--seed", default=0, show_default=True, help="Seed of the plant's parameter draw.")
@click.option(
    "--duration", type=float, default=None, help="Seconds to run [default: the trajectory + 1 s]."
)
@click.option("--speed-mm-s", default=3.0, show_default=True, help="Speed along the S, mm/s.")
@click.option(
    "--rate-hz",
    type=float,
    default=math.inf,
    help="Fluoroscopy rate of the feedback, Hz [default: every 25 Hz camera frame].",
)
@click.option(
    "--sigma-mm", default=0.0, show_default=True, help="Feedback noise sigma on x and on y, mm."
)
@click.option(
    "--camera",
    is_flag=True,
    help="Render camera frames and track them with the UNet (default: the exact pose).",
)
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
    as_json: bool,
) -> None:
    """Track the paper's 43 x 43 mm S-trajectory on the simulated rig.

    Runs each METHOD (default: all six) closed loop at 25 Hz and prints RMS tracking and
    one-step prediction errors and solve times. The controller's feedback is the exact pose
    (or, with --camera, the UNet's pose on rendered frames), degraded to --rate-hz with
    N(0, --sigma-mm²) noise as the paper mimics fluoroscopy.
    """
    from magrun.control import METHODS
    from magrun.control.methods import make_controller
    from magrun.loop import run_trial
    from magrun.protocol import ControllerSettings
    from magrun.rigs.sim import SimRig
    from magrun.scene import s_trajectory
    from magrun.tracking.camera import CameraConfig
    from magrun.tracking.fluoroscopy import FluoroscopyMimic
    from magrun.trial import control_config

    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise InputError(
            f"unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}"
        )
    if speed_mm_s <= 0:
        raise InputError("--speed-mm-s must be positive")
    if not rate_hz > 0 or sigma_mm < 0:
        raise InputError("--rate-hz must be positive and --sigma-mm non-negative")
    reference = s_trajectory(speed=speed_mm_s * 1e-3)
    results = []
    for method in methods or METHODS:
        try:
            # the tuning `magrun run` gives this condition (a protocol's default controller
            # settings, at this command's 25 Hz)
            cfg = control_config(
                ControllerSettings(rate_hz=25.0), robot, {"noise_sigma_mm": sigma_mm}
            )
            controller = make_controller(method, robot, cfg)
            rig = SimRig.default(robot=robot, seed=seed, camera=CameraConfig() if camera else None)
        except KeyError as exc:
            raise InputError(str(exc).strip("'\"")) from exc
        tracker = _default_tracker(rig.camera, rig.nominal_robot) if rig.camera else None
        mimic = FluoroscopyMimic(rate_hz, sigma_mm * 1e-3, seed=seed)
        t0 = time.perf_counter()
        progress = _Progress(f"{method:>9}", not as_json)
        log = run_trial(
            controller, rig, reference, feedback=mimic, duration=duration, progress=progress,
            tracker=tracker,
        )  # fmt: skip
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
            "tracking_lost": int(np.isnan(log.tracked[:, 0]).sum()),
            "wall_s": wall,
        }
        # NaN (no prediction: the PID) is written as JSON null, never as a bare NaN
        row = {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}
        results.append(row)
        if not as_json:
            pred = (
                f"{row['rms_prediction_position_mm']:.3f} mm"
                f" {row['rms_prediction_orientation_deg']:.2f}°"
                if row["rms_prediction_position_mm"] is not None
                else "none"
            )
            click.echo(
                f"{method:>9}: RMS {row['rms_position_mm']:.3f} mm"
                f" {row['rms_orientation_deg']:.2f}°  prediction {pred}"
                f"  solve median {row['median_solve_ms']:.1f} ms"
                f"  failed {row['failed_solves']}/{row['ticks']}"
            )
    if as_json:
        doc = {
            "robot": robot,
            "seed": seed,
            "speed_mm_s": speed_mm_s,
            "feedback": {
                "source": "unet camera tracking" if camera else "exact pose",
                "rate_hz": None if math.isinf(rate_hz) else rate_hz,
                "sigma_mm": sigma_mm,
            },
        }
        click.echo(json.dumps({**doc, "results": results}))


def _default_tracker(camera: Any, robot: Any, weights: Path | None = None) -> Any:
    from magrun.tracking.tracker import Tracker

    try:
        return Tracker.default(camera, robot, weights)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot load tracker weights: {exc}") from exc


@cli.group()
def tracker() -> None:
    """The UNet keypoint tracker: train it, evaluate it."""


def _weights_option(help_text: str) -> Any:
    return click.option(
        "--weights",
        type=click.Path(exists=True, dir_okay=False, path_type=Path),
        default=None,
        help=help_text,
    )


@tracker.command("train")
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("recordings/tracker/unet.npz"),
    show_default=True,
    help="Where to write the weights (.npz).",
)
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Optimiser steps.")
@click.option("--batch", type=click.IntRange(min=2), default=None, help="Crops per step.")
@click.option("--seed", default=0, show_default=True, help="Seeds the data and the weights.")
@click.option(
    "--init",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Start from these weights (fine-tuning) instead of random ones.",
)
@click.option(
    "--images",
    type=click.Path(exists=True, path_type=Path),
    default=None,
    help="Real frames for fine-tuning: an image folder or a video file.",
)
@click.option(
    "--labels",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    default=None,
    help="Keypoint annotations of --images (CSV; see the README).",
)
@click.option("--px-per-mm", type=float, default=None, help="Scale of --images, px per mm.")
def tracker_train(
    out: Path,
    steps: int | None,
    batch: int | None,
    seed: int,
    init: Path | None,
    images: Path | None,
    labels: Path | None,
    px_per_mm: float | None,
) -> None:
    """Train the tracker on rendered crops (and optionally real annotated frames), on the CPU.

    The defaults reproduce the shipped weights (magrun/tracking/data/unet.npz) in about ten
    minutes on two cores. With --images, --labels and --px-per-mm, half of every batch is
    crops of the lab's own frames, rescaled to the tracker's 2.5 px/mm.
    """
    from dataclasses import replace

    from magrun.robot import load_robots
    from magrun.tracking.camera import CameraConfig
    from magrun.tracking.dataset import real_samples
    from magrun.tracking.train import TrainConfig, train
    from magrun.tracking.unet import load_weights, save_weights

    if (images is None) != (labels is None) or (images is not None and px_per_mm is None):
        raise InputError("fine-tuning needs --images, --labels and --px-per-mm together")
    cfg = TrainConfig(seed=seed)
    cfg = replace(cfg, steps=steps or cfg.steps, batch=batch or cfg.batch)
    camera = CameraConfig()
    real: list[Any] = []
    if images is not None and labels is not None and px_per_mm is not None:
        if not px_per_mm > 0:
            raise InputError("--px-per-mm must be positive")
        try:
            real = real_samples(images, labels, px_per_mm, camera.px_per_mm)
        except (ValueError, OSError) as exc:
            raise InputError(str(exc)) from exc
    model = None
    if init is not None:
        try:
            model, _ = load_weights(init)
        except (ValueError, OSError, KeyError) as exc:
            raise InputError(f"{init}: cannot load weights: {exc}") from exc
    t0 = time.perf_counter()
    bar: Any = click.progressbar(
        length=cfg.steps, label="training", file=sys.stderr, show_eta=True,
        item_show_func=lambda loss: f"loss {loss:.2e}" if loss is not None else "",
    )  # fmt: skip
    with bar:

        def progress(step: int, total: int, loss: float) -> None:
            bar.update(1, loss)

        net = train(list(load_robots().values()), cfg, camera, model, real, progress)
    meta = {
        "steps": cfg.steps,
        "batch": cfg.batch,
        "seed": seed,
        "px_per_mm": camera.px_per_mm,
        "real_frames": len(real),
        "train_s": round(time.perf_counter() - t0, 1),
        "magrun": __version__,
    }
    save_weights(net, out, meta)
    click.echo(f"wrote {out} ({meta['train_s']} s)")


@tracker.command("run")
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@click.option("--px-per-mm", type=float, required=True, help="Scale of the frames, px per mm.")
@click.option("--robot", default="magnet", show_default=True, help="Robot in robots.yaml.")
@_weights_option("Weights [default: the shipped ones].")
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="CSV of poses [default: standard output].",
)
def tracker_run(
    source: Path, px_per_mm: float, robot: str, weights: Path | None, out: Path | None
) -> None:
    """Track the robot in every frame of SOURCE (an image folder or a video file).

    Writes one CSV row per frame: frame name, x and y in mm from the image centre (x right,
    y up), heading in degrees, the lowest keypoint confidence, and the keypoints in pixels.
    A frame where the robot was not found has empty pose columns.
    """
    import csv
    from dataclasses import replace

    from magrun.robot import load_robot
    from magrun.tracking.camera import DEFAULT_CAMERA, Camera
    from magrun.tracking.dataset import iter_frames

    if not px_per_mm > 0:
        raise InputError("--px-per-mm must be positive")
    try:
        params = load_robot(robot)
    except KeyError as exc:
        raise InputError(str(exc).strip("'\"")) from exc
    stream = open(out, "w", newline="", encoding="utf-8") if out else sys.stdout  # noqa: SIM115
    try:
        writer = csv.writer(stream)
        writer.writerow(
            ["frame", "x_mm", "y_mm", "theta_deg", "confidence",
             "tail_u", "tail_v", "centre_u", "centre_v", "head_u", "head_v"]
        )  # fmt: skip
        tracker_ = None
        found = total = 0
        for name, rgb in iter_frames(source):
            if tracker_ is None:
                h, w = rgb.shape[:2]
                cfg = replace(DEFAULT_CAMERA, width_px=w, height_px=h, px_per_mm=px_per_mm)
                tracker_ = _default_tracker(Camera(cfg), params, weights)
            if rgb.shape[:2] != tracker_.camera.shape:
                raise InputError(
                    f"{source}: frame {name} is {rgb.shape[:2]}, not {tracker_.camera.shape}"
                )
            result = tracker_.track(rgb)
            pose = ["", "", ""]
            if result.pose is not None:
                x, y, th = result.pose
                pose = [f"{x * 1e3:.4f}", f"{y * 1e3:.4f}", f"{math.degrees(th):.3f}"]
                found += 1
            total += 1
            kp = [f"{v:.2f}" for v in result.keypoints.ravel()]
            writer.writerow([name, *pose, f"{result.confidence:.3f}", *kp])
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    finally:
        if out:
            stream.close()
    click.echo(f"tracked {found} of {total} frames", err=True)


@tracker.command("eval")
@_weights_option("Weights to evaluate [default: the shipped ones].")
@click.option("--frames", type=click.IntRange(min=10), default=1000, show_default=True)
@click.option(
    "--search-frames",
    type=click.IntRange(min=0),
    default=100,
    show_default=True,
    help="Extra frames tracked with no previous pose (whole-frame search).",
)
@click.option("--seed", default=10_000, show_default=True, help="Seed of the held-out frames.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def tracker_eval(
    weights: Path | None, frames: int, search_frames: int, seed: int, as_json: bool
) -> None:
    """Accuracy and speed of the tracker on rendered frames it never saw.

    Position error (mm), orientation error (degrees), failure rate (no pose, or more than
    1 mm off) and time per frame (ms), over both robots and each, on the default camera.
    """
    from magrun.robot import load_robots
    from magrun.tracking.evaluate import evaluate
    from magrun.tracking.tracker import default_weights_path
    from magrun.tracking.unet import load_weights

    path = weights if weights is not None else default_weights_path()
    try:
        model, meta = load_weights(path)
    except (ValueError, OSError, KeyError) as exc:
        raise InputError(f"{path}: cannot load weights: {exc}") from exc
    progress = _Progress("evaluating", not as_json)
    report = evaluate(
        model, list(load_robots().values()), frames, search_frames, seed=seed, progress=progress
    )
    report = {"weights": str(path), "trained": meta, **report}
    if as_json:
        click.echo(json.dumps(report))
        return
    for name, r in [("tracking", report["tracking"]), *report["per_robot"].items(),
                    ("search", report["search"])]:  # fmt: skip
        if r is None:
            continue
        click.echo(
            f"{name:>14}: {r['frames']} frames  RMS {r['rms_position_mm']:.3f} mm"
            f" {r['rms_orientation_deg']:.2f}°  failures {100 * r['failure_rate']:.1f} %"
            f"  median {r['median_ms']:.2f} ms/frame"
        )


# --------------------------------------------------------------------------------------------
# protocols, runs, recordings


def _load_protocols(paths: tuple[Path, ...]) -> list[Any]:
    """Every protocol, or one InputError listing every problem in every file."""
    from magrun.protocol import load_protocol
    from magrun.yamlio import YamlModelError

    protocols, problems = [], []
    for path in paths:
        try:
            protocols.append(load_protocol(path))
        except YamlModelError as exc:
            problems.extend(exc.problems)
    if problems:
        raise InputError("\n".join(problems))
    return protocols


@cli.command("validate")
@click.argument("protocols", nargs=-1, required=True, type=click.Path(path_type=Path))
def validate(protocols: tuple[Path, ...]) -> None:
    """Check protocol files without running anything.

    Exit status 0 when every file is valid; 2 with one line per problem (file:line: field:
    message) otherwise.
    """
    for path, protocol in zip(protocols, _load_protocols(protocols), strict=True):
        n, nq = len(protocol.expand()), len(protocol.expand(quick=True))
        click.echo(f"{path}: ok ({protocol.name}: {n} trials, {nq} with --quick)")


@cli.group("protocol")
def protocol_group() -> None:
    """Protocol files: their JSON Schema."""


@protocol_group.command("schema")
@click.option("--out", type=click.Path(path_type=Path), help="Write to a file instead.")
def protocol_schema(out: Path | None) -> None:
    """Print the protocol JSON Schema (for editors: completion and checking of YAML files)."""
    from magrun.atomic import write_text
    from magrun.protocol import json_schema

    text = json_schema()
    if out is None:
        click.echo(text, nl=False)
    else:
        write_text(out, text)
        click.echo(f"wrote {out}", err=True)


class _RunProgress:
    """A bar per protocol (trials) and one per running trial (ticks), on a terminal only."""

    def __init__(self, name: str, total: int) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self.bar = tqdm(total=total, desc=name, unit="trial", position=0, disable=None)
        self.trials: dict[str, Any] = {}
        self.failed = 0

    def tick(self, relpath: str, done: int, total: int) -> None:
        bar = self.trials.get(relpath)
        if bar is None:
            slot = len(self.trials) + 1
            bar = self._tqdm(
                total=total, desc=relpath.split("/", 1)[1], unit="tick", leave=False,
                position=slot, disable=None,
            )  # fmt: skip
            self.trials[relpath] = bar
        bar.update(done - bar.n)

    def trial_done(self, entry: dict[str, Any]) -> None:
        bar = self.trials.pop(f"{entry['protocol']}/{entry['path']}", None)
        if bar is not None:
            bar.close()
        self.failed += entry["status"] not in ("ok", "stopped")
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=self.failed)

    def close(self) -> None:
        for bar in self.trials.values():
            bar.close()
        self.bar.close()


def _summary(manifest: dict[str, Any]) -> list[str]:
    """One line per condition: trials ok, mean RMS errors, overruns, drops, wall time."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for e in manifest["trials"]:
        groups.setdefault(e["path"].rsplit("/", 1)[0], []).append(e)
    width = max(len(k) for k in groups)
    lines = [
        f"{'condition':<{width}}  ok   RMS mm  RMS deg  overrun  dropped  wall s",
    ]
    for slug, entries in groups.items():
        ok = [e for e in entries if e["status"] == "ok"]

        def mean(key: str, rows: list[dict[str, Any]] = ok) -> float:
            vals = [r[key] for r in rows if r.get(key) is not None]
            return float(np.mean(vals)) if vals else math.nan

        ticks = sum(e.get("ticks", 0) for e in ok)
        overrun = sum(e.get("overruns", 0) for e in ok) / ticks if ticks else math.nan
        lines.append(
            f"{slug:<{width}}  {len(ok)}/{len(entries)}  {mean('rms_position_mm'):6.3f}"
            f"  {mean('rms_orientation_deg'):7.2f}  {overrun:6.0%}"
            f"  {sum(e.get('dropped_ticks', 0) for e in entries):7d}"
            f"  {sum(e.get('wall_s', 0.0) for e in entries):6.0f}"
        )
    for e in manifest["trials"]:
        if e["status"] == "stopped":
            lines.append(f"STOPPED {e['path']}: {e.get('error', '')}")
        elif e["status"] != "ok":
            lines.append(f"FAILED {e['path']}: {e.get('error', '')}")
        for warning in e.get("warnings") or []:
            lines.append(f"WARNING {e['path']}: {warning}")
    return lines


@cli.command("run")
@click.argument("protocol_file", type=click.Path(path_type=Path))
@click.option(
    "--out", type=click.Path(path_type=Path), default=Path("recordings"), show_default=True,
    help="Recordings go to OUT/<protocol name>/.",
)  # fmt: skip
@click.option("--quick", is_flag=True, help="One trial of a reduced set, shorter (the demo).")
@click.option("--seed", type=click.IntRange(min=0), help="Override the protocol's seed.")
@click.option("--jobs", type=click.IntRange(min=1), default=1, show_default=True,
              help="Trials run in parallel, one process each.")  # fmt: skip
@click.option(
    "--rig", type=click.Choice(["sim", "hardware"]), default="sim", show_default=True,
    help="sim: the simulated plant; hardware: the coils through --driver, in real time.",
)  # fmt: skip
@click.option(
    "--driver", metavar="URL",
    help="Hardware rig: the coil driver, tcp://HOST:PORT (the line protocol; "
    "`magrun rig-emulator` serves one) or a plugin's scheme.",
)  # fmt: skip
@click.option(
    "--camera", "camera_source", default="driver", show_default=True, metavar="SOURCE",
    help="Hardware rig: 'driver' (frames over the driver's connection) or an OpenCV source "
    "(device index, video file, GStreamer pipeline).",
)  # fmt: skip
@click.option(
    "--executor", type=click.Choice(["local", "ray"]), default="local", show_default=True,
    help="local: this machine's processes (--jobs); ray: Ray tasks (pip install magrun[ray]).",
)  # fmt: skip
@click.option("--ray-address", help="Ray cluster to join (default: start a local instance).")
@click.option("--overwrite", is_flag=True, help="Replace OUT/<protocol>/ if it exists.")
@click.option(
    "--resume", is_flag=True,
    help="Continue the run in OUT/<protocol>/: trials already ok are kept, the rest run.",
)  # fmt: skip
def run(
    protocol_file: Path,
    out: Path,
    quick: bool,
    seed: int | None,
    jobs: int,
    rig: str,
    driver: str | None,
    camera_source: str,
    executor: str,
    ray_address: str | None,
    overwrite: bool,
    resume: bool,
) -> None:
    """Run every trial of a protocol and record each to MCAP and Rerun.

    The protocol is validated first; a bad file exits with status 2 before anything runs.
    Writes OUT/<protocol>/<condition>/trial-<k>.{mcap,rrd} and OUT/<protocol>/manifest.json,
    then prints a summary per condition. Exit status 1 when a trial failed (the manifest
    holds its error; the other trials' recordings are complete). SIGINT (Ctrl-C) or SIGTERM
    ends the running trials cleanly (zero currents, recordings finished and indexed, marked
    "interrupted" in the manifest) and exits with 130 / 143; --resume runs the rest.
    """
    from magrun import interrupt
    from magrun.runner import (
        HardwareSpec,
        RigSpec,
        RunError,
        local_executor,
        ray_executor,
        run_protocol,
    )

    (protocol,) = _load_protocols((protocol_file,))
    if driver is not None and rig != "hardware":
        raise InputError("--driver is for --rig hardware")
    the_rig: RigSpec = HardwareSpec(driver, camera_source) if driver is not None else rig
    n = len(protocol.expand(quick=quick, seed=seed))
    chosen = ray_executor(ray_address, jobs) if executor == "ray" else local_executor(jobs)
    progress = _RunProgress(protocol.name, n)
    if resume and overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    t0 = time.perf_counter()
    interrupt.clear()
    try:
        with interrupt.handling():
            manifest = run_protocol(
                protocol, out, quick=quick, seed=seed, jobs=jobs, rig=the_rig,
                executor=None if executor == "local" else chosen,
                overwrite=overwrite, protocol_file=str(protocol_file),
                on_trial=progress.trial_done, progress=progress.tick, resume=resume,
            )  # fmt: skip
    except RunError as exc:
        raise InputError(str(exc)) from exc
    finally:
        progress.close()
    wall = time.perf_counter() - t0
    for line in _summary(manifest):
        click.echo(line)
    failed = sum(e["status"] not in ("ok", "stopped") for e in manifest["trials"])
    dropped = sum(e.get("dropped_ticks", 0) for e in manifest["trials"])
    click.echo(
        f"{len(manifest['trials'])} trials in {wall:.0f} s -> {out / protocol.name}"
        + (f"; {dropped} ticks dropped by the recorder" if dropped else "")
    )
    normal = [
        e for e in manifest["trials"] if e.get("loop_scheduling", "").startswith("SCHED_OTHER")
    ]
    if normal:
        click.echo(
            f"note: the control loop ran without real-time priority in {len(normal)} trial(s)"
            ' (not permitted: see the README\'s "Hardware rig", Pacing)',
            err=True,
        )
    stopped = interrupt.requested()
    if stopped is not None:
        left = sum(e["status"] != "ok" for e in manifest["trials"])
        click.echo(
            f"stopped by {manifest.get('interrupted', stopped)}: currents zeroed, recordings "
            f"closed; {left} trial(s) not complete. Continue with --resume.",
            err=True,
        )
        sys.exit(interrupt.exit_status(stopped))
    if failed:
        raise click.ClickException(f"{failed} trial(s) failed; see {out / protocol.name}")


@cli.command("view")
@click.argument("recording", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option(
    "--save", type=click.Path(dir_okay=False, path_type=Path),
    help="Write an .rrd (an .mcap is converted) instead of opening the viewer.",
)  # fmt: skip
def view(recording: Path, save: Path | None) -> None:
    """Open a recording (.rrd or .mcap) in the Rerun viewer, or save it as an .rrd."""
    import shutil
    import subprocess

    suffix = recording.suffix.lower()
    if suffix not in (".rrd", ".mcap"):
        raise InputError(f"{recording}: not a recording (.rrd or .mcap)")
    if suffix == ".mcap":
        _check_mcap(recording)
    rerun = _rerun_executable()
    if save is None:
        sys.exit(subprocess.call([rerun, str(recording)]))
    if save.suffix.lower() != ".rrd":
        raise InputError(f"--save {save}: the output must be an .rrd file")
    if suffix == ".rrd":
        shutil.copyfile(recording, save)
    else:
        _mcap_to_rrd(recording, save)
    click.echo(f"wrote {save}")


def _check_mcap(path: Path) -> None:
    """An InputError naming ``path`` and the fix unless it is an indexed MCAP file."""
    from mcap.reader import make_reader

    from analysis.load import RECOVER_HINT

    try:
        with path.open("rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception as exc:  # mcap raises several types for damaged files
        raise InputError(f"{path}: cannot be read: {RECOVER_HINT} ({exc})") from exc
    if summary is None:
        raise InputError(f"{path}: no summary or index: {RECOVER_HINT}")


def _rerun_executable() -> str:
    import shutil

    return shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))


def _mcap_to_rrd(mcap: Path, rrd: Path) -> None:
    """Rerun's own MCAP importer (``rerun mcap convert``)."""
    import subprocess

    done = subprocess.run(
        [_rerun_executable(), "mcap", "convert", str(mcap), "-o", str(rrd)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if done.returncode != 0:
        raise click.ClickException(f"rerun mcap convert failed: {done.stderr.strip()}")


@cli.command("recover")
@click.argument("src", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("dst", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--rrd", is_flag=True, help="Also regenerate DST's .rrd from the recovered MCAP.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON object.")
def recover_cmd(src: Path, dst: Path, rrd: bool, as_json: bool) -> None:
    """Rebuild a complete, indexed MCAP file DST from a truncated or damaged SRC.

    Every intact record is kept (a recorder killed mid-trial loses at most its open chunk,
    about the last second); SRC is never modified. Prints how many messages were recovered
    and how many bytes were not. Exit status 2 when SRC is not an MCAP file.
    """
    from magrun.recover import recover

    if dst.suffix.lower() != ".mcap":
        raise InputError(f"{dst}: the recovered file must be an .mcap")
    try:
        report = recover(src, dst)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    rrd_path = None
    if rrd:
        rrd_path = dst.with_suffix(".rrd")
        _mcap_to_rrd(dst, rrd_path)
    if as_json:
        doc = {
            "source": str(src), "recovered": str(dst), "rrd": str(rrd_path) if rrd_path else None,
            "messages": report.messages, "per_topic": dict(report.per_topic),
            "metadata": report.metadata, "complete": report.complete,
            "bytes_total": report.bytes_total, "bytes_lost": report.bytes_lost,
            "last_time_s": None if report.last_time_ns is None else report.last_time_ns / 1e9,
            "problem": report.problem,
        }  # fmt: skip
        click.echo(json.dumps(doc))
        return
    click.echo(f"{src} -> {dst}: {report.summary()}")
    if rrd_path is not None:
        click.echo(f"wrote {rrd_path}")


@cli.command("figures")
@click.argument(
    "recordings", type=click.Path(exists=True, path_type=Path), default=Path("recordings")
)
@click.option(
    "--out", type=click.Path(file_okay=False, path_type=Path),
    help="Output folder  [default: RECORDINGS/figures]",
)  # fmt: skip
@click.option(
    "--zernike-data", type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Field-fit figure data (magrun field fit writes it)  [default: the shipped fit]",
)  # fmt: skip
@click.option("--no-zernike", is_flag=True, help="Skip the Zernike field-model figure.")
def figures(
    recordings: Path, out: Path | None, zernike_data: Path | None, no_zernike: bool
) -> None:
    """The paper's figures, results.csv and report.md from a folder of recordings.

    RECORDINGS is what `magrun run --out` wrote (a folder of protocol folders), one protocol
    folder, or one .mcap file. Every figure for which recordings exist is drawn, as PNG and
    PDF; the Zernike figure comes from the field fit. Unreadable recordings are named on
    stderr and left out; the rest still make figures (exit status 1 then).
    """
    from tqdm import tqdm

    import analysis
    from analysis.report import report_markdown

    out = out or (recordings / "figures" if recordings.is_dir() else recordings.parent)
    try:
        data = analysis.load(
            recordings,
            progress=lambda it: tqdm(list(it), desc="reading", unit="trial", disable=None),
        )
    except (FileNotFoundError, analysis.RecordingError) as exc:
        raise InputError(str(exc)) from exc
    for problem in data.problems:
        click.echo(f"unreadable: {problem}", err=True)
    if data.trials.empty:
        raise InputError(f"{recordings}: no recordings found (run `magrun run PROTOCOL` first)")
    z = None
    if not no_zernike:
        from magrun.field.fitting import FIGURE_FILE

        path = zernike_data or Path(__file__).parent / "field" / "data" / FIGURE_FILE
        with np.load(path) as npz:
            z = dict(npz)
    written = analysis.figures.draw_all(data, out, zernike_data=z)
    results = analysis.write_results(data, out / "results.csv")
    report = out / "report.md"
    report.write_text(report_markdown(data, written, out_dir=out))
    for name, paths in written.items():
        click.echo(f"{name:>18}: " + ", ".join(str(p) for p in paths))
    click.echo(f"{'results':>18}: {results} ({len(data.trials)} trials)")
    click.echo(f"{'report':>18}: {report}")
    if data.problems:
        raise click.ClickException(f"{len(data.problems)} recording(s) could not be read")


@cli.group()
def bench() -> None:
    """Benchmarks; --json prints one JSON object."""


@bench.command("nmpc")
@click.option(
    "--ticks", type=int, default=None, help="Closed-loop ticks per variant [default: the whole S]."
)
@click.option(
    "--variant",
    "variants",
    multiple=True,
    type=click.Choice(["proposed", "proposed_ipopt_reference", "b5_lut", "b5_lut_ipopt"]),
    help="Variants to run (repeatable) [default: all four].",
)
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_nmpc(ticks: int | None, variants: tuple[str, ...], as_json: bool) -> None:
    """NMPC solve times and closed-loop tracking, fast solver vs the IPOPT reference.

    Each variant (proposed: Gauss-Newton RTI + HPIPM on the Zernike model;
    proposed_ipopt_reference: IPOPT to convergence, same problem; b5_lut / b5_lut_ipopt: the
    same two on the lookup tables) runs the S-trajectory closed loop on the simulated rig,
    one after the other, pinned to one core. The first run on a machine also compiles the
    solvers' C code (about a minute for each IPOPT variant; cached, see README).
    """
    from magrun.bench import NMPC_VARIANTS
    from magrun.bench import bench_nmpc as run

    if ticks is not None and ticks < 2:
        raise InputError("--ticks must be at least 2")
    chosen = variants or tuple(NMPC_VARIANTS)
    out = run(ticks, chosen, progress=None if as_json else _say("running"))
    if as_json:
        click.echo(json.dumps(out))
        return
    for name, r in out["variants"].items():
        click.echo(
            f"{name:>25}: median {r['median_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms,"
            f" max {r['max_ms']:.2f} ms, {r['median_iterations']:.0f} it,"
            f" RMS {r['rms_position_mm']:.4f} mm / {r['rms_orientation_deg']:.3f} deg,"
            f" build {r['build_s']:.1f} s"
        )
    for key in ("speedup_vs_ipopt", "p99_speedup_vs_ipopt", "b5_speedup_vs_ipopt"):
        if key in out:
            click.echo(f"{key}: {out[key]:.1f}x")
    if "rms_position_vs_ipopt" in out:
        click.echo(f"RMS position vs IPOPT: {100 * out['rms_position_vs_ipopt']:+.2f} %")


@bench.command("recorder")
@click.option("--seconds", default=5.0, show_default=True, help="Length of the throughput run.")
@click.option("--fps", default=200.0, show_default=True, help="Camera frames per second offered.")
@click.option("--width", default=1280, show_default=True, help="Frame width, px.")
@click.option("--height", default=1024, show_default=True, help="Frame height, px.")
@click.option(
    "--compression",
    type=click.Choice(["lz4", "zstd", "none"]),
    default="none",
    show_default=True,
    help="MCAP chunk compression (LZ4 does not shrink noisy 8-bit frames: same MB/s, more CPU).",
)
@click.option(
    "--dir",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Where the scratch recordings go (deleted after) [default: the system temp dir].",
)
@click.option("--ticks", default=1000, show_default=True, help="Control ticks per tick-cost phase.")
@click.option(
    "--pinned/--no-pinned", default=True, show_default=True,
    help="Also measure each writer as on the rig: the loop on the first core at real-time"
    " priority (where permitted), the writer on the others.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_recorder(
    seconds: float,
    fps: float,
    width: int,
    height: int,
    compression: str,
    out_dir: Path | None,
    ticks: int,
    pinned: bool,
    as_json: bool,
) -> None:
    """Raw camera frames into MCAP at FPS with poses and currents; logging's cost per tick,
    for the thread writer and the process writer side by side (and pinned, as on the rig)."""
    from magrun.bench import bench_recorder as run

    if seconds <= 0 or fps <= 0 or width < 16 or height < 16 or ticks < 10:
        raise InputError(
            "--seconds and --fps must be positive, --width/--height at least 16, --ticks 10"
        )
    folder = None if out_dir is None else str(out_dir)
    out = run(seconds, fps, width, height, folder, compression, ticks, pinned=pinned)
    if as_json:
        click.echo(json.dumps(out))
        return
    c = out["tick_cost"]
    click.echo(f"tick cost: p99 {c['p99_bare_ms']:.2f} ms bare")
    if "p99_bare_pinned_ms" in c:
        click.echo(
            f"tick cost: p99 {c['p99_bare_pinned_ms']:.2f} ms bare, loop placed as on a rig"
            f" ({out['loop_scheduling']})"
        )
    for writer, t in out["throughput"].items():
        w = c[writer]
        click.echo(
            f"{writer} writer: {t['frames_written']}/{t['frames_offered']} frames of"
            f" {out['frame']}, {t['ticks_dropped']} dropped, {t['sustained_fps']:.0f} fps"
            f" sustained, {t['mcap_mb_per_s']:.0f} MB/s; p99 {w['p99_logging_ms']:.2f} ms"
            f" logging (+{w['p99_added_ms']:.2f} ms)"
        )


@bench.command("sigkill")
@click.option("--kills", default=20, show_default=True, help="Processes to kill.")
@click.option("--seed", default=0, show_default=True, help="Seeds the kill moments.")
@click.option(
    "--writer", type=click.Choice(["thread", "process"]), default="thread", show_default=True,
    help="The recorder's writer: in the killed process, or a child process that survives it.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_sigkill(kills: int, seed: int, writer: str, as_json: bool) -> None:
    """Recordings after SIGKILL: kill a recording process at random moments, recover, count."""
    from magrun.bench import bench_sigkill as run

    if kills < 1:
        raise InputError("--kills must be at least 1")
    result = run(kills=kills, seed=seed, writer=writer)
    if as_json:
        click.echo(json.dumps(result))
        return
    click.echo(
        f"{kills} kills ({writer} writer): trial time lost max {result['max_trial_s_lost']:.3f}"
        f" s, median {result['median_trial_s_lost']:.3f} s (chunks closed every"
        f" {result['flush_s']} s); {result['complete_files']} files finished with their footer"
    )


@bench.command("rig")
@click.argument("protocol_file", default="protocols/noise.yaml", type=click.Path(path_type=Path))
@click.option("--stalls", default=20, show_default=True, help="Watchdog trips to time.")
@click.option("--watchdog-ms", default=100.0, show_default=True, help="Watchdog timeout, ms.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_rig(protocol_file: Path, stalls: int, watchdog_ms: float, as_json: bool) -> None:
    """The hardware path on `magrun rig-emulator`: latency, pacing, dropped frames of the
    protocol's --quick trials, and the watchdog's reaction to a stalled loop."""
    from magrun.bench import bench_rig as run

    if stalls < 1 or watchdog_ms <= 0:
        raise InputError("--stalls must be at least 1 and --watchdog-ms positive")
    _load_protocols((protocol_file,))
    result = run(str(protocol_file), stalls, watchdog_ms)
    if as_json:
        click.echo(json.dumps(result))
        return
    for t in result["run"]["trials"]:
        click.echo(
            f"{t['path']}: {t['status']}, {t['ticks']} ticks in {t['wall_s']:.2f} s"
            f" ({t['duration_s']:.2f} s of trial), latency median"
            f" {t.get('latency_median_ms', 0):.1f} ms, p99 {t.get('latency_p99_ms', 0):.1f} ms,"
            f" {t.get('overrun_ticks', 0)} overruns,"
            f" {t.get('dropped_frames', 0)} dropped frames"
        )
    w = result["watchdog"]
    click.echo(
        f"watchdog ({w['timeout_ms']:g} ms, {w['stalls']} stalls): reaction median"
        f" {w['reaction_median_ms']:.1f} ms, max {w['reaction_max_ms']:.1f} ms; currents at"
        f" zero {w['ramp_to_zero_median_ms']:.1f} ms later (median)"
    )


@bench.command("campaign")
@click.argument("protocols", nargs=-1, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--jobs", default=2, show_default=True, help="Trials run in parallel.")
@click.option("--quick", is_flag=True, help="The protocols' --quick sets instead of full ones.")
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Keep the recordings here (replacing its protocol folders) [default: a temp dir].",
)
@click.option(
    "--feedback",
    type=click.Choice(["camera", "truth"]),
    default=None,
    help="Override every protocol's feedback.camera: UNet tracking of rendered frames, or the "
    "simulator's true pose into the fluoroscopy mimic [default: as the protocols say].",
)
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_campaign(
    protocols: tuple[Path, ...],
    jobs: int,
    quick: bool,
    out: Path | None,
    feedback: str | None,
    as_json: bool,
) -> None:
    """The paper's campaign: PROTOCOLS [default: protocols/*.yaml] with recordings, timed."""
    import tempfile

    from magrun.bench import bench_campaign as run

    files = [str(p) for p in protocols] or sorted(str(p) for p in Path("protocols").glob("*.yaml"))
    if not files:
        raise InputError("no protocols given and none in ./protocols")
    _load_protocols(tuple(Path(f) for f in files))  # all valid before anything runs
    if jobs < 1:
        raise InputError("--jobs must be at least 1")
    with tempfile.TemporaryDirectory(prefix="magrun-campaign-") as tmp:
        target = str(out) if out is not None else tmp
        result = run(
            files, target, jobs, quick, progress=None if as_json else _say("running"),
            feedback=feedback,
        )  # fmt: skip
    if as_json:
        click.echo(json.dumps(result))
        return
    for name, r in [*result["protocols"].items(), ("total", result["total"])]:
        click.echo(
            f"{name:>18}: {r['trials']} trials in {r['wall_s'] / 60:.1f} min"
            f" ({r['trials_per_min']:.1f}/min), {r['failed']} failed,"
            f" {r['dropped_ticks']} dropped, {r['overrun_ticks']} overruns,"
            f" {r['recordings_mb']:.0f} MB"
        )


@bench.command("tick")
@click.option(
    "--protocol",
    "protocol_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("protocols/noise.yaml"),
    show_default=True,
    help="Protocol whose first trial of the method is timed.",
)
@click.option("--ticks", default=800, show_default=True, help="Ticks to time.")
@click.option("--method", default="proposed", show_default=True, help="Control method.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
def bench_tick(protocol_file: Path, ticks: int, method: str, as_json: bool) -> None:
    """Median time per tick of each stage of a camera trial: render, track, control, plant."""
    from magrun.bench import bench_tick as run
    from magrun.control.methods import METHODS

    _load_protocols((protocol_file,))
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if ticks < 10:
        raise InputError("--ticks must be at least 10")
    out = run(str(protocol_file), ticks, method)
    if as_json:
        click.echo(json.dumps(out))
        return
    for stage in ("render", "track", "control", "plant"):
        click.echo(f"{stage:>8}: {out[stage + '_ms']:.2f} ms")
    click.echo(f"{'sum':>8}: {out['sum_of_medians_ms']:.2f} ms (medians)")


def _say(prefix: str) -> Any:
    def say(what: str) -> None:
        click.echo(f"{prefix} {what} ...", err=True)

    return say


@cli.command("rig-emulator")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("--port", type=click.IntRange(0, 65535), default=5555, show_default=True,
              help="TCP port (0: any free port, printed).")  # fmt: skip
@click.option("--robot", default="magnet", show_default=True, help="A robot of robots.yaml.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seeds the plant's parameter draw and the camera noise.")  # fmt: skip
@click.option("--camera/--no-camera", default=True, show_default=True,
              help="Serve rendered camera frames (GRAB).")  # fmt: skip
@click.option("--drop-every", type=click.IntRange(min=0), default=0, show_default=True,
              help="Fail every n-th GRAB, as a camera that drops frames (0: never).")  # fmt: skip
def rig_emulator(
    host: str, port: int, robot: str, seed: int, camera: bool, drop_every: int
) -> None:
    """Serve the simulated plant and camera over the rig's line protocol, in real time.

    For testing the hardware path without coils: in another terminal,
    `magrun run PROTOCOL --rig hardware --driver tcp://HOST:PORT`. The protocol is in
    magrun/rigs/wire.py (and the README). Ctrl-C stops it.
    """
    from magrun.rigs.emulator import RigEmulator
    from magrun.rigs.sim import SimRig
    from magrun.robot import load_robots
    from magrun.tracking.camera import CameraConfig

    if robot not in load_robots():
        raise InputError(f"unknown robot {robot!r}; robots.yaml has {', '.join(load_robots())}")
    rig = SimRig.default(robot=robot, seed=seed, camera=CameraConfig() if camera else None)
    try:
        emulator = RigEmulator(rig, host, port, drop_every=drop_every)
    except OSError as exc:
        raise InputError(f"cannot listen on {host}:{port}: {exc}") from exc
    h, p = emulator.address
    click.echo(f"rig emulator: {robot}, {len(rig.channel_names)} channels, tcp://{h}:{p}")
    try:
        emulator.serve_forever()
    except KeyboardInterrupt:
        click.echo("rig emulator stopped")


def main() -> None:
    """Console-script entry point."""
    try:
        cli.main(prog_name="magrun", standalone_mode=True)
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
