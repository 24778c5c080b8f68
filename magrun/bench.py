"""Benchmarks behind ``magrun bench``: each returns one JSON-ready dict of measured figures.

Every figure in a result comes from the same run on the same machine (described under
``machine``), so ratios between variants are side by side; timings on these shared machines
vary from run to run, ratios much less. Nothing here asserts a speed: the test suite checks
correctness, these functions measure.
"""

from __future__ import annotations

import contextlib
import math
import os
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np

#: NMPC variants: name → (method, solver)
NMPC_VARIANTS: dict[str, tuple[str, str]] = {
    "proposed": ("proposed", "rti"),
    "proposed_ipopt_reference": ("proposed", "ipopt"),
    "b5_lut": ("baseline5", "rti"),
    "b5_lut_ipopt": ("baseline5", "ipopt"),
}


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


def _ms(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q) * 1e3)


def bench_nmpc(
    ticks: int | None = None,
    variants: tuple[str, ...] = tuple(NMPC_VARIANTS),
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Per-solve times and closed-loop tracking of the NMPC variants on one core.

    Each variant runs the paper's S-trajectory (43 mm, 3 mm/s; the first ``ticks`` ticks, or
    all of it plus 1 s of hold) closed loop on the simulated rig with perfect feedback and no
    latency charged, so tracking differences come from the solver alone. Solve times are the
    planner's wall time per tick, the first (cold, iterated to convergence) excluded.
    """
    from magrun.control.methods import ControlConfig, make_controller
    from magrun.loop import run_trial
    from magrun.rigs.sim import SimRig
    from magrun.scene import s_trajectory

    unknown = set(variants) - set(NMPC_VARIANTS)
    if unknown:
        raise ValueError(f"unknown variants {sorted(unknown)}; known: {', '.join(NMPC_VARIANTS)}")
    reference = s_trajectory()
    base = ControlConfig()
    duration = None if ticks is None else (ticks - 1) * base.dt  # ticks at 0, dt, …
    out: dict[str, Any] = {
        "benchmark": "nmpc",
        "horizon": base.nmpc.horizon,
        "dt_s": base.dt,
        "coils": 8,
        "trajectory": "S, 43 mm, 3 mm/s, perfect feedback, no latency charged",
        "machine": machine(),
        "variants": {},
    }
    with one_core() as core:
        out["pinned_core"] = core
        for name in variants:
            method, solver = NMPC_VARIANTS[name]
            if progress is not None:
                progress(name)
            cfg = replace(base, nmpc=replace(base.nmpc, solver=solver))  # type: ignore[arg-type]
            t0 = time.perf_counter()
            controller = make_controller(method, "magnet", cfg)
            build = time.perf_counter() - t0
            log = run_trial(controller, SimRig.default(seed=0), reference, duration=duration)
            solve = log.solve_times[1:]
            out["variants"][name] = {
                "method": method,
                "model": "lookup_table" if method == "baseline5" else "zernike",
                "solver": "Gauss-Newton RTI + HPIPM" if solver == "rti" else "IPOPT (converged)",
                "build_s": build,
                "ticks": len(log.t),
                "median_ms": _ms(solve, 50),
                "p90_ms": _ms(solve, 90),
                "p99_ms": _ms(solve, 99),
                "max_ms": float(np.max(solve) * 1e3),
                "median_iterations": float(np.median([s.iterations for s in log.status[1:]])),
                "failed_solves": sum(not s.success for s in log.status),
                # RTI: QPs HPIPM's fast preset failed and the robust one solved
                "robust_retries": getattr(
                    getattr(controller.planner, "backend", None), "robust_retries", 0
                ),
                "achievable_rate_hz": float(1.0 / np.median(solve)),
                "rms_position_mm": log.rms_position_mm,
                "rms_orientation_deg": log.rms_orientation_deg,
            }
    v = out["variants"]
    if "proposed" in v and "proposed_ipopt_reference" in v:
        fast, ref = v["proposed"], v["proposed_ipopt_reference"]
        out["speedup_vs_ipopt"] = ref["median_ms"] / fast["median_ms"]
        out["p99_speedup_vs_ipopt"] = ref["p99_ms"] / fast["p99_ms"]
        out["rms_position_vs_ipopt"] = fast["rms_position_mm"] / ref["rms_position_mm"] - 1.0
    if "b5_lut" in v and "b5_lut_ipopt" in v:
        out["b5_speedup_vs_ipopt"] = v["b5_lut_ipopt"]["median_ms"] / v["b5_lut"]["median_ms"]
    return out


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
    the loop's process, :class:`~magrun.recording.TrialRecorder`; ``process``: in a child
    process, :class:`~magrun.recorder_process.ProcessRecorder`).

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
    from magrun.recorder_process import ProcessRecorder
    from magrun.recording import RecordingSetup, TrialRecorder
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
            cost[f"p50_{v}_ms"], cost[f"p99_{v}_ms"] = _ms(t, 50), _ms(t, 99)
        for w, rec in live.items():
            stats = rec.close()
            logged = np.array(times[w])
            reference = bare["bare_pinned" if w.endswith("_pinned") else "bare"]
            cost[w] = {
                "p50_logging_ms": _ms(logged, 50),
                "p99_logging_ms": _ms(logged, 99),
                "p50_added_ms": _ms(logged, 50) - _ms(reference, 50),
                "p99_added_ms": _ms(logged, 99) - _ms(reference, 99),
                "ticks_dropped": stats.dropped_ticks,
            }
        out["tick_cost"] = cost
    return out


def bench_campaign(
    protocol_files: list[str],
    out: str,
    jobs: int = 2,
    quick: bool = False,
    progress: Callable[[str], None] | None = None,
    feedback: str | None = None,
) -> dict[str, Any]:
    """Run the protocols, recordings written, their trials sharing one pool of ``jobs``
    processes (protocols with the fewest trials first, so that no worker idles at the end).

    Figures per protocol: trials, ``wall_s`` (from the campaign's start to the protocol's
    last trial done: protocols overlap), failed trials, dropped recorder ticks, control ticks
    that overran their period, ticks, and the recordings' size; in total the same, with the
    campaign's wall time and trials per minute. ``feedback`` "camera" or "truth" overrides
    every protocol's ``feedback.camera`` (None: as the files say).
    """
    import concurrent.futures as cf
    from pathlib import Path

    from magrun.protocol import load_protocol
    from magrun.runner import pool_executor, run_protocol, shared_pool

    if feedback not in (None, "camera", "truth"):
        raise ValueError(f"feedback must be camera or truth, got {feedback!r}")
    result: dict[str, Any] = {
        "benchmark": "campaign",
        "machine": machine(),
        "jobs": jobs,
        "quick": quick,
        "feedback": feedback or "as in the protocols",
        "protocols": {},
    }
    protocols = []
    for path in protocol_files:
        protocol = load_protocol(path)
        if feedback is not None:
            camera = feedback == "camera"
            protocol = protocol.model_copy(
                update={"feedback": protocol.feedback.model_copy(update={"camera": camera})}
            )
        protocols.append(protocol)

    # the protocols with the fewest trials first: those (spine, prediction) have the longest
    # trials (wall contact, a frame every tick), and the hundreds of short sweep trials then
    # fill the pool's end instead of one long trial running alone there
    protocols.sort(key=lambda p: len(p.expand(quick=quick)))
    total_start = time.perf_counter()

    def run_one(protocol: Any, executor: Any) -> tuple[dict[str, Any], float]:
        if progress is not None:
            progress(protocol.name)
        manifest = run_protocol(protocol, out, quick=quick, executor=executor, overwrite=True)
        return manifest, time.perf_counter() - total_start

    with shared_pool(jobs) as pool, cf.ThreadPoolExecutor(max(len(protocols), 1)) as threads:
        executor = pool_executor(pool)
        futures = []
        for protocol in protocols:  # the pool queues trials in submission order
            futures.append(threads.submit(run_one, protocol, executor))
            time.sleep(0.2)
        done = [f.result() for f in futures]
    for protocol, (manifest, finished) in zip(protocols, done, strict=True):
        trials = manifest["trials"]
        folder = Path(out) / protocol.name
        size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
        result["protocols"][protocol.name] = {
            "trials": len(trials),
            "wall_s": finished,
            "trials_per_min": len(trials) / finished * 60,
            "failed": sum(t["status"] != "ok" for t in trials),
            "dropped_ticks": sum(int(t.get("dropped_ticks") or 0) for t in trials),
            "overrun_ticks": sum(int(t.get("overruns") or 0) for t in trials),
            "ticks": sum(int(t.get("ticks") or 0) for t in trials),
            "trial_wall_s": sum(float(t.get("wall_s") or 0.0) for t in trials),
            "recordings_mb": size / 1e6,
        }
    wall = time.perf_counter() - total_start
    rows = result["protocols"].values()
    result["total"] = {
        "trials": sum(r["trials"] for r in rows),
        "wall_s": wall,
        "trials_per_min": sum(r["trials"] for r in rows) / wall * 60,
        "failed": sum(r["failed"] for r in rows),
        "dropped_ticks": sum(r["dropped_ticks"] for r in rows),
        "overrun_ticks": sum(r["overrun_ticks"] for r in rows),
        "recordings_mb": sum(r["recordings_mb"] for r in rows),
    }
    return result


def bench_tick(
    protocol_file: str = "protocols/noise.yaml", ticks: int = 800, method: str = "proposed"
) -> dict[str, Any]:
    """Median time per control tick of each stage of a camera trial, in one process.

    The protocol's (default ``noise``: 25.5 Hz, S trajectory, camera tracking) first
    ``method`` trial, feedback every frame without noise, ``ticks`` ticks run stage by stage like
    :func:`magrun.loop.run_trial` with each stage timed: render (the rig's camera frame),
    track (UNet window, keypoints, pose fit), control (mimic, estimator, planner), plant
    (one control period of the simulated rig). No recorder, no latency charged.
    """
    import cv2
    import torch

    from magrun.control.methods import make_controller
    from magrun.protocol import load_protocol
    from magrun.robot import load_robot
    from magrun.runner import _make_rig, build_scene
    from magrun.tracking.fluoroscopy import FluoroscopyMimic
    from magrun.tracking.tracker import Tracker
    from magrun.trial import control_config

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    protocol = load_protocol(protocol_file)
    trial = next(t for t in protocol.expand() if t.method == method)
    scene = build_scene(protocol)
    cfg = control_config(protocol.controller, protocol.robot, trial.condition)
    controller = make_controller(method, load_robot(protocol.robot), cfg)
    rig = _make_rig("sim", protocol.robot, scene.walls, trial.seed, True)
    tracker = Tracker.default(rig.camera, rig.nominal_robot)
    mimic = FluoroscopyMimic(25.5, 0.0, seed=trial.seed)
    ref, dt = scene.reference, controller.dt
    offsets = np.arange(protocol.controller.horizon + 1) * dt
    rig.reset(ref.pose(0.0))
    controller.reset(ref.pose(0.0))
    tracker.reset()
    stages: dict[str, list[float]] = {"render": [], "track": [], "control": [], "plant": []}
    for k in range(ticks):
        t = k * dt
        t0 = time.perf_counter()
        obs = rig.observe()
        t1 = time.perf_counter()
        pose = tracker(obs.frame) if obs.frame is not None else None
        t2 = time.perf_counter()
        out = controller.step(mimic(t, pose), ref.pose(t + offsets))
        t3 = time.perf_counter()
        rig.apply(out.currents)
        rig.advance(dt)
        t4 = time.perf_counter()
        for name, v in zip(stages, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
            stages[name].append(v)
    medians = {f"{k}_ms": _ms(np.array(v), 50) for k, v in stages.items()}
    return {
        "benchmark": "tick",
        "machine": machine(),
        "method": method,
        "ticks": ticks,
        **medians,
        "sum_of_medians_ms": sum(medians.values()),
    }


#: the recording child of :func:`bench_sigkill`: logs synthetic ticks at the trial's pace,
#: printing each tick's index once it is handed to the recorder
_RECORDING_CHILD = """
import sys, time
import numpy as np
from magrun.records import ControllerStatus, Tick
from magrun.recorder_process import ProcessRecorder
from magrun.recording import RecordingSetup, TrialRecorder
dt, base, writer = float(sys.argv[1]), sys.argv[2], sys.argv[3]
setup = RecordingSetup(trial={"method": "bench"}, channel_names=tuple("abcdefgh"))
cls = ProcessRecorder if writer == "process" else TrialRecorder
rec = cls(base, setup, flush_s=1.0).start()
status = ControllerStatus(0.001, 1, True, "", "0")
start = time.perf_counter()
k = 0
while True:
    p = np.array([1e-4 * k, 0.0, 0.0])
    rec.log(Tick(k=k, t=k * dt, actual=p, tracked=p, measured=p if k % 8 == 0 else None,
                 estimated=p, predicted=p, desired=p, currents=np.zeros(8), status=status,
                 compute_time=0.001))
    print(k, flush=True)
    k += 1
    time.sleep(max(0.0, start + k * dt - time.perf_counter()))
"""


def _wait_for_footer(path: Any, timeout: float) -> None:
    """Until ``path`` ends with MCAP's closing magic (its writer finished it) or ``timeout``."""
    magic = b"\x89MCAP0\r\n"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with open(path, "rb") as fh:
                fh.seek(-len(magic), 2)
                if fh.read() == magic:
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
    time in ``window`` s, then recovers the file (:func:`magrun.recover.recover`; for the
    process writer, once the writer has finished it, at most 10 s). Lost = ticks handed to
    the recorder (printed by the child before it died) minus ticks recovered, in ticks and
    in seconds of trial time; ``complete``: the file had its footer (no recovery needed).
    """
    import signal
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    from magrun.recover import recover

    rng = np.random.default_rng(seed)
    rows = []
    with tempfile.TemporaryDirectory(prefix="magrun-sigkill-") as tmp:
        for i in range(kills):
            base = Path(tmp) / f"kill-{i}"
            child = subprocess.Popen(
                [sys.executable, "-c", _RECORDING_CHILD, str(dt), str(base), writer],
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


def bench_rig(
    protocol_file: str = "protocols/noise.yaml", stalls: int = 20, watchdog_ms: float = 100.0
) -> dict[str, Any]:
    """The hardware path on ``magrun rig-emulator`` (its own process, loopback TCP).

    1. A run: the protocol's ``--quick`` trials through the TCP driver, camera frames over
       the wire, the UNet tracking in the rig, real-time pacing. Figures per trial: latency
       (frame to the controller's acknowledgement of the tick's currents: median, p99, max),
       overrunning ticks, dropped frames, wall time against the trial's duration.
    2. The watchdog: ``stalls`` times, command 10 A on every coil, then stop commanding and
       poll ``STATUS`` every millisecond; the reaction is the wall time from the last
       command's acknowledgement to the first status ``watchdog``; then how long until the
       driven currents (the emulated amplifiers ramp at the slew limit) read zero.
    """
    import subprocess
    import sys
    import tempfile

    from magrun.protocol import load_protocol
    from magrun.rigs.drivers import TcpLineDriver
    from magrun.runner import HardwareSpec, run_protocol

    proc = subprocess.Popen(
        [sys.executable, "-m", "magrun.cli", "rig-emulator", "--port", "0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    url = proc.stdout.readline().split()[-1]
    host, port = url.removeprefix("tcp://").rsplit(":", 1)
    out: dict[str, Any] = {"benchmark": "rig", "machine": machine(), "emulator": url}
    try:
        protocol = load_protocol(protocol_file)
        with tempfile.TemporaryDirectory(prefix="magrun-rig-") as tmp:
            t0 = time.perf_counter()
            manifest = run_protocol(protocol, tmp, quick=True, rig=HardwareSpec(url))
            wall = time.perf_counter() - t0
        out["run"] = {
            "protocol": protocol.name,
            "wall_s": wall,
            "trials": [
                {
                    "path": e["path"],
                    "status": e["status"],
                    "error": e["error"],
                    "ticks": e.get("ticks"),
                    "wall_s": e["wall_s"],
                    "duration_s": protocol.trial_duration(True),
                    "rms_position_mm": e.get("rms_position_mm"),
                    **e.get("hardware", {}),
                }
                for e in manifest["trials"]
            ],
        }
        driver = TcpLineDriver(host, int(port))
        driver.open(watchdog_ms * 1e-3)
        reactions: list[float] = []
        to_zero: list[float] = []
        for _ in range(stalls):
            driver.conn.request("ARM", "OK")
            driver.send(np.full(len(driver.channel_names), 10.0))
            last = time.perf_counter()
            while True:
                fields = driver.conn.request("STATUS", "STATUS")
                now = time.perf_counter()
                if fields[0] == "watchdog":
                    reactions.append(now - last)
                    break
                time.sleep(0.001)
            while True:
                fields = driver.conn.request("STATUS", "STATUS")
                if not any(float(v) for v in fields[2:]):  # the driven currents
                    to_zero.append(time.perf_counter() - now)
                    break
                time.sleep(0.001)
            driver.conn.request("ARM", "OK")
            driver.send(np.zeros(len(driver.channel_names)))
            time.sleep(0.15)  # the amplifiers settle at zero
        driver.close()
        r = np.array(reactions)
        out["watchdog"] = {
            "timeout_ms": watchdog_ms,
            "stalls": stalls,
            "reaction_median_ms": _ms(r, 50),
            "reaction_max_ms": float(r.max() * 1e3),
            "beyond_timeout_max_ms": float(r.max() * 1e3 - watchdog_ms),
            "ramp_to_zero_median_ms": _ms(np.array(to_zero), 50),
            "ramp_to_zero_max_ms": float(max(to_zero) * 1e3),
        }
    finally:
        proc.terminate()
        proc.wait(10)
        proc.stdout.close()
    return out
