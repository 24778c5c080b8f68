"""The ``magrun`` command line: one module per verb group, each verb a thin function over the
library (the work lives in :mod:`magrun` and :mod:`analysis`).

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
    magrun build protocols/spine.yaml              # compile ahead what its trials compile
    magrun run protocols/rate.yaml --jobs 2        # run, record MCAP + Rerun, manifest
    magrun view recordings/rate/proposed_rate-3hz/trial-0.rrd      # open in the Rerun viewer
    magrun figures recordings --out figures        # paper figures, results.csv, report.md
    magrun replay REC.mcap --set controller.kalman.measurement_sigma_mm=0.5   # other filter

=====================  ==================================================================
:mod:`.field`          ``field reference | fit | import-comsol``
:mod:`.track`          ``track``
:mod:`.tracker`        ``tracker train | run | eval``
:mod:`.protocols`      ``validate``, ``protocol schema``, ``run``
:mod:`.recordings`     ``view``, ``recover``, ``figures``
:mod:`.replay`         ``replay``
:mod:`.identify`       ``identify``
:mod:`.bench`          ``bench nmpc | tick | recorder | sigkill | campaign | rig``
:mod:`.rig`            ``rig-emulator``
:mod:`.build`          ``build``
:mod:`.common`         the input-error exit, progress output, loading users' files
=====================  ==================================================================

Bad input (a malformed file, an unknown option value) exits with status 2 and one message
naming the file (and line where there is one); it never prints a traceback.
"""

from __future__ import annotations

import signal
import sys

import click

from magrun import __version__
from magrun.cli.bench import bench
from magrun.cli.build import build_cmd
from magrun.cli.common import INPUT_ERROR, InputError
from magrun.cli.field import field
from magrun.cli.identify import identify_cmd
from magrun.cli.protocols import protocol_group, run, validate
from magrun.cli.recordings import figures, recover_cmd, view
from magrun.cli.replay import replay
from magrun.cli.rig import rig_emulator
from magrun.cli.track import track
from magrun.cli.tracker import tracker

__all__ = ["INPUT_ERROR", "InputError", "cli", "main"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="magrun")
def cli() -> None:
    """Run, record and analyse magnetic-robot control experiments."""


for command in (
    field, track, tracker, validate, protocol_group, run, view, recover_cmd, figures, replay,
    identify_cmd, bench, rig_emulator, build_cmd,
):  # fmt: skip
    cli.add_command(command)


def main() -> None:
    """The command line: click's own handling of its errors, with a Ctrl-C at any moment
    (before a run's stop handler is set up, or after) ending it with exit status 130 and one
    line (click alone prints "Aborted!" and exits 1)."""
    from magrun.interrupt import exit_interrupted, requested

    interrupted = False
    try:
        code = cli.main(prog_name="magrun", standalone_mode=False)
    except (KeyboardInterrupt, click.exceptions.Abort):
        interrupted = True  # exit below, once the exception's frames are freed
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except Exception:
        if requested() is None:
            raise
        interrupted = True  # a stop signal that an extension module's import turned into this
    if interrupted:
        exit_interrupted(requested() or signal.SIGINT)
    sys.exit(code if isinstance(code, int) else 0)
