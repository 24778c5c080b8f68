"""The reference ("FEA") winding model against closed-form physics, and the shipped maps
against that model."""

from __future__ import annotations

import magpylib as mp
import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun.field.coils import CoilSystem
from magrun.field.reference import (
    MU0,
    FieldMap,
    ReferenceMaps,
    reference_field_map,
    thick_coil_field,
    thick_coil_moment,
)


def thick_solenoid_on_axis(coil, distance: np.ndarray) -> np.ndarray:
    """Closed-form axial field of a uniform thick solenoid at ``distance`` from its centre.

    B = μ0 J/2 [z ln((b + √(b²+z²))/(a + √(a²+z²)))] from z = d − L/2 to d + L/2.
    """
    a, b, L = coil.inner_radius, coil.outer_radius, coil.length
    J = coil.turns / (L * (b - a))

    def f(z: np.ndarray) -> np.ndarray:
        return z * np.log((b + np.sqrt(b * b + z * z)) / (a + np.sqrt(a * a + z * z)))

    return MU0 * J / 2 * (f(distance + L / 2) - f(distance - L / 2))


@pytest.mark.parametrize("coil_type", ["small", "medium", "large"])
def test_on_axis_field_matches_closed_form(coils: CoilSystem, coil_type: str) -> None:
    coil = coils.coil_types[coil_type]
    y = np.linspace(-0.05, 0.05, 21)
    B = thick_coil_field(np.column_stack([0 * y, y, 0 * y]), coil)
    expected = thick_solenoid_on_axis(coil, coil.center - y)
    # moment toward the workspace centre: the axial field points along -y
    assert_allclose(-B[:, 1], expected, rtol=1e-9)  # 12-point Gauss–Legendre in radius
    assert_allclose(B[:, [0, 2]], 0.0, atol=1e-15)


def test_far_field_is_a_dipole(coils: CoilSystem) -> None:
    coil = coils.coil_types["large"]
    direction = np.array([[0.3, -0.8, 0.52]])
    obs = 5.0 * direction / np.linalg.norm(direction) + np.array([0, coil.center, 0])
    B = thick_coil_field(obs, coil)
    dip = mp.func.dipole_field(
        "B", obs, moments=(0.0, -thick_coil_moment(coil), 0.0), positions=(0.0, coil.center, 0.0)
    )
    # the next multipole is O((R/r)²) = (0.05/5)² = 1e-4 of the dipole
    assert_allclose(B, np.atleast_2d(dip), rtol=2e-4)


def test_sheets_agree_with_independent_current_loops(coils: CoilSystem) -> None:
    """The current-sheet model against a dense grid of circular loops (magpylib Circle)."""
    coil = coils.coil_types["small"]
    nr, nz = 40, 60
    r = coil.inner_radius + (np.arange(nr) + 0.5) * (coil.outer_radius - coil.inner_radius) / nr
    z = (np.arange(nz) + 0.5) / nz * coil.length - coil.length / 2
    R, Z = np.meshgrid(r, z, indexing="ij")
    # loops lie in planes y = center - z, axis along -y, counter-clockwise seen from the centre
    from scipy.spatial.transform import Rotation

    positions = np.column_stack([0 * R.ravel(), coil.center - Z.ravel(), 0 * R.ravel()])
    rot = Rotation.from_rotvec(np.tile([np.pi / 2, 0, 0], (R.size, 1)))
    rng = np.random.default_rng(1)
    obs = np.column_stack(
        [rng.uniform(-0.05, 0.05, 30), rng.uniform(-0.05, 0.04, 30), np.zeros(30)]
    )
    loops = mp.func.circle_field(
        "B",
        obs[:, None, :].repeat(R.size, 1).reshape(-1, 3),
        diameters=np.tile(2 * R.ravel(), len(obs)),
        currents=coil.turns / R.size,
        positions=np.tile(positions, (len(obs), 1)),
        orientations=Rotation.concatenate([rot] * len(obs)),
    )
    loops = loops.reshape(len(obs), R.size, 3).sum(axis=1)
    sheets = thick_coil_field(obs, coil)
    scale = np.linalg.norm(sheets, axis=1, keepdims=True)
    # the loop grid's own midpoint error in r and z is ~1e-4 relative at these distances
    assert np.all(np.abs(loops - sheets) / scale < 2e-4)


def test_reference_field_is_curl_free_and_obeys_gauss(coils: CoilSystem) -> None:
    coil = coils.coil_types["small"]
    fmap = reference_field_map(coil, half_width=0.05, pitch=5e-3)
    G = fmap.dB
    scale = np.sqrt(np.mean(np.sum(G**2, axis=(-2, -1))))
    curl = G[..., 1, 0] - G[..., 0, 1]
    assert np.max(np.abs(curl)) / scale < 1e-6
    # in-plane divergence is −∂Bz/∂z, not zero: check the 3-D divergence instead
    pts = fmap.points().reshape(-1, 2)
    h = 1e-6

    def Bz(dz: float) -> np.ndarray:
        return thick_coil_field(np.column_stack([pts, np.full(len(pts), dz)]), coil)[:, 2]

    dBz_dz = (Bz(h) - Bz(-h)) / (2 * h)
    div3 = (G[..., 0, 0] + G[..., 1, 1]).ravel() + dBz_dz
    assert np.max(np.abs(div3)) / scale < 1e-6
    assert np.sqrt(np.mean(dBz_dz**2)) / scale > 0.1  # and the planar divergence really is not 0


def test_field_in_the_coil_plane_has_no_z_component(coils: CoilSystem) -> None:
    pts = np.column_stack(
        [np.linspace(-0.05, 0.05, 11), np.linspace(0.05, -0.05, 11), np.zeros(11)]
    )
    for coil in coils.coil_types.values():
        B = thick_coil_field(pts, coil)
        assert np.max(np.abs(B[:, 2])) < 1e-12 * np.max(np.abs(B))


def test_shipped_maps_match_the_shipped_geometry(
    coils: CoilSystem, reference: ReferenceMaps
) -> None:
    assert reference.meta["coils"] == coils.spec.model_dump(mode="json")
    rng = np.random.default_rng(7)
    for name, coil in coils.coil_types.items():
        fmap = reference[name]
        i, j = rng.integers(0, fmap.x.size, 25), rng.integers(0, fmap.y.size, 25)
        obs = np.column_stack([fmap.x[i], fmap.y[j], np.zeros(25)])
        assert_allclose(fmap.B[i, j], thick_coil_field(obs, coil)[:, :2], rtol=1e-12, atol=1e-18)
        # gradient table: central differences of the map itself agree to the grid's O(h²)
        fd = (fmap.B[2:, 1:-1] - fmap.B[:-2, 1:-1]) / (fmap.x[2] - fmap.x[0])
        interior = fmap.dB[1:-1, 1:-1, :, 0]
        far = fmap.points()[1:-1, 1:-1, 1] < 0.03  # away from the small coil's steep near field
        assert np.max(np.abs(fd - interior)[far]) < 1e-2 * np.max(np.abs(interior))


def test_maps_save_and_load_round_trip(tmp_path, coils: CoilSystem) -> None:
    fmap = reference_field_map(coils.coil_types["large"], 0.05, pitch=10e-3)
    maps = ReferenceMaps({"large": fmap}, meta={"source": "test"})
    maps.save(tmp_path / "m.npz")
    back = ReferenceMaps.load(tmp_path / "m.npz")
    assert back.meta["source"] == "test"
    assert_allclose(back["large"].B, fmap.B, rtol=0, atol=0)
    assert_allclose(back["large"].dB, fmap.dB, rtol=0, atol=0)
    with pytest.raises(KeyError, match="no reference map for coil type 'small'"):
        back["small"]
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"bad\.npz"):
        ReferenceMaps.load(tmp_path / "bad.npz")


def test_field_map_validates_shapes() -> None:
    x = np.linspace(0, 1, 3)
    with pytest.raises(ValueError, match="shapes"):
        FieldMap(x=x, y=x, B=np.zeros((3, 2, 2)), dB=np.zeros((3, 3, 2, 2)))
    with pytest.raises(ValueError, match="increasing"):
        FieldMap(x=x[::-1], y=x, B=np.zeros((3, 3, 2)), dB=np.zeros((3, 3, 2, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        FieldMap(x=x, y=x, B=np.full((3, 3, 2), np.nan), dB=np.zeros((3, 3, 2, 2)))


def test_truncated_map_file_is_a_clear_error(tmp_path, reference: ReferenceMaps) -> None:
    reference.save(tmp_path / "full.npz")
    data = (tmp_path / "full.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.npz: not a readable magrun reference-map file"):
        ReferenceMaps.load(tmp_path / "cut.npz")
