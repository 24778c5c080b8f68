"""Reference ("FEA") unit-current field maps: the ground truth the models are fitted to.

The paper fitted COMSOL maps. We compute the equivalent from a numerical model of the
windings with magpylib, and ship the result (``magrun/field/data/reference_maps.npz``) so
nothing is recomputed at run time. Regenerate it with::

    magrun field reference --out magrun/field/data/reference_maps.npz

A lab with its own FEA replaces it with COMSOL exports (:mod:`magrun.field.comsol`).

Winding model
-------------
A coil is a thick solenoid: current density J = N I / (L (b − a)) over the annulus
a ≤ r ≤ b, |z| ≤ L/2 of its own frame. The radial integral is done by Gauss–Legendre
quadrature: ``sheets`` thin cylindrical current sheets at the quadrature radius r_i, each
carrying K_i = J w_i (A/m) with w_i the quadrature weight. A sheet's field is exactly that of
a uniformly magnetised cylinder with polarisation μ0 K_i, which magpylib computes in closed
form, so the model is exact along the axis and converges spectrally in radius (checked against
the closed-form on-axis field of a thick solenoid and against a dense grid of current loops).
Outside the windings,
which is everywhere in the workspace, this is the B-field of the coil.

Gradients are central differences of that closed-form field with a 1 µm step: truncation and
round-off are both below 1e-8 relative at the scale lengths (mm) of these coils.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun import atomic
from magrun.field.coils import LIMIT_KEYS, CoilSystem, CoilTypeSpec
from magrun.yamlio import read_npz, safe_json

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

# magpylib (and scipy.spatial with it) is imported where the maps are computed: two thirds of
# a second of every fresh process's start-up, where the maps are only read

MU0 = 4e-7 * np.pi  # T m / A; magpylib uses the CODATA value, 1e-10 relative difference
DEFAULT_SHEETS = 12
DEFAULT_PITCH = 1e-3  # m
GRADIENT_STEP = 1e-6  # m
FORMAT_VERSION = 1


@dataclass(frozen=True)
class FieldMap:
    """Unit-current (1 A) in-plane field of one coil type on a regular grid, base-stack frame.

    Attributes
    ----------
    x : ndarray, shape (nx,)
        Grid abscissae in metres, strictly increasing.
    y : ndarray, shape (ny,)
        Grid ordinates in metres, strictly increasing.
    B : ndarray, shape (nx, ny, 2)
        (Bx, By) in tesla per ampere at ``(x[i], y[j])``.
    dB : ndarray, shape (nx, ny, 2, 2)
        ``dB[i, j, k, l] = ∂B_k/∂x_l`` in tesla per metre per ampere.
    """

    x: NDArray[np.float64]
    y: NDArray[np.float64]
    B: NDArray[np.float64]
    dB: NDArray[np.float64]

    def __post_init__(self) -> None:
        nx, ny = self.x.size, self.y.size
        if self.B.shape != (nx, ny, 2) or self.dB.shape != (nx, ny, 2, 2):
            raise ValueError(
                f"field map shapes do not match the grid ({nx}, {ny}): "
                f"B {self.B.shape}, dB {self.dB.shape}"
            )
        for name, axis in (("x", self.x), ("y", self.y)):
            if axis.size < 2 or np.any(np.diff(axis) <= 0):
                raise ValueError(f"grid axis {name} must hold >= 2 strictly increasing values")
        if not (np.all(np.isfinite(self.B)) and np.all(np.isfinite(self.dB))):
            raise ValueError("field map holds non-finite values")

    def points(self) -> NDArray[np.float64]:
        """Grid points, shape (nx, ny, 2), metres."""
        X, Y = np.meshgrid(self.x, self.y, indexing="ij")
        return np.stack([X, Y], axis=-1)


@dataclass(frozen=True)
class ReferenceMaps:
    """Unit-current field maps for every coil type, plus provenance metadata."""

    maps: dict[str, FieldMap]
    meta: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, coil_type: str) -> FieldMap:
        try:
            return self.maps[coil_type]
        except KeyError:
            raise KeyError(
                f"no reference map for coil type {coil_type!r} (have {sorted(self.maps)})"
            ) from None

    def require_made_for(self, coils: CoilSystem) -> None:
        """Raise ``ValueError`` if these maps record a coil system other than ``coils``.

        Maps record the coil system they were computed (or imported) for in ``meta["coils"]``;
        only its geometry is compared (drive limits do not change a unit-current map). Maps
        without that record are taken as they are.
        """
        made_for = self.meta.get("coils")
        if (
            made_for is not None
            and {k: v for k, v in made_for.items() if k not in LIMIT_KEYS} != coils.spec.geometry()
        ):
            raise ValueError(
                f"the reference maps were made for another coil system than {coils.source}; "
                "regenerate them with 'magrun field reference --coils ...' (or import them with "
                "'magrun field import-comsol --coils ...')"
            )

    def save(self, path: str | Path) -> None:
        """Write an ``.npz`` file (arrays per coil type, metadata as JSON)."""
        arrays: dict[str, NDArray[Any]] = {
            "meta": np.array(json.dumps({"format_version": FORMAT_VERSION, **self.meta}))
        }
        for name, fmap in self.maps.items():
            arrays[f"{name}.x"], arrays[f"{name}.y"] = fmap.x, fmap.y
            arrays[f"{name}.B"], arrays[f"{name}.dB"] = fmap.B, fmap.dB
        atomic.write_npz(path, arrays)

    @classmethod
    def load(cls, path: str | Path | None = None) -> ReferenceMaps:
        """Read maps written by :meth:`save`; ``None`` reads the maps shipped with magrun."""
        if path is None:
            path = default_reference_path()
        try:
            data = read_npz(path, "magrun field reference")
            meta = safe_json(str(data["meta"]), "its metadata")
            names = sorted({k.split(".")[0] for k in data if k != "meta"})
            maps = {
                n: FieldMap(
                    x=data[f"{n}.x"], y=data[f"{n}.y"], B=data[f"{n}.B"], dB=data[f"{n}.dB"]
                )
                for n in names
            }
        except (KeyError, ValueError) as exc:
            raise ValueError(f"{path}: not a readable magrun reference-map file: {exc}") from exc
        return cls(maps=maps, meta=meta)


def default_reference_path() -> Path:
    """The reference maps shipped in the package data."""
    return Path(__file__).parent / "data" / "reference_maps.npz"


def _base_stack_pose(coil: CoilTypeSpec) -> tuple[tuple[float, float, float], Rotation]:
    # magpylib cylinders have their axis on local +z; turn it onto -y, i.e. pointing from the
    # base-stack coil at (0, center) toward the workspace centre.
    from scipy.spatial.transform import Rotation

    return (0.0, coil.center, 0.0), Rotation.from_rotvec([np.pi / 2, 0.0, 0.0])


def thick_coil_field(
    observers: ArrayLike, coil: CoilTypeSpec, sheets: int = DEFAULT_SHEETS
) -> NDArray[np.float64]:
    """B-field of one base-stack coil carrying 1 A.

    Parameters
    ----------
    observers : array_like, shape (n, 3)
        Points (x, y, z) in metres, workspace frame, outside the winding.
    coil : CoilTypeSpec
        Winding geometry; the coil sits at (0, center, 0) with its axis along -y.
    sheets : int
        Number of radial current sheets the winding is split into.

    Returns
    -------
    ndarray, shape (n, 3)
        B in tesla per ampere.
    """
    import magpylib as mp

    obs = np.atleast_2d(np.asarray(observers, dtype=np.float64))
    a, b = coil.inner_radius, coil.outer_radius
    nodes, weights = np.polynomial.legendre.leggauss(sheets)
    radii = 0.5 * (b - a) * nodes + 0.5 * (b + a)
    widths = 0.5 * (b - a) * weights  # Σ widths = b − a
    density = coil.turns / (coil.length * (b - a))  # A/m² at 1 A
    position, orientation = _base_stack_pose(coil)
    total = np.zeros_like(obs)
    for r, dr in zip(radii, widths, strict=True):
        total += mp.func.cylinder_field(
            "B",
            obs,
            dimensions=(2 * r, coil.length),
            polarizations=(0.0, 0.0, MU0 * density * dr),
            positions=position,
            orientations=orientation,
        )
    return total


def thick_coil_moment(coil: CoilTypeSpec) -> float:
    """Magnetic moment magnitude of the winding at 1 A, A·m² (= Σ turns·π r², uniform density)."""
    a, b = coil.inner_radius, coil.outer_radius
    return float(coil.turns * np.pi * (a * a + a * b + b * b) / 3.0)


def reference_field_map(
    coil: CoilTypeSpec,
    half_width: float,
    pitch: float = DEFAULT_PITCH,
    sheets: int = DEFAULT_SHEETS,
) -> FieldMap:
    """Unit-current map of one coil type on the square grid |x|, |y| ≤ ``half_width``."""
    n = round(2 * half_width / pitch) + 1
    axis = np.linspace(-half_width, half_width, n)
    X, Y = np.meshgrid(axis, axis, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)

    def in_plane(offset: tuple[float, float]) -> NDArray[np.float64]:
        shifted = pts + np.array([offset[0], offset[1], 0.0])
        return thick_coil_field(shifted, coil, sheets)[:, :2].reshape(n, n, 2)

    h = GRADIENT_STEP
    B = in_plane((0.0, 0.0))
    dB = np.empty((n, n, 2, 2))
    dB[..., 0] = (in_plane((h, 0.0)) - in_plane((-h, 0.0))) / (2 * h)
    dB[..., 1] = (in_plane((0.0, h)) - in_plane((0.0, -h))) / (2 * h)
    return FieldMap(x=axis, y=axis.copy(), B=B, dB=dB)


def compute_reference_maps(
    coils: CoilSystem, pitch: float = DEFAULT_PITCH, sheets: int = DEFAULT_SHEETS
) -> ReferenceMaps:
    """Reference maps for every coil type of ``coils`` over its workspace."""
    maps = {
        name: reference_field_map(spec, coils.workspace_half_width, pitch, sheets)
        for name, spec in coils.coil_types.items()
    }
    import magpylib as mp

    meta = {
        "source": "magpylib thick-solenoid current-sheet model (magrun.field.reference)",
        "magpylib_version": mp.__version__,
        "pitch_m": pitch,
        "sheets": sheets,
        "coils": coils.spec.model_dump(mode="json"),
        "units": {"x": "m", "y": "m", "B": "T/A", "dB": "T/(m A)"},
    }
    return ReferenceMaps(maps=maps, meta=meta)
