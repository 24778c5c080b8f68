"""The free space the controllers are given: projection of estimates, the corridor's
half-planes, the NMPC's corridor constraint, and a spine trial that stays off the critical
wall."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magrun.control.base import Controller, Plan, Planner
from magrun.control.estimation import KalmanConfig, KalmanPoseFilter
from magrun.control.methods import make_controller
from magrun.control.nmpc import NMPC, STATE_SCALE, NMPCConfig
from magrun.freespace import FreeSpace
from magrun.loop import run_trial
from magrun.phantom import load_phantom
from magrun.protocol import load_protocol
from magrun.records import ControllerStatus
from magrun.rigs.sim import SimRig
from magrun.robot import load_robots
from magrun.trial import build_scene, free_space_of

PROTOCOLS = Path(__file__).parents[1] / "protocols"


@pytest.fixture(scope="module")
def spine() -> FreeSpace:
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    robot = load_robots()["drug_delivery"]
    return FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)


coordinate = st.floats(-0.06, 0.06, allow_nan=False)
angle = st.floats(-10.0, 10.0, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(x=coordinate, y=coordinate, theta=angle)
def test_projection_puts_the_body_in_the_channel(spine: FreeSpace, x, y, theta) -> None:
    """Any pose, however far outside: the projected centre is inside the outline and the
    body clear of every boundary (to 1 µm)."""
    p = spine.project(np.array([x, y, theta]))
    assert spine.contains(p[:2])
    assert spine.clearance(p) >= -1e-6


def test_projection_keeps_a_pose_that_fits(spine: FreeSpace) -> None:
    """A pose on the delivery path, body along it, comes back unchanged."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    assert phantom.path is not None
    a, b = phantom.path[40], phantom.path[41]
    pose = np.array([*a, math.atan2(*(b - a)[::-1])])
    assert spine.clearance(pose) > 0
    np.testing.assert_array_equal(spine.project(pose), pose)


def _star(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0, 2 * math.pi, n))
    radii = rng.uniform(0.004, 0.03, n)
    points = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
    return np.vstack([points, points[:1]])


@pytest.mark.parametrize("where", ["spine", "square", "star"])
def test_the_fallback_grid_holds_every_pose_that_fits_and_no_other(spine, where) -> None:
    """The grid of poses that fit (the projection's last resort; the docstring's pitch, 16
    headings over π), checked pose by pose with :meth:`FreeSpace.clearances`, which measures
    the body against the walls in its own way (and agrees with :meth:`FreeSpace.clearance`
    to 1e-12 m, tested above): a candidate is in the grid exactly where the body clears
    every wall by a thousandth of its radius (poses within 1 nm of that are not judged)."""
    robot = load_robots()["drug_delivery"]
    fs = {
        "spine": spine,
        "square": FreeSpace.square(0.006, robot.length, robot.diameter),
        "star": FreeSpace({"a": _star(40, 5)}, None, robot.length, robot.diameter),
    }[where]
    outline = fs.walls().segments[:, 0]
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    pitch = max(0.5e-3, float(np.max(hi - lo)) / 60)
    xs, ys = np.arange(lo[0], hi[0] + pitch, pitch), np.arange(lo[1], hi[1] + pitch, pitch)
    centres = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    centres = centres[fs.inside(centres)]
    grid = {(round(x / pitch), round(y / pitch), round(t * 16 / math.pi)) for x, y, t in
            fs._fitting}  # fmt: skip
    fitting = np.asarray(fs._fitting)[::3]  # every third, and every third centre below
    kept = fs.clearances(fitting) - 0.001 * fs.radius
    assert np.all(kept > -1e-9), fitting[np.argmin(kept)]
    at = np.repeat(centres[::3], 16, axis=0)  # each centre at the 16 headings
    headings = np.tile(np.arange(16), len(centres[::3]))
    poses = np.column_stack([at, headings * math.pi / 16])
    margin = fs.clearances(poses) - 0.001 * fs.radius
    judged = np.abs(margin) >= 1e-9
    in_grid = np.array(
        [(round(x / pitch), round(y / pitch), int(j)) in grid
         for (x, y), j in zip(at, headings, strict=True)]
    )  # fmt: skip
    wrong = judged & (in_grid != (margin > 0))
    assert not np.any(wrong), poses[wrong][:5]
    inside = int(np.sum(judged & (margin > 0)))
    assert 0 < inside < int(np.sum(judged))  # poses that fit and poses that do not were judged


@pytest.mark.parametrize(
    ("outline", "robot"),
    [("square", "magnet"), ("square", "drug_delivery"), ("spine_l3l4", "micro_magnet"),
     ("channel_bends", "micro_magnet"), ("spine_l3l4", "drug_delivery")],
)  # fmt: skip
def test_a_centre_in_a_sure_cell_fits_at_every_heading(outline: str, robot: str) -> None:
    """The shortcut of the projection's fit test: every pose whose centre lies in a sure cell
    passes the measured test, at any heading (1,000 random poses in those cells, and the
    corners of the cells at the region's edge at 8 headings). The 40 mm square's cells are
    mostly sure, so the shortcut fires on most ticks of an open workspace; in the phantoms'
    channels only a small robot has a few, and the drug-delivery capsule (longer than the
    spine's channel is wide) has at most one: its poses are measured as before."""
    body = load_robots()[robot]
    if outline == "square":
        fs = FreeSpace.square(0.02, body.length, body.diameter)
    else:
        phantom = load_phantom(PROTOCOLS / "phantoms" / f"{outline}.yaml")
        fs = FreeSpace(phantom.boundaries, phantom.critical, body.length, body.diameter)
    assert fs._sure is not None
    x0, y0, pitch, sure = fs._sure
    cells = np.argwhere(sure)
    if outline == "square":
        assert len(cells) > 0.2 * sure.size
    elif robot == "micro_magnet":
        assert 0 < len(cells) < 0.1 * sure.size
    else:
        assert len(cells) <= 1
    if not len(cells):
        return
    rng = np.random.default_rng(5)
    picked = cells[rng.integers(len(cells), size=1000)]
    xy = np.array([x0, y0]) + (picked + rng.uniform(0, 1, picked.shape)) * pitch
    poses = np.column_stack([xy, rng.uniform(-math.pi, math.pi, len(xy))])
    assert all(fs._in_sure_cell(p) for p in poses)
    # the cells at the sure region's edge (a neighbour not sure), where a wall is nearest
    padded = np.pad(sure, 1)
    inner = padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:]
    edge = cells[~inner[cells[:, 0], cells[:, 1]]]
    corners = np.array([x0, y0]) + (edge[:, None] + [[0, 0], [1, 0], [0, 1], [1, 1]]) * pitch
    corners = np.unique(corners.reshape(-1, 2), axis=0)
    turns = np.repeat(np.arange(8) * math.pi / 8, len(corners))
    poses = np.concatenate([poses, np.column_stack([np.tile(corners, (8, 1)), turns])])
    for pose in poses:
        assert fs._fits_measured(pose), pose


def test_nearest_for_one_point_is_the_nearest_for_many_to_the_last_bit(spine: FreeSpace) -> None:
    """The one-point path (the NMPC's start, every tick) gives the vectorised one's nearest
    point and normal bit for bit: inside and outside the outline, on a vertex's normal, and
    on the boundary itself (the normal then the segment's)."""
    rng = np.random.default_rng(5)
    points = rng.uniform(-0.02, 0.02, (400, 2))
    boundary = spine.boundaries["anterior"]
    points = np.vstack([points, boundary[::7], boundary[1::7] + 1e-3 * rng.normal(size=(1, 2))])
    for names in (["anterior"], ["posterior", "chamber", "entry"], list(spine.boundaries)):
        q, n = spine.nearest(points, names)
        for i, point in enumerate(points):
            q1, n1 = spine.nearest(point[None], names)
            np.testing.assert_array_equal(q1[0], q[i])
            np.testing.assert_array_equal(n1[0], n[i])


def test_clearances_of_many_poses_are_each_poses_clearance(spine: FreeSpace) -> None:
    """The vectorised clearances (a path's check before a run) against :meth:`clearance`, one
    pose at a time (which looks only at the walls within the body's reach): inside the
    channel, across its walls (negative) and far outside, to 1e-12 m; in blocks of one pose
    and of seven (the last one shorter) alike; a body that is a point too."""
    rng = np.random.default_rng(8)
    poses = np.column_stack([rng.uniform(-0.025, 0.025, (300, 2)), rng.uniform(-4, 4, 300)])
    robot = load_robots()["drug_delivery"]
    dot = FreeSpace(spine.boundaries, spine.critical, robot.diameter, robot.diameter)
    for fs in (spine, dot):
        for names in (["anterior"], None):
            want = np.array([fs.clearance(p, names) for p in poses])
            assert np.any(want < 0)  # overlapping
            assert np.any(want > 1e-3)  # and clear
            np.testing.assert_allclose(fs.clearances(poses, names), want, rtol=0, atol=1e-12)
    want = np.array([spine.clearance(p, ["anterior"]) for p in poses])
    for pairs in (1, 7 * 148):  # one pose a block; 7 (the anterior wall's 148 segments each)
        got = spine.clearances(poses, ["anterior"], pairs=pairs)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_corridor_for_one_point_is_the_vectorised_corridor_to_the_last_bit(
    spine: FreeSpace,
) -> None:
    """The one-point corridor (the NMPC's start, every tick) gives the half-plane the
    vectorised path gives that point bit for bit: with and without a covariance (one with
    a correlation, whose variance along the normal depends on the order of summation), with
    the margin capped by the channel's width or not, inside and outside the outline. (The
    vectorised path's einsum may sum many rows in another order than one: each point is
    compared with the vectorised path given that point alone, what the NMPC's start got
    from it.)"""
    rng = np.random.default_rng(7)
    points = np.vstack([
        rng.uniform(-0.02, 0.02, (300, 2)),
        spine.boundaries["anterior"][::9] + 1e-3 * rng.normal(size=(1, 2)),
    ])  # fmt: skip
    correlated = np.array([[2.0e-6, 0.7e-6], [0.7e-6, 1.1e-6]])
    for covariance in (None, np.diag([1e-6, 4e-6]), correlated):
        for sigmas, share in ((1.0, 1.0), (2.0, 0.3)):
            for point in points:
                alone = spine._corridor_many(
                    point[None], np.empty((1, 3)), covariance, 0.5e-3, sigmas, share
                )
                one = spine.corridor(point[None], covariance, 0.5e-3, sigmas, share)
                np.testing.assert_array_equal(one, alone)


def test_corridor_faces_into_the_channel(spine: FreeSpace) -> None:
    """At points of the path, the corridor's normal points from the anterior wall into the
    channel and c puts the body's edge D/2 (+ margin) from the wall: the path's points
    satisfy it with the clearance the geometry gives (radius 13.4 vs 10.5 mm); the nearest
    posterior point's normal faces the other way, 2.1 mm off; the free width is 5 mm."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    assert phantom.path is not None
    pts = phantom.path[10:150:20]
    planes = spine.corridor(pts, None, margin=0.0, sigmas=1.0, share=1.0)
    gap = np.sum(planes[:, :2] * pts, axis=1) - planes[:, 2]
    # the centre is 13.4 − 10.5 = 2.9 mm from the anterior arc; the plane asks for D/2
    np.testing.assert_allclose(gap, 2.9e-3 - spine.radius, atol=2e-5)
    q, n = spine.nearest(pts, ["posterior"])
    np.testing.assert_allclose(np.sum(n * planes[:, :2], axis=1), -1.0, atol=1e-3)
    np.testing.assert_allclose(np.sum(n * (pts - q), axis=1), 2.1e-3, atol=2e-5)
    np.testing.assert_allclose(spine.free_width(pts), 5e-3, atol=2e-5)


class _Still(Planner):
    """A planner that asks for nothing and predicts the pose it is given."""

    def reset(self) -> None:
        pass

    def plan(self, state, reference, previous) -> Plan:  # type: ignore[no-untyped-def]
        return Plan(np.zeros(8), np.asarray(state, dtype=np.float64), ControllerStatus(0.0))

    def predict(self, state, currents):  # type: ignore[no-untyped-def]
        return np.asarray(state, dtype=np.float64)


measurements = st.lists(
    st.one_of(st.none(), st.tuples(coordinate, coordinate, angle)), min_size=1, max_size=30
)


@settings(max_examples=60, deadline=None)
@given(zs=measurements, heading_bias=st.sampled_from([0.0, math.radians(0.5)]))
def test_estimate_never_leaves_the_free_space(spine: FreeSpace, zs, heading_bias) -> None:
    """The Kalman filter (with and without its heading-bias state) fed adversarial
    measurements (anywhere in ±60 mm, any heading, or none): every estimate the controller
    hands its planner is inside the channel."""
    kf = KalmanPoseFilter(KalmanConfig(heading_bias=heading_bias))
    c = Controller("proposed", kf, _Still(), 0.04, 30.0, 1e4, 8, spine)
    c.reset(np.array([-6e-3, -13.4e-3, 0.0]))
    ref = np.zeros((21, 3))
    for z in zs:
        out = c.step(None if z is None else np.array(z), ref)
        assert spine.contains(out.estimate[:2])
        assert spine.clearance(out.estimate) >= -1e-6


def test_model_velocity_does_not_spike_at_frames() -> None:
    """With velocity="model", a measurement that moves the estimate 2 mm does not reach the
    planner as a 50 mm/s velocity (it does with the finite difference)."""
    seen: list[np.ndarray] = []

    class _Record(_Still):
        def plan(self, state, reference, previous):  # type: ignore[no-untyped-def]
            seen.append(np.asarray(state).copy())
            return super().plan(state, reference, previous)

    for velocity in ("model", "difference"):
        seen.clear()
        c = Controller("p", KalmanPoseFilter(), _Record(), 0.04, 30.0, 1e4, 8, velocity=velocity)
        c.reset(np.zeros(3))
        ref = np.zeros((21, 3))
        c.step(None, ref)
        c.step(np.array([2e-3, 0.0, 0.0]), ref)
        speed = float(np.hypot(*seen[-1][3:5]))
        if velocity == "model":
            assert speed == 0.0
        else:
            assert speed > 0.01


def test_corridor_holds_in_the_plan_and_both_solvers_agree(zernike_model) -> None:
    """A reference 1 mm inside the anterior wall (the critical one): both solvers, to
    convergence, plan every state with the body's ends on the free side of the stage's
    critical half-plane, the margin away (to the soft constraint's sag: 0.05 mm at this
    weight), and agree; the real-time iteration with the soft constraints as slacks in its
    QPs as well as with them as penalty residuals."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    robot = load_robots()["drug_delivery"]
    fs = FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)
    centre = np.array([-6e-3, 0.0])
    a0 = math.radians(-40.0)
    start = centre + 13.0e-3 * np.array([math.cos(a0), math.sin(a0)])
    state = np.array([*start, a0 + math.pi / 2, 0.0, 0.0, 0.0])
    angles = a0 + np.linspace(0.0, 0.15, 21)
    ref = np.column_stack(
        [centre[0] + 10.9e-3 * np.cos(angles), centre[1] + 10.9e-3 * np.sin(angles),
         angles + math.pi / 2]
    )  # fmt: skip
    converge = {"iterations": 60, "first_tick_iterations": 60, "step_tolerance": 1e-9}
    plans = {}
    for solver, soft in (("rti", "penalty"), ("rti", "slack"), ("ipopt", "penalty")):
        cfg = NMPCConfig(solver=solver, corridor_weight=1e4, tol=1e-10, soft_constraints=soft,  # type: ignore[arg-type]
                         **converge)  # fmt: skip
        if solver == "ipopt":
            cfg = replace(cfg, compile=False, ipopt={"acceptable_iter": 0})
        nmpc = NMPC(zernike_model, robot, cfg, fs)
        assert nmpc.plan(state, ref, np.zeros(8)).status.success
        X = nmpc.backend.states_plan()
        assert X is not None
        poses = X[:, :3] * STATE_SCALE[:3]
        clear = np.array([fs.clearance(p, [fs.critical]) for p in poses])  # type: ignore[list-item]
        assert clear.min() >= cfg.corridor_margin - 0.05e-3, (solver, clear.min())
        plans[f"{solver}-{soft}"] = nmpc.backend.currents_plan()
    np.testing.assert_allclose(plans["rti-penalty"], plans["ipopt-penalty"], atol=2e-3)
    np.testing.assert_allclose(plans["rti-slack"], plans["ipopt-penalty"], atol=2e-3)


def test_one_real_time_iteration_sees_the_corridor_before_it_is_violated(zernike_model) -> None:
    """A plan converged on a reference 2 mm clear of the corridor, then the reference moved
    1 mm inside the anterior wall and one Gauss-Newton step per tick. With the soft
    constraints as slacks in the QP the first step already plans every state at the
    corridor's margin (0.5 mm, to 0.01 mm). With penalty residuals min(0, g) the step does
    not see the corridor, inactive where it linearised, and plans the body through the wall
    (1 mm past it on this problem); the next step comes back to the margin."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    robot = load_robots()["drug_delivery"]
    fs = FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)
    centre = np.array([-6e-3, 0.0])
    a0 = math.radians(-40.0)
    state = np.array([*(centre + 13.0e-3 * np.array([math.cos(a0), math.sin(a0)])),
                      a0 + math.pi / 2, 0.0, 0.0, 0.0])  # fmt: skip
    angles = a0 + np.linspace(0.0, 0.15, 21)

    def reference(radius: float) -> np.ndarray:
        x, y = centre[0] + radius * np.cos(angles), centre[1] + radius * np.sin(angles)
        return np.column_stack([x, y, angles + math.pi / 2])

    least = {}
    for soft in ("slack", "penalty"):
        cfg = NMPCConfig(soft_constraints=soft, corridor_weight=1e4)  # type: ignore[arg-type]
        nmpc = NMPC(zernike_model, robot, cfg, fs)
        if nmpc.backend.kernel is None:
            pytest.skip("the slacks need the compiled kernel (no C compiler here)")
        assert nmpc.plan(state, reference(13.0e-3), np.zeros(8)).status.success
        previous = nmpc.backend.currents_plan()[0] * nmpc.max_current  # type: ignore[index]
        least[soft] = []
        for _ in range(2):
            assert nmpc.plan(state, reference(10.9e-3), previous).status.success
            X = nmpc.backend.states_plan()
            assert X is not None
            poses = X[:, :3] * STATE_SCALE[:3]
            least[soft].append(min(fs.clearance(p, [fs.critical]) for p in poses))  # type: ignore[arg-type]
    margin = NMPCConfig().corridor_margin
    assert least["slack"] == pytest.approx([margin, margin], abs=0.01e-3)
    assert least["penalty"][0] < -0.5e-3  # through the wall
    assert least["penalty"][1] == pytest.approx(margin, abs=0.01e-3)


def test_short_spine_trial_with_exact_feedback_keeps_off_the_critical_wall() -> None:
    """The proposed controller in the spine phantom, exact feedback every tick, the first 12 s
    (the channel up to the chamber): the body never comes within 0.05 mm of the anterior
    boundary, and the robot follows the path to under 0.5 mm RMS."""
    protocol = load_protocol(PROTOCOLS / "spine.yaml")
    scene = build_scene(protocol)
    robot = load_robots()[protocol.robot]
    fs = free_space_of(scene, robot)
    c = make_controller("proposed", robot, free_space=fs)
    rig = SimRig.default(robot=protocol.robot, walls=scene.walls, seed=1)
    log = run_trial(c, rig, scene.reference, duration=12.0)
    clear = np.array([fs.clearance(p, [fs.critical]) for p in log.actual])
    assert clear.min() > 0.05e-3
    assert log.rms_position_mm < 0.5


def test_play_in_the_square_is_the_distance_to_the_walls() -> None:
    """The open workspace, body at (x0, 0) along x or along y: its play along ±x is the
    distance from its tip (half the length) or its side (the radius) to the walls, to 1e-12 m."""
    h, L, D = 0.05, 0.016, 0.0028
    fs = FreeSpace.square(h, L, D)
    reach = 0.2
    lo, hi = fs.play(np.array([0.01, 0.0, 0.0]), np.array([1.0, 0.0]), reach=reach)
    assert hi == pytest.approx(h - 0.01 - L / 2, abs=1e-12)
    assert lo == pytest.approx(-(h + 0.01 - L / 2), abs=1e-12)
    lo, hi = fs.play(np.array([0.01, 0.0, math.pi / 2]), np.array([1.0, 0.0]), reach=reach)
    assert hi == pytest.approx(h - 0.01 - D / 2, abs=1e-12)
    assert lo == pytest.approx(-(h + 0.01 - D / 2), abs=1e-12)
    assert fs.play(np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0]), reach=0.01) == (-0.01, 0.01)


def _disks_clear(fs: FreeSpace, pose: np.ndarray) -> float:
    """Least distance of the body's disks (as play places them) to any wall, less the radius:
    a brute-force check over every segment."""
    from magrun.phantom import point_to_segments
    from magrun.scene import capsule_disks

    axis = np.array([math.cos(pose[2]), math.sin(pose[2])])
    disks = pose[:2] + capsule_disks(fs.half_axis, fs.radius)[:, None] * axis
    segs = fs.walls().segments
    d = point_to_segments(disks[:, None, :], segs[None, :, 0], segs[None, :, 1])
    return float(d.min() - fs.radius)


def test_segment_distances_are_the_least_over_both_segments_points(rng) -> None:
    """The segment-to-segment distance that every clearance uses, broadcast over many pairs,
    against brute force: 401 points along each segment, whose least distance exceeds the
    true one by at most half of each segment's point spacing. Crossing pairs are at 0, and a
    segment of zero length is a point (its distance to the other segment)."""
    from magrun.phantom import point_to_segments, segment_distances

    p0, p1, a, b = (rng.uniform(-1.0, 1.0, (300, 2)) for _ in range(4))
    p1[:20] = p0[:20]  # points
    d = segment_distances(p0, p1, a, b)
    assert d.shape == (300,)
    s = np.linspace(0.0, 1.0, 401)[:, None]
    for k in range(300):
        one = p0[k] + s * (p1[k] - p0[k])
        other = a[k] + s * (b[k] - a[k])
        brute = np.hypot(*(one[:, None] - other[None]).T).min()
        slack = (np.hypot(*(p1[k] - p0[k])) + np.hypot(*(b[k] - a[k]))) / 800
        assert d[k] <= brute + 1e-12
        assert brute <= d[k] + slack + 1e-12
    np.testing.assert_array_equal(d[:20], point_to_segments(p0[:20], a[:20], b[:20]))
    crossing = segment_distances(np.array([-1.0, 0.0]), np.array([1.0, 0.0]),
                                 np.array([[0.0, -1.0]]), np.array([[0.3, 1.0]]))  # fmt: skip
    assert crossing.tolist() == [0.0]
    # one body against many walls, and many bodies against many walls, at once
    many = segment_distances(p0[:7, None], p1[:7, None], a[None, :5], b[None, :5])
    assert many.shape == (7, 5)
    assert many[3, 2] == segment_distances(p0[3], p1[3], a[2], b[2])


@settings(max_examples=100, deadline=None)
@given(s=st.floats(0.0, 1.0), offset=st.floats(-1.0, 1.0), tilt=st.floats(-0.3, 0.3),
       turn=st.floats(0.0, 2 * math.pi))  # fmt: skip
def test_play_ends_where_the_body_meets_a_wall(spine: FreeSpace, s, offset, tilt, turn) -> None:
    """Poses along the spine's channel (any point of the path, off it by up to 1 mm, tilted up
    to 17°) and any direction: the body moved 1 µm short of either end of its play still
    clears every wall, and 1 µm past an end that is not the reach it meets one (brute force
    over every disk and segment)."""
    phantom = load_phantom(PROTOCOLS / "phantoms" / "spine_l3l4.yaml")
    assert phantom.path is not None
    path = phantom.path
    i = min(int(s * (len(path) - 2)), len(path) - 2)
    a, b = path[i], path[i + 1]
    heading = math.atan2(*(b - a)[::-1])
    normal = np.array([-math.sin(heading), math.cos(heading)])
    pose = np.array([*(a + offset * 1e-3 * normal), heading + tilt])
    if _disks_clear(spine, pose) < 0:
        return  # the body does not fit there: play is (0, 0), tested below
    direction = np.array([math.cos(turn), math.sin(turn)])
    reach = 4e-3
    lo, hi = spine.play(pose, direction, reach=reach)
    assert lo <= 0 <= hi
    for end, sign in ((hi, 1.0), (lo, -1.0)):
        inside = pose.copy()
        inside[:2] += (end - sign * 1e-6) * direction
        assert _disks_clear(spine, inside) >= -1e-9
        if abs(end) < reach:
            past = pose.copy()
            past[:2] += (end + sign * 1e-6) * direction
            assert _disks_clear(spine, past) < 0


def test_truncation_moves_an_estimate_off_the_far_wall(spine: FreeSpace) -> None:
    """At a measurement, a Kalman estimate 0.1 mm from the posterior wall, with 1 mm of
    spread across the channel, moves toward the channel's middle (the walls make the far edge
    unlikely); without a measurement it stays where it is."""
    c = Controller("proposed", KalmanPoseFilter(), _Still(), 0.04, 30.0, 1e4, 8, spine)
    # radius 13.8 mm around the dural sac's centre (-6, 0): the body 0.1 mm off the posterior wall
    pose = np.array([-6e-3 + 13.8e-3, 0.0, math.pi / 2])
    across = spine.across(pose)
    assert across is not None
    hi = across[2]
    assert hi == pytest.approx(0.1e-3, abs=2e-5)
    c.reset(pose)
    c.estimator.kf.P = np.diag([1e-6, 1e-6, 1e-3])
    ref = np.tile(pose, (21, 1))
    held = c.step(None, ref).estimate
    np.testing.assert_allclose(held, pose, rtol=0, atol=1e-12)
    moved = c.step(pose, ref).estimate  # a measurement right at the estimate: no innovation
    assert -1.0e-3 < moved[0] - pose[0] < -0.3e-3  # toward the anterior wall, i.e. inward
    assert spine.clearance(moved) > spine.clearance(pose)


def test_open_workspace_has_no_interval_to_condition_on() -> None:
    """Without a critical boundary (the open workspace) there is nothing across: the
    estimators are left as they are."""
    fs = FreeSpace.square(0.05, 0.016, 0.0028)
    assert fs.across(np.array([0.0, 0.0, 0.3])) is None


def test_a_start_inside_the_corridor_margin_is_led_out_at_the_recovery_speed(
    spine: FreeSpace, zernike_model
) -> None:
    """An estimate whose body is 0.4 mm inside the critical margin (where a noisy frame can put
    it): stage k's half-plane is moved back by what is left of the intrusion after k stages at
    ``corridor_recovery``, so at stage 0 it passes through the body's nearer end and, once
    the intrusion is recovered, it is the plain half-plane again; the normals are unchanged.
    A start outside the margin leaves every half-plane as it was."""
    robot = load_robots()["drug_delivery"]
    centre, a0 = np.array([-6e-3, 0.0]), math.radians(-40.0)
    angles = a0 + np.linspace(0.0, 0.15, 21)
    ref = np.column_stack([centre[0] + 13.4e-3 * np.cos(angles),
                           centre[1] + 13.4e-3 * np.sin(angles), angles + math.pi / 2])  # fmt: skip
    rate = 2e-3  # m/s
    plain = NMPC(zernike_model, robot, NMPCConfig(corridor_recovery=0.0), spine)
    led = NMPC(zernike_model, robot, NMPCConfig(corridor_recovery=rate), spine)
    dt = led.config.dt
    P0 = plain.corridor(ref[0], ref)  # (N+1, 1, 3); c in mm
    n, c = P0[0, 0, :2], P0[0, 0, 2] * 1e-3

    def nearer_end(state: np.ndarray) -> float:
        axis = spine.half_axis * np.array([math.cos(state[2]), math.sin(state[2])])
        return min(n @ (state[:2] + axis), n @ (state[:2] - axis))

    # the reference's pose moved along the normal until its nearer end is 0.4 mm inside
    inside = ref[0].copy()
    inside[:2] += n * (c - 0.4e-3 - nearer_end(ref[0]))
    assert c - nearer_end(inside) == pytest.approx(0.4e-3, abs=1e-12)
    P, L = plain.corridor(inside, ref), led.corridor(inside, ref)
    np.testing.assert_array_equal(L[:, :, :2], P[:, :, :2])
    k = np.arange(len(P))
    moved_back = np.maximum(0.0, 0.4e-3 - k * dt * rate) / 1e-3  # mm
    np.testing.assert_allclose(L[:, 0, 2], P[:, 0, 2] - moved_back, rtol=0, atol=1e-9)
    assert L[0, 0, 2] * 1e-3 == pytest.approx(nearer_end(inside), abs=1e-12)
    assert np.array_equal(L[k * dt * rate >= 0.4e-3 + 1e-12], P[k * dt * rate >= 0.4e-3 + 1e-12])
    # clear of the margin: nothing moves
    outside = ref[0].copy()
    outside[:2] += n * 0.2e-3
    np.testing.assert_array_equal(led.corridor(outside, ref), plain.corridor(outside, ref))


def _warm_in_the_spine(
    model, spine: FreeSpace, radius: float
) -> tuple[NMPC, np.ndarray, np.ndarray, np.ndarray]:
    """An NMPC on the spine, its corridor's margins from a covariance, converged on a
    reference along the channel at ``radius`` around its centre (10.9 mm: 1 mm inside the
    anterior wall, the corridor active), and the next tick's predicted state, reference
    and previous currents. The corridor's weight is the corridor tests' above (1e4), so a
    session compiles one kernel for both (the weight is part of the kernel's code)."""
    robot = load_robots()["drug_delivery"]
    cfg = NMPCConfig(soft_constraints="slack", first_tick_iterations=60, corridor_weight=1e4)
    nmpc = NMPC(model, robot, cfg, spine)
    if nmpc.backend.kernel is None:
        pytest.skip("the split needs the compiled kernel (no C compiler here)")
    centre, a0 = np.array([-6e-3, 0.0]), math.radians(-40.0)
    state = np.array([*(centre + 13.0e-3 * np.array([math.cos(a0), math.sin(a0)])),
                      a0 + math.pi / 2, 0.0, 0.0, 0.0])  # fmt: skip
    angles = a0 + np.linspace(0.0, 0.15, 21)
    ref = np.column_stack([centre[0] + radius * np.cos(angles),
                           centre[1] + radius * np.sin(angles), angles + math.pi / 2])  # fmt: skip
    nmpc.observe_uncertainty(np.diag([0.8e-3, 0.8e-3, 0.05]) ** 2)
    first = nmpc.plan(state, ref, np.zeros(8))
    assert first.status.success
    return nmpc, nmpc.predict(state, first.currents), ref, first.currents


def _unprepared_and_prepared(
    model,
    spine: FreeSpace,
    radius: float,
    expected: np.ndarray,
    shown: np.ndarray,
    move: np.ndarray,
) -> tuple[NMPC, Plan, Plan]:
    """Two NMPCs warmed alike (:func:`_warm_in_the_spine`) and the next tick's plan of each,
    both shown the covariance ``shown``, from the predicted state moved by ``move``: one
    unprepared, one prepared at the predicted state with the covariance ``expected``."""
    plain, x_p, ref, currents = _warm_in_the_spine(model, spine, radius)
    split, _, _, _ = _warm_in_the_spine(model, spine, radius)
    plain.observe_uncertainty(shown)
    a = plain.plan(x_p + move, ref, currents)
    split.expect_uncertainty(expected)
    split.prepare(x_p, ref, currents)
    split.observe_uncertainty(shown)
    return split, a, split.plan(x_p + move, ref, currents)


def test_a_phantom_tick_is_prepared_from_the_covariance_the_filter_will_have(
    zernike_model, spine: FreeSpace
) -> None:
    """The NMPC prepares a phantom's tick with the corridor's margins from the covariance
    it is told to expect (the filter's prediction, which the controller shows it at every
    tick, frame or not). A tick shown that covariance uses the preparation: at the
    predicted state, the unprepared tick's currents to 1e-12 A. A tick shown another (a
    planner driven otherwise) iterates in full, as the unprepared tick does (1e-12 A)."""
    between = np.diag([0.9e-3, 0.9e-3, 0.05]) ** 2  # the filter's prediction
    framed = np.diag([0.7e-3, 0.7e-3, 0.04]) ** 2  # another
    for covariance, embedded in ((between, 1), (framed, 0)):
        split, a, b = _unprepared_and_prepared(
            zernike_model, spine, 10.9e-3, between, covariance, np.zeros(6)
        )
        assert b.status.prepare_time > 0
        assert split.backend.embedded == embedded  # type: ignore[attr-defined]
        np.testing.assert_allclose(b.currents, a.currents, rtol=0, atol=1e-12)


def test_a_prepared_phantom_tick_embeds_the_measured_state_to_first_order(
    zernike_model, spine: FreeSpace
) -> None:
    """Prepared at the predicted state x_p with the covariance the tick then has, the
    feedback at the measured x_p + h d answers the move as the tick linearised at the
    measured state does, to first order (within 3 % of the answer, as on the open S): on
    the channel's path, the body clear of the corridor's margin (a start inside it is led
    out from where it is measured, and such a tick iterates in full)."""
    between = np.diag([0.3e-3, 0.3e-3, 0.05]) ** 2
    d = np.array([0.5e-3, -0.3e-3, 0.03, 1e-3, 0.5e-3, 0.05])  # m, rad, m/s, rad/s
    h = 1e-3
    answers = []
    for move in (0.0, h):
        split, a, b = _unprepared_and_prepared(
            zernike_model, spine, 13.4e-3, between, between, move * d
        )
        assert b.status.success
        assert split.backend.embedded == 1  # type: ignore[attr-defined]
        answers.append((a.currents, b.currents))
    relinearised = answers[1][0] - answers[0][0]
    embedded = answers[1][1] - answers[0][1]
    assert np.max(np.abs(embedded)) > 1e-4  # the move is felt (A)
    assert np.linalg.norm(embedded - relinearised) < 0.03 * np.linalg.norm(relinearised)


def test_the_spine_prepares_every_tick_in_the_loop() -> None:
    """The spine protocol (3 Hz frames, Kalman filter, corridor), its first 4 s: every tick
    after the first is prepared (the corridor's margins come from the covariance before the
    tick's frame, known a tick ahead), and the feedback phase uses the preparation in most
    ticks without a frame (80 of 90 seen). A tick whose start the corridor leads out of its
    margin iterates in full (the lead-out follows the measured start): on the spine, whose
    path runs in the margin, the frames' ticks (13 of 13 seen). The loop tracks as one that
    never prepares (RMS within 5 %)."""
    from magrun.trial import assemble, single_trial

    protocol = load_protocol(PROTOCOLS / "spine.yaml", ("duration_s=4",))
    logs, used = {}, {}
    for prepare in (False, True):
        parts = assemble(single_trial(protocol, "proposed", seed=0))
        backend = parts.controller.planner.backend  # type: ignore[attr-defined]
        if backend.kernel is None:
            pytest.skip("the split needs the compiled kernel (no C compiler here)")
        if not prepare:
            parts.controller.prepare = lambda reference: None  # type: ignore[method-assign]
        ticks: list[int] = []
        solve = backend._solve_kernel

        def counted(*args, solve=solve, ticks=ticks, backend=backend):  # type: ignore[no-untyped-def]
            before = backend.embedded
            result = solve(*args)
            ticks.append(backend.embedded - before)
            return result

        backend._solve_kernel = counted
        logs[prepare] = parts.run()
        used[prepare] = np.array(ticks, dtype=bool)
    prepared = [s.prepare_time > 0 for s in logs[True].status]
    assert all(prepared[1:])
    assert not any(s.prepare_time > 0 for s in logs[False].status)
    assert not used[False].any()
    framed = ~np.isnan(logs[True].measured[:, 0])
    between = used[True][~framed]
    assert between.sum() > 0.8 * len(between), (between.sum(), len(between))
    assert logs[True].rms_position_mm == pytest.approx(logs[False].rms_position_mm, rel=0.05)


def test_a_process_builds_each_free_space_once() -> None:
    """free_space_of keeps what it built: the same phantom and robot give the same FreeSpace
    (a campaign's trials share it), another robot or another geometry another one, equal to
    one built afresh."""
    spine_protocol = load_protocol(PROTOCOLS / "spine.yaml")
    scene = build_scene(spine_protocol)
    robot = spine_protocol.robot_params()
    first = free_space_of(scene, robot)
    assert free_space_of(build_scene(spine_protocol), robot) is first
    other_robot = replace(robot, length=robot.length * 0.9)
    smaller = free_space_of(scene, other_robot)
    assert smaller is not first
    assert smaller.length == other_robot.length
    fresh = FreeSpace(scene.boundaries, scene.critical, other_robot.length, robot.diameter)
    poses = np.array([[0.0, 0.0, 0.0], [0.004, -0.002, 0.5], [0.0074, 0.0, 1.2]])
    for pose in poses:
        assert smaller.clearance(pose) == fresh.clearance(pose)
    assert smaller.inside(poses[:, :2]).tolist() == fresh.inside(poses[:, :2]).tolist()
    moved = replace(scene, boundaries={k: v + 1e-3 for k, v in scene.boundaries.items()})
    assert free_space_of(moved, robot) is not first
    square = build_scene(load_protocol(PROTOCOLS / "rate.yaml"))
    assert free_space_of(square, robot).critical is None
