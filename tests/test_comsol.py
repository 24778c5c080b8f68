"""COMSOL import: round trips through the export layout, and every malformed file gets an
error naming the file and line."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from magrun.field.comsol import ComsolFormatError, import_comsol, read_comsol_map, write_comsol_map
from magrun.field.reference import FieldMap, ReferenceMaps, reference_field_map


@pytest.fixture(scope="module")
def fmap(coils) -> FieldMap:
    return reference_field_map(coils.coil_types["large"], half_width=0.05, pitch=2.5e-3)


@pytest.mark.parametrize(
    ("length_unit", "field_unit", "current"),
    [("mm", "mT", 10.0), ("m", "T", 1.0), ("cm", "G", 2.5)],
)
def test_round_trip(
    tmp_path, fmap: FieldMap, length_unit: str, field_unit: str, current: float
) -> None:
    path = tmp_path / "export.txt"
    write_comsol_map(path, fmap, length_unit=length_unit, field_unit=field_unit, current_a=current)
    back = read_comsol_map(path, current_a=current)
    assert_allclose(back.x, fmap.x, rtol=0, atol=1e-12)
    assert_allclose(back.y, fmap.y, rtol=0, atol=1e-12)
    assert_allclose(back.B, fmap.B, rtol=1e-12, atol=1e-20)
    # gradients come from 2nd-order differences of the 2.5 mm grid: O(h²) against the exact table
    scale = np.abs(fmap.dB).max()
    assert np.max(np.abs(back.dB - fmap.dB)) < 0.05 * scale
    assert np.sqrt(np.mean((back.dB - fmap.dB) ** 2)) < 2e-3 * scale


def test_shuffled_rows_plain_header_and_3d_plane(tmp_path) -> None:
    xs, ys = np.array([-1.0, 0.0, 1.0, 2.0]), np.array([0.0, 0.5, 1.0])
    rows = [(x, y, 0.2, 3 * x + 2 * y, x - y) for x in xs for y in ys]
    rng = np.random.default_rng(3)
    rng.shuffle(rows)
    text = "% Length unit: mm\n% x y z Bx By\n" + "\n".join(" ".join(map(str, r)) for r in rows)
    path = tmp_path / "plain.txt"
    path.write_text(text)
    m = read_comsol_map(path)
    assert_allclose(m.x, xs * 1e-3)
    assert_allclose(m.B[..., 0], 3 * m.x[:, None] * 1e3 + 2 * m.y[None, :] * 1e3)
    assert_allclose(m.dB[..., 0, 0], 3e3)  # linear fields: exact derivatives, T/m
    assert_allclose(m.dB[..., 1, 1], -1e3)


def bad(tmp_path, text: str) -> str:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ComsolFormatError) as info:
        read_comsol_map(path)
    message = str(info.value)
    assert message.startswith(str(path) + ":")
    return message


HEADER = "% Model: x\n% Length unit: mm\n% x  y  mf.Bx (T)  mf.By (T)\n"
GRID = "".join(f"{x} {y} 1e-3 2e-3\n" for x in (0, 1, 2) for y in (0, 1, 2))


def test_bad_files_name_the_file_and_line(tmp_path) -> None:
    assert ":3: column header" in bad(tmp_path, "% a\n% b\n% x  y  mf.Bz (T)\n0 0 1\n")
    assert ":4: 'abc' is not a number" in bad(tmp_path, HEADER + "0 0 abc 1\n" + GRID)
    assert ":5: 3 values" in bad(tmp_path, HEADER + "0 0 1 1\n0 1 1\n")
    assert ":4: non-finite" in bad(tmp_path, HEADER + "0 0 NaN 1\n" + GRID)
    assert "data before the column header" in bad(tmp_path, "0 0 1 1\n")
    assert "no data rows" in bad(tmp_path, HEADER)
    assert "do not form a complete grid" in bad(tmp_path, HEADER + GRID.split("\n", 1)[1])
    assert "appears more than once" in bad(tmp_path, HEADER + GRID + "0 0 1 1\n")
    assert "unknown unit 'furlong'" in bad(tmp_path, HEADER.replace("mm", "furlong") + GRID)
    assert "more than one plane" in bad(
        tmp_path,
        "% x y z Bx By\n" + "".join(f"{x} {y} {x} 1 1\n" for x in (0, 1, 2) for y in (0, 1, 2)),
    )
    big = "".join(f"{x} {y} 1 1\n" for x in (-50, 0, 50) for y in (-50, 0, 50))
    assert "state the length unit" in bad(tmp_path, "% x y Bx By\n" + big)  # mm read as m
    # a coordinate near the float limit: refused before its span or rounding overflows
    far = "% x y z Bx By Bz\n0.0 1.797693134862316e+296 0.0 0.0 0.0 0.0\n"
    assert "y reaches 1.79769e+296 m from the origin" in bad(tmp_path, far)
    huge_field = HEADER + "".join(f"{x} {y} 1e300 0\n" for x in (0, 1, 2) for y in (0, 1, 2))
    assert "too large for a coil: state the field unit" in bad(tmp_path, huge_field)
    path = tmp_path / "small_current.txt"
    path.write_text(HEADER + GRID)
    with pytest.raises(ComsolFormatError, match="T per ampere"):  # finite, over a tiny current
        read_comsol_map(path, current_a=1e-306)


def test_missing_file_and_bad_current(tmp_path) -> None:
    with pytest.raises(ComsolFormatError, match="cannot read"):
        read_comsol_map(tmp_path / "nope.txt")
    with pytest.raises(ValueError, match="current_a"):
        read_comsol_map(tmp_path / "nope.txt", current_a=0.0)


def test_import_builds_reference_maps(tmp_path, fmap: FieldMap) -> None:
    write_comsol_map(tmp_path / "large.txt", fmap)
    maps = import_comsol({"large": tmp_path / "large.txt"})
    maps.save(tmp_path / "maps.npz")
    assert_allclose(ReferenceMaps.load(tmp_path / "maps.npz")["large"].B, fmap.B, rtol=1e-12)
