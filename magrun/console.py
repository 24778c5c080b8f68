"""The ``magrun`` console script.

It imports the command line inside its own guard, so that a Ctrl-C at any moment, while the
command's modules are still importing too, ends the command with exit status 130 and one
line, never a traceback (:func:`magrun.cli.main` does the same once it runs).
"""

from __future__ import annotations

import sys

#: what a stop by Ctrl-C prints, and its exit status (128 + SIGINT)
INTERRUPTED = ("interrupted", 130)


def interrupted() -> None:
    """End the process as a Ctrl-C does: one line on stderr, exit status 130."""
    print(f"\n{INTERRUPTED[0]}", file=sys.stderr)
    sys.exit(INTERRUPTED[1])


def main() -> None:
    """Console-script entry point."""
    try:
        from magrun.cli import main as run
    except KeyboardInterrupt:
        interrupted()
    run()


if __name__ == "__main__":  # python -m magrun.console, as the console script
    main()
