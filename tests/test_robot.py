"""Robot parameters, magnetic wrench and the discretisation of the dynamics."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp

from magrun.control.symbolic import casadi_step_function
from magrun.field.grid import ChannelGrid
from magrun.field.zernike import ZernikeFieldModel
from magrun.robot import (
    RobotParams,
    RobotSpec,
    aligned_substep,
    discrete_step,
    exponential_substep,
    load_robots,
    magnetic_wrench,
    slender_body_drag,
    state_derivative,
)
from magrun.yamlio import YamlModelError


def test_robots_file_holds_the_papers_robots() -> None:
    robots = load_robots()
    assert set(robots) == {"magnet", "drug_delivery", "micro_magnet"}  # and a small one
    assert robots["magnet"].moment == pytest.approx(1.35e-3)
    assert robots["magnet"].length == pytest.approx(16e-3)
    assert robots["drug_delivery"].moment == pytest.approx(8.9e-4)
    assert robots["drug_delivery"].length == pytest.approx(7.4e-3)


def test_drag_coefficients_match_their_documented_derivation() -> None:
    """robots.yaml: drag = contact_factor x slender-body Stokes drag, to the 3 digits given."""
    import yaml

    from magrun.robot import robots_path

    doc = yaml.safe_load(robots_path().read_text())
    for name, raw in doc.items():
        spec = RobotSpec.model_validate(raw)
        free = slender_body_drag(
            spec.length_mm * 1e-3, spec.diameter_mm * 1e-3, spec.viscosity_mpa_s * 1e-3
        )
        given = (
            spec.drag_parallel_n_s_per_m,
            spec.drag_perpendicular_n_s_per_m,
            spec.drag_rotation_n_m_s,
        )
        assert_allclose(given, np.array(free) * spec.contact_factor, rtol=5e-3, err_msg=name)


def test_slender_body_drag_orders() -> None:
    # a long rod: sideways drag is about twice the axial drag (slender-body limit 2)
    d_par, d_perp, _ = slender_body_drag(0.3, 0.001, 1e-3)
    assert 1.6 < d_perp / d_par < 2.0


def test_bad_robots_file_names_file_line_and_field(tmp_path) -> None:
    bad = tmp_path / "robots.yaml"
    bad.write_text(
        "magnet:\n  description: x\n  length_mm: -16\n  diameter_mm: 2.8\n  moment_am2: 1e-3\n"
        "  mass_g: 0.2\n  viscosity_mpa_s: 6\n  contact_factor: 1\n"
        "  drag_parallel_n_s_per_m: 1\n  drag_perpendicular_n_s_per_m: 1\n"
        "  drag_rotation_n_m_s: 1\n"
    )
    with pytest.raises(YamlModelError, match=r"robots.yaml:3: magnet.length_mm"):
        load_robots(bad)
    # every number finite: an infinite mass once loaded and ran
    bad.write_text(bad.read_text().replace("length_mm: -16", "length_mm: 16").replace(
        "mass_g: 0.2", "mass_g: .inf"))  # fmt: skip
    with pytest.raises(YamlModelError, match=r"robots.yaml:6: magnet.mass_g: .*finite number"):
        load_robots(bad)


def test_wrench_is_the_gradient_of_m_dot_b(zernike_model: ZernikeFieldModel, rng) -> None:
    """F = ∇(m·B) at fixed m, τ = ∂(m·B)/∂θ; checked by central differences (h = 1 µm)."""
    moment, h = 1.35e-3, 1e-6
    for _ in range(10):
        p = rng.uniform(-0.04, 0.04, 2)
        theta = rng.uniform(-math.pi, math.pi)
        I = rng.uniform(-30, 30, 8)

        def m_dot_b(q: np.ndarray, th: float, I: np.ndarray = I) -> float:
            B, _ = zernike_model.field_and_gradient(q, I)
            return moment * (math.cos(th) * B[0] + math.sin(th) * B[1])

        B, G = zernike_model.field_and_gradient(p, I)
        (fx, fy), tau = magnetic_wrench(theta, moment, B, G)
        fd_force = [
            (m_dot_b(p + h * e, theta) - m_dot_b(p - h * e, theta)) / (2 * h) for e in np.eye(2)
        ]
        fd_torque = (m_dot_b(p, theta + 1e-6) - m_dot_b(p, theta - 1e-6)) / 2e-6
        scale = np.hypot(fx, fy)
        assert_allclose([fx, fy], fd_force, rtol=0, atol=1e-6 * scale)
        assert tau == pytest.approx(fd_torque, rel=1e-6, abs=1e-15)


def test_zero_currents_no_motion(channel_grid: ChannelGrid, magnet_robot: RobotParams) -> None:
    state = (0.01, -0.02, 0.7, 0.0, 0.0, 0.0)
    for _ in range(50):
        state = discrete_step(
            state, lambda x, y: channel_grid.field(x, y, np.zeros(8)), magnet_robot, 0.04
        )
    assert state == (0.01, -0.02, 0.7, 0.0, 0.0, 0.0)


def test_uniform_gradient_gives_the_exact_damped_motion(magnet_robot: RobotParams) -> None:
    """Field along the moment (no torque) and a constant gradient: the closed-form solution."""
    r = magnet_robot
    B = (2e-3, 0.0)
    G = ((0.05, 0.0), (0.0, -0.05))  # force (m 0.05, 0) along the robot's axis
    v0, h = 0.004, 0.04
    x = discrete_step((0.0, 0.0, 0.0, v0, 0.0, 0.0), lambda x, y: (B, G), r, h, substeps=3)
    u_ss = r.moment * 0.05 / r.drag_parallel
    tau = r.mass / r.drag_parallel
    assert x[3] == pytest.approx(u_ss + (v0 - u_ss) * math.exp(-h / tau), rel=1e-12)
    assert x[0] == pytest.approx(u_ss * h + (v0 - u_ss) * tau * (1 - math.exp(-h / tau)), rel=1e-12)
    assert x[1:3] == (0.0, 0.0)


def test_step_matches_stiff_reference_integration(
    channel_grid: ChannelGrid, magnet_robot: RobotParams
) -> None:
    """40 ms steps vs LSODA (rtol 1e-9) on the continuous equations, field re-evaluated along
    the path; currents drawn in ±10 A and switched every step (harsher than any controller).
    Measured: ≤ 6 µm / 0.05° per step and ≤ 0.05 mm / 0.2° after 20 steps; bounds 3-5x.
    (LSODA switches to a stiff method where needed; on these 60 steps it agrees with Radau at
    the same tolerances to 3e-13 m and 1e-10 rad, in a twentieth of Radau's time.)"""
    rng = np.random.default_rng(7)
    one_pos = one_ang = n_pos = n_ang = 0.0
    for _ in range(3):
        x0 = np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(-3, 3), 0.0, 0.0, 0.0])
        ours, ref = tuple(x0), x0.copy()
        for _ in range(20):
            I = rng.uniform(-10, 10, 8)

            def field(px: float, py: float, I: np.ndarray = I):
                return channel_grid.field(px, py, I)

            sol = solve_ivp(
                lambda t, s, field=field: state_derivative(s, *field(s[0], s[1]), magnet_robot),
                (0.0, 0.04),
                ref,
                method="LSODA",
                rtol=1e-9,
                atol=1e-12,
            )
            one = discrete_step(tuple(ref), field, magnet_robot, 0.04)
            ref = sol.y[:, -1]
            one_pos = max(one_pos, math.dist(one[:2], ref[:2]))
            one_ang = max(one_ang, abs(one[2] - ref[2]))
            ours = discrete_step(ours, field, magnet_robot, 0.04)
        n_pos = max(n_pos, math.dist(ours[:2], ref[:2]))
        n_ang = max(n_ang, abs(ours[2] - ref[2]))
    assert one_pos < 20e-6
    assert one_ang < math.radians(0.2)
    assert n_pos < 0.2e-3
    assert n_ang < math.radians(1.0)


@pytest.mark.parametrize("substep", [aligned_substep, exponential_substep])
def test_casadi_step_equals_numpy_step(
    zernike_model: ZernikeFieldModel, magnet_robot, rng, substep
) -> None:
    f = casadi_step_function(
        magnet_robot, zernike_model.casadi_field_and_gradient, 8, 0.04, substep=substep
    )
    for _ in range(5):
        x = np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(-3, 3), *rng.normal(0, 1e-3, 3)])
        I = rng.uniform(-30, 30, 8)

        def field(px: float, py: float, I: np.ndarray = I):
            return zernike_model.field_and_gradient(np.array([px, py]), I)

        expected = discrete_step(tuple(x), field, magnet_robot, 0.04, substep=substep)
        got = np.asarray(f(x, I)).ravel()
        assert_allclose(got, expected, rtol=1e-10, atol=1e-15)
    assert isinstance(f, ca.Function)


def _held_field_reference(robot: RobotParams, B, G, state, dt: float) -> np.ndarray:
    """The continuous equations over ``dt`` with (B, G) held, by LSODA (rtol 1e-10), which
    switches to a stiff method where the field turns the robot fast. On the strong-field
    cases below it agrees with Radau at the same tolerances to 1e-9 rad and 1e-13 m, at a
    twentieth of Radau's time.

    With the field held the derivative does not depend on the position, and a numerical
    Jacobian may grow its difference step for those columns until the step factor overflows
    (scipy's own heuristic, harmless: the columns are zero). On some processors numpy then
    warns, which the test suite treats as an error, so that overflow is let be."""
    with np.errstate(over="ignore"):
        sol = solve_ivp(
            lambda t, s: state_derivative(s, B, G, robot),
            (0.0, dt), np.asarray(state, dtype=float), method="LSODA", rtol=1e-10, atol=1e-13,
        )  # fmt: skip
    assert sol.success
    return sol.y[:, -1]


@pytest.mark.parametrize("name", ["micro_magnet", "drug_delivery", "magnet"])
def test_model_step_holds_in_strong_fields(name: str) -> None:
    """The NMPC's step (2 aligned sub-steps of 20 ms) against a stiff reference integration
    (LSODA) where the field turns the robot within a fraction of a sub-step: uniform fields
    of 2 to 100 mT at up to 149° from the robot (alignment rate k|B| = m|B|/d_r up to 770
    1/s, k|B|·h up to 15, where the plant's exponential sub-step, made for k|B|·h below 1, is
    tens of degrees off), with a gradient and a start turning at ~1 rad/s. Measured: at most
    0.4° (micro_magnet), 2.0° (drug_delivery), 1.7° (magnet) and 12 µm per step; bounds 4°,
    25 µm."""
    robot = load_robots()[name]
    rng = np.random.default_rng(3)
    worst_pos = worst_ang = old_ang = 0.0
    for _ in range(40):
        strength = 10 ** rng.uniform(math.log10(2e-3), math.log10(0.1))
        phi = rng.uniform(-math.pi, math.pi)
        B = (strength * math.cos(phi), strength * math.sin(phi))
        g = rng.normal(0.0, 0.05, (2, 2))
        G = ((g[0, 0], g[0, 1]), (g[0, 1], -g[0, 0]))  # curl- and divergence-free in the plane
        state = (0.0, 0.0, phi + rng.uniform(-2.6, 2.6), 0.0, 0.0, rng.normal(0.0, 1.0))
        ref = _held_field_reference(robot, B, G, state, 0.04)
        ours = state
        for _ in range(2):
            ours = aligned_substep(ours, B, G, robot, 0.02)
        old = discrete_step(state, lambda x, y, held=(B, G): held, robot, 0.04, 2)
        worst_pos = max(worst_pos, math.dist(ours[:2], ref[:2]))
        worst_ang = max(worst_ang, abs(math.remainder(ours[2] - ref[2], 2 * math.pi)))
        old_ang = max(old_ang, abs(math.remainder(old[2] - ref[2], 2 * math.pi)))
    assert worst_ang < math.radians(4.0)
    assert worst_pos < 25e-6
    if name != "magnet":  # the stiff ones: the exponential sub-step fails there
        assert old_ang > 10 * worst_ang


def test_aligned_step_is_smooth_at_zero_field_and_anti_aligned(magnet_robot) -> None:
    """No field: the robot coasts (its turn rate relaxes over J/d_r, nothing else). A field
    exactly against the moment: the unstable rest holds, and the step's derivative there is
    finite (CasADi, the NMPC's linearisation)."""
    r = magnet_robot
    zero = ((0.0, 0.0), ((0.0, 0.0), (0.0, 0.0)))
    x = aligned_substep((0.0, 0.0, 0.3, 0.0, 0.0, 2.0), *zero, r, 0.02)
    tau = r.inertia / r.drag_rotation
    assert x[2] == pytest.approx(0.3 + 2.0 * tau * (1 - math.exp(-0.02 / tau)), rel=1e-9)
    assert x[5] == pytest.approx(2.0 * math.exp(-0.02 / tau), rel=1e-9)
    against = ((-5e-3, 0.0), ((0.0, 0.0), (0.0, 0.0)))
    x = aligned_substep((0.0, 0.0, 0.0, 0.0, 0.0, 0.0), *against, r, 0.02)
    assert x[2] == pytest.approx(0.0, abs=1e-12)
    X = ca.SX.sym("X", 6)
    from magrun.control.symbolic import CASADI_OPS

    for B in ((0.0, 0.0), (-5e-3, 0.0)):
        nxt = aligned_substep(tuple(X[i] for i in range(6)), B, zero[1], r, 0.02, CASADI_OPS)
        J = ca.Function("J", [X], [ca.jacobian(ca.vertcat(*nxt), X)])
        assert np.all(np.isfinite(np.asarray(J(np.zeros(6)))))


def test_the_relaxation_constants_are_the_decay_and_its_integral() -> None:
    """robot.relaxation (the one definition the Python and the compiled plant share): the
    decay e^(−h/τ) and ∫₀ʰ e^(−t/τ) dt, here by quadrature (scipy, 1e-12 relative), for time
    constants from far below the sub-step to far above it."""
    from scipy.integrate import quad

    from magrun.robot import relaxation

    for tau in (1e-5, 3e-4, 2e-3, 6e-3, 0.5):
        for h in (1e-3, 5e-4, 0.02):
            decay, integral = relaxation(tau, h)
            assert decay == pytest.approx(np.exp(-h / tau), rel=1e-14, abs=1e-300)
            want, _ = quad(lambda t, tau=tau: np.exp(-t / tau), 0.0, h, epsabs=0, epsrel=1e-13)
            assert integral == pytest.approx(want, rel=1e-12)
