"""``magrun bench sigkill``: what a recording keeps when its process is killed."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from magrun.bench.machine import machine
from magrun.recordings.recover import MCAP_MAGIC


def _wait_for_footer(path: Any, timeout: float) -> None:
    """Until ``path`` ends with MCAP's closing magic (its writer finished it) or ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(path, "rb") as fh:
                fh.seek(-len(MCAP_MAGIC), 2)
                if fh.read() == MCAP_MAGIC:
                    return
        except OSError:
            pass
        time.sleep(0.05)


def bench_sigkill(
    kills: int = 20,
    dt: float = 1 / 25.5,
    window: tuple[float, float] = (1.0, 6.0),
    seed: int = 0,
    writer: str = "thread",
) -> dict[str, Any]:
    """Kill a recording process with SIGKILL at random moments and recover each file.

    Each run starts a process that records ticks of ``dt`` s at real-time pace (one chunk
    per second of trial time) with the ``writer`` (``thread``: in that process, so the kill
    takes the writer too; ``process``: the writer is a child process, which survives the
    kill of the loop's process and finishes the file), kills it after a uniformly random
    time in ``window`` s, then recovers the file (:func:`magrun.recordings.recover.recover`; for the
    process writer, once the writer has finished it, at most 10 s). Lost = ticks handed to
    the recorder (printed by the child before it died) minus ticks recovered, in ticks and
    in seconds of trial time; ``complete``: the file had its footer (no recovery needed).
    """
    import signal
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from magrun.recordings.recover import recover

    rng = np.random.default_rng(seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="magrun-sigkill-") as tmp:
        for i in range(kills):
            base = Path(tmp) / f"kill-{i}"
            child = subprocess.Popen(
                [sys.executable, "-m", "magrun.bench.recording_child", str(dt), str(base), writer],
                stdout=subprocess.PIPE,
                text=True,
            )
            assert child.stdout is not None
            first = child.stdout.readline()  # imports done, recording
            wait = float(rng.uniform(*window))
            time.sleep(wait)
            child.send_signal(signal.SIGKILL)
            printed = [first, *child.stdout.read().split()]
            child.stdout.close()
            child.wait()
            handed = max(int(x) for x in printed if x.strip()) + 1
            if writer == "process":
                _wait_for_footer(base.with_suffix(".mcap"), timeout=10.0)
            report = recover(base.with_suffix(".mcap"), base.with_name(base.name + "-r.mcap"))
            got = report.per_topic.get("/robot/pose/desired", 0)
            rows.append(
                {
                    "killed_after_s": wait,
                    "ticks_logged": handed,
                    "ticks_recovered": got,
                    "ticks_lost": handed - got,
                    "trial_s_lost": (handed - got) * dt,
                    "messages_recovered": report.messages,
                    "bytes_lost": report.bytes_lost,
                    "complete": report.complete,
                }
            )
    lost = np.array([r["trial_s_lost"] for r in rows])
    return {
        "benchmark": "sigkill",
        "machine": machine(),
        "writer": writer,
        "kills": kills,
        "tick_s": dt,
        "flush_s": 1.0,
        "max_trial_s_lost": float(lost.max()),
        "median_trial_s_lost": float(np.median(lost)),
        "max_ticks_lost": int(max(r["ticks_lost"] for r in rows)),
        "complete_files": sum(bool(r["complete"]) for r in rows),
        "runs": rows,
    }


def summary(result: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    return [
        f"{result['kills']} kills ({result['writer']} writer): trial time lost max"
        f" {result['max_trial_s_lost']:.3f} s, median {result['median_trial_s_lost']:.3f} s"
        f" (chunks closed every {result['flush_s']} s); {result['complete_files']} files"
        " finished with their footer"
    ]
