"""Run a protocol: expand it into trials, run each on a rig, record it, keep a manifest.

    >>> from magrun.protocol import load_protocol
    >>> from magrun.runner import run_protocol
    >>> manifest = run_protocol(load_protocol("protocols/rate.yaml"), "recordings", jobs=2)

One trial (:func:`execute_trial`) is built from the :class:`~magrun.protocol.Trial` alone by
:func:`magrun.trial.assemble` (the rig, seeded; the controller; the camera tracker; the
fluoroscopy mimic, seeded; the safety layer); the runner adds a recorder
(:class:`~magrun.recordings.writer.TrialRecorder`), runs it and writes its manifest entry.
Because a trial depends on nothing else, trials run in any order, in any process: a local
process pool (``jobs``), or Ray on a cluster (:func:`ray_executor`), give the same recordings
(up to the wall-clock fields: solve and compute times; and with ``latency_ms: measured`` the
plant's timing too).

Output, per the recording contract::

    OUT/<protocol>/manifest.json
    OUT/<protocol>/<condition slug>/trial-<k>.mcap
    OUT/<protocol>/<condition slug>/trial-<k>.rrd

The manifest is rewritten atomically after every trial: each entry's ``status`` is
``pending``, ``ok``, ``stopped`` (the safety layer ended it early: ``error`` says why and
``stopped_at_s`` when; its recording is complete up to there), ``interrupted`` or ``failed``
(with the error), so an interrupted campaign says exactly what it holds. A trial that ran to
its end also carries ``warnings`` (:mod:`magrun.health`: sustained saturation, failed
solves, a lost estimate, contact with the critical boundary), which ``magrun run`` prints.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime
import json
import logging
import math
import multiprocessing
import os
import shutil
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack, contextmanager, nullcontext, suppress
from pathlib import Path
from typing import Any

import numpy as np

from magrun import interrupt
from magrun.atomic import LOCK_NAME, FolderBusy, FolderLock, write_text
from magrun.loop import STAGES
from magrun.protocol import Protocol, Trial
from magrun.realtime import cpu_split, loop_placement
from magrun.scene import Trajectory
from magrun.trial import (
    NO_DRIVER,
    HardwareSpec,
    RigSpec,
    RunError,
    check_system,
    coil_gains_of,
    handshake,
    trial_threads,
)
from magrun.yamlio import YamlModelError, read_text_file, safe_json

RIGS = ("sim", "hardware")
ProgressFn = Callable[[str, int, int], None]  # (trial relpath, ticks done, ticks total)


def execute_trial(
    trial: Trial,
    out: str | Path,
    rig: RigSpec = "sim",
    progress: ProgressFn | None = None,
    view: str = "",
) -> dict[str, Any]:
    """Run and record one trial under ``out``; returns its manifest entry (never raises).

    ``view``: a Rerun viewer's gRPC URL (``rerun+http://HOST:PORT/proxy``) that the trial
    is also streamed to while it runs ("": none)."""
    from magrun.health import trial_health
    from magrun.recordings.process import ProcessRecorder
    from magrun.recordings.writer import RecordingSetup, TrialRecorder, software_versions
    from magrun.trial import assemble

    entry = manifest_entry(trial)
    if interrupt.requested() is not None:
        return entry  # stopping: a trial not yet started stays pending (--resume runs it)
    t0 = time.perf_counter()
    cpu0 = (time.thread_time(), time.process_time())
    base = Path(out) / trial.relpath
    recorder = None
    parts = None
    sim = rig == "sim"
    try:
        with trial_threads(1):  # the tracker's network is made here, with its threads
            parts = assemble(trial, rig)
        protocol, scene, robot = trial.protocol, parts.scene, parts.robot
        controller, the_rig, tracker = parts.controller, parts.rig, parts.tracker
        meta = {
            **trial.describe(),
            "rig": str(rig),
            # the simulated plant: a preset's name or a plant file's (its terms: `plant` record)
            "plant": Path(protocol.simulation.plant).name if sim else "",
            "robot": protocol.robot,
            "robot_length_m": robot.length,
            "robot_diameter_m": robot.diameter,
            "control_rate_hz": protocol.controller.rate_hz,
            "max_current_a": np.broadcast_to(
                np.asarray(controller.max_current, dtype=np.float64), (controller.n_channels,)
            ).tolist(),
            "latency_ms": _latency_ms(protocol.controller.latency),
            "charge_compute_time": protocol.controller.latency == "measured",
            "feedback": "camera" if tracker is not None else "truth",
            "camera_frames": protocol.feedback.camera_frames if tracker is not None else "",
            "critical_boundary": scene.critical or "",
            "software": software_versions(),
        }
        setup = RecordingSetup(
            trial=meta,
            channel_names=tuple(the_rig.channel_names),
            protocol_json=protocol.model_dump_json(),
            boundaries=scene.boundaries,
            workspace_half_width=scene.half_width,
            reference=scene.reference.poses,
            camera=the_rig.camera,
            image_every=protocol.recording.image_every,
            jpeg_quality=protocol.recording.jpeg_quality,
            image_format=protocol.recording.image_format,
            rerun_image_every=protocol.recording.rerun_image_every,
            compression=protocol.recording.compression,
            recording_id=f"{trial.relpath}@{trial.seed}",
            name=f"{trial.relpath} (seed {trial.seed})",
            extra_metadata={"plant": the_rig.plant_record()} if the_rig.simulated else {},
            live_view=view,
        )
        writer = protocol.recording.writer
        cam = the_rig.camera
        # on a rig the loop gets a core of its own at real-time priority (where permitted),
        # the writer the others (magrun.realtime); in simulation nothing is placed
        cores = None if sim else cpu_split()
        writer_cpus = cores[1] if cores else None
        recorder = (
            ProcessRecorder(
                base, setup, wait_when_full=sim, writer_cpus=writer_cpus,
                frame_bytes=cam.shape[0] * cam.shape[1] * 3 if cam is not None else None,
            )
            if writer == "process" or (writer == "auto" and not sim)
            else TrialRecorder(base, setup, writer_cpus=writer_cpus, wait_when_full=sim)
        ).start()  # fmt: skip
        tick_progress = (
            (lambda done, total: progress(trial.relpath, done, total)) if progress else None
        )
        placement = loop_placement(cores[0] if cores else None) if not sim else nullcontext("")
        loop_start = time.thread_time()
        with trial_threads(1), placement as scheduling:
            log = parts.run(
                on_tick=recorder.log, progress=tick_progress,
                stop=lambda: interrupt.requested() is not None,
            )  # fmt: skip
        loop_cpu = (loop_start, time.thread_time())
        safety = parts.safety
        status = "interrupted" if log.interrupted else "stopped" if log.stop_reason else "ok"
        health, warnings = trial_health(
            log, controller.dt, controller.max_current, parts.free_space,
            predict=controller.planner.predict, frame_ticks=parts.frame_ticks,
        )  # fmt: skip
        if parts.held is not scene.reference:  # headings the coils can hold (trial.py)
            warnings.extend(_held_heading_warning(parts.held, scene.reference))
        reason = log.stop_reason
        if log.interrupted:
            reason = f"stopped by {_signal_name(interrupt.requested())} at t = {log.t[-1]:.2f} s"
        elif reason:
            reason = f"safety stop at t = {safety.tripped_at:.2f} s: {reason}"
        stats = recorder.close(status, reason)
        recorder = None
        error = stats.error or reason
        entry.update(
            status=status if not stats.error else "failed",
            stopped_at_s=safety.tripped_at if log.stop_reason else None,
            error=error,
            ticks=len(log.t),
            dropped_ticks=stats.dropped_ticks,
            rms_position_mm=log.rms_position_mm,
            rms_orientation_deg=log.rms_orientation_deg,
            rms_prediction_position_mm=log.rms_prediction_position_mm,
            rms_prediction_orientation_deg=log.rms_prediction_orientation_deg,
            rms_prediction_measured_position_mm=log.rms_prediction_measured_position_mm,
            rms_prediction_measured_orientation_deg=log.rms_prediction_measured_orientation_deg,
            overruns=int(np.count_nonzero(log.compute_time > controller.dt)),
            median_compute_ms=float(np.median(log.compute_time) * 1e3),
            **health,
            warnings=warnings,
        )
        entry["cpu_s"] = cpu_breakdown(cpu0, loop_cpu, log.stage_cpu_s or {})
        if not sim:
            entry["hardware"] = the_rig.report()  # a real rig's link statistics
            entry["loop_scheduling"] = scheduling
    except Exception as exc:
        entry.update(status="failed", error=f"{type(exc).__name__}: {exc}")
        entry["traceback"] = traceback.format_exc(limit=8)
        if recorder is not None:
            recorder.close("failed", entry["error"])
    finally:
        if parts is not None and not sim:
            with suppress(Exception):  # the rig's watchdog covers a dead link
                parts.rig.disconnect()
    entry["wall_s"] = time.perf_counter() - t0
    return entry


#: a trial's CPU seconds in the manifest (``cpu_s``): the trial's set-up (assembling it,
#: opening the recording), the loop's stages (:data:`magrun.loop.STAGES`), its finish
#: (closing the recording, the health figures), the process's other threads meanwhile (the
#: recorder's writer thread, Rerun's and ONNX Runtime's threads; a writer process, as on the
#: hardware rig, is not counted), and the total: the process's CPU time over the trial
CPU_PARTS = ("setup", *STAGES, "finish", "other_threads", "total")


def cpu_breakdown(
    start: tuple[float, float], loop: tuple[float, float], stages: dict[str, float]
) -> dict[str, float]:
    """The trial's ``cpu_s`` (:data:`CPU_PARTS`) from its start's ``(thread_time,
    process_time)``, the loop's ``thread_time`` before and after, and the loop's stages."""
    now = (time.thread_time(), time.process_time())
    out = {"setup": loop[0] - start[0]}
    out.update({name: stages.get(name, 0.0) for name in STAGES})
    # the loop's own part: the rest of the call that ran it (the trial's reset before its
    # first tick and the log's arrays after the last included)
    out["loop"] = max(loop[1] - loop[0] - sum(out[name] for name in STAGES if name != "loop"), 0)
    out["finish"] = now[0] - loop[1]
    out["other_threads"] = max(now[1] - start[1] - (now[0] - start[0]), 0.0)
    out["total"] = now[1] - start[1]
    return {k: round(v, 4) for k, v in out.items()}


def _latency_ms(latency: float | str) -> float | str:
    """The declared latency as the recording states it: ms, or "measured"."""
    return latency if isinstance(latency, str) else latency * 1e3


def _signal_name(signum: int | None) -> str:
    import signal

    try:
        return signal.Signals(signum).name if signum is not None else "a stop request"
    except ValueError:
        return f"signal {signum}"


def manifest_entry(trial: Trial) -> dict[str, Any]:
    return {
        "path": trial.relpath.split("/", 1)[1],
        "mcap": trial.relpath.split("/", 1)[1] + ".mcap",
        "rrd": trial.relpath.split("/", 1)[1] + ".rrd",
        "protocol": trial.protocol.name,
        "method": trial.method,
        "conditions": trial.condition.model_dump(),
        "trial": trial.index,
        "seed": trial.seed,
        "status": "pending",
    }


# --------------------------------------------------------------------------------------------
# executors: each yields manifest entries as trials finish


Executor = Callable[[list[Trial], Path, RigSpec, ProgressFn | None], Iterable[dict[str, Any]]]


#: trial statuses a --resume keeps: the trial ran to its end, or to a safety stop
COMPLETE = ("ok", "stopped")

#: thread pools of native libraries, one thread each in worker processes
THREAD_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _one_thread_per_worker() -> Iterator[None]:
    """Spawned workers start with one BLAS/OpenMP thread (unless the user set a number).

    With ``jobs`` processes on as many cores, every library's own thread pool oversubscribes
    the machine: the lookup-table baselines' small least-squares problems took 2.5× longer
    in two parallel workers with OpenBLAS's default threads than with one.
    """
    saved = {k: os.environ.get(k) for k in THREAD_ENV}
    for k in THREAD_ENV:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextmanager
def _children_ignore_stops() -> Iterator[None]:
    """Processes started inside the block begin with SIGINT and SIGTERM ignored: an ignored
    signal is inherited across the spawn's exec, and Python then installs no
    KeyboardInterrupt handler, so a Ctrl-C (or the stop this process passes on) while a
    worker still imports (seconds: torch, CasADi) cannot kill it mid-import, a traceback on
    the terminal and the pool broken. The worker's initializer installs the stop handler
    (:func:`_worker_init`). The block only starts processes (milliseconds); a signal within
    it is lost to this process too."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in interrupt.SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


#: a pool worker's progress queue (:func:`_worker_init`; None: no progress is sent)
_progress_queue: Any = None


def _worker_init(progress: Any = None) -> None:
    global _progress_queue
    # first: SIGINT / SIGTERM end the worker's trial cleanly from here on (before, the
    # worker ignored them: _children_ignore_stops)
    interrupt.install_in_worker()
    _progress_queue = progress
    import cv2

    cv2.setNumThreads(1)  # the tracker's network: one thread per trial (trial_threads)


def _pool_progress(q: Any) -> ProgressFn:
    def send(relpath: str, done: int, total: int) -> None:
        if done == total or done % 25 == 0:
            q.put((relpath, done, total))

    return send


def _run_in_worker(trial: Trial, out: str, rig: RigSpec, q: Any, view: str = "") -> dict[str, Any]:
    """One trial in a worker; progress into ``q``, else into the pool's queue, if any."""
    q = q if q is not None else _progress_queue
    return execute_trial(trial, out, rig, _pool_progress(q) if q is not None else None, view)


def _result_or_failure(get: Callable[[], dict[str, Any]], trial: Trial) -> dict[str, Any]:
    """A worker's manifest entry, or a failed one when the worker itself died."""
    try:
        return get()
    except Exception as exc:  # a killed or crashed worker process, a lost Ray node
        return {**manifest_entry(trial), "status": "failed", "error": f"worker died: {exc!r}"}


def _held_heading_warning(planned: Trajectory, reference: Trajectory) -> list[str]:
    """The run's warning where the planner follows other headings than the reference's
    (the ones the coils can hold): the share of the trajectory's time where they differ by
    more than 1°, and by how much at most; none where they never differ by 1°."""
    t = np.linspace(0.0, reference.duration, 2001)
    turn = np.degrees(np.abs(planned.pose(t)[:, 2] - reference.pose(t)[:, 2]))
    if not np.any(turn > 1.0):
        return []
    return [
        f"the coils cannot hold the reference's heading along {np.mean(turn > 1.0):.0%} of it: "
        f"the planner followed headings up to {turn.max():.0f}° off it"
    ]


def local_executor(jobs: int = 1, view: str = "") -> Executor:
    """Run trials in this process (``jobs`` = 1) or a pool of ``jobs`` processes; each
    streamed live to the Rerun viewer at the gRPC URL ``view`` too, if one is given."""

    def run(
        trials: list[Trial], out: Path, rig: RigSpec, progress: ProgressFn | None
    ) -> Iterator[dict[str, Any]]:
        if jobs <= 1:
            for trial in trials:
                if interrupt.requested() is not None:
                    return  # the rest stay pending (magrun run --resume)
                yield execute_trial(trial, out, rig, progress, view)
            return
        ctx = multiprocessing.get_context("spawn")  # no forked torch / casadi state
        # progress through a queue the workers inherit (no manager process to start)
        q = ctx.SimpleQueue() if progress is not None else None
        with _one_thread_per_worker(), ExitStack() as stack:
            pool = stack.enter_context(
                cf.ProcessPoolExecutor(
                    jobs, mp_context=ctx, initializer=_worker_init, initargs=(q,)
                )
            )
            with _children_ignore_stops():  # each submit starts a worker, up to ``jobs``
                futures = {
                    pool.submit(_run_in_worker, t, str(out), rig, None, view): t for t in trials
                }
            pending = set(futures)
            stopping = False
            while pending:
                if interrupt.requested() is not None:
                    if not stopping:
                        stopping = True  # running trials end cleanly; queued ones never start
                        for fut in pending:
                            fut.cancel()
                        pending = {f for f in pending if not f.cancelled()}
                        if not pending:
                            break
                    # at every wait: a worker still starting ignores the stop until its
                    # handler is set up (_worker_init), and must not then run a whole trial
                    _signal_workers(pool, interrupt.requested())
                done, pending = cf.wait(pending, timeout=0.2)
                while q is not None and not q.empty():
                    assert progress is not None
                    progress(*q.get())
                for fut in done:
                    yield _result_or_failure(fut.result, futures[fut])

    return run


@contextmanager
def shared_pool(jobs: int) -> Iterator[cf.ProcessPoolExecutor]:
    """A pool of ``jobs`` worker processes set up as :func:`local_executor`'s, for several
    runs to share (:func:`pool_executor`)."""
    ctx = multiprocessing.get_context("spawn")
    with (
        _one_thread_per_worker(),
        cf.ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init) as pool,
    ):
        with _children_ignore_stops():
            for _ in range(jobs):  # each submit starts a worker, ignoring stops until set up
                pool.submit(int)
        yield pool


def pool_executor(pool: cf.ProcessPoolExecutor) -> Executor:
    """Trials into an existing pool: several protocols' runs, each on its own thread, share
    the workers, so no worker idles at the end of one protocol while another has trials
    (``magrun bench campaign``). No tick progress; a stop signal reaches the workers'
    own handlers only (a terminal's Ctrl-C does)."""

    def run(
        trials: list[Trial], out: Path, rig: RigSpec, progress: ProgressFn | None
    ) -> Iterator[dict[str, Any]]:
        futures = {pool.submit(_run_in_worker, t, str(out), rig, None): t for t in trials}
        for fut in cf.as_completed(futures):
            yield _result_or_failure(fut.result, futures[fut])

    return run


def _signal_workers(pool: cf.ProcessPoolExecutor, signum: int | None) -> None:
    """Pass a stop signal on to the pool's worker processes (a terminal's Ctrl-C reaches
    them itself; ``kill`` of the parent does not)."""
    import signal

    for proc in list(getattr(pool, "_processes", {}).values()):
        with suppress(OSError):  # already gone
            os.kill(proc.pid, signum or signal.SIGTERM)


def _run_on_ray_node(trial: Trial, rig: RigSpec, view: str = "") -> dict[str, Any]:
    """One trial as a Ray task: recorded into the node's own temporary folder, then returned
    whole: its manifest entry (with the node's id), and every file it wrote, by its path
    under the output folder. The driver writes them (:func:`_write_back`), so no node needs
    the driver's output folder."""
    import tempfile

    import cv2
    import ray

    cv2.setNumThreads(1)  # as the run's pool starts its workers (_worker_init)
    with tempfile.TemporaryDirectory(prefix="magrun-ray-") as tmp:
        entry = _run_in_worker(trial, tmp, rig, None, view)
        files = {
            p.relative_to(tmp).as_posix(): p.read_bytes()
            for p in sorted(Path(tmp).rglob("*"))
            if p.is_file()
        }
    entry["ray_node"] = ray.get_runtime_context().get_node_id()
    return {"entry": entry, "files": files}


def _write_back(out: Path, files: dict[str, bytes]) -> None:
    """A Ray task's files under the driver's output folder ``out``, each written whole to a
    temporary name and renamed (a crash of the driver leaves no half file). Paths are checked:
    relative, inside ``out``."""
    for rel, data in files.items():
        parts = Path(rel).parts
        if Path(rel).is_absolute() or not parts or ".." in parts:
            raise RunError(f"a Ray task returned a file outside the output folder: {rel!r}")
        target = out / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        partial = target.with_name(target.name + ".part")
        partial.write_bytes(data)
        os.replace(partial, target)


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A :class:`RunError` unless ``address`` (``HOST:PORT``, ``ray://HOST:PORT`` or
    ``auto``) answers a TCP connection within ``timeout_s``: Ray's own connection to a
    cluster that is not there waits for many minutes."""
    import socket

    if address == "auto":
        return  # Ray finds the cluster this machine runs, or says at once there is none
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise RunError(
            f"--ray-address {address!r}: give HOST:PORT (the head's GCS port, 6379 by "
            "default), ray://HOST:PORT (Ray's client port, 10001) or auto"
        )
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise RunError(
            f"could not connect to the Ray cluster at {address}: {exc} (is `ray start "
            "--head` running there, and the port open?)"
        ) from exc


def ray_executor(
    address: str | None = None, num_cpus: int | None = None, view: str = ""
) -> Executor:
    """Run trials as Ray tasks (``pip install magrun[ray]``), one CPU each; ``view`` as for
    :func:`local_executor` (each node must reach it).

    ``address`` is a running cluster's (``ray://host:10001``, ``HOST:6379`` or ``auto``);
    ``None`` starts a local Ray instance with ``num_cpus`` CPUs. Each trial records on its
    node, into a temporary folder, and its files come back to this process with its result
    (:func:`_run_on_ray_node`), which writes them under the output folder: the nodes need
    magrun installed, not the driver's disk. The manifest entry names the node
    (``ray_node``). A stop signal (:mod:`magrun.interrupt`) cancels what has not come back;
    those trials stay pending.
    """
    try:
        import ray
    except ImportError as exc:
        raise RunError("the Ray executor needs Ray: pip install 'magrun[ray]'") from exc
    if address:
        _check_reachable(address)  # before a run writes anything

    def run(
        trials: list[Trial], out: Path, rig: RigSpec, progress: ProgressFn | None
    ) -> Iterator[dict[str, Any]]:
        started = not ray.is_initialized()
        if started:
            try:
                ray.init(
                    # a running cluster has its own CPUs: Ray refuses num_cpus with an address
                    address=address, num_cpus=None if address else num_cpus,
                    include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING,
                )  # fmt: skip
            except Exception as exc:  # no cluster there, refused, another version, …
                where = f"the Ray cluster at {address}" if address else "a local Ray instance"
                hint = (
                    " (a cluster that `ray start --head` started asks for its token: set "
                    "RAY_AUTH_MODE=token, with the head's ~/.ray/auth_token on this machine)"
                    if address else ""
                )  # fmt: skip
                raise RunError(f"could not connect to {where}: {exc}{hint}") from exc
        try:
            # no runtime_env: Ray runs a task that has one in worker processes of its own,
            # started for it, beside the workers each node keeps warm. The trial's threads
            # are limited in the task (_run_on_ray_node, trial_threads) instead
            task = ray.remote(num_cpus=1)(_run_on_ray_node)
            refs = {task.remote(t, rig, view): t for t in trials}
            pending = list(refs)
            while pending:
                if interrupt.requested() is not None:
                    # a stop: queued trials never start, running ones are cancelled on
                    # their nodes (nothing of them is written here); all stay pending for
                    # --resume
                    for ref in pending:
                        ray.cancel(ref)
                    return
                ready, pending = ray.wait(pending, num_returns=1, timeout=0.2)
                if not ready:
                    continue
                ref = ready[0]

                def get(ref: Any = ref) -> dict[str, Any]:
                    result: dict[str, Any] = ray.get(ref)
                    _write_back(out, result["files"])
                    entry: dict[str, Any] = result["entry"]
                    return entry

                yield _result_or_failure(get, refs[ref])
                del refs[ref]  # its files are written: Ray may free them
        finally:
            if started:
                ray.shutdown()

    return run


# --------------------------------------------------------------------------------------------
# a protocol run


def run_protocol(
    protocol: Protocol,
    out: str | Path = "recordings",
    quick: bool = False,
    seed: int | None = None,
    jobs: int = 1,
    rig: RigSpec = "sim",
    executor: Executor | None = None,
    overwrite: bool = False,
    protocol_file: str | None = None,
    on_trial: Callable[[dict[str, Any]], None] | None = None,
    progress: ProgressFn | None = None,
    resume: bool = False,
    view: str = "",
    check_reach: bool = True,
    warn: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run every trial of ``protocol``; returns the manifest (also written to disk).

    Refuses (:class:`RunError`) to write into an existing ``OUT/<protocol>`` folder unless
    ``overwrite``, which deletes it first: recordings are never silently mixed or replaced.
    ``resume`` continues the run recorded there instead (same protocol, seed and --quick):
    trials whose status is ``ok`` and whose MCAP exists are kept, the others run again.
    A stop signal (:mod:`magrun.interrupt`) ends the running trials cleanly, starts no new
    one and records the signal under ``interrupted`` in the manifest. ``view`` streams each
    trial to a Rerun viewer as well (:func:`local_executor`; an ``executor`` has its own).
    What the checks before the first trial warn of (:func:`magrun.trial.check_system`) goes
    to ``warn`` as it is found and into the manifest's ``warnings``.
    """
    if isinstance(rig, HardwareSpec):
        if jobs != 1 or executor is not None:
            raise RunError("the hardware rig runs one trial at a time: --jobs 1, local executor")
    elif rig not in RIGS:
        raise RunError(f"unknown rig {rig!r}; choose {' or '.join(RIGS)}")
    elif rig == "hardware":
        raise RunError(NO_DRIVER)
    # a bad system folder, or damaged maps or models in it, fail here (RunError), before any run
    # and so does a trajectory the coils cannot move the robot along (unless not asked)
    # and, with camera feedback in simulation, a robot the camera's tracker cannot find
    notes: list[str] = []

    def noted(line: str) -> None:
        notes.append(line)
        if warn is not None:
            warn(line)

    coils = check_system(
        protocol, feasibility=check_reach, tracking=rig == "sim" and protocol.feedback.camera,
        warn=noted,
    )  # fmt: skip
    if isinstance(rig, HardwareSpec):
        # an unknown scheme, a rig out of reach or one whose channels or limits are not the
        # system's fails here (RunError), before a folder is made or a current sent
        handshake(rig, coils, protocol.safety.stall_timeout_ms * 1e-3)
    if protocol.controller.coil_gains is not None:
        coil_gains_of(protocol, coils)  # its channels are the coils' (RunError)
    out = Path(out)
    folder = out / protocol.name
    existed = folder.exists()
    try:  # one writer per folder: a second run, --resume or --overwrite waits its turn
        lock = FolderLock(folder)
    except FolderBusy as exc:
        raise RunError(str(exc)) from exc
    except OSError as exc:
        raise RunError(f"{folder}: cannot write there: {exc}") from exc
    try:
        return _run_locked(
            protocol, folder, quick, seed, jobs, rig, executor, overwrite, protocol_file,
            on_trial, progress, resume, view, notes,
        )  # fmt: skip
    finally:
        lock.release()
        if not existed and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()  # refused before anything was written: leave no trace


def _run_locked(
    protocol: Protocol,
    folder: Path,
    quick: bool,
    seed: int | None,
    jobs: int,
    rig: RigSpec,
    executor: Executor | None,
    overwrite: bool,
    protocol_file: str | None,
    on_trial: Callable[[dict[str, Any]], None] | None,
    progress: ProgressFn | None,
    resume: bool,
    view: str,
    notes: list[str],
) -> dict[str, Any]:
    """:func:`run_protocol`'s work in ``folder``, whose lock the caller holds."""
    out = folder.parent
    path = folder / "manifest.json"
    previous: dict[str, Any] | None = None
    if any(p.name != LOCK_NAME for p in folder.iterdir()):
        if resume:
            previous = _resumable(path, protocol, quick, seed)
        elif not overwrite:
            raise RunError(
                f"{folder} already holds recordings; choose another --out, pass --overwrite, "
                "or --resume an interrupted run"
            )
        else:
            for item in folder.iterdir():  # all but the lock this run holds
                if item.name == LOCK_NAME:
                    continue
                if item.is_dir() and not item.is_symlink():
                    shutil.rmtree(item)
                else:
                    item.unlink()
    trials = protocol.expand(quick=quick, seed=seed)
    from magrun.recordings.writer import software_versions

    manifest: dict[str, Any] = {
        "protocol": protocol.name,
        "protocol_file": protocol_file,
        "description": protocol.description,
        "seed": protocol.seed if seed is None else seed,
        "quick": quick,
        "rig": str(rig),
        **({"driver": rig.driver, "camera": rig.camera} if isinstance(rig, HardwareSpec) else {}),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "software": software_versions(),
        **({"warnings": notes} if notes else {}),
        "trials": [manifest_entry(t) for t in trials],
    }
    index = {e["path"]: i for i, e in enumerate(manifest["trials"])}
    if previous is not None:
        for old in previous.get("trials", []):
            done = old.get("status") in COMPLETE and _intact(folder, old)
            if done and old.get("path") in index:
                manifest["trials"][index[old["path"]]] = old
        kept = {e["path"] for e in manifest["trials"] if e.get("status") in COMPLETE}
        trials = [t for t in trials if manifest_entry(t)["path"] not in kept]
    write_manifest(path, manifest)
    run = executor or local_executor(jobs, view)
    for entry in run(trials, out, rig, progress):
        entry = _finite(entry)  # NaN (no prediction: the PID) is null, in memory as on disk
        manifest["trials"][index[entry["path"]]] = entry
        write_manifest(path, manifest)
        if on_trial is not None:
            on_trial(entry)
    if interrupt.requested() is not None:
        manifest["interrupted"] = _signal_name(interrupt.requested())
        write_manifest(path, manifest)
    return manifest


#: the topic with one message per recorded tick, counted by :func:`_intact`
STATUS_TOPIC = "/controller/status"


def _intact(folder: Path, entry: dict[str, Any]) -> bool:
    """Whether a finished trial's recording in ``folder`` is whole: its MCAP indexed (a
    summary), with one controller status per recorded tick (``ticks`` − ``dropped_ticks`` of
    its manifest entry), and its ``.rrd`` there. A truncated or tampered file is not, and
    ``--resume`` runs its trial again."""
    from magrun.recordings.reader import message_counts

    relpath, rrd = str(entry.get("mcap", "")), str(entry.get("rrd", ""))
    try:
        mcap = (folder / relpath).resolve()
        if not relpath or not mcap.is_relative_to(folder.resolve()) or not mcap.is_file():
            return False
        if rrd and not (folder / rrd).is_file():
            return False
        counts = message_counts(mcap)
        if counts is None:
            return False
        status = counts.get(STATUS_TOPIC, 0)
        recorded = int(entry.get("ticks", -1)) - int(entry.get("dropped_ticks") or 0)
    except Exception:  # any damage (mcap raises several types): not intact
        return False
    return status == recorded


def _resumable(path: Path, protocol: Protocol, quick: bool, seed: int | None) -> dict[str, Any]:
    """The manifest of the run to resume in ``path``'s folder, checked to be this run's."""
    try:
        previous = safe_json(read_text_file(path), str(path))
    except YamlModelError as exc:
        raise RunError(f"no readable manifest to resume from: {exc}") from exc
    if not isinstance(previous, dict):
        raise RunError(f"{path}: no readable manifest to resume from (not a JSON object)")
    want = {"protocol": protocol.name, "quick": quick,
            "seed": protocol.seed if seed is None else seed}  # fmt: skip
    have = {k: previous.get(k) for k in want}
    if have != want:
        raise RunError(
            f"{path} records another run ({have}), not this one ({want}); "
            "choose another --out or pass --overwrite"
        )
    return previous


def write_manifest(path: Path, manifest: dict[str, Any]) -> None:
    write_text(path, json.dumps(_finite(manifest), indent=2) + "\n")


def _finite(value: Any) -> Any:
    """NaN and infinities as JSON null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value
