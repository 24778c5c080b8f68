"""A real bench's imperfections in the simulated plant (magrun.rigs.plant), each against theory on
a fixed problem, and the presets as a protocol states them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun.rigs.plant import (
    Imperfections,
    OrnsteinUhlenbeck,
    PlantDraw,
    TrackingErrors,
    amplifier_path,
    contact_substep,
    contact_vector,
    draw_plant,
    harmonic_field,
    perturb_table,
    residual_rms,
)
from magrun.rigs.sim import Perturbation, SimRig

NOMINAL = Perturbation()  # the nominal robot and coils: only the imperfection under test


def _held(B: tuple[float, float], G: tuple[tuple[float, float], tuple[float, float]]):
    """A field function that returns the same field everywhere."""
    return lambda x, y: (B, G)


# --------------------------------------------------------------------------------------------
# amplifiers


def test_amplifier_lag_is_the_first_order_step_response() -> None:
    """Without a binding slew limit: I(kh) = I*(1 − e^(−kh/τ)) at every sub-step (1e-12 A)."""
    tau, h, n = 0.01, 1e-3, 200
    path = amplifier_path(np.zeros(2), np.array([10.0, -4.0]), tau, 1e9, h, n)
    t = h * np.arange(1, n + 1)[:, None]
    assert_allclose(path, np.array([10.0, -4.0]) * (1 - np.exp(-t / tau)), atol=1e-12, rtol=0)


def test_amplifier_lag_keeps_the_slew_limit() -> None:
    """A step larger than the slew limit allows: the rate is the limit until the lag's rate
    falls below it, then the exponential; never faster than the limit."""
    slew, h = 1000.0, 1e-3
    path = amplifier_path(np.zeros(1), np.array([30.0]), 0.005, slew, h, 100)
    steps = np.diff(np.concatenate([[0.0], path[:, 0]]))
    assert np.all(steps <= slew * h * (1 + 1e-12))
    assert_allclose(steps[:5], slew * h, rtol=1e-12)  # (30 − I)(1 − e^(−h/τ)) > 1 A at first
    assert abs(path[-1, 0] - 30.0) < 1e-3


def test_the_compiled_plants_lag_and_flow_are_the_python_ones_to_the_last_bit() -> None:
    """The compiled rig runs the amplifiers' lag and the flow's recurrence compiled from the
    same definitions; on random channels, steps, slew limits (per channel or one) and time
    constants they give the Python loops' numbers bit for bit, so a trial records the same
    either way."""
    from magrun.rigs import kernel
    from magrun.rigs.plant import ou_path

    rng = np.random.default_rng(11)
    for _ in range(200):
        ch, n = int(rng.integers(1, 9)), int(rng.integers(1, 60))
        driven, target = rng.normal(0, 10, ch), rng.normal(0, 10, ch)
        tau = float(rng.uniform(1e-4, 0.05))
        slew = rng.uniform(10, 2000, ch) if rng.random() < 0.5 else float(rng.uniform(10, 2000))
        python = amplifier_path(driven, target, tau, slew, 1e-3, n)
        compiled = amplifier_path(driven, target, tau, slew, 1e-3, n, kernel.lag_path)
        assert np.array_equal(python, compiled)
        assert np.any(python != driven)  # it moved
        v, xi = rng.normal(0, 1, 2), rng.normal(0, 1, (n, 2))
        a, b = float(rng.uniform(0.9, 1.0)), float(rng.uniform(0.0, 0.1))
        assert np.array_equal(ou_path(v, a, b, xi), kernel.ou_path(v, a, b, xi))


def test_rig_drives_its_currents_through_the_lag(coils, channel_grid, magnet_robot) -> None:
    """The simulated rig's amplifiers follow a commanded step as the lag says."""
    imp = Imperfections(amplifier_tau=0.02)
    rig = SimRig(coils, channel_grid, magnet_robot, perturbation=NOMINAL, imperfections=imp)
    rig.reset([0.0, 0.0, 0.0])
    rig.apply(np.full(coils.n_channels, 2.0))  # 2 A: within 1 ms of slew
    rig.advance(0.04)
    assert_allclose(rig.driven, 2.0 * (1 - math.exp(-0.04 / 0.02)), atol=1e-12)
    rig.advance(1.0)  # settled: the rig holds the target exactly
    assert np.array_equal(rig.driven, np.full(coils.n_channels, 2.0))


# --------------------------------------------------------------------------------------------
# contact: friction, stiction, flow, misalignment


def _push(force: float, robot, imp: Imperfections, steps: int, h: float = 1e-3):
    """Integrate a robot at θ = 0 pushed along +x by ``force`` N (a gradient, no field)."""
    g = force / robot.moment  # F_x = m ∂Bx/∂x with the moment along x
    field = _held((0.0, 0.0), ((g, 0.0), (0.0, 0.0)))
    state = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    contact = contact_vector(imp, robot, 0.0)
    for _ in range(steps):
        state = contact_substep(state, field, robot, h, contact, (0.0, 0.0))
    return state


def test_stiction_holds_a_force_below_its_threshold(magnet_robot) -> None:
    """A robot at rest stays exactly at rest while the force is at most the stiction."""
    imp = Imperfections(friction=1e-3, stiction=2e-3)
    threshold = magnet_robot.drag_parallel * 2e-3
    state = _push(0.999 * threshold, magnet_robot, imp, 500)
    assert state == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def test_above_stiction_it_slides_at_the_kinetic_terminal_speed(magnet_robot) -> None:
    """Above the threshold the robot breaks free and moves at (F − F_k)/d∥ (after ~100 τ)."""
    imp = Imperfections(friction=1e-3, stiction=2e-3)
    d = magnet_robot.drag_parallel
    force = 1.2 * d * 2e-3
    state = _push(force, magnet_robot, imp, 500)
    assert_allclose(state[3], (force - d * 1e-3) / d, rtol=1e-9)
    assert state[4] == 0.0
    assert state[1] == 0.0


def test_kinetic_friction_stops_a_coasting_robot(magnet_robot) -> None:
    """A robot moving at 2 mm/s with no force stops (to exactly zero) and stays."""
    imp = Imperfections(friction=1e-3)
    contact = contact_vector(imp, magnet_robot, 0.0)
    field = _held((0.0, 0.0), ((0.0, 0.0), (0.0, 0.0)))
    state = (0.0, 0.0, 0.0, 2e-3, 0.0, 0.0)
    for _ in range(200):
        state = contact_substep(state, field, magnet_robot, 1e-3, contact, (0.0, 0.0))
    assert state[3:] == (0.0, 0.0, 0.0)
    # with friction F_k the deceleration is faster than drag alone: it moved less than v₀ τ
    assert 0 < state[0] < 2e-3 * magnet_robot.mass / magnet_robot.drag_parallel


def test_rotational_stiction_holds_a_small_torque(magnet_robot) -> None:
    """A torque at most the rotational stiction does not turn a robot at rest; above it,
    it turns."""
    imp = Imperfections(rotational_friction=0.5, rotational_stiction=1.0)
    contact = contact_vector(imp, magnet_robot, 0.0)
    d_r = magnet_robot.drag_rotation
    for factor, turns in ((0.99, False), (2.0, True)):
        # the torque m × B with the moment along x and B along y
        field = _held((0.0, factor * d_r / magnet_robot.moment), ((0.0, 0.0), (0.0, 0.0)))
        state = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for _ in range(3):
            state = contact_substep(state, field, magnet_robot, 1e-4, contact, (0.0, 0.0))
        assert (state[5] > 0 and state[2] > 0) if turns else (state[2] == state[5] == 0.0)


def test_rotational_friction_stops_a_spin_when_theory_says(magnet_robot) -> None:
    """No field, a spin of ω₀ = 10 rad/s, kinetic friction torque τ_k: J ω̇ = −d_r ω − τ_k
    stops it at t* = (J/d_r) ln(1 + ω₀ d_r/τ_k); the plant stops within a sub-step of t*."""
    imp = Imperfections(rotational_friction=0.5)
    contact = contact_vector(imp, magnet_robot, 0.0)
    field = _held((0.0, 0.0), ((0.0, 0.0), (0.0, 0.0)))
    tau = magnet_robot.inertia / magnet_robot.drag_rotation
    t_stop = tau * math.log(1 + 10.0 / 0.5)
    h, state, t = 1e-5, (0.0, 0.0, 0.0, 0.0, 0.0, 10.0), 0.0
    while state[5] != 0.0 and t < 1.0:
        state = contact_substep(state, field, magnet_robot, h, contact, (0.0, 0.0))
        t += h
    assert abs(t - t_stop) <= h * (1 + 1e-9)
    for _ in range(100):  # and it stays stopped
        state = contact_substep(state, field, magnet_robot, h, contact, (0.0, 0.0))
    assert state[5] == 0.0


def test_flow_drags_a_free_robot_to_the_fluid_velocity(magnet_robot) -> None:
    """No field, no friction, a fluid moving at (1, −2) mm/s: the robot moves with it."""
    contact = contact_vector(Imperfections(flow_sigma=1e-3), magnet_robot, 0.0)
    field = _held((0.0, 0.0), ((0.0, 0.0), (0.0, 0.0)))
    state = (0.0, 0.0, 0.3, 0.0, 0.0, 0.0)
    for _ in range(300):
        state = contact_substep(state, field, magnet_robot, 1e-3, contact, (1e-3, -2e-3))
    assert_allclose(state[3:5], (1e-3, -2e-3), rtol=1e-9)
    assert_allclose(state[2], 0.3, atol=1e-15)  # and does not turn it


def test_a_misaligned_moment_settles_the_body_off_the_field(magnet_robot) -> None:
    """In a uniform field along x the moment aligns with it: the body, α off the moment,
    settles at θ = −α."""
    alpha = math.radians(4.0)
    contact = contact_vector(Imperfections(moment_misalignment=1.0), magnet_robot, alpha)
    field = _held((20e-3, 0.0), ((0.0, 0.0), (0.0, 0.0)))  # relaxes at m B / d_r ≈ 13 /s
    state = (0.0, 0.0, 0.2, 0.0, 0.0, 0.0)
    for _ in range(3000):
        state = contact_substep(state, field, magnet_robot, 1e-3, contact, (0.0, 0.0))
    assert_allclose(state[2], -alpha, atol=1e-9)


@pytest.mark.parametrize("walls", [False, True])
def test_compiled_contact_kernel_follows_the_python_reference(
    coils, channel_grid, magnet_robot, walls: bool
) -> None:
    """Friction, stiction, flow and misalignment in the Numba kernel against the Python
    reference: 2 s of jumping currents, uneven advance calls, 1e-12."""
    from magrun.scene import Walls

    imp = Imperfections(
        friction=0.5e-3, stiction=1e-3, rotational_friction=0.05, rotational_stiction=0.1,
        flow_sigma=0.5e-3, flow_time=0.5, moment_misalignment=0.05, amplifier_tau=0.01,
    )  # fmt: skip
    box = Walls.box(0.012) if walls else None

    def run(compiled: bool) -> np.ndarray:
        rig = SimRig(
            coils, channel_grid, magnet_robot, walls=box, seed=3, compiled=compiled,
            imperfections=imp,
        )  # fmt: skip
        rig.reset([0.001, -0.002, 0.4])
        for k in range(50):
            rig.apply(np.roll(np.array([12.0, -6, 9, 0, -12, 6, 0, 3]), k // 10) * (k % 3))
            rig.advance(0.013)
            rig.advance(0.027)
        return rig.state.copy()

    fast, reference = run(True), run(False)
    assert np.linalg.norm(fast[:2] - [0.001, -0.002]) > 1e-3  # it moved
    assert_allclose(fast, reference, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------------------------
# processes


def test_ornstein_uhlenbeck_variance_and_correlation_time() -> None:
    """Stationary σ² and autocorrelation e^(−s/T): from 400 000 steps of T/20 (≈ 10 000
    correlation times: σ̂² within 8 %, ρ(T) within 0.03 of e^(−1))."""
    sigma, T, h = 2e-3, 0.5, 0.025
    v = OrnsteinUhlenbeck(sigma, T, 1, np.random.default_rng(5)).sample(400_000, h)[:, 0]
    assert_allclose(np.var(v), sigma**2, rtol=0.08)
    lag = round(T / h)
    rho = np.corrcoef(v[:-lag], v[lag:])[0, 1]
    assert abs(rho - math.exp(-1)) < 0.03


def test_tracking_errors_have_their_stated_statistics() -> None:
    """White noise of the stated σ, the stated fractions of drops and outliers; reset
    repeats the sequence."""
    imp = Imperfections(
        tracker_position=0.3e-3, tracker_heading=0.05, drop_rate=0.1, outlier_rate=0.05,
        outlier_size=5e-3,
    )  # fmt: skip
    errors = TrackingErrors(imp, 7)
    n = 40_000
    out = [errors(np.zeros(3)) for _ in range(n)]
    kept = np.array([p for p in out if p is not None])
    assert abs(1 - len(kept) / n - 0.1) < 0.01
    far = np.hypot(kept[:, 0], kept[:, 1]) > 2e-3  # outliers (noise alone: > 6 σ)
    assert abs(far.mean() - 0.05 * math.exp(-((2e-3) ** 2) / (2 * 5e-3**2))) < 0.01
    inliers = kept[~far]
    assert_allclose(np.std(inliers[:, :2]), 0.3e-3, rtol=0.05)
    assert_allclose(np.std(kept[:, 2]), 0.05, rtol=0.05)
    errors.reset()
    again = [errors(np.zeros(3)) for _ in range(20)]
    assert all(
        (a is None and b is None) or np.array_equal(a, b)
        for a, b in zip(again, out[:20], strict=True)
    )


# --------------------------------------------------------------------------------------------
# frame age


def test_frame_age_shifts_the_camera_pose_by_exactly_the_age(
    coils, channel_grid, magnet_robot
) -> None:
    """With a 30 ms frame age the camera reports, at every observation, the pose the robot
    had 30 ms earlier (recorded from the same rig every millisecond), to 1e-12."""
    imp = Imperfections(frame_age=0.03)
    rig = SimRig(coils, channel_grid, magnet_robot, perturbation=NOMINAL, imperfections=imp)
    rig.reset([0.0, 0.0, 0.0])
    truth = {0: rig.observe().pose}
    checked = 0
    for k in range(1, 400):
        if k % 40 == 1:
            rig.apply(np.roll(np.array([10.0, -5, 8, 0, -10, 5, 0, 3]), k // 40))
        rig.advance(1e-3)
        obs = rig.observe(frame=False)
        truth[k] = obs.pose
        if k >= 30:
            assert_allclose(obs.camera_pose, truth[k - 30], rtol=0, atol=1e-12)
            assert obs.frame_time == pytest.approx(obs.t - 0.03, abs=1e-12)
            checked += 1
    assert np.hypot(*(truth[399][:2] - truth[0][:2])) > 1e-4  # it moved
    assert checked == 370


def test_ideal_rig_reports_the_pose_itself(coils, channel_grid, magnet_robot) -> None:
    """No imperfection: the observation carries no separate camera pose."""
    rig = SimRig(coils, channel_grid, magnet_robot)
    rig.reset([0.0, 0.0, 0.0])
    obs = rig.observe()
    assert obs.camera_pose is None
    assert obs.frame_time == obs.t


# --------------------------------------------------------------------------------------------
# field-model error


def test_harmonic_field_is_curl_and_divergence_free_and_its_gradient_is_exact() -> None:
    """The residual field's G against central differences of B (1e-7 relative), trace 0
    (div B = 0) and symmetric (curl B = 0)."""
    rng = np.random.default_rng(2)
    c = rng.normal(size=4) + 1j * rng.normal(size=4)
    p = rng.uniform(-0.05, 0.05, (20, 2))
    B, G = harmonic_field(p, c, 0.05)
    h = 1e-7
    for axis in range(2):
        dp = np.zeros(2)
        dp[axis] = h
        fd = (harmonic_field(p + dp, c, 0.05)[0] - harmonic_field(p - dp, c, 0.05)[0]) / (2 * h)
        assert_allclose(G[..., axis], fd, rtol=1e-6, atol=1e-7 * np.abs(B).max())
    assert_allclose(np.trace(G, axis1=-2, axis2=-1), 0.0, atol=1e-12)
    assert_allclose(G[..., 0, 1], G[..., 1, 0], atol=1e-15)


def test_residual_field_has_its_stated_rms_at_the_current_limit() -> None:
    """draw_plant scales each channel's residual: RMS over the workspace at the limit = the
    setting (0.5 mT), per channel, whatever the limits."""
    imp = Imperfections(residual_field=0.5e-3)
    limits = np.array([30.0, 10.0, 50.0])
    draw = draw_plant(imp, 3, limits, 0.05, np.random.default_rng(0))
    assert_allclose(residual_rms(draw.residual, 0.05) * limits, 0.5e-3, rtol=1e-12)


def _draw(n: int, offsets=None, rotations=None) -> PlantDraw:
    return PlantDraw(
        np.zeros((n, 2)) if offsets is None else np.asarray(offsets, float),
        np.zeros(n) if rotations is None else np.asarray(rotations, float),
        np.zeros((n, 4), complex),
        0.0,
    )


def test_coil_offset_moves_its_map(channel_grid) -> None:
    """A coil displaced by (2, −3) mm (whole grid steps): its map at p is the old one at
    p − d, exactly, at every node whose source lies on the grid; other coils unchanged."""
    g = channel_grid
    n = len(g.channel_names)
    offsets = np.zeros((n, 2))
    offsets[1] = (2 * g.step, -3 * g.step)
    out = perturb_table(g.table, g.x0, g.y0, g.step, _draw(n, offsets), np.zeros((n, 2)), 0.05)
    assert_allclose(out[2:, :-3, 1], g.table[:-2, 3:, 1], rtol=1e-9, atol=1e-15)
    assert np.array_equal(out[:, :, 0], g.table[:, :, 0])


def test_coil_rotation_turns_its_map_about_the_pivot(channel_grid) -> None:
    """A quarter turn about the workspace centre: B'(p) = R B(Rᵀp), G' = R G Rᵀ at the grid's
    nodes (the square grid maps onto itself)."""
    g = channel_grid
    n = len(g.channel_names)
    rotations = np.zeros(n)
    rotations[0] = math.pi / 2
    out = perturb_table(
        g.table, g.x0, g.y0, g.step, _draw(n, rotations=rotations), np.zeros((n, 2)), 0.05
    )
    R = np.array([[0.0, -1.0], [1.0, 0.0]])
    i, j = 70, 40  # node p; Rᵀp is node (j, 100 − i) on the symmetric 101-node grid
    src = g.table[j, 100 - i, 0]
    assert_allclose(out[i, j, 0, :2], R @ src[:2], rtol=1e-9, atol=1e-15)
    assert_allclose(out[i, j, 0, 2:].reshape(2, 2), R @ src[2:].reshape(2, 2) @ R.T, atol=1e-12)


# --------------------------------------------------------------------------------------------
# presets and settings


def test_presets_load_and_ideal_is_all_off() -> None:
    from magrun.protocol import PLANT_PRESETS, SimulationSettings

    for name in PLANT_PRESETS:
        imp = SimulationSettings(plant=name).imperfections()
        assert imp.ideal == (name == "ideal")
    bench = SimulationSettings(plant="bench", frame_age_ms=7.0).imperfections()
    assert bench.frame_age == pytest.approx(7e-3)  # a setting overrides the preset
    assert bench.tracker_position > 0


def _protocol(tmp_path: Path, simulation: str) -> Path:
    p = tmp_path / "p.yaml"
    p.write_text(
        f"name: t\ntrajectory: {{kind: s_curve}}\nmethods: [baseline1]\nsimulation:\n{simulation}"
    )
    return p


@pytest.mark.parametrize(
    ("setting", "field"),
    [
        ("  frame_age_ms: -5\n", "simulation.frame_age_ms"),
        ("  tracker_sigma_mm: .nan\n", "simulation.tracker_sigma_mm"),
        ("  drop_rate: 1.0\n", "simulation.drop_rate"),
        ("  plant: no_such_plant.yaml\n", "simulation.plant"),
    ],
)
def test_bad_plant_settings_exit_2_with_the_line(tmp_path: Path, setting: str, field: str) -> None:
    from click.testing import CliRunner

    from magrun.cli import cli

    path = _protocol(tmp_path, "  plant: bench\n" + setting if "plant:" not in setting else setting)
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2, result.output
    assert f"{path}:" in result.output
    assert field in result.output
    assert "Traceback" not in result.output


def test_a_bad_plant_file_is_named_with_its_line(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from magrun.cli import cli

    (tmp_path / "lab.yaml").write_text("frame_age_ms: 10\namplifier_tau_ms: -1\n")
    path = _protocol(tmp_path, "  plant: lab.yaml\n")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2, result.output
    assert "lab.yaml:2" in result.output
    assert "amplifier_tau_ms" in result.output


def test_a_plant_file_is_read_relative_to_the_protocol(tmp_path: Path) -> None:
    from magrun.protocol import load_protocol

    (tmp_path / "lab.yaml").write_text("description: my bench\namplifier_tau_ms: 12\n")
    protocol = load_protocol(_protocol(tmp_path, "  plant: lab.yaml\n  frame_age_ms: 4\n"))
    imp = protocol.simulation.imperfections()
    assert imp.amplifier_tau == pytest.approx(0.012)
    assert imp.frame_age == pytest.approx(0.004)
    assert imp.tracker_position == 0.0  # left out of the file: off


def test_a_bench_trial_records_its_plant_and_the_measured_prediction(tmp_path: Path) -> None:
    """A short bench trial: the plant record holds the settings and draws; results.csv has
    the prediction error against the measured pose and the coils' effort."""
    from analysis.load import read_recording
    from magrun.protocol import load_protocol
    from magrun.runner import run_protocol

    path = tmp_path / "b.yaml"
    path.write_text(
        "name: b\ntrajectory: {kind: s_curve}\nmethods: [baseline1]\ntrials: 1\n"
        "duration_s: 2\nfeedback: {camera: false}\nsimulation: {plant: bench}\n"
    )
    manifest = run_protocol(load_protocol(path), tmp_path / "out", jobs=1)
    entry = manifest["trials"][0]
    assert entry["status"] == "ok", entry
    assert 0 < entry["rms_prediction_measured_position_mm"] < 10
    rec = read_recording(tmp_path / "out" / "b" / entry["mcap"])
    from mcap.reader import make_reader

    with open(tmp_path / "out" / "b" / entry["mcap"], "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    imp = json.loads(meta["plant"]["imperfections"])
    assert imp["frame_age"] == pytest.approx(0.02)
    draw = json.loads(meta["plant"]["draw"])
    assert set(draw["coil_offsets_mm"]) == set(rec.currents.columns) - {"t", "t_ns"}
    assert rec.trial["max_current_a"] == [30.0] * 8
    # the results table and the report say which plant the trials ran on
    import analysis
    from analysis.report import report_markdown

    data = analysis.load(tmp_path / "out")
    assert data.trials["plant"].tolist() == ["bench"]
    assert "Simulated plant (`simulation.plant`): bench (1 trials)." in report_markdown(data)


def test_a_bench_trial_is_the_same_every_time(tmp_path: Path) -> None:
    """Every imperfection on (the clinical preset: frame age with jitter, flow, outliers,
    drops): the same protocol and seed record the same poses and currents, bit for bit."""
    from magrun.protocol import load_protocol
    from magrun.recordings.reader import read_ticks
    from magrun.runner import run_protocol

    path = tmp_path / "c.yaml"
    path.write_text(
        "name: c\ntrajectory: {kind: s_curve}\nmethods: [proposed]\ntrials: 1\nduration_s: 2\n"
        "conditions: {tracking_rate_hz: 7.5, noise_sigma_mm: 1}\nfeedback: {camera: false}\n"
        "simulation: {plant: clinical}\n"
    )
    runs = []
    for k in range(2):
        manifest = run_protocol(load_protocol(path), tmp_path / f"out{k}", jobs=1)
        runs.append(read_ticks(tmp_path / f"out{k}" / "c" / manifest["trials"][0]["mcap"]))
    a, b = runs
    for stream in ("actual", "measured", "estimated", "predicted"):
        assert np.array_equal(a.poses[stream], b.poses[stream], equal_nan=True), stream
    assert np.array_equal(a.currents, b.currents)
    assert np.isfinite(a.poses["measured"][:, 0]).sum() > 5  # measurements arrived


# --------------------------------------------------------------------------------------------
# the camera's own artefacts: motion blur, glints, occluders


def _quiet_renderer(robot_name: str = "drug_delivery"):
    from magrun.robot import load_robot
    from magrun.tracking.camera import Camera, CameraConfig
    from magrun.tracking.render import Renderer

    camera = Camera(CameraConfig(noise=0.0, lighting=0.0))
    return camera, Renderer(camera, load_robot(robot_name), seed=1)


def test_a_motion_blurred_frame_is_the_mean_of_the_frames_along_the_exposure() -> None:
    """Without sensor noise and flicker a frame is a linear map of the scene, so the robot
    blurred over four poses is the mean of the four sharp frames (to the uint8 rounding: one
    grey level), and differs from the sharp frame at the exposure's end."""
    _camera, renderer = _quiet_renderer()
    poses = np.array([[1e-3 * k, 2e-3, 0.3 + 0.05 * k] for k in range(4)])
    blurred = renderer.render(poses[-1], poses).astype(float)
    sharp = np.array([renderer.render(p).astype(float) for p in poses])
    assert np.max(np.abs(blurred - sharp.mean(axis=0))) <= 1.0
    assert np.max(np.abs(blurred - sharp[-1])) > 20  # the blur is visible
    # one pose over the whole exposure: the sharp frame
    held = renderer.render(poses[0], np.repeat(poses[:1], 4, axis=0)).astype(float)
    assert np.max(np.abs(held - sharp[0])) <= 1.0


def test_glints_and_occluders_appear_at_their_rates_near_the_robot() -> None:
    """Over 3000 frames, the share with a glint and with an occluder is each rate within
    five binomial standard deviations, and every changed pixel lies within reach of the
    robot's pixel plus the artefact's own size (a glint's 4 σ, an occluder's radius)."""
    from magrun.rigs.plant import ImageArtifacts

    camera, renderer = _quiet_renderer()
    frame = renderer.render([0.0, 0.0, 0.0])
    centre = camera.to_pixel([0.0, 0.0])
    radius = 1.4e-3 * camera.scale
    reach = 3.7e-3 * camera.scale
    n = 3000
    for field_name, rate, size in (("glare_rate", 0.1, 4 * 3.0), ("occlusion_rate", 0.05, radius)):
        art = ImageArtifacts(Imperfections(**{field_name: rate}), 7, radius)
        hits = 0
        for _ in range(n):
            out = art(frame, centre, reach)
            if out is frame:  # the frame itself, unchanged: nothing to look for
                continue
            changed = np.argwhere(np.any(out != frame, axis=2))
            if len(changed) == 0:
                continue
            hits += 1
            d = np.hypot(changed[:, 1] - centre[0], changed[:, 0] - centre[1])
            if field_name == "occlusion_rate":
                assert d.max() <= reach + size + 1
            else:  # a glint's tail beyond 4 σ adds under half a grey level
                strong = np.any(np.abs(out.astype(int) - frame) > 2, axis=2)
                far = np.argwhere(strong)
                assert len(far) > 0  # a glint of 120 grey levels or more shows
                d = np.hypot(far[:, 1] - centre[0], far[:, 0] - centre[1])
                assert d.max() <= reach + size + 1
        se = math.sqrt(rate * (1 - rate) / n)
        assert abs(hits / n - rate) <= 5 * se, (field_name, hits / n)


def test_the_exposure_blurs_the_rigs_frames_and_an_ideal_camera_is_unchanged(
    coils, channel_grid
) -> None:
    """A simulated rig with a camera: with no exposure its frames are those of the ideal
    plant bit for bit; with a 40 ms exposure, a moving robot is drawn blurred (the frame
    differs from the ideal rig's) and the artefacts' stream leaves the plant's draws as they
    were (the same robot and gains)."""
    from magrun.robot import load_robot
    from magrun.tracking.camera import CameraConfig

    robot = load_robot("drug_delivery")

    def frames(imp: Imperfections) -> tuple[list[np.ndarray], SimRig]:
        rig = SimRig(coils, channel_grid, robot, perturbation=Perturbation(), seed=4,
                     camera=CameraConfig(), imperfections=imp)  # fmt: skip
        rig.reset([0.0, 0.0, 0.0])
        drive = np.zeros(coils.n_channels)
        drive[0] = 20.0  # A: a gradient that pulls the robot along
        rig.apply(drive)
        out = []
        start = rig.state[:2].copy()
        for _ in range(5):
            rig.advance(0.04)
            out.append(rig.observe(frame=True).frame)
        assert np.hypot(*(rig.state[:2] - start)) > 0.2e-3  # it moved
        return out, rig

    ideal, rig0 = frames(Imperfections())
    same, _ = frames(Imperfections(glare_rate=0.0))
    assert all(np.array_equal(a, b) for a, b in zip(ideal, same, strict=True))
    blurred, rig1 = frames(Imperfections(exposure=0.04))
    assert any(not np.array_equal(a, b) for a, b in zip(ideal, blurred, strict=True))
    assert rig1.robot == rig0.robot
    assert_allclose(rig1.coil_gains, rig0.coil_gains, rtol=0, atol=0)
