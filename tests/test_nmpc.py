"""The fast NMPC: polynomial field form, compiled functions, and RTI vs the IPOPT reference.

The RTI solver and IPOPT solve the same optimal control problem by different methods
(Gauss–Newton SQP with HPIPM QPs vs an interior point method with the exact Hessian). On fixed
problems, the RTI iterated to convergence must reach IPOPT's optimum; these tests check the
currents plan and the objective, with constraints inactive and active.
"""

from __future__ import annotations

import hashlib
import math
import tempfile
import warnings
from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun import compiled as compiled_mod
from magrun.control.nmpc import NMPC, STATE_SCALE, NMPCConfig
from magrun.field.polynomial import PolynomialField, exponents, monomials

# -- the polynomial form of the Zernike model ---------------------------------------------------


def test_polynomial_form_equals_the_zernike_model(zernike_model, rng) -> None:
    """Same field and gradient as the term-by-term Zernike model, to rounding (1e-10 relative)."""
    poly = zernike_model.polynomial
    assert poly.degree == 9
    assert poly.coefficients.shape == (2, len(exponents(9)), 8)
    p = rng.uniform(-0.05, 0.05, (500, 2))
    currents = rng.uniform(-30, 30, (500, 8))
    Bu, Gu = zernike_model.unit_field_and_gradient_terms(p)  # term by term, per channel
    B0, G0 = np.einsum("nck,nc->nk", Bu, currents), np.einsum("nckl,nc->nkl", Gu, currents)
    B1, G1 = poly.field_and_gradient(p, currents)
    assert_allclose(B1, B0, rtol=0, atol=1e-10 * np.abs(B0).max())
    assert_allclose(G1, G0, rtol=0, atol=1e-10 * np.abs(G0).max())
    # the model's own NumPy evaluation is the polynomial form, per channel and at one point
    B2, G2 = zernike_model.unit_field_and_gradient(p)
    assert B2.shape == Bu.shape
    assert G2.shape == Gu.shape
    assert_allclose(B2, Bu, rtol=0, atol=1e-10 * np.abs(Bu).max())
    assert_allclose(G2, Gu, rtol=0, atol=1e-10 * np.abs(Gu).max())
    b, g = zernike_model.unit_field_and_gradient(p[7])
    assert b.shape == (8, 2)
    assert g.shape == (8, 2, 2)
    assert_allclose(b, Bu[7], rtol=0, atol=1e-10 * np.abs(Bu).max())


def test_polynomial_gradient_matches_finite_differences(zernike_model, rng) -> None:
    poly = zernike_model.polynomial
    p, currents, h = rng.uniform(-0.03, 0.03, 2), rng.uniform(-30, 30, 8), 1e-6
    _, G = poly.field_and_gradient(p, currents)
    for axis in range(2):
        e = np.zeros(2)
        e[axis] = h
        Bp, _ = poly.field_and_gradient(p + e, currents)
        Bm, _ = poly.field_and_gradient(p - e, currents)
        assert_allclose(G[:, axis], (Bp - Bm) / (2 * h), rtol=1e-6, atol=1e-9)


def test_polynomial_casadi_form_equals_the_term_form(zernike_model, rng) -> None:
    p, I = ca.SX.sym("p", 2), ca.SX.sym("I", 8)
    fast = ca.Function("f", [p, I], list(zernike_model.casadi_field_and_gradient(p, I)))
    slow = ca.Function("s", [p, I], list(zernike_model.casadi_field_and_gradient_terms(p, I)))
    assert fast.n_instructions() < slow.n_instructions() * 0.6
    for _ in range(5):
        x, c = rng.uniform(-0.05, 0.05, 2), rng.uniform(-30, 30, 8)
        for a, b in zip(fast(x, c), slow(x, c), strict=True):
            a, b = np.asarray(a), np.asarray(b)
            assert_allclose(a, b, rtol=0, atol=1e-11 * np.abs(b).max())


def test_polynomial_form_refuses_a_model_that_is_not_a_polynomial(lut_model) -> None:
    with pytest.raises(ValueError, match="not a polynomial of degree 4"):
        PolynomialField.from_model(lut_model, degree=4)
    with pytest.raises(ValueError, match="states no polynomial degree"):
        PolynomialField.from_model(lut_model)


def test_monomials_order() -> None:
    x, y = np.array([2.0]), np.array([3.0])
    expected = [2.0**i * 3.0**j for i, j in exponents(3)]
    assert_allclose(monomials(x, y, 3)[0], expected)
    assert exponents(2) == [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]


# -- compiled functions and their cache ---------------------------------------------------------


def _square() -> ca.Function:
    x = ca.SX.sym("x", 3)
    return ca.Function("magrun_test_square", [x], [ca.sin(x) * x])


def test_compiled_function_matches_and_is_cached(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path))
    f = _square()
    fc = compiled_mod.compiled(f)
    libraries = list((tmp_path / "casadi").glob("magrun_test_square-*.so"))
    assert len(libraries) == 1
    x = np.array([0.3, -1.2, 2.0])
    assert_allclose(np.asarray(fc(x)).ravel(), np.sin(x) * x, rtol=1e-15)
    stamp = libraries[0].stat().st_mtime_ns
    compiled_mod.compiled(_square())  # same code: the cached library, not a rebuild
    assert libraries[0].stat().st_mtime_ns == stamp
    assert len(list((tmp_path / "casadi").glob("*.so"))) == 1
    y = ca.SX.sym("x", 3)
    compiled_mod.compiled(ca.Function("magrun_test_square", [y], [ca.cos(y) * y]))
    assert len(list((tmp_path / "casadi").glob("*.so"))) == 2  # new code, new key


def test_a_library_is_found_by_its_graph_without_generating_code(tmp_path, monkeypatch) -> None:
    """The cache's entry for a function's graph names the library its code compiled to: the
    same graph again (a new Function object) loads it without generating code; a constant
    changed in its last bit, or another version of magrun, generates code again; an entry
    that is damaged, names a library elsewhere or one that is gone is passed over and
    written again."""
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path))
    x = ca.SX.sym("x", 2)
    first = compiled_mod.compiled(ca.Function("magrun_test_scale", [x], [0.1 * x]))
    (library,) = (tmp_path / "casadi").glob("magrun_test_scale-*.so")
    (entry,) = (tmp_path / "casadi" / "known").glob("magrun_test_scale-*")
    assert entry.read_text().strip() == library.name
    generated: list[str] = []
    real = ca.CodeGenerator

    def counting(*args, **kwargs):
        generated.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(compiled_mod.ca, "CodeGenerator", counting)
    y = ca.SX.sym("x", 2)
    again = compiled_mod.compiled(ca.Function("magrun_test_scale", [y], [0.1 * y]))
    assert generated == []
    assert_allclose(np.asarray(again([1.0, -2.0])).ravel(), np.asarray(first([1.0, -2.0])).ravel())
    nudged = ca.Function("magrun_test_scale", [y], [np.nextafter(0.1, 1.0) * y])
    compiled_mod.compiled(nudged)
    assert len(generated) == 1  # another constant: another graph, generated and compiled
    assert len(list((tmp_path / "casadi").glob("magrun_test_scale-*.so"))) == 2

    elsewhere = "../magrun_test_scale-0123456789abcdef0123.so"
    gone = "magrun_test_scale-0123456789abcdef0123.so"
    for damaged in ("", "\x00\xff garbage", elsewhere, gone, "nmpc_rti-0123456789abcdef0123.so"):
        entry.write_text(damaged, encoding="latin-1")
        generated.clear()
        compiled_mod.compiled(ca.Function("magrun_test_scale", [y], [0.1 * y]))
        assert generated == ["magrun_test_scale.c"], damaged
        assert entry.read_text().strip() == library.name  # written again, as it should read

    monkeypatch.setattr(compiled_mod, "package_digest", lambda: "another version of magrun")
    generated.clear()
    compiled_mod.compiled(ca.Function("magrun_test_scale", [y], [0.1 * y]))
    assert generated == ["magrun_test_scale.c"]
    assert len(list((tmp_path / "casadi" / "known").glob("magrun_test_scale-*"))) == 3


class _Generated(Exception):
    """What a kernel's cache key and generated source were (the test stops there)."""


def test_the_kernels_fingerprint_separates_what_its_source_separates(
    zernike_model, magnet_robot, monkeypatch
) -> None:
    """The cache finds the RTI's kernel by the graph it is generated from: configurations
    whose generated C differs (a weight, the horizon, the soft constraints' form, no heading
    term, the field-model error, another robot, a corridor, a lookup table's entry) must have
    different fingerprints, and the same configuration built twice the same one, or the cache
    would load another controller's kernel, or never hit. The same for IPOPT's callbacks."""
    from magrun.control import rti_kernel
    from magrun.freespace import FreeSpace
    from magrun.phantom import load_phantom
    from magrun.robot import load_robot

    if rti_kernel.hpipm_build() is None:
        pytest.skip("no HPIPM build to generate the kernel for")

    def recorded(name, write_source, *, fingerprint=None, **_):
        with tempfile.TemporaryDirectory() as tmp:
            source = write_source(Path(tmp)).read_bytes()
        raise _Generated(fingerprint, hashlib.sha256(source).hexdigest())

    monkeypatch.setenv("MAGRUN_COMPILE", "1")
    monkeypatch.setattr(compiled_mod, "compilation_enabled", lambda: True)
    monkeypatch.setattr(rti_kernel, "shared_library", recorded)
    # the planner's other compiled functions are not under test: left uncompiled
    monkeypatch.setattr("magrun.control.nmpc.problem.compiled", lambda function: function)
    capsule = load_robot("drug_delivery")
    square = FreeSpace.square(0.02, capsule.length, capsule.diameter)
    spine = Path(__file__).parents[1] / "protocols" / "phantoms" / "spine_l3l4.yaml"
    phantom = load_phantom(spine)
    channel = FreeSpace(phantom.boundaries, phantom.critical, capsule.length, capsule.diameter)
    base = NMPCConfig()
    other_form = replace(
        base, soft_constraints="slack" if base.soft_constraints == "penalty" else "penalty"
    )
    variants = {
        "default": (zernike_model, magnet_robot, base, None),
        "default again": (zernike_model, magnet_robot, base, None),
        "position weight": (zernike_model, magnet_robot, replace(base, q_position=1.01), None),
        "horizon": (zernike_model, magnet_robot, replace(base, horizon=base.horizon - 2), None),
        "no heading term": (zernike_model, magnet_robot, replace(base, heading_weight=0.0), None),
        "field-model error": (zernike_model, magnet_robot, replace(base, field_error=0.05), None),
        "capsule": (zernike_model, capsule, base, square),
        "capsule in a channel": (zernike_model, capsule, base, channel),
        "channel, the soft constraints' other form": (zernike_model, capsule, other_form, channel),
    }
    keys = {}
    for name, (model, robot, config, free_space) in variants.items():
        with pytest.raises(_Generated) as seen:
            NMPC(model, robot, config, free_space)
        keys[name] = seen.value.args
        assert keys[name][0] is not None, name
    names = list(keys)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            same_print = keys[a][0] == keys[b][0]
            same_source = keys[a][1] == keys[b][1]
            assert same_print == same_source, (a, b, same_print, same_source)
    assert keys["default"] == keys["default again"]
    assert len({k[1] for k in keys.values()}) == len(keys) - 1  # each variant's own code

    # a lookup-table model's graph holds its tables: one entry nudged is another graph
    x = ca.MX.sym("x")
    grid, values = np.linspace(0.0, 1.0, 5), np.linspace(0.0, 2.0, 5)
    nudged = values.copy()
    nudged[2] = np.nextafter(nudged[2], 2.0)
    tables = [ca.interpolant("lut", "linear", [grid], v) for v in (values, values, nudged)]
    prints = [compiled_mod.fingerprint(ca.Function("f", [x], [t(x)])) for t in tables]
    assert prints[0] == prints[1] != prints[2]

    # IPOPT's callbacks, by the NLP's graph and the solver's options (its code takes a
    # second a variant to generate: the keys alone)
    from magrun.control.nmpc import ipopt

    def key_only(name, write_source, *, fingerprint=None, **_):
        raise _Generated(fingerprint)

    monkeypatch.setattr(ipopt, "shared_library", key_only)
    nlps = {}
    for name, config in [("default", base), ("default again", base),
                         ("position weight", replace(base, q_position=1.01)),
                         ("iterations", replace(base, max_iter=base.max_iter + 1))]:  # fmt: skip
        with pytest.raises(_Generated) as seen:
            NMPC(zernike_model, magnet_robot, replace(config, solver="ipopt"))
        nlps[name] = seen.value.args
    assert nlps["default"] == nlps["default again"]
    assert nlps["position weight"] != nlps["default"]
    assert nlps["iterations"] != nlps["default"]  # an option: a key of its own


def test_without_a_compiler_functions_run_uncompiled(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("MAGRUN_COMPILE", "0")
    monkeypatch.setattr(compiled_mod, "_warned", False)
    f = _square()
    with pytest.warns(compiled_mod.CompileWarning, match="uncompiled"):
        g = compiled_mod.compiled(f)
    assert g is f
    assert not (tmp_path / "casadi").exists()


# -- RTI vs the IPOPT reference on fixed problems -----------------------------------------------


CONVERGE = {"first_tick_iterations": 60, "step_tolerance": 1e-10}


def _problem(kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(state, reference window (21, 3), previous currents) of a fixed test problem."""
    ref = np.zeros((21, 3))
    state = np.zeros(6)
    previous = np.zeros(8)
    if kind == "track":  # a gentle move: no constraint active
        ref[:, 0] = np.linspace(0, 2e-3, 21)
        ref[:, 2] = 0.2
    elif kind == "slew":  # a step target from rest: the slew limit binds on the first steps
        ref[:, 0] = 0.006
        ref[:, 2] = math.radians(20)
    elif kind == "wall":  # a target outside the workspace box: the position bound binds
        ref[:, 0] = 0.06
        state[:3] = [0.035, 0.0, 0.0]
    return state, ref, previous


def _solve(
    model, robot, solver: str, kind: str, qp: str = "direct", soft: str = "penalty"
) -> tuple[NMPC, np.ndarray]:
    cfg = NMPCConfig(solver=solver, tol=1e-10, rti_qp=qp, soft_constraints=soft,  # type: ignore[arg-type]
                     **CONVERGE)  # fmt: skip
    if solver == "ipopt":
        cfg = replace(cfg, compile=False, ipopt={"acceptable_iter": 0})
    nmpc = NMPC(model, robot, cfg)
    state, ref, previous = _problem(kind)
    plan = nmpc.plan(state, ref, previous)
    assert plan.status.success, plan.status
    if solver == "rti":  # the QP path asked for, where it can be built
        assert (nmpc.backend.kernel is not None) == (qp == "direct" and compiled_mod.
                                                     compilation_enabled())  # fmt: skip
    currents = nmpc.backend.currents_plan()
    assert currents is not None
    assert_allclose(currents[0] * nmpc.max_current, plan.currents, atol=1e-12)
    return nmpc, currents


_IPOPT: dict[str, tuple[NMPC, np.ndarray]] = {}


def _ipopt(model, robot, kind: str) -> tuple[NMPC, np.ndarray]:
    """The reference's optimum of a fixed problem (solved once per session)."""
    if kind not in _IPOPT:
        _IPOPT[kind] = _solve(model, robot, "ipopt", kind)
    return _IPOPT[kind]


@pytest.mark.parametrize(("qp", "soft"), [("direct", "slack"), ("direct", "penalty"),
                                          ("casadi", "penalty")])  # fmt: skip
@pytest.mark.parametrize("kind", ["track", "slew", "wall"])
def test_rti_converges_to_the_ipopt_optimum(
    zernike_model, magnet_robot, kind: str, qp: str, soft: str
) -> None:
    """Whole current plans agree within 1e-4 of the limit, objectives within 1e-6 relative,
    with the QPs through magrun's compiled HPIPM kernel (the soft constraints as slacks or
    as penalty residuals) and through CasADi's interface. On each problem the heading-stable
    field's soft term is active: the optimum leaves the field along the moment short of B_min
    somewhere (by 0.003-2 %), so the slacks are tested where they matter."""
    rti, u_rti = _solve(zernike_model, magnet_robot, "rti", kind, qp, soft)
    X = rti.backend.states_plan()
    assert X is not None
    starts = [_problem(kind)[0] / STATE_SCALE, *X[:-1]]
    gaps = [float(rti.problem.heading_gap(x, u)) for x, u in zip(starts, u_rti, strict=True)]
    assert min(gaps) < 0
    ipopt, u_ipopt = _ipopt(zernike_model, magnet_robot, kind)
    assert_allclose(u_rti, u_ipopt, atol=1e-4)
    state, ref, previous = _problem(kind)
    x0 = state.copy()
    x0[:2] = np.clip(x0[:2], -rti.position_bound, rti.position_bound)
    args = (x0 / STATE_SCALE, previous / rti.max_current, rti.problem.stage_parameters(ref))
    J_rti, J_ipopt = rti.problem.cost(*args, u_rti), ipopt.problem.cost(*args, u_ipopt)
    assert J_rti == pytest.approx(J_ipopt, rel=1e-6)
    if kind == "slew":  # the constraint the test is about is active
        du = np.diff(np.vstack([previous / rti.max_current, u_rti]), axis=0)
        assert np.max(np.abs(du)) == pytest.approx(rti.problem.du_max, abs=1e-6)
    if kind == "wall":
        X = rti.backend.states_plan()
        assert X is not None
        assert np.max(X[:, 0]) == pytest.approx(rti.problem.pos_max, abs=1e-4)


def test_step_damping_shortens_the_steps_not_the_optimum(zernike_model, magnet_robot) -> None:
    """The step damping (a Levenberg-Marquardt term on each step) leaves the iteration's fixed
    point where it was: iterated to convergence from rest, the damped RTI reaches the IPOPT
    optimum of the tracking problem within 1e-4 of the limit, as the undamped one does; its
    first step is shorter (the same first QP with the proximal term added)."""
    _, u_ipopt = _ipopt(zernike_model, magnet_robot, "track")
    state, ref, previous = _problem("track")
    firsts = []
    for mu in (0.0, 1.0):
        cfg = NMPCConfig(tol=1e-10, step_damping=mu, first_tick_iterations=1,
                         step_tolerance=1e-10)  # fmt: skip
        one = NMPC(zernike_model, magnet_robot, cfg)
        first = one.plan(state, ref, previous)
        assert first.status.success, first.status
        firsts.append(np.abs(first.currents).max())
        converged = NMPC(zernike_model, magnet_robot,
                         replace(cfg, first_tick_iterations=3000))  # fmt: skip
        assert converged.plan(state, ref, previous).status.success
        u = converged.backend.currents_plan()
        assert u is not None
        assert_allclose(u, u_ipopt, atol=1e-4)
    assert firsts[1] < 0.9 * firsts[0]


@pytest.mark.parametrize("compile_", [False, True], ids=["expanded", "compiled"])
def test_the_objective_sums_the_residuals_over_the_simulated_plan(
    zernike_model, magnet_robot, rng, compile_
) -> None:
    """OCP.objective (one CasADi function, the checked steps' merit) against the stage and
    terminal residuals summed in a Python loop over states stepped one by one (each position
    held within the bound), for random currents on a problem whose heading term is active
    and whose target lies outside the bound: equal to rounding. Both of its forms: the graph
    expanded to scalar operations (run uncompiled) and the graph compiled to C."""
    from magrun.compiled import compilation_enabled

    nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig(compile=compile_))
    ocp = nmpc.problem
    compiled_c = compile_ and compilation_enabled()
    assert ocp.objective.class_name() == ("External" if compiled_c else "SXFunction")
    state, ref, previous = _problem("wall")
    x0, u_prev, par = nmpc._start(state, ref, previous)
    X, before, J = x0 / STATE_SCALE, u_prev, 0.0
    for _ in range(3):
        u = rng.uniform(-0.5, 0.5, (ocp.N, ocp.nu))
        X, before, J = x0 / STATE_SCALE, u_prev, 0.0
        for k in range(ocp.N):
            if k > 0:
                J += float(ca.sumsqr(ocp.pose_residual["stage"](X, par[:, k])))
            J += float(ca.sumsqr(ocp.heading(X, u[k]))) + float(ca.sumsqr(ocp.uncertainty(X, u[k])))
            J += ocp.config.r_current * float(np.sum(u[k] ** 2))
            J += ocp.config.s_current_change * float(np.sum((u[k] - before) ** 2))
            X, before = np.asarray(ocp.step_scaled(X, u[k])).ravel(), u[k]
            X[:2] = np.clip(X[:2], -ocp.pos_max, ocp.pos_max)  # held within the bound
        J += float(ca.sumsqr(ocp.pose_residual["terminal"](X, par[:, ocp.N])))
        assert ocp.cost(x0 / STATE_SCALE, u_prev, par, u) == pytest.approx(J, rel=1e-12)


def test_a_checked_descent_converges_where_full_gauss_newton_steps_diverge() -> None:
    """descend() on r(x) = atan(x), the textbook case: the Gauss-Newton step -r/r' =
    -atan(x)(1 + x²) overshoots from |x| > 1.39 and its iterates grow without bound (from 2:
    -3.54, 13.95, ...). Checked, the first full step is taken back (the iterate restored to
    2), and the iterate reaches the minimum, 0, to 1e-8."""
    from magrun.control.nmpc import descend

    def gauss_newton(x: float, mu: float) -> float:
        slope = 1.0 / (1.0 + x * x)
        return -slope * math.atan(x) / (slope * slope + mu)

    x = 2.0
    for _ in range(3):
        x += gauss_newton(x, 0.0)
    assert abs(x) > 100  # full steps diverge

    plan = {"S": np.zeros((1, 1)), "V": np.array([[2.0]])}  # the plan's V holds x
    restored: list[float] = []

    def objective(V: np.ndarray) -> float:
        return math.atan(float(V[0, 0])) ** 2

    def iterate() -> tuple[np.ndarray, np.ndarray]:
        return plan["S"].copy(), plan["V"].copy()

    def restore(S: np.ndarray, V: np.ndarray) -> None:
        restored.append(float(V[0, 0]))
        plan["S"], plan["V"] = S.copy(), V.copy()

    def step(mu: float) -> tuple[str, float]:
        dx = gauss_newton(float(plan["V"][0, 0]), mu)
        plan["V"] = plan["V"] + dx
        return "", abs(dx)

    cfg = NMPCConfig(first_tick_iterations=200, step_tolerance=1e-12)
    iterations, back, kept, error = descend(objective, iterate, restore, step, cfg)
    assert error == ""
    assert kept > 0
    assert restored[0] == 2.0
    assert back == len(restored) > 0
    assert abs(float(plan["V"][0, 0])) < 1e-8
    assert iterations < 200


@pytest.mark.parametrize("qp", ["direct", "casadi"])
def test_checked_steps_reach_the_ipopt_optimum(zernike_model, magnet_robot, qp: str) -> None:
    """Checking each step against the objective leaves the iteration's fixed point where it
    is: iterated from rest, the checked RTI reaches IPOPT's optimum of the tracking problem
    within 1e-4 of the limit, through either QP."""
    _, u_ipopt = _ipopt(zernike_model, magnet_robot, "track")
    state, ref, previous = _problem("track")
    cfg = NMPCConfig(step_check=True, rti_qp=qp, first_tick_iterations=3000,
                     step_tolerance=1e-10)  # fmt: skip
    nmpc = NMPC(zernike_model, magnet_robot, cfg)
    assert nmpc.plan(state, ref, previous).status.success
    u = nmpc.backend.currents_plan()
    assert u is not None
    assert_allclose(u, u_ipopt, atol=1e-4)


def test_step_damping_must_be_a_number_at_least_zero(zernike_model, magnet_robot) -> None:
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="step_damping"):
            NMPC(zernike_model, magnet_robot, NMPCConfig(step_damping=bad, compile=False))


def test_damped_corrective_iterations_leave_a_cycle_that_full_steps_keep(zernike_model) -> None:
    """A tick of the spine phantom on the bench (the capsule at the channel's apex, its
    estimate just moved 0.56 mm toward the critical wall by a frame), the NMPC as the phantom
    protocols run it: full Gauss-Newton steps alternate between two plans whose fields run
    against the moment (the heading residual at the first currents over 0.5 mT short, the
    objective more than 50 times IPOPT's optimum, 10 ticks on), where half steps in the
    corrective iterations reach IPOPT's optimum (objective within 10 %, first currents within
    3 A, the heading within 0.2 mT of its bound)."""
    from magrun.freespace import FreeSpace
    from magrun.phantom import load_phantom
    from magrun.protocol import load_protocol
    from magrun.robot import load_robots
    from magrun.trial import build_scene

    protocols = Path(__file__).parents[1] / "protocols"
    ref = build_scene(load_protocol(protocols / "spine.yaml")).reference.pose(
        7.02 + 0.04 * np.arange(21)
    )
    # the tick as it was recorded (m, rad, m/s, rad/s; A; the position covariance, m²)
    state = np.array([6.740e-3, -0.949e-3, 1.5878, -0.121e-3, 3.071e-3, -0.0927])
    previous = np.array([-0.88, -7.22, -0.91, -3.73, -4.26, -2.38, -5.96, -2.31])
    covariance = np.array([[2.26e-7, 0.96e-7, 0.0], [0.96e-7, 1.30e-6, 0.0], [0.0, 0.0, 1e-4]])
    phantom = load_phantom(protocols / "phantoms" / "spine_l3l4.yaml")
    robot = load_robots()["drug_delivery"]
    fs = FreeSpace(phantom.boundaries, phantom.critical, robot.length, robot.diameter)
    base = NMPCConfig(field_error=0.05, soft_constraints="slack", corrective_iterations=6)

    def run(cfg: NMPCConfig, ticks: int) -> tuple[float, float, np.ndarray]:
        nmpc = NMPC(zernike_model, robot, cfg, fs)
        if cfg.solver == "rti" and nmpc.backend.kernel is None:
            pytest.skip("the slacks need the compiled kernel (no C compiler here)")
        nmpc.observe_uncertainty(covariance)
        for _ in range(ticks):
            currents = nmpc.plan(state, ref, previous).currents
        x0, u_prev, par = nmpc._start(state, ref, previous)
        u = nmpc.backend.currents_plan()
        assert u is not None
        ocp = nmpc.problem
        heading = float(ocp.heading_check(x0 / STATE_SCALE, u[0])) / math.sqrt(cfg.heading_weight)
        return ocp.cost(x0 / STATE_SCALE, u_prev, par, u), heading, currents

    J_ipopt, h_ipopt, I_ipopt = run(replace(base, solver="ipopt", compile=False), 1)
    assert h_ipopt > -0.05  # mT: IPOPT holds the heading
    J_full, h_full, _ = run(replace(base, corrective_step=1.0), 10)
    J_half, h_half, I_half = run(replace(base, corrective_step=0.5), 10)
    assert J_full > 50 * J_ipopt
    assert h_full < -0.5
    assert J_half == pytest.approx(J_ipopt, rel=0.1)
    assert np.max(np.abs(I_half - I_ipopt)) < 3.0
    assert h_half > -0.2


class _FailingQP:
    """Stands in for the fast HPIPM preset: solves with it, then reports failure."""

    def __init__(self, qp: object) -> None:
        self.qp = qp

    def __call__(self, **kw: object) -> object:
        return self.qp(**kw)  # type: ignore[operator]

    def stats(self) -> dict[str, object]:
        return {"success": False, "return_status": "forced failure"}


@pytest.mark.parametrize("qp", ["direct", "casadi"])
def test_a_qp_the_fast_preset_fails_is_solved_by_the_robust_one(
    zernike_model, magnet_robot, qp: str
) -> None:
    """Every QP handed to the robust preset after the fast one failed: the same plan (the SQP
    iterations end ~2e-6 apart in normalised current, against the 1e-4 both keep to IPOPT's
    optimum above), one retry per QP, and no failure reported."""
    fast, u_fast = _solve(zernike_model, magnet_robot, "rti", "slew", qp)
    assert fast.backend.robust_retries == 0  # this problem needs no retry

    cfg = NMPCConfig(solver="rti", tol=1e-10, rti_qp=qp, **CONVERGE)  # type: ignore[arg-type]
    nmpc = NMPC(zernike_model, magnet_robot, cfg)
    if nmpc.backend.kernel is not None:  # the fast mode stops after one interior-point step
        nmpc.backend.kernel.limit_fast_iterations(1)
    else:
        nmpc.backend.qp_solver = _FailingQP(nmpc.backend.qp_solver)  # type: ignore[assignment]
    state, ref, previous = _problem("slew")
    plan = nmpc.plan(state, ref, previous)
    assert plan.status.success, plan.status
    assert nmpc.backend.robust_retries == plan.status.iterations >= 2
    u_robust = nmpc.backend.currents_plan()
    assert_allclose(u_robust, u_fast, atol=1e-5)


def test_rti_on_the_lookup_tables_reaches_the_ipopt_optimum(lut_model, magnet_robot) -> None:
    """Baseline 5's model through the same two solvers: same optimum."""
    _, u_rti = _solve(lut_model, magnet_robot, "rti", "track")
    _, u_ipopt = _solve(lut_model, magnet_robot, "ipopt", "track")
    assert_allclose(u_rti, u_ipopt, atol=1e-4)


def test_rti_falls_back_on_a_failed_qp(zernike_model, magnet_robot) -> None:
    """A non-finite QP gives the previous plan's next currents, then zero without a plan."""
    nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig())
    state, ref, previous = _problem("track")
    first = nmpc.plan(state, ref, previous)
    assert first.status.success
    planned = nmpc.backend.currents_plan()
    assert planned is not None
    bad = state.copy()
    bad[0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        second = nmpc.plan(bad, ref, first.currents)
    assert not second.status.success
    assert second.status.fallback == "shifted"
    assert_allclose(second.currents, planned[1] * nmpc.max_current)
    nmpc.reset()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        third = nmpc.plan(bad, ref, previous)
    assert third.status.fallback == "zero"
    assert_allclose(third.currents, 0.0)


def test_rti_prediction_is_the_model_step(zernike_model, magnet_robot) -> None:
    """The plan's predicted state is one exact model step of the applied currents."""
    from magrun.robot import aligned_substep, discrete_step

    nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig())
    state, ref, previous = _problem("track")
    plan = nmpc.plan(state, ref, previous)

    def field(x: float, y: float):
        B, G = zernike_model.field_and_gradient(np.array([x, y]), plan.currents)
        return B, G

    expected = discrete_step(tuple(state), field, magnet_robot, 0.04, 2, substep=aligned_substep)
    assert_allclose(plan.predicted_state, expected, rtol=1e-9, atol=1e-15)


# -- the real-time iteration's preparation / feedback split --------------------------------------


def _warm(model, robot, **config: float) -> tuple[NMPC, np.ndarray, np.ndarray, np.ndarray]:
    """An NMPC with a converged plan of the 'track' problem, and that problem."""
    nmpc = NMPC(model, robot, NMPCConfig(**CONVERGE, **config))  # type: ignore[arg-type]
    if nmpc.backend.kernel is None:
        pytest.skip("the split needs the compiled kernel (no C compiler here)")
    state, ref, previous = _problem("track")
    first = nmpc.plan(state, ref, previous)
    assert first.status.success
    return nmpc, state, ref, first.currents


def test_feedback_after_a_preparation_at_the_start_is_the_plain_iteration(
    zernike_model, magnet_robot
) -> None:
    """Prepared at the very state the tick then measures, the feedback phase solves the QP
    the unsplit tick solves: the same currents to 1e-12 A."""
    ref_next = _problem("track")[1]
    plain, state, _, currents = _warm(zernike_model, magnet_robot)
    split, _, _, _ = _warm(zernike_model, magnet_robot)
    x1 = plain.predict(state, currents)
    a = plain.plan(x1, ref_next, currents)
    split.prepare(x1, ref_next, currents)
    b = split.plan(x1, ref_next, currents)
    assert b.status.prepare_time > 0
    assert a.status.prepare_time == 0
    assert_allclose(b.currents, a.currents, rtol=0, atol=1e-12)


def test_feedback_embeds_the_measured_state_to_first_order(zernike_model, magnet_robot) -> None:
    """Prepared at a predicted state x_p, the feedback at the measured x_p + h d solves the
    QP linearised at x_p with the start moved exactly for the linear model: its currents
    answer the move as the QP linearised at the measured state does, to first order. The
    two differ by the linearisation's curvature times the QP's step (O(h) here: the shifted
    plan is not the optimum of the next tick), 0.6 % of the answer on this problem, where
    leaving the move out of the dynamics leaves 100 %."""
    ref_next = _problem("track")[1]
    d = np.array([1e-3, -0.6e-3, 0.05, 2e-3, 1e-3, 0.1])  # m, rad, m/s, rad/s
    h = 1e-3
    answers = []
    for move in (0.0, h):
        plain, state, _, currents = _warm(zernike_model, magnet_robot)
        split, _, _, _ = _warm(zernike_model, magnet_robot)
        x_p = plain.predict(state, currents)
        measured = x_p + move * d
        a = plain.plan(measured, ref_next, currents)
        split.prepare(x_p, ref_next, currents)
        b = split.plan(measured, ref_next, currents)
        assert b.status.success
        assert b.status.prepare_time > 0
        answers.append((a.currents, b.currents))
    relinearised = answers[1][0] - answers[0][0]
    embedded = answers[1][1] - answers[0][1]
    assert np.max(np.abs(embedded)) > 1e-3  # the move is felt (A)
    assert np.linalg.norm(embedded - relinearised) < 0.03 * np.linalg.norm(relinearised)


def test_a_measurement_far_from_the_prediction_is_linearised_afresh(
    zernike_model, magnet_robot
) -> None:
    """Where the model linearised at the prediction maps the measured state far from the
    model itself (the embedding's defect above ``max_embedding_defect``), the feedback phase
    linearises at the measurement instead: the unprepared tick's currents to 1e-12 A. Near
    the prediction the defect is small (second order) and the preparation is used."""
    ref_next = _problem("track")[1]
    plain, state, _, currents = _warm(zernike_model, magnet_robot)
    split, _, _, _ = _warm(zernike_model, magnet_robot, max_embedding_defect=1e-3)
    x_p = plain.predict(state, currents)
    far = x_p + np.array([2e-3, -2e-3, 0.8, 20e-3, -20e-3, 5.0])  # m, rad, m/s, rad/s
    a = plain.plan(far, ref_next, currents)
    split.prepare(x_p, ref_next, currents)
    b = split.plan(far, ref_next, currents)
    assert split.backend.relinearised == 1
    assert_allclose(b.currents, a.currents, rtol=0, atol=1e-12)
    # close to the prediction: embedded, no second linearisation
    split2, _, _, _ = _warm(zernike_model, magnet_robot, max_embedding_defect=1e-3)
    near = x_p + 1e-3 * np.array([1e-3, -1e-3, 0.01, 1e-3, 1e-3, 0.01])
    split2.prepare(x_p, ref_next, currents)
    assert split2.plan(near, ref_next, currents).status.success
    assert split2.backend.relinearised == 0


def test_a_preparation_for_other_parameters_is_not_used(zernike_model, magnet_robot) -> None:
    """A tick whose reference or previous currents are not the prepared ones iterates from
    its own linearisation: the currents of the unprepared tick, to 1e-12 A."""
    ref_next = _problem("track")[1]
    other = ref_next.copy()
    other[:, 1] += 1e-3
    plain, state, _, currents = _warm(zernike_model, magnet_robot)
    split, _, _, _ = _warm(zernike_model, magnet_robot)
    x1 = plain.predict(state, currents)
    a = plain.plan(x1 + 1e-4, other, currents)
    split.prepare(x1, ref_next, currents)
    b = split.plan(x1 + 1e-4, other, currents)
    assert_allclose(b.currents, a.currents, rtol=0, atol=1e-12)


def test_controller_prepares_between_ticks_in_the_loop(zernike_model, magnet_robot) -> None:
    """On the simulated rig every NMPC tick after the first is prepared (prepare_time > 0)
    and the closed loop tracks the S within 1 % of the unprepared loop's RMS."""
    from magrun.bench.nmpc import s_curve_protocol
    from magrun.trial import assemble, single_trial

    proto = s_curve_protocol(60)
    parts = assemble(single_trial(proto, "proposed", seed=0))
    if parts.controller.planner.backend.kernel is None:  # type: ignore[attr-defined]
        pytest.skip("the split needs the compiled kernel (no C compiler here)")
    log = parts.run()
    prepared = [s.prepare_time > 0 for s in log.status]
    assert not prepared[0]
    assert all(prepared[1:])
    assert all(s.success for s in log.status)
    # the same trial with the preparation switched off
    plain = assemble(single_trial(proto, "proposed", seed=0))
    plain.controller.prepare = lambda reference: None  # type: ignore[method-assign]
    log_plain = plain.run()
    assert not any(s.prepare_time > 0 for s in log_plain.status)
    assert log.rms_position_mm == pytest.approx(log_plain.rms_position_mm, rel=0.01)


def test_the_kernel_links_another_hpipm_build_or_warns(
    zernike_model, magnet_robot, tmp_path, monkeypatch
) -> None:
    """``MAGRUN_HPIPM_DIR`` names the HPIPM / BLASFEO build the kernel links (here one laid
    out as an install prefix around the CasADi wheel's own files: the same plan to 1e-12);
    one without the libraries gives a warning and CasADi's interface (the same optimum to
    the 1e-5 the two QP paths keep)."""
    from magrun.control import rti_kernel

    if not compiled_mod.compilation_enabled():
        pytest.skip("no C compiler")
    _, u_default = _solve(zernike_model, magnet_robot, "rti", "slew")  # the session's cache
    # libraries linked to this test's prefix go to a cache of their own, which goes with it;
    # the session's other libraries (no HPIPM in them) are linked in, not compiled again
    session = compiled_mod.cache_dir() / "casadi"
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path / "cache"))
    own = compiled_mod.cache_dir() / "casadi"
    own.mkdir(parents=True)
    for library in session.glob("*.so"):
        if not library.name.startswith("nmpc_rti-"):
            (own / library.name).symlink_to(library)
    wheel = rti_kernel.casadi_folder()
    prefix = tmp_path / "hpipm"
    (prefix / "lib").mkdir(parents=True)
    (prefix / "include").symlink_to(wheel / "include")
    for name in ("libhpipm.so", "libblasfeo.so"):
        (prefix / "lib" / name).symlink_to(wheel / name)
    monkeypatch.setenv(rti_kernel.HPIPM_DIR_VARIABLE, str(prefix))
    assert rti_kernel.hpipm_build() == ([prefix / "include"], prefix / "lib")
    nmpc, u_prefix = _solve(zernike_model, magnet_robot, "rti", "slew")
    assert nmpc.backend.kernel is not None
    assert_allclose(u_prefix, u_default, rtol=0, atol=1e-12)

    monkeypatch.setenv(rti_kernel.HPIPM_DIR_VARIABLE, str(tmp_path / "empty"))
    with pytest.warns(compiled_mod.CompileWarning, match="holds no HPIPM"):
        nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig(tol=1e-10, **CONVERGE))
    assert nmpc.backend.kernel is None
    state, ref, previous = _problem("slew")
    assert nmpc.plan(state, ref, previous).status.success
    assert_allclose(nmpc.backend.currents_plan(), u_default, atol=1e-5)


def test_an_estimate_outside_the_box_is_planned_from_inside_it(zernike_model, magnet_robot):
    """An estimate past the position bound, moving outward, with the currents that pushed it
    there: clipped onto the bound (which is hard for every stage), the tick's QP has no
    feasible point; the plan is solved again from 1 mm inside the bound at rest, and succeeds
    with its states within the bound, for the real-time iteration's kernel and CasADi's QP
    alike."""
    for qp in ("direct", "casadi"):
        nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig(rti_qp=qp))  # type: ignore[arg-type]
        state, ref, previous = _problem("wall")
        pushed = nmpc.plan(state, ref, previous)  # toward a target outside the box
        assert pushed.status.success
        bound = nmpc.position_bound
        outside = np.array([bound + 3e-3, 1e-3, 0.0, 0.02, 0.0, 0.0])
        inside = np.tile([bound - 5e-3, 0.0, 0.0], (21, 1))
        solve, starts, outcomes = nmpc.backend.solve, [], []

        def recorded(x0, u_prev, par, start=None, solve=solve, starts=starts, outcomes=outcomes):
            result = solve(x0, u_prev, par, start)
            starts.append(np.array(x0) * STATE_SCALE)
            outcomes.append(result.ok)
            return result

        nmpc.backend.solve = recorded  # type: ignore[method-assign]
        plan = nmpc.plan(outside, inside, pushed.currents)
        assert outcomes == [False, True], qp  # on the bound: infeasible; inside: solved
        assert starts[0][0] == pytest.approx(bound)
        assert starts[1][0] == pytest.approx(bound - 1e-3)
        assert_allclose(starts[1][3:], 0.0)
        assert plan.status.success, plan.status
        X = nmpc.backend.states_plan()
        assert X is not None
        assert np.all(np.abs(X[:, :2] * 1e-3) <= bound + 1e-9)


def test_a_failed_tick_is_planned_again_from_rest_braking(zernike_model, magnet_robot):
    """A tick whose QP fails is solved once more from the same pose at rest, starting from a
    plan that brakes: the currents brought to zero at the slew bound (each step
    −clip(I, ±ΔI_max)), the states the model gives for them, within the bound. Whichever
    way the start moves (toward the bound or away from it) and whatever made the QP fail;
    here the first solve of each tick is made to fail, and the retry's start and plan are
    checked against that rule computed here."""
    from magrun.control.nmpc import SolveResult

    nmpc = NMPC(zernike_model, magnet_robot, NMPCConfig())
    bound, N = nmpc.position_bound, nmpc.config.horizon
    ref = np.tile([bound - 5e-3, 0.0, 0.0], (N + 1, 1))
    # some beyond one step's slew
    previous = np.clip(
        np.linspace(-1.2, 1.0, 8) * nmpc.max_change, -nmpc.max_current, nmpc.max_current
    )
    for velocity in (0.04, -0.04):
        nmpc.reset()
        start = np.array([bound - 1.5e-3, 0.0, 0.3, velocity, 0.0, 0.0])
        solve, calls = nmpc.backend.solve, []

        def failing_first(x0, u_prev, par, start=None, solve=solve, calls=calls):
            calls.append((np.array(x0) * STATE_SCALE, start))
            if len(calls) == 1:
                return SolveResult(False, np.zeros(8), 1, "made to fail")
            return solve(x0, u_prev, par, start)

        nmpc.backend.solve = failing_first  # type: ignore[method-assign]
        plan = nmpc.plan(start, ref, previous)
        assert plan.status.success, velocity
        assert len(calls) == 2
        (first, none), (retry, braking) = calls
        assert none is None
        assert_allclose(first, start)
        assert_allclose(retry[:3], start[:3])
        assert_allclose(retry[3:], 0.0)
        S, V = braking
        currents, x = previous.copy(), retry.copy()
        for k in range(N):
            step = -np.clip(currents, -nmpc.max_change, nmpc.max_change)
            currents = currents + step
            x = nmpc.predict(x, currents)
            x[:2] = np.clip(x[:2], -bound, bound)
            assert_allclose(V[k] * nmpc.max_current, step, atol=1e-12)
            assert_allclose(S[k, 6:] * nmpc.max_current, currents, atol=1e-12)
            assert_allclose(S[k, :6] * STATE_SCALE, x, rtol=1e-9, atol=1e-12)
        assert_allclose(S[-1, 6:], 0.0)  # braked to rest within the horizon
        assert np.all(np.abs(S[:, :2] * 1e-3) <= bound)


def test_position_uncertainty_residuals_against_finite_differences(
    zernike_model, magnet_robot
) -> None:
    """The residuals σ [√qθ Gᵀm̂⊥ / b, √Qp |m|/d T_f vec ∂(Gᵀm̂)/∂p], with
    b = (B_∥ + √(B_∥² + B_min²)) / 2, against central differences (h = 1 µm) of the model's
    numpy field, at a robot aligned with the field as a held one is: the field's angle φ over
    the position (its turn per error) and the pull Gᵀm̂ over the position (the velocity's
    change per error), within 1e-5 relative. Turned against the field the turn's residuals
    are the same turn over the one-sided floor of B_∥ = −|B|: larger by b(|B|) / b(−|B|)."""
    sigma, frame = 1.5e-3, 0.3
    cfg = NMPCConfig(position_uncertainty=sigma, frame_interval=frame, compile=False)
    nmpc = NMPC(zernike_model, magnet_robot, cfg)
    rng = np.random.default_rng(3)
    h = 1e-6
    mobility = magnet_robot.moment / min(
        magnet_robot.drag_parallel, magnet_robot.drag_perpendicular
    )
    for _ in range(5):
        p = rng.uniform(-0.02, 0.02, 2)
        currents = rng.uniform(-10, 10, nmpc.n_currents)
        B, _ = zernike_model.field_and_gradient(p, currents)
        theta = math.atan2(B[1], B[0])
        X = np.array([*p, theta, 0.0, 0.0, 0.0]) / STATE_SCALE
        r = np.asarray(nmpc.problem.uncertainty(X, currents / nmpc.max_current)).ravel()
        heading = np.array([math.cos(theta), math.sin(theta)])

        def angle(q: np.ndarray, currents: np.ndarray = currents) -> float:
            b, _ = zernike_model.field_and_gradient(q, currents)
            return math.atan2(b[1], b[0])

        def pull(
            q: np.ndarray, currents: np.ndarray = currents, heading: np.ndarray = heading
        ) -> np.ndarray:
            _, g = zernike_model.field_and_gradient(q, currents)
            return g.T @ heading  # T/m

        steps = np.eye(2) * h
        dphi = np.array([(angle(p + e) - angle(p - e)) / (2 * h) for e in steps])  # rad/m
        dpull = np.column_stack([(pull(p + e) - pull(p - e)) / (2 * h) for e in steps])
        along = 1e3 * float(heading @ B)  # mT
        floor = along / ((along + math.hypot(along, nmpc.min_aligned_field * 1e3)) / 2)
        turn = math.sqrt(cfg.q_angle) * sigma * dphi * floor
        drift = math.sqrt(cfg.q_position) * sigma / 1e-3 * mobility * frame * dpull.T.ravel()
        expected = np.concatenate([turn, drift])
        assert_allclose(r, expected, rtol=1e-5, atol=1e-7 * np.abs(expected).max())
        flipped = X.copy()
        flipped[2] += math.pi
        r_against = np.asarray(nmpc.problem.uncertainty(flipped, currents / nmpc.max_current))
        b_min = nmpc.min_aligned_field * 1e3
        ratio = (along + math.hypot(along, b_min)) / (-along + math.hypot(along, b_min))
        assert_allclose(r_against.ravel()[:2], -turn * ratio, rtol=1e-5)
    off = NMPC(zernike_model, magnet_robot, NMPCConfig(compile=False))
    assert np.asarray(off.problem.uncertainty(X, currents / nmpc.max_current)).size == 0


def test_rti_with_position_uncertainty_reaches_the_ipopt_optimum(
    zernike_model, magnet_robot
) -> None:
    """With the position uncertainty's residuals in the cost the RTI (magrun's kernel)
    iterated to convergence and IPOPT agree on the whole current plan within 1e-4 of the
    limit, and the residuals change the plan (by more than 1e-3 of the limit)."""
    plans = {}
    for solver in ("rti", "ipopt"):
        cfg = NMPCConfig(solver=solver, tol=1e-10, position_uncertainty=2e-3,  # type: ignore[arg-type]
                         frame_interval=0.3, **CONVERGE)  # fmt: skip
        if solver == "ipopt":
            cfg = replace(cfg, compile=False, ipopt={"acceptable_iter": 0})
        nmpc = NMPC(zernike_model, magnet_robot, cfg)
        plan = nmpc.plan(*_problem("track"))
        assert plan.status.success, plan.status
        plans[solver] = nmpc.backend.currents_plan()
    assert_allclose(plans["rti"], plans["ipopt"], atol=1e-4)
    _, plain = _ipopt(zernike_model, magnet_robot, "track")
    assert np.max(np.abs(plans["ipopt"] - plain)) > 1e-3
