"""The safety layer between every controller and the coils: limits, safe stop, stop reasons."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from magrun.control.base import Controller, Plan, Planner
from magrun.control.estimation import MeasurementOrPrediction
from magrun.loop import run_trial
from magrun.records import ControllerStatus
from magrun.rigs.sim import SimRig
from magrun.safety import SafetyConfig, SafetyLayer
from magrun.scene import s_trajectory

I_MAX, SLEW, DT, N = 30.0, 300.0, 0.04, 8
STEP = SLEW * DT  # 12 A per tick

currents = st.floats(allow_nan=True, allow_infinity=True, width=64)
requests = st.lists(st.lists(currents, min_size=N, max_size=N), min_size=1, max_size=40)


@settings(max_examples=300, deadline=None)
@given(requests=requests, faults=st.lists(st.booleans(), min_size=40, max_size=40))
def test_invariants_hold_for_any_controller_output(requests, faults) -> None:
    """|I| ≤ I_max, |ΔI| ≤ slew·Δt, always finite; the first non-finite request or fault
    trips a safe stop, after which every current falls monotonically to 0 A and stays."""
    layer = SafetyLayer(N, I_MAX, SLEW, DT)
    previous = np.zeros(N)
    tripped_at = None
    for k, req in enumerate(requests):
        fault = "planner fault" if faults[k] and k % 7 == 3 else ""
        out = layer.limit(req, fault)
        assert np.all(np.isfinite(out))
        assert np.all(np.abs(out) <= I_MAX)
        assert np.all(np.abs(out - previous) <= STEP + 1e-9)
        bad = fault or not np.all(np.isfinite(req))
        if bad and tripped_at is None:
            tripped_at = k
            assert layer.tripped
        if tripped_at is not None:
            assert np.all(np.abs(out) <= np.abs(previous) + 1e-12)  # toward zero only
            if k - tripped_at >= math.ceil(I_MAX / STEP):
                assert not np.any(out)
        else:
            assert not layer.tripped
        previous = out
    assert layer.tripped == (tripped_at is not None)


def test_the_first_reason_is_kept_with_its_time() -> None:
    layer = SafetyLayer(N, I_MAX, SLEW, DT)
    layer.limit(np.full(N, 20.0))
    assert_allclose(layer.limit(np.full(N, 20.0)), 20.0)  # 12 A a tick: 12, then 20
    assert_allclose(layer.limit(np.r_[np.nan, np.ones(N - 1)], t=1.5), 8.0)  # ramping down
    layer.trip("interrupted", 2.0)
    assert layer.reason.startswith("non-finite currents from the controller (nan")
    assert layer.tripped_at == 1.5
    assert layer.ticks_to_rest() == 1
    assert not layer.at_rest
    assert_allclose(layer.limit(np.full(N, 20.0)), 0.0)  # requests no longer matter
    assert layer.at_rest


def test_wrong_number_of_currents_trips() -> None:
    layer = SafetyLayer(N, I_MAX, SLEW, DT)
    assert not np.any(layer.limit(np.ones(3)))
    assert "(3,) currents for 8" in layer.reason


def test_tracking_lost_longer_than_the_timeout_trips() -> None:
    """Lost frames accumulate time; a found robot resets it; ticks without a frame neither."""
    layer = SafetyLayer(N, I_MAX, SLEW, DT, SafetyConfig(lost_timeout_s=0.5))
    pose = np.zeros(3)
    layer.check(0.0, pose, False)
    layer.check(0.4, pose, None)
    layer.check(0.45, pose, True)  # found again: the clock restarts
    layer.check(0.5, pose, False)
    layer.check(1.0, pose, False)
    assert not layer.tripped  # lost for exactly 0.5 s
    layer.check(1.04, pose, None)
    layer.check(1.08, pose, False)
    assert layer.reason == "tracking lost for 0.58 s (limit 0.5 s)"
    assert layer.tripped_at == 1.08


@pytest.mark.parametrize(
    ("pose", "trips"), [([0.034, 0.0, 0.0], False), ([0.0, -0.0351, 1.0], True)]
)
def test_leaving_the_workspace_trips(pose, trips: bool) -> None:
    cfg = SafetyConfig(workspace_margin_m=0.005)
    layer = SafetyLayer(N, I_MAX, SLEW, DT, cfg, workspace_half_width=0.03)
    layer.check(2.0, pose)
    assert layer.tripped == trips
    if trips:
        assert layer.reason == (
            "the robot left the workspace at (0.0, -35.1) mm (allowed: |x|, |y| ≤ 35.0 mm)"
        )


class _NaNAfter(Planner):
    """A constant 25 A request, NaN from the given tick on."""

    def __init__(self, k_nan: int) -> None:
        self.k_nan, self.k = k_nan, 0

    def reset(self) -> None:
        self.k = 0

    def plan(self, state, reference, previous) -> Plan:
        self.k += 1
        value = np.nan if self.k > self.k_nan else 25.0
        return Plan(np.full(N, value), state.copy(), ControllerStatus(0.0))

    def predict(self, state, currents) -> np.ndarray:
        return state.copy()


def test_a_nan_ends_the_trial_with_a_recorded_ramp_to_zero() -> None:
    """Closed loop on the simulated rig: tick 6 plans NaN; the ramp 25 → 13 → 1 → 0 A is
    recorded, then the trial ends with the reason, long before the trajectory does."""
    controller = Controller("nan", MeasurementOrPrediction(), _NaNAfter(5), DT, I_MAX, SLEW, N)
    log = run_trial(controller, SimRig.default(), s_trajectory())
    first = log.currents[:, 0]
    assert_allclose(first, [12, 24, 25, 25, 25, 13, 1, 0])
    assert log.stop_reason == "the nan planner returned non-finite currents"
    assert not log.interrupted
    assert_allclose(log.t[-1], 7 * DT)
