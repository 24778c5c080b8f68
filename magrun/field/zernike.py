"""Zernike polynomials in Cartesian form, their analytic gradients, and least-squares fits.

The paper (Section II-B, Table I) expands each in-plane field component of a coil in Zernike
polynomials on a scaled, shifted disk centred on the coil. Terms are in the Wyant / University
of Arizona "fringe" order, counted from 0 and not normalised (R_n^m(1) = 1)::

    #   n  m   Z
    0   0  0   1
    1   1  1   x
    2   1 -1   y
    3   2  0   2(x² + y²) − 1
    4   2  2   x² − y²
    5   2 -2   2xy
    6   3  1   (3(x² + y²) − 2) x
    ...

A negative m marks the sine ("odd") member of a pair. ``order`` is the highest radial degree
n; a model of order N holds every term with n ≤ N, kept in fringe order ((N+1)(N+2)/2 terms).

Every polynomial is evaluated as ``P(x² + y²) · Re/Im((x + iy)^|m|)`` with P the radial
polynomial divided by ρ^|m|, so values and gradients are plain sums and products. The same
code therefore builds NumPy arrays and CasADi expressions (SX or MX) from one definition.

    >>> import numpy as np
    >>> from magrun.field import zernike
    >>> zernike.basis(np.array([0.5]), np.array([0.25]), order=2).round(4)
    array([[ 1.    ,  0.5   ,  0.25  , -0.375 ,  0.1875,  0.25  ]])
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cache, cached_property
from math import factorial
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun import atomic
from magrun.field.coils import CoilSystem, CoilSystemSpec, MapSystemSpec
from magrun.field.model import PlanarFieldModel, weighted_sum
from magrun.field.polynomial import PolynomialField
from magrun.yamlio import read_text_file, safe_json


@dataclass(frozen=True)
class ZernikeTerm:
    """One fringe-ordered Zernike polynomial: index, radial degree n, signed frequency m."""

    index: int
    n: int
    m: int

    @property
    def radial_coefficients(self) -> tuple[int, ...]:
        """Coefficients c_k of R_n^|m|(ρ) = Σ_k c_k ρ^(n−2k), k = 0 … (n−|m|)/2."""
        return _radial_coefficients(self.n, abs(self.m))


@cache
def _radial_coefficients(n: int, m: int) -> tuple[int, ...]:
    return tuple(
        (-1) ** k
        * factorial(n - k)
        // (factorial(k) * factorial((n + m) // 2 - k) * factorial((n - m) // 2 - k))
        for k in range((n - m) // 2 + 1)
    )


@cache
def fringe_terms(order: int) -> tuple[ZernikeTerm, ...]:
    """Terms with radial degree n ≤ ``order``, in fringe order.

    Fringe group j = (n + |m|)/2 holds, for |m| = j … 0, the cosine then the sine member, so
    group j starts at index j².
    """
    if order < 0:
        raise ValueError(f"order must be >= 0, got {order}")
    terms = []
    for j in range(order + 1):
        index = j * j
        for m in range(j, -1, -1):
            n = 2 * j - m
            for signed_m in (m, -m) if m > 0 else (0,):
                if n <= order:
                    terms.append(ZernikeTerm(index=index, n=n, m=signed_m))
                index += 1
    return tuple(terms)


def n_terms(order: int) -> int:
    """Number of terms of a model of radial degree ``order``: (order+1)(order+2)/2."""
    return (order + 1) * (order + 2) // 2


def _horner(coeffs: tuple[int, ...], s: Any) -> Any:
    # Σ coeffs[k] s^(K−k), highest power first
    acc: Any = coeffs[0]
    for c in coeffs[1:]:
        acc = acc * s + c
    return acc


def generic_terms(
    x: Any, y: Any, order: int, gradient: bool
) -> tuple[list[Any], list[Any], list[Any]]:
    """Values (and d/dx, d/dy) of every term, built from +, − and × only.

    Works on NumPy arrays, Python floats and CasADi symbols alike. Constant terms come back
    as Python numbers; the typed wrappers :func:`basis` and :func:`basis_gradient` broadcast.
    """
    s = x * x + y * y
    # (x + iy)^m = C[m] + i S[m]
    C: list[Any] = [1]
    S: list[Any] = [0]
    for _ in range(order):
        c, sn = C[-1], S[-1]
        C.append(c * x - sn * y)
        S.append(c * y + sn * x)
    values, ddx, ddy = [], [], []
    for term in fringe_terms(order):
        m = abs(term.m)
        coeffs = term.radial_coefficients  # R_n^m(ρ)/ρ^m = P(s), degree (n−m)/2 in s
        P = _horner(coeffs, s)
        angular = C[m] if term.m >= 0 else S[m]  # ρ^m cos(mφ) or ρ^m sin(mφ)
        values.append(P * angular)
        if not gradient:
            continue
        K = len(coeffs) - 1
        dP = _horner(tuple(c * (K - k) for k, c in enumerate(coeffs[:-1])), s) if K > 0 else 0
        # d(x+iy)^m/dx = m (x+iy)^(m−1);  d/dy = i m (x+iy)^(m−1)
        if m == 0:
            da_dx: Any = 0
            da_dy: Any = 0
        elif term.m > 0:
            da_dx, da_dy = m * C[m - 1], -m * S[m - 1]
        else:
            da_dx, da_dy = m * S[m - 1], m * C[m - 1]
        ddx.append(dP * 2 * x * angular + P * da_dx)
        ddy.append(dP * 2 * y * angular + P * da_dy)
    return values, ddx, ddy


def basis(x: ArrayLike, y: ArrayLike, order: int) -> NDArray[np.float64]:
    """Zernike basis at points on the unit disk.

    Parameters
    ----------
    x, y : array_like, broadcastable shapes (...)
        Normalised disk coordinates (dimensionless, x² + y² ≤ 1 inside the disk).
    order : int
        Highest radial degree n included.

    Returns
    -------
    ndarray, shape (..., n_terms(order))
        Term values in fringe order.
    """
    xa, ya = _as_arrays(x, y)
    values, _, _ = generic_terms(xa, ya, order, gradient=False)
    return _stack_terms(values, xa.shape)


def basis_gradient(x: ArrayLike, y: ArrayLike, order: int) -> NDArray[np.float64]:
    """Analytic gradient of :func:`basis`.

    Returns
    -------
    ndarray, shape (..., n_terms(order), 2)
        ``[..., k, 0] = ∂Z_k/∂x`` and ``[..., k, 1] = ∂Z_k/∂y`` in normalised coordinates
        (divide by the disk radius for physical units).
    """
    return basis_and_gradient(x, y, order)[1]


def basis_and_gradient(
    x: ArrayLike, y: ArrayLike, order: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`basis` and :func:`basis_gradient` from one pass over the terms."""
    xa, ya = _as_arrays(x, y)
    vals, ddx, ddy = generic_terms(xa, ya, order, gradient=True)
    gradient = np.stack([_stack_terms(ddx, xa.shape), _stack_terms(ddy, xa.shape)], axis=-1)
    return _stack_terms(vals, xa.shape), gradient


def _as_arrays(x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    xa, ya = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    return xa, ya


def _stack_terms(terms: list[Any], shape: tuple[int, ...]) -> NDArray[np.float64]:
    # constant terms come back from generic_terms as Python numbers: broadcast them
    return np.stack([np.broadcast_to(v, shape) for v in terms], axis=-1)


@dataclass(frozen=True)
class LeastSquaresFit:
    """Result of :func:`fit`: coefficients and the design matrix's conditioning."""

    coefficients: NDArray[np.float64]  # (n_terms, k)
    rank: int
    condition_number: float


def fit(x: ArrayLike, y: ArrayLike, values: ArrayLike, order: int) -> LeastSquaresFit:
    """Least-squares Zernike coefficients of sampled data.

    Parameters
    ----------
    x, y : array_like, shape (n,)
        Sample points in normalised disk coordinates.
    values : array_like, shape (n,) or (n, k)
        Samples of one or k functions.
    order : int
        Highest radial degree n of the model.

    Returns
    -------
    LeastSquaresFit
        ``coefficients`` has shape (n_terms, k) (k = 1 for 1-D ``values``).

    Raises
    ------
    ValueError
        If there are fewer samples than terms, or the samples do not determine every term.
    """
    A = basis(np.ravel(x), np.ravel(y), order)
    v = np.asarray(values, dtype=np.float64)
    v = v.reshape(len(v), -1)
    if A.shape[0] != v.shape[0]:
        raise ValueError(f"{A.shape[0]} sample points but {v.shape[0]} values")
    if A.shape[0] < A.shape[1]:
        raise ValueError(f"{A.shape[0]} samples cannot determine {A.shape[1]} terms")
    coef, _, rank, sv = np.linalg.lstsq(A, v, rcond=None)
    if rank < A.shape[1]:
        raise ValueError(f"samples determine only {rank} of {A.shape[1]} Zernike terms")
    return LeastSquaresFit(
        coefficients=np.asarray(coef, dtype=np.float64),
        rank=int(rank),
        condition_number=float(sv[0] / sv[-1]),
    )


# --------------------------------------------------------------------------------------------
# The field model: one Zernike expansion of (Bx, By) per coil type
# --------------------------------------------------------------------------------------------

MODEL_FORMAT_VERSION = 1


@dataclass(frozen=True)
class ZernikeCoilFit:
    """Zernike expansion of one coil type's unit-current field, base-stack frame.

    ``B(q) = Σ_t coefficients[t] Z_t((q − center)/disk_radius)`` with q in metres.
    """

    coil_type: str
    order: int
    center: tuple[float, float]  # disk centre, m
    disk_radius: float  # m
    coefficients: NDArray[np.float64]  # (n_terms(order), 2), T/A, columns Bx, By

    def __post_init__(self) -> None:
        if self.coefficients.shape != (n_terms(self.order), 2):
            raise ValueError(
                f"{self.coil_type}: order {self.order} needs coefficients of shape "
                f"({n_terms(self.order)}, 2), got {self.coefficients.shape}"
            )

    def normalise(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return (q[..., 0] - self.center[0]) / self.disk_radius, (
            q[..., 1] - self.center[1]
        ) / self.disk_radius

    def field(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """Field (n, 2) in T/A at base-frame points (n, 2)."""
        u, v = self.normalise(q)
        return basis(u, v, self.order) @ self.coefficients

    def evaluate(self, q: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Field (n, 2) in T/A and gradient (n, 2, 2) in T/(m A) at base-frame points (n, 2)."""
        u, v = self.normalise(q)
        Z, dZ = basis_and_gradient(u, v, self.order)
        B = Z @ self.coefficients
        G = np.einsum("ntl,tk->nkl", dZ, self.coefficients)
        return B, G / self.disk_radius

    def evaluate_casadi(self, qx: Any, qy: Any) -> tuple[list[Any], list[list[Any]]]:
        u = (qx - self.center[0]) / self.disk_radius
        v = (qy - self.center[1]) / self.disk_radius
        vals, ddx, ddy = generic_terms(u, v, self.order, gradient=True)
        coef = self.coefficients
        B = [weighted_sum(coef[:, k], vals) for k in range(2)]
        G = [[weighted_sum(coef[:, k], d) / self.disk_radius for d in (ddx, ddy)] for k in range(2)]
        return B, G


class ZernikeFieldModel(PlanarFieldModel):
    """The paper's field model: analytic Zernike expansions, NumPy and CasADi from one source.

    >>> from magrun.field.zernike import ZernikeFieldModel
    >>> model = ZernikeFieldModel.load()          # shipped fit of the shipped reference
    >>> B, G = model.field_and_gradient([0.0, 0.01], currents=[1, 0, 0, 0, 0, 0, 0, 0])
    """

    def __init__(self, coils: CoilSystem, fits: dict[str, ZernikeCoilFit]) -> None:
        super().__init__(coils)
        missing = {ch.coil_type for ch in coils.channels} - set(fits)
        if coils.has_background and "background" not in fits:
            missing.add("background")
        if missing:
            raise ValueError(f"no Zernike fit for driven coil types {sorted(missing)}")
        self.fits = fits

    @property
    def polynomial_degree(self) -> int:
        """Highest total degree in x, y of the driven channels' fields (the highest order)."""
        return max(self.fits[ch.coil_type].order for ch in self.coils.channels)

    @cached_property
    def polynomial(self) -> PolynomialField:
        """The same model as one polynomial in the workspace frame (:mod:`.polynomial`)."""
        return PolynomialField.from_model(self)

    def unit_field_and_gradient(
        self, positions: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """From :attr:`polynomial` (faster than term by term: BENCHMARKS.md); the two agree
        to rounding (tests/test_nmpc.py). Term by term: :meth:`unit_field_and_gradient_terms`."""
        return self.polynomial.unit_field_and_gradient(positions)

    def unit_field_and_gradient_terms(
        self, positions: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Every channel's field and gradient summed term by term over Zernike polynomials."""
        return super().unit_field_and_gradient(positions)

    def casadi_field_and_gradient(self, position: Any, currents: Any) -> tuple[Any, Any]:
        """The CasADi form from :attr:`polynomial`, the cheapest to evaluate and differentiate.

        The term-by-term form remains :meth:`casadi_field_and_gradient_terms`; the two agree to
        rounding (tests/test_nmpc.py).
        """
        B, G = self.polynomial.casadi_field_and_gradient(position, currents)
        if not self.coils.has_background:
            return B, G
        B0, G0 = self.casadi_background(position[0], position[1])
        return B + ca.vertcat(*B0), G + ca.blockcat(G0)

    def casadi_field_and_gradient_terms(self, position: Any, currents: Any) -> tuple[Any, Any]:
        """The CasADi form summed term by term over Zernike polynomials and channels."""
        return super().casadi_field_and_gradient(position, currents)

    def type_field(
        self, coil_type: str, q: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return self.fits[coil_type].evaluate(q)

    def type_field_casadi(
        self, coil_type: str, qx: Any, qy: Any
    ) -> tuple[list[Any], list[list[Any]]]:
        return self.fits[coil_type].evaluate_casadi(qx, qy)

    def to_json(self) -> dict[str, Any]:
        return {
            "format_version": MODEL_FORMAT_VERSION,
            "basis": "Zernike, fringe order, unnormalised, on the disk (q - center) / disk_radius",
            "units": {"center": "m", "disk_radius": "m", "coefficients": "T/A"},
            "coils": self.coils.spec.model_dump(mode="json"),
            "coil_types": {
                name: {
                    "order": f.order,
                    "center": list(f.center),
                    "disk_radius": f.disk_radius,
                    "terms": [[t.index, t.n, t.m] for t in fringe_terms(f.order)],
                    "bx": f.coefficients[:, 0].tolist(),
                    "by": f.coefficients[:, 1].tolist(),
                }
                for name, f in self.fits.items()
            },
        }

    def save(self, path: str | Path) -> None:
        """Write the model as JSON (atomically)."""
        atomic.write_text(path, json.dumps(self.to_json(), indent=1) + "\n")

    @classmethod
    def load(
        cls, path: str | Path | None = None, system: str | Path | None = None
    ) -> ZernikeFieldModel:
        """Read a model written by :meth:`save`; ``None`` reads the one shipped with magrun.

        ``system``: a system folder (``magrun field import-mpem``): its fitted model
        (``zernike_model.json``, which the import writes and ``magrun field fit --system``
        writes again with other options).
        """
        if system is not None:
            return cls.of_system(CoilSystem.load(system))
        path = Path(path) if path is not None else default_model_path()
        try:
            doc = safe_json(read_text_file(path), "")
            if not isinstance(doc, dict):
                raise ValueError("not a JSON object")
            if doc.get("format_version") != MODEL_FORMAT_VERSION:
                raise ValueError(f"unsupported format_version {doc.get('format_version')!r}")
            kind = MapSystemSpec if doc["coils"].get("kind") == "maps" else CoilSystemSpec
            coils = CoilSystem(
                spec=kind.model_validate(doc["coils"]), source=str(path),
                folder=path.parent if kind is MapSystemSpec else None,
            )  # fmt: skip
            fits = {
                name: ZernikeCoilFit(
                    coil_type=name,
                    order=int(d["order"]),
                    center=(float(d["center"][0]), float(d["center"][1])),
                    disk_radius=float(d["disk_radius"]),
                    coefficients=np.column_stack([d["bx"], d["by"]]).astype(np.float64),
                )
                for name, d in doc["coil_types"].items()
            }
        except (OSError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable magrun Zernike model: {exc}") from exc
        return cls(coils, fits)

    @classmethod
    def of_system(cls, coils: CoilSystem) -> ZernikeFieldModel:
        """The model fitted to a system's folder (``zernike_model.json``), with ``coils``
        and so their limits; the shipped model where ``coils`` has no folder."""
        if coils.folder is None:
            return cls.load()
        saved = coils.folder / SYSTEM_MODEL_FILE
        if not saved.is_file():
            raise ValueError(
                f"{coils.folder}: no {SYSTEM_MODEL_FILE}; fit one with "
                f"'magrun field fit --system {coils.folder}'"
            )
        model = cls.load(saved)
        if model.coils.spec.geometry() != coils.spec.geometry():
            raise ValueError(
                f"{saved} was fitted to another system than {coils.source}: fit it again "
                f"with 'magrun field fit --system {coils.folder} --overwrite'"
            )
        return cls(coils, model.fits)  # the folder's limits, which a fit does not fix


#: a system folder's fitted model (magrun.field.fitting writes it under this name)
SYSTEM_MODEL_FILE = "zernike_model.json"


def default_model_path() -> Path:
    """The Zernike model shipped in the package data."""
    return Path(__file__).parent / "data" / "zernike_model.json"
