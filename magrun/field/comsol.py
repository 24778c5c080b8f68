"""Import unit-current field maps exported from COMSOL (plain-text spreadsheet/grid export).

A lab with its own FEA model exports, per coil type, B on a regular grid of the robot's plane
(Results > Export > Data, "Spreadsheet" format, a Grid dataset or a Cut Plane evaluated on a
grid) and builds a reference-map file from it::

    magrun field import-comsol --small small.txt --medium medium.txt --large large.txt \\
        --current-a 1 --out my_reference_maps.npz
    magrun field fit --reference my_reference_maps.npz --out my_field

Expected file (COMSOL writes the ``%`` header itself; only the column line is required)::

    % Model:              coils.mph
    % Length unit:        mm
    % x                       y                        mf.Bx (T)                mf.By (T)
    -50                       -50                      1.2345E-4                -6.789E-5
    ...

- Columns are found by name: ``x``, ``y`` (optionally ``z``) and any ``Bx``/``By`` expression
  (``mf.Bx``, ``mfnc.Bx``, ``B_x``, ``Bx``). Other columns (``Bz``, ``mf.normB``, ...) are ignored.
- Units: a unit in brackets after a column name (``(mm)``, ``[mT]``) wins; otherwise coordinates
  use the ``% Length unit:`` line, then metres; fields default to tesla. Length units: m, cm,
  mm, um/µm; field units: T, mT, uT/µT, nT, G, kG.
- Coordinates are in the base-stack frame of ``coils.yaml``: workspace centre at the origin,
  the coil on the +y axis. A 3-D export must hold one plane (a single z value).
- The points must form a complete rectilinear grid, in any order. Gradients are computed from
  the grid with second-order finite differences (``numpy.gradient``).
- Values are divided by ``current_a``, the current the map was computed at.

Any malformed file raises :class:`ComsolFormatError` naming the file and line.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.field.reference import FieldMap, ReferenceMaps
from magrun.yamlio import YamlModelError, read_text_file

#: the most characters a COMSOL export may have (a 2-D grid of some million points)
MAX_COMSOL_CHARS = 500_000_000

LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6}
FIELD_UNITS = {
    "t": 1.0,
    "mt": 1e-3,
    "ut": 1e-6,
    "µt": 1e-6,
    "μt": 1e-6,
    "nt": 1e-9,
    "g": 1e-4,
    "gauss": 1e-4,
    "kg": 1e-1,
}
_UNIT_TOKEN = re.compile(r"^[\(\[]\s*([^\)\]]*?)\s*[\)\]]$")
_FIELD_NAME = re.compile(r"(?:^|[.:])b_?([xyz])$", re.IGNORECASE)
_LENGTH_LINE = re.compile(r"^length unit\s*:\s*(\S+)", re.IGNORECASE)
MAX_SPAN_M = 2.0  # a coil-rig workspace map spanning more than this is a unit mistake
#: a field per ampere above this (T/A) is a unit mistake too (coils give mT per ampere)
MAX_FIELD_T_PER_A = 1e3


class ComsolFormatError(ValueError):
    """A COMSOL export that cannot be read; the message starts with ``file:line:``."""


def _columns(header: str) -> list[tuple[str, str | None]]:
    """Split a ``% x y mf.Bx (T) ...`` column line into (name, unit or None) pairs."""
    cols: list[tuple[str, str | None]] = []
    for token in header.split():
        unit = _UNIT_TOKEN.match(token)
        if unit and cols and cols[-1][1] is None:
            cols[-1] = (cols[-1][0], unit.group(1))
        else:
            cols.append((token, None))
    return cols


def read_comsol_map(path: str | Path, current_a: float = 1.0) -> FieldMap:
    """Read one COMSOL plain-text export into a unit-current :class:`FieldMap`.

    Parameters
    ----------
    path : str or Path
        The exported text file.
    current_a : float
        Coil current (A) the map was computed at; values are divided by it.
    """
    path = Path(path)
    if not (current_a > 0 and math.isfinite(current_a)):
        raise ValueError(f"current_a must be a positive number of amperes, got {current_a}")
    try:
        lines = read_text_file(path, MAX_COMSOL_CHARS).removeprefix("\ufeff").splitlines()
    except YamlModelError as exc:
        raise ComsolFormatError(f"{path}:0: {exc}") from exc

    length_unit: str | None = None
    header: list[tuple[str, str | None]] | None = None
    header_line = 0
    rows: list[list[float]] = []
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("%"):
            body = line[1:].strip()
            m = _LENGTH_LINE.match(body)
            if m:
                length_unit = m.group(1)
            elif not rows and _looks_like_column_line(body):
                header, header_line = _columns(body), lineno
            continue
        if header is None:
            raise ComsolFormatError(
                f"{path}:{lineno}: data before the column header line "
                "(e.g. '% x y mf.Bx (T) mf.By (T)')"
            )
        parts = line.replace(",", " ").split()
        if len(parts) != len(header):
            raise ComsolFormatError(
                f"{path}:{lineno}: {len(parts)} values but the header at line {header_line} "
                f"names {len(header)} columns"
            )
        try:
            values = [float(p) for p in parts]
        except ValueError:
            bad = next(p for p in parts if not _is_float(p))
            raise ComsolFormatError(f"{path}:{lineno}: {bad!r} is not a number") from None
        if not all(math.isfinite(v) for v in values):
            raise ComsolFormatError(
                f"{path}:{lineno}: non-finite value (NaN/Inf): the grid reaches outside the "
                "model's domain; export only points inside the workspace"
            )
        rows.append(values)
    if header is None:
        raise ComsolFormatError(
            f"{path}:{len(lines)}: no column header line ('% x y mf.Bx mf.By ...')"
        )
    if not rows:
        raise ComsolFormatError(f"{path}:{len(lines)}: no data rows")

    where = f"{path}:{header_line}"
    index = _column_index(header, where)
    data = np.asarray(rows)
    length_scale = {
        axis: _scale(header[index[axis]][1] or length_unit or "m", LENGTH_UNITS, where, axis)
        for axis in ("x", "y") + (("z",) if "z" in index else ())
    }
    field_scale = {
        c: _scale(header[index[c]][1] or "T", FIELD_UNITS, where, c) for c in ("bx", "by")
    }
    x = data[:, index["x"]] * length_scale["x"]
    y = data[:, index["y"]] * length_scale["y"]
    if "z" in index:
        z = data[:, index["z"]] * length_scale["z"]
        if np.ptp(z) > 1e-9:
            raise ComsolFormatError(
                f"{where}: points lie on more than one plane (z from {z.min():g} to {z.max():g} m);"
                " export a single plane"
            )
    with np.errstate(over="ignore"):  # a huge value over a small current: checked below
        B = (
            np.column_stack(
                [data[:, index["bx"]] * field_scale["bx"], data[:, index["by"]] * field_scale["by"]]
            )
            / current_a
        )
    strongest = float(np.max(np.abs(B))) if B.size else 0.0
    if not strongest <= MAX_FIELD_T_PER_A:
        raise ComsolFormatError(
            f"{where}: a field of {strongest:g} T per ampere at {current_a:g} A, too large for a "
            "coil: state the field unit (e.g. 'mf.Bx (mT)') and the current the map was computed at"
        )
    return _to_grid(x, y, B, path)


def _looks_like_column_line(body: str) -> bool:
    names = [n.lower() for n, _ in _columns(body)]
    return "x" in names and "y" in names


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _column_index(header: list[tuple[str, str | None]], where: str) -> dict[str, int]:
    index: dict[str, int] = {}
    for i, (name, _) in enumerate(header):
        key = name.lower()
        if key in ("x", "y", "z"):
            index.setdefault(key, i)
            continue
        m = _FIELD_NAME.search(name)
        if m and m.group(1).lower() in "xy":
            index.setdefault("b" + m.group(1).lower(), i)
    missing = [c for c in ("x", "y", "bx", "by") if c not in index]
    if missing:
        names = " ".join(n for n, _ in header)
        raise ComsolFormatError(
            f"{where}: column header '{names}' lacks {', '.join(missing)} "
            "(expected x, y and Bx/By expressions such as mf.Bx, mf.By)"
        )
    return index


def _scale(unit: str, table: Mapping[str, float], where: str, column: str) -> float:
    key = unit.strip()
    for candidate in (key, key.lower()):
        if candidate in table:
            return table[candidate]
    raise ComsolFormatError(
        f"{where}: unknown unit {unit!r} for column {column} "
        f"(known: {', '.join(sorted(set(table)))})"
    )


def _to_grid(x: NDArray[Any], y: NDArray[Any], B: NDArray[Any], path: Path) -> FieldMap:
    for name, v in (("x", x), ("y", y)):
        farthest = float(np.max(np.abs(v)))
        if farthest > MAX_SPAN_M:  # checked first: the span of such values can overflow
            raise ComsolFormatError(
                f"{path}:0: {name} reaches {farthest:g} m from the origin, too far for a "
                "workspace map: state the length unit (e.g. '% Length unit: mm' or a '(mm)' "
                "after the column name)"
            )
        if np.ptp(v) > MAX_SPAN_M:
            raise ComsolFormatError(
                f"{path}:0: {name} spans {np.ptp(v):g} m, too large for a workspace map: "
                "state the length unit (e.g. '% Length unit: mm' or a '(mm)' after the column name)"
            )
    xs, xi = np.unique(np.round(x, 12), return_inverse=True)
    ys, yi = np.unique(np.round(y, 12), return_inverse=True)
    if xs.size < 3 or ys.size < 3:
        raise ComsolFormatError(
            f"{path}:0: need at least 3 distinct x and y values, got {xs.size} x {ys.size}"
        )
    count = np.zeros((xs.size, ys.size), dtype=np.int64)
    np.add.at(count, (xi, yi), 1)
    if np.any(count > 1):
        i, j = np.argwhere(count > 1)[0]
        raise ComsolFormatError(f"{path}:0: point ({xs[i]:g}, {ys[j]:g}) m appears more than once")
    if np.any(count == 0):
        raise ComsolFormatError(
            f"{path}:0: points do not form a complete grid ({x.size} points for "
            f"{xs.size} x {ys.size} distinct coordinates); export on a regular grid"
        )
    grid = np.empty((xs.size, ys.size, 2))
    grid[xi, yi] = B
    dB = np.empty((xs.size, ys.size, 2, 2))
    for k in range(2):
        dB[..., k, 0], dB[..., k, 1] = np.gradient(grid[..., k], xs, ys, edge_order=2)
    return FieldMap(x=xs, y=ys, B=grid, dB=dB)


def import_comsol(
    files: Mapping[str, str | Path],
    current_a: float = 1.0,
    coils_meta: dict[str, Any] | None = None,
) -> ReferenceMaps:
    """Reference maps from one COMSOL export per coil type (e.g. ``{"small": "small.txt"}``)."""
    maps = {coil_type: read_comsol_map(path, current_a) for coil_type, path in files.items()}
    meta: dict[str, Any] = {
        "source": "COMSOL export (magrun.field.comsol)",
        "files": {k: str(v) for k, v in files.items()},
        "current_a": current_a,
        "units": {"x": "m", "y": "m", "B": "T/A", "dB": "T/(m A)"},
    }
    if coils_meta is not None:
        meta["coils"] = coils_meta
    return ReferenceMaps(maps=maps, meta=meta)


def write_comsol_map(
    path: str | Path,
    fmap: FieldMap,
    length_unit: str = "mm",
    field_unit: str = "T",
    current_a: float = 1.0,
) -> None:
    """Write a map in COMSOL's spreadsheet export layout (for tests and for sharing maps)."""
    ls, fs = LENGTH_UNITS[length_unit], FIELD_UNITS[field_unit.lower()]
    pts = fmap.points().reshape(-1, 2)
    B = fmap.B.reshape(-1, 2) * current_a
    lines = [
        "% Model:              magrun export",
        "% Dimension:          2",
        f"% Nodes:              {len(pts)}",
        "% Expressions:        2",
        "% Description:        Magnetic flux density, x-component, "
        "Magnetic flux density, y-component",
        f"% Length unit:        {length_unit}",
        f"% x{' ' * 23}y{' ' * 24}mf.Bx ({field_unit}){' ' * 16}mf.By ({field_unit})",
    ]
    lines += [
        f"{p[0] / ls:<25.17g} {p[1] / ls:<24.17g} {b[0] / fs:<24.17g} {b[1] / fs:.17g}"
        for p, b in zip(pts, B, strict=True)
    ]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
