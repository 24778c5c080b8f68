"""The ``magrun field`` verbs, in process (click's runner) and once as the installed script."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from magrun.cli import cli
from magrun.field.comsol import write_comsol_map
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def test_fit_json_reports_mae_and_r2_per_coil_and_order(runner: CliRunner, tmp_path) -> None:
    result = runner.invoke(
        cli, ["field", "fit", "--out", str(tmp_path), "--max-order", "6", "--json"]
    )
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert set(report["coil_types"]) == {"small", "medium", "large"}
    for rep in report["coil_types"].values():
        assert [o["order"] for o in rep["orders"]] == [1, 2, 3, 4, 5, 6]
        r2 = [o["r2"] for o in rep["orders"]]
        # nested least-squares models: more terms never explain less variance
        assert all(np.diff(r2) >= -1e-12)
        assert all(o["mae_mT"] > 0 for o in rep["orders"])
        assert 1 <= rep["selected_order"] <= 6
    model = ZernikeFieldModel.load(report["files"]["model"])
    assert {t: f.order for t, f in model.fits.items()} == {
        t: r["selected_order"] for t, r in report["coil_types"].items()
    }
    with np.load(report["files"]["figure"]) as fig:
        assert fig["small_field_mT"].shape == fig["small_error_mT"].shape == (101, 101)


def test_fit_with_fixed_orders(runner: CliRunner, tmp_path) -> None:
    result = runner.invoke(
        cli,
        [
            "field",
            "fit",
            "--out",
            str(tmp_path),
            "--max-order",
            "5",
            "--order",
            "small=4",
            "--order",
            "medium=3",
            "--order",
            "large=3",
        ],
    )
    assert result.exit_code == 0, result.output
    assert "small: selected order 4 (fixed)" in result.output
    model = ZernikeFieldModel.load(tmp_path / "zernike_model.json")
    assert {t: f.order for t, f in model.fits.items()} == {"small": 4, "medium": 3, "large": 3}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--order", "small"], "TYPE=N"),
        (["--order", "tiny=3"], "unknown coil types ['tiny']"),
        (["--order", "small=9", "--max-order", "4"], "outside 1..4"),
    ],
)
def test_fit_bad_options_exit_2_without_traceback(
    runner: CliRunner, tmp_path, args, message
) -> None:
    result = runner.invoke(cli, ["field", "fit", "--out", str(tmp_path), *args])
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_reference_command_writes_loadable_maps(runner: CliRunner, tmp_path) -> None:
    out = tmp_path / "maps.npz"
    result = runner.invoke(cli, ["field", "reference", "--out", str(out), "--pitch-mm", "10"])
    assert result.exit_code == 0, result.output
    maps = ReferenceMaps.load(out)
    assert maps["small"].B.shape == (11, 11, 2)
    assert maps.meta["pitch_m"] == pytest.approx(0.01)


def test_import_comsol_then_fit(runner: CliRunner, tmp_path, reference: ReferenceMaps) -> None:
    args = []
    for name in ("small", "large"):
        coarse = reference[name]
        write_comsol_map(tmp_path / f"{name}.txt", coarse, length_unit="mm", field_unit="mT")
        args += [f"--{name}", str(tmp_path / f"{name}.txt")]
    result = runner.invoke(cli, ["field", "import-comsol", *args, "--out", str(tmp_path / "m.npz")])
    assert result.exit_code == 0, result.output
    imported = ReferenceMaps.load(tmp_path / "m.npz")
    np.testing.assert_allclose(imported["small"].B, reference["small"].B, rtol=1e-12, atol=1e-20)


def test_import_comsol_bad_file_exits_2_naming_file_and_line(runner: CliRunner, tmp_path) -> None:
    bad = tmp_path / "small.txt"
    bad.write_text("% x y mf.Bx (T) mf.By (T)\n0 0 1e-3 oops\n")
    result = runner.invoke(
        cli,
        [
            "field",
            "import-comsol",
            "--small",
            str(bad),
            "--large",
            str(bad),
            "--out",
            str(tmp_path / "m.npz"),
        ],
    )
    assert result.exit_code == 2
    assert f"{bad}:2: 'oops' is not a number" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "m.npz").exists()


def test_installed_console_script() -> None:
    # the script sits beside the interpreter of the environment it was installed into
    beside = Path(sys.executable).with_name("magrun")
    exe = str(beside) if beside.exists() else shutil.which("magrun")
    assert exe is not None, "the magrun console script is not installed"
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "magrun, version 0.1.0"


def test_fit_refuses_maps_made_for_another_coil_system(runner: CliRunner, tmp_path) -> None:
    from importlib import resources

    text = (resources.files("magrun.field") / "data" / "coils.yaml").read_text()
    other = tmp_path / "other.yaml"
    other.write_text(text.replace("turns: 90", "turns: 120"))
    result = runner.invoke(cli, ["field", "fit", "--coils", str(other), "--out", str(tmp_path)])
    assert result.exit_code == 2
    assert "made for another coil system" in result.output
    # maps made for that system are accepted
    maps = tmp_path / "other.npz"
    made = runner.invoke(
        cli, ["field", "reference", "--coils", str(other), "--out", str(maps), "--pitch-mm", "5"]
    )
    assert made.exit_code == 0, made.output
    fitted = runner.invoke(
        cli,
        [
            "field",
            "fit",
            "--coils",
            str(other),
            "--reference",
            str(maps),
            "--max-order",
            "3",
            "--out",
            str(tmp_path / "fit"),
        ],
    )
    assert fitted.exit_code == 0, fitted.output


def test_track_json_reports_errors_per_method(runner: CliRunner) -> None:
    args = ["track", "baseline2", "baseline3", "--duration", "2"]
    result = runner.invoke(cli, [*args, "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert [r["method"] for r in doc["results"]] == ["baseline2", "baseline3"]
    pid, lmpc = doc["results"]
    assert pid["rms_prediction_position_mm"] is None  # the PID predicts nothing: null, not NaN
    assert lmpc["rms_prediction_position_mm"] >= 0
    for r in doc["results"]:
        assert r["ticks"] == 51
        assert 0 <= r["rms_position_mm"] < 5
        assert r["max_abs_current_a"] <= 30


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["track", "nmpc9"], "unknown method(s) nmpc9"),
        (["track", "baseline2", "--robot", "rover"], "unknown robot 'rover'"),
        (["track", "baseline2", "--speed-mm-s", "0"], "Invalid value for '--speed-mm-s'"),
        (["track", "baseline2", "--rate-hz", "30"], "above the control rate 25 Hz"),
        (["bench", "nmpc", "--ticks", "1"], "Invalid value for '--ticks'"),
    ],
)
def test_control_verbs_reject_bad_input(runner: CliRunner, args: list[str], message: str) -> None:
    result = runner.invoke(cli, args)
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


@pytest.mark.filterwarnings("ignore::magrun.compiled.CompileWarning")
def test_bench_nmpc_json(runner: CliRunner, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every variant's figures, and the ratios computed from them (uncompiled: quick to build)."""
    monkeypatch.setenv("MAGRUN_COMPILE", "0")
    variants = ["proposed", "proposed_ipopt_reference", "b5_lut"]
    args = ["bench", "nmpc", "--ticks", "3", "--json"]
    result = runner.invoke(cli, args + [f"--variant={v}" for v in variants])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert list(doc["variants"]) == variants
    for name in variants:
        r = doc["variants"][name]
        assert r["ticks"] == 3
        assert 0 < r["median_ms"] <= r["p90_ms"] <= r["p99_ms"] <= r["max_ms"]
        assert r["failed_solves"] == 0
        assert r["rms_position_mm"] >= 0
    ref, fast = doc["variants"]["proposed_ipopt_reference"], doc["variants"]["proposed"]
    assert doc["speedup_vs_ipopt"] == pytest.approx(ref["median_ms"] / fast["median_ms"])
    assert doc["machine"]["logical_cores"] >= 1
    assert "b5_speedup_vs_ipopt" not in doc  # its IPOPT variant did not run
    assert "feedback" not in fast  # uncompiled: no kernel, so no preparation


def test_bench_nmpc_reports_the_feedback_phase(runner: CliRunner) -> None:
    """With the compiled kernel every tick after the first is prepared; the per-tick figure
    is preparation + feedback, so it is at least the feedback phase's."""
    result = runner.invoke(cli, ["bench", "nmpc", "--ticks", "6", "--variant", "proposed",
                                 "--json"])  # fmt: skip
    assert result.exit_code == 0, result.output
    r = json.loads(result.output)["variants"]["proposed"]
    f = r["feedback"]
    assert f["prepared_ticks"] == 5 == r["ticks"] - 1  # the first (cold) tick is excluded
    assert 0 < f["median_ms"] <= f["p90_ms"] <= f["p99_ms"] <= f["max_ms"]
    assert f["median_ms"] < r["median_ms"]
    assert f["prepare_median_ms"] > 0


def test_bench_nmpc_runs_a_protocols_ticks_beside_the_s(runner: CliRunner) -> None:
    """``--protocol``: the protocol's proposed method, one trial under its own conditions
    (the spine: phantom, 3 Hz frames, Kalman filter), as ``proposed@<name>``, with its
    feedback phase over the S's from the same run; a protocol with errors exits 2."""
    spine = Path(__file__).parents[1] / "protocols" / "spine.yaml"
    args = ["bench", "nmpc", "--ticks", "30", "--variant", "proposed", "--protocol", str(spine)]
    result = runner.invoke(cli, [*args, "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert list(doc["variants"]) == ["proposed", "proposed@spine"]
    s, r = doc["variants"]["proposed"], doc["variants"]["proposed@spine"]
    assert r["robot"] == "drug_delivery"
    assert r["ticks"] == 30
    assert r["failed_solves"] == 0
    f = r["feedback"]
    assert f["prepared_ticks"] == 29  # every tick after the first (cold) one
    assert 0 < f["embedded_ticks"] <= f["prepared_ticks"]
    assert r["feedback_vs_s"] == pytest.approx(f["median_ms"] / s["feedback"]["median_ms"])
    bad = runner.invoke(cli, [*args, "--json", "--protocol", str(Path(__file__))])
    assert bad.exit_code == 2, bad.output
    assert "Traceback" not in bad.output


def test_track_with_camera_and_fluoroscopy_json(runner: CliRunner) -> None:
    """UNet tracking on rendered frames, 7.5 Hz, σ 2 mm: 16 measurements in 2 s, none lost."""
    args = ["track", "baseline2", "--duration", "2", "--camera", "--rate-hz", "7.5"]
    result = runner.invoke(cli, [*args, "--sigma-mm", "2", "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["feedback"] == {"source": "unet camera tracking", "rate_hz": 7.5, "sigma_mm": 2.0}
    [row] = doc["results"]
    assert row["measurements"] == 16
    assert row["tracking_lost"] == 0


def test_tracker_train_then_eval_json(runner: CliRunner, tmp_path) -> None:
    out = tmp_path / "w.npz"
    trained = runner.invoke(
        cli, ["tracker", "train", "--steps", "2", "--batch", "2", "--out", str(out)]
    )
    assert trained.exit_code == 0, trained.output
    result = runner.invoke(
        cli,
        ["tracker", "eval", "--weights", str(out), "--frames", "10", "--search-frames", "2",
         "--json"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["trained"]["steps"] == 2
    assert doc["tracking"]["frames"] == 10
    assert doc["search"]["frames"] == 2
    assert set(doc["per_robot"]) == {"magnet", "drug_delivery"}
    assert 0 <= doc["tracking"]["failure_rate"] <= 1
    assert doc["tracking"]["median_ms"] > 0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["tracker", "train", "--labels", "{junk}"], "fine-tuning needs --images"),
        (["tracker", "eval", "--weights", "{junk}"], "cannot load weights"),
        (["track", "baseline2", "--rate-hz", "0"], "Invalid value for '--rate-hz'"),
    ],
)
def test_tracker_verbs_reject_bad_input(
    runner: CliRunner, tmp_path, args: list[str], message: str
) -> None:
    junk = tmp_path / "junk.npz"
    junk.write_text("not weights\n")
    result = runner.invoke(cli, [a.format(junk=junk) for a in args])
    assert result.exit_code == 2
    assert message in result.output
    assert "Traceback" not in result.output


def test_tracker_run_on_an_image_folder(runner: CliRunner, tmp_path) -> None:
    """Frames a lab's camera might give (4 px/mm, 320 × 240): poses in mm from the centre."""
    import csv
    from dataclasses import replace

    import cv2

    from magrun.robot import load_robot
    from magrun.tracking.camera import DEFAULT_CAMERA, Camera
    from magrun.tracking.render import Renderer

    cam = Camera(replace(DEFAULT_CAMERA, width_px=320, height_px=240, px_per_mm=4.0))
    renderer = Renderer(cam, load_robot("magnet"), seed=1)
    poses = [(0.005, 0.002, 0.3), (0.006, 0.002, 0.35), (-0.01, -0.005, -2.0)]
    for k, pose in enumerate(poses):
        bgr = cv2.cvtColor(renderer.render(pose), cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(tmp_path / f"frame{k:03d}.png"), bgr)
    out = tmp_path / "poses.csv"
    result = runner.invoke(
        cli, ["tracker", "run", str(tmp_path), "--px-per-mm", "4", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    with out.open() as f:
        rows = list(csv.DictReader(f))
    assert [r["frame"] for r in rows] == ["frame000.png", "frame001.png", "frame002.png"]
    for row, (x, y, th) in zip(rows, poses, strict=True):
        assert abs(float(row["x_mm"]) - x * 1e3) < 0.3
        assert abs(float(row["y_mm"]) - y * 1e3) < 0.3
        assert abs(float(row["theta_deg"]) - np.degrees(th)) < 2.0
    empty = tmp_path / "empty"
    empty.mkdir()
    result = runner.invoke(cli, ["tracker", "run", str(empty), "--px-per-mm", "4"])
    assert result.exit_code == 2
    assert "no images" in result.output


def test_bench_recorder_json(runner: CliRunner) -> None:
    args = ["bench", "recorder", "--seconds", "0.2", "--fps", "50", "--width", "64"]
    result = runner.invoke(cli, [*args, "--height", "48", "--ticks", "20", "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    c = doc["tick_cost"]
    assert c["ticks"] == 20
    pinned = len(os.sched_getaffinity(0)) >= 2  # the pinned variants need two cores
    expected = {"thread", "process"} | ({"thread_pinned", "process_pinned"} if pinned else set())
    assert set(doc["throughput"]) == expected
    for writer, t in doc["throughput"].items():
        assert t["frames_offered"] == 10
        assert t["frames_written"] == 10
        assert t["ticks_dropped"] == 0
        assert t["error"] == ""
        assert t["sustained_fps"] == pytest.approx(10 / t["finished_s"])
        w = c[writer]
        assert w["ticks_dropped"] == 0
        bare = c["p99_bare_pinned_ms" if writer.endswith("_pinned") else "p99_bare_ms"]
        assert w["p99_added_ms"] == pytest.approx(w["p99_logging_ms"] - bare)


def test_bench_sigkill_json(runner: CliRunner) -> None:
    """One killed recording process, recovered: the figures add up, ≤ 1 s + 2 ticks lost;
    a kill window that is not 0 < MIN <= MAX exits 2."""
    for window in (["0", "1"], ["2", "1"], ["1", "nan"]):
        bad = runner.invoke(cli, ["bench", "sigkill", "--kill-after", *window])
        assert bad.exit_code == 2, bad.output
        assert "--kill-after" in bad.output
    args = ["bench", "sigkill", "--kills", "1", "--kill-after", "1.2", "1.6", "--json"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    (run,) = doc["runs"]
    assert 1.2 <= run["killed_after_s"] <= 1.6
    assert run["ticks_logged"] > 25  # killed after ≥ 1.2 s of trial at 25.5 Hz
    assert run["ticks_lost"] == run["ticks_logged"] - run["ticks_recovered"]
    assert 0 <= doc["max_trial_s_lost"] <= doc["flush_s"] + 2 * doc["tick_s"]


def test_bench_sigkill_process_writer_finishes_the_file(runner: CliRunner) -> None:
    """The writer outlives the killed loop: the file has its footer and holds every tick
    the loop handed over (one more if the kill fell between handing over and printing)."""
    args = ["bench", "sigkill", "--kills", "1", "--writer", "process", "--kill-after", "1", "2",
            "--json"]  # fmt: skip
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    (run,) = doc["runs"]
    assert doc["writer"] == "process"
    assert run["complete"]
    assert doc["complete_files"] == 1
    assert run["ticks_lost"] in (0, -1)


def test_bench_campaign_json(runner: CliRunner, tmp_path: Path) -> None:
    """The figures add up; --feedback truth reaches the trials: they run without the camera
    (the metadata says so; no frames), their recordings finished."""
    from mcap.reader import make_reader

    tiny = Path(__file__).parent / "data" / "protocols" / "tiny.yaml"
    args = ["bench", "campaign", str(tiny), "--jobs", "1", "--out", str(tmp_path),
            "--feedback", "truth", "--json"]  # fmt: skip
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["feedback"] == "truth"
    row = doc["protocols"]["tiny"]
    assert row["trials"] == 4
    assert row["failed"] == 0
    assert row["trials_per_min"] == pytest.approx(row["trials"] / row["wall_s"] * 60)
    assert doc["total"]["trials"] == 4
    # where the trials' CPU went: the manifest's per trial, summed; each trial's parts add up
    # to its total (the process's CPU over the trial)
    from magrun.runner import CPU_PARTS

    entries = json.loads((tmp_path / "tiny" / "manifest.json").read_text())["trials"]
    for entry in entries:
        cpu = entry["cpu_s"]
        assert list(cpu) == list(CPU_PARTS)
        assert min(cpu.values()) >= 0
        assert sum(v for k, v in cpu.items() if k != "total") == pytest.approx(
            cpu["total"], abs=1e-3
        )
        assert cpu["track"] < cpu["control"]  # no tracker: the truth into the mimic
    for part in CPU_PARTS:
        summed = sum(e["cpu_s"][part] for e in entries)
        assert row["cpu_s"][part] == pytest.approx(summed, abs=2e-3)
        assert doc["total"]["cpu_s"][part] == pytest.approx(summed, abs=2e-3)
    files = sorted((tmp_path / "tiny").rglob("*.mcap"))
    assert len(files) == 4
    for file in files:
        with file.open("rb") as fh:
            reader = make_reader(fh)
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
            summary = reader.get_summary()
        assert meta["trial"]["feedback"] == "truth"
        assert summary is not None
        assert not any(c.topic.startswith("/camera") for c in summary.channels.values())


def test_bench_cluster_json(runner: CliRunner, tmp_path: Path) -> None:
    """One local one-node Ray cluster running two trials (the tiny protocol at one rate):
    the figures add up; bad sizes exit 2 before any."""
    pytest.importorskip("ray")
    text = (Path(__file__).parent / "data" / "protocols" / "tiny.yaml").read_text()
    assert "tracking_rate_hz: [5, 25.5]" in text
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(text.replace("tracking_rate_hz: [5, 25.5]", "tracking_rate_hz: [25.5]"))
    for nodes in ("0", "two", ""):
        bad = runner.invoke(cli, ["bench", "cluster", str(tiny), "--nodes", nodes])
        assert bad.exit_code == 2, bad.output
        assert "--nodes" in bad.output
    result = runner.invoke(cli, ["bench", "cluster", str(tiny), "--nodes", "1", "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output.strip().splitlines()[-1])
    row = doc["clusters"]["1"]
    assert doc["trials"] == 2
    assert row["failed"] == 0
    assert row["nodes_used"] == 1
    assert row["speedup"] == 1.0
    assert 0 < row["run_s"] < row["wall_s"]
    assert row["trials_per_min"] == pytest.approx(2 / row["wall_s"] * 60)
    assert row["recordings_mb"] > 0


def test_bench_campaign_checks_every_protocol_before_running(
    runner: CliRunner, tmp_path: Path
) -> None:
    tiny = Path(__file__).parent / "data" / "protocols" / "tiny.yaml"
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\nmethods: [nmpc9]\n")
    args = ["bench", "campaign", str(tiny), str(bad), "--out", str(tmp_path / "out")]
    result = runner.invoke(cli, args)
    assert result.exit_code == 2
    assert "bad.yaml" in result.output
    assert not (tmp_path / "out").exists()


def test_bench_tick_json(runner: CliRunner) -> None:
    protocol = Path(__file__).parents[1] / "protocols" / "noise.yaml"
    args = ["bench", "tick", "--protocol", str(protocol), "--ticks", "10", "--json"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    stages = [doc[f"{s}_ms"] for s in ("render", "track", "control", "prepare", "plant")]
    assert all(v > 0 for v in stages)  # the proposed NMPC prepares every tick but the last
    assert doc["sum_of_medians_ms"] == pytest.approx(sum(stages))


def test_track_assembles_its_trial_as_run_does_for_the_same_condition(
    runner: CliRunner, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`magrun track --sigma-mm 2 --rate-hz 5` and a protocol trial with the same condition
    (default controller settings, the same robot and rate) are assembled alike: the methods
    get the same configuration (the Kalman filter assumes the 2 mm noise it gets), the
    feedback the same rate and noise, the safety layer the same limits."""
    import magrun.trial as trial_module
    from magrun.protocol import Protocol

    seen: list[trial_module.TrialParts] = []
    real = trial_module.assemble

    def spy(*args: object, **kw: object) -> trial_module.TrialParts:
        parts = real(*args, **kw)  # type: ignore[arg-type]
        seen.append(parts)
        return parts

    monkeypatch.setattr(trial_module, "assemble", spy)
    args = ["track", "baseline3", "--sigma-mm", "2", "--rate-hz", "5", "--duration", "0.2"]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    protocol = Protocol.model_validate(
        {
            "name": "same", "description": "track's condition", "robot": "magnet",
            "workspace": {"kind": "open"}, "trajectory": {"kind": "s_curve"},
            "methods": ["baseline3"], "controller": {"rate_hz": 25.0},
            "conditions": {"noise_sigma_mm": 2.0, "tracking_rate_hz": 5.0}, "trials": 1,
        }
    )  # fmt: skip
    (trial,) = protocol.expand()
    from_run = real(trial)
    (from_track,) = seen
    assert from_track.config == from_run.config
    assert from_run.config.kalman.measurement_position == pytest.approx(2e-3)
    for parts in (from_track, from_run):
        assert (parts.feedback.rate_hz, parts.feedback.sigma_position) == (5.0, 2e-3)
        assert parts.safety.config == from_run.safety.config
        assert parts.free_space.critical is None


@pytest.mark.parametrize(
    ("args", "message", "absent"),
    [
        (["recover", "{six}", "{tmp}/r.mcap"], "not an MCAP file", "struct"),
        (["view", "{six}"], "not an MCAP file", "magrun recover"),
        (["field", "fit", "--reference", "{notes}"], "not an .npz archive", "pickle"),
        (["field", "fit", "--order", "small=x"], "got 'small=x'", "Traceback"),
        (["track", "proposed", "--duration", "-1"], "Invalid value for '--duration'", "stack"),
        (["validate", "{typo}"], "trails: Extra inputs are not permitted; did you mean 'trials'?",
         "Traceback"),
    ],
)  # fmt: skip
def test_bad_input_is_named_with_exit_2(
    runner: CliRunner, tmp_path: Path, args: list[str], message: str, absent: str
) -> None:
    """Files that are not what they claim, malformed option values and a misspelt protocol
    key: exit 2, a message that names the problem (and the fix), no traceback."""
    six = tmp_path / "six.mcap"
    six.write_bytes(b"abcdef")
    notes = tmp_path / "notes.txt"
    notes.write_text("not a reference map\n")
    tiny = (Path(__file__).parent / "data" / "protocols" / "tiny.yaml").read_text()
    typo = tmp_path / "typo.yaml"
    typo.write_text(tiny.replace("trials:", "trails:"))
    assert "trails:" in typo.read_text()
    fields = {"six": six, "tmp": tmp_path, "notes": notes, "typo": typo}
    result = runner.invoke(cli, [a.format(**fields) for a in args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert absent not in result.output
    assert "Traceback" not in result.output


def test_run_summary_names_trials_that_did_not_complete() -> None:
    """Pending, interrupted and failed trials each get a line with their reason; a condition
    with no complete trial shows dashes, never nan; lost robots are counted."""
    from magrun.cli.protocols import _summary

    base = {"protocol": "p", "ticks": 0, "dropped_ticks": 0, "wall_s": 1.0}
    manifest = {
        "trials": [
            {**base, "path": "a/trial-0", "status": "ok", "rms_position_mm": 1.0,
             "rms_orientation_deg": 2.0, "ticks": 10, "overruns": 1},
            {**base, "path": "a/trial-1", "status": "ok", "rms_position_mm": 9.0,
             "rms_orientation_deg": 2.0, "ticks": 10, "overruns": 1, "lost": True},
            {**base, "path": "b/trial-0", "status": "interrupted",
             "error": "stopped by SIGINT at t = 1.20 s"},
            {**base, "path": "b/trial-1", "status": "pending"},
            {**base, "path": "c/trial-0", "status": "failed", "error": None},
        ]
    }  # fmt: skip
    lines = _summary(manifest)
    text = "\n".join(lines)
    assert "nan" not in text
    # a lost trial is complete (ok) and counted in the lost column and the means
    assert lines[1].split()[:6] == ["a", "2/2", "1", "5.000", "2.00", "10%"]
    assert lines[2].split()[:6] == ["b", "0/2", "0", "—", "—", "—"]
    # the last column is the trials' own times summed, not the run's wall time (with --jobs
    # the trials overlap): it says so
    assert lines[0].split()[-2:] == ["trial", "s"]
    assert lines[1].split()[-1] == "2"
    assert "INTERRUPTED b/trial-0: stopped by SIGINT at t = 1.20 s" in lines
    assert "PENDING b/trial-1: not started (magrun run --resume runs it)" in lines
    assert "FAILED c/trial-0: no error recorded" in lines
