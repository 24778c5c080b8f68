"""The simulated plant's field: dense world-frame tables of every channel, read bilinearly.

A campaign integrates millions of 1 ms plant steps, so the plant must not evaluate a
Biot–Savart sum (or even a SciPy interpolator) per step. :class:`ChannelGrid`
rotates the reference ("FEA") maps into the workspace frame once, storing for every grid node
and channel ``(Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y)`` per ampere, and
:meth:`ChannelGrid.field` reads one point with a 2×2 gather: a few microseconds. The plant
reads through :class:`GridCells`, which keeps each visited cell's corners (and, for held
currents, their contraction with the currents: :class:`HeldField`); the compiled plant
(:mod:`magrun.rigs.kernel`) reads :attr:`ChannelGrid.table` itself.

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
    table : ndarray, shape (nx, ny, n_channels (+ 1), 6)
        ``(Bx, By, ∂Bx/∂x, ∂Bx/∂y, ∂By/∂x, ∂By/∂y)`` per ampere, T/A and T/(m A); with a
        background, its field (T, T/m) is one more column, read at a "current" of 1
        (:meth:`inputs`).
    channel_names : tuple of str
    background : bool
        Whether the last column is a background field.
    """

    x0: float
    y0: float
    step: float
    table: FloatArray
    channel_names: tuple[str, ...]
    background: bool = False

    def inputs(self, currents: ArrayLike) -> FloatArray:
        """What the table is contracted with: ``currents`` (..., n_channels) A, and a 1 for
        the background where there is one."""
        I = np.asarray(currents, dtype=np.float64)
        if not self.background:
            return I
        return np.concatenate([I, np.ones((*I.shape[:-1], 1))], axis=-1)

    @classmethod
    def from_reference(cls, coils: CoilSystem, reference: ReferenceMaps) -> ChannelGrid:
        """Tabulate ``coils``' channels on the grid of the reference maps."""
        lut = LookupTableFieldModel(coils, reference)
        fmap = next(iter(reference.maps.values()))
        step = float(fmap.x[1] - fmap.x[0])
        if not np.allclose(np.diff(fmap.x), step) or not np.allclose(np.diff(fmap.y), step):
            raise ValueError("ChannelGrid needs reference maps on a regular square grid")
        X, Y = np.meshgrid(fmap.x, fmap.y, indexing="ij")
        points = np.stack([X, Y], axis=-1)
        B, G = lut.unit_field_and_gradient(points)
        if coils.has_background:
            B0, G0 = lut.background_field_and_gradient(points)
            B = np.concatenate([B, B0[..., None, :]], axis=-2)
            G = np.concatenate([G, G0[..., None, :, :]], axis=-3)
        table = np.concatenate([B, G.reshape(*G.shape[:-2], 4)], axis=-1)
        return cls(
            x0=float(fmap.x[0]),
            y0=float(fmap.y[0]),
            step=step,
            table=np.ascontiguousarray(table),
            channel_names=coils.channel_names,
            background=coils.has_background,
        )

    @classmethod
    def load(
        cls, coils: CoilSystem | None = None, reference: str | Path | None = None
    ) -> ChannelGrid:
        """The grid of the shipped (or given) reference maps for ``coils`` (default rig; a
        system folder's coils read the folder's maps)."""
        coils = coils or CoilSystem.load()
        path = reference if reference is not None else coils.maps_path
        return cls.from_reference(coils, ReferenceMaps.load(path))

    def unit(self, x: float, y: float) -> FloatArray:
        """Bilinear values of every column at (x, y) m: shape (n_channels (+ 1), 6)."""
        nx, ny = self.table.shape[:2]
        fx, fy = (x - self.x0) / self.step, (y - self.y0) / self.step
        i = min(max(math.floor(fx), 0), nx - 2)
        j = min(max(math.floor(fy), 0), ny - 2)
        tx, ty = fx - i, fy - j
        c = self.table[i : i + 2, j : j + 2]
        return (1 - tx) * ((1 - ty) * c[0, 0] + ty * c[0, 1]) + tx * (
            (1 - ty) * c[1, 0] + ty * c[1, 1]
        )

    def units(self, positions: ArrayLike) -> FloatArray:
        """:meth:`unit` at many positions (n, 2) m at once: shape (n, n_channels (+ 1), 6),
        the same blend of the same corners (equal to :meth:`unit` to rounding)."""
        p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
        nx, ny = self.table.shape[:2]
        fx, fy = (p[:, 0] - self.x0) / self.step, (p[:, 1] - self.y0) / self.step
        i = np.clip(np.floor(fx), 0, nx - 2).astype(np.intp)
        j = np.clip(np.floor(fy), 0, ny - 2).astype(np.intp)
        tx, ty = (fx - i)[:, None, None], (fy - j)[:, None, None]
        t = self.table
        return (1 - tx) * ((1 - ty) * t[i, j] + ty * t[i, j + 1]) + tx * (
            (1 - ty) * t[i + 1, j] + ty * t[i + 1, j + 1]
        )

    def field(self, x: float, y: float, currents: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Total field (2,) in T and gradient (2, 2) in T/m at (x, y) for ``currents`` in A."""
        v = self.inputs(currents) @ self.unit(x, y)
        return v[:2], v[2:].reshape(2, 2)


class GridCells:
    """The plant's reader of a :class:`ChannelGrid`: each visited cell's four corners, kept.

    The plant reads the field once per 1 ms sub-step and the robot stays in a cell for many
    of them, so each cell's corners are gathered once as an (n_channels, 24) table.
    :meth:`read` (any currents, e.g. while the amplifiers ramp) is then one small product and
    a blend, cheaper than :meth:`ChannelGrid.unit` and the product (BENCHMARKS.md);
    :meth:`held` serves currents held over a control period faster still. Both equal
    ``currents @ grid.unit(x, y)`` to rounding (tests/test_sim.py).
    """

    def __init__(self, grid: ChannelGrid) -> None:
        self.grid = grid
        self._cells: dict[tuple[int, int], FloatArray] = {}

    def locate(self, x: float, y: float) -> tuple[int, int, float, float]:
        """The cell (i, j) holding (x, y) m (border cells extrapolate) and the position in it."""
        g = self.grid
        nx, ny = g.table.shape[:2]
        fx, fy = (x - g.x0) / g.step, (y - g.y0) / g.step
        i = min(max(math.floor(fx), 0), nx - 2)
        j = min(max(math.floor(fy), 0), ny - 2)
        return i, j, fx - i, fy - j

    def corners(self, i: int, j: int) -> FloatArray:
        """Cell (i, j)'s corners (00, 01, 10, 11) of every channel: shape (n_channels, 4 · 6)."""
        cell = self._cells.get((i, j))
        if cell is None:
            c = self.grid.table[i : i + 2, j : j + 2]  # (2, 2, ch, 6)
            cell = self._cells[(i, j)] = np.ascontiguousarray(
                c.transpose(2, 0, 1, 3).reshape(c.shape[2], 24)
            )
        return cell

    def read(
        self, currents: FloatArray, x: float, y: float
    ) -> tuple[list[float], tuple[list[float], list[float]]]:
        """``(B, G)`` at (x, y) m for ``currents`` (A), in the form of :class:`HeldField`."""
        i, j, tx, ty = self.locate(x, y)
        return _blend((currents @ self.corners(i, j)).tolist(), tx, ty)

    def held(self, currents: ArrayLike) -> HeldField:
        """A reader for ``currents`` (A) held: each cell contracted with them once."""
        return HeldField(self, np.asarray(currents, dtype=np.float64))


def _blend(
    v: list[float], tx: float, ty: float
) -> tuple[list[float], tuple[list[float], list[float]]]:
    """Bilinear blend of the corner values v = [00 (6), 01 (6), 10 (6), 11 (6)]."""
    sx, sy = 1 - tx, 1 - ty
    out = [
        sx * (sy * a + ty * b) + tx * (sy * c + ty * d)
        for a, b, c, d in zip(v[0:6], v[6:12], v[12:18], v[18:24], strict=True)
    ]
    return out[:2], (out[2:4], out[4:6])


class HeldField:
    """The total field of a :class:`ChannelGrid` for one set of held currents.

    The currents stay the same over a control period: each cell's corners are contracted with
    them once, when the robot first enters the cell, so a read is a bilinear blend of six
    numbers.
    """

    def __init__(self, cells: GridCells, currents: FloatArray) -> None:
        self.cells = cells
        self.currents = currents
        self._contracted: dict[tuple[int, int], list[float]] = {}

    def __call__(self, x: float, y: float) -> tuple[list[float], tuple[list[float], list[float]]]:
        """``(B, G)`` at (x, y) m: B = [Bx, By] in T, G = ([∂Bx/∂x, ∂Bx/∂y], [∂By/∂x, ∂By/∂y])
        in T/m, the nested form :func:`magrun.robot.discrete_step` takes."""
        i, j, tx, ty = self.cells.locate(x, y)
        return _blend(self.cell(i, j), tx, ty)

    def cell(self, i: int, j: int) -> list[float]:
        """Cell (i, j)'s corner values for the held currents: [00 (6), 01 (6), 10 (6), 11 (6)]."""
        v = self._contracted.get((i, j))
        if v is None:
            v = self._contracted[(i, j)] = (self.currents @ self.cells.corners(i, j)).tolist()
        return v
