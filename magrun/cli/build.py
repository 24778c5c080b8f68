"""``magrun build``: compile ahead what a protocol's trials compile on first use."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from magrun.cli.common import SET_HELP, InputError, load_protocols


@click.command("build")
@click.argument("protocol_files", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--quick", is_flag=True, help="Only what the protocols' --quick runs need.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=SET_HELP)
def build_cmd(protocol_files: tuple[Path, ...], quick: bool, overrides: tuple[str, ...]) -> None:
    """Compile the NMPC kernels and the simulated plant that PROTOCOL_FILES' trials need.

    A trial compiles them on first use into the user cache (seconds to a minute each, once
    per machine and controller configuration); this does it ahead, e.g. before a session on
    the coils, by running the first ticks of one trial per distinct controller
    configuration on the simulated rig. What is cached is loaded, not rebuilt. Without a C
    compiler it says so and exits 0: trials then run the NMPC uncompiled (the same results,
    slower).
    """
    from magrun.build import build, where
    from magrun.trial import RunError

    protocols = load_protocols(protocol_files, overrides)
    shown = sys.stderr.isatty()

    def progress(name: str, done: int, total: int) -> None:
        if shown:
            click.echo(f"\r{name}: {done}/{total} configurations", err=True, nl=done == total)

    try:
        report = build(protocols, quick, progress)
    except RunError as exc:
        raise InputError(str(exc)) from exc
    for name, n in report.variants.items():
        click.echo(f"{name}: {n} controller configuration{'s' * (n != 1)}")
    click.echo(f"built in {report.seconds:.0f} s; cache: {where()}")
    if not report.compiler:
        click.echo(
            "warning: no C compiler found (set CC, or install one, e.g. gcc), or "
            "MAGRUN_COMPILE=0: nothing was compiled. Trials run the NMPC in CasADi's virtual "
            "machine instead: the same results, several times slower.",
            err=True,
        )
    for line in report.warnings:
        click.echo(f"warning: {line}", err=True)
