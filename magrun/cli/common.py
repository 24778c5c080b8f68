"""What the verbs share: the input-error exit, progress output, loading users' files."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

INPUT_ERROR = 2


class InputFile(click.Path):
    """An existing regular file to read (a path argument or option): a folder, a FIFO (where
    reading waits for a writer for ever), a socket or a device is refused with exit 2."""

    name = "file"

    def __init__(self) -> None:
        super().__init__(exists=True, dir_okay=False, path_type=Path)

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        path = super().convert(value, param, ctx)
        if not Path(str(path)).is_file():
            self.fail(f"{str(path)!r} is not a regular file.", param, ctx)
        return path


class InputError(click.ClickException):
    """User input we cannot use: exit status 2, message only."""

    exit_code = INPUT_ERROR


@contextlib.contextmanager
def claimed_outputs(outputs: list[Path], inputs: list[Path], overwrite: bool) -> Iterator[None]:
    """Hold each output's lock (:class:`~magrun.atomic.OutputLock`) while the block writes
    them, and check them (:func:`fresh_outputs`) once held: a second command writing the same
    output is refused (InputError) rather than interleaved."""
    from magrun.atomic import FolderBusy, OutputLock

    with contextlib.ExitStack() as stack:
        for out in outputs:
            try:
                stack.enter_context(OutputLock(out))
            except FolderBusy as exc:
                raise InputError(str(exc)) from exc
            except OSError as exc:
                raise InputError(f"{out}: cannot write there: {exc}") from exc
        fresh_outputs(outputs, inputs, overwrite)
        yield


def fresh_outputs(outputs: list[Path], inputs: list[Path], overwrite: bool) -> None:
    """Refuse (:class:`InputError`) to write an output that is, or shadows, an input (the same
    file, or the same name in any case with another extension: the input's ``.rrd`` beside it
    is derived from that name), and one that exists unless ``overwrite``: no verb replaces a
    recording unasked."""
    for out in outputs:
        for src in inputs:
            same_place = out.parent.resolve() == src.parent.resolve()
            if (same_place and out.stem.lower() == src.stem.lower()) or (
                out.exists() and src.exists() and out.resolve() == src.resolve()
            ):
                raise InputError(
                    f"{out}: would replace {src} or the files written beside it; choose "
                    "another output"
                )
        if (out.exists() or out.is_symlink()) and not overwrite:
            raise InputError(
                f"{out} exists; pass --overwrite to replace it, or choose another output"
            )


def load_coils(path: Path | None) -> Any:
    """The coil system of a coil-system YAML (default: the paper's), or an InputError."""
    from magrun.field.coils import CoilFileError
    from magrun.field.system import load_system

    try:
        return load_system(path).coils
    except CoilFileError as exc:
        raise InputError(str(exc)) from exc


def load_protocols(paths: tuple[Path, ...], overrides: tuple[str, ...] = ()) -> list[Any]:
    """Every protocol (``overrides``: ``--set KEY=VALUE`` applied to each), or one
    InputError listing every problem in every file."""
    from magrun.protocol import load_protocol
    from magrun.yamlio import YamlModelError

    protocols, problems = [], []
    for path in paths:
        try:
            protocols.append(load_protocol(path, overrides))
        except YamlModelError as exc:
            problems.extend(exc.problems)
    if problems:
        raise InputError("\n".join(problems))
    return protocols


#: ``--set KEY=VALUE``, shared by the verbs that take a protocol
SET_HELP = (
    "Override a protocol value: a dotted key and a YAML value, e.g. "
    "--set controller.kalman.measurement_sigma_mm=0.5 (repeatable; checked like the file)."
)


def default_tracker(camera: Any, robot: Any, weights: Path | None = None) -> Any:
    """The UNet tracker with ``weights`` (default: the shipped ones), or an InputError."""
    from magrun.tracking.tracker import Tracker

    try:
        return Tracker.default(camera, robot, weights)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"cannot load tracker weights: {exc}") from exc


class Progress:
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


def say(prefix: str) -> Any:
    """A progress callback printing ``prefix what ...`` on stderr."""

    def echo(what: str) -> None:
        click.echo(f"{prefix} {what} ...", err=True)

    return echo


JSON_OPTION = click.option(
    "--json", "as_json", is_flag=True, help="Print the figures as one JSON object."
)


class Latency(click.ParamType):
    """A latency in ms (a number ≥ 0), ``measured`` or ``none``, as a protocol's
    ``controller.latency_ms``."""

    name = "MS|measured|none"

    def convert(self, value: Any, param: Any, ctx: Any) -> float | str:
        if value in ("measured", "none") or isinstance(value, float):
            return value
        try:
            ms = float(value)
        except ValueError:
            ms = -1.0
        if not ms >= 0:
            self.fail(f"{value!r}: a number of ms (0 or more), 'measured' or 'none'", param, ctx)
        return ms
