"""The coil-system file: the paper's rig as data, and clear errors for bad files."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from magrun.field.coils import CoilFileError, CoilSystem, rotation_matrix


def test_default_rig_is_the_papers(coils: CoilSystem) -> None:
    assert coils.channel_names == (
        "small_N",
        "large_N",
        "small_W",
        "large_W",
        "small_S",
        "large_S",
        "small_E",
        "large_E",
    )
    assert coils.max_current == 30.0
    assert coils.workspace_half_width == pytest.approx(0.05)
    table_two = {"small": (57.69, 118.731), "medium": (71.295, 136.186), "large": (90.925, 165.341)}
    for name, (center, radius) in table_two.items():
        assert coils.coil_types[name].center_mm == center
        assert coils.coil_types[name].disk_radius_mm == radius


def test_windings_fit_between_workspace_and_neighbours(coils: CoilSystem) -> None:
    types = sorted(coils.coil_types.values(), key=lambda c: c.center)
    for inner, outer in itertools.pairwise(types):  # stacked one behind the other
        assert inner.center + inner.length / 2 <= outer.center - outer.length / 2
    nearest_face = min(c.front_face for c in types)
    assert nearest_face > coils.workspace_half_width
    # a coil of one stack stays clear of any coil of the next stack (90° away)
    assert max(c.outer_radius for c in types) < nearest_face


def test_stack_rotations_are_exact() -> None:
    assert_array_equal(rotation_matrix(math.pi / 2), [[0, -1], [1, 0]])
    assert_array_equal(rotation_matrix(3 * math.pi / 2), [[0, 1], [-1, 0]])
    R = rotation_matrix(0.3)
    np.testing.assert_allclose(R @ R.T, np.eye(2), atol=1e-15)
    # the W stack (90°) is the N stack turned onto -x
    np.testing.assert_array_equal(rotation_matrix(math.pi / 2) @ np.array([0.0, 1.0]), [-1.0, 0.0])


def write(tmp_path, text: str):
    path = tmp_path / "coils.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_unknown_key_is_rejected_with_the_file_named(tmp_path) -> None:
    from importlib import resources

    text = (resources.files("magrun.field") / "data" / "coils.yaml").read_text()
    path = write(
        tmp_path, text.replace("max_current_a: 30.0", "max_current_a: 30.0\nmax_curent: 3")
    )
    with pytest.raises(CoilFileError) as info:
        CoilSystem.load(path)
    line = text.splitlines().index("max_current_a: 30.0") + 2  # the inserted line, 1-based
    assert str(info.value).startswith(f"{path}:{line}: max_curent: Extra inputs are not permitted")


def test_coil_reaching_into_workspace_is_rejected(tmp_path) -> None:
    from importlib import resources

    text = (resources.files("magrun.field") / "data" / "coils.yaml").read_text()
    path = write(tmp_path, text.replace("length_mm: 10.0", "length_mm: 20.0"))
    with pytest.raises(CoilFileError, match="reaches into the workspace"):
        CoilSystem.load(path)


def test_unreadable_and_invalid_yaml(tmp_path) -> None:
    with pytest.raises(CoilFileError, match="cannot read"):
        CoilSystem.load(tmp_path / "missing.yaml")
    with pytest.raises(CoilFileError, match=r"coils\.yaml:\d+: not valid YAML"):
        CoilSystem.load(write(tmp_path, "a: [1, 2"))


def test_bad_value_names_its_line_and_field(tmp_path) -> None:
    from importlib import resources

    text = (resources.files("magrun.field") / "data" / "coils.yaml").read_text()
    path = write(tmp_path, text.replace("turns: 168", "turns: -3"))
    line = text.splitlines().index("    turns: 168") + 1
    with pytest.raises(
        CoilFileError,
        match=rf"coils\.yaml:{line}: coil_types\.medium\.turns: Input should be greater than 0",
    ):
        CoilSystem.load(path)


@pytest.mark.parametrize("value", [".inf", ".nan", "-.inf"])
def test_a_limit_that_is_not_finite_is_refused_with_its_line(tmp_path, value: str) -> None:
    """An infinite current limit once passed validate, run and the emulator (which then
    acknowledged 1e9 A): every number of a coil file must be finite."""
    from importlib import resources

    text = (resources.files("magrun.field") / "data" / "coils.yaml").read_text()
    path = write(tmp_path, text.replace("max_current_a: 30.0", f"max_current_a: {value}"))
    line = text.splitlines().index("max_current_a: 30.0") + 1
    with pytest.raises(
        CoilFileError, match=rf"coils\.yaml:{line}: max_current_a: Input should be a finite number"
    ):
        CoilSystem.load(path)


@pytest.mark.parametrize(
    "text",
    [
        "kind: maps\n" + "a: " + "[" * 5000 + "]" * 5000 + "\n",  # deeper than the parser goes
        "max_current_a: " + "9" * 5000 + "\n",  # more digits than Python converts
    ],
)
def test_a_hostile_system_file_is_refused_with_its_name(tmp_path, text: str) -> None:
    """coils.py read a system's `kind` with an unguarded yaml.safe_load: a deep or a big-int
    document ended in a traceback. Every YAML document now goes through one reader."""
    path = write(tmp_path, text)
    with pytest.raises(CoilFileError, match=r"coils\.yaml.*not valid YAML"):
        CoilSystem.load(path)
