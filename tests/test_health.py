"""Trial health: the warnings a trial that ran to its end still gets, and the one-step
prediction error the Kalman filter's process noise comes from."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from magrun.freespace import FreeSpace
from magrun.health import HealthLimits, longest_run, prediction_error, trial_health
from magrun.loop import TrialLog
from magrun.phantom import load_phantom
from magrun.protocol import load_protocol
from magrun.records import ControllerStatus
from magrun.robot import load_robots
from magrun.trial import build_scene

PROTOCOLS = Path(__file__).parents[1] / "protocols"


def _log(n: int = 100, dt: float = 0.04) -> TrialLog:
    t = np.arange(n) * dt
    poses = np.column_stack([np.linspace(0, 1e-2, n), np.zeros(n), np.zeros(n)])
    return TrialLog(
        t=t, actual=poses.copy(), tracked=poses.copy(), desired=poses.copy(),
        measured=poses.copy(), estimated=poses.copy(), predicted=poses.copy(),
        currents=np.zeros((n, 8)), status=[ControllerStatus(0.001) for _ in range(n)],
        compute_time=np.full(n, 1e-3),
    )  # fmt: skip


def test_a_clean_trial_has_no_warnings() -> None:
    figures, warnings = trial_health(_log(), 0.04, 30.0)
    assert warnings == []
    assert figures["failed_solves"] == 0
    assert figures["longest_saturation_s"] == 0.0


def test_saturation_failed_solves_and_a_lost_estimate_are_reported() -> None:
    log = _log()
    log.currents[10:40, 3] = 30.0  # 30 ticks = 1.2 s at the limit
    log.currents[50:60, 5] = -29.8  # 10 ticks (≥ 99 % of the limit)
    for k in range(20, 25):
        log.status[k] = ControllerStatus(0.001, success=False, fallback="shifted")
    log.estimated[70, 1] = 8e-3
    figures, warnings = trial_health(log, 0.04, 30.0, limits=HealthLimits(saturation_s=1.0))
    assert figures["longest_saturation_s"] == pytest.approx(1.2)
    assert figures["failed_solves"] == 5
    assert figures["max_estimate_error_mm"] == pytest.approx(8.0)
    assert len(warnings) == 3
    assert "1.2 s" in warnings[1]
    assert "t = 2.8 s" in warnings[2]


def test_a_robot_far_from_the_reference_long_enough_is_lost() -> None:
    """The reference runs 10 mm along x: the loss distance is a quarter of that, 2.5 mm. A
    robot 3 mm off in 30 of 100 ticks is lost (≥ 25 %), in 20 it is not; 2 mm off in every
    tick is an error, not a loss; a tick without a pose (NaN) counts as far."""
    log = _log()
    log.actual[:30, 1] = 3e-3
    figures, warnings = trial_health(log, 0.04, 30.0)
    assert figures["lost"] is True
    assert figures["lost_share"] == pytest.approx(0.30)
    assert (
        warnings[0] == "the robot was lost: more than 2.5 mm from the reference in 30% of the ticks"
    )
    log.actual[20:30, 1] = 0.0
    assert trial_health(log, 0.04, 30.0)[0]["lost"] is False
    log.actual[:, 1] = 2e-3
    assert trial_health(log, 0.04, 30.0)[0]["lost"] is False
    log.actual[:, 1] = 0.0
    log.actual[75:, :] = np.nan
    assert trial_health(log, 0.04, 30.0)[0]["lost"] is True


def test_holding_still_the_loss_distance_is_its_floor() -> None:
    """A reference that stays put has no extent: the loss distance is lost_floor (2 mm)."""
    log = _log()
    log.desired[:] = log.desired[0]
    log.actual[:] = log.desired[0]
    log.actual[:50, 0] += 2.5e-3
    figures, _ = trial_health(log, 0.04, 30.0)
    assert figures["lost"] is True
    assert trial_health(log, 0.04, 30.0, limits=HealthLimits(lost_floor=3e-3))[0]["lost"] is False


def test_ticks_whose_compute_overran_the_period_are_flagged() -> None:
    """1 overrunning tick in 100 is within the 1 % limit; 2 are flagged, with the longest."""
    log = _log()
    log.compute_time[5] = 0.05
    assert trial_health(log, 0.04, 30.0)[1] == []
    log.compute_time[7] = 0.061
    _, warnings = trial_health(log, 0.04, 30.0)
    assert warnings == [
        "2 of 100 ticks' compute exceeded the 40.0 ms control period (longest 61.0 ms):"
        " too slow for the rig at this rate"
    ]


def test_contact_with_the_critical_boundary_is_timed() -> None:
    """Three ticks with the capsule's side against the anterior arc: 0.12 s of contact."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    robot = load_robots()["drug_delivery"]
    fs = FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)
    log = _log(20)
    angle = math.radians(-30.0)
    radius = np.full(20, 13.4e-3)
    radius[5:8] = 10.5e-3 + robot.diameter / 2  # touching, tangent to the arc
    log.actual[:] = np.column_stack(
        [-6e-3 + radius * math.cos(angle), radius * math.sin(angle), np.full(20, angle + 1.5708)]
    )
    figures, warnings = trial_health(log, 0.04, 30.0, fs)
    assert figures["critical_contact_s"] == pytest.approx(0.12)
    assert any("anterior" in w for w in warnings)


def test_longest_run() -> None:
    assert longest_run(np.array([0, 1, 1, 0, 1, 1, 1, 0], dtype=bool)) == 3
    assert longest_run(np.zeros(4, dtype=bool)) == 0


def test_prediction_error_of_exact_and_biased_models() -> None:
    """A model that predicts the next actual pose exactly has no error; one that is off by
    0.1 mm in x and 1° every tick has, over one tick, 0.1/√2 mm per axis and 1°, and over 4
    ticks (a bias adds up: 0.4 mm, 4°) √4 times that per tick."""
    log = _log(50)
    step = log.actual[1] - log.actual[0]  # the log moves uniformly along x

    def exact(state: np.ndarray, currents: np.ndarray) -> np.ndarray:
        return np.concatenate([state[:3] + step, np.zeros(3)])

    def biased(state: np.ndarray, currents: np.ndarray) -> np.ndarray:
        return exact(state, currents) + np.array([1e-4, 0, math.radians(1.0), 0, 0, 0])

    assert prediction_error(log, 0.04, exact) == pytest.approx((0.0, 0.0), abs=1e-12)
    pos, ang = prediction_error(log, 0.04, biased)
    assert pos == pytest.approx(1e-4 / math.sqrt(2))
    assert ang == pytest.approx(math.radians(1.0))
    pos, ang = prediction_error(log, 0.04, biased, steps=4)
    assert pos == pytest.approx(2 * 1e-4 / math.sqrt(2))
    assert ang == pytest.approx(2 * math.radians(1.0))


def test_quick_spine_runs_the_whole_delivery() -> None:
    """spine.yaml --quick: out, station-keeping, flip and back (the trajectory's full length)."""
    protocol = load_protocol(PROTOCOLS / "spine.yaml")
    assert protocol.trial_duration(quick=True) is None  # the trajectory plus 1 s of hold
    reference = build_scene(protocol).reference
    poses = reference.poses
    assert abs(poses[-1, 2] - poses[0, 2]) == pytest.approx(math.pi, abs=1e-9)  # flipped
    assert np.hypot(*(poses[-1, :2] - poses[0, :2])) < 1e-9  # back at the start


def test_second_phantom_is_a_valid_outline_with_a_path_inside() -> None:
    protocol = load_protocol(PROTOCOLS / "channel.yaml")
    scene = build_scene(protocol)
    phantom = load_phantom(PROTOCOLS / "phantoms" / "channel_bends.yaml")
    robot = load_robots()["drug_delivery"]
    fs = FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)
    assert phantom.path is not None
    assert all(fs.contains(p) for p in phantom.path[1:-1])
    assert scene.critical == "medial"


def test_phantom_walls_have_no_zero_length_segments() -> None:
    """Boundaries of several pieces share their joints; a repeated point would make a
    zero-length wall, whose NaN distances hid every wall from the plant's contact test."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "channel_bends.yaml")
    seg = phantom.walls().segments
    assert np.all(np.hypot(*(seg[:, 1] - seg[:, 0]).T) > 1e-9)


def test_tracking_lost_counts_only_the_frames_taken() -> None:
    """Ticks without a frame have no tracked pose either; only frames taken and not found
    count as lost."""
    log = _log(10)
    log.tracked[:, :] = np.nan
    log.tracked[::3] = 0.0  # frames at ticks 0, 3, 6, 9 ...
    log.framed = np.zeros(10, dtype=bool)
    log.framed[::3] = True
    log.framed[4] = True  # ... and one at tick 4 in which the robot was not found
    assert log.tracking_lost == 1
    log.framed = None  # no schedule recorded: every tick took a frame
    assert log.tracking_lost == 6


def test_second_phantoms_turn_keeps_the_body_off_the_critical_wall() -> None:
    """The capsule turns at the path's last point: at every heading its body (axis of length
    L − D, radius D/2) clears the medial wall by 1.3 mm (5.0 − 2.3 − 1.4: the wall's end at
    the chamber's mouth is 5.0 mm away), against 0.8 mm at the chamber's centre. Computed on
    the axis and the wall sampled densely."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "channel_bends.yaml")
    robot = load_robots()["drug_delivery"]
    wall = phantom.boundaries["medial"]
    t = np.linspace(0.0, 1.0, 50)[:, None]
    wall_points = np.concatenate([a + t * (b - a) for a, b in itertools.pairwise(wall)])

    def least_clearance(centre: np.ndarray) -> float:
        half = (robot.length - robot.diameter) / 2
        clear = np.inf
        for heading in np.linspace(0.0, math.pi, 181):  # the axis at θ and θ + π is one
            axis = centre + np.linspace(-half, half, 41)[:, None] * [
                math.cos(heading),
                math.sin(heading),
            ]
            d = np.hypot(*(axis[:, None, :] - wall_points[None]).transpose(2, 0, 1))
            clear = min(clear, float(d.min()) - robot.diameter / 2)
        return clear

    assert phantom.path is not None
    turn = phantom.path[-1]
    centre = np.array([23.0e-3, 15.0e-3])  # the chamber's centre (the file's chamber arc)
    assert least_clearance(turn) == pytest.approx(1.3e-3, abs=0.05e-3)
    assert least_clearance(centre) == pytest.approx(0.8e-3, abs=0.05e-3)


def test_second_phantoms_path_keeps_the_body_off_the_critical_wall() -> None:
    """The delivery plan: the capsule (axis L − D, radius D/2) on the path, heading along it,
    clears the medial (critical) wall by at least 1.35 mm at every point (the file: 1.4 mm
    wherever the channel allows; 1.5 mm in the second bend, where the body's ends swing out
    towards the critical outer wall) and fits the channel (0.4 mm from the lateral wall).
    Computed on the axis and the walls sampled densely, independently of the analysis
    package's clearance."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "channel_bends.yaml")
    robot = load_robots()["drug_delivery"]
    assert phantom.path is not None
    t = np.linspace(0.0, 1.0, 30)[:, None]

    def dense(points: np.ndarray) -> np.ndarray:
        return np.concatenate([a + t * (b - a) for a, b in itertools.pairwise(points)])

    walls = {name: dense(phantom.boundaries[name]) for name in ("medial", "lateral")}
    half, radius = (robot.length - robot.diameter) / 2, robot.diameter / 2
    least = {"medial": np.inf, "lateral": np.inf}
    second_bend = np.inf
    for a, b in itertools.pairwise(phantom.path):
        heading = math.atan2(b[1] - a[1], b[0] - a[0])
        centre = (a + b) / 2
        axis = centre + np.linspace(-half, half, 21)[:, None] * [
            math.cos(heading),
            math.sin(heading),
        ]
        for name, w in walls.items():
            clear = float(np.hypot(*(axis[:, None, :] - w[None]).transpose(2, 0, 1)).min()) - radius
            least[name] = min(least[name], clear)
            in_second_bend = centre[0] > 1.0e-3 and centre[1] > 1.5e-3 and centre[0] < 13.9e-3
            if name == "medial" and in_second_bend:
                second_bend = min(second_bend, clear)
    assert least["medial"] >= 1.35e-3
    assert second_bend >= 1.45e-3
    assert least["lateral"] >= 0.4e-3
