"""What a coil system can do with a robot (magrun.field.capability, ``magrun field check``).

The linear program is checked against a two-channel pose solved by hand, and its currents on
an imported three-coil system with a background field against the robot's wrench computed
independently (:func:`magrun.robot.magnetic_wrench` on the model's field at those currents).
``magrun run`` refuses a trajectory the coils cannot follow, naming where.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from test_emns import SYNTHETIC

from magrun.cli import cli
from magrun.field.capability import (
    HELD_SAMPLES,
    HELD_SMOOTHING,
    HELD_SPARE,
    Site,
    WorkspaceCapability,
    _sites,
    held_reference,
    pose_capability,
    reachable,
    trajectory_capability,
)
from magrun.field.coils import CoilSystem
from magrun.field.mpem import import_mpem
from magrun.field.system import load_system
from magrun.protocol import load_protocol
from magrun.robot import drag_matrix, load_robot, magnetic_wrench
from magrun.scene import s_trajectory
from magrun.trial import (
    HELD_ANGLE_WEIGHT,
    PAPER_SPEED_FACTOR,
    RunError,
    check_system,
    check_tracking,
)

ROOT = Path(__file__).resolve().parents[1]
ROBOT = load_robot("micro_magnet")


@pytest.fixture(scope="module")
def three(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three unsymmetric dipole coils and a background field, imported over ±10 mm."""
    base = tmp_path_factory.mktemp("three")
    (base / "three.yaml").write_text(SYNTHETIC)
    return import_mpem(base / "three.yaml", base / "system", 0.0, (0.0, 0.0), 10e-3)


def _two_channels(field_direction: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Channel 0: a uniform field of 1 mT/A along ``field_direction``; channel 1: a pure
    gradient ∂Bx/∂x = −∂By/∂y = 0.5 T/(m A) (divergence-free) and no field at the point."""
    B = np.array([[field_direction[0] * 1e-3, field_direction[1] * 1e-3], [0.0, 0.0]])
    G = np.zeros((2, 2, 2))
    G[1] = [[0.5, 0.0], [0.0, -0.5]]
    return B, G


def test_the_speed_along_the_axis_is_the_force_the_gradient_gives_over_the_drag() -> None:
    """Heading along x, moving along x: the force is m ∂Bx/∂x I₁ (largest at I₁ = I_max), the
    field along the moment I₀ · 1 mT (at least B_min), no torque: s = m g I_max / d∥."""
    B, G = _two_channels((1.0, 0.0))
    site = Site(B, G, np.zeros(2), np.zeros((2, 2)), np.array([2.0, 3.0]), ROBOT)
    cap = pose_capability(site, 0.0, [1.0, 0.0])
    assert cap.speed_factor == pytest.approx(ROBOT.moment * 0.5 * 3.0 / ROBOT.drag_parallel)
    assert cap.currents is not None
    assert cap.currents[0] * 1e-3 >= ROBOT.min_aligned_field - 1e-12
    assert cap.currents[1] == pytest.approx(3.0)
    # across the axis the gradient pushes nothing: the robot cannot move sideways at all
    side = pose_capability(site, 0.0, [0.0, 1.0])
    assert side.speed_factor == pytest.approx(0.0, abs=1e-9)


def test_a_pose_whose_heading_no_current_can_hold_is_not_holdable() -> None:
    """The only field is across the heading: holding it needs zero torque, so I₀ = 0, and
    then nothing is left along the moment (B_min > 0): no solution at all (NaN)."""
    B, G = _two_channels((0.0, 1.0))
    site = Site(B, G, np.zeros(2), np.zeros((2, 2)), np.array([2.0, 3.0]), ROBOT)
    cap = pose_capability(site, 0.0, [1.0, 0.0])
    assert math.isnan(cap.speed_factor)
    assert cap.currents is None
    # turned by 90° the field lies along the moment: held, and moving along it is possible
    factor, offset = reachable(site, 0.0, [0.0, 1e-3])
    assert factor >= 1.0
    assert abs(offset) > 0


def test_the_currents_give_the_asked_wrench_on_a_three_coil_system(three: Path) -> None:
    """On the imported three-coil system (background included), at poses across the
    workspace, the LP's currents, put through the model and the robot's wrench, give the
    force s D(θ) v, the torque d_r ω and the field along the moment ≥ B_min, within limits."""
    coils = CoilSystem.load(three)
    model = load_system(three).models[1]
    limits = np.full(3, 10.0)
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(40):
        p = rng.uniform(-8e-3, 8e-3, 2)
        theta = rng.uniform(-math.pi, math.pi)
        v = rng.normal(size=2) * 1e-3
        omega = rng.normal() * 0.2
        B, G = model.unit_field_and_gradient(p)
        B0, G0 = model.background_field_and_gradient(p)
        cap = pose_capability(Site(B, G, B0, G0, limits, ROBOT), theta, v, omega)
        if cap.currents is None:
            continue
        checked += 1
        assert np.all(np.abs(cap.currents) <= limits * (1 + 1e-9))
        Bt, Gt = model.field_and_gradient(p, cap.currents)
        force, torque = magnetic_wrench(theta, ROBOT.moment, Bt, Gt)
        expected = cap.speed_factor * drag_matrix(ROBOT, theta) @ v
        scale = np.abs(ROBOT.moment * np.abs(G).max() * limits).max()  # N: the largest force
        assert_allclose(force, expected, atol=1e-7 * scale)
        assert torque == pytest.approx(ROBOT.drag_rotation * omega, abs=1e-7 * scale * 1e-2)
        along = Bt @ np.array([math.cos(theta), math.sin(theta)])
        assert along >= ROBOT.min_aligned_field * (1 - 1e-6)
    assert coils.n_channels == 3
    assert checked >= 10


def test_a_slow_s_is_within_reach_and_a_fast_one_is_not(three: Path) -> None:
    model = load_system(three).models[1]
    slow = s_trajectory(size=0.012, speed=1e-3)
    assert trajectory_capability(model, ROBOT, 10.0, slow, samples=80).feasible
    fast = s_trajectory(size=0.012, speed=0.5)
    reach = trajectory_capability(model, ROBOT, 10.0, fast, samples=80)
    assert not reach.feasible
    # where the S turns, the robot cannot even be turned that fast (NaN); on its straight
    # parts the gradient cannot push it to 0.5 m/s
    straight = np.abs(reach.turn_rate) < 1e-9
    assert np.any(straight)
    assert np.all(reach.factor[straight] < 1.0)
    assert np.all(reach.speed[straight] == pytest.approx(0.5, rel=1e-3))


def test_run_refuses_a_trajectory_the_coils_cannot_follow(three: Path, tmp_path: Path) -> None:
    overrides = [f"system={three}", "trajectory.speed_mm_s=100"]
    protocol = load_protocol(ROOT / "protocols" / "octomag.yaml", overrides=overrides)
    with pytest.raises(RunError, match=r"the coils can move the robot at .*% of the 100"):
        check_system(protocol)
    check_system(protocol, feasibility=False)  # told to go on: only the rest is checked
    args = ["run", str(ROOT / "protocols" / "octomag.yaml"), "--out", str(tmp_path), "--quick"]
    args += [a for o in overrides for a in ("--set", o)]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2, result.output
    assert "--allow-infeasible" in result.output
    assert not (tmp_path / "octomag").exists()  # nothing was run or written


def test_every_shipped_protocol_is_within_its_coils_reach() -> None:
    """... and where it tracks camera frames, its robot is one the tracker finds."""
    for path in sorted((ROOT / "protocols").glob("*.yaml")):
        protocol = load_protocol(path)
        check_system(protocol, tracking=protocol.feedback.camera)


def _must_not_run(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("the probe ran again")


def test_run_refuses_camera_feedback_for_a_robot_the_tracker_cannot_find(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The probe itself (a cache of the test's own): the paper's two robots are found in
    their rendered frames; micro_magnet, a quarter of the magnet robot's length, in none, and
    its run is refused before anything is written, the remedy named. From the machine's
    cache a second check gives the same verdicts without tracking a frame."""
    import magrun.tracking.evaluate

    refused = r"'micro_magnet' \(4 mm × 1 mm.* in 100% of 40"
    with monkeypatch.context() as m:
        m.setenv("MAGRUN_CACHE_DIR", str(tmp_path / "cache"))
        for again in (False, True):
            if again:  # the answers kept: nothing is rendered or tracked
                m.setattr(magrun.tracking.evaluate, "evaluate", _must_not_run)
            for name in ("magnet", "drug_delivery"):
                check_tracking(load_robot(name))
            with pytest.raises(RunError, match=refused):
                check_tracking(load_robot("micro_magnet"))
        assert len(list((tmp_path / "cache" / "answers").glob("tracking-*.json"))) == 3
    args = ["run", str(ROOT / "protocols" / "octomag.yaml"), "--out", str(tmp_path / "out")]
    result = CliRunner().invoke(cli, [*args, "--quick", "--set", "feedback.camera=true"])
    assert result.exit_code == 2, result.output
    assert "Set `feedback: {camera: false}`" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()  # nothing was run or written


def test_field_check_prints_a_summary_and_draws_the_map(three: Path, tmp_path: Path) -> None:
    figure = tmp_path / "check.png"
    args = ["field", "check", str(three), "--robot", "micro_magnet", "--points", "4"]
    result = CliRunner().invoke(cli, [*args, "--speed-mm-s", "1", "--json", "--out", str(figure)])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["robot"] == "micro_magnet"
    assert summary["positions"] == 16
    assert summary["feasible"] is True
    assert summary["largest_force_uN"] > 0
    assert figure.stat().st_size > 10_000
    too_fast = CliRunner().invoke(cli, [*args, "--speed-mm-s", "900", "--headings", "2", "--json"])
    assert json.loads(too_fast.output)["feasible"] is False
    bad = CliRunner().invoke(cli, [*args, "--out", str(tmp_path / "map.txt")])
    assert bad.exit_code == 2
    assert "png" in bad.output


#: three dipole coils 120° apart, 50 mm from the centre and pointing at it (docs/systems.md)
TRI = "Coil_List: [c0, c1, c2]\n" + "".join(
    f"{name}:\n  Source_List: [s]\n  s: {{Source_Position: [{x}, {y}, 0.0], "
    f"Source_Direction: [{dx}, {dy}, 0.0], B_Coeff: [2.0e-7]}}\n"
    for name, x, y, dx, dy in (
        ("c0", 0.0, 0.05, 0.0, -1.0),
        ("c1", -0.043301, -0.025, 0.866025, 0.5),
        ("c2", 0.043301, -0.025, -0.866025, 0.5),
    )
)


def test_the_planned_headings_are_ones_the_coils_hold(tmp_path: Path) -> None:
    """On three symmetric coils the S's own heading cannot be held on much of it (no
    currents give the force and hold the heading there): the planned reference keeps the
    positions and timing, turns the headings there, and at each checked pose its offset
    (before smoothing) is one at which the coils give the velocity HELD_SPARE times over,
    where the reference's own heading does not; elsewhere it is zero."""
    (tmp_path / "tri.yaml").write_text(TRI)
    folder = import_mpem(tmp_path / "tri.yaml", tmp_path / "tri", 0.0, (0.0, 0.0), 10e-3)
    model = load_system(folder).models[1]
    reference = s_trajectory(size=12e-3, speed=1e-3)
    held = held_reference(model, ROBOT, 10.0, reference)
    planned, offsets = held.trajectory, held.offsets
    assert planned is not reference
    # the same positions at the same times: on the reference's knots and the samples'
    assert np.all(np.isin(reference.t, planned.t))
    assert_allclose(planned.poses[:, :2], reference.pose(planned.t)[:, :2], rtol=0, atol=1e-12)
    t = np.linspace(0.0, reference.duration, HELD_SAMPLES)
    poses = reference.pose(t)
    rates = np.gradient(poses, t, axis=0)
    sites = _sites(model, ROBOT, np.full(3, 10.0), poses[:, :2])

    def factor(k: int, offset: float) -> float:
        cap = pose_capability(sites[k], poses[k, 2] + offset, rates[k, :2], rates[k, 2])
        return cap.speed_factor

    turned = np.flatnonzero(offsets)
    assert 0.2 < len(turned) / HELD_SAMPLES < 0.8  # the S's second half, about (49 % here)
    for k in turned[:: max(1, len(turned) // 25)]:  # 25 of them: an LP each
        assert not factor(k, 0.0) >= HELD_SPARE
        assert factor(k, offsets[k]) >= HELD_SPARE
        assert held.factor[k] == pytest.approx(factor(k, offsets[k]), rel=1e-9)
    for k in np.flatnonzero(offsets == 0)[::40]:
        assert factor(k, 0.0) >= HELD_SPARE
    # the planned headings are the reference's plus the smoothed offsets: within their range
    turn = planned.poses[:, 2] - reference.pose(planned.t)[:, 2]
    assert turn.min() >= offsets.min() - 1e-12
    assert turn.max() <= offsets.max() + 1e-12


def test_a_reference_of_few_knots_keeps_its_held_headings_between_them(tmp_path: Path) -> None:
    """A hand-drawn polyline has a knot only at each corner: the headings the coils can hold,
    found at HELD_SAMPLES poses along it, are the planned reference's between its knots too
    (they once reached the planner only where a knot fell, so it followed the reference's
    own headings). The planned headings at the samples are the reference's plus the
    smoothed offsets, and the run's warning states them."""
    from magrun.runner import _held_heading_warning
    from magrun.scene import out_and_back

    (tmp_path / "tri.yaml").write_text(TRI)
    folder = import_mpem(tmp_path / "tri.yaml", tmp_path / "tri", 0.0, (0.0, 0.0), 10e-3)
    model = load_system(folder).models[1]
    reference = out_and_back(np.array([[-4, -3], [-1, 3], [2, -3], [4, 2]]) * 1e-3, 1e-3)
    assert len(reference.t) < HELD_SAMPLES / 4  # few knots
    held = held_reference(model, ROBOT, 10.0, reference)
    assert held.offsets.any()
    t = np.linspace(0.0, reference.duration, HELD_SAMPLES)
    turn = held.trajectory.pose(t)[:, 2] - reference.pose(t)[:, 2]
    half = HELD_SMOOTHING // 2
    smooth = np.convolve(np.pad(held.offsets, half, mode="edge"), np.ones(HELD_SMOOTHING), "valid")
    assert_allclose(turn, smooth / HELD_SMOOTHING, rtol=0, atol=1e-9)
    assert np.degrees(np.abs(turn).max()) > 4.0  # a 5° step at least, smoothed
    (warning,) = _held_heading_warning(held.trajectory, reference)
    assert "cannot hold the reference's heading" in warning
    assert _held_heading_warning(reference, reference) == []


def test_a_reference_the_coils_hold_is_planned_as_it_is() -> None:
    """The paper rig's S for the magnet robot (its protocol's) is held at every pose: the
    planner gets the reference object itself, so nothing of the paper rig's trials changes."""
    protocol = load_protocol(ROOT / "protocols" / "rate.yaml")
    coils = check_system(protocol, feasibility=False)
    from magrun.trial import build_scene

    reference = build_scene(protocol, coils).reference
    model = load_system(coils.folder).models[1]
    held = held_reference(model, load_robot("magnet"), coils.max_current, reference)
    assert held.trajectory is reference
    assert not held.offsets.any()
    # the coils give the S's velocity about 8 times over: the NMPC's weights as set there
    assert 5.0 < held.median_factor <= PAPER_SPEED_FACTOR


def test_the_nmpc_weighs_currents_by_what_the_task_needs() -> None:
    """The weights were set on the paper rig, whose coils give its references' velocities
    about PAPER_SPEED_FACTOR times over: where a system gives the reference's velocity f times
    over, the same work takes currents f / PAPER_SPEED_FACTOR times smaller as fractions of
    the limit, so R and S scale by that squared (never below the paper rig's); the step damping
    is 1 where the planner follows held headings, and its steps are checked there. A
    protocol's numbers (and its step_check) override these."""
    from magrun.control.nmpc import NMPCConfig
    from magrun.protocol import ControllerSettings
    from magrun.trial import nmpc_tuning

    base = NMPCConfig()
    auto = ControllerSettings()
    strong = nmpc_tuning(base, auto, True, 2 * PAPER_SPEED_FACTOR)
    assert strong.r_current == pytest.approx(4 * base.r_current)
    assert strong.s_current_change == pytest.approx(4 * base.s_current_change)
    assert strong.step_damping == 1.0
    # where the headings are held, they are the planner's, not the task's: weighed lightly
    assert strong.q_angle == pytest.approx(HELD_ANGLE_WEIGHT * base.q_angle)
    assert strong.q_angle_terminal == pytest.approx(HELD_ANGLE_WEIGHT * base.q_angle_terminal)
    assert strong.step_check  # and its steps checked (light heading weights let them diverge)
    paper = nmpc_tuning(base, auto, False, 0.7 * PAPER_SPEED_FACTOR)
    assert (paper.r_current, paper.s_current_change, paper.step_damping, paper.q_angle) == (
        base.r_current, base.s_current_change, 0.0, base.q_angle,
    )  # fmt: skip
    assert not paper.step_check
    assert nmpc_tuning(base, auto, False, math.nan).r_current == base.r_current
    given = ControllerSettings(step_damping=0.25, current_weight=3.0, angle_weight=0.5)
    tuned = nmpc_tuning(base, given, True, 10 * PAPER_SPEED_FACTOR)
    assert tuned.step_damping == 0.25
    assert tuned.q_angle == pytest.approx(0.5 * base.q_angle)
    assert tuned.r_current == pytest.approx(3 * base.r_current)
    assert tuned.step_check  # auto: held
    # the protocol's step_check wins over the held-heading rule, either way
    off = nmpc_tuning(base, ControllerSettings(step_check=False), True, PAPER_SPEED_FACTOR)
    on = nmpc_tuning(base, ControllerSettings(step_check=True), False, PAPER_SPEED_FACTOR)
    assert (off.step_check, on.step_check) == (False, True)
    with pytest.raises(ValueError, match="step_check"):
        ControllerSettings(step_check="maybe")  # type: ignore[arg-type]


def test_integral_action_where_the_weights_are_raised_and_the_headings_are_the_references() -> None:
    """auto: INTEGRAL_TIME where the current weights are above the paper rig's and the planner
    follows the reference's own headings; none on the paper rig (its trials unchanged), none
    where the headings are held; a protocol's number (0 included) wins."""
    from magrun.protocol import ControllerSettings
    from magrun.trial import INTEGRAL_TIME, integral_time

    auto = ControllerSettings()
    assert integral_time(auto, False, 2 * PAPER_SPEED_FACTOR) == INTEGRAL_TIME
    assert integral_time(auto, True, 2 * PAPER_SPEED_FACTOR) == 0.0
    assert integral_time(auto, False, 0.9 * PAPER_SPEED_FACTOR) == 0.0
    assert integral_time(auto, False, math.nan) == 0.0
    # a weight the protocol raises turns it on as the speed factor would
    assert integral_time(ControllerSettings(current_weight=2.0), False, 1.0) == INTEGRAL_TIME
    assert integral_time(ControllerSettings(integral_time_s=0), False, 50.0) == 0.0
    assert integral_time(ControllerSettings(integral_time_s=2.5), True, 1.0) == 2.5


def test_the_heading_withstands_the_filters_position_error_where_it_is_held() -> None:
    """auto: POSITION_SIGMAS × the Kalman filter's steady position σ before a frame where the
    planner follows held headings (so 2 × 1.5 mm at 3 Hz with σ = 2 mm, hand-computed from
    P⁻² − n q² P⁻ − n q² r² = 0 with n = 9, q = 0.3 mm, r = 2 mm: P⁻ = 2.25 mm²), 0 where it
    follows the reference's (the paper rig's, OctoMag's, MiniMag's trials unchanged); a
    protocol's number, in mm, wins."""
    from magrun.control.estimation import KalmanConfig
    from magrun.protocol import ControllerSettings
    from magrun.trial import POSITION_SIGMAS, position_uncertainty

    kalman = KalmanConfig(measurement_position=2e-3, process_position=0.3e-3)
    auto = ControllerSettings()
    assert position_uncertainty(auto, True, kalman, 9) == pytest.approx(POSITION_SIGMAS * 1.5e-3)
    assert position_uncertainty(auto, False, kalman, 9) == 0.0
    given = ControllerSettings(position_uncertainty_mm=0.7)
    assert position_uncertainty(given, False, kalman, 1) == pytest.approx(0.7e-3)
    assert position_uncertainty(ControllerSettings(position_uncertainty_mm=0), True, kalman, 9) == 0


def test_strong_tracking_guards_the_linearised_filter_and_helps_the_papers_where_held() -> None:
    """auto: with the linearised filter (the default) the fading is on everywhere as a
    divergence guard (β = GUARD_WEAKENING); with the paper's filter (F = I) it is on where
    the planner follows held headings, at β = 1.5; a protocol's choice of on or off wins
    either way, with the weakening of its filter."""
    from magrun.control.estimation import KalmanConfig
    from magrun.protocol import ControllerSettings, KalmanSettings
    from magrun.trial import GUARD_WEAKENING, strong_tracking

    auto = ControllerSettings()
    assert auto.kalman.linearised is True
    assert strong_tracking(auto, True) == (True, GUARD_WEAKENING)
    assert strong_tracking(auto, False) == (True, GUARD_WEAKENING)
    paper = ControllerSettings(kalman=KalmanSettings(linearised=False))
    assert strong_tracking(paper, True) == (True, KalmanConfig.weakening)
    assert strong_tracking(paper, False) == (False, KalmanConfig.weakening)
    off = ControllerSettings(kalman=KalmanSettings(strong_tracking=False))
    assert strong_tracking(off, True) == (False, GUARD_WEAKENING)
    on = ControllerSettings(kalman=KalmanSettings(strong_tracking=True, linearised=False))
    assert strong_tracking(on, False) == (True, KalmanConfig.weakening)


def test_soft_constraints_as_slacks_where_the_headings_are_held() -> None:
    """auto: the NMPC's soft constraints as slacks of its QPs where the planner follows held
    headings, as penalty residuals elsewhere (OctoMag's and MiniMag's trials unchanged); a
    protocol's choice wins."""
    from magrun.protocol import ControllerSettings
    from magrun.trial import soft_constraints

    auto = ControllerSettings()
    assert soft_constraints(auto, True) == "slack"
    assert soft_constraints(auto, False) == "penalty"
    assert soft_constraints(ControllerSettings(soft_constraints="penalty"), True) == "penalty"
    assert soft_constraints(ControllerSettings(soft_constraints="slack"), False) == "slack"


#: each coil's field over the model's in the sweep below (a plant's per-coil gain error)
GAINS = np.array([0.97, 1.04, 0.99])


@pytest.fixture(scope="module")
def tri_nmpc(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The proposed method's NMPC on three symmetric coils, tuned as a trial on them is (the
    S's headings held, so step damping 1 and the current weights of its speed factor)."""
    from magrun.control.nmpc import NMPC, NMPCConfig
    from magrun.protocol import ControllerSettings
    from magrun.trial import nmpc_tuning

    base = tmp_path_factory.mktemp("tri")
    (base / "tri.yaml").write_text(TRI)
    folder = import_mpem(base / "tri.yaml", base / "tri", 0.0, (0.0, 0.0), 10e-3)
    zernike, lut = load_system(folder).models
    held = held_reference(lut, ROBOT, 10.0, s_trajectory(size=12e-3, speed=1e-3))
    assert held.offsets.any()
    config = nmpc_tuning(NMPCConfig(), ControllerSettings(), True, held.median_factor)
    return NMPC(zernike, ROBOT, config)


#: a start the sweep below found: 2 rad off the direction of travel, where plain
#: Gauss-Newton steps diverged (:func:`test_checked_steps_keep_a_turned_start_on_three_coils`)
TURNED = {"x": 0.0, "y": 0.001953125, "heading": -2.0, "direction": 0.0, "speed": 0.001953125,
          "turn": 0.0}  # fmt: skip


@settings(max_examples=40, deadline=None)
@example(**TURNED)
@given(
    x=st.floats(-7e-3, 7e-3), y=st.floats(-7e-3, 7e-3), heading=st.floats(-math.pi, math.pi),
    direction=st.floats(-math.pi, math.pi), speed=st.floats(0.0, 2e-3),
    turn=st.floats(-0.5, 0.5),
)  # fmt: skip
def test_the_nmpc_solves_every_tick_on_three_coils(
    tri_nmpc: Any, x: float, y: float, heading: float, direction: float, speed: float,
    turn: float,
) -> None:  # fmt: skip
    """From any start pose in the workspace, towards a reference moving up to 2 mm/s in any
    direction at a heading up to 0.5 rad from the start's: the first tick (iterated) and 15
    real-time ticks after it, the robot moving as the model says for coils a few per cent off
    (GAINS, as a simulated rig's), each solve, with finite currents within the limits."""
    nmpc = tri_nmpc
    nmpc.reset()
    state = np.array([x, y, heading, 0.0, 0.0, 0.0])
    currents = np.zeros(3)
    t = np.arange(nmpc.config.horizon + 1) * nmpc.config.dt
    for tick in range(16):
        s = t + tick * nmpc.config.dt
        window = np.column_stack([
            x + speed * s * math.cos(direction), y + speed * s * math.sin(direction),
            np.full(s.size, heading + turn),
        ])  # fmt: skip
        plan = nmpc.plan(state, window, currents)
        assert plan.status.success, (tick, plan.status)
        assert np.all(np.isfinite(plan.currents))
        assert np.all(np.abs(plan.currents) <= nmpc.max_current + 1e-9)
        currents = plan.currents
        state = nmpc.predict(state, currents * GAINS)  # coils a few per cent off the model


def test_checked_steps_keep_a_turned_start_on_three_coils(tri_nmpc: Any) -> None:
    """From :data:`TURNED`, with the held headings' light heading weights: unchecked, the
    first tick's Gauss-Newton iterates run off (to the position bound at 100-200 mm/s, until
    HPIPM stops at its minimum step), so that tick fails or plans currents whose objective
    is at least twice the checked plan's. Checked (the trial's tuning), it and 15 real-time
    ticks solve, and the robot, moving as the model says, stays below 10 mm/s where the
    reference moves at 2 mm/s."""
    from dataclasses import replace

    from magrun.control.nmpc import NMPC, STATE_SCALE

    nmpc = tri_nmpc
    assert nmpc.config.step_check
    t = np.arange(nmpc.config.horizon + 1) * nmpc.config.dt
    start = np.array([TURNED["x"], TURNED["y"], TURNED["heading"], 0.0, 0.0, 0.0])

    def window(tick: int) -> np.ndarray:
        s = t + tick * nmpc.config.dt
        return np.column_stack([TURNED["x"] + TURNED["speed"] * s, np.full(s.size, TURNED["y"]),
                                np.full(s.size, TURNED["heading"])])  # fmt: skip

    def first_objective(planner: Any) -> float:
        planner.reset()
        plan = planner.plan(start, window(0), np.zeros(3))
        if not plan.status.success:
            return math.inf
        u = planner.backend.currents_plan()
        x0, u_prev, par = planner._start(start, window(0), np.zeros(3))
        return float(planner.problem.cost(x0 / STATE_SCALE, u_prev, par, u))

    unchecked = NMPC(nmpc.model, nmpc.robot, replace(nmpc.config, step_check=False))
    assert first_objective(unchecked) >= 2 * first_objective(nmpc)
    nmpc.reset()
    state, currents = start.copy(), np.zeros(3)
    for tick in range(16):
        plan = nmpc.plan(state, window(tick), currents)
        assert plan.status.success, (tick, plan.status)
        currents = plan.currents
        state = nmpc.predict(state, currents * GAINS)
        assert math.hypot(state[3], state[4]) < 10e-3, tick


@pytest.mark.parametrize("linearised", [True, False])
def test_a_protocols_filter_choice_reaches_the_filter(linearised: bool) -> None:
    """``controller.kalman.linearised`` is the Kalman filter's (and its controller computes
    the prediction's Jacobian only for a filter that uses it)."""
    from magrun.control.estimation import KalmanPoseFilter
    from magrun.protocol import Protocol
    from magrun.trial import control_config

    protocol = Protocol.model_validate(
        {
            "name": "f", "description": "filter", "robot": "magnet", "workspace": {"kind": "open"},
            "trajectory": {"kind": "s_curve"}, "methods": ["proposed"], "trials": 1,
            "controller": {"kalman": {"linearised": linearised}},
        }
    )  # fmt: skip
    (trial,) = protocol.expand()
    config = control_config(protocol.controller, protocol.robot_params(), trial.condition)
    assert config.kalman.linearised is linearised
    assert KalmanPoseFilter(config.kalman).uses_jacobian is linearised


def test_the_typical_force_is_the_median_over_the_poses_that_move() -> None:
    """Speeds by hand: NaN (heading not held) and 0 (held, cannot move) poses are left out
    of the median force; the field's median is over positions."""
    speed = np.array([[[math.nan, 0.0], [1.0, 2.0]], [[3.0, 5.0], [0.0, math.nan]]])
    field = np.array([[1e-3, 2e-3], [4e-3, 8e-3]])
    axis = np.array([-1e-3, 1e-3])
    cap = WorkspaceCapability(axis, axis, np.array([0.0, math.pi]), speed, field, 0.5, 1e-3)
    assert cap.typical_force == pytest.approx(0.5 * 2.5)  # median of 1, 2, 3, 5 m/s × 0.5 N s/m
    assert cap.typical_field == pytest.approx(3e-3)
    none = WorkspaceCapability(
        axis, axis, np.array([0.0, math.pi]), np.zeros_like(speed), field, 0.5, 1e-3
    )
    assert none.typical_force == 0.0


def test_the_coils_typical_wrench_is_homogeneous_in_the_limits() -> None:
    """With no field asked along the moment (B_min = 0) every constraint of the capability's
    linear program is homogeneous in the currents (the paper rig has no background): at twice
    the limits each pose's force and each position's largest field are exactly twice."""
    from dataclasses import replace
    from types import SimpleNamespace
    from typing import cast

    from magrun.trial import typical_wrench

    robot = replace(load_robot("magnet"), min_aligned_field=0.0)
    paper = load_system(None).models[1].coils
    stronger = cast(CoilSystem, SimpleNamespace(folder=None, max_current=2 * paper.max_current))
    force, torque = typical_wrench(paper, robot)
    assert force > 0
    assert torque > 0
    assert_allclose(typical_wrench(stronger, robot), (2 * force, 2 * torque), rtol=1e-4)


def test_the_baselines_wrench_follows_the_robots_drag_within_the_coils_reach() -> None:
    """By hand: the paper rig's values for its magnet robot, to the last digit; for another
    robot, the linear MPC's units times its drags over the magnet robot's and the
    allocation's references times its moment over the magnet robot's; on coils too weak
    for those, the linear MPC's limits are what they typically give; a number multiplies
    the paper rig's values for any robot."""
    from types import SimpleNamespace
    from typing import cast

    from magrun.control.methods import ControlConfig
    from magrun.protocol import ControllerSettings
    from magrun.trial import two_layer_tuning, typical_wrench

    auto, base = ControllerSettings(), ControlConfig()
    mpc, alloc = base.linear_mpc, base.allocation
    paper = load_system(None).models[1].coils
    magnet = load_robot("magnet")
    assert two_layer_tuning(base, auto, paper, magnet) == base

    f = ROBOT.drag_parallel / magnet.drag_parallel
    t = ROBOT.drag_rotation / magnet.drag_rotation
    tuned = two_layer_tuning(base, auto, paper, ROBOT)
    assert tuned.linear_mpc.force_unit == pytest.approx(4e-4 * f, rel=1e-12)
    assert tuned.linear_mpc.torque_unit == pytest.approx(4e-6 * t, rel=1e-12)
    assert (tuned.linear_mpc.max_force, tuned.linear_mpc.max_torque) == (
        tuned.linear_mpc.force_unit, tuned.linear_mpc.torque_unit,
    )  # fmt: skip
    m = ROBOT.moment / magnet.moment
    assert tuned.allocation.force_ref == pytest.approx(1e-5 * m, rel=1e-12)
    assert tuned.allocation.torque_ref == pytest.approx(1e-7 * m, rel=1e-12)
    assert tuned.allocation.align_field == alloc.align_field

    weak = cast(CoilSystem, SimpleNamespace(folder=None, max_current=0.2 * paper.max_current))
    force, _ = typical_wrench(weak, magnet)
    assert 0 < force < mpc.max_force  # at 6 A the paper rig gives the magnet robot less
    limited = two_layer_tuning(base, auto, weak, magnet)
    assert limited.linear_mpc.max_force == force
    assert limited.linear_mpc.force_unit == mpc.force_unit  # what a newton costs is the robot's

    given = two_layer_tuning(base, ControllerSettings(wrench_scale=0.5), paper, ROBOT)
    assert given.linear_mpc.max_force == pytest.approx(0.5 * mpc.max_force, rel=1e-12)
    assert given.allocation.torque_ref == pytest.approx(0.5 * alloc.torque_ref, rel=1e-12)


@pytest.mark.parametrize(("scale", "factor"), [("auto", 1.0), (3.0, 3.0)])
def test_a_baseline_is_built_with_the_scaled_wrench(scale: Any, factor: float) -> None:
    """The protocol's ``wrench_scale`` (``auto``: the hand-set values on the paper rig with
    its magnet robot) reaches Baseline 3's linear MPC and its allocation."""
    from magrun.control.allocation import AllocationConfig
    from magrun.control.two_layer import LinearMPCConfig, LinearMPCPlanner
    from magrun.protocol import Protocol
    from magrun.trial import build_controller

    protocol = Protocol.model_validate(
        {
            "name": "w", "description": "wrench", "robot": "magnet", "workspace": {"kind": "open"},
            "trajectory": {"kind": "s_curve"}, "methods": ["baseline3"], "trials": 1,
            "controller": {"wrench_scale": scale},
        }
    )  # fmt: skip
    (trial,) = protocol.expand()
    planner = build_controller(trial).controller.planner
    assert isinstance(planner, LinearMPCPlanner)
    mpc, alloc = LinearMPCConfig(), AllocationConfig()
    assert planner.config.max_force == factor * mpc.max_force
    assert planner.config.max_torque == factor * mpc.max_torque
    assert planner.config.force_unit == factor * mpc.force_unit
    assert planner.allocation.force_ref == factor * alloc.force_ref
    assert planner.allocation.torque_ref == factor * alloc.torque_ref
