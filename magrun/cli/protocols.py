"""``magrun validate``, ``magrun protocol schema`` and ``magrun run``: protocols and runs."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import click
import numpy as np

from magrun.cli.common import SET_HELP, InputError, load_protocols
from magrun.cli.viewer import LiveView, live_view, live_view_options


@click.command("validate")
@click.argument("protocols", nargs=-1, required=True, type=click.Path(path_type=Path))
def validate(protocols: tuple[Path, ...]) -> None:
    """Check protocol files without running anything.

    Each file's schema and values and the files it names (robots, phantom, coil system).
    Exit status 0 when every file is valid; 2 with one line per problem (file:line: field:
    message) otherwise. `magrun run` checks more before its first trial, without loading a
    solver here: the system folder's maps and models, the robot's room in the workspace,
    the robot's clearance from a phantom's critical boundary along its path, the coils'
    reach along the trajectory and, with camera feedback in simulation, that the camera's
    tracker finds the robot.
    """
    for path, protocol in zip(protocols, load_protocols(protocols), strict=True):
        n, nq = len(protocol.expand()), len(protocol.expand(quick=True))
        click.echo(f"{path}: ok ({protocol.name}: {n} trials, {nq} with --quick)")


@click.group("protocol")
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
    """On a terminal, a bar per protocol (trials) and one per running trial (ticks); otherwise
    (a CI log, ``nohup``) one line on stderr per finished trial."""

    def __init__(self, name: str, total: int) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self.bar = tqdm(total=total, desc=name, unit="trial", position=0, disable=None)
        self.trials: dict[str, Any] = {}
        self.failed = 0
        self.total, self.done = total, 0
        self.lines = not sys.stderr.isatty()

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
        self.done += 1
        self.bar.update(1)
        if self.failed:
            self.bar.set_postfix(failed=self.failed)
        if self.lines:
            rms = entry.get("rms_position_mm")
            click.echo(
                f"[{self.done}/{self.total}] {entry['protocol']}/{entry['path']}: "
                f"{entry['status']}" + (", the robot LOST" if entry.get("lost") else "")
                + (f", RMS {rms:.3f} mm" if rms is not None else "")
                + (f" ({entry['wall_s']:.0f} s)" if entry.get("wall_s") is not None else ""),
                err=True,
            )  # fmt: skip

    def warn(self, line: str) -> None:
        """A warning on stderr, above the bars on a terminal."""
        self._tqdm.write(f"warning: {line}", file=sys.stderr)

    def close(self) -> None:
        for bar in self.trials.values():
            bar.close()
        self.bar.close()


def _summary(manifest: dict[str, Any]) -> list[str]:
    """One line per condition: trials ok, mean RMS errors, overruns, drops, the trials' times
    summed ("—" where no trial of the condition completed; with ``--jobs`` they overlap, and
    the run's wall time is :func:`_run`'s last line); then every trial that did not
    complete."""
    groups: dict[str, list[dict[str, Any]]] = {}
    for e in manifest["trials"]:
        groups.setdefault(e["path"].rsplit("/", 1)[0], []).append(e)
    width = max(len(k) for k in groups)
    lines = [
        f"{'condition':<{width}}  ok   lost  RMS mm  RMS deg  overrun  dropped  trial s",
    ]

    def shown(value: float, spec: str, width: int) -> str:
        return f"{value:{width}{spec}}" if math.isfinite(value) else f"{'—':>{width}}"

    for slug, entries in groups.items():
        ok = [e for e in entries if e["status"] == "ok"]

        def mean(key: str, rows: list[dict[str, Any]] = ok) -> float:
            vals = [r[key] for r in rows if r.get(key) is not None]
            return float(np.mean(vals)) if vals else math.nan

        ticks = sum(e.get("ticks", 0) for e in ok)
        overrun = sum(e.get("overruns", 0) for e in ok) / ticks if ticks else math.nan
        lines.append(
            f"{slug:<{width}}  {len(ok)}/{len(entries)}  {sum(bool(e.get('lost')) for e in ok):4d}"
            f"  {shown(mean('rms_position_mm'), '.3f', 6)}"
            f"  {shown(mean('rms_orientation_deg'), '.2f', 7)}  {shown(overrun, '.0%', 7)}"
            f"  {sum(e.get('dropped_ticks', 0) for e in entries):7d}"
            f"  {sum(e.get('wall_s', 0.0) for e in entries):7.0f}"
        )
    for e in manifest["trials"]:
        status, error = e["status"], e.get("error") or ""
        if status == "pending":
            lines.append(f"PENDING {e['path']}: not started (magrun run --resume runs it)")
        elif status == "interrupted":
            lines.append(f"INTERRUPTED {e['path']}: {error or 'stopped before its end'}")
        elif status == "stopped":
            lines.append(f"STOPPED {e['path']}: {error or 'safety stop'}")
        elif status != "ok":
            lines.append(f"FAILED {e['path']}: {error or 'no error recorded'}")
        for warning in e.get("warnings") or []:
            lines.append(f"WARNING {e['path']}: {warning}")
    lines.extend(f"WARNING {manifest['protocol']}: {w}" for w in manifest.get("warnings", []))
    return lines


@click.command("run")
@click.argument("protocol_file", type=click.Path(path_type=Path))
@click.option(
    "--out", type=click.Path(path_type=Path), default=Path("recordings"), show_default=True,
    help="Recordings go to OUT/<protocol name>/.",
)  # fmt: skip
@click.option("--quick", is_flag=True, help="One trial of a reduced set, shorter (the demo).")
@click.option("--seed", type=click.IntRange(min=0), help="Override the protocol's seed.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=SET_HELP)
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
    "--rig-secret", "rig_secret", type=click.Path(dir_okay=False, path_type=Path),
    envvar="MAGRUN_RIG_SECRET_FILE", show_envvar=True,
    help="Hardware rig: a file holding the rig's shared secret (chmod 600); needed for a rig "
    "that is not on this machine (docs: Rigs, 'Security').",
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
@click.option(
    "--allow-infeasible", is_flag=True,
    help="Run a trajectory the coils cannot move the robot along, or one that puts the "
    "robot's body on a phantom's critical boundary (refused by default).",
)  # fmt: skip
@live_view_options
def run(
    protocol_file: Path,
    out: Path,
    quick: bool,
    seed: int | None,
    overrides: tuple[str, ...],
    jobs: int,
    rig: str,
    driver: str | None,
    rig_secret: Path | None,
    camera_source: str,
    executor: str,
    ray_address: str | None,
    overwrite: bool,
    resume: bool,
    allow_infeasible: bool,
    open_view: bool,
    connect: str | None,
    web: bool,
    web_port: int,
) -> None:
    """Run every trial of a protocol and record each to MCAP and Rerun.

    The protocol is validated first; a bad file exits with status 2 before anything runs.
    Writes OUT/<protocol>/<condition>/trial-<k>.{mcap,rrd} and OUT/<protocol>/manifest.json,
    then prints a summary per condition. Exit status 1 when a trial failed (the manifest
    holds its error; the other trials' recordings are complete). SIGINT (Ctrl-C) or SIGTERM
    ends the running trials cleanly (zero currents, recordings finished and indexed, marked
    "interrupted" in the manifest) and exits with 130 / 143; --resume runs the rest.

    Before anything runs, the trajectory is checked against what the coils can do with the
    robot (the velocity at every pose, the robot's field held, within the current limits):
    one they cannot follow exits 2, naming where, unless --allow-infeasible. In a phantom, so
    is a path on which the robot's body touches the critical boundary; one that passes it
    closer than the NMPC's corridor margin (0.5 mm) is run with a warning.

    With --view, --connect or --web each trial is also streamed to a Rerun viewer while it
    runs, one recording per trial, with the same views as its .rrd. The recordings are
    written the same with or without a viewer, and whatever becomes of it.
    """
    from magrun.runner import HardwareSpec, RigSpec

    if resume and overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    if driver is not None and rig != "hardware":
        raise InputError("--driver is for --rig hardware")
    secret = None
    if rig_secret is not None and driver is not None:
        from magrun.rigs.wire import read_secret

        try:
            secret = read_secret(rig_secret)
        except ValueError as exc:
            raise InputError(str(exc)) from exc
    (protocol,) = load_protocols((protocol_file,), overrides)
    the_rig: RigSpec = HardwareSpec(driver, camera_source, secret) if driver is not None else rig
    n = len(protocol.expand(quick=quick, seed=seed))
    with live_view(open_view, connect, web, web_port, f"magrun run {protocol_file} --web") as lv:
        _run(
            protocol, protocol_file, out, quick, seed, jobs, the_rig, executor, ray_address,
            overwrite, resume, n, lv, not allow_infeasible,
        )  # fmt: skip


def _run(
    protocol: Any,
    protocol_file: Path,
    out: Path,
    quick: bool,
    seed: int | None,
    jobs: int,
    the_rig: Any,
    executor: str,
    ray_address: str | None,
    overwrite: bool,
    resume: bool,
    n: int,
    view: LiveView | None,
    check_reach: bool = True,
) -> None:
    from magrun import interrupt
    from magrun.runner import RunError, local_executor, ray_executor, run_protocol

    url = view.url if view is not None else ""
    try:
        chosen = (
            ray_executor(ray_address, jobs, view=url)
            if executor == "ray"
            else local_executor(jobs, view=url)
        )
    except RunError as exc:
        raise InputError(str(exc)) from exc
    progress = _RunProgress(protocol.name, n)
    t0 = time.perf_counter()
    try:  # a Ctrl-C already remembered (magrun.console) stops the run before its first tick
        with interrupt.handling():
            manifest = run_protocol(
                protocol, out, quick=quick, seed=seed, jobs=jobs, rig=the_rig,
                executor=None if executor == "local" else chosen,
                overwrite=overwrite, protocol_file=str(protocol_file),
                on_trial=progress.trial_done, progress=progress.tick, resume=resume, view=url,
                check_reach=check_reach,
                warn=progress.warn,
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
        f"{len(manifest['trials'])} trials in {wall:.0f} s wall time -> {out / protocol.name}"
        + (f"; {dropped} ticks dropped by the recorder" if dropped else "")
    )
    normal = [
        e for e in manifest["trials"] if e.get("loop_scheduling", "").startswith("SCHED_OTHER")
    ]
    if normal:
        click.echo(
            f"note: the control loop ran without real-time priority in {len(normal)} trial(s)"
            " (not permitted: see docs/rigs.md, Pacing)",
            err=True,
        )
    stopped = interrupt.requested()
    if view is not None and stopped is None:
        view.linger()  # --web: the browser may still be looking
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
