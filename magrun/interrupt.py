"""SIGINT and SIGTERM end a run cleanly instead of killing it mid-write.

A handler installed by :func:`handling` only records the first signal; the trial loop asks
:func:`requested` at every tick and, when set, commands zero currents, ends the trial and
lets its recorder finish and index both files. The runner then starts no further trial,
marks the interrupted one in the manifest, and ``magrun run`` exits with 128 + the signal
number (130 for SIGINT, 143 for SIGTERM). ``magrun run --resume`` runs what is left.

    >>> with handling():                       # doctest: +SKIP
    ...     run_protocol(...)
    >>> requested()                            # None, or signal.SIGINT / signal.SIGTERM
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from types import FrameType
from typing import Any, NoReturn

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_requested: int | None = None


def requested() -> int | None:
    """The first stop signal received (``signal.SIGINT`` / ``SIGTERM``), or None."""
    return _requested


def request(signum: int) -> None:
    """Ask the run to stop as if ``signum`` had arrived (the first request wins)."""
    global _requested
    if _requested is None:
        _requested = int(signum)


def clear() -> None:
    """Forget a request (a new run in the same process)."""
    global _requested
    _requested = None


def exit_interrupted(signum: int = signal.SIGINT) -> NoReturn:
    """End the process as a Ctrl-C outside a run does: one line on stderr, exit status
    128 + ``signum`` (130 for SIGINT).

    Call it after the ``except KeyboardInterrupt`` block, not inside it, so that the frames the
    exception held are freed (and any file they had open closed) first. The exit runs
    Python's exit functions (``atexit``: worker pools, logging) and flushes stdout and stderr,
    then leaves with ``os._exit``: CPython 3.11 takes a KeyboardInterrupt that escaped code
    run by ``exec`` of a string (dataclasses build their methods that way, while modules
    import) for an unhandled one even when it was caught, and its normal exit would then kill
    the process with SIGINT instead of returning 130.
    """
    import atexit
    import gc
    import os
    import sys

    print("\ninterrupted", file=sys.stderr)
    gc.collect()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with suppress(OSError, ValueError):  # a closed pipe: nothing left to say
            stream.flush()
    os._exit(exit_status(signum))


@contextmanager
def remembering_ctrl_c() -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt as usual while the block runs, and is remembered
    (:func:`requested`) too: a KeyboardInterrupt raised inside a weakref callback or a
    ``__del__`` (the import system has both) is printed as "Exception ignored" and lost,
    and the caller should still stop (main thread only; elsewhere this installs nothing)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        request(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def exit_status(signum: int) -> int:
    """The shell's convention for a process ended by ``signum``: 128 + its number."""
    return 128 + int(signum)


@contextmanager
def handling(on_signal: Callable[[int], None] | None = None) -> Iterator[None]:
    """Record SIGINT / SIGTERM instead of dying while the block runs (main thread only).

    ``on_signal(signum)`` is called too (e.g. to pass the signal on to worker processes).
    Elsewhere than the main thread this installs nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        request(signum)
        if on_signal is not None:
            on_signal(signum)

    previous: dict[int, Any] = {s: signal.signal(s, handler) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def install_in_worker() -> None:
    """A worker process records stop signals for the rest of its life (its trial ends cleanly)."""
    for s in SIGNALS:
        signal.signal(s, lambda signum, frame: request(signum))
