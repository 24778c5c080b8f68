"""``python -m magrun.cli``: the ``magrun`` command."""

from magrun.cli import main

main()
