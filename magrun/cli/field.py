"""``magrun field``: coil field models (reference maps, Zernike fit, COMSOL import)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from magrun.cli.common import InputError, InputFile, fresh_outputs, load_coils


@click.group()
def field() -> None:
    """Coil field models: reference maps, Zernike fit, COMSOL import."""


COILS_OPTION = click.option(
    "--coils",
    type=InputFile(),
    default=None,
    help="Coil-system YAML (default: the paper's rig shipped with magrun).",
)


OVERWRITE_OPTION = click.option(
    "--overwrite", is_flag=True, help="Replace the files this command writes if they exist."
)


def _fresh(outputs: list[Path], overwrite: bool) -> None:
    """Refuse (exit 2) before any work where one of ``outputs`` exists, unless
    ``overwrite``: a fit or an import never replaces a lab's files unasked."""
    fresh_outputs(outputs, [], overwrite)


def _folder_outputs(folder: Path) -> list[Path]:
    """The files a coil-system folder import writes into ``folder``."""
    from magrun.field.coils import MAPS_FILE, SYSTEM_FILE

    return [folder / SYSTEM_FILE, folder / MAPS_FILE, *_fit_outputs(folder)]


def _fit_outputs(folder: Path) -> list[Path]:
    from magrun.field.fitting import FIGURE_FILE, MODEL_FILE, REPORT_FILE

    return [folder / MODEL_FILE, folder / REPORT_FILE, folder / FIGURE_FILE]


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
@OVERWRITE_OPTION
def field_reference(
    coils: Path | None, out: Path, pitch_mm: float, sheets: int, overwrite: bool
) -> None:
    """Compute unit-current reference maps of every coil type with magpylib.

    To refresh the maps shipped with magrun, run from a source checkout with
    --out magrun/field/data/reference_maps.npz (see docs/data.md).
    """
    from magrun.field.reference import compute_reference_maps

    system = load_coils(coils)
    _fresh([out], overwrite)
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
    type=InputFile(),
    default=None,
    help="Reference maps .npz (default: the maps shipped with magrun).",
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="Folder for zernike_model.json, zernike_fit.json and zernike_figure.npz  "
    "[default: recordings/field; with --system, the system folder].",
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
    "--gradient/--field-only",
    default=None,
    help="Select orders at which the gradient's R² saturates too (the force), or by the "
    "field's alone  [default: with --system, as the folder was fitted (import-mpem: "
    "--gradient); else --field-only, the paper's rule].",
)
@click.option(
    "--order",
    "orders",
    multiple=True,
    metavar="TYPE=N",
    help="Fix the order of a coil type instead of selecting it (repeatable), e.g. small=4.",
)
@click.option(
    "--system", "system_dir", type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="A system folder (magrun field import-mpem): fit each of its channels (and its "
    "background) on a disk around the workspace; the model goes into the folder unless "
    "--out says otherwise.",
)  # fmt: skip
@click.option("--json", "as_json", is_flag=True, help="Print the fit report as one JSON object.")
@OVERWRITE_OPTION
def field_fit(
    coils: Path | None,
    reference: Path | None,
    out: Path | None,
    system_dir: Path | None,
    max_order: int,
    r2_saturation: float,
    gradient: bool | None,
    orders: tuple[str, ...],
    as_json: bool,
    overwrite: bool,
) -> None:
    """Fit the Zernike model to reference maps and report MAE and R² per coil type and order
    (per channel for a system folder)."""
    from magrun.field.fitting import fit_reference, fitted_with_gradient, parse_orders
    from magrun.field.reference import ReferenceMaps

    if system_dir is not None:
        if coils is not None or reference is not None:
            raise InputError("--system holds its own coils and maps: no --coils, --reference")
        system = load_coils(system_dir)
        reference = system.maps_path
        out = out or system_dir
        gradient = fitted_with_gradient(system_dir) if gradient is None else gradient
    else:
        system = load_coils(coils)
        out = out or Path("recordings/field")
    _fresh(_fit_outputs(out), overwrite)
    try:
        fixed = parse_orders(list(orders))
        maps = ReferenceMaps.load(reference)
        result = fit_reference(
            system, maps, max_order=max_order, r2_saturation=r2_saturation, fixed_orders=fixed,
            gradient=bool(gradient),
        )  # fmt: skip
    except KeyError as exc:  # str() of a KeyError quotes its message
        raise InputError(str(exc.args[0])) from exc
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    paths = result.save(out)
    if as_json:
        click.echo(json.dumps({**result.report, "files": {k: str(v) for k, v in paths.items()}}))
        return
    for coil_type, rep in result.report["coil_types"].items():
        unit = "" if coil_type == "background" else "/A"  # a background is in T, not T/A
        rule = rep["selected_by"]
        if rule == "r2_saturation" and result.report["selection"]["gradient"]:
            rule += " of the field and its gradient"
        click.echo(f"{coil_type}: selected order {rep['selected_order']} ({rule})")
        click.echo(f"  order  terms   MAE [mT{unit}]       R²   max err [mT{unit}]   R² of ∇B")
        for s in rep["orders"]:
            mark = "*" if s["order"] == rep["selected_order"] else " "
            click.echo(
                f" {mark}{s['order']:>5} {s['n_terms']:>6} {s['mae_mT']:>12.4f} "
                f"{s['r2']:>8.5f} {s['max_error_mT']:>16.4f} {s['gradient_r2']:>10.5f}"
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
    type=InputFile(),
    help="Small-coil export.",
)
@click.option(
    "--medium",
    type=InputFile(),
    help="Medium-coil export.",
)
@click.option(
    "--large",
    type=InputFile(),
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
    type=click.Path(path_type=Path),
    required=True,
    help="Output reference-map .npz, usable with 'magrun field fit --reference'; or, not "
    "ending in .npz, a coil-system folder (the coils file, the maps and their Zernike fit) "
    "for a protocol's `system:`.",
)
@OVERWRITE_OPTION
def field_import_comsol(
    coils: Path | None,
    small: Path | None,
    medium: Path | None,
    large: Path | None,
    current_a: float,
    out: Path,
    overwrite: bool,
) -> None:
    """Build reference maps from COMSOL plain-text exports, one per coil type."""
    from magrun.field.comsol import import_comsol

    system = load_coils(coils)
    files = {
        k: v for k, v in (("small", small), ("medium", medium), ("large", large)) if v is not None
    }
    missing = sorted({ch.coil_type for ch in system.channels} - set(files))
    if missing:
        raise InputError(f"the driven coil types need exports too: --{' --'.join(missing)}")
    _fresh([out] if out.suffix.lower() == ".npz" else _folder_outputs(out), overwrite)
    try:
        maps = import_comsol(files, current_a, coils_meta=system.spec.model_dump(mode="json"))
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    what = ", ".join(f"{k} {m.x.size} x {m.y.size}" for k, m in maps.maps.items())
    if out.suffix.lower() == ".npz":
        maps.save(out)
        click.echo(f"wrote {out}: {what}")
        return
    from importlib import resources

    from magrun.field.fitting import write_system_folder

    text = (
        coils.read_text(encoding="utf-8")
        if coils is not None
        else (resources.files("magrun.field") / "data" / "coils.yaml").read_text(encoding="utf-8")
    )
    try:
        write_system_folder(out, text, maps)
    except (KeyError, ValueError) as exc:
        raise InputError(str(exc)) from exc
    click.echo(f"wrote the system folder {out}: {what}, and their Zernike fit")


@field.command("import-mpem")
@click.argument("calibration", type=InputFile())
@click.option(
    "--plane-z-mm", type=float, required=True,
    help="The robot's plane: z of the calibration frame, mm.",
)  # fmt: skip
@click.option(
    "--center-mm", type=(float, float), required=True, metavar="X Y",
    help="The workspace centre on that plane, calibration frame, mm.",
)  # fmt: skip
@click.option(
    "--half-width-mm", type=click.FloatRange(min=0, min_open=True), required=True,
    help="The workspace square's half width, mm.",
)  # fmt: skip
@click.option(
    "--pitch-mm", type=click.FloatRange(min=0, min_open=True),
    help="Map grid spacing, mm  [default: the width in 40 steps].",
)  # fmt: skip
@click.option(
    "--max-current-a", type=click.FloatRange(min=0, min_open=True), default=10.0,
    show_default=True, help="Per-channel current limit, A (your amplifiers').",
)  # fmt: skip
@click.option(
    "--max-slew-a-s", type=click.FloatRange(min=0, min_open=True), default=200.0,
    show_default=True, help="Per-channel slew limit, A/s (your amplifiers').",
)  # fmt: skip
@click.option(
    "--out", type=click.Path(file_okay=False, path_type=Path), required=True,
    help="The system folder to write (system.yaml, reference_maps.npz, the Zernike fit).",
)  # fmt: skip
@OVERWRITE_OPTION
def field_import_mpem(
    calibration: Path,
    plane_z_mm: float,
    center_mm: tuple[float, float],
    half_width_mm: float,
    pitch_mm: float | None,
    max_current_a: float,
    max_slew_a_s: float,
    out: Path,
    overwrite: bool,
) -> None:
    """Write a coil-system folder from an ETH multipole (MPEM) calibration.

    The plane z = Z of the calibration's frame, centred at (X, Y), becomes the workspace
    square of half width H; every coil's field and gradient per ampere are sampled on it
    (order-1 sources, point dipoles; an Offset entry becomes the background field). Protocols
    use the folder with `system: DIR`; `magrun field fit --system DIR` fits its Zernike model.
    """
    from magrun.field.mpem import MpemError, MpemModel, import_mpem

    _fresh(_folder_outputs(out), overwrite)
    try:
        folder = import_mpem(
            calibration, out, plane_z_mm * 1e-3, (center_mm[0] * 1e-3, center_mm[1] * 1e-3),
            half_width_mm * 1e-3, pitch_mm * 1e-3 if pitch_mm is not None else None,
            max_current_a, max_slew_a_s,
        )  # fmt: skip
    except MpemError as exc:
        raise InputError(str(exc)) from exc
    system = load_coils(folder)
    model = MpemModel.load(calibration)
    box = model.doc.workspace
    if box and len(box) == 3:
        (x0, x1), (y0, y1), (z0, z1) = box
        h = half_width_mm * 1e-3
        cx, cy, z = center_mm[0] * 1e-3, center_mm[1] * 1e-3, plane_z_mm * 1e-3
        if not (x0 <= cx - h and cx + h <= x1 and y0 <= cy - h and cy + h <= y1 and z0 <= z <= z1):
            click.echo(
                "note: the workspace reaches outside the calibrated box "
                f"({', '.join(f'{a * 1e3:g}..{b * 1e3:g}' for a, b in box)} mm): the model is "
                "extrapolated there",
                err=True,
            )
    click.echo(
        f"wrote {folder}: {system.name}, {system.n_channels} channels"
        + (" and a background field" if system.has_background else "")
        + f", workspace ±{half_width_mm:g} mm on z = {plane_z_mm:g} mm"
    )


@field.command("check")
@click.argument(
    "system_dir", metavar="[SYSTEM]", required=False,
    type=click.Path(exists=True, file_okay=False, path_type=Path),
)  # fmt: skip
@click.option("--robot", required=True, help="A robot of robots.yaml (or of --robots-file).")
@click.option("--robots-file", type=InputFile(), help="A robots file (default: magrun's).")
@click.option(
    "--speed-mm-s", type=click.FloatRange(min=0.001, max=1000.0),
    help="A trajectory speed, mm/s: say whether the robot can move that fast everywhere.",
)  # fmt: skip
@click.option(
    "--points", type=click.IntRange(min=2, max=101), default=11, show_default=True,
    help="Grid positions along each side of the workspace.",
)  # fmt: skip
@click.option(
    "--headings", type=click.IntRange(min=1, max=72), default=8, show_default=True,
    help="Robot headings per position.",
)  # fmt: skip
@click.option(
    "--out",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the map figure (.png, .pdf, .svg).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one JSON object.")
def field_check(
    system_dir: Path | None,
    robot: str,
    robots_file: Path | None,
    speed_mm_s: float | None,
    points: int,
    headings: int,
    out: Path | None,
    as_json: bool,
) -> None:
    """What a coil system (a folder; default: the paper's rig) can do with a robot over its
    workspace: the largest force and torque, the largest field, and the speed the robot can
    hold moving along its axis while its heading is held (the field along its moment at least
    its min_aligned_field, no torque), per position and heading; with --speed-mm-s, whether
    that speed is reachable everywhere ("feasible")."""
    from magrun.field.capability import workspace_capability
    from magrun.field.system import load_system
    from magrun.robot import load_robot
    from magrun.yamlio import YamlModelError

    if out is not None and out.suffix.lower() not in {".png", ".pdf", ".svg"}:
        raise InputError(f"{out}: the figure is a .png, .pdf or .svg file")
    coils = load_coils(system_dir)
    try:
        params = load_robot(robot, robots_file)
        model = load_system(coils.folder).models[1]
    except (KeyError, YamlModelError, ValueError) as exc:
        raise InputError(str(exc.args[0]) if isinstance(exc, KeyError) else str(exc)) from exc
    speed = None if speed_mm_s is None else speed_mm_s * 1e-3
    cap = workspace_capability(
        model, params, coils.max_current, coils.workspace_half_width, points, headings, speed
    )
    summary = {"system": coils.name, "robot": params.name, **cap.summary()}
    if out is not None:
        _capability_figure(cap, summary, out)
        summary["figure"] = str(out)
    if as_json:
        click.echo(json.dumps(summary))
        return
    limit = np.max(coils.max_current)
    s = summary["speed_along_axis_mm_s"]
    click.echo(
        f"{coils.name} ({coils.n_channels} channels, up to {limit:g} A, workspace "
        f"±{coils.workspace_half_width * 1e3:g} mm) with {params.name}, "
        f"{points} × {points} positions × {headings} headings:"
    )
    force = summary["largest_force_uN"]
    click.echo(f"  largest force   {force:10.1f} µN   (along the robot's axis, heading held)")
    click.echo(f"  largest torque  {summary['largest_torque_uNm']:10.2f} µN m")
    click.echo(f"  largest field   {summary['largest_field_mT']:10.1f} mT")
    click.echo(f"  heading held at {summary['poses_held_share']:10.0%} of positions × headings")
    click.echo(
        f"  speed along the axis, heading held: {s['worst']:.2f} mm/s at the worst position and "
        f"heading, median over positions {s['median']:.2f}; best {s['best']:.2f} mm/s"
    )
    if speed_mm_s is not None:
        verdict = "feasible" if summary["feasible"] else "NOT feasible"
        click.echo(
            f"  {speed_mm_s:g} mm/s in every direction (the robot free to point elsewhere): "
            f"{verdict} ({summary['feasible_share']:.0%} of positions × directions)"
        )
    if out is not None:
        click.echo(f"wrote {out}")


def _capability_figure(cap: Any, summary: dict[str, Any], out: Path) -> None:
    """Three maps: the share of headings the coils can hold, the speed along the axis at the
    best heading, the largest field."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from magrun import atomic

    held = np.isfinite(cap.speed)
    panels = [
        ("headings held [%]", held.mean(axis=2) * 100, (0.0, 100.0)),
        ("speed along the axis, best heading [mm/s]",
         np.where(held, cap.speed, 0.0).max(axis=2) * 1e3, (0.0, None)),
        ("largest field [mT]", cap.field * 1e3, (0.0, None)),
    ]  # fmt: skip
    extent = [cap.x[0] * 1e3, cap.x[-1] * 1e3, cap.y[0] * 1e3, cap.y[-1] * 1e3]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), constrained_layout=True)
    for ax, (title, values, (low, high)) in zip(axes, panels, strict=True):
        top = high if high is not None else max(float(values.max()), 1e-9)
        image = ax.imshow(values, origin="lower", extent=extent, cmap="viridis", vmin=low, vmax=top)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x [mm]")
        ax.set_ylabel("y [mm]")
        fig.colorbar(image, ax=ax, shrink=0.85)
    fig.suptitle(f"{summary['system']} with {summary['robot']}")
    atomic.write_figure(fig, out)
    plt.close(fig)
