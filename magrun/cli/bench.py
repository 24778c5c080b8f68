"""``magrun bench …``: the benchmarks (:mod:`magrun.bench`); --json prints one JSON object."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

import click

from magrun.cli.common import JSON_OPTION, InputError, load_protocols, say


def _emit(result: dict[str, Any], lines: list[str], as_json: bool) -> None:
    click.echo(json.dumps(result) if as_json else "\n".join(lines))


@click.group()
def bench() -> None:
    """Benchmarks; --json prints one JSON object."""


@bench.command("nmpc")
@click.option(
    "--ticks", type=click.IntRange(min=2), default=None,
    help="Closed-loop ticks per variant [default: the whole S].",
)  # fmt: skip
@click.option(
    "--variant",
    "variants",
    multiple=True,
    type=click.Choice(["proposed", "proposed_ipopt_reference", "b5_lut", "b5_lut_ipopt"]),
    help="Variants to run (repeatable) [default: all four].",
)
@click.option(
    "--system", "systems", multiple=True,
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="A coil-system folder: run the proposed method on it too (repeatable), on the S "
    "scaled to its workspace with the micro_magnet robot; its channel count is reported.",
)  # fmt: skip
@click.option(
    "--protocol", "protocol_files", multiple=True,
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="A protocol file: run its proposed method too (repeatable), one trial under its "
    "fixed conditions (feedback, plant, phantom as declared), e.g. protocols/spine.yaml for "
    "a phantom's ticks beside the S's.",
)  # fmt: skip
@JSON_OPTION
def bench_nmpc(
    ticks: int | None, variants: tuple[str, ...], systems: tuple[Path, ...],
    protocol_files: tuple[Path, ...], as_json: bool,
) -> None:  # fmt: skip
    """NMPC solve times and closed-loop tracking, fast solver vs the IPOPT reference.

    Each variant (proposed: Gauss-Newton RTI + HPIPM on the Zernike model;
    proposed_ipopt_reference: IPOPT to convergence, same problem; b5_lut / b5_lut_ipopt: the
    same two on the lookup tables) runs the S-trajectory closed loop on the simulated rig,
    one after the other, pinned to one core. The first run on a machine also compiles the
    solvers' C code (about a minute for each IPOPT variant; cached, see docs/data.md).
    """
    from magrun.bench import nmpc

    protocols = load_protocols(protocol_files)
    chosen = variants or tuple(nmpc.NMPC_VARIANTS)
    out = nmpc.bench_nmpc(
        ticks, chosen, progress=None if as_json else say("running"), systems=systems,
        protocols=tuple(protocols),
    )  # fmt: skip
    _emit(out, nmpc.summary(out), as_json)


@bench.command("recorder")
@click.option(
    "--seconds", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True,
    help="Length of the throughput run, s.",
)  # fmt: skip
@click.option(
    "--fps", type=click.FloatRange(min=0, min_open=True), default=200.0, show_default=True,
    help="Camera frames per second offered.",
)  # fmt: skip
@click.option("--width", type=click.IntRange(min=16), default=1280, show_default=True,
              help="Frame width, px.")  # fmt: skip
@click.option("--height", type=click.IntRange(min=16), default=1024, show_default=True,
              help="Frame height, px.")  # fmt: skip
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
@click.option("--ticks", type=click.IntRange(min=10), default=1000, show_default=True,
              help="Control ticks per tick-cost phase.")  # fmt: skip
@click.option(
    "--pinned/--no-pinned", default=True, show_default=True,
    help="Also measure each writer as on the rig: the loop on the first core at real-time"
    " priority (where permitted), the writer on the others.",
)  # fmt: skip
@JSON_OPTION
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
    from magrun.bench import recorder

    folder = None if out_dir is None else str(out_dir)
    out = recorder.bench_recorder(
        seconds, fps, width, height, folder, compression, ticks, pinned=pinned
    )
    _emit(out, recorder.summary(out), as_json)


@bench.command("sigkill")
@click.option("--kills", type=click.IntRange(min=1), default=20, show_default=True,
              help="Processes to kill.")  # fmt: skip
@click.option("--seed", default=0, show_default=True, help="Seeds the kill moments.")
@click.option(
    "--writer", type=click.Choice(["thread", "process"]), default="thread", show_default=True,
    help="The recorder's writer: in the killed process, or a child process that survives it.",
)  # fmt: skip
@click.option(
    "--kill-after", "kill_after", type=(float, float), default=(1.0, 6.0), show_default=True,
    metavar="MIN MAX",
    help="Each kill comes a uniformly random time between MIN and MAX s after the recording"
    " started (its chunks close every 1 s of trial).",
)  # fmt: skip
@JSON_OPTION
def bench_sigkill(
    kills: int, seed: int, writer: str, kill_after: tuple[float, float], as_json: bool
) -> None:
    """Recordings after SIGKILL: kill a recording process at random moments, recover, count."""
    from magrun.bench import sigkill

    low, high = kill_after
    if not (math.isfinite(low) and math.isfinite(high) and 0 < low <= high):
        raise click.BadParameter(
            f"{low:g} {high:g}: give MIN MAX in s with 0 < MIN <= MAX", param_hint="--kill-after"
        )
    result = sigkill.bench_sigkill(kills=kills, seed=seed, writer=writer, window=(low, high))
    _emit(result, sigkill.summary(result), as_json)


@bench.command("rig")
@click.argument("protocol_file", default="protocols/noise.yaml", type=click.Path(path_type=Path))
@click.option("--stalls", type=click.IntRange(min=1), default=20, show_default=True,
              help="Watchdog trips to time.")  # fmt: skip
@click.option(
    "--watchdog-ms", type=click.FloatRange(min=0, min_open=True), default=100.0,
    show_default=True, help="Watchdog timeout, ms.",
)  # fmt: skip
@JSON_OPTION
def bench_rig(protocol_file: Path, stalls: int, watchdog_ms: float, as_json: bool) -> None:
    """The hardware path on `magrun rig-emulator`: latency, pacing, dropped frames of the
    protocol's --quick trials, and the watchdog's reaction to a stalled loop."""
    from magrun.bench import rig

    load_protocols((protocol_file,))
    result = rig.bench_rig(str(protocol_file), stalls, watchdog_ms)
    _emit(result, rig.summary(result), as_json)


@bench.command("campaign")
@click.argument("protocols", nargs=-1, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--jobs", type=click.IntRange(min=1), default=2, show_default=True,
              help="Trials run in parallel.")  # fmt: skip
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
@JSON_OPTION
def bench_campaign(
    protocols: tuple[Path, ...],
    jobs: int,
    quick: bool,
    out: Path | None,
    feedback: str | None,
    as_json: bool,
) -> None:
    """The paper's campaign: PROTOCOLS [default: protocols/*.yaml] with recordings, timed."""
    from magrun.bench import campaign

    files = [str(p) for p in protocols] or sorted(str(p) for p in Path("protocols").glob("*.yaml"))
    if not files:
        raise InputError("no protocols given and none in ./protocols")
    load_protocols(tuple(Path(f) for f in files))  # all valid before anything runs
    with tempfile.TemporaryDirectory(prefix="magrun-campaign-") as tmp:
        target = str(out) if out is not None else tmp
        result = campaign.bench_campaign(
            files, target, jobs, quick, progress=None if as_json else say("running"),
            feedback=feedback,
        )  # fmt: skip
    _emit(result, campaign.summary(result), as_json)


@bench.command("cluster")
@click.argument("protocol_file", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--nodes", default="1,2", show_default=True,
              help="Cluster sizes to compare, comma-separated (local Ray clusters).")  # fmt: skip
@click.option("--cpus-per-node", type=click.IntRange(min=1), default=1, show_default=True,
              help="CPUs each node offers (one trial each).")  # fmt: skip
@click.option("--full", is_flag=True, help="The protocol's full set of trials, not --quick.")
@JSON_OPTION
def bench_cluster(
    protocol_file: Path, nodes: str, cpus_per_node: int, full: bool, as_json: bool
) -> None:
    """PROTOCOL_FILE's trials on local Ray clusters of each size, recordings written back to
    the driver (needs the ray extra)."""
    try:
        sizes = [int(n) for n in nodes.split(",") if n.strip()]
    except ValueError:
        raise InputError(f"--nodes: comma-separated whole numbers, got {nodes!r}") from None
    if not sizes or min(sizes) < 1 or max(sizes) > 16:
        raise InputError(f"--nodes: sizes from 1 to 16, got {nodes!r}")
    try:
        import ray  # noqa: F401
    except ImportError:
        raise InputError("magrun bench cluster needs Ray: pip install 'magrun[ray]'") from None
    from magrun.bench import cluster

    load_protocols((protocol_file,))
    result = cluster.bench_cluster(
        str(protocol_file), sizes, cpus_per_node, quick=not full,
        progress=None if as_json else say("cluster of"),
    )  # fmt: skip
    _emit(result, cluster.summary(result), as_json)


@bench.command("tick")
@click.option(
    "--protocol",
    "protocol_file",
    type=click.Path(dir_okay=False, path_type=Path),
    default=Path("protocols/noise.yaml"),
    show_default=True,
    help="Protocol whose first trial of the method is timed.",
)
@click.option("--ticks", type=click.IntRange(min=10), default=800, show_default=True,
              help="Ticks to time.")  # fmt: skip
@click.option("--method", default="proposed", show_default=True, help="Control method.")
@JSON_OPTION
def bench_tick(protocol_file: Path, ticks: int, method: str, as_json: bool) -> None:
    """Median time per tick of each stage of a camera trial: render, track, control, plant."""
    from magrun.bench import tick
    from magrun.control import METHODS

    (protocol,) = load_protocols((protocol_file,))
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if method not in protocol.methods:
        raise InputError(
            f"{protocol_file}: has no {method!r} trials; its methods: "
            + ", ".join(protocol.methods)
        )
    out = tick.bench_tick(str(protocol_file), ticks, method)
    _emit(out, tick.summary(out), as_json)
