"""``magrun rig-emulator``: the simulated plant and camera behind the rig's line protocol."""

from __future__ import annotations

from pathlib import Path

import click

from magrun.cli.common import InputError, load_coils


@click.command("rig-emulator")
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
@click.option(
    "--system", type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="A coil-system folder (magrun field import-mpem) to emulate  [default: the paper's rig].",
)  # fmt: skip
@click.option(
    "--secret", type=click.Path(dir_okay=False, path_type=Path),
    envvar="MAGRUN_RIG_SECRET_FILE", show_envvar=True,
    help="A file holding a shared secret (chmod 600): clients must prove they hold it. "
    "Required with a --host other than loopback.",
)  # fmt: skip
def rig_emulator(
    host: str,
    port: int,
    robot: str,
    seed: int,
    camera: bool,
    drop_every: int,
    system: Path | None,
    secret: Path | None,
) -> None:
    """Serve the simulated plant and camera over the rig's line protocol, in real time.

    For testing the hardware path without coils: in another terminal,
    `magrun run PROTOCOL --rig hardware --driver tcp://HOST:PORT`. The protocol is in
    magrun/rigs/wire.py (and docs/rigs.md). Ctrl-C stops it.
    """
    from magrun.rigs.emulator import RigEmulator
    from magrun.rigs.sim import SimRig
    from magrun.rigs.wire import is_loopback, read_secret
    from magrun.robot import load_robots
    from magrun.tracking.camera import CameraConfig

    key = None
    try:
        key = read_secret(secret) if secret is not None else None
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    if key is None and not is_loopback(host):
        raise InputError(
            f"--host {host} is not loopback: give a shared secret (--secret FILE); without one "
            "anyone who can reach the port could drive the coils"
        )
    if robot not in load_robots():
        raise InputError(f"unknown robot {robot!r}; robots.yaml has {', '.join(load_robots())}")
    coils = load_coils(system)
    try:  # a system's maps are read here: a bad file is named, nothing served
        rig = SimRig.default(
            robot=robot, seed=seed, camera=CameraConfig() if camera else None, coils=coils
        )
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    try:
        emulator = RigEmulator(rig, host, port, drop_every=drop_every, secret=key)
    except OSError as exc:
        raise InputError(f"cannot listen on {host}:{port}: {exc}") from exc
    h, p = emulator.address
    click.echo(
        f"rig emulator: {coils.name}, {robot}, {len(rig.channel_names)} channels, tcp://{h}:{p}"
        + (" (shared secret)" if key is not None else "")
    )
    try:
        emulator.serve_forever()
    except KeyboardInterrupt:
        click.echo("rig emulator stopped")
