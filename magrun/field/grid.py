"""The simulated plant's field: dense world-frame tables of every channel, read bilinearly.

A campaign integrates millions of 1 ms plant steps, so the plant must not evaluate a
Biot–Savart sum (or even a SciPy interpolator, ~50 µs a call) per step. :class:`ChannelGrid`
rotates the reference ("FEA") maps into the workspace frame once, storing for every grid node
and channel ``(Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y)`` per ampere, and
:meth:`ChannelGrid.field` reads one point with a 2×2 gather: a few microseconds.

    >>> from magrun.field.grid import ChannelGrid
    >>> grid = ChannelGrid.load()
    >>> B, G = grid.field(0.0, 0.0, currents)   # doctest: +SKIP

Outside the grid the border cells are extrapolated linearly (the plant keeps the robot inside
the workspace walls, so this only matters for the wall contact itself).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.coils import CoilSystem
from magrun.field.lut import LookupTableFieldModel
from magrun.field.reference import ReferenceMaps

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ChannelGrid:
    """Per-channel unit-current field tables on a regular grid in the workspace frame.

    Attributes
    ----------
    x0, y0 : float
        First grid node, m.
    step : float
        Grid spacing, m (equal in x and y).
    table : ndarray, shape (nx, ny, n_channels, 6)
        ``(Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y)`` per ampere, T/A and T/(m A).
    channel_names : tuple of str
    """

    x0: float
    y0: float
    step: float
    table: FloatArray
    channel_names: tuple[str, ...]

    @classmethod
    def from_reference(cls, coils: CoilSystem, reference: ReferenceMaps) -> ChannelGrid:
        """Tabulate ``coils``' channels on the grid of the reference maps."""
        lut = LookupTableFieldModel(coils, reference)
        fmap = next(iter(reference.maps.values()))
        step = float(fmap.x[1] - fmap.x[0])
        if not np.allclose(np.diff(fmap.x), step) or not np.allclose(np.diff(fmap.y), step):
            raise ValueError("ChannelGrid needs reference maps on a regular square grid")
        X, Y = np.meshgrid(fmap.x, fmap.y, indexing="ij")
        B, G = lut.unit_field_and_gradient(np.stack([X, Y], axis=-1))
        table = np.concatenate([B, G.reshape(*G.shape[:-2], 4)], axis=-1)
        return cls(
            x0=float(fmap.x[0]),
            y0=float(fmap.y[0]),
            step=step,
            table=np.ascontiguousarray(table),
            channel_names=coils.channel_names,
        )

    @classmethod
    def load(
        cls, coils: CoilSystem | None = None, reference: str | Path | None = None
    ) -> ChannelGrid:
        """The grid of the shipped (or given) reference maps for ``coils`` (default rig)."""
        return cls.from_reference(coils or CoilSystem.load(), ReferenceMaps.load(reference))

    def unit(self, x: float, y: float) -> FloatArray:
        """Bilinear values of every channel at (x, y) m: shape (n_channels, 6)."""
        nx, ny = self.table.shape[:2]
        fx, fy = (x - self.x0) / self.step, (y - self.y0) / self.step
        i = min(max(math.floor(fx), 0), nx - 2)
        j = min(max(math.floor(fy), 0), ny - 2)
        tx, ty = fx - i, fy - j
        c = self.table[i : i + 2, j : j + 2]
        return (1 - tx) * ((1 - ty) * c[0, 0] + ty * c[0, 1]) + tx * (
            (1 - ty) * c[1, 0] + ty * c[1, 1]
        )

    def held(self, currents: ArrayLike) -> HeldField:
        """A reader of the total field for ``currents`` (A) held, in Python floats (below)."""
        return HeldField(self, np.asarray(currents, dtype=np.float64))

    def field(self, x: float, y: float, currents: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Total field (2,) in T and gradient (2, 2) in T/m at (x, y) for ``currents`` in A."""
        v = np.asarray(currents, dtype=np.float64) @ self.unit(x, y)
        return v[:2], v[2:].reshape(2, 2)


class HeldField:
    """The total field of :class:`ChannelGrid` for one set of held currents, as Python floats.

    The plant reads the field once per 1 ms sub-step, and the currents stay the same over a
    control period: each grid cell's four corners are contracted with the currents once, when
    the robot first enters the cell, so a read is a bilinear blend of six numbers (~2 µs
    against ~12 µs for :meth:`ChannelGrid.unit` and the product). The result equals
    ``currents @ grid.unit(x, y)`` to rounding (tests/test_sim.py).
    """

    def __init__(self, grid: ChannelGrid, currents: FloatArray) -> None:
        self.grid = grid
        self.currents = currents
        self._cells: dict[tuple[int, int], list[list[list[float]]]] = {}

    def __call__(self, x: float, y: float) -> tuple[list[float], tuple[list[float], list[float]]]:
        """``(B, G)`` at (x, y) m: B = [Bx, By] in T, G = ([∂Bx/∂x, ∂Bx/∂y], [∂By/∂x, ∂By/∂y])
        in T/m, the nested form :func:`magrun.robot.discrete_step` takes."""
        g = self.grid
        nx, ny = g.table.shape[:2]
        fx, fy = (x - g.x0) / g.step, (y - g.y0) / g.step
        i = min(max(math.floor(fx), 0), nx - 2)
        j = min(max(math.floor(fy), 0), ny - 2)
        tx, ty = fx - i, fy - j
        cell = self._cells.get((i, j))
        if cell is None:
            corners = np.einsum("c,abcv->abv", self.currents, g.table[i : i + 2, j : j + 2])
            cell = self._cells[(i, j)] = corners.reshape(4, 6).tolist()
        c00, c01, c10, c11 = cell
        sx, sy = 1 - tx, 1 - ty
        v = [
            sx * (sy * a + ty * b) + tx * (sy * c + ty * d)
            for a, b, c, d in zip(c00, c01, c10, c11, strict=True)
        ]
        return v[:2], (v[2:4], v[4:6])
