"""Field models: NumPy and CasADi agree, gradients are the field's derivatives, stacks are
placed where the physics puts them, and the shipped fit is current and as accurate as stated."""

from __future__ import annotations

import itertools

import casadi as ca
import magpylib as mp
import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from magrun.field.coils import CoilSystem
from magrun.field.fitting import fit_reference
from magrun.field.lut import LookupTableFieldModel
from magrun.field.model import CalibratedFieldModel, PlanarFieldModel
from magrun.field.reference import MU0, ReferenceMaps, thick_coil_field
from magrun.field.zernike import ZernikeFieldModel


def workspace_points(rng: np.random.Generator, n: int, half: float = 0.049) -> np.ndarray:
    return rng.uniform(-half, half, size=(n, 2))


#: per-channel gains a few percent off 1, as a coil calibration finds them
GAINS = np.array([0.97, 1.02, 1.01, 0.99, 1.03, 1.0, 0.98, 1.015])


@pytest.fixture(params=["zernike", "lut", "calibrated"])
def model(request, zernike_model, lut_model) -> PlanarFieldModel:
    if request.param == "calibrated":
        return CalibratedFieldModel(zernike_model, GAINS)
    return {"zernike": zernike_model, "lut": lut_model}[request.param]


def test_shapes(model: PlanarFieldModel) -> None:
    B, G = model.unit_field_and_gradient(np.zeros((5, 3, 2)))
    assert B.shape == (5, 3, 8, 2)
    assert G.shape == (5, 3, 8, 2, 2)
    b, g = model.field_and_gradient([0.01, 0.02], np.ones(8))
    assert b.shape == (2,)
    assert g.shape == (2, 2)
    with pytest.raises(ValueError, match="8 channels"):
        model.field_and_gradient([0.0, 0.0], np.ones(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\)"):
        model.unit_field(np.zeros(3))


def test_numpy_and_casadi_agree(model: PlanarFieldModel, rng: np.random.Generator) -> None:
    f = model.casadi_function()
    for p in workspace_points(rng, 20):
        currents = rng.uniform(-30, 30, 8)
        B, G = model.field_and_gradient(p, currents)
        Bc, Gc = f(p, currents)
        assert_allclose(np.asarray(Bc).ravel(), B, rtol=1e-10, atol=1e-15)
        assert_allclose(np.asarray(Gc), G, rtol=1e-10, atol=1e-13)


def test_zernike_gradient_is_the_derivative_of_its_field(
    zernike_model: ZernikeFieldModel, rng: np.random.Generator
) -> None:
    # against CasADi's algorithmic differentiation of B ...
    p, I = ca.SX.sym("p", 2), ca.SX.sym("I", 8)
    B, G = zernike_model.casadi_field_and_gradient(p, I)
    check = ca.Function("check", [p, I], [ca.jacobian(B, p) - G])
    for q in workspace_points(rng, 10):
        assert np.max(np.abs(np.asarray(check(q, rng.uniform(-30, 30, 8))))) < 1e-12
    # ... and against central differences of the NumPy field
    h = 1e-7
    for q in workspace_points(rng, 10):
        currents = rng.uniform(-30, 30, 8)
        _, G = zernike_model.field_and_gradient(q, currents)
        for axis in range(2):
            dq = np.zeros(2)
            dq[axis] = h
            fd = (
                zernike_model.field_and_gradient(q + dq, currents)[0]
                - zernike_model.field_and_gradient(q - dq, currents)[0]
            ) / (2 * h)
            assert_allclose(G[:, axis], fd, rtol=1e-6, atol=1e-9)


def test_lut_reproduces_its_table_at_grid_nodes(
    lut_model: LookupTableFieldModel, reference: ReferenceMaps
) -> None:
    fmap = reference["small"]
    pts = fmap.points()[::10, ::10].reshape(-1, 2)
    B, G = lut_model.unit_field_and_gradient(pts)
    k = lut_model.channel_names.index("small_N")  # the base stack: no rotation
    assert_allclose(B[:, k], fmap.B[::10, ::10].reshape(-1, 2), rtol=1e-12, atol=1e-18)
    assert_allclose(G[:, k], fmap.dB[::10, ::10].reshape(-1, 2, 2), rtol=1e-12, atol=1e-15)


def test_lut_evenly_spaced_grid_equals_scipys_interpolator(
    reference: ReferenceMaps, rng: np.random.Generator
) -> None:
    """The lookup table's fast bilinear read against RegularGridInterpolator (linear, linear
    extrapolation) on the same table: inside the grid, on its nodes and edges, and beyond it
    (an optimiser's infeasible iterates), to 1e-12 of the table's scale."""
    from scipy.interpolate import RegularGridInterpolator

    from magrun.field.lut import _table, _UniformGrid

    fmap = reference["small"]
    table = _table(fmap)
    fast = _UniformGrid.of(fmap.x, fmap.y, table)
    assert fast is not None  # the shipped maps are evenly spaced
    scipy_rgi = RegularGridInterpolator(
        (fmap.x, fmap.y), table, method="linear", bounds_error=False, fill_value=None
    )
    lo, hi = np.array([fmap.x[0], fmap.y[0]]), np.array([fmap.x[-1], fmap.y[-1]])
    span = hi - lo
    q = np.vstack(
        [
            rng.uniform(lo, hi, size=(500, 2)),
            fmap.points()[::7, ::9].reshape(-1, 2),  # nodes
            np.column_stack([np.full(20, hi[0]), rng.uniform(lo[1], hi[1], 20)]),  # last column
            rng.uniform(lo - 0.1 * span, hi + 0.1 * span, size=(200, 2)),  # partly outside
        ]
    )
    scale = np.abs(table).max(axis=(0, 1))
    assert_allclose(fast(q) / scale, scipy_rgi(q) / scale, rtol=0, atol=1e-12)
    uneven = fmap.x.copy()
    uneven[1] += 0.3 * (uneven[2] - uneven[1])
    assert _UniformGrid.of(uneven, fmap.y, table) is None  # falls back to scipy's


def test_stacks_match_coils_placed_independently(
    coils: CoilSystem, lut_model: LookupTableFieldModel, rng: np.random.Generator
) -> None:
    """Every channel against magpylib with the coil physically placed in its stack."""
    pts = workspace_points(rng, 15, half=0.045)
    B = lut_model.unit_field(pts)
    for c, ch in enumerate(coils.channels):
        spec = coils.coil_types[ch.coil_type]
        placed = Rotation.from_rotvec([0, 0, ch.angle])
        center = placed.apply([0.0, spec.center, 0.0])
        # a dense loop grid of the winding, oriented with its axis toward the centre
        r = np.linspace(spec.inner_radius, spec.outer_radius, 9)
        z = np.linspace(-spec.length / 2, spec.length / 2, 13)
        # trapezoid weights over the winding cross-section, summing to 1
        wr = np.full(r.size, 1.0 / (r.size - 1))
        wr[[0, -1]] /= 2
        wz = np.full(z.size, 1.0 / (z.size - 1))
        wz[[0, -1]] /= 2
        axis = -center / np.linalg.norm(center)
        obs = np.column_stack([pts, np.zeros(len(pts))])
        field = np.zeros((len(pts), 3))
        orient = placed * Rotation.from_rotvec([np.pi / 2, 0, 0])
        for (i, ri), (j, zi) in itertools.product(enumerate(r), enumerate(z)):
            field += (
                wr[i]
                * wz[j]
                * mp.func.circle_field(
                    "B",
                    obs,
                    diameters=2 * ri,
                    currents=spec.turns,
                    positions=center + zi * axis,
                    orientations=orient,
                )
            )
        # a 9 x 13 trapezoid loop grid and bilinear interpolation on a 1 mm grid each err by
        # ~1e-3 of the largest field here (seen: at most 1.7e-3)
        scale = np.linalg.norm(B[:, c], axis=1).max()
        assert np.max(np.abs(field[:, :2] - B[:, c])) < 5e-3 * scale, ch.name
        assert field[:, 2] == pytest.approx(0.0, abs=1e-15)


def test_positive_current_points_the_moment_at_the_centre(lut_model: LookupTableFieldModel) -> None:
    B = lut_model.unit_field([0.0, 0.0])
    expected_direction = {"N": [0, -1], "W": [1, 0], "S": [0, 1], "E": [-1, 0]}
    for c, name in enumerate(lut_model.channel_names):
        unit = B[c] / np.linalg.norm(B[c])
        assert_allclose(unit, expected_direction[name.split("_")[1]], atol=1e-12)


def test_shipped_zernike_model_is_the_fit_of_the_shipped_maps(
    coils: CoilSystem, reference: ReferenceMaps, zernike_model: ZernikeFieldModel
) -> None:
    orders = {t: f.order for t, f in zernike_model.fits.items()}
    refit = fit_reference(coils, reference, max_order=max(orders.values()), fixed_orders=orders)
    for t, fit in zernike_model.fits.items():
        # near-zero coefficients of a least-squares fit move with the BLAS build and the
        # processor: compare against the scale of the coefficients, not at rounding noise
        scale = float(np.max(np.abs(fit.coefficients)))
        assert_allclose(
            fit.coefficients, refit.model.fits[t].coefficients, rtol=1e-7, atol=1e-7 * scale
        )
    # and the shipped orders are what the selection rule picks today
    auto = fit_reference(coils, reference)
    assert {t: f.order for t, f in auto.model.fits.items()} == orders


def test_small_coil_fit_error_below_4mT_over_the_workspace(
    zernike_model: ZernikeFieldModel, reference: ReferenceMaps
) -> None:
    """The paper: "below 4 mT across the majority of the workspace" (small coil)."""
    fmap = reference["small"]
    Bf, _ = zernike_model.fits["small"].evaluate(fmap.points().reshape(-1, 2))
    err = np.linalg.norm(Bf - fmap.B.reshape(-1, 2), axis=1)
    assert np.all(err < 4e-3)  # at unit current, everywhere
    assert np.mean(err * 30.0 < 4e-3) > 0.95  # at the 30 A limit, on > 95 % of the area


def test_model_file_errors(tmp_path) -> None:
    bad = tmp_path / "model.json"
    bad.write_text('{"format_version": 99}')
    with pytest.raises(ValueError, match=r"model\.json.*format_version"):
        ZernikeFieldModel.load(bad)
    with pytest.raises(ValueError, match=r"missing\.json"):
        ZernikeFieldModel.load(tmp_path / "missing.json")


def test_save_load_round_trip(zernike_model: ZernikeFieldModel, tmp_path) -> None:
    zernike_model.save(tmp_path / "m.json")
    back = ZernikeFieldModel.load(tmp_path / "m.json")
    p = np.array([[0.01, -0.02], [0.03, 0.04]])
    assert_allclose(back.unit_field(p), zernike_model.unit_field(p), rtol=0, atol=0)


def test_field_magnitudes_are_realistic(lut_model: LookupTableFieldModel) -> None:
    """All eight coils at +30 A put tens of mT and a few tenths of T/m at the centre region."""
    # sanity against a loop estimate: the large coil alone ~ μ0 N I R²/(2(R²+d²)^1.5)
    B = np.linalg.norm(lut_model.unit_field([0.0, 0.0])[1])
    spec = lut_model.coils.coil_types["large"]
    R = (spec.inner_radius + spec.outer_radius) / 2
    estimate = MU0 * spec.turns * R**2 / (2 * (R**2 + spec.center**2) ** 1.5)
    assert pytest.approx(estimate, rel=0.1) == B
    assert 5e-3 < 30 * B < 30e-3
    one = thick_coil_field([[0.0, 0.0, 0.0]], spec)
    assert np.linalg.norm(one) == pytest.approx(B, rel=1e-3)


@pytest.mark.parametrize("base", ["zernike", "lut"])
def test_calibrated_model_is_the_base_with_scaled_currents(
    base: str, zernike_model, lut_model, rng: np.random.Generator
) -> None:
    """Fields are linear in the currents: a channel's gain g_c acts as the current g_c I_c on
    the base model, in NumPy and in CasADi."""
    plain = {"zernike": zernike_model, "lut": lut_model}[base]
    calibrated = CalibratedFieldModel(plain, GAINS)
    f = calibrated.casadi_function()
    for p in workspace_points(rng, 10):
        currents = rng.uniform(-30, 30, 8)
        B, G = plain.field_and_gradient(p, currents * GAINS)
        Bk, Gk = calibrated.field_and_gradient(p, currents)
        assert_allclose(Bk, B, rtol=1e-12, atol=1e-16)
        assert_allclose(Gk, G, rtol=1e-12, atol=1e-14)
        Bc, Gc = f(p, currents)
        assert_allclose(np.asarray(Bc).ravel(), B, rtol=1e-10, atol=1e-15)
        assert_allclose(np.asarray(Gc), G, rtol=1e-10, atol=1e-13)
    # and it is not the base model: a 3 % gain shows at full current
    B0, _ = plain.field_and_gradient([0.0, 0.0], np.eye(8)[4] * 30)
    B1, _ = calibrated.field_and_gradient([0.0, 0.0], np.eye(8)[4] * 30)
    assert_allclose(B1, 1.03 * B0, rtol=1e-12)
    with pytest.raises(ValueError, match="8 coil gains expected"):
        CalibratedFieldModel(plain, GAINS[:7])
    with pytest.raises(ValueError, match="finite and positive"):
        CalibratedFieldModel(plain, -GAINS)
