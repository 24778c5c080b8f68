"""The six controllers: one interface, limits on every tick, fallbacks, closed-loop sanity."""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun.control import METHODS
from magrun.control.allocation import AllocationConfig, allocate, wrench_matrix
from magrun.control.base import Controller, ControlOutput, Plan, Planner
from magrun.control.estimation import MeasurementOrPrediction
from magrun.control.methods import ControlConfig, make_controller
from magrun.control.nmpc import NMPCConfig
from magrun.control.two_layer import linear_model
from magrun.loop import run_trial
from magrun.records import ControllerStatus
from magrun.rigs.sim import SimRig
from magrun.scene import Trajectory, s_trajectory

MAX_CHANGE = 300.0 * 0.04  # A per tick: the shipped slew limit over one control period


@pytest.fixture(scope="module")
def controllers(zernike_model, lut_model) -> dict[str, Controller]:
    return {m: make_controller(m, "magnet", zernike=zernike_model, lut=lut_model) for m in METHODS}


@pytest.fixture
def rig(coils, channel_grid, magnet_robot) -> SimRig:
    return SimRig(coils, channel_grid, magnet_robot, seed=11)


def assert_within_limits(currents: np.ndarray) -> None:
    assert np.all(np.isfinite(currents))
    assert np.all(np.abs(currents) <= 30.0 + 1e-9)
    steps = np.diff(np.vstack([np.zeros(currents.shape[1]), currents]), axis=0)
    assert np.all(np.abs(steps) <= MAX_CHANGE + 1e-9)


def point_target(start: tuple[float, float, float], goal: tuple[float, float, float]) -> Trajectory:
    """Start pose at t = 0, then the goal pose held: a step reference."""
    return Trajectory(np.array([0.0, 1e-3, 10.0]), np.array([start, goal, goal]))


@pytest.mark.parametrize("method", METHODS)
def test_every_method_shares_the_interface(controllers, method: str) -> None:
    c = controllers[method]
    assert isinstance(c, Controller)
    assert c.name == method
    c.reset([0.0, 0.0, 0.0])
    ref = np.zeros((21, 3))
    ref[:, 0] = np.linspace(0, 2e-3, 21)
    out = c.step(np.zeros(3), ref)
    assert isinstance(out, ControlOutput)
    assert out.currents.shape == (8,)
    assert out.estimate.shape == (3,)
    assert out.predicted.shape == (3,)
    assert isinstance(out.status, ControllerStatus)
    assert out.status.solve_time >= 0


@pytest.mark.parametrize("method", METHODS)
def test_step_reference_converges_within_limits(controllers, rig: SimRig, method: str) -> None:
    """A 5 mm / 30° step, perfect feedback: within 0.1 mm and 1° after 3 s, limits every tick."""
    ref = point_target((0.0, 0.0, 0.0), (0.005, 0.003, math.radians(30)))
    log = run_trial(controllers[method], rig, ref, duration=3.0)
    assert_within_limits(log.currents)
    assert log.position_error[-1] < 0.1e-3
    assert log.orientation_error[-1] < math.radians(1.0)


@pytest.mark.parametrize("method", ["proposed", "baseline2", "baseline3"])
def test_limits_hold_under_noisy_feedback(controllers, rig: SimRig, method: str) -> None:
    """3 mm measurement noise on the S-trajectory start: limits still hold every tick."""
    noise = np.random.default_rng(5)

    def noisy(t: float, pose: np.ndarray) -> np.ndarray:
        return pose + noise.normal(0, [3e-3, 3e-3, 0.2])

    log = run_trial(controllers[method], rig, s_trajectory(), feedback=noisy, duration=2.0)
    assert_within_limits(log.currents)


def test_solver_failure_falls_back_and_never_breaks_limits(
    zernike_model, lut_model, rig: SimRig
) -> None:
    """IPOPT capped at 1 iteration fails every tick: zero currents first, then the shifted plan."""
    cfg = ControlConfig(nmpc=replace(NMPCConfig(), solver="ipopt", compile=False, max_iter=1))
    c = make_controller("proposed", "magnet", cfg, zernike_model, lut_model)
    log = run_trial(c, rig, s_trajectory(), duration=1.0)
    assert_within_limits(log.currents)
    assert all(not s.success for s in log.status)
    assert log.status[0].fallback == "zero"
    assert_allclose(log.currents[0], 0.0)
    assert np.all(np.isfinite(log.predicted[1:]))


class _BrokenPlanner(Planner):
    """Returns NaN (twice), then absurd currents, like a solver gone wrong."""

    def __init__(self) -> None:
        self.k = 0

    def reset(self) -> None:
        self.k = 0

    def plan(self, state, reference, previous) -> Plan:
        self.k += 1
        bad = np.full(8, np.nan) if self.k <= 2 else np.full(8, 1e6)
        return Plan(bad, np.full(6, np.nan), ControllerStatus(0.0, 0, False, "", "broken"))

    def predict(self, state, currents) -> np.ndarray:
        return state.copy()


def test_safety_clamp_catches_any_planner_output() -> None:
    c = Controller("broken", MeasurementOrPrediction(), _BrokenPlanner(), 0.04, 30.0, 300.0, 8)
    c.reset(np.zeros(3))
    out = np.array([c.step(np.zeros(3), np.zeros((21, 3))).currents for _ in range(10)])
    assert_within_limits(out)
    # NaN becomes 0 A; the absurd request then ramps at the slew limit and saturates
    assert_allclose(out[:, 0], [0, 0, 12, 24, 30, 30, 30, 30, 30, 30])


def test_allocation_reaches_a_feasible_wrench(lut_model, magnet_robot) -> None:
    p, theta = np.array([0.01, -0.005]), 0.4
    wrench = np.array([1e-4, -5e-5, 1e-6])
    cfg = AllocationConfig(align_weight=0.0, regularisation=1e-8)
    I, achieved = allocate(
        lut_model, p, theta, magnet_robot.moment, wrench, -30 * np.ones(8), 30 * np.ones(8), cfg, 30
    )
    assert_allclose(achieved, wrench, rtol=1e-4)
    A, _ = wrench_matrix(lut_model, p, theta, magnet_robot.moment)
    assert_allclose(A @ I, achieved)


def test_allocation_respects_bounds(lut_model, magnet_robot) -> None:
    lo, hi = -2 * np.ones(8), np.linspace(-1, 3, 8)
    I, _ = allocate(
        lut_model,
        np.zeros(2),
        0.0,
        magnet_robot.moment,
        np.array([1e-2, 0, 0]),
        lo,
        hi,
        AllocationConfig(),
        30.0,
    )
    assert np.all(lo - 1e-12 <= I)
    assert np.all(hi + 1e-12 >= I)


def test_linear_model_matches_the_exponential_integrator(magnet_robot) -> None:
    """At a fixed heading with a held wrench the ZOH model is exact; so is robot.discrete_step."""
    from magrun.robot import NUMPY_OPS, _substep_with_wrench

    theta = 0.3
    x0 = np.array([0.001, 0.002, theta, 0.003, -0.001, 0.0])
    w = np.array([2e-4, -1e-4, 0.0])
    Ad, Bd = linear_model(magnet_robot, theta, 0.04)
    ours = _substep_with_wrench(tuple(x0), ((w[0], w[1]), w[2]), magnet_robot, 0.04, NUMPY_OPS)
    assert_allclose(Ad @ x0 + Bd @ w, ours, rtol=1e-9, atol=1e-15)


class _DriftPlanner(Planner):
    """A planner whose model moves the pose by the currents (a fixed, nonlinear map): enough
    for the estimation tests, which replace planning by given currents."""

    def reset(self) -> None:
        pass

    def plan(self, state, reference, previous) -> Plan:
        raise NotImplementedError("the tests replay currents")

    def predict(self, state, currents) -> np.ndarray:
        s = np.asarray(state, dtype=np.float64)
        v = np.array([currents[0], currents[1], currents[2]]) * 1e-4
        v[0] += 1e-4 * np.sin(20.0 * s[1])  # the step depends on where it starts
        return np.concatenate([s[:3] + v * 0.04, v])


def _estimator(kind: str):
    from magrun.control.estimation import KalmanConfig, KalmanPoseFilter, MeasurementOrPrediction

    if kind == "measurement":
        return MeasurementOrPrediction()
    return KalmanPoseFilter(KalmanConfig(linearised=kind == "linearised"))


@pytest.mark.parametrize("kind", ["kalman", "linearised", "measurement"])
def test_a_late_measurement_gives_the_estimate_of_one_fused_in_time(kind: str) -> None:
    """Measurements taken every 3rd tick and delivered 2 ticks (2.3 periods) late: where the
    late controller has received what the in-time one had, their estimates agree (1e-12)."""
    dt = 0.04
    rng = np.random.default_rng(4)
    currents = rng.normal(0.0, 3.0, (60, 3))
    truth = np.cumsum(currents * 4e-6, axis=0)
    measured = truth + rng.normal(0.0, 5e-4, truth.shape)

    def controller() -> Controller:
        velocity = "difference" if kind == "measurement" else "model"
        c = Controller("t", _estimator(kind), _DriftPlanner(), dt, 30.0, 1e4, 3, velocity=velocity)
        c.reset(np.zeros(3))
        return c

    on_time, late = controller(), controller()
    compared = 0
    for k in range(60):
        z_now = measured[k] if k % 3 == 0 else None
        a, _ = on_time.replay_step(z_now, currents[k])
        z_late = measured[k - 2] if k >= 2 and (k - 2) % 3 == 0 else None
        b, _ = late.replay_step(z_late, currents[k], age=2.3 * dt if z_late is not None else 0.0)
        if z_late is not None:
            assert_allclose(b, a, rtol=0, atol=1e-12)
            compared += 1
    assert compared == 20
    assert late.late_fused == 20


def test_a_measurement_older_than_the_memory_is_dropped() -> None:
    from magrun.control.base import MEMORY

    c = Controller("t", _estimator("kalman"), _DriftPlanner(), 0.04, 30.0, 1e4, 3, velocity="model")
    c.reset(np.zeros(3))
    for _ in range(5):
        c.replay_step(None, np.ones(3))
    before, _ = c.replay_step(None, np.ones(3))
    after, _ = c.replay_step(np.full(3, 0.01), np.ones(3), age=0.04 * (MEMORY + 5))
    assert c.late_dropped == 1
    assert c.late_fused == 0
    assert np.linalg.norm(after - before) < 1e-4  # the 10 mm measurement was not fused


class _LinearPlanner(_DriftPlanner):
    """An exact model of a plant whose pose moves at a velocity proportional to the currents
    (an instant drag response): one period of ``currents`` moves it by k I Δt."""

    def predict(self, state, currents) -> np.ndarray:
        v = np.asarray(currents[:3], dtype=np.float64) * 1e-3
        return np.concatenate([np.asarray(state[:3]) + v * 0.04, v])


def test_planning_across_the_latency_predicts_the_delayed_plant_exactly() -> None:
    """Currents that apply L = 15 ms after each observation, the previous ones acting until
    then: for the linear plant, x' = x + k (I_prev L + I (Δt − L)); the controller's
    prediction (through the interpolation of its module doc) is exact there (1e-15 m)."""
    dt, lat = 0.04, 0.015
    c = Controller("t", _estimator("measurement"), _LinearPlanner(), dt, 30.0, 1e4, 3,
                   latency=lat)  # fmt: skip
    c.reset(np.zeros(3))
    rng = np.random.default_rng(1)
    pose, previous = np.zeros(3), np.zeros(3)
    for _ in range(10):
        currents = rng.normal(0.0, 5.0, 3)
        _, predicted = c.replay_step(pose, currents)
        truth = pose + 1e-3 * (previous * lat + currents * (dt - lat))
        assert_allclose(predicted, truth, rtol=0, atol=1e-15)
        pose, previous = truth, currents


class _ProportionalPlanner(_LinearPlanner):
    """The reference's velocity plus a proportional correction, v = (r₁ − r₀)/Δt + k (r₀ − x),
    as currents of _LinearPlanner's model (v = 1e-3 I): a planner that trusts its model."""

    GAIN = 5.0  # 1/s

    def plan(self, state, reference, previous) -> Plan:
        ref = np.asarray(reference)
        v = (ref[1] - ref[0]) / 0.04 + self.GAIN * (ref[0] - np.asarray(state[:3]))
        currents = v / 1e-3
        return Plan(currents, self.predict(state, currents), ControllerStatus(0.0, 0, True, ""))


def _ramp(k: int, speed: float = 1e-3) -> np.ndarray:
    """The reference window at tick k: x moving at ``speed`` (m/s), 21 poses."""
    t = (k + np.arange(21)) * 0.04
    return np.column_stack([speed * t, np.zeros(21), np.zeros(21)])


@pytest.mark.parametrize("integral_time", [0.0, 0.5])
def test_integral_action_removes_the_lag_a_model_error_leaves(integral_time: float) -> None:
    """The plant moves 0.8 of the model's step (its mobility). Following a ramp at v, the
    proportional planner then lags by the error e with e' = e (1 − m k Δt) + (1 − m) v Δt,
    e_ss = (1 − m) v / (m k) = 50 µm (theory, within 1 %); with the integral action the lag
    goes to zero (below 0.1 % of that after 30 s)."""
    dt, mobility, v = 0.04, 0.8, 1e-3
    c = Controller("t", _estimator("measurement"), _ProportionalPlanner(), dt, 30.0, 1e4, 3,
                   integral_time=integral_time)  # fmt: skip
    c.reset(np.zeros(3))
    x = np.zeros(3)
    for k in range(750):
        out = c.step(x, _ramp(k))
        x = x + mobility * 1e-3 * out.currents * dt
    lag = v * 750 * dt - x[0]
    theory = (1 - mobility) * v / (mobility * _ProportionalPlanner.GAIN)
    if integral_time == 0:
        assert lag == pytest.approx(theory, rel=1e-2)
    else:
        assert abs(lag) < 1e-3 * theory
        assert c.reference_offset[0] == pytest.approx(theory, rel=1e-2)  # what it made up


class _Uncertain(MeasurementOrPrediction):
    """The measurement as the estimate, with a given position σ per axis as its covariance."""

    def __init__(self, sigma: float) -> None:
        super().__init__()
        self.sigma = sigma

    @property
    def covariance(self) -> np.ndarray:
        return np.diag([self.sigma**2, self.sigma**2, 1e-4])


@pytest.mark.parametrize("sigma_over_sigma0", [0.0, 1.0, 3.0])
def test_the_integral_action_slows_down_with_the_estimates_uncertainty(
    sigma_over_sigma0: float,
) -> None:
    """One tick with a 1 mm error at the plan's start: the offset grows by
    Δt/T · σ₀²/(σ₀² + σ²) of it (the module doc's gain), exactly."""
    from magrun.control.base import INTEGRAL_SIGMA

    sigma = sigma_over_sigma0 * INTEGRAL_SIGMA
    c = Controller("t", _Uncertain(sigma), _ProportionalPlanner(), 0.04, 30.0, 1e4, 3,
                   integral_time=0.5)  # fmt: skip
    c.reset(np.zeros(3))
    reference = np.zeros((21, 3))
    reference[:, 0] = 1e-5  # small enough to stay clear of the current limit
    c.step(np.zeros(3), reference)
    gain = 0.04 / 0.5 / (1 + sigma_over_sigma0**2)
    assert_allclose(c.reference_offset, [1e-5 * gain, 0.0], rtol=1e-12, atol=0)


def test_the_integral_action_holds_at_its_limit_and_while_a_coil_is_saturated() -> None:
    """A 10 mm error that the currents cannot close: the offset stops at INTEGRAL_LIMIT where
    the currents are free, and does not grow at all while they sit at the 30 A limit."""
    from magrun.control.base import INTEGRAL_LIMIT

    reference = np.zeros((21, 3))
    reference[:, 1] = 10e-3
    free = Controller("t", _estimator("measurement"), _ProportionalPlanner(), 0.04, 1e6, 1e9, 3,
                      integral_time=0.5)  # fmt: skip
    saturated = Controller("t", _estimator("measurement"), _ProportionalPlanner(), 0.04, 30.0,
                           1e9, 3, integral_time=0.5)  # fmt: skip
    for c in (free, saturated):
        c.reset(np.zeros(3))
        for _ in range(200):
            c.step(np.zeros(3), reference)  # the robot held where it is
    assert_allclose(free.reference_offset, [0.0, INTEGRAL_LIMIT], rtol=1e-12, atol=1e-18)
    assert_allclose(saturated.reference_offset, [0.0, 0.0], rtol=0, atol=0)


def test_a_latency_aware_loop_records_the_reference_of_the_observation_time(
    coils, channel_grid, magnet_robot
) -> None:
    """With the controller planning across 15 ms of latency the loop hands it a window that
    starts 15 ms later, but records (and scores) the desired pose of each observation's own
    time; without latency the window starts at the observation."""
    reference = s_trajectory()
    for lead in (0.0, 0.015):
        config = ControlConfig(dt=1 / 25.5, latency=lead)
        c = make_controller("baseline3", magnet_robot, config)
        rig = SimRig(coils, channel_grid, magnet_robot, seed=2)
        log = run_trial(c, rig, reference, duration=1.0, latency=0.015)
        assert_allclose(log.desired, reference.pose(log.t), rtol=0, atol=1e-15)
        assert c.latency == lead


def _burn(seconds: float) -> None:
    """Spend ``seconds`` of this thread's CPU time (however loaded the machine)."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass


def test_the_loop_charges_each_stage_its_own_cpu_time(coils, channel_grid, magnet_robot) -> None:
    """A feedback function and a recorder hook that each spend a known CPU time per tick:
    the control stage holds at least the feedback's, the record stage the hook's and little
    more, and no other stage either of them (CPU time of the loop's thread: a loaded machine
    stretches the wall time, not these)."""
    from magrun.loop import STAGES

    feed, record = 0.004, 0.006  # s of CPU per tick

    def slow_feedback(t: float, pose: np.ndarray | None) -> np.ndarray | None:
        _burn(feed)
        return pose

    c = make_controller("baseline3", magnet_robot, ControlConfig(dt=1 / 25.5))
    rig = SimRig(coils, channel_grid, magnet_robot, seed=2)
    log = run_trial(
        c, rig, s_trajectory(), feedback=slow_feedback, duration=1.0,
        on_tick=lambda tick: _burn(record),
    )  # fmt: skip
    spent, n = log.stage_cpu_s, len(log.t)
    assert spent is not None
    assert set(spent) == set(STAGES)
    assert spent["control"] >= n * feed
    assert n * record <= spent["record"] < n * (record + 0.001)
    for stage in ("observe", "track", "plant", "prepare", "loop"):
        assert 0 <= spent[stage] < n * feed, (stage, spent)


class _AffinePlanner(_DriftPlanner):
    """A model whose next pose is affine in the pose, p⁺ = A p + c(I): its Jacobian is A."""

    A = np.array([[1.1, 0.05, 2e-3], [-0.02, 0.9, -1e-3], [3.0, -2.0, 0.8]])

    def predict(self, state, currents) -> np.ndarray:
        s = np.asarray(state, dtype=np.float64)
        p = self.A @ s[:3] + 1e-4 * np.asarray(currents[:3], dtype=np.float64)
        return np.concatenate([p, np.zeros(3)])


@pytest.mark.parametrize("latency", [0.0, 0.015])
def test_a_linearised_filter_gets_the_prediction_jacobian_across_the_latency(
    latency: float,
) -> None:
    """The controller hands a linearised filter ∂(next pose)/∂(pose) of its prediction, by
    central differences: for an affine model p⁺ = A p + c, and latency L (f = L/Δt), the
    prediction goes ahead by f of a step and back by 1 − f (module doc), so the Jacobian is
    (f I + (1 − f) A)((1 − f) I + f A), and A without latency (1e-9); a filter that does
    not use it (the paper's) gets none. The next tick's filter gets it as its F."""
    from magrun.control.estimation import KalmanConfig, KalmanPoseFilter

    dt = 0.04
    f = latency / dt
    I3, A = np.eye(3), _AffinePlanner.A
    expected = (f * I3 + (1 - f) * A) @ ((1 - f) * I3 + f * A)
    for linearised in (True, False):
        kf = KalmanPoseFilter(KalmanConfig(linearised=linearised))
        c = Controller("t", kf, _AffinePlanner(), dt, 30.0, 1e4, 3, latency=latency,
                       velocity="model")  # fmt: skip
        c.reset(np.array([1e-3, -1e-3, 0.2]))
        c.replay_step(None, np.array([1.0, -2.0, 0.5]))
        c.prepare(np.zeros((21, 3)))  # computed there, off the feedback path
        if linearised:
            assert_allclose(c._jacobian, expected, rtol=0, atol=1e-9)
        else:
            assert c._jacobian is None
        P = kf.covariance
        c.replay_step(None, np.zeros(3))
        F = expected if linearised else I3
        assert_allclose(kf.covariance, F @ P @ F.T + kf.Q, rtol=1e-7)


def test_the_linear_mpcs_limits_bound_the_wrench_without_changing_its_cost(
    lut_model, magnet_robot
) -> None:
    """The wrench weights are per the paper rig's limits (``force_unit``, ``torque_unit``),
    whatever a system's limits are: near the reference, where the wrench is within the
    paper rig's box, ten times wider limits give the same wrench (to rounding); 20 mm off,
    the paper rig's box clips the force to 0.4 mN and the wider one lets it grow past that,
    within its own limit."""
    from magrun.control.two_layer import LinearMPCConfig, LinearMPCPlanner

    paper = LinearMPCConfig()
    wide = replace(paper, max_force=10 * paper.max_force, max_torque=10 * paper.max_torque)
    reference = s_trajectory()
    window = reference.pose(np.arange(21) / 25.5)  # (N + 1, 3): the reference ahead
    near = np.concatenate([window[0] + [0.05e-3, -0.03e-3, 0.01], np.zeros(3)])
    far = np.concatenate([window[0] + [20e-3, 0.0, 0.0], np.zeros(3)])
    wrenches = {}
    for name, config in (("paper", paper), ("wide", wide)):
        planner = LinearMPCPlanner(lut_model, magnet_robot, 1 / 25.5, config)
        wrenches[name, "near"] = planner.desired_wrench(near, window)
        planner.reset()
        wrenches[name, "far"] = planner.desired_wrench(far, window)
    assert np.all(np.abs(wrenches["paper", "near"][:2]) < 0.9 * paper.max_force)
    assert_allclose(wrenches["wide", "near"], wrenches["paper", "near"], rtol=1e-6, atol=1e-12)
    assert abs(wrenches["paper", "far"][0]) == pytest.approx(paper.max_force, rel=1e-6)
    assert paper.max_force * 1.5 < abs(wrenches["wide", "far"][0]) <= wide.max_force * (1 + 1e-9)


class _Watching(_ProportionalPlanner):
    """A linear planner that keeps the covariances it is shown and expects."""

    uses_uncertainty = True

    def __init__(self) -> None:
        self.observed: list[np.ndarray | None] = []
        self.expected: list[np.ndarray | None] = []

    def observe_uncertainty(self, covariance) -> None:
        self.observed.append(None if covariance is None else np.array(covariance))

    def expect_uncertainty(self, covariance) -> None:
        self.expected.append(None if covariance is None else np.array(covariance))


@pytest.mark.parametrize("kind", ["kalman", "linearised"])
def test_the_planner_sees_the_covariance_before_the_ticks_frame_known_a_tick_ahead(
    kind: str,
) -> None:
    """The corridor's margins come from the estimate's covariance before the tick's frame:
    the filter's prediction, which a tick without a frame ends with and which a frame's
    tick shrinks. So the covariance the planner is told to expect at the preparation is
    the one the next tick shows it, bit for bit, frame or not; and it is the filter's
    covariance after an update without a measurement."""
    planner = _Watching()
    c = Controller("t", _estimator(kind), planner, 0.04, 30.0, 1e4, 3, velocity="model")
    c.reset(np.zeros(3))
    rng = np.random.default_rng(5)
    ref = np.zeros((3, 3))
    frames = 0
    for k in range(24):
        z = rng.normal(0.0, 5e-4, 3) if k % 4 == 1 else None
        frames += z is not None
        before = c.estimator.snapshot()
        prior = None if k == 0 else c.estimator.predicted_covariance(c._prediction, c._jacobian)
        c.estimator.restore(before)
        c.step(z, ref)
        if k == 0:  # no prediction yet: the estimator's own
            np.testing.assert_array_equal(planner.observed[0], c.estimator.covariance)
        else:
            np.testing.assert_array_equal(planner.observed[-1], prior)
            np.testing.assert_array_equal(planner.observed[-1], planner.expected[-1])
            if z is not None:  # the frame shrank the filter's own, not what the planner saw
                assert np.trace(c.estimator.covariance[:2, :2]) < np.trace(prior[:2, :2])
        c.prepare(ref)
    assert frames == 6
    assert len(planner.expected) == 24
