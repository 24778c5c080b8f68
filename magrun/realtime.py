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
  simulated campaign does not, its workers share every core);
- :func:`realtime_priority`: the loop's thread under ``SCHED_FIFO`` (priority
  :data:`LOOP_RTPRIO`), so that nothing of normal priority on its core — the kernel's
  write-back threads flushing the recording, other programs — preempts a tick (``magrun run
  --rig hardware`` asks for it; Linux grants it to root, to a process with ``CAP_SYS_NICE``, or
  to a user with an ``rtprio`` limit in /etc/security/limits.conf; otherwise the loop keeps
  the normal policy and the trial's manifest entry says so).

``magrun bench recorder`` measures what each costs the tick (BENCHMARKS.md, "Recorder").
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

#: the writer's nice value: under CPU contention the scheduler gives the control loop (nice 0)
#: ~10× the writer's share and preempts the writer when a tick wakes up; an idle core still
#: runs the writer at full speed. ``MAGRUN_WRITER_NICE`` overrides it (0: the loop's own)
WRITER_NICE = int(os.environ.get("MAGRUN_WRITER_NICE", "10"))


#: the control loop's ``SCHED_FIFO`` priority on a rig (1–99); ``MAGRUN_LOOP_RTPRIO`` overrides
#: it (0: the loop keeps the normal policy)
LOOP_RTPRIO = int(os.environ.get("MAGRUN_LOOP_RTPRIO", "50"))


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


#: (policy, priority) of a thread, as :func:`realtime_priority` returns and restores it
Scheduling = tuple[int, int]


def realtime_priority(priority: int | None = None) -> Scheduling | None:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (default
    :data:`LOOP_RTPRIO`). Threads and processes it starts afterwards get the normal policy
    (``SCHED_RESET_ON_FORK``): a helper that never blocks must not starve the loop on its core.
    Returns the previous scheduling, to restore with :func:`restore_scheduling`; None when
    nothing changed (priority 0, not Linux, or not permitted)."""
    priority = LOOP_RTPRIO if priority is None else priority
    if priority <= 0:
        return None
    try:
        before = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except (AttributeError, OSError):
        return None
    return before


def restore_scheduling(before: Scheduling | None) -> None:
    """Undo :func:`realtime_priority` (None: nothing to undo)."""
    if before is not None:
        os.sched_setscheduler(0, before[0], os.sched_param(before[1]))


def describe_scheduling() -> str:
    """The calling thread's policy, priority and CPUs, e.g. ``"SCHED_FIFO 50, CPUs 0"``."""
    try:
        policy = os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0)
        priority = os.sched_getparam(0).sched_priority
        cpus = ",".join(str(c) for c in sorted(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return "unknown"
    names = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_RR: "SCHED_RR"}
    return f"{names.get(policy, str(policy))} {priority}, CPUs {cpus}"


@contextmanager
def loop_placement(cpus: Iterable[int] | None, priority: int | None = None) -> Iterator[str]:
    """The calling thread, for the block, on ``cpus`` (None: unchanged) at real-time priority
    ``priority`` (:func:`realtime_priority`; default :data:`LOOP_RTPRIO`, 0 none); yields
    :func:`describe_scheduling`'s account of what it got. Restored on leaving."""
    cpus_before = pin_thread(cpus)
    sched_before = realtime_priority(priority)
    try:
        yield describe_scheduling()
    finally:
        restore_scheduling(sched_before)
        pin_thread(cpus_before)
