"""The runner and the recordings: files, topics, counts, determinism, timing, drops."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from google.protobuf.json_format import MessageToDict
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from magrun.cli import cli
from magrun.control.methods import make_controller
from magrun.loop import run_trial
from magrun.protocol import load_protocol
from magrun.recordings.writer import TOPICS, RecordingSetup, TrialRecorder, yaw_of
from magrun.records import Tick
from magrun.rigs.sim import SimRig
from magrun.runner import RunError, ray_executor, run_protocol
from magrun.scene import s_trajectory

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "protocols" / "tiny.yaml"
# wall-clock fields, different on every run
TIMING_FIELDS = {"solveTime", "computeTime", "prepareTime"}


def read_mcap(path: Path) -> tuple[dict[str, int], list[tuple[str, int, dict[str, Any]]], dict]:
    """Topic counts (from the summary), decoded messages minus timing, metadata records."""
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        counts = {
            ch.topic: summary.statistics.channel_message_counts.get(cid, 0)
            for cid, ch in summary.channels.items()
        }
        messages = []
        for _schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=True):
            d = MessageToDict(decoded)
            for key in TIMING_FIELDS:
                d.pop(key, None)
            messages.append((channel.topic, message.log_time, d))
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return counts, messages, metadata


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    out = tmp_path_factory.mktemp("rec")
    manifest = run_protocol(load_protocol(TINY), out, jobs=1)
    return out, manifest


def test_manifest_lists_every_trial_with_its_files_and_conditions(tiny_run: Any) -> None:
    out, manifest = tiny_run
    on_disk = json.loads((out / "tiny" / "manifest.json").read_text())
    assert on_disk == json.loads(json.dumps(manifest))
    entries = manifest["trials"]
    assert len(entries) == 2 * 2
    assert {e["status"] for e in entries} == {"ok"}
    for e in entries:
        assert (out / "tiny" / e["mcap"]).stat().st_size > 0
        assert (out / "tiny" / e["rrd"]).stat().st_size > 0
        assert e["dropped_ticks"] == 0
        assert e["conditions"]["noise_sigma_mm"] == 1.0
    assert {e["path"] for e in entries} == {
        f"{m}_rate-{r}hz/trial-0" for m in ("baseline3", "baseline2") for r in ("5", "25.5")
    }


def test_mcap_has_the_contract_topics_and_counts(tiny_run: Any) -> None:
    out, manifest = tiny_run
    dt = 1 / 25.5
    n = math.floor(1.0 / dt + 1e-9) + 1  # ticks in a 1 s trial, t = 0 included
    for e in manifest["trials"]:
        counts, messages, meta = read_mcap(out / "tiny" / e["mcap"])
        rate = e["conditions"]["tracking_rate_hz"]
        # fluoroscopy frames are due at k / rate, up to the last tick at (n - 1) dt
        frames = math.floor((n - 1) * dt * rate + 1e-9) + 1
        assert set(counts) == set(TOPICS)
        expected = dict.fromkeys(TOPICS, n)
        expected["/robot/pose/measured"] = frames
        # the simulated camera takes only the fluoroscopy frames (feedback.camera_frames)
        expected["/camera/image"] = expected["/robot/pose/tracked"] = frames
        expected["/robot/pose/predicted"] = n - 1  # no prediction of the first tick
        assert counts == expected
        assert e["ticks"] == n
        trial = meta["trial"]
        assert trial["method"] == e["method"]
        assert json.loads(trial["seed"]) == e["seed"]
        assert json.loads(trial["tracking_rate_hz"]) == rate
        assert meta["recorder"]["dropped_ticks"] == "0"
        assert meta["recorder"]["status"] == "ok"
        assert json.loads(meta["protocol"]["json"])["name"] == "tiny"
        times = [t for topic, t, _ in messages if topic == "/robot/pose/actual"]
        assert times[0] == 0
        np.testing.assert_allclose(np.diff(times) * 1e-9, dt, atol=1e-6)


def test_camera_every_tick_tracks_and_records_every_tick(tmp_path: Path) -> None:
    """feedback.camera_frames: every_tick: a frame (and a tracked pose) at every tick, while
    the fluoroscopy mimic still delivers only its 5 Hz frames."""
    protocol = load_protocol(TINY)
    protocol = protocol.model_copy(
        update={
            "methods": ["baseline2"],
            "feedback": protocol.feedback.model_copy(update={"camera_frames": "every_tick"}),
        }
    )
    manifest = run_protocol(protocol, tmp_path, jobs=1)
    entry = next(e for e in manifest["trials"] if e["conditions"]["tracking_rate_hz"] == 5)
    counts, _, meta = read_mcap(tmp_path / "tiny" / entry["mcap"])
    n = entry["ticks"]
    assert counts["/camera/image"] == counts["/robot/pose/tracked"] == n
    assert counts["/robot/pose/measured"] == math.floor((n - 1) / 25.5 * 5 + 1e-9) + 1
    assert meta["trial"]["camera_frames"] == "every_tick"


def test_a_trials_loop_runs_on_one_blas_thread(tmp_path: Path, monkeypatch) -> None:
    """OpenBLAS's threads spin beside the loop (a Baseline 3 trial's other threads took 3.7 s
    of CPU against 0.5 s on one thread): every trial's loop runs with each BLAS library that
    NumPy and SciPy loaded on one thread, and the process's setting comes back after it."""
    import scipy.linalg  # noqa: F401  (SciPy's own BLAS loaded too)
    from threadpoolctl import threadpool_info, threadpool_limits

    import magrun.trial

    seen: list[list[int]] = []
    loop = magrun.trial.run_trial

    def probed(*args: Any, **kwargs: Any) -> Any:
        seen.append([p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"])
        return loop(*args, **kwargs)

    monkeypatch.setattr(magrun.trial, "run_trial", probed)
    protocol = load_protocol(TINY, ("methods=[baseline3]", "sweep.tracking_rate_hz=[5]"))
    with threadpool_limits(limits=2, user_api="blas"):
        manifest = run_protocol(protocol, tmp_path, jobs=1)
        after = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
    assert [e["status"] for e in manifest["trials"]] == ["ok"]
    assert len(seen) == 1
    assert set(seen[0]) == {1}, seen
    assert set(after) == {2}


def test_poses_round_trip_through_foxglove_pose_in_frame(tiny_run: Any) -> None:
    out, manifest = tiny_run
    _, messages, _ = read_mcap(out / "tiny" / manifest["trials"][0]["mcap"])
    desired = [d for topic, _, d in messages if topic == "/robot/pose/desired"]
    ref = s_trajectory()
    for k in (0, 10, 20):
        d = desired[k]
        assert d["frameId"] == "workspace"
        p, q = d["pose"]["position"], d["pose"]["orientation"]
        want = ref.pose(k / 25.5)
        assert p["x"] == pytest.approx(want[0], abs=1e-12)
        assert p["y"] == pytest.approx(want[1], abs=1e-12)
        assert "z" not in p  # proto3 leaves the 0 out
        theta = yaw_of(q.get("z", 0.0), q.get("w", 0.0))
        assert math.cos(theta - want[2]) == pytest.approx(1.0, abs=1e-12)


def test_rrd_reads_back_with_its_entities_and_passes_rerun_verify(tiny_run: Any) -> None:
    from rerun.chunk import RrdReader

    out, manifest = tiny_run
    path = out / "tiny" / manifest["trials"][0]["rrd"]
    reader = RrdReader(path)
    assert [b.application_id for b in reader.blueprints()] == ["magrun"]  # the default layout
    entities = {str(chunk.entity_path) for chunk in reader.stream()}
    for entity in (
        "/camera/image", "/camera/actual", "/camera/paths/actual", "/workspace/actual",
        "/workspace/paths/predicted", "/coils/currents", "/errors/position_mm",
    ):  # fmt: skip
        assert entity in entities
    rerun = Path(sys.executable).with_name("rerun")
    done = subprocess.run([str(rerun), "rrd", "verify", str(path)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_rerun_decodes_the_mcap_natively(tiny_run: Any) -> None:
    from rerun.chunk import McapReader

    out, manifest = tiny_run
    reader = McapReader(out / "tiny" / manifest["trials"][0]["mcap"])
    entities = {str(chunk.entity_path) for chunk in reader.stream()}
    assert {"/robot/pose/actual", "/camera/image", "/coils/currents"} <= entities


def test_ray_trials_on_two_nodes_come_back_to_the_drivers_folder(
    tiny_run: Any, tmp_path: Path
) -> None:
    """A local two-node Ray cluster (a head and a second raylet, one CPU each): every trial
    records on its node into the node's own temporary folder and comes back with its result;
    the driver writes it. Both nodes ran trials, and every recording at the driver is the
    in-process run's, message for message, with its summary index (the topic counts). A stop
    once the first trial is back leaves the other three pending, none of them written."""
    pytest.importorskip("ray")
    import signal

    import ray
    from ray.cluster_utils import Cluster

    from magrun import interrupt

    store = 100 * 1024**2
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 1, "object_store_memory": store, "include_dashboard": False},
    )
    try:
        cluster.add_node(num_cpus=1, object_store_memory=store)
        cluster.wait_for_nodes()
        # as `magrun run --executor ray --ray-address ADDR --jobs 2` makes it
        executor = ray_executor(cluster.address, num_cpus=2)
        manifest = run_protocol(load_protocol(TINY), tmp_path, executor=executor)
        assert not ray.is_initialized()  # the executor connected, and let go
        # a stop once the first trial is back: the others are cancelled, none written
        interrupt.clear()
        try:
            stopped = run_protocol(
                load_protocol(TINY), tmp_path / "stopped", executor=executor,
                on_trial=lambda entry: interrupt.request(signal.SIGINT),
            )  # fmt: skip
        finally:
            interrupt.clear()
    finally:
        ray.shutdown()
        cluster.shutdown()
    statuses = sorted(e["status"] for e in stopped["trials"])
    assert statuses == ["ok", "pending", "pending", "pending"], statuses
    assert stopped["interrupted"] == "SIGINT"
    assert len(list((tmp_path / "stopped" / "tiny").rglob("*.mcap"))) == 1
    entries = manifest["trials"]
    assert {e["status"] for e in entries} == {"ok"}
    assert len({e["ray_node"] for e in entries}) == 2
    out1, local = tiny_run
    assert [e["mcap"] for e in entries] == [e["mcap"] for e in local["trials"]]
    for e in entries:
        here = read_mcap(out1 / "tiny" / e["mcap"])
        there = read_mcap(tmp_path / "tiny" / e["mcap"])
        assert there[0] == here[0]
        assert there[0]["/robot/pose/actual"] == e["ticks"]
        assert there[1] == here[1]
        assert (tmp_path / "tiny" / e["rrd"]).stat().st_size > 0
    assert not list(tmp_path.rglob("*.part"))


def test_no_ray_cluster_at_the_address_is_a_clear_error(tmp_path: Path) -> None:
    """Nothing at the address, or no port in it: exit 2 at once, the address named (Ray's own
    connection attempt waits for many minutes)."""
    pytest.importorskip("ray")
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    result = CliRunner().invoke(
        cli,
        ["run", str(TINY), "--out", str(tmp_path), "--executor", "ray",
         "--ray-address", f"127.0.0.1:{port}"],
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert f"could not connect to the Ray cluster at 127.0.0.1:{port}" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "tiny").exists()  # nothing written: the same command runs again
    bad = CliRunner().invoke(
        cli, ["run", str(TINY), "--out", str(tmp_path / "b"), "--executor", "ray",
              "--ray-address", "head-without-port"],
    )  # fmt: skip
    assert bad.exit_code == 2, bad.output
    assert "give HOST:PORT" in bad.output


def test_a_ray_task_cannot_write_outside_the_output_folder(tmp_path: Path) -> None:
    from magrun.runner import _write_back

    for rel in ("../escape.mcap", "/abs/path.mcap", ""):
        with pytest.raises(RunError, match="outside the output folder"):
            _write_back(tmp_path / "out", {rel: b"x"})
    assert not (tmp_path / "escape.mcap").exists()
    _write_back(tmp_path / "out", {"p/a/trial-0.mcap": b"data"})
    assert (tmp_path / "out" / "p" / "a" / "trial-0.mcap").read_bytes() == b"data"


def test_analysis_reads_the_runner_recordings_to_the_same_errors(tiny_run: Any) -> None:
    # the analysis package computes its errors from the MCAP alone; magrun computed the
    # manifest's from the loop's arrays: two independent computations of the same RMS
    import analysis

    out, manifest = tiny_run
    data = analysis.load(out)
    assert not data.problems
    by_path = {Path(p).relative_to(out / "tiny").as_posix(): row for p, row in zip(
        data.trials["path"], data.trials.to_dict("records"), strict=True)}  # fmt: skip
    for entry in manifest["trials"]:
        row = by_path[entry["mcap"]]
        for key in ("rms_position_mm", "rms_orientation_deg", "rms_prediction_position_mm",
                    "rms_prediction_orientation_deg"):  # fmt: skip
            if entry[key] is None:  # no predictions (a PID baseline): empty in both
                assert math.isnan(row[key]), key
            else:
                assert row[key] == pytest.approx(entry[key], rel=1e-9, abs=1e-12), key
        assert row["ticks"] == entry["ticks"]
        assert (row["method"], row["trial"]) == (entry["method"], entry["trial"])
        rec = data.recordings[row["path"]]
        assert rec.workspace["half_width_m"] > 0.02


def test_run_refuses_to_overwrite_recordings(tiny_run: Any) -> None:
    out, _ = tiny_run
    result = CliRunner().invoke(cli, ["run", str(TINY), "--out", str(out)])
    assert result.exit_code == 2
    assert "--overwrite" in result.output


def test_view_save_converts_an_mcap_to_a_verified_rrd(tiny_run: Any, tmp_path: Path) -> None:
    out, manifest = tiny_run
    target = tmp_path / "converted.rrd"
    src = out / "tiny" / manifest["trials"][0]["mcap"]
    result = CliRunner().invoke(cli, ["view", str(src), "--save", str(target)])
    assert result.exit_code == 0, result.output
    rerun = Path(sys.executable).with_name("rerun")
    assert subprocess.run([str(rerun), "rrd", "verify", str(target)], check=False).returncode == 0


def test_view_names_a_cut_mcap_and_the_fix(tiny_run: Any, tmp_path: Path) -> None:
    out, manifest = tiny_run
    data = (out / "tiny" / manifest["trials"][0]["mcap"]).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    result = CliRunner().invoke(cli, ["view", str(cut), "--save", str(tmp_path / "x.rrd")])
    assert result.exit_code == 2
    assert str(cut) in result.output
    assert "magrun recover" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "x.rrd").exists()


def test_view_rejects_other_files(tmp_path: Path) -> None:
    other = tmp_path / "x.csv"
    other.write_text("a\n")
    result = CliRunner().invoke(cli, ["view", str(other)])
    assert result.exit_code == 2
    assert "not a recording" in result.output


def test_hardware_rig_is_refused_before_anything_is_written(tmp_path: Path) -> None:
    args = ["run", str(TINY), "--out", str(tmp_path), "--rig", "hardware"]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2
    assert "--rig hardware needs --driver" in result.output
    assert not any(tmp_path.iterdir())


def test_protocol_schema_command_prints_json() -> None:
    result = CliRunner().invoke(cli, ["protocol", "schema"])
    assert result.exit_code == 0
    schema = json.loads(result.output)
    assert schema["additionalProperties"] is False
    assert "sweep" in schema["properties"]


# ---- the recorder --------------------------------------------------------------------------


def _tick(k: int) -> Tick:
    from magrun.records import ControllerStatus

    pose = np.array([1e-3 * k, 0.0, 0.1])
    return Tick(
        k=k, t=k * 0.04, actual=pose, tracked=None, measured=None, estimated=pose,
        predicted=None, desired=pose, currents=np.zeros(2), status=ControllerStatus(0.001),
        compute_time=0.001,
    )  # fmt: skip


def test_a_full_queue_drops_ticks_counts_them_and_never_blocks(tmp_path: Path) -> None:
    setup = RecordingSetup(trial={"method": "x"}, channel_names=("a", "b"))
    rec = TrialRecorder(tmp_path / "trial-0", setup, queue_size=2)
    entered, release = threading.Event(), threading.Event()
    original = rec._write

    def slow_write(tick: Tick) -> None:
        entered.set()
        release.wait(timeout=30)
        original(tick)

    rec._write = slow_write  # type: ignore[method-assign]
    rec.start()
    rec.log(_tick(0))
    assert entered.wait(timeout=30)  # the writer holds tick 0 ...
    for k in range(1, 10):
        rec.log(_tick(k))  # ... the queue takes 2 more: 7 are dropped
    release.set()
    stats = rec.close()
    assert stats.ticks_logged == 10
    assert stats.dropped_ticks == 7
    assert stats.ticks_written == 3
    counts, _, meta = read_mcap(rec.mcap_path)
    assert counts["/robot/pose/actual"] == 3
    assert meta["recorder"]["dropped_ticks"] == "7"


def test_a_writer_failure_is_reported_not_silent(tmp_path: Path) -> None:
    setup = RecordingSetup(trial={}, channel_names=("a", "b"))
    rec = TrialRecorder(tmp_path / "trial-0", setup)

    def broken(tick: Tick) -> None:
        raise OSError("disk full")

    rec._write = broken  # type: ignore[method-assign]
    with rec:
        for k in range(3):
            rec.log(_tick(k))
    assert rec.status == "failed"
    assert "disk full" in rec.stats.error
    assert read_mcap(rec.mcap_path)[2]["recorder"]["error"] == "OSError: disk full"


# ---- honest timing -------------------------------------------------------------------------


class _LoggingRig:
    """A SimRig that logs the order of apply and advance calls."""

    def __init__(self) -> None:
        self.rig = SimRig.default(seed=0)
        self.calls: list[tuple[str, float]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.rig, name)

    def apply(self, currents: Any) -> Any:
        self.calls.append(("apply", 0.0))
        return self.rig.apply(currents)

    def advance(self, duration: float) -> None:
        self.calls.append(("advance", duration))
        self.rig.advance(duration)


@pytest.mark.parametrize("compute_ticks", [0.25, 2.5])
def test_measured_latency_delays_the_currents_and_stretches_overrunning_ticks(
    compute_ticks: float,
) -> None:
    controller = make_controller("baseline3")
    dt = controller.dt
    c = compute_ticks * dt
    times = iter(np.arange(1000) * c)  # the loop reads the clock before and after: c apart
    rig = _LoggingRig()
    log = run_trial(
        controller, rig, s_trajectory(), duration=0.5, latency="measured",  # type: ignore[arg-type]
        clock=lambda: float(next(times)),
    )  # fmt: skip
    period = max(dt, c)
    np.testing.assert_allclose(np.diff(log.t), period, rtol=1e-12)
    np.testing.assert_allclose(log.compute_time, c, rtol=1e-9)
    # each tick: the plant runs c with the old currents, then the new ones for the rest
    first = rig.calls[:3] if c < dt else rig.calls[:2]
    assert first[0] == ("advance", pytest.approx(c))
    assert first[1] == ("apply", 0.0)
    if c < dt:
        assert first[2] == ("advance", pytest.approx(dt - c))
    assert len(log.t) == math.floor(0.5 / period + 1e-9) + 1


@pytest.mark.parametrize("latency_ticks", [0.0, 0.125, 1.5])
def test_declared_latency_ignores_the_clock(latency_ticks: float) -> None:
    """A declared latency passes on the plant (old currents) whatever the controller's wall
    time was: a clock that claims 3 ticks of compute per tick changes nothing but the logged
    compute time, and the plant's schedule is that of the declared latency."""
    controller = make_controller("baseline3")
    dt = controller.dt
    latency = latency_ticks * dt
    slow = iter(np.arange(1000) * 3 * dt)
    rig = _LoggingRig()
    log = run_trial(
        controller, rig, s_trajectory(), duration=0.5, latency=latency,  # type: ignore[arg-type]
        clock=lambda: float(next(slow)),
    )  # fmt: skip
    period = max(dt, latency)
    np.testing.assert_allclose(np.diff(log.t), period, rtol=1e-12)
    np.testing.assert_allclose(log.compute_time, 3 * dt, rtol=1e-9)  # measured, logged
    expected = [("apply", 0.0), ("advance", pytest.approx(dt))]
    if latency > 0:
        rest = [("advance", pytest.approx(period - latency))] if latency < dt else []
        expected = [("advance", pytest.approx(latency)), ("apply", 0.0), *rest]
    assert rig.calls[: len(expected)] == expected
    assert len(log.t) == math.floor(0.5 / period + 1e-9) + 1


@pytest.mark.parametrize("latency_ticks", [0.0, 0.125, 1.5])
def test_the_window_prepared_is_the_next_ticks_to_the_bit(latency_ticks: float) -> None:
    """The loop prepares the next tick with the reference window at the time the rig's
    clock will then read, to the bit, whatever latency is declared (the plant advanced in
    two parts in a tick: a window a rounding apart would not use the preparation)."""
    controller = make_controller("baseline3")
    prepared: list[np.ndarray] = []
    planned: list[np.ndarray] = []
    step, prepare = controller.step, controller.prepare

    def stepping(z, window, age=0.0):  # type: ignore[no-untyped-def]
        planned.append(np.array(window))
        return step(z, window, age)

    def preparing(window) -> None:  # type: ignore[no-untyped-def]
        prepared.append(np.array(window))
        prepare(window)

    controller.step, controller.prepare = stepping, preparing  # type: ignore[method-assign]
    latency = latency_ticks * controller.dt
    log = run_trial(
        controller, SimRig.default(seed=0), s_trajectory(), duration=2.0, latency=latency
    )
    assert len(planned) == len(log.t) > 30
    for before, after in zip(prepared[:-1], planned[1:], strict=True):
        np.testing.assert_array_equal(after, before)


def test_without_charging_the_plant_waits_for_the_controller() -> None:
    controller = make_controller("baseline3")
    rig = _LoggingRig()
    log = run_trial(controller, rig, s_trajectory(), duration=0.2)  # type: ignore[arg-type]
    assert rig.calls[:2] == [("apply", 0.0), ("advance", controller.dt)]
    np.testing.assert_allclose(np.diff(log.t), controller.dt, rtol=1e-9)


def test_a_dead_worker_becomes_a_failed_trial_not_a_crashed_run() -> None:
    from concurrent.futures.process import BrokenProcessPool

    from magrun.runner import _result_or_failure

    trial = load_protocol(TINY).expand()[0]

    def dead() -> dict[str, Any]:
        raise BrokenProcessPool("a child process terminated abruptly")

    entry = _result_or_failure(dead, trial)
    assert entry["status"] == "failed"
    assert "terminated abruptly" in entry["error"]
    assert entry["path"] == "baseline3_rate-5hz/trial-0"


# -- stopping and resuming ----------------------------------------------------------------------


def _long_tiny(tmp_path: Path, duration_s: float = 1.0) -> Path:
    text = TINY.read_text().replace("duration_s: 1.0", f"duration_s: {duration_s}")
    path = tmp_path / "tiny.yaml"
    path.write_text(text)
    return path


def test_a_stop_request_ends_the_trial_cleanly_and_resume_runs_the_rest(tmp_path: Path) -> None:
    """Stop requested at tick 10 of the first trial: its currents ramp to zero (recorded), it
    ends with its recordings indexed and marked interrupted, no other trial starts; --resume
    keeps nothing unfinished and runs all."""
    import signal

    from magrun import interrupt

    protocol = load_protocol(_long_tiny(tmp_path))
    interrupt.clear()

    def progress(relpath: str, done: int, total: int) -> None:
        if done == 10:
            interrupt.request(signal.SIGTERM)

    try:
        manifest = run_protocol(protocol, tmp_path / "out", jobs=1, progress=progress)
        assert manifest["interrupted"] == "SIGTERM"
        statuses = [e["status"] for e in manifest["trials"]]
        assert statuses == ["interrupted", "pending", "pending", "pending"]
        first = manifest["trials"][0]
        assert 10 < first["ticks"] <= 10 + 3  # the ramp from ≤ 30 A at 12 A a tick
        assert "SIGTERM" in first["error"]
        counts, messages, meta = read_mcap(tmp_path / "out" / "tiny" / first["mcap"])  # indexed
        assert counts["/robot/pose/actual"] == first["ticks"]
        currents = [m for topic, _, m in messages if topic == "/coils/currents"]
        assert not any(currents[-1].get("currents", []))  # the last tick drives 0 A
        assert any(currents[-2].get("currents", []))
        assert meta["recorder"]["status"] == "interrupted"
        assert "SIGTERM" in meta["recorder"]["reason"]
        with pytest.raises(RunError, match="--resume"):
            run_protocol(protocol, tmp_path / "out", jobs=1)
    finally:
        interrupt.clear()
    resumed = run_protocol(protocol, tmp_path / "out", jobs=1, resume=True)
    assert [e["status"] for e in resumed["trials"]] == ["ok"] * 4
    assert "interrupted" not in resumed
    counts, _, _ = read_mcap(tmp_path / "out" / "tiny" / resumed["trials"][0]["mcap"])
    assert counts["/robot/pose/actual"] == resumed["trials"][0]["ticks"] > 10
    # a second resume finds everything done and runs nothing
    mtimes = {p: p.stat().st_mtime_ns for p in (tmp_path / "out" / "tiny").rglob("*.mcap")}
    again = run_protocol(protocol, tmp_path / "out", jobs=1, resume=True)
    assert [e["status"] for e in again["trials"]] == ["ok"] * 4
    assert {p: p.stat().st_mtime_ns for p in mtimes} == mtimes


def test_a_safety_stop_is_recorded_with_its_reason_and_kept_by_resume(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A trip at t ≥ 0.2 s (here: forced) ends the trial after the ramp to zero: status
    "stopped", the reason in the manifest, the summary and the MCAP; --resume keeps it."""
    from magrun.safety import SafetyLayer

    check = SafetyLayer.check

    def tripping(self, t, pose, tracked=None):
        check(self, t, pose, tracked)
        if t >= 0.2:
            self.trip("forced by the test", t)

    monkeypatch.setattr(SafetyLayer, "check", tripping)
    protocol = load_protocol(_long_tiny(tmp_path))
    manifest = run_protocol(protocol, tmp_path / "out", jobs=1)
    entries = manifest["trials"]
    assert {e["status"] for e in entries} == {"stopped"}
    for e in entries:
        assert e["error"].startswith("safety stop at t = 0.2")
        assert e["error"].endswith("forced by the test")
        assert e["stopped_at_s"] == pytest.approx(0.2, abs=0.04)
        _, messages, meta = read_mcap(tmp_path / "out" / "tiny" / e["mcap"])
        assert meta["recorder"]["status"] == "stopped"
        assert meta["recorder"]["reason"] == e["error"]
        currents = [m for topic, _, m in messages if topic == "/coils/currents"]
        assert not any(currents[-1].get("currents", []))
    monkeypatch.undo()
    again = run_protocol(protocol, tmp_path / "out", jobs=1, resume=True)
    assert [e["status"] for e in again["trials"]] == ["stopped"] * len(entries)


def test_resume_refuses_another_runs_folder(tmp_path: Path) -> None:
    protocol = load_protocol(TINY)
    run_protocol(protocol, tmp_path, jobs=1, quick=True)
    with pytest.raises(RunError, match="records another run"):
        run_protocol(protocol, tmp_path, jobs=1, resume=True)  # not --quick this time


@pytest.mark.parametrize(
    ("signum", "status", "jobs"), [("SIGTERM", 143, 1), ("SIGINT", 130, 1), ("SIGTERM", 143, 2)]
)
def test_magrun_run_exits_128_plus_the_signal(
    tmp_path: Path, signum: str, status: int, jobs: int
) -> None:
    """A real signal to a running `magrun run` (to the parent only, also with worker
    processes): exit status 128 + n, the manifest marks the running trials, and their MCAP
    files are complete (indexed)."""
    import signal
    import subprocess
    import sys
    import time

    path = _long_tiny(tmp_path, duration_s=60.0)
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "magrun.cli", "run", str(path), "--out", str(out),
         "--jobs", str(jobs)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while not list(out.rglob("*.mcap")) and time.monotonic() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)  # into the first trial
    proc.send_signal(getattr(signal, signum))
    summary, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err
    assert "--resume" in err
    assert f"[1/{len(load_protocol(path).expand())}] tiny/" in err  # no terminal: line per trial
    # the summary names the interrupted trials and their reason; nothing reads "nan" or FAILED
    assert "INTERRUPTED " in summary
    assert "stopped by" in summary
    assert "nan" not in summary
    assert "FAILED" not in summary
    manifest = json.loads((out / "tiny" / "manifest.json").read_text())
    assert manifest["interrupted"] == signum
    stopped = [e for e in manifest["trials"] if e["status"] == "interrupted"]
    assert 1 <= len(stopped) <= jobs
    assert {e["status"] for e in manifest["trials"]} <= {"interrupted", "pending"}
    for entry in stopped:
        counts, _, meta = read_mcap(out / "tiny" / entry["mcap"])
        assert counts["/robot/pose/actual"] == entry["ticks"]
        assert meta["recorder"]["status"] == "interrupted"


def _spawned_children(pid: int) -> int:
    """How many processes ``pid`` has started with multiprocessing's spawn (Linux /proc)."""
    count = 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            line = (stat.parent / "cmdline").read_bytes()
        except (OSError, ValueError, IndexError):
            continue  # gone meanwhile
        count += parent == pid and b"spawn_main" in line
    return count


def _cpu_seconds(pid: int) -> float:
    """CPU time, s, that process ``pid`` has used so far (Linux /proc; 0 once it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def _as_from_a_terminal() -> None:
    """A child as a terminal starts it: SIGINT at its default (a test run from a script in
    the background inherits it ignored) and its own process group, for the Ctrl-C."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds the workers in /proc")
@pytest.mark.parametrize(
    ("moment", "signum"),
    [("importing", "SIGINT"), ("workers starting", "SIGINT"), ("workers starting", "SIGTERM")],
)
def test_a_ctrl_c_at_any_moment_of_a_two_job_run_is_clean(
    tmp_path: Path, moment: str, signum: str
) -> None:
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) while the command
    still imports, or while its two worker processes import (seconds: torch, CasADi), and
    SIGTERM to the parent alone then (which passes it on): exit 128 + n, no traceback
    anywhere (the workers' own stderr included), and every trial pending or interrupted,
    never failed; after the workers' start --resume (with --jobs 1) runs them all."""
    import os
    import signal
    import time

    out = tmp_path / "out"
    run = [sys.executable, "-m", "magrun.console", "run", str(TINY), "--out", str(out)]
    command = [*run, "--jobs", "2"]
    proc = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, preexec_fn=_as_from_a_terminal,
    )  # fmt: skip
    manifest = out / "tiny" / "manifest.json"
    if moment == "importing":
        # past the interpreter's own start-up (its site module, under 0.1 s of CPU: a Ctrl-C
        # there is CPython's "Fatal Python error", before any of magrun runs) and into
        # magrun's imports (seconds of CPU): counted in the child's CPU time, not the wall
        # clock, which a loaded machine stretches
        deadline = time.monotonic() + 120
        while _cpu_seconds(proc.pid) < 0.3 and proc.poll() is None:
            assert time.monotonic() < deadline
            time.sleep(0.01)
    else:
        deadline = time.monotonic() + 120
        while _spawned_children(proc.pid) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert _spawned_children(proc.pid) >= 2
        time.sleep(0.3)  # into the workers' imports, which take seconds
    if signum == "SIGINT":
        os.killpg(proc.pid, signal.SIGINT)
    else:
        proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + getattr(signal, signum), stderr
    assert "Traceback" not in stdout + stderr, stderr
    assert "Aborted" not in stderr
    if manifest.exists():
        statuses = {e["status"] for e in json.loads(manifest.read_text())["trials"]}
        assert statuses <= {"pending", "interrupted"}, statuses
    if moment == "workers starting" and signum == "SIGINT":
        # the folder the stopped run left, resumed (in the command's own process: the
        # workers' start is not what a resume checks)
        again = subprocess.run(
            [*run, "--jobs", "1", "--resume"], capture_output=True, text=True, timeout=300
        )  # fmt: skip
        assert again.returncode == 0, again.stderr
        assert {e["status"] for e in json.loads(manifest.read_text())["trials"]} == {"ok"}


def _run_module(tmp_path: Path, source: str) -> subprocess.CompletedProcess[str]:
    """Run ``source`` as ``python -m`` runs a module (the way ``python -m magrun.console``
    starts), with magrun importable."""
    (tmp_path / "probe_main.py").write_text(source)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    return subprocess.run(
        [sys.executable, "-m", "probe_main"], capture_output=True, text=True, env=env,
        timeout=120, cwd=tmp_path,
    )  # fmt: skip


def test_exit_interrupted_returns_130_after_a_ctrl_c_that_escaped_exec(tmp_path: Path) -> None:
    """A KeyboardInterrupt that escaped code run by ``exec`` of a string (as dataclasses
    build their methods while modules import) and was then caught: CPython 3.11 still
    counts it as unhandled and a normal exit of ``python -m`` kills the process with SIGINT
    (return code -2, checked here first); exit_interrupted returns 130 and one line."""
    source = (
        "import sys\n"
        "try:\n"
        "    exec('raise KeyboardInterrupt')\n"
        "except KeyboardInterrupt:\n"
        "    caught = True\n"
        "if sys.argv[1:] == []:\n"
        "    from magrun.interrupt import exit_interrupted\n"
        "    exit_interrupted()\n"
    )
    quirk = _run_module(tmp_path, source.replace("if sys.argv[1:] == []:", "if False:")
                        + "sys.exit(130)\n")  # fmt: skip
    assert quirk.returncode in (130, -2)  # -2 on CPython 3.11, where the quirk lives
    done = _run_module(tmp_path, source)
    assert done.returncode == 130, done.stderr
    assert done.stderr == "\ninterrupted\n"


def test_a_stop_signal_an_import_turned_into_another_error_still_exits_130(
    tmp_path: Path,
) -> None:
    """A compiled extension whose initialisation a Ctrl-C interrupts raises ImportError
    ("initialization failed"), not KeyboardInterrupt. Once the signal was remembered
    (magrun.console's guard), the command ends with 130 and one line; without a remembered
    signal the same error is the bug it is and keeps its traceback."""
    source = (
        "import signal, sys, click\n"
        "import magrun.cli as c\n"
        "from magrun import interrupt\n"
        "@click.command('boom')\n"
        "def boom():\n"
        "    if REMEMBERED:\n"
        "        interrupt.request(signal.SIGINT)\n"
        "    raise ImportError('initialization failed')\n"
        "c.cli.add_command(boom)\n"
        "sys.argv = ['magrun', 'boom']\n"
        "c.main()\n"
    )
    stopped = _run_module(tmp_path, "REMEMBERED = True\n" + source)
    assert stopped.returncode == 130, stopped.stderr
    assert stopped.stderr.strip() == "interrupted"
    failed = _run_module(tmp_path, "REMEMBERED = False\n" + source)
    assert failed.returncode == 1
    assert "ImportError: initialization failed" in failed.stderr


def test_remembering_ctrl_c_raises_and_remembers_then_restores() -> None:
    """Inside the block SIGINT raises KeyboardInterrupt and is remembered (a swallowed
    exception still stops the command); after it, the previous handler is back."""
    import signal
    import time

    from magrun import interrupt

    def ctrl_c_inside() -> None:
        with interrupt.remembering_ctrl_c():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler runs (and raises) at once: never reaches the end

    before = signal.getsignal(signal.SIGINT)
    interrupt.clear()
    try:
        with pytest.raises(KeyboardInterrupt):
            ctrl_c_inside()
        assert interrupt.requested() == signal.SIGINT
    finally:
        interrupt.clear()
    assert signal.getsignal(signal.SIGINT) is before


def test_a_declared_latency_gives_the_same_recordings_under_load_and_with_any_jobs(
    tmp_path: Path,
) -> None:
    """The same protocol and seed with the default declared latency (camera tracking, two
    methods, two rates): run alone in one process, then with --jobs 2 beside a process that
    keeps a core busy (three busy processes on a two-core machine: each trial's ticks take
    longer, and wait). Every pose, current and status message is identical (the status
    without its wall-clock fields): neither the job count nor the load changes a
    recording."""
    text = TINY.read_text().replace("latency_ms: none", "latency_ms: 5")
    assert "latency_ms: 5" in text
    path = tmp_path / "tiny.yaml"
    path.write_text(text)
    protocol = load_protocol(path)
    quiet = run_protocol(protocol, tmp_path / "quiet", jobs=1)
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])]
    try:
        loaded = run_protocol(protocol, tmp_path / "loaded", jobs=2)
    finally:
        for proc in burners:
            proc.kill()
            proc.wait()
    assert [e["status"] for e in quiet["trials"]] == ["ok"] * 4
    assert [e["status"] for e in loaded["trials"]] == ["ok"] * 4
    for entry in quiet["trials"]:
        _, a, _ = read_mcap(tmp_path / "quiet" / "tiny" / entry["mcap"])
        _, b, _ = read_mcap(tmp_path / "loaded" / "tiny" / entry["mcap"])
        assert len(a) == len(b) > 0
        assert a == b, entry["path"]


@pytest.mark.parametrize("kind", ["rrd", "mcap"])
def test_view_web_serves_the_viewer_on_localhost(tiny_run: Any, kind: str) -> None:
    """`magrun view FILE --web --port N` answers HTTP on 127.0.0.1:N and prints the URL, for
    an .rrd and for an .mcap (converted first); SIGTERM stops it as Ctrl-C does."""
    import os
    import signal
    import socket
    import time
    import urllib.request

    out, manifest = tiny_run
    rrd = out / "tiny" / manifest["trials"][0][kind]
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "magrun.cli", "view", str(rrd), "--web", "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    status = None
    try:
        deadline = time.monotonic() + 120
        while status is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as reply:
                    status = reply.status
            except OSError:
                time.sleep(0.5)
    finally:
        os.killpg(proc.pid, signal.SIGTERM)  # magrun and the viewer it started
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:  # reported below, never left running
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
            err = f"still running 60 s after SIGTERM\n{err}"
    assert status == 200, err
    assert proc.returncode == 130, err  # stopped as by Ctrl-C, temporary files removed
    assert f"http://127.0.0.1:{port}/?url=rerun" in err


def test_view_without_a_display_points_to_web(
    tiny_run: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    out, manifest = tiny_run
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    result = CliRunner().invoke(cli, ["view", str(out / "tiny" / manifest["trials"][0]["rrd"])])
    assert result.exit_code == 2
    assert "no display" in result.output
    assert "--web" in result.output


HOLD = """
import sys, time
from magrun.atomic import FolderLock
with FolderLock(sys.argv[1]):
    print("held", flush=True)
    sys.stdin.read()  # until the test closes our stdin
"""


def test_one_writer_per_run_folder_across_processes(tmp_path: Path) -> None:
    """Two runs into one folder once both exited 0 with both recordings unreadable; an
    --overwrite during a live run deleted its files. With another process holding the
    folder, a run, a --resume and an --overwrite are each refused (exit 2) and nothing in the
    folder is touched; once that process is gone (the OS releases its lock, whatever way it
    ended), the run goes ahead."""
    out = tmp_path / "out"
    folder = out / "tiny"
    folder.mkdir(parents=True)
    (folder / "trial-0.mcap").write_bytes(b"recorded")
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline().strip() == "held"
        for extra in ([], ["--resume"], ["--overwrite"]):
            result = CliRunner().invoke(cli, ["run", str(TINY), "--out", str(out), *extra])
            assert result.exit_code == 2, (extra, result.output)
            assert "being written by another magrun (pid" in result.output
            assert "Traceback" not in result.output
        assert (folder / "trial-0.mcap").read_bytes() == b"recorded"
    finally:
        holder.kill()  # a crash: its lock file stays, its lock does not
        holder.wait(30)
        for stream in (holder.stdin, holder.stdout):
            if stream is not None:
                stream.close()
    assert (folder / ".magrun-lock").exists()
    manifest = run_protocol(load_protocol(TINY), out, overwrite=True)
    assert all(e["status"] == "ok" for e in manifest["trials"])
    assert not (folder / ".magrun-lock").exists()


def test_a_run_refused_for_a_busy_folder_writes_nothing(tmp_path: Path) -> None:
    from magrun.atomic import FolderLock

    folder = tmp_path / "out" / "tiny"
    with FolderLock(folder), pytest.raises(RunError, match="another magrun"):
        run_protocol(load_protocol(TINY), tmp_path / "out")
    assert folder.is_dir()  # the holder's folder stays; the lock file went with the holder
    assert list(folder.iterdir()) == []


def test_resume_runs_a_trial_again_whose_recording_is_broken(tmp_path: Path) -> None:
    """`--resume` kept a truncated `ok` trial as ok. Now each kept trial's MCAP must be
    indexed with one status message per recorded tick: the truncated one and one whose file
    is gone run again, the intact ones are kept untouched."""
    out = tmp_path / "out"
    first = run_protocol(load_protocol(TINY), out)
    folder = out / "tiny"
    cut, gone, *kept = first["trials"]
    path = folder / cut["mcap"]
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    (folder / gone["mcap"]).unlink()
    mtimes = {e["mcap"]: (folder / e["mcap"]).stat().st_mtime_ns for e in kept}
    resumed = run_protocol(load_protocol(TINY), out, resume=True)
    assert [e["status"] for e in resumed["trials"]] == ["ok"] * len(first["trials"])
    for entry in (cut, gone):
        counts, _, _ = read_mcap(folder / entry["mcap"])  # whole again
        assert counts["/controller/status"] == entry["ticks"] - entry["dropped_ticks"]
    assert {e["mcap"]: (folder / e["mcap"]).stat().st_mtime_ns for e in kept} == mtimes


def test_view_save_of_a_damaged_recording_exits_2_and_writes_nothing(
    tiny_run: Any, tmp_path: Path
) -> None:
    """Bits flipped in a recording (40 each, 12 seeds) ended `view --save` in ZstdError,
    protobuf's DecodeError or McapError tracebacks. Now each either converts or exits 2
    naming the damage, and a failed one leaves no .rrd, partial or otherwise."""
    import random

    out, manifest = tiny_run
    data = (out / "tiny" / manifest["trials"][0]["mcap"]).read_bytes()
    codes = []
    for seed in range(12):
        rng, damaged = random.Random(seed), bytearray(data)
        for _ in range(40):
            damaged[rng.randrange(100, len(damaged))] ^= 1 << rng.randrange(8)
        src, target = tmp_path / f"flip{seed}.mcap", tmp_path / f"flip{seed}.rrd"
        src.write_bytes(bytes(damaged))
        result = CliRunner().invoke(cli, ["view", str(src), "--save", str(target)])
        assert result.exit_code in (0, 2), (seed, result.output)
        assert "Traceback" not in result.output
        if result.exit_code == 2:
            assert str(src) in result.output  # the file named, with what is wrong
            assert not target.exists()
        codes.append(result.exit_code)
    assert 2 in codes  # the damage was seen at least once
    assert not list(tmp_path.glob(".*part*"))
