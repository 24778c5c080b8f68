"""``magrun tracker``: train the UNet keypoint tracker, evaluate it, track a lab's footage."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import click

from magrun import __version__
from magrun.cli.common import InputError, InputFile, Progress, default_tracker


@click.group()
def tracker() -> None:
    """The UNet keypoint tracker: train it, evaluate it."""


def _weights_option(help_text: str) -> Any:
    return click.option(
        "--weights",
        type=InputFile(),
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
    type=InputFile(),
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
    type=InputFile(),
    default=None,
    help="Keypoint annotations of --images (CSV; see docs/tracking.md).",
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

    from magrun.tracking.camera import CameraConfig
    from magrun.tracking.dataset import real_samples, tracked_robots
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

        net = train(tracked_robots(), cfg, camera, model, real, progress)
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
    graph, _ = _export(out)
    click.echo(f"wrote {out} ({meta['train_s']} s) and its ONNX graph {graph}")


def _export(weights: Path, out: Path | None = None) -> tuple[Path, float]:
    """:func:`magrun.tracking.export.export_graph`, its errors as InputError."""
    from magrun.tracking.inference import TRAIN_EXTRA

    try:
        from magrun.tracking.export import export_graph

        return export_graph(weights, out)
    except ImportError as exc:  # torch or onnx: the train extra
        raise InputError(
            f"exporting the tracker's graph needs torch and onnx ({exc.name or exc}): {TRAIN_EXTRA}"
        ) from exc
    except (ValueError, OSError, KeyError) as exc:
        raise InputError(f"{weights}: {exc}") from exc


@tracker.command("export")
@click.argument("weights", type=InputFile())
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    default=None,
    help="Where to write the graph [default: beside WEIGHTS, suffix .onnx].",
)
@click.option("--overwrite", is_flag=True, help="Replace an existing graph.")
def tracker_export(weights: Path, out: Path | None, overwrite: bool) -> None:
    """Write the ONNX graph of the tracker WEIGHTS (.npz), which tracking runs.

    The graph is exported from torch's model (batch norm folded in), checked to give the
    same heat maps on fixed windows, and stamped with the weights' digest, so that a graph
    left beside other weights is not used. `magrun tracker train` writes it too; this is for
    weights trained elsewhere or before. Needs torch (the train extra).
    """
    target = out if out is not None else weights.with_suffix(".onnx")
    if target.exists() and not overwrite:
        raise InputError(f"{target} exists; add --overwrite to replace it")
    graph, worst = _export(weights, out)
    click.echo(f"wrote {graph} (its heat maps agree with torch's to {worst:.0e})")


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
                tracker_ = default_tracker(Camera(cfg), params, weights)
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
    from magrun.tracking.dataset import tracked_robots
    from magrun.tracking.evaluate import evaluate
    from magrun.tracking.tracker import default_weights_path, load_net
    from magrun.tracking.weights import read_weights

    path = weights if weights is not None else default_weights_path()
    try:
        file = read_weights(path)
        net = load_net(file)
    except (ValueError, OSError, KeyError) as exc:
        raise InputError(f"{path}: cannot load weights: {exc}") from exc
    progress = Progress("evaluating", not as_json)
    report = evaluate(net, tracked_robots(), frames, search_frames, seed=seed, progress=progress)
    report = {"weights": str(path), "trained": file.meta, **report}
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
