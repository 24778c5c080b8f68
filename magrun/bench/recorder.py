"""``magrun bench recorder``: camera frames into MCAP, and what logging adds to a tick."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from magrun.bench.machine import machine, ms


def _camera_frames(width: int, height: int, n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` 8-bit mono frames like a fluoroscope's: smooth shading, a dark body, sensor noise."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    base = 140 + 40 * np.sin(u / width * 3.1) * np.cos(v / height * 2.3)
    frames = []
    for k in range(n):
        img = base.copy()
        cx, cy = width * (0.3 + 0.4 * k / n), height / 2
        img[(u - cx) ** 2 / 900 + (v - cy) ** 2 / 100 < 1] = 40
        img += rng.normal(0, 4, img.shape).astype(np.float32)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    return frames


#: the recorder's writers `bench recorder` compares
WRITERS = ("thread", "process")

#: ticks each writer buffers in `bench recorder` (the thread's queue, the process's ring):
#: the same for both, and the recorders' default
QUEUE = 256


def bench_recorder(
    seconds: float = 5.0,
    fps: float = 200.0,
    width: int = 1280,
    height: int = 1024,
    out_dir: str | None = None,
    compression: str = "none",
    ticks: int = 1000,
    writers: tuple[str, ...] = WRITERS,
    pinned: bool = True,
) -> dict[str, Any]:
    """Camera frames into MCAP at ``fps``, interleaved with poses and currents, and the cost
    of logging to the control tick, for each writer (``thread``: the writer on a thread of
    the loop's process, :class:`~magrun.recordings.writer.TrialRecorder`; ``process``: in a child
    process, :class:`~magrun.recordings.process.ProcessRecorder`).

    Phase 1 (throughput), per writer: a producer paced at ``fps`` hands the recorder a tick
    per frame (a raw ``width`` × ``height`` mono8 frame, six poses, eight currents, a status)
    for ``seconds``; the figures are frames written and dropped, the writer's sustained rate
    (frames over the time until the file is finished) and MB/s. The .rrd gets every 20th frame.

    Phase 2 (tick cost): the same control tick — one proposed-NMPC solve on a fixed problem —
    runs ``ticks`` times at ``fps`` without logging and ``ticks`` times logging each tick
    (frames as in phase 1) to each writer, the conditions alternating in blocks of a tenth so
    that a change in the machine's load meets all of them, each block starting once every
    writer has written its backlog; the figures are the p50 and p99 tick times of each and
    their difference to the bare ticks'.

    With ``pinned`` (and two cores or more) each writer is also measured as ``magrun run
    --rig hardware`` places it (:mod:`magrun.realtime`): ``<writer>_pinned``, the writer on
    the cores after the first and the loop's thread on the first, at real-time priority where
    the system permits it, against bare ticks with the loop placed the same way
    (``bare_pinned``); ``loop_scheduling`` says what the pinned loop got.
    """
    import tempfile
    from pathlib import Path

    from magrun.control.methods import make_controller
    from magrun.realtime import cpu_split, describe_scheduling, loop_placement
    from magrun.recordings.process import ProcessRecorder
    from magrun.recordings.writer import RecordingSetup, TrialRecorder
    from magrun.records import ControllerStatus, Tick

    frames = _camera_frames(width, height, 8)
    names = tuple(f"coil{i}" for i in range(8))
    status = ControllerStatus(0.0015, 1, True, "", "0")

    def tick(k: int) -> Tick:
        pose = np.array([1e-3 * math.sin(k / 50), 1e-3 * math.cos(k / 50), k / 1000])
        return Tick(
            k=k, t=k / fps, actual=pose, tracked=pose, measured=pose, estimated=pose,
            predicted=pose, desired=pose, currents=np.full(8, 0.1 * (k % 7)), status=status,
            compute_time=0.0015, frame=frames[k % len(frames)],
        )  # fmt: skip

    cores = cpu_split()
    variants = list(writers)
    if pinned and cores is not None:
        variants += [f"{w}_pinned" for w in writers]

    def recorder(variant: str, base: Path) -> Any:
        writer, _, pin = variant.partition("_")
        cpus = cores[1] if pin and cores is not None else None
        setup = RecordingSetup(
            trial={"protocol": "bench", "method": "none"},
            channel_names=names,
            image_format="raw",
            rerun_image_every=20,
            compression=compression,
        )
        if writer == "thread":
            return TrialRecorder(base, setup, queue_size=QUEUE, writer_cpus=cpus).start()
        return ProcessRecorder(
            base, setup, slots=QUEUE, frame_bytes=width * height, writer_cpus=cpus
        ).start()

    def placed(variant: str) -> Any:
        """The loop as a variant's blocks run it (the pinned ones: as on a rig)."""
        if variant.endswith("_pinned") and cores is not None:
            return loop_placement(cores[0])
        return contextlib.nullcontext()

    out: dict[str, Any] = {
        "benchmark": "recorder",
        "machine": machine(),
        "frame": f"{width}x{height} mono8 (foxglove.RawImage)",
        "target_fps": fps,
        "seconds": seconds,
        "compression": compression,
        "throughput": {},
    }
    with tempfile.TemporaryDirectory(dir=out_dir, prefix="magrun-bench-") as tmp:
        # phase 1: sustained throughput
        n = int(seconds * fps)
        for writer in variants:
            rec = recorder(writer, Path(tmp) / f"throughput-{writer}")
            with placed(writer):
                start = time.perf_counter()
                for k in range(n):
                    delay = start + k / fps - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    rec.log(tick(k))
                produced = time.perf_counter() - start
                stats = rec.close()
                finished = time.perf_counter() - start
            size = rec.mcap_path.stat().st_size
            out["throughput"][writer] = {
                "frames_offered": n,
                "frames_written": stats.images,
                "ticks_dropped": stats.dropped_ticks,
                "producer_s": produced,
                "finished_s": finished,
                "sustained_fps": stats.images / finished,
                "mcap_mb": size / 1e6,
                "mcap_mb_per_s": size / 1e6 / finished,
                "error": stats.error,
            }
        # phase 2: what logging adds to a control tick
        controller = make_controller("proposed")
        ref = np.zeros((21, 3))
        ref[:, 0] = np.linspace(0, 2e-3, 21)
        controller.reset(np.zeros(3))

        def control_tick() -> None:
            controller.step(np.zeros(3), ref)

        period = 1.0 / fps

        def timed(log: Callable[[Tick], None] | None, n: int, k0: int) -> list[float]:
            times = []
            begin = time.perf_counter()
            for k in range(n):
                delay = begin + k * period - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                t0 = time.perf_counter()
                control_tick()
                if log is not None:
                    log(tick(k0 + k))
                times.append(time.perf_counter() - t0)
            return times

        timed(None, min(50, ticks), 0)  # warm up
        block = max(ticks // 10, 1)
        bares = ["bare"] + (["bare_pinned"] if len(variants) > len(writers) else [])
        times: dict[str, list[float]] = {v: [] for v in bares + variants}
        live = {w: recorder(w, Path(tmp) / f"tick_cost-{w}") for w in variants}
        while len(times["bare"]) < ticks:
            n = min(block, ticks - len(times["bare"]))
            for v in times:
                rec = live.get(v)
                with placed(v):
                    times[v] += timed(rec.log if rec is not None else None, n, len(times[v]))
                    if v == "bare_pinned":
                        out["loop_scheduling"] = describe_scheduling()
                # the next block starts once every writer is idle: a writer still busy
                # with this block's frames would load the next condition's ticks
                idle_by = time.monotonic() + 30.0
                while any(r.backlog() > 0 for r in live.values()):
                    if time.monotonic() > idle_by:
                        raise RuntimeError("a recorder did not write its backlog in 30 s")
                    time.sleep(0.01)
                time.sleep(0.05)
        bare = {v: np.array(times[v]) for v in bares}
        cost: dict[str, Any] = {"ticks": len(bare["bare"]), "rate_hz": fps}
        for v, t in bare.items():
            cost[f"p50_{v}_ms"], cost[f"p99_{v}_ms"] = ms(t, 50), ms(t, 99)
        for w, rec in live.items():
            stats = rec.close()
            logged = np.array(times[w])
            reference = bare["bare_pinned" if w.endswith("_pinned") else "bare"]
            cost[w] = {
                "p50_logging_ms": ms(logged, 50),
                "p99_logging_ms": ms(logged, 99),
                "p50_added_ms": ms(logged, 50) - ms(reference, 50),
                "p99_added_ms": ms(logged, 99) - ms(reference, 99),
                "ticks_dropped": stats.dropped_ticks,
            }
        out["tick_cost"] = cost
    return out


def summary(out: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    c = out["tick_cost"]
    lines = [f"tick cost: p99 {c['p99_bare_ms']:.2f} ms bare"]
    if "p99_bare_pinned_ms" in c:
        lines.append(
            f"tick cost: p99 {c['p99_bare_pinned_ms']:.2f} ms bare, loop placed as on a rig"
            f" ({out['loop_scheduling']})"
        )
    for writer, t in out["throughput"].items():
        w = c[writer]
        lines.append(
            f"{writer} writer: {t['frames_written']}/{t['frames_offered']} frames of"
            f" {out['frame']}, {t['ticks_dropped']} dropped, {t['sustained_fps']:.0f} fps"
            f" sustained, {t['mcap_mb_per_s']:.0f} MB/s; p99 {w['p99_logging_ms']:.2f} ms"
            f" logging (+{w['p99_added_ms']:.2f} ms)"
        )
    return lines
