"""A trial recorder whose writer runs in its own process: logging costs the loop a copy.

:class:`~magrun.recordings.writer.TrialRecorder` writes on a thread of the control loop's
process. Its Python work (protobuf, MCAP chunking, Rerun's Arrow conversion) holds the GIL in
slices, and a control tick that needs the GIL meanwhile waits: at 200 fps of 1280 × 1024
frames that added 1–3 ms to the p99 tick time (BENCHMARKS.md, "Recorder").
:class:`ProcessRecorder` has the same interface (``start``, ``log``, ``close``, ``stats``,
the two paths) and moves the writer, unchanged, into a child process::

    loop process                                   writer process
    log(tick) ─► ring slot (shared memory):          ┌─► TrialRecorder (its thread writes
                 pickled tick + frame bytes ─ sem ───┘    MCAP and .rrd as in-process)
                 full ring: drop and count

``log`` pickles the tick without its frame (a few µs), copies the frame into the slot and
releases a semaphore; it never blocks and never waits for the writer. Slots are reused once
the writer has taken their content (a shared ``taken`` counter). A full ring drops the tick
and counts it, as the thread recorder's full queue does.

On a clock (not ``wait_when_full``) the writer process runs at a lower priority (nice
:data:`~magrun.realtime.WRITER_NICE`, inherited by its threads), so that on a busy machine
the scheduler runs the control loop first.

The writer ignores SIGINT and SIGTERM (the loop's process handles those and closes the
recording). If the loop's process dies (SIGKILL, a crash), the writer sees its control pipe
close, writes what it has, and finishes both files with status ``"interrupted"``: nothing is
lost that reached the ring.

The child is started with the ``forkserver`` method, the server preloading what a writer
imports (:data:`PRELOAD`), so that after the first trial in a process a recorder starts in
milliseconds (60 ms here, against 1 s with the writer's module alone).
"""

from __future__ import annotations

import contextlib
import mmap
import multiprocessing as mp
import pickle
import signal
from collections.abc import Iterable
from dataclasses import replace
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np

from magrun.realtime import lower_priority, pin_thread
from magrun.recordings.writer import Recorder, RecorderStats, RecordingSetup, TrialRecorder
from magrun.records import Tick

#: modules the forkserver imports once for every writer it forks: the writer, and what its
#: first Rerun recording imports (Rerun's blueprint API; pandas, which pyarrow imports on its
#: first array conversion). Importing them takes about a second, each writer otherwise again.
PRELOAD = (
    "magrun.recordings.writer", "rerun", "rerun.blueprint",
    "pandas", "pyarrow.pandas_compat", "pyarrow.vendored.version",
)  # fmt: skip
#: bytes of each slot kept for the pickled tick (a tick without its frame is ~2 KB)
META_BYTES = 16 << 10
_HEADER = 16  # int64 pickle length, int64 frame length (-1: a stop entry)


class ProcessRecorder(Recorder):
    """Writes one trial to ``<base>.mcap`` and ``<base>.rrd`` from a child process.

    Parameters
    ----------
    base, setup, flush_s
        As :class:`~magrun.recordings.writer.TrialRecorder`'s.
    slots : int
        Ticks the ring holds (default 256, as the thread writer's queue: 1.3 s at 200 fps;
        336 MB of shared memory with 1280 × 1024 mono8 frames, touched when it opens).
    start_timeout : float
        Seconds to wait for the writer to open its files.
    wait_when_full : bool
        Wait for a free slot instead of dropping the tick (a simulation, where no clock
        runs; never on a rig). The writer then keeps the loop's priority (otherwise nice
        :data:`~magrun.realtime.WRITER_NICE`).
    frame_bytes : int, optional
        The camera frames' size in bytes, if known: the ring is then allocated in
        :meth:`start` rather than on the first frame (its first ``log`` otherwise takes
        ~20–40 ms with 1280 × 1024 frames; a larger frame is dropped and counted).
    writer_cpus : iterable of int, optional
        Restrict the writer process (all its threads) to these CPUs (:mod:`magrun.realtime`).
    """

    def __init__(
        self,
        base: str | Path,
        setup: RecordingSetup,
        slots: int = 256,
        flush_s: float = 1.0,
        start_timeout: float = 60.0,
        wait_when_full: bool = False,
        frame_bytes: int | None = None,
        writer_cpus: Iterable[int] | None = None,
    ) -> None:
        super().__init__(base, setup, writer_cpus)
        self.frame_bytes = frame_bytes
        self.slots = slots
        self.flush_s = flush_s
        self.start_timeout = start_timeout
        self.wait_when_full = wait_when_full
        self._proc: Any = None
        self._ring: SharedMemory | None = None
        self._counters: SharedMemory | None = None

    # ---- lifecycle ---------------------------------------------------------------------

    def start(self) -> ProcessRecorder:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(list(PRELOAD))
        self._counters = SharedMemory(create=True, size=16)
        # [entries taken from the ring, ticks written]: written by the writer
        self._taken = np.ndarray((2,), np.int64, self._counters.buf)
        self._taken[:] = 0
        self._head = 0  # entries written; only this process changes it
        self._items = ctx.Semaphore(0)
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_writer_main,
            args=(
                child,
                self._items,
                self._counters.name,
                self.base,
                self.setup,
                self.flush_s,
                self.writer_cpus,
                self.wait_when_full,
            ),
            name=f"recorder {self.base.name}",
            daemon=True,
        )
        self._proc.start()
        child.close()
        if not self._conn.poll(self.start_timeout):
            self._abandon()
            raise RuntimeError(f"the recorder process for {self.base} did not start")
        try:
            reply = self._conn.recv()
        except EOFError:  # it died before it could answer
            reply = f"the process exited (code {self._proc.exitcode})"
        if reply != "ready":
            self._abandon()
            raise RuntimeError(f"the recorder process could not open {self.base}: {reply}")
        if self.frame_bytes is not None:
            self._open_ring(self.frame_bytes)
        return self

    def log(self, tick: Tick) -> None:
        """Hand a tick to the writer; never blocks (a full ring drops and counts it)."""
        self.stats.ticks_logged += 1
        frame = tick.frame
        if frame is None:
            meta = pickle.dumps((tick, None, None), protocol=5)
        else:
            meta = pickle.dumps((replace(tick, frame=None), frame.shape, frame.dtype.str), 5)
        nbytes = 0 if frame is None else frame.nbytes
        if self._ring is None:
            self._open_ring(nbytes)
        if self.wait_when_full:
            self._wait_for_slot()
        if (
            self._head - int(self._taken[0]) >= self.slots
            or len(meta) > META_BYTES
            or nbytes > self._frame_bytes
        ):
            self.stats.dropped_ticks += 1
            return
        self._put(meta, frame)

    def backlog(self) -> int:
        """Ticks in the ring or in the writer's hands, not yet written (as of the writer's
        last report, at most ~20 ms old)."""
        if self._proc is None:
            return 0
        return self._head - int(self._taken[1])

    def close(self, status: str = "ok", reason: str = "") -> RecorderStats:
        """Let the writer write what is in the ring and finish both files; its statistics.
        ``status`` and ``reason`` as :meth:`TrialRecorder.close`'s."""
        if self._proc is None:
            return self.stats
        if self._ring is None:
            self._open_ring(0)
        self._wait_for_slot()  # room for the stop entry
        stop = pickle.dumps((status, reason))
        self._put(stop, None, stop_entry=True)
        written: RecorderStats | None = None
        if self._conn.poll(self.start_timeout + 60.0):
            try:
                written = self._conn.recv()
            except EOFError:
                written = None
        self._proc.join(10.0)
        self._abandon()
        if written is None:
            self.stats.error = self.stats.error or "the recorder process ended without a report"
        else:
            self.stats.ticks_written = written.ticks_written
            self.stats.images = written.images
            self.stats.dropped_ticks += written.dropped_ticks
            self.stats.error = written.error
            self.stats.live_view_error = written.live_view_error
        self.status = status if not self.stats.error else "failed"
        return self.stats

    # ---- the ring ----------------------------------------------------------------------

    def _wait_for_slot(self) -> None:
        """Until the writer has taken an entry (or is gone)."""
        while self._head - int(self._taken[0]) >= self.slots and self._proc.is_alive():
            self._proc.join(0.0005)

    def _open_ring(self, frame_bytes: int) -> None:
        self._frame_bytes = frame_bytes
        self._slot_bytes = _HEADER + META_BYTES + frame_bytes
        self._ring = SharedMemory(create=True, size=self.slots * self._slot_bytes)
        # touch every page now: otherwise each slot's first use page-faults its ~300 pages
        # (a 1.3 MB frame) inside a control tick
        assert self._ring.buf is not None
        np.frombuffer(self._ring.buf, np.uint8)[:: mmap.PAGESIZE] = 0
        self._conn.send(("ring", self._ring.name, self.slots, frame_bytes))

    def _put(self, meta: bytes, frame: np.ndarray | None, stop_entry: bool = False) -> None:
        assert self._ring is not None
        off = (self._head % self.slots) * self._slot_bytes
        buf = self._ring.buf
        assert buf is not None
        n_frame = -1 if stop_entry else (0 if frame is None else frame.nbytes)
        header = np.ndarray((2,), np.int64, buf, off)
        header[:] = (len(meta), n_frame)
        buf[off + _HEADER : off + _HEADER + len(meta)] = meta
        if frame is not None:
            start = off + _HEADER + META_BYTES
            dst = np.ndarray(frame.shape, frame.dtype, buf, start)
            np.copyto(dst, frame)
        self._head += 1
        self._items.release()

    def _abandon(self) -> None:
        """Release the shared memory and the pipe (after the writer is done or gone)."""
        if self._proc is not None and self._proc.is_alive():
            self._proc.join(1.0)
            if self._proc.is_alive():
                self._proc.kill()
        self._proc = None
        self._conn.close()
        self._taken = np.zeros(2, np.int64)  # drop the view before closing its memory
        for shm in (self._ring, self._counters):
            if shm is not None:
                shm.close()
                shm.unlink()
        self._ring = self._counters = None


def _writer_main(
    conn: Connection,
    items: Any,
    counters_name: str,
    base: Path,
    setup: RecordingSetup,
    flush_s: float,
    writer_cpus: frozenset[int] | None,
    loop_waits: bool,
) -> None:
    """The writer process: ring entries → a thread-mode TrialRecorder, until a stop entry."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the loop's process closes the recording
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if not loop_waits:  # on a clock: below the loop (this process's threads inherit it)
        lower_priority()
    pin_thread(writer_cpus)
    counters = SharedMemory(name=counters_name)
    taken = np.ndarray((2,), np.int64, counters.buf)
    try:
        rec = TrialRecorder(
            base, setup, queue_size=1 << 30, flush_s=flush_s, wait_when_full=loop_waits
        ).start()
    except Exception as exc:
        conn.send(f"{type(exc).__name__}: {exc}")
        return
    conn.send("ready")
    ring: list[Any] = []  # [SharedMemory, slots, slot bytes] once the loop has sent them
    status, reason = "interrupted", "the loop's process ended without closing the recording"

    def control() -> bool:
        """Take the loop's messages; False when its end of the pipe is closed (it died)."""
        try:
            while conn.poll():
                _, name, slots, frame_bytes = conn.recv()
                ring[:] = [SharedMemory(name=name), slots, _HEADER + META_BYTES + frame_bytes]
            return True
        except (EOFError, OSError):
            return False

    while True:
        taken[1] = rec.stats.ticks_written  # for backlog(): at most one wait (20 ms) old
        if not items.acquire(timeout=0.02):
            if not control():
                break  # the loop's process died: finish what we have
            continue
        if not ring:
            control()  # the ring is announced before the first entry
        shm, slots, slot_bytes = ring
        off = (int(taken[0]) % slots) * slot_bytes
        n_meta, n_frame = (int(v) for v in np.ndarray((2,), np.int64, shm.buf, off))
        payload = pickle.loads(shm.buf[off + _HEADER : off + _HEADER + n_meta])
        if n_frame < 0:
            status, reason = payload
            taken[0] += 1
            break
        tick, shape, dtype = payload
        if shape is not None:
            start = off + _HEADER + META_BYTES
            frame = np.frombuffer(shm.buf[start : start + n_frame], np.dtype(dtype)).copy()
            tick = replace(tick, frame=frame.reshape(shape))
        taken[0] += 1
        rec._queue.put(tick)  # blocking: the ring, not this queue, is where ticks drop
        rec.stats.ticks_logged += 1
    stats = rec.close(status, reason)
    del taken
    for mem in (counters, *ring[:1]):
        with contextlib.suppress(BufferError):  # a view still alive: the process exits anyway
            mem.close()
    with contextlib.suppress(BrokenPipeError, OSError):  # nobody may be listening any more
        conn.send(stats)
