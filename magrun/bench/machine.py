"""What every benchmark shares: the machine's description, one pinned core, percentiles, a
folder's size."""

from __future__ import annotations

import os
import platform
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    import casadi

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return {
        "cpu": cpu,
        "logical_cores": os.cpu_count(),
        "python": platform.python_version(),
        "casadi": casadi.CasadiMeta.version(),
        "platform": platform.platform(),
    }


@contextmanager
def one_core() -> Iterator[int | None]:
    """Pin this process to one core (Linux) for the duration; yields the core or None."""
    if not hasattr(os, "sched_getaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    core = max(before)
    os.sched_setaffinity(0, {core})
    try:
        yield core
    finally:
        os.sched_setaffinity(0, before)


def ms(values: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of ``values`` (s), in ms."""
    return float(np.percentile(values, q) * 1e3)


def folder_bytes(folder: Path) -> int:
    """The size of every file under ``folder`` (a protocol's recordings), bytes."""
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
