"""Where the control loop and the recorder's writer run: priorities and CPU affinity (Linux).

A control tick that shares a core with the writer (a thread, or a process with Rerun's
threads, compressing and writing ~260 MB/s at 200 fps of 1280 × 1024 frames) waits for it now
and then, which shows in the tick's p99. Two remedies, both per thread, both no-ops where the
platform lacks them:

- :func:`lower_priority`: the writer runs at nice :data:`WRITER_NICE`, so that under
  contention the scheduler serves the loop first (every writer on a clock does this; in
  simulation the loop waits for a full writer instead, and a low-priority writer would only
  slow the campaign down);
- :func:`cpu_split` and :func:`pin_thread`: the loop on one core, the writer on the others
  (``magrun run --rig hardware`` does this when the machine has two cores or more; the
  simulated campaign does not, its workers share every core).

``magrun bench recorder`` measures what each costs the tick (BENCHMARKS.md, "Recorder").
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable

#: the writer's nice value: under CPU contention the scheduler gives the control loop (nice 0)
#: ~10× the writer's share and preempts the writer when a tick wakes up; an idle core still
#: runs the writer at full speed. ``MAGRUN_WRITER_NICE`` overrides it (0: the loop's own)
WRITER_NICE = int(os.environ.get("MAGRUN_WRITER_NICE", "10"))


def lower_priority(nice: int | None = None) -> None:
    """Raise the calling thread's nice value to at least ``nice`` (default
    :data:`WRITER_NICE`). Threads it starts afterwards inherit it."""
    nice = WRITER_NICE if nice is None else nice
    try:
        tid = threading.get_native_id()
        if os.getpriority(os.PRIO_PROCESS, tid) < nice:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (AttributeError, OSError):  # not Linux, or not permitted: keep the priority
        pass


def cpu_split() -> tuple[frozenset[int], frozenset[int]] | None:
    """``(loop CPUs, writer CPUs)`` of this process's allowed CPUs: the loop on the first,
    the writer on the others; None with a single CPU or without affinity support."""
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except AttributeError:
        return None
    if len(cpus) < 2:
        return None
    return frozenset(cpus[:1]), frozenset(cpus[1:])


def pin_thread(cpus: Iterable[int] | None) -> frozenset[int] | None:
    """Restrict the calling thread (and the threads it starts later) to ``cpus``; returns its
    previous CPUs, to restore with another call (None: nothing changed)."""
    if cpus is None:
        return None
    try:
        before = frozenset(os.sched_getaffinity(0))
        os.sched_setaffinity(0, set(cpus))
    except (AttributeError, OSError):
        return None
    return before
