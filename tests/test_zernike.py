"""Zernike basis: values against the paper's Table I and the radial formula, analytic
gradients against finite differences, and least-squares recovery of known coefficients."""

from __future__ import annotations

from math import factorial

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun.field import zernike


def disk_points(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    r = np.sqrt(rng.uniform(0, 1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    return r * np.cos(phi), r * np.sin(phi)


def test_first_terms_match_table_one_and_wyant(rng: np.random.Generator) -> None:
    x, y = disk_points(rng, 50)
    r2 = x**2 + y**2
    expected = np.stack(
        [
            np.ones_like(x),
            x,
            y,
            2 * r2 - 1,
            x**2 - y**2,
            2 * x * y,  # Table I
            (3 * r2 - 2) * x,
            (3 * r2 - 2) * y,
            6 * r2**2 - 6 * r2 + 1,  # Wyant Z6-Z8
        ],
        axis=-1,
    )
    got = zernike.basis(x, y, order=4)
    # order 4 in fringe order: Z0..Z8, then Z9..Z12 (n=3,4), then Z16, Z17 (n=4, m=4)
    assert_allclose(got[:, :9], expected, rtol=0, atol=1e-14)
    assert_allclose(got[:, 9], x**3 - 3 * x * y**2, atol=1e-14)  # Z9 = ρ³cos3φ
    assert_allclose(got[:, 14], 4 * x * y * (x**2 - y**2), atol=1e-14)  # Z17 = ρ⁴sin4φ


def test_fringe_order_indices() -> None:
    # Wyant's fringe list, Z0..Z15: (n, m) with m < 0 for the sine member
    fringe16 = [
        (0, 0),
        (1, 1),
        (1, -1),
        (2, 0),
        (2, 2),
        (2, -2),
        (3, 1),
        (3, -1),
        (4, 0),
        (3, 3),
        (3, -3),
        (4, 2),
        (4, -2),
        (5, 1),
        (5, -1),
        (6, 0),
    ]
    terms = zernike.fringe_terms(6)
    by_index = {t.index: (t.n, t.m) for t in terms}
    assert [by_index[i] for i in range(16)] == fringe16
    for order in range(9):
        terms = zernike.fringe_terms(order)
        assert len(terms) == zernike.n_terms(order) == (order + 1) * (order + 2) // 2
        assert all(t.n <= order for t in terms)
        assert [t.index for t in terms] == sorted(t.index for t in terms)
    with pytest.raises(ValueError, match="order"):
        zernike.fringe_terms(-1)


def radial_reference(n: int, m: int, rho: np.ndarray) -> np.ndarray:
    """The paper's Eq. (3), summed term by term in polar form."""
    total = np.zeros_like(rho)
    for k in range((n - m) // 2 + 1):
        c = (
            (-1) ** k
            * factorial(n - k)
            / (factorial(k) * factorial((n + m) // 2 - k) * factorial((n - m) // 2 - k))
        )
        total += c * rho ** (n - 2 * k)
    return total


def test_all_terms_match_polar_definition(rng: np.random.Generator) -> None:
    x, y = disk_points(rng, 200)
    rho, phi = np.hypot(x, y), np.arctan2(y, x)
    order = 10
    got = zernike.basis(x, y, order)
    for k, t in enumerate(zernike.fringe_terms(order)):
        m = abs(t.m)
        angular = np.cos(m * phi) if t.m >= 0 else np.sin(m * phi)
        assert_allclose(
            got[:, k],
            radial_reference(t.n, m, rho) * angular,
            atol=1e-12,
            err_msg=f"Z{t.index} (n={t.n}, m={t.m})",
        )
    # unnormalised: R_n^m(1) = 1
    edge = zernike.basis(np.array([1.0]), np.array([0.0]), order)[0]
    cos_terms = [k for k, t in enumerate(zernike.fringe_terms(order)) if t.m >= 0]
    assert_allclose(edge[cos_terms], 1.0, atol=1e-12)


def test_gradient_matches_central_differences(rng: np.random.Generator) -> None:
    x, y = disk_points(rng, 100)
    order, h = 10, 1e-6
    grad = zernike.basis_gradient(x, y, order)
    fd_x = (zernike.basis(x + h, y, order) - zernike.basis(x - h, y, order)) / (2 * h)
    fd_y = (zernike.basis(x, y + h, order) - zernike.basis(x, y - h, order)) / (2 * h)
    # truncation ~h²·|Z'''| ≲ 1e-8 for these degrees; round-off ~1e-16/h = 1e-10
    assert_allclose(grad[..., 0], fd_x, rtol=0, atol=1e-7)
    assert_allclose(grad[..., 1], fd_y, rtol=0, atol=1e-7)


def test_shapes_broadcast() -> None:
    x = np.zeros((4, 3))
    assert zernike.basis(x, 0.5, 3).shape == (4, 3, 10)
    assert zernike.basis_gradient(x, 0.5, 3).shape == (4, 3, 10, 2)


def test_fit_recovers_known_coefficients_exactly(rng: np.random.Generator) -> None:
    order = 6
    truth = rng.normal(size=(zernike.n_terms(order), 2))
    g = np.linspace(-0.7, 0.7, 30)  # a square inside the disk, as the workspace is
    X, Y = np.meshgrid(g, g, indexing="ij")
    values = zernike.basis(X.ravel(), Y.ravel(), order) @ truth
    result = zernike.fit(X.ravel(), Y.ravel(), values, order)
    assert result.rank == zernike.n_terms(order)
    assert_allclose(result.coefficients, truth, rtol=0, atol=1e-9)


def test_fit_rejects_undetermined_problems() -> None:
    with pytest.raises(ValueError, match="cannot determine"):
        zernike.fit([0.1, 0.2], [0.0, 0.1], [1.0, 2.0], order=2)
    line = np.linspace(-0.5, 0.5, 50)  # points on one line cannot separate x from y terms
    with pytest.raises(ValueError, match="determine only"):
        zernike.fit(line, line, line, order=2)
