"""The recorder whose writer is a child process: same files, drops counted, survives its parent."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from test_recording import _rrd_rows

from magrun.realtime import (
    LOOP_RTPRIO,
    WRITER_NICE,
    cpu_split,
    describe_scheduling,
    loop_placement,
    pin_thread,
)
from magrun.recordings.process import ProcessRecorder
from magrun.recordings.writer import RecordingSetup, TrialRecorder
from magrun.records import ControllerStatus, Tick
from magrun.tracking.camera import Camera

STATUS = ControllerStatus(0.001, 1, True, "", "0")


def _ticks(n: int, frames: list[np.ndarray | None]) -> list[Tick]:
    out = []
    for k in range(n):
        pose = np.array([1e-3 * k, -1e-3 * k, 0.01 * k])
        out.append(
            Tick(
                k=k, t=k * 0.04, actual=pose, tracked=None if k % 5 == 4 else pose,
                measured=pose if k % 3 == 0 else None, estimated=pose, predicted=pose,
                desired=pose, currents=np.full(8, float(k)), status=STATUS,
                compute_time=0.002, frame=frames[k % len(frames)],
            )
        )  # fmt: skip
    return out


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with path.open("rb") as fh:
        reader = make_reader(fh)
        return [(ch.topic, m.log_time, m.data) for _, ch, m in reader.iter_messages()]


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with path.open("rb") as fh:
        return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}


def _setup(**kw) -> RecordingSetup:
    return RecordingSetup(trial={"method": "x"}, channel_names=tuple("abcdefgh"), **kw)


def test_process_writer_writes_what_the_thread_writer_writes(tmp_path: Path) -> None:
    """Every MCAP message identical (topic, time, bytes) for JPEG and raw frames, and the
    same .rrd rows, ticks without a frame among them."""
    rng = np.random.default_rng(3)
    rgb = [rng.integers(0, 256, (256, 256, 3), dtype=np.uint8) for _ in range(3)]
    for fmt, frames in (("jpeg", [*rgb, None]), ("raw", [rgb[0][..., 0], None])):
        setup = _setup(camera=Camera(), image_format=fmt)
        ticks = _ticks(70, frames)
        recs = []
        for name, cls in (("thread", TrialRecorder), ("process", ProcessRecorder)):
            with cls(tmp_path / f"{fmt}-{name}", setup) as rec:
                for tick in ticks:
                    rec.log(tick)
            assert rec.stats.error == ""
            assert rec.stats.dropped_ticks == 0
            assert rec.stats.ticks_written == rec.stats.ticks_logged == len(ticks)
            recs.append(rec)
        thread, proc = recs
        assert proc.stats.images == thread.stats.images > 0
        assert _messages(proc.mcap_path) == _messages(thread.mcap_path)
        assert _metadata(proc.mcap_path)["recorder"] == _metadata(thread.mcap_path)["recorder"]
        assert _rrd_rows(proc.rrd_path) == _rrd_rows(thread.rrd_path)


def test_full_ring_and_oversized_frames_are_dropped_and_counted(tmp_path: Path) -> None:
    frame = np.zeros((32, 32), np.uint8)
    rec = ProcessRecorder(tmp_path / "t", _setup(image_format="raw"), slots=4).start()
    ticks = _ticks(10, [frame])
    os.kill(rec._proc.pid, signal.SIGSTOP)  # the writer takes nothing while stopped
    try:
        for tick in ticks[:7]:
            rec.log(tick)
        assert rec.backlog() == 4  # the ring's four, none written
    finally:
        os.kill(rec._proc.pid, signal.SIGCONT)
    rec.log(_ticks(1, [np.zeros((33, 32), np.uint8)])[0])  # larger than the ring's frames
    deadline = time.monotonic() + 10.0
    while rec.backlog() > 0:  # the writer catches up, and says so
        assert time.monotonic() < deadline, f"backlog stuck at {rec.backlog()}"
        time.sleep(0.01)
    stats = rec.close()
    assert (stats.ticks_logged, stats.dropped_ticks, stats.ticks_written) == (8, 4, 4)
    assert _metadata(rec.mcap_path)["recorder"]["ticks_written"] == "4"


def test_writer_ignores_sigint_and_sigterm(tmp_path: Path) -> None:
    """Ctrl-C reaches the whole process group: the loop's process, not the writer, decides."""
    rec = ProcessRecorder(tmp_path / "t", _setup()).start()
    for sig in (signal.SIGINT, signal.SIGTERM):
        os.kill(rec._proc.pid, sig)
    time.sleep(0.2)
    assert rec._proc.is_alive()
    for tick in _ticks(5, [None]):
        rec.log(tick)
    assert rec.close().ticks_written == 5


CHILD = """
import os, sys, numpy as np
sys.path.insert(0, "tests")
from test_recorder_process import _setup, _ticks
from magrun.recordings.process import ProcessRecorder
rec = ProcessRecorder(sys.argv[1], _setup(image_format="raw")).start()
for tick in _ticks(40, [np.full((64, 64), 7, np.uint8)]):
    rec.log(tick)
print(rec._proc.pid, flush=True)
os.kill(os.getpid(), 9)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread nice is Linux's")
def test_writers_run_below_the_loops_priority(tmp_path: Path) -> None:
    """The process writer runs at nice WRITER_NICE, the thread writer's thread too, and the
    loop's own thread keeps its priority."""
    loop_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    rec = ProcessRecorder(tmp_path / "p", _setup()).start()
    try:
        assert os.getpriority(os.PRIO_PROCESS, rec._proc.pid) == max(WRITER_NICE, loop_nice)
    finally:
        rec.close()
    thread_rec = TrialRecorder(tmp_path / "t", _setup()).start()
    try:
        assert thread_rec._thread is not None
        tid = thread_rec._thread.native_id
        assert tid is not None
        deadline = time.monotonic() + 5.0
        while os.getpriority(os.PRIO_PROCESS, tid) != max(WRITER_NICE, loop_nice):
            assert time.monotonic() < deadline, "the writer thread kept the loop's priority"
            time.sleep(0.01)
    finally:
        thread_rec.close()
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == loop_nice


def test_simulation_writers_wait_instead_of_dropping_and_keep_the_loops_priority(
    tmp_path: Path,
) -> None:
    """wait_when_full (no clock): a 2-tick queue and a 4-slot ring take 40 ticks logged as
    fast as possible without a drop, and neither writer is put below the loop."""
    loop_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    frame = np.zeros((32, 32), np.uint8)
    thread_rec = TrialRecorder(
        tmp_path / "t", _setup(image_format="raw"), queue_size=2, wait_when_full=True
    ).start()
    assert thread_rec._thread is not None
    tid = thread_rec._thread.native_id
    assert tid is not None
    for tick in _ticks(40, [frame]):
        thread_rec.log(tick)
    assert os.getpriority(os.PRIO_PROCESS, tid) == loop_nice
    stats = thread_rec.close()
    assert (stats.ticks_logged, stats.dropped_ticks, stats.ticks_written) == (40, 0, 40)
    rec = ProcessRecorder(
        tmp_path / "p", _setup(image_format="raw"), slots=4, wait_when_full=True
    ).start()
    for tick in _ticks(40, [frame]):
        rec.log(tick)
    assert os.getpriority(os.PRIO_PROCESS, rec._proc.pid) == loop_nice
    stats = rec.close()
    assert (stats.ticks_logged, stats.dropped_ticks, stats.ticks_written) == (40, 0, 40)


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
    reason="needs CPU affinity and two cores",
)
def test_writers_keep_to_their_cpus_and_the_loop_to_its_own(tmp_path: Path) -> None:
    """cpu_split gives the loop one core and the writers the rest: the writer process (its
    every thread) and the writer thread run there, the loop's thread is pinned and restored."""
    split = cpu_split()
    assert split is not None
    loop_cpus, writer_cpus = split
    allowed = frozenset(os.sched_getaffinity(0))
    assert loop_cpus | writer_cpus == allowed
    assert not loop_cpus & writer_cpus

    rec = ProcessRecorder(tmp_path / "p", _setup(), writer_cpus=writer_cpus).start()
    try:
        pid = rec._proc.pid
        for tid in os.listdir(f"/proc/{pid}/task"):  # the writer's and Rerun's threads
            assert os.sched_getaffinity(int(tid)) == writer_cpus
    finally:
        rec.close()
    thread_rec = TrialRecorder(tmp_path / "t", _setup(), writer_cpus=writer_cpus).start()
    try:
        assert thread_rec._thread is not None
        assert thread_rec._thread.native_id is not None
        tid = thread_rec._thread.native_id
        deadline = time.monotonic() + 5.0
        while os.sched_getaffinity(tid) != writer_cpus:
            assert time.monotonic() < deadline, "the writer thread was not pinned"
            time.sleep(0.01)
    finally:
        thread_rec.close()
    before = pin_thread(loop_cpus)
    assert before == allowed
    assert os.sched_getaffinity(0) == loop_cpus
    pin_thread(before)
    assert os.sched_getaffinity(0) == allowed


def _fifo_permitted() -> bool:
    """Whether this process may use SCHED_FIFO (asked on a thread of its own)."""
    result: list[bool] = []

    def ask() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=ask)
    t.start()
    t.join()
    return result[0]


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="Linux scheduling API")
def test_loop_placement_pins_raises_and_restores() -> None:
    """Inside the block the thread is on the given CPUs and, where permitted, under SCHED_FIFO
    at LOOP_RTPRIO (the account it yields says which); on leaving both are as before.
    Priority 0 leaves the policy alone."""
    allowed = os.sched_getaffinity(0)
    first = frozenset(sorted(allowed)[:1])
    policy = os.sched_getscheduler(0)
    with loop_placement(first) as got:
        assert os.sched_getaffinity(0) == first
        if LOOP_RTPRIO > 0 and _fifo_permitted():
            assert os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK == os.SCHED_FIFO
            assert os.sched_getparam(0).sched_priority == LOOP_RTPRIO
            assert got == f"SCHED_FIFO {LOOP_RTPRIO}, CPUs {min(first)}"
            seen: list[int] = []  # a thread it starts gets the normal policy
            helper = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
            helper.start()
            helper.join()
            assert seen == [os.SCHED_OTHER]
        else:
            assert os.sched_getscheduler(0) == policy
            assert got.startswith("SCHED_OTHER 0")
    assert os.sched_getaffinity(0) == allowed
    assert os.sched_getscheduler(0) == policy
    with loop_placement(None, priority=0) as got:
        assert os.sched_getscheduler(0) == policy
        assert os.sched_getaffinity(0) == allowed
    assert got == describe_scheduling()


def test_writer_finishes_the_files_when_the_loop_process_is_killed(tmp_path: Path) -> None:
    """SIGKILL of the loop's process: the writer finishes both files, indexed, status
    "interrupted", every tick handed over before the kill written."""
    base = tmp_path / "killed"
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(base)],
        capture_output=True, text=True, timeout=120, cwd=Path(__file__).parents[1],
    )  # fmt: skip
    assert out.returncode == -signal.SIGKILL, out.stderr
    writer = int(out.stdout.split()[0])
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # the writer notices within 0.25 s, then finishes
        try:
            os.kill(writer, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    meta = _metadata(base.with_suffix(".mcap"))["recorder"]
    assert meta["status"] == "interrupted"
    assert meta["ticks_written"] == "40"
    assert base.with_suffix(".rrd").stat().st_size > 0


#: a writer as the forkserver forks it: PRELOAD imported, then one recording opened, written
#: (JPEG frames, every message kind) and finished; prints the modules that imported meanwhile
_WRITER_AFTER_PRELOAD = """
import importlib, sys
from pathlib import Path
import numpy as np
from magrun.recordings.process import PRELOAD
for name in PRELOAD:
    importlib.import_module(name)
from magrun.recordings.writer import RecordingSetup, TrialRecorder
from magrun.records import ControllerStatus, Tick
from magrun.tracking.camera import Camera
before = set(sys.modules)
setup = RecordingSetup(trial={"method": "x"}, channel_names=tuple("abcdefgh"), camera=Camera(),
                       image_format="jpeg", rerun_image_every=1)
with TrialRecorder(Path(sys.argv[1]), setup) as rec:
    pose = np.array([1e-3, -1e-3, 0.1])
    for k in range(3):
        rec.log(Tick(k=k, t=k * 0.04, actual=pose, tracked=pose, measured=pose, estimated=pose,
                     predicted=pose, desired=pose, currents=np.full(8, 1.0),
                     status=ControllerStatus(0.001, 1, True, "", "0"), compute_time=0.002,
                     frame=np.zeros((48, 64, 3), np.uint8)))
assert rec.stats.error == "" and rec.stats.ticks_written == 3
print(sorted(set(sys.modules) - before))
"""


def test_the_forkservers_preload_is_all_a_writer_imports(tmp_path: Path) -> None:
    """Every recorder process is forked from a server that imported PRELOAD: what a writer
    imports beyond it, each writer imports again (Rerun and pandas took a second a trial
    here, against 60 ms with them preloaded). A fresh interpreter that imports PRELOAD, then
    writes a recording, must import nothing more."""
    run = subprocess.run(
        [sys.executable, "-c", _WRITER_AFTER_PRELOAD, str(tmp_path / "t")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]", run.stdout[:1000]
