"""Simulated rig: field tables, limits, walls, parameter draws."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from magrun.field.grid import ChannelGrid
from magrun.field.lut import LookupTableFieldModel
from magrun.rigs.sim import Perturbation, SimRig
from magrun.robot import load_robot
from magrun.safety import clamp_currents
from magrun.scene import Walls, s_trajectory

currents = st.lists(
    st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=8, max_size=8
)
prev_currents = st.lists(st.floats(-30, 30), min_size=8, max_size=8)


@settings(max_examples=200, deadline=None)
@given(currents, prev_currents)
def test_clamp_currents_always_within_limits(req: list[float], prev: list[float]) -> None:
    out = clamp_currents(req, prev, 30.0, 12.0)
    assert np.all(np.isfinite(out))
    assert np.all(np.abs(out) <= 30.0)
    assert np.all(np.abs(out - np.array(prev)) <= 12.0 + 1e-12)
    # a request inside the limits passes unchanged
    assert_allclose(clamp_currents(out, prev, 30.0, 12.0), out, rtol=0, atol=0)


def test_channel_grid_equals_the_lookup_table_model(
    channel_grid: ChannelGrid, lut_model: LookupTableFieldModel, rng
) -> None:
    pts = rng.uniform(-0.05, 0.05, (50, 2))
    B, G = lut_model.unit_field_and_gradient(pts)
    for p, b, g in zip(pts, B, G, strict=True):
        u = channel_grid.unit(*p)
        assert_allclose(u[:, :2], b, rtol=1e-9, atol=1e-15)
        assert_allclose(u[:, 2:].reshape(8, 2, 2), g, rtol=1e-9, atol=1e-13)


def test_cell_reads_equal_the_grid_times_the_currents(channel_grid: ChannelGrid, rng) -> None:
    """Per-cell corner tables, read for any currents or held ones, equal the blend of every
    channel times the currents (rounding: 1e-12 of the largest value), inside the grid, on
    revisited cells and beyond its border (linear extrapolation)."""
    from magrun.field.grid import GridCells

    cells = GridCells(channel_grid)
    currents = rng.uniform(-30, 30, 8)
    held = cells.held(currents)
    inside = rng.uniform(-0.05, 0.05, (300, 2))
    revisit = inside[:50] + rng.normal(0, 1e-5, (50, 2))
    beyond = rng.uniform(-0.09, 0.09, (50, 2))
    for x, y in np.vstack([inside, revisit, beyond]):
        v = currents @ channel_grid.unit(x, y)
        tol = 1e-12 * np.abs(v).max()
        for B, (gx, gy) in (held(x, y), cells.read(currents, x, y)):
            assert_allclose(np.concatenate([B, gx, gy]), v, rtol=0, atol=tol)


def _reference_advance(rig: SimRig, duration: float) -> None:
    """The plant's step as first written: clamp the ramp and read the grid every sub-step."""
    from functools import partial

    from magrun.robot import MATH_OPS, discrete_step
    from magrun.safety import clamp_currents

    def field(I: np.ndarray, x: float, y: float) -> tuple[list[float], tuple]:
        v = (I @ rig.grid.unit(x, y)).tolist()
        return v[:2], (v[2:4], v[4:6])

    n = max(1, round(duration / rig.fine_step))
    h = duration / n
    state = tuple(rig.state)
    for _ in range(n):
        nxt = clamp_currents(rig.target, rig.driven, rig.max_current, rig.max_slew_rate * h)
        drive = 0.5 * (rig.driven + nxt) * rig.coil_gains
        rig.driven = nxt
        state = discrete_step(state, partial(field, drive), rig.robot, h, 1, MATH_OPS)
    rig.state = np.array(state)
    rig.t += duration


def test_plant_moves_as_with_a_clamped_ramp_and_a_grid_read_per_substep(
    coils, channel_grid, magnet_robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    """2 s of currents that jump (ramps of several sub-steps, then holds), in uneven advance
    calls as when compute time is charged: the same motion to rounding as the reference."""

    def run() -> tuple[np.ndarray, np.ndarray]:
        rig = SimRig(coils, channel_grid, magnet_robot, seed=1)
        rig.reset([0.01, -0.01, 0.5])
        for k in range(50):
            rig.apply(np.roll(np.array([12.0, -6, 9, 0, -12, 6, 0, 3]), k // 10) * (k % 3))
            rig.advance(0.013)
            rig.advance(0.027)
        return rig.state.copy(), rig.driven.copy()

    fast, driven = run()
    monkeypatch.setattr(SimRig, "advance", _reference_advance)
    reference, reference_driven = run()
    assert np.linalg.norm(fast[:2] - [0.01, -0.01]) > 1e-3  # it moved
    assert_allclose(fast, reference, rtol=1e-9, atol=1e-12)
    assert_allclose(driven, reference_driven, rtol=0, atol=1e-12)


@pytest.mark.parametrize("setting", ["open", "box", "spine"])
def test_compiled_plant_follows_the_python_reference(
    coils, channel_grid, magnet_robot, setting: str
) -> None:
    """The Numba kernel (magrun.rigs.kernel) against the Python plant it replaces, with
    currents that jump every tick (ramps, then holds) in uneven advance calls: in open space,
    turning in a box barely longer than the body, and along the spine phantom's channel
    (hundreds of segments).
    Only the order of floating-point sums differs, so 2 s of motion agree to 1e-12 m / rad
    and every contact is reported on the same tick. (A body longer than its box, jammed and
    squeezed out of it, would be chaotic: rounding grows there, so no such case here.)"""
    from pathlib import Path

    from magrun.phantom import load_phantom

    robot, walls, start = magnet_robot, None, (0.001, -0.002)
    if setting == "box":  # 18 mm across for the 16 mm magnet: it turns against the walls
        walls, start = Walls.box(0.009), (0.0, 0.0)
    elif setting == "spine":
        phantom = load_phantom(Path(__file__).parents[1] / "protocols/phantoms/spine_l3l4.yaml")
        walls = phantom.walls() + Walls.box(coils.workspace_half_width)
        assert phantom.path is not None
        start, robot = tuple(phantom.path[0]), load_robot("drug_delivery")

    def run(compiled: bool) -> tuple[np.ndarray, list[bool]]:
        rig = SimRig(coils, channel_grid, robot, walls=walls, seed=4, compiled=compiled)
        rig.reset([start[0], start[1], 0.4])
        draw = np.random.default_rng(5)
        states, contacts = [], []
        pull = np.array([20.0, -10, 15, 0, -20, 10, 0, 5])
        for k in range(50):  # strong pulls that turn every 10 ticks, and jitter every tick
            rig.apply(np.roll(pull, k // 10) + draw.normal(0.0, 3.0, coils.n_channels))
            rig.advance(0.009)
            rig.advance(0.031)
            states.append(rig.state.copy())
            contacts.append(rig.observe(frame=False).in_contact)
        return np.array(states), contacts

    fast, fast_contacts = run(True)
    reference, reference_contacts = run(False)
    assert np.ptp(reference[:, :3], axis=0).max() > 1e-3  # it moved (m) or turned (rad)
    assert_allclose(fast[:, :3], reference[:, :3], rtol=0, atol=1e-12)
    assert_allclose(fast[:, 3:], reference[:, 3:], rtol=1e-9, atol=1e-12)
    assert fast_contacts == reference_contacts
    if setting != "open":
        assert sum(reference_contacts) >= 5  # the walls were touched


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-0.006, 0.006),
    y=st.floats(-0.006, 0.006),
    th=st.floats(-4.0, 4.0),
    v=st.tuples(*[st.floats(-0.05, 0.05)] * 3),
    mu=st.sampled_from([(0.0, 0.0), (0.05, 0.1), (0.5, 0.5)]),
)
def test_compiled_capsule_contact_equals_the_reference(
    x: float, y: float, th: float, v: tuple[float, float, float], mu: tuple[float, float]
) -> None:
    """kernel.resolve_capsule against Walls.resolve_capsule (NumPy), a 3 mm body in a 8 mm
    box with a wall across it, frictionless and with wall friction: the same push and turn
    to 1e-12."""
    from magrun.rigs.kernel import resolve_capsule
    from magrun.scene import capsule_disks

    walls = Walls.box(0.004) + Walls(np.array([[[-0.004, 0.001], [0.002, -0.003]]]))
    half_axis, radius, ct, cr = 1.2e-3, 0.3e-3, 2e-3, 3e-9
    state = (x, y, th, *v)
    friction = (*mu, 1e-3)
    expected, touched = walls.resolve_capsule(
        state, half_axis, radius, ct, cr, wall_friction=friction
    )
    out = np.array(state)
    disks = capsule_disks(half_axis, radius)
    got = resolve_capsule(out, walls.segments, disks, radius, ct, cr, 16, *friction)
    assert got == touched
    assert_allclose(out, expected, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    ("along", "mu_k", "mu_s", "speed"),
    [
        (0.3, 0.0, 0.0, 0.3),  # frictionless: F_t / c_t
        (0.3, 0.1, 0.2, 0.2),  # sliding: (F_t - μ_k F_n) / c_t
        (0.15, 0.1, 0.2, 0.0),  # F_t ≤ μ_s F_n: it sticks
        (0.25, 0.1, 0.2, 0.15),  # above the static threshold it slides at the kinetic rate
    ],
)
def test_wall_friction_is_coulombs(along: float, mu_k: float, mu_s: float, speed: float) -> None:
    """A capsule lying on a straight wall, pressed into it by F_n and pushed along it by F_t
    (a drag-dominated body: its velocity is F / c_t each 1 ms step), for 2 s: it slides at
    (F_t − μ_k F_n) / c_t, or stays put while F_t ≤ μ_s F_n (Coulomb's law), to 1e-6 of
    F_n / c_t, and stays on the wall without turning (forces as multiples of F_n, so the
    expected speeds are multiples of F_n / c_t = 1 mm/s)."""
    wall = Walls(np.array([[[-1.0, 0.0], [1.0, 0.0]]]))
    half_axis, radius, ct, cr = 1.5e-3, 0.5e-3, 3e-2, 4e-7
    press = 1e-3  # F_n / c_t, m/s
    h, steps = 1e-3, 2000
    state: tuple[float, ...] = (0.0, radius, 0.0, 0.0, 0.0, 0.0)
    for _ in range(steps):
        vx, vy = along * press, -press
        x, y, th = state[0] + vx * h, state[1] + vy * h, state[2]
        state, touched = wall.resolve_capsule(
            (x, y, th, vx, vy, 0.0), half_axis, radius, ct, cr, wall_friction=(mu_k, mu_s, h)
        )
        assert touched
    assert state[0] / (steps * h) == pytest.approx(speed * press, abs=1e-6 * press)
    assert state[1] == pytest.approx(radius, abs=1e-12)
    assert state[2] == pytest.approx(0.0, abs=1e-12)


@pytest.fixture
def rig(coils, channel_grid, magnet_robot) -> SimRig:
    return SimRig(coils, channel_grid, magnet_robot, perturbation=Perturbation(), seed=0)


def test_zero_currents_keep_the_robot_still(rig: SimRig) -> None:
    rig.reset([0.01, 0.02, 0.3])
    for _ in range(25):
        rig.apply(np.zeros(8))
        rig.advance(0.04)
    obs = rig.observe()
    assert obs.t == pytest.approx(1.0)
    assert_allclose(obs.pose, [0.01, 0.02, 0.3], rtol=0, atol=0)


def test_apply_clamps_and_amplifiers_ramp_at_the_slew_limit(rig: SimRig) -> None:
    rig.reset([0.0, 0.0, 0.0])
    applied = rig.apply([100, -100, np.nan, 5, 0, 0, 0, 0])
    assert_allclose(applied, [30, -30, 0, 5, 0, 0, 0, 0])
    rig.advance(0.04)  # 300 A/s x 40 ms = 12 A
    assert_allclose(rig.driven, [12, -12, 0, 5, 0, 0, 0, 0], atol=1e-9)


def test_walls_stop_the_robot(rig: SimRig) -> None:
    """Full current pulling toward the east wall: the robot's disk stops at the wall."""
    rig.reset([0.03, 0.0, 0.0])
    I = np.zeros(8)
    I[rig.channel_names.index("large_E")] = -30.0  # attracts the moment toward the east coil
    I[rig.channel_names.index("small_E")] = -30.0
    touched = False
    for _ in range(100):
        rig.apply(I)
        rig.advance(0.04)
        obs = rig.observe()
        touched |= obs.in_contact
        assert obs.pose[0] <= 0.05 - rig.robot.diameter / 2 + 1e-12
    assert touched


def test_walls_resolve_projects_out_and_removes_inward_velocity() -> None:
    walls = Walls.box(0.05)
    p, v, hit = walls.resolve(np.array([0.0495, 0.0]), np.array([0.01, 0.002]), 0.0014)
    assert hit
    assert p[0] == pytest.approx(0.05 - 0.0014)
    assert_allclose(v, [0.0, 0.002])


def test_perturbation_draws_are_seeded(coils, channel_grid, magnet_robot) -> None:
    a = SimRig(
        coils, channel_grid, magnet_robot, perturbation=Perturbation(0.1, 0.1, 0.1, 0.1), seed=3
    )
    b = SimRig(
        coils, channel_grid, magnet_robot, perturbation=Perturbation(0.1, 0.1, 0.1, 0.1), seed=3
    )
    c = SimRig(
        coils, channel_grid, magnet_robot, perturbation=Perturbation(0.1, 0.1, 0.1, 0.1), seed=4
    )
    assert a.robot == b.robot
    assert_allclose(a.coil_gains, b.coil_gains)
    assert a.robot != c.robot
    nominal = SimRig(coils, channel_grid, magnet_robot, perturbation=Perturbation(), seed=3)
    assert nominal.robot == magnet_robot
    assert_allclose(nominal.coil_gains, 1.0)


def test_s_trajectory_geometry() -> None:
    ref = s_trajectory(size=0.043, speed=0.003)
    xy = ref.poses[:, :2]
    assert_allclose(xy.min(axis=0), [-0.0215, -0.0215], atol=1e-6)
    assert_allclose(xy.max(axis=0), [0.0215, 0.0215], atol=1e-6)
    length = 0.043 * 2 + math.pi * 0.043 / 2  # three legs (2 x 43 mm in all) + two half circles
    assert ref.duration == pytest.approx(length / 0.003, rel=1e-3)
    # heading along the path: θ is the direction of motion
    d = np.diff(xy, axis=0)
    moving = np.hypot(*d.T) > 0
    heading = np.arctan2(d[moving, 1], d[moving, 0])
    err = (heading - ref.poses[:-1][moving, 2] + math.pi) % (2 * math.pi) - math.pi
    assert np.max(np.abs(err)) < 0.02
    assert_allclose(ref.pose(ref.duration + 5.0), ref.poses[-1])


def _disk_clearance(walls: Walls, state: tuple[float, ...], half_axis: float) -> float:
    """Smallest distance from the capsule's axis (sampled finely) to any wall."""
    x, y, th = state[:3]
    s = np.linspace(-half_axis, half_axis, 201)
    pts = np.column_stack([x + s * np.cos(th), y + s * np.sin(th)])
    return min(float(walls.distances(p).min()) for p in pts)


def test_capsule_contact_pushes_and_turns_the_body_out_of_a_channel() -> None:
    # a 7.4 x 2.8 mm capsule turned 40 deg in a straight 5 mm channel overlaps both walls;
    # it can only fit turned by at most asin((2.5 - 1.4) / 2.3) = 28.6 deg
    walls = Walls(
        np.array([[[-0.05, -0.0025], [0.05, -0.0025]], [[-0.05, 0.0025], [0.05, 0.0025]]])
    )
    half, r = 2.3e-3, 1.4e-3
    state = (0.0, 0.0, np.radians(40.0), 0.0, 0.0, 5.0)  # turning further into the walls
    assert _disk_clearance(walls, state, half) < r
    out, touched = walls.resolve_capsule(state, half, r, 2.53e-2, 3.4e-7)
    assert touched
    assert _disk_clearance(walls, out, half) >= r - 2e-6  # 16 passes resolve to within 2 µm
    assert abs(out[2]) <= np.arcsin((2.5 - 1.4) / 2.3) + 1e-3
    assert abs(out[5]) < 5.0  # the turn into the walls was slowed by the contact


def test_capsule_clear_of_walls_is_untouched() -> None:
    walls = Walls.box(0.05)
    state = (0.01, -0.02, 0.3, 0.001, 0.002, 0.5)
    assert walls.resolve_capsule(state, 6.6e-3, 1.4e-3, 3.5e-2, 2e-6) == (state, False)


def test_capsule_contact_removes_only_the_velocity_into_the_wall() -> None:
    walls = Walls.box(0.05)
    # the capsule's centre disk touches the right wall, moving into it and along it
    state = (0.05 - 1.3e-3, 0.0, np.pi / 2, 0.004, 0.003, 0.0)
    out, touched = walls.resolve_capsule(state, 2.3e-3, 1.4e-3, 2.5e-2, 3.4e-7)
    assert touched
    assert out[0] == pytest.approx(0.05 - 1.4e-3, abs=1e-12)
    assert out[3] == pytest.approx(0.0, abs=1e-12)  # into the wall: gone
    assert out[4] == pytest.approx(0.003)  # along the wall: kept
    assert out[2] == pytest.approx(np.pi / 2)  # pushed at its centre: no turn


def test_broad_phase_gives_the_same_motion_as_testing_every_wall(
    coils, channel_grid, monkeypatch: pytest.MonkeyPatch
) -> None:
    """In the spine phantom's channel (hundreds of wall segments, in contact most of the time)
    the candidate walls give exactly the motion of the exact test against all of them."""
    from pathlib import Path

    from magrun.phantom import load_phantom
    from magrun.robot import load_robot

    phantom = load_phantom(Path(__file__).parents[1] / "protocols/phantoms/spine_l3l4.yaml")
    walls = phantom.walls() + Walls.box(coils.workspace_half_width)
    assert phantom.path is not None
    start = phantom.path[0]
    robot = load_robot("drug_delivery")

    def run() -> tuple[np.ndarray, int]:
        rig = SimRig(coils, channel_grid, robot, walls=walls, seed=3)
        rig.reset([start[0], start[1], 0.3])
        currents = np.array([20.0, -10, 15, 0, -20, 10, 0, 5])
        contacts = 0
        for k in range(50):  # 2 s of strong, changing pulls into the walls
            rig.apply(np.roll(currents, k // 10))
            rig.advance(0.04)
            contacts += rig.observe().in_contact
        return rig.state.copy(), contacts

    fast, fast_contacts = run()
    monkeypatch.setattr(SimRig, "_walls_in_reach", lambda self, x, y: self.walls)
    exact, exact_contacts = run()
    assert fast_contacts == exact_contacts > 10
    assert_allclose(fast, exact, rtol=0, atol=1e-15)
