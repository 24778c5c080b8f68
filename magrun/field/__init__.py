"""Coil system and magnetic field models (paper, Section II-B).

Data flow::

    coils.yaml ──► CoilSystem ──► reference.py (magpylib windings) ──► reference_maps.npz
                                         │            comsol.py (a lab's COMSOL export) ──┘
                                         ▼
            reference_maps.npz ──► fitting.py ──► zernike_model.json  (ZernikeFieldModel)
                               └──────────────► lut.py               (LookupTableFieldModel)

Both models share :class:`~magrun.field.model.PlanarFieldModel`: unit-current field and
gradient maps per channel, total field for given currents, and CasADi expressions.
"""

from magrun.field.coils import CoilSystem
from magrun.field.lut import LookupTableFieldModel
from magrun.field.model import PlanarFieldModel
from magrun.field.reference import FieldMap, ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel

__all__ = [
    "CoilSystem",
    "FieldMap",
    "LookupTableFieldModel",
    "PlanarFieldModel",
    "ReferenceMaps",
    "ZernikeFieldModel",
]
