"""Lookup-table field model: the baselines' "FEA look-up tables" (paper, Section II-E).

Field and gradient come from bilinear interpolation of the unit-current reference tables,
the gradient from its own precomputed table (the "precomputed Jacobian matrices" of
Baseline 5), never from differentiating the interpolated field. NumPy evaluation uses
:class:`scipy.interpolate.RegularGridInterpolator` (on an evenly spaced grid, the shipped
one, the same interpolation written out for speed); the CasADi form uses
``casadi.interpolant(..., "linear", ...)`` on the same tables, so both agree to rounding.

Outside the table's grid both extrapolate linearly from the border cells; the tables cover
the whole workspace, so only infeasible iterates of an optimiser ever go there.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray

from magrun.field.coils import CoilSystem
from magrun.field.model import PlanarFieldModel
from magrun.field.reference import FieldMap, ReferenceMaps

if TYPE_CHECKING:
    from scipy.interpolate import RegularGridInterpolator

FloatArray = NDArray[np.float64]

# Table columns per grid point: Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y
_N_OUT = 6


def _table(fmap: FieldMap) -> NDArray[np.float64]:
    return np.concatenate([fmap.B, fmap.dB.reshape(*fmap.dB.shape[:2], 4)], axis=-1)


class _UniformGrid:
    """:class:`RegularGridInterpolator`'s linear interpolation (and linear extrapolation from
    the border cells) on an evenly spaced grid, without its general-grid search: ~10× less
    time for the few points a controller asks for per tick; equal to it to rounding
    (tests/test_models.py)."""

    def __init__(self, x: FloatArray, y: FloatArray, table: FloatArray) -> None:
        self.x0, self.dx, self.y0, self.dy = x[0], x[1] - x[0], y[0], y[1] - y[0]
        self.x, self.y = x, y
        self.table = np.ascontiguousarray(table)
        self.i_max, self.j_max = x.size - 2, y.size - 2

    @classmethod
    def of(cls, x: FloatArray, y: FloatArray, table: FloatArray) -> _UniformGrid | None:
        """The interpolator, or None if the grid is not evenly spaced (to 1e-9 relative)."""
        even = all(np.allclose(np.diff(a), a[1] - a[0], rtol=1e-9, atol=0) for a in (x, y))
        return cls(x, y, table) if even else None

    def __call__(self, q: FloatArray) -> FloatArray:
        fx, fy = (q[:, 0] - self.x0) / self.dx, (q[:, 1] - self.y0) / self.dy
        i = np.clip(np.floor(fx).astype(np.intp), 0, self.i_max)
        j = np.clip(np.floor(fy).astype(np.intp), 0, self.j_max)
        # the position within the cell from its nodes, as scipy's (exact on a node)
        x, y = self.x, self.y
        tx = ((q[:, 0] - x[i]) / (x[i + 1] - x[i]))[:, None]
        ty = ((q[:, 1] - y[j]) / (y[j + 1] - y[j]))[:, None]
        t = self.table
        return (1 - tx) * ((1 - ty) * t[i, j] + ty * t[i, j + 1]) + tx * (
            (1 - ty) * t[i + 1, j] + ty * t[i + 1, j + 1]
        )


def _scipy_grid(x: FloatArray, y: FloatArray, table: FloatArray) -> RegularGridInterpolator:
    """scipy's interpolator for an unevenly spaced grid (imported here: scipy.interpolate is
    half a second of a fresh process's start-up, and evenly spaced grids never need it)."""
    from scipy.interpolate import RegularGridInterpolator

    return RegularGridInterpolator(
        (x, y), table, method="linear", bounds_error=False, fill_value=None
    )


class LookupTableFieldModel(PlanarFieldModel):
    """Bilinear interpolation of reference field and gradient tables."""

    def __init__(self, coils: CoilSystem, reference: ReferenceMaps) -> None:
        super().__init__(coils)
        reference.require_made_for(coils)
        self.reference = reference
        self._numpy: dict[str, RegularGridInterpolator | _UniformGrid] = {}
        self._casadi: dict[str, ca.Function] = {}
        for coil_type in {ch.coil_type for ch in coils.channels} | (
            {"background"} if coils.has_background else set()
        ):
            fmap = reference[coil_type]
            table = _table(fmap)
            self._numpy[coil_type] = _UniformGrid.of(fmap.x, fmap.y, table) or _scipy_grid(
                fmap.x, fmap.y, table
            )
            # CasADi wants the outputs fastest, then x, then y
            self._casadi[coil_type] = ca.interpolant(
                f"lut_{coil_type}", "linear", [fmap.x, fmap.y], table.transpose(1, 0, 2).ravel()
            )

    @classmethod
    def load(
        cls,
        coils: CoilSystem | None = None,
        path: str | Path | None = None,
        system: str | Path | None = None,
    ) -> LookupTableFieldModel:
        """The model on the shipped reference maps (or ``path``) for ``coils`` (default rig);
        or on a system folder's maps (``system``, ``magrun field import-mpem``)."""
        if system is not None:
            coils = CoilSystem.load(system)
        coils = coils or CoilSystem.load()
        return cls(coils, ReferenceMaps.load(path if path is not None else coils.maps_path))

    def type_field(
        self, coil_type: str, q: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        out = self._numpy[coil_type](q)
        return out[:, :2], out[:, 2:].reshape(-1, 2, 2)

    def type_field_casadi(
        self, coil_type: str, qx: Any, qy: Any
    ) -> tuple[list[Any], list[list[Any]]]:
        out = self._casadi[coil_type](ca.vertcat(qx, qy))
        return [out[0], out[1]], [[out[2], out[3]], [out[4], out[5]]]
