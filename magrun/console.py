"""The ``magrun`` console script.

It imports the command line inside its own guard, so that a Ctrl-C at any moment, while the
command's modules are still importing too, ends the command with exit status 130 and one
line, never a traceback (:func:`magrun.cli.main` does the same once it runs). The guard also
remembers the Ctrl-C (:func:`magrun.interrupt.remembering_ctrl_c`) for the whole command:
while modules import, the KeyboardInterrupt can be lost (raised inside a weakref callback)
or turned into an ImportError by a compiled extension's initialisation, and the command must
stop all the same.
"""

from __future__ import annotations

from magrun.interrupt import exit_interrupted, remembering_ctrl_c, requested


def main() -> None:
    """Console-script entry point."""
    with remembering_ctrl_c():
        interrupted = False
        try:
            from magrun.cli import main as run
        except BaseException:
            if requested() is None:
                raise
            interrupted = True  # KeyboardInterrupt, or what an extension's import made of it
        if interrupted or requested() is not None:  # the latter: an import swallowed it
            exit_interrupted()
        run()


if __name__ == "__main__":  # python -m magrun.console, as the console script
    main()
