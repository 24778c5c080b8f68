"""The recording process ``magrun bench sigkill`` kills: it logs synthetic ticks at a trial's
pace and prints each tick's index once the recorder has it.

    python -m magrun.bench.recording_child DT BASE WRITER     # WRITER: thread or process
"""

from __future__ import annotations

import sys
import time

import numpy as np

from magrun.recordings.process import ProcessRecorder
from magrun.recordings.writer import RecordingSetup, TrialRecorder
from magrun.records import ControllerStatus, Tick


def record_until_killed(dt: float, base: str, writer: str) -> None:
    """Log ticks of ``dt`` s in real time to ``base``.mcap, forever."""
    setup = RecordingSetup(trial={"method": "bench"}, channel_names=tuple("abcdefgh"))
    cls = ProcessRecorder if writer == "process" else TrialRecorder
    rec = cls(base, setup, flush_s=1.0).start()
    status = ControllerStatus(0.001, 1, True, "", "0")
    start = time.perf_counter()
    k = 0
    while True:
        p = np.array([1e-4 * k, 0.0, 0.0])
        rec.log(
            Tick(
                k=k, t=k * dt, actual=p, tracked=p, measured=p if k % 8 == 0 else None,
                estimated=p, predicted=p, desired=p, currents=np.zeros(8), status=status,
                compute_time=0.001,
            )
        )  # fmt: skip
        print(k, flush=True)
        k += 1
        time.sleep(max(0.0, start + k * dt - time.perf_counter()))


if __name__ == "__main__":
    record_until_killed(float(sys.argv[1]), sys.argv[2], sys.argv[3])
