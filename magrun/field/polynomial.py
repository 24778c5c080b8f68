"""A polynomial field model re-expressed in its cheapest form: monomials in the workspace frame.

Every coil type's Zernike expansion is a polynomial of degree ``order`` in the disk
coordinates, and those are an affine map of the workspace position; rotating the field into
its stack is linear. So the total field of all channels is one polynomial in (x, y)::

    B_k(p, I) = Σ_{i+j ≤ d} x̃^i ỹ^j a_kij(I),   a_k(I) = C_k I,   (x̃, ỹ) = p / L

with ``C_k`` a (monomials × channels) matrix per field component and L a length scale (the
workspace half width, to keep the monomials of order one). The gradient reuses the same
``a_k``: ``∂B_k/∂x = Σ i x̃^(i−1) ỹ^j a_kij / L``. Evaluated this way the field and gradient
of all 8 channels cost about a thousand multiply-adds, against several thousand for the term
by term Zernike form, and the CasADi expressions (and their derivatives, which an NMPC's
Hessian needs) shrink in proportion.

:meth:`PolynomialField.from_model` recovers ``C`` by least squares on a grid of points; the
fit is exact (a polynomial of degree ≤ d is its own monomial expansion), and it is refused if
the residual says the model is not such a polynomial.

    >>> from magrun.field.zernike import ZernikeFieldModel
    >>> from magrun.field.polynomial import PolynomialField
    >>> poly = PolynomialField.from_model(ZernikeFieldModel.load())
    >>> poly.degree, poly.coefficients.shape
    (9, (2, 55, 8))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.model import PlanarFieldModel

FloatArray = NDArray[np.float64]

#: largest relative residual accepted when recovering the monomial form
EXACTNESS = 1e-9


def exponents(degree: int) -> list[tuple[int, int]]:
    """Monomial exponents (i, j) with i + j ≤ degree, by total degree then falling i."""
    return [(d - j, j) for d in range(degree + 1) for j in range(d + 1)]


def _powers(x: FloatArray, y: FloatArray, degree: int) -> tuple[list[Any], list[Any]]:
    xp, yp = [np.ones_like(x)], [np.ones_like(y)]
    for _ in range(degree):
        xp.append(xp[-1] * x)
        yp.append(yp[-1] * y)
    return xp, yp


def monomials(x: FloatArray, y: FloatArray, degree: int) -> FloatArray:
    """x^i y^j for every exponent pair of :func:`exponents`, shape (..., n_monomials)."""
    xp, yp = _powers(x, y, degree)
    return np.stack([xp[i] * yp[j] for i, j in exponents(degree)], axis=-1)


def monomials_and_derivatives(
    x: FloatArray, y: FloatArray, degree: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`monomials` and their derivatives in x and in y, each (..., n_monomials)."""
    i, j = np.array(exponents(degree)).T
    k = np.arange(degree + 1)
    xp = np.asarray(x, dtype=np.float64)[..., None] ** k  # (..., d + 1)
    yp = np.asarray(y, dtype=np.float64)[..., None] ** k
    xi, yj = xp[..., i], yp[..., j]
    phi = xi * yj
    ddx = i * xp[..., np.maximum(i - 1, 0)] * yj
    ddy = j * xi * yp[..., np.maximum(j - 1, 0)]
    return phi, ddx, ddy


@dataclass(frozen=True)
class PolynomialField:
    """Total in-plane field of all channels as one polynomial (see the module doc).

    Attributes
    ----------
    degree : int
        Highest total degree d.
    scale : float
        Length L, m: the monomials are in (x/L, y/L).
    coefficients : ndarray, shape (2, n_monomials, n_channels)
        ``C[k, t, c]``: T/A per unit of monomial t, field component k, channel c.
    """

    degree: int
    scale: float
    coefficients: FloatArray

    @classmethod
    def from_model(
        cls, model: PlanarFieldModel, degree: int | None = None, scale: float | None = None
    ) -> PolynomialField:
        """The monomial form of a model whose unit fields are polynomials of degree ≤ d.

        ``degree`` defaults to the model's ``polynomial_degree`` attribute (a Zernike model's
        highest order). Raises ``ValueError`` if the model is not such a polynomial.
        """
        d = degree if degree is not None else getattr(model, "polynomial_degree", None)
        if d is None:
            raise ValueError(f"{type(model).__name__} states no polynomial degree")
        L = scale if scale is not None else model.coils.workspace_half_width
        # 3× oversampled tensor grid of Chebyshev points on [−1, 1]²: well conditioned
        n = 3 * (d + 1)
        nodes = np.cos(np.pi * (np.arange(n) + 0.5) / n)
        X, Y = np.meshgrid(nodes, nodes, indexing="ij")
        V = monomials(X.ravel(), Y.ravel(), d)
        # the model's own evaluation (a model may answer unit_field from this very form)
        points = np.column_stack([X.ravel(), Y.ravel()]) * L
        B = PlanarFieldModel.unit_field_and_gradient(model, points)[0]  # (n², ch, 2)
        target = B.transpose(0, 2, 1).reshape(len(V), -1)  # (n², 2·ch)
        coef, *_ = np.linalg.lstsq(V, target, rcond=None)
        residual = np.max(np.abs(V @ coef - target)) / np.max(np.abs(target))
        if residual > EXACTNESS:
            raise ValueError(
                f"the field is not a polynomial of degree {d}: relative residual {residual:.1e}"
            )
        n_ch = B.shape[1]
        C = np.ascontiguousarray(coef.reshape(len(exponents(d)), 2, n_ch).transpose(1, 0, 2))
        return cls(d, float(L), C.astype(np.float64))

    # -- NumPy --------------------------------------------------------------------------------

    def field_and_gradient(
        self, positions: ArrayLike, currents: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """Total field (..., 2) in T and gradient (..., 2, 2) in T/m, as the models return."""
        p = np.asarray(positions, dtype=np.float64) / self.scale
        a = np.einsum("ktc,...c->...kt", self.coefficients, np.asarray(currents, dtype=float))
        phi, dx, dy = monomials_and_derivatives(p[..., 0], p[..., 1], self.degree)
        B = np.einsum("...t,...kt->...k", phi, a)
        G = np.stack(
            [np.einsum("...t,...kt->...k", dx, a), np.einsum("...t,...kt->...k", dy, a)], axis=-1
        )
        return B, G / self.scale

    def unit_field_and_gradient(self, positions: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Every channel at 1 A, as :meth:`PlanarFieldModel.unit_field_and_gradient`:
        B (..., n_channels, 2) in T/A, G (..., n_channels, 2, 2) in T/(m A)."""
        p = np.asarray(positions, dtype=np.float64)
        if p.shape[-1:] != (2,):
            raise ValueError(f"positions must have shape (..., 2), got {p.shape}")
        p = p / self.scale
        phi, dx, dy = monomials_and_derivatives(p[..., 0], p[..., 1], self.degree)
        _, t, c = self.coefficients.shape
        C = self.coefficients.transpose(1, 2, 0).reshape(t, 2 * c)  # [t, (c, k)]
        lead = p.shape[:-1]
        B = (phi @ C).reshape(*lead, c, 2)
        G = np.stack([dx @ C, dy @ C], axis=-1).reshape(*lead, c, 2, 2) / self.scale
        return B, G

    # -- CasADi -------------------------------------------------------------------------------

    def casadi_field_and_gradient(self, position: Any, currents: Any) -> tuple[Any, Any]:
        """Field (2×1) and gradient (2×2) as CasADi expressions, like the models' method."""
        x, y = position[0] / self.scale, position[1] / self.scale
        d = self.degree
        xp: list[Any] = [1, x]
        yp: list[Any] = [1, y]
        for _ in range(d - 1):
            xp.append(xp[-1] * x)
            yp.append(yp[-1] * y)
        terms = exponents(d)
        phi = [xp[i] * yp[j] for i, j in terms]
        dphi_dx = [i * xp[i - 1] * yp[j] if i else 0 for i, j in terms]
        dphi_dy = [j * xp[i] * yp[j - 1] if j else 0 for i, j in terms]
        B, G = [], []
        for k in range(2):
            a = ca.mtimes(ca.DM(self.coefficients[k]), currents)  # (n_monomials,)
            B.append(_dot(phi, a))
            G.append([_dot(dphi_dx, a) / self.scale, _dot(dphi_dy, a) / self.scale])
        return ca.vertcat(*B), ca.blockcat(G)


def _dot(terms: list[Any], a: Any) -> Any:
    acc: Any = 0
    for t, term in enumerate(terms):
        if not (isinstance(term, int) and term == 0):
            acc = acc + term * a[t]
    return acc
