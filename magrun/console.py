"""The ``magrun`` console script.

It imports the command line inside its own guard, so that a Ctrl-C at any moment, while the
command's modules are still importing too, ends the command with exit status 130 and one
line, never a traceback (:func:`magrun.cli.main` does the same once it runs).
"""

from __future__ import annotations

from magrun.interrupt import exit_interrupted


def main() -> None:
    """Console-script entry point."""
    try:
        from magrun.cli import main as run
    except KeyboardInterrupt:
        exit_interrupted()
    run()


if __name__ == "__main__":  # python -m magrun.console, as the console script
    main()
