"""analysis.metrics and analysis.load: hand-computed values on synthetic recordings.

Tolerances: metrics read back from an MCAP are float64 round trips through protobuf doubles
and a quaternion (yaw to ~1e-15 rad), so 1e-9 of the unit is ample.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from synthetic import DIAMETER, DT, LENGTH, SynthTrial, wall, write_mcap, write_set

import analysis
from analysis import metrics
from analysis.load import read_recording, samples_of
from magrun.phantom import load_phantom

PHANTOM = Path(__file__).parents[1] / "protocols" / "phantoms" / "spine_l3l4.yaml"


# ---- pure metrics ---------------------------------------------------------------------------


def test_wrap_angle_maps_into_minus_pi_to_pi() -> None:
    got = metrics.wrap_angle([0.0, math.pi, -math.pi, 1.5 * math.pi, -1.5 * math.pi, 7.0])
    want = [0.0, math.pi, math.pi, -0.5 * math.pi, 0.5 * math.pi, 7.0 - 2 * math.pi]
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_pose_errors_wrap_across_the_pi_seam() -> None:
    pos, ang = metrics.pose_errors(
        [[0.003, 0.004, math.radians(-179)]], [[0, 0, math.radians(179)]]
    )
    assert pos[0] == pytest.approx(0.005, abs=1e-15)
    assert math.degrees(ang[0]) == pytest.approx(2.0, abs=1e-9)


def test_rms_ignores_missing_samples() -> None:
    assert metrics.rms([3.0, math.nan, 4.0]) == pytest.approx(math.sqrt(12.5))
    assert math.isnan(metrics.rms([math.nan]))


def _minimised_segment_distance(p0, p1, a, b) -> float:  # type: ignore[no-untyped-def]
    """The distance between segments p0–p1 and a–b by minimising |p(s) − q(t)|² over the
    box 0 ≤ s, t ≤ 1 numerically (a convex quadratic: L-BFGS-B finds its minimum)."""
    from scipy.optimize import minimize

    d1, d2, w = p1 - p0, b - a, p0 - a

    def f(x):  # type: ignore[no-untyped-def]
        r = w + x[0] * d1 - x[1] * d2
        return float(r @ r), np.array([2 * r @ d1, -2 * r @ d2])

    best = min(
        (
            minimize(f, start, jac=True, method="L-BFGS-B", bounds=[(0, 1), (0, 1)],
                     options={"ftol": 1e-15, "gtol": 1e-12})
            for start in ([0.5, 0.5], [0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0])
        ),
        key=lambda r: r.fun,
    )  # fmt: skip
    return math.sqrt(max(best.fun, 0.0))


def test_segment_distance_matches_a_numerical_minimisation(rng: np.random.Generator) -> None:
    # the squared distance between points of the two segments is a convex quadratic in their
    # parameters: its minimum over the unit box, found numerically, is the distance to about
    # 1e-7 (the square root of the optimiser's tolerance on the squared distance)
    for _ in range(200):
        p0, p1, a, b = rng.uniform(-1, 1, size=(4, 2))
        got = metrics.segment_segment_distance(p0, p1, a, b)
        assert float(got) == pytest.approx(_minimised_segment_distance(p0, p1, a, b), abs=1e-6)
    # nearly parallel and touching at an end: the closed form's special cases
    for p0, p1, a, b in (
        ([0, 0], [1, 0], [0.2, 0.3], [1.4, 0.3 + 1e-9]),
        ([0, 0], [1, 0], [1.0, 0.0], [2.0, 1.0]),
        ([0, 0], [1, 1], [2, 2], [3, 3]),
    ):
        p0, p1, a, b = (np.array(x, dtype=float) for x in (p0, p1, a, b))
        got = metrics.segment_segment_distance(p0, p1, a, b)
        assert float(got) == pytest.approx(_minimised_segment_distance(p0, p1, a, b), abs=1e-6)


def test_crossing_segments_are_at_zero_distance() -> None:
    d = metrics.segment_segment_distance(
        np.array([-1.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, -1.0]), np.array([0.0, 1.0])
    )
    assert float(d) == 0.0


@pytest.mark.parametrize(
    ("theta", "expected"),
    [
        (0.0, 0.010 - 0.002 - DIAMETER / 2),  # parallel to the wall: the side faces it
        (math.pi / 2, 0.010 - 0.002 - LENGTH / 2),  # pointing at the wall: the tip faces it
    ],
)
def test_capsule_clearance_from_a_straight_wall(theta: float, expected: float) -> None:
    c = metrics.capsule_clearance([[0.0, 0.002, theta]], LENGTH, DIAMETER, wall(0.010))
    assert c[0] == pytest.approx(expected, abs=1e-12)


def test_capsule_clearance_agrees_with_the_simulator_phantom(rng: np.random.Generator) -> None:
    # two independent implementations (magrun.phantom for the plant, analysis.metrics for
    # the recordings) of the same definition, on the shipped phantom's critical boundary
    phantom = load_phantom(PHANTOM)
    poses = np.column_stack(
        [rng.uniform(-0.015, 0.01, 200), rng.uniform(-0.015, 0.015, 200), rng.uniform(-4, 4, 200)]
    )
    ours = metrics.capsule_clearance(poses, 7.4e-3, 2.2e-3, phantom.boundaries[phantom.critical])
    theirs = [phantom.clearance(p, 7.4e-3, 2.2e-3) for p in poses]
    np.testing.assert_allclose(ours, theirs, atol=1e-12)


def test_capsule_clearance_is_nan_for_missing_poses() -> None:
    c = metrics.capsule_clearance([[math.nan, 0, 0], [0, 0, 0]], LENGTH, DIAMETER, wall(0.01))
    assert math.isnan(c[0])
    assert c[1] == pytest.approx(0.01 - DIAMETER / 2)


def test_time_in_counts_each_sample_until_the_next() -> None:
    t = np.arange(10) * 0.5
    assert metrics.time_in([False] * 7 + [True] * 3, t) == pytest.approx(1.5)
    assert metrics.time_in([True, False], [0.0, 0.25]) == pytest.approx(0.25)


# ---- recordings -----------------------------------------------------------------------------


def test_known_offsets_give_known_errors(tmp_path: Path) -> None:
    # actual = desired + (3, 4) mm and +10° across the ±180° seam; prediction 1 mm off
    s = SynthTrial(
        "p", "m", offset=(3e-3, 4e-3, math.radians(10)), start=(0.0, 0.0, math.radians(175))
    )
    rec = read_recording(write_mcap(tmp_path / "t.mcap", s))
    m = metrics.trial_metrics(rec, samples_of(rec))
    assert m["rms_position_mm"] == pytest.approx(5.0, abs=1e-9)
    assert m["rms_orientation_deg"] == pytest.approx(10.0, abs=1e-9)
    assert m["rms_prediction_position_mm"] == pytest.approx(1.0, abs=1e-9)
    assert m["rms_prediction_orientation_deg"] == pytest.approx(0.0, abs=1e-9)
    assert m["ticks"] == s.n
    assert m["duration_s"] == pytest.approx((s.n - 1) * DT, abs=1e-9)
    assert m["control_rate_hz"] == pytest.approx(1 / DT, rel=1e-9)
    assert math.isnan(m["min_clearance_mm"])  # no boundaries: empty, not zero


def test_poses_and_currents_round_trip_in_si(tmp_path: Path) -> None:
    s = SynthTrial("p", "m", velocity=(0.004, -0.002, 0.3))
    rec = read_recording(write_mcap(tmp_path / "t.mcap", s))
    d = rec.poses["desired"][["x", "y", "theta"]].to_numpy()
    want = s.desired()
    want[:, 2] = metrics.wrap_angle(want[:, 2])
    np.testing.assert_allclose(d, want, atol=1e-12)
    np.testing.assert_allclose(rec.poses["desired"]["t"], np.arange(s.n) * DT, atol=1e-9)
    assert list(rec.currents.columns) == ["t_ns", "t", "c0", "c1"]
    np.testing.assert_allclose(rec.currents["c1"], -np.arange(s.n))
    assert rec.trial["method"] == "m"
    assert rec.robot_length == LENGTH


def test_clearance_and_contact_time_from_a_path_at_known_distance(tmp_path: Path) -> None:
    # the body slides along y = 4 mm, parallel to a wall at y = 10 mm: clearance 10 − 4 − 1
    s = SynthTrial(
        "p", "m", offset=(0.0, 4e-3, 0.0), boundaries={"wall": wall(0.010)}, critical="wall"
    )
    rec = read_recording(write_mcap(tmp_path / "far.mcap", s))
    m = metrics.trial_metrics(rec, samples_of(rec))
    assert m["min_clearance_mm"] == pytest.approx(5.0, abs=1e-9)
    assert m["p5_clearance_mm"] == pytest.approx(5.0, abs=1e-9)
    assert m["min_clearance_mm[wall]"] == pytest.approx(5.0, abs=1e-9)
    assert m["contact_time_s"] == 0.0
    # it drifts towards the wall at 0.5 mm per tick into a 0.5 mm overlap (clearance is
    # unsigned distance − D/2, so overlaps are defined down to −D/2 = −1 mm): it touches
    # (clearance ≤ 0.05 mm) on ticks 10 and 11 of the 12
    s = SynthTrial(
        "p", "m", n=12, offset=(0.0, 4e-3, 0.0), velocity=(0.0, 0.5e-3 / DT, 0.0),
        start=(0.0, 0.0, 0.0), boundaries={"wall": wall(0.010)}, critical="wall",
    )  # fmt: skip
    rec = read_recording(write_mcap(tmp_path / "near.mcap", s))
    samples = samples_of(rec)
    np.testing.assert_allclose(samples["clearance_mm"], 5.0 - 0.5 * np.arange(12), atol=1e-9)
    m = metrics.trial_metrics(rec, samples)
    assert m["min_clearance_mm"] == pytest.approx(-0.5, abs=1e-9)
    assert m["contact_time_s"] == pytest.approx(2 * DT, abs=1e-9)


def test_controller_statistics(tmp_path: Path) -> None:
    solve = list(np.linspace(0.001, 0.06, 60))
    s = SynthTrial("p", "m", solve_times=solve, fallback_ticks=(3, 7), dropped_ticks=4)
    rec = read_recording(write_mcap(tmp_path / "t.mcap", s))
    m = metrics.trial_metrics(rec, samples_of(rec))
    assert m["solve_ms_median"] == pytest.approx(np.median(solve) * 1e3)
    assert m["solve_ms_p99"] == pytest.approx(np.percentile(solve, 99) * 1e3)
    assert m["overrun_fraction"] == pytest.approx(np.mean(np.array(solve) > DT))
    assert m["fallbacks"] == 2
    assert m["dropped_ticks"] == 4
    assert m["iterations_median"] == 3
    assert m["prepare_ms_median"] == 0  # the field unset: no preparation


def test_preparation_time_statistics(tmp_path: Path) -> None:
    prepare = list(np.linspace(0.0001, 0.0003, 60))
    s = SynthTrial("p", "m", prepare_times=prepare)
    rec = read_recording(write_mcap(tmp_path / "t.mcap", s))
    m = metrics.trial_metrics(rec, samples_of(rec))
    assert m["prepare_ms_median"] == pytest.approx(np.median(prepare) * 1e3)


def test_a_camera_slower_than_the_controller_leaves_gaps_not_wrong_matches(tmp_path: Path) -> None:
    s = SynthTrial("p", "m", actual_every=2)
    rec = read_recording(write_mcap(tmp_path / "t.mcap", s))
    samples = samples_of(rec)
    assert samples["position_error_mm"].isna().sum() == s.n // 2
    assert metrics.trial_metrics(rec, samples)["rms_position_mm"] == pytest.approx(5.0)


# ---- damaged input --------------------------------------------------------------------------


def test_truncated_recording_names_the_file_and_the_fix(tmp_path: Path) -> None:
    path = write_mcap(tmp_path / "t.mcap", SynthTrial("p", "m"))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(analysis.RecordingError, match=r"t\.mcap.*truncated or damaged.*recover"):
        read_recording(path)


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all", b"\x89MCAP0\r\n" + b"\0" * 9])
def test_garbage_is_a_recording_error(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(analysis.RecordingError, match=r"bad\.mcap"):
        read_recording(path)


def test_load_keeps_going_past_damaged_and_failed_trials(tmp_path: Path) -> None:
    good = [SynthTrial("p", "m", trial=k) for k in range(3)]
    root = write_set(tmp_path, good, failed=[SynthTrial("p", "m", trial=3)])
    broken = root / "p" / good[1].slug / "trial-1.mcap"
    broken.write_bytes(broken.read_bytes()[:200])
    data = analysis.load(root)
    assert len(data.trials) == 4
    status = dict(zip(data.trials["trial"], data.trials["status"], strict=True))
    assert status == {0: "ok", 1: "unreadable", 2: "ok", 3: "failed"}
    assert [p.path for p in data.problems] == [broken]
    bad = data.trials[data.trials["status"] != "ok"]
    assert bad["rms_position_mm"].isna().all()
    assert set(data.samples["trial"]) == {0, 2}


def test_load_finds_mcaps_without_a_manifest(tmp_path: Path) -> None:
    write_mcap(tmp_path / "a" / "one.mcap", SynthTrial("p", "m", trial=0))
    write_mcap(tmp_path / "b" / "two.mcap", SynthTrial("p", "m", trial=1))
    data = analysis.load(tmp_path)
    assert sorted(data.trials["trial"]) == [0, 1]
    assert (data.trials["rms_position_mm"] - 5.0).abs().max() < 1e-9


def test_load_of_a_missing_folder_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no such file or folder"):
        analysis.load(tmp_path / "nope")


def test_analysis_imports_nothing_of_magrun() -> None:
    # it must read recordings from any rig: no control, field or recorder code behind it
    code = (
        "import sys, analysis, analysis.figures, analysis.report;"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'magrun'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_a_trial_that_failed_midway_keeps_its_metrics_but_not_its_samples(tmp_path: Path) -> None:
    failed = SynthTrial("p", "m", trial=1)
    root = write_set(tmp_path, [SynthTrial("p", "m", trial=0)], failed=[failed])
    write_mcap(root / "p" / failed.slug / "trial-1.mcap", failed)  # the part it recorded
    data = analysis.load(root)
    row = data.trials.set_index("trial").loc[1]
    assert (row["status"], row["error"]) == ("failed", "boom")
    assert row["rms_position_mm"] == pytest.approx(5.0)
    assert set(data.samples["trial"]) == {0}


def test_coil_effort_by_hand() -> None:
    """Two coils, samples 0.1 s apart (each value holds until the next; the last for the
    median step): RMS per coil, ∫ΣI² dt, total variation and time within 0.5 % of the limit."""
    import pandas as pd

    from analysis.metrics import coil_effort

    frame = pd.DataFrame({"t": [0.0, 0.1, 0.2, 0.3], "a": [0.0, 10.0, 10.0, -10.0],
                          "b": [1.0, 1.0, 29.9, 30.0]})  # fmt: skip
    out = coil_effort(frame, 30.0)
    assert out["rms_current_a[a]"] == pytest.approx(np.sqrt(300 / 4))
    assert out["rms_current_a[b]"] == pytest.approx(np.sqrt((1 + 1 + 29.9**2 + 900) / 4))
    heat = 0.1 * ((0 + 1) + (100 + 1) + (100 + 29.9**2) + (100 + 900))
    assert out["current_squared_integral_a2s"] == pytest.approx(heat)
    assert out["current_variation_a"] == pytest.approx(10 + 0 + 20 + 0 + 28.9 + 0.1)
    assert out["time_at_limit_s"] == pytest.approx(0.2)  # 29.9 and 30 A: ≥ 29.85
    per_coil = coil_effort(frame, [5.0, 100.0])  # limits per coil: a is at its limit 3 samples
    assert per_coil["time_at_limit_s"] == pytest.approx(0.3)
    assert np.isnan(coil_effort(frame, None)["time_at_limit_s"])  # no limits recorded


@pytest.mark.parametrize(
    "manifest",
    [
        '{"trials": [1, 2]}',
        '{"trials": [{"path": "a"}]}',
        '{"trials": [{"mcap": 5}]}',
        '{"trials": {"mcap": "a.mcap"}}',
        '{"trials": [{"mcap": "../../outside.mcap"}]}',
        "[" * 100_000 + "]" * 100_000,
        "not json",
    ],
)
def test_a_tampered_manifest_is_refused_naming_it(tmp_path: Path, manifest: str) -> None:
    """A manifest whose entries were not what `magrun run` writes ended `figures` in a
    KeyError or TypeError traceback; one 100,000 deep in RecursionError. Now exit 2, named."""
    from click.testing import CliRunner

    from magrun.cli import cli

    run = tmp_path / "rec" / "proto"
    run.mkdir(parents=True)
    (run / "manifest.json").write_text(manifest)
    args = ["figures", str(tmp_path / "rec"), "--out", str(tmp_path / "f")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2, result.output
    assert "manifest.json" in result.output
    assert "Traceback" not in result.output
