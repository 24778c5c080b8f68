"""Lookup-table field model: the baselines' "FEA look-up tables" (paper, Section II-E).

Field and gradient come from bilinear interpolation of the unit-current reference tables,
the gradient from its own precomputed table (the "precomputed Jacobian matrices" of
Baseline 5), never from differentiating the interpolated field. NumPy evaluation uses
:class:`scipy.interpolate.RegularGridInterpolator`; the CasADi form uses
``casadi.interpolant(..., "linear", ...)`` on the same tables, so both agree to rounding.

Outside the table's grid both extrapolate linearly from the border cells; the tables cover
the whole workspace, so only infeasible iterates of an optimiser ever go there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RegularGridInterpolator

from magrun.field.coils import CoilSystem
from magrun.field.model import PlanarFieldModel
from magrun.field.reference import FieldMap, ReferenceMaps

# Table columns per grid point: Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y
_N_OUT = 6


def _table(fmap: FieldMap) -> NDArray[np.float64]:
    return np.concatenate([fmap.B, fmap.dB.reshape(*fmap.dB.shape[:2], 4)], axis=-1)


class LookupTableFieldModel(PlanarFieldModel):
    """Bilinear interpolation of reference field and gradient tables."""

    def __init__(self, coils: CoilSystem, reference: ReferenceMaps) -> None:
        super().__init__(coils)
        reference.require_made_for(coils)
        self.reference = reference
        self._numpy: dict[str, RegularGridInterpolator] = {}
        self._casadi: dict[str, ca.Function] = {}
        for coil_type in {ch.coil_type for ch in coils.channels}:
            fmap = reference[coil_type]
            table = _table(fmap)
            self._numpy[coil_type] = RegularGridInterpolator(
                (fmap.x, fmap.y), table, method="linear", bounds_error=False, fill_value=None
            )
            # CasADi wants the outputs fastest, then x, then y
            self._casadi[coil_type] = ca.interpolant(
                f"lut_{coil_type}", "linear", [fmap.x, fmap.y], table.transpose(1, 0, 2).ravel()
            )

    @classmethod
    def load(
        cls, coils: CoilSystem | None = None, path: str | Path | None = None
    ) -> LookupTableFieldModel:
        """The model on the shipped reference maps (or ``path``) for ``coils`` (default rig)."""
        return cls(coils or CoilSystem.load(), ReferenceMaps.load(path))

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
