"""``magrun view``, ``magrun recover`` and ``magrun figures``: what is done with recordings."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import click

from magrun.cli.common import InputError, InputFile, claimed_outputs
from magrun.cli.viewer import WEB_PORT, check_display, open_file


@click.command("view")
@click.argument("recording", type=InputFile())
@click.option(
    "--save", type=click.Path(dir_okay=False, path_type=Path),
    help="Write an .rrd (an .mcap is converted) instead of opening the viewer.",
)  # fmt: skip
@click.option(
    "--web", is_flag=True,
    help="Serve Rerun's web viewer on 127.0.0.1 instead of opening a window (a headless "
    "workstation, a remote server: forward the port over ssh); Ctrl-C stops it.",
)  # fmt: skip
@click.option(
    "--port", "--web-port", "port", type=click.IntRange(1, 65535), default=WEB_PORT,
    show_default=True,
    help="With --web: the web viewer's HTTP port.",
)  # fmt: skip
def view(recording: Path, save: Path | None, web: bool, port: int) -> None:
    """Open a recording (.rrd or .mcap) in the Rerun viewer, or save it as an .rrd.

    An .mcap is converted to Rerun's format first, with the same layout, trial time axis and
    name as the .rrd written beside it. Without a display (no DISPLAY or WAYLAND_DISPLAY on
    Linux) use --web, which serves the viewer over HTTP on 127.0.0.1 and prints the address
    to open in a browser.
    """
    import shutil

    suffix = recording.suffix.lower()
    if suffix not in (".rrd", ".mcap"):
        raise InputError(f"{recording}: not a recording (.rrd or .mcap)")
    if suffix == ".mcap":
        _check_mcap(recording)
    if save is None and not web:
        check_display(f"magrun view {recording} --web")
    if suffix == ".mcap" and save is None:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="magrun-view-") as tmp:
            rrd = Path(tmp) / (recording.stem + ".rrd")
            click.echo(f"converting {recording} to Rerun's format ...", err=True)
            _mcap_to_rrd(recording, rrd)
            open_file(rrd, web, port, shown=recording)
        return
    if save is not None:
        if save.suffix.lower() != ".rrd":
            raise InputError(f"--save {save}: the output must be an .rrd file")
        if suffix == ".rrd":
            shutil.copyfile(recording, save)
        else:
            _mcap_to_rrd(recording, save)
        click.echo(f"wrote {save}")
        return
    open_file(recording, web, port, shown=recording)


def _check_mcap(path: Path) -> None:
    """An InputError naming ``path`` and the fix unless it is an indexed MCAP file."""
    from analysis.load import RECOVER_HINT
    from magrun.recordings.reader import has_summary
    from magrun.recordings.recover import not_mcap

    if (why := not_mcap(path)) is not None:
        raise InputError(f"{path}: {why}")
    try:
        indexed = has_summary(path)
    except Exception as exc:  # mcap raises several types for damaged files
        raise InputError(f"{path}: cannot be read: {RECOVER_HINT} ({exc})") from exc
    if not indexed:
        raise InputError(f"{path}: no summary or index: {RECOVER_HINT}")


def _mcap_to_rrd(mcap: Path, rrd: Path) -> None:
    """The MCAP as an .rrd with the recorder's views
    (:func:`magrun.recordings.rerun_log.rrd_from_mcap`)."""
    from magrun.recordings.rerun_log import rrd_from_mcap

    try:
        rrd_from_mcap(mcap, rrd)
    except ValueError as exc:
        raise InputError(str(exc)) from exc


@click.command("recover")
@click.argument("src", type=InputFile())
@click.argument("dst", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--rrd", is_flag=True, help="Also regenerate DST's .rrd from the recovered MCAP.")
@click.option("--overwrite", is_flag=True, help="Replace DST (and its .rrd) if they exist.")
@click.option("--json", "as_json", is_flag=True, help="Print the report as one JSON object.")
def recover_cmd(src: Path, dst: Path, rrd: bool, overwrite: bool, as_json: bool) -> None:
    """Rebuild a complete, indexed MCAP file DST from a truncated or damaged SRC.

    Every intact record is kept (a recorder killed mid-trial loses at most its open chunk,
    about the last second); SRC is never modified, and an existing DST is not replaced
    without --overwrite. Prints how many messages were recovered
    and how many bytes were not. Exit status 2 when SRC is not an MCAP file, or when not
    one message of it survives (DST is then not written).
    """
    from magrun.recordings.recover import recover

    if dst.suffix.lower() != ".mcap":
        raise InputError(f"{dst}: the recovered file must be an .mcap")
    rrd_path = dst.with_suffix(".rrd") if rrd else None
    # held while written: a second recover or replay into DST is refused, not interleaved
    with claimed_outputs([dst, *([rrd_path] if rrd_path else [])], [src], overwrite):
        try:
            report = recover(src, dst)
        except ValueError as exc:
            raise InputError(str(exc)) from exc
        if rrd_path is not None:
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


@click.command("figures")
@click.argument(
    "recordings", type=click.Path(exists=True, path_type=Path), default=Path("recordings")
)
@click.option(
    "--out", type=click.Path(file_okay=False, path_type=Path),
    help="Output folder  [default: RECORDINGS/figures]",
)  # fmt: skip
@click.option(
    "--zernike-data", type=InputFile(),
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
    z = None  # read first: a bad file is refused before the recordings are
    if not no_zernike:
        from magrun.field.fitting import FIGURE_FILE, read_figure_data

        path = zernike_data or Path(__file__).parents[1] / "field" / "data" / FIGURE_FILE
        try:
            z = read_figure_data(path)
        except ValueError as exc:
            raise InputError(f"{path}: not Zernike figure data: {exc}") from exc
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
    source = str(zernike_data) if zernike_data is not None else None
    if z is not None and zernike_data is None:
        z, source = _zernike_of_systems(data, z)
    written = analysis.figures.draw_all(data, out, zernike_data=z)
    results = analysis.write_results(data, out / "results.csv")
    replays = _replays(recordings, out, written)
    report = out / "report.md"
    report.write_text(
        report_markdown(data, written, out_dir=out, replays=replays, zernike_source=source)
    )
    for name, paths in written.items():
        click.echo(f"{name:>18}: " + ", ".join(str(p) for p in paths))
    if replays is not None:
        click.echo(f"{'replays':>18}: {out / 'replays.csv'} ({len(replays)} replays)")
    click.echo(f"{'results':>18}: {results} ({len(data.trials)} trials)")
    click.echo(f"{'report':>18}: {report}")
    if data.problems:
        raise click.ClickException(f"{len(data.problems)} recording(s) could not be read")


def _zernike_of_systems(data: Any, shipped: Any) -> tuple[Any, str | None]:
    """The Zernike figure data for the recordings' coil system, and what it is the fit of:
    the shipped fit for the paper's rig; a system folder's own ``zernike_figure.npz`` where
    every recording is of that one folder and it is there; else none (a note on stderr),
    never another system's figure."""
    from magrun.field.fitting import FIGURE_FILE, read_figure_data

    systems = {rec.protocol.get("system") for rec in data.recordings.values()}
    if systems <= {None}:
        return shipped, "the paper's rig (the fit shipped with magrun)"
    named = sorted(str(v) for v in systems if v)
    if len(systems) == 1:
        folder = Path(named[0])
        try:
            return read_figure_data(folder / FIGURE_FILE), str(folder)
        except (OSError, ValueError):
            pass
    click.echo(
        "note: no Zernike figure: the recordings are of "
        + ", ".join(named + (["the paper's rig"] if None in systems else []))
        + f", not one system whose fit figure data is here (`magrun field fit --system DIR "
        f"--overwrite` writes DIR/{FIGURE_FILE}; pass it with --zernike-data)",
        err=True,
    )
    return None, None


def _replays(recordings: Path, out: Path, written: dict[str, list[Path]]) -> Any:
    """The estimator replays beside the recordings (analysis.replays): their table, written
    as replays.csv with its figure; None where there are none."""
    import analysis.figures
    from analysis.replays import figure, find_replays, replay_table

    paths = find_replays(recordings)
    if not paths:
        return None
    try:
        table = replay_table(paths)
    except analysis.RecordingError as exc:
        raise InputError(str(exc)) from exc
    out.mkdir(parents=True, exist_ok=True)
    table.to_csv(out / "replays.csv", index=False)
    written["replays"] = analysis.figures.save(figure(table), out, "replays")
    return table
