"""Coil calibration files (magrun/calibration.py) and the simulated rig's fixed plant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from synthetic import TINY

from magrun.calibration import gains_file_text, gains_in_order, load_coil_gains
from magrun.field.coils import CoilSystem
from magrun.protocol import load_protocol
from magrun.rigs.sim import SimRig
from magrun.trial import RunError, coil_gains_of
from magrun.yamlio import YamlModelError


def test_gains_file_round_trip_and_order(coils: CoilSystem, tmp_path: Path) -> None:
    names = coils.channel_names
    gains = {n: 1.0 + 0.01 * i for i, n in enumerate(reversed(names))}
    path = tmp_path / "gains.yaml"
    path.write_text(gains_file_text(gains, "reference", ["a header line"]))
    assert path.read_text().startswith("# a header line\n")
    read = load_coil_gains(path)
    assert read == pytest.approx(gains, rel=1e-6)
    ordered = gains_in_order(read, names, str(path))
    np.testing.assert_allclose(ordered, [gains[n] for n in names], rtol=1e-6)
    with pytest.raises(ValueError, match=f"no gain for {names[0]}.*unknown channel.*coil_x"):
        gains_in_order({**dict.fromkeys(names[1:], 1.0), "coil_x": 1.0}, names, "f.yaml")


def test_bad_gains_files_name_the_file_line_and_field(tmp_path: Path) -> None:
    path = tmp_path / "gains.yaml"
    path.write_text("model: reference\ncoil_gains:\n  small_N: 1.0\n  large_N: -0.5\n")
    with pytest.raises(YamlModelError, match=r"gains.yaml:4.*coil_gains.large_N"):
        load_coil_gains(path)
    path.write_text("coil_gains: {}\n")
    with pytest.raises(YamlModelError, match=r"gains\.yaml:1"):
        load_coil_gains(path)


def test_protocol_coil_gains_relative_to_the_protocol(coils: CoilSystem, tmp_path: Path) -> None:
    (tmp_path / "tiny.yaml").write_text(TINY.read_text())
    names = coils.channel_names
    (tmp_path / "gains.yaml").write_text(gains_file_text(dict.fromkeys(names, 1.02), "lut"))
    protocol = load_protocol(tmp_path / "tiny.yaml", ("controller.coil_gains=gains.yaml",))
    np.testing.assert_allclose(coil_gains_of(protocol, coils), 1.02)
    # the file's channels are checked against the coil system's
    (tmp_path / "other.yaml").write_text(gains_file_text({"a": 1.0}, "lut"))
    other = load_protocol(tmp_path / "tiny.yaml", ("controller.coil_gains=other.yaml",))
    with pytest.raises(RunError, match=r"other\.yaml: no gain for"):
        coil_gains_of(other, coils)
    with pytest.raises(YamlModelError, match=r"controller\.coil_gains"):
        load_protocol(tmp_path / "tiny.yaml", ("controller.coil_gains=missing.yaml",))


def test_plant_seed_keeps_one_plant_across_trials(coils: CoilSystem) -> None:
    """Rigs with different seeds and one plant_seed: the same robot and gains (one real
    rig); without it each seed draws its own."""
    a = SimRig.default("drug_delivery", seed=1, coils=coils, plant_seed=42)
    b = SimRig.default("drug_delivery", seed=2, coils=coils, plant_seed=42)
    c = SimRig.default("drug_delivery", seed=2, coils=coils)
    assert a.robot == b.robot
    np.testing.assert_array_equal(a.coil_gains, b.coil_gains)
    assert not np.allclose(b.coil_gains, c.coil_gains)
    assert np.all(np.abs(np.log(a.coil_gains)) < 0.1)  # σ = 2 %: drawn, not wild
