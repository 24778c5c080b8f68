"""Any electromagnetic navigation system: MPEM calibrations imported, fitted and driven.

The importer is checked against an independent computation (magpylib's point dipoles, and
finite differences of them for the gradients) and against the closed-form on-axis field of
a dipole; the system folders' models against the N-channel shape contract; a 3-channel
system and the shipped OctoMag run closed loops.
"""

from __future__ import annotations

import itertools
import math
import textwrap
from pathlib import Path

import magpylib as mp
import numpy as np
import pytest
from click.testing import CliRunner
from numpy.testing import assert_allclose

from magrun.cli import cli
from magrun.field.coils import CoilSystem
from magrun.field.lut import LookupTableFieldModel
from magrun.field.mpem import MpemError, MpemModel, import_mpem
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeFieldModel

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = {
    "octomag": (ROOT / "systems" / "octomag" / "OctoMag_Calibration.yaml", 10e-3),
    "minimag": (ROOT / "systems" / "minimag" / "MINIMAG_E090094.yaml", 5e-3),
}
MU0 = 4e-7 * math.pi


def _magpylib_field(model: MpemModel, coil: str, points: np.ndarray) -> np.ndarray:
    """The coil's field per ampere from magpylib dipoles: b = μ0 m / 4π, m = 4π b / μ0."""
    pos, dirs, b = model._sources(coil)
    dipoles = [
        mp.misc.Dipole(moment=4 * math.pi / MU0 * bi * di, position=pi)
        for pi, di, bi in zip(pos, dirs, b, strict=True)
    ]
    return np.asarray(mp.getB(dipoles, points, sumup=True), dtype=np.float64)


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_imported_maps_agree_with_magpylib(name: str, tmp_path: Path) -> None:
    """Every channel's map: the field within 0.1 % of the largest field, the gradient (central
    differences of magpylib, 1 µm steps) within 1 % of the largest gradient."""
    cal, half = SHIPPED[name]
    folder = import_mpem(cal, tmp_path / name, 0.0, (0.0, 0.0), half, pitch=half / 5)
    maps = ReferenceMaps.load(folder / "reference_maps.npz")
    model = MpemModel.load(cal)
    for coil in model.coil_names:
        fmap = maps[coil]
        xy = fmap.points().reshape(-1, 2)
        pts = np.column_stack([xy, np.zeros(len(xy))])
        B = _magpylib_field(model, coil, pts)[:, :2]
        h = 1e-6
        steps = np.eye(3)[:2] * h
        G = np.stack(
            [
                (_magpylib_field(model, coil, pts + e) - _magpylib_field(model, coil, pts - e))
                for e in steps
            ],
            axis=-1,
        )[:, :2] / (2 * h)
        got_B, got_G = fmap.B.reshape(-1, 2), fmap.dB.reshape(-1, 2, 2)
        assert np.max(np.abs(got_B - B)) < 1e-3 * np.max(np.abs(B)), coil
        assert np.max(np.abs(got_G - G)) < 1e-2 * np.max(np.abs(G)), coil


SYNTHETIC = """\
Coil_List:
  - north
  - east
  - south
  - Offset
north:
  Source_List: [Src_0]
  Src_0:
    Source_Position: [0.0, 0.05, 0.0]
    Source_Direction: [0.0, -2.0, 0.0]     # not unit: normalised
    B_Coeff: [2.0e-7]
    A_Coeff: ~
east:
  Source_List: [Src_0, Src_1]
  Src_0:
    Source_Position: [0.05, 0.0, 0.0]
    Source_Direction: [-1.0, 0.0, 0.0]
    B_Coeff: [1.0e-7]
  Src_1:
    Source_Position: [0.06, 0.01, 0.02]
    Source_Direction: [0.0, 0.0, 1.0]
    B_Coeff: [3.0e-8]
south:
  Source_List: [Src_0]
  Src_0:
    Source_Position: [0.0, -0.05, 0.0]
    Source_Direction: [0.0, 1.0, 0.0]
    B_Coeff: [2.0e-7]
Offset:
  Source_List: [Src_0]
  Src_0:
    Source_Position: [-0.3, 0.0, 0.0]
    Source_Direction: [1.0, 0.0, 0.0]
    B_Coeff: [2.7e-5]
Workspace_Dimensions: [[-0.01, 0.01], [-0.01, 0.01], [-0.01, 0.01]]
System_Name: three coils and a background
"""


@pytest.fixture(scope="module")
def three(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A synthetic three-channel system with a background field, imported (±10 mm)."""
    base = tmp_path_factory.mktemp("three")
    (base / "three.yaml").write_text(SYNTHETIC)
    return import_mpem(base / "three.yaml", base / "system", 0.0, (0.0, 0.0), 10e-3)


def test_a_synthetic_file_gives_the_dipoles_closed_form(three: Path) -> None:
    """On a dipole's axis at distance r its field is 2 b / r³ along the axis; the gradient
    along the axis is −6 b / r⁴; the background (Offset) is in T, present at zero current."""
    coils = CoilSystem.load(three)
    assert coils.channel_names == ("north", "east", "south")
    assert coils.has_background
    maps = ReferenceMaps.load(three / "reference_maps.npz")
    north = maps["north"]
    j = np.argmin(np.abs(north.y))  # y = 0: the centre column, x = 0 too
    i = np.argmin(np.abs(north.x))
    r = 0.05
    assert_allclose(north.B[i, j], [0.0, -2 * 2e-7 / r**3], atol=1e-12)
    # ∂By/∂y on the axis: By = −2b/(0.05 − y)³ → −6b/r⁴
    assert north.dB[i, j, 1, 1] == pytest.approx(-6 * 2e-7 / r**4, rel=1e-9)
    bg = maps["background"]
    assert_allclose(bg.B[i, j], [2 * 2.7e-5 / 0.3**3, 0.0], rtol=1e-9)  # 2 mT along +x


def test_an_mpem_import_selects_orders_by_the_gradient_too(three: Path, tmp_path: Path) -> None:
    """The dipoles 50 mm off a ±10 mm workspace are nearly linear over it: the field's R²
    saturates at order 2, whose gradient (the force) is linear and about 20 % off. The
    importer's selection asks the gradient's R² to saturate too: each channel's order is the
    first whose next adds < 0.01 to both R², computed here from the report's scores, and its
    gradient is within 5 % RMS. `magrun field fit --system` refits the same way unless told
    --field-only, which gives the paper's rule (order 2)."""
    import json

    report = json.loads((three / "zernike_fit.json").read_text())
    assert report["selection"]["gradient"] is True
    for name in ("north", "east", "south"):
        rep = report["coil_types"][name]
        scores = rep["orders"]
        first = next(
            a["order"] for a, b in itertools.pairwise(scores)
            if b["r2"] - a["r2"] < 0.01 and b["gradient_r2"] - a["gradient_r2"] < 0.01
        )  # fmt: skip
        assert rep["selected_order"] == first > 2
        assert rep["relative_rms_error"]["gradient_workspace"] < 0.05
    folder = tmp_path / "copy"
    folder.mkdir()
    for f in three.iterdir():
        (folder / f.name).write_bytes(f.read_bytes())
    for flags, north in (([], report["coil_types"]["north"]["selected_order"]),
                         (["--field-only"], 2)):  # fmt: skip
        result = CliRunner().invoke(
            cli, ["field", "fit", "--system", str(folder), "--json", "--overwrite", *flags]
        )
        assert result.exit_code == 0, result.output
        refit = json.loads(result.output)
        assert refit["coil_types"]["north"]["selected_order"] == north
        if flags:
            gradient_error = refit["coil_types"]["north"]["relative_rms_error"]
            assert gradient_error["gradient_workspace"] > 0.1  # what the field's rule leaves


def test_models_of_a_system_follow_the_shape_contract(three: Path) -> None:
    """``load(system=DIR)``: (..., N, 2) and (..., N, 2, 2), G[..., k, l] = ∂B_k/∂x_l (checked
    by central differences), and the background in the total field and the CasADi form."""
    lut = LookupTableFieldModel.load(system=three)
    zernike = ZernikeFieldModel.load(system=three)
    rng = np.random.default_rng(3)
    p = rng.uniform(-8e-3, 8e-3, (4, 5, 2))
    for model in (lut, zernike):
        B, G = model.unit_field_and_gradient(p)
        assert B.shape == (4, 5, 3, 2)
        assert G.shape == (4, 5, 3, 2, 2)
    h = 1e-6
    B, G = zernike.unit_field_and_gradient(p)
    for col in range(2):
        e = np.zeros(2)
        e[col] = h
        fd = (zernike.unit_field(p + e) - zernike.unit_field(p - e)) / (2 * h)
        assert_allclose(G[..., col], fd, atol=1e-6 * np.max(np.abs(G)))
    # the fit at the order the R² rule selects explains the maps: R² ≥ 0.99 per channel
    maps = ReferenceMaps.load(three / "reference_maps.npz")
    q = maps["east"].points().reshape(-1, 2)
    fit, ref = zernike.unit_field(q), lut.unit_field(q)
    for c in range(3):
        resid = np.sum((fit[:, c] - ref[:, c]) ** 2)
        assert 1 - resid / np.sum((ref[:, c] - ref[:, c].mean(axis=0)) ** 2) > 0.99
    currents = np.array([1.0, -2.0, 0.5])
    B0, _ = lut.background_field_and_gradient(np.zeros(2))
    assert np.linalg.norm(B0) == pytest.approx(2 * 2.7e-5 / 0.3**3, rel=1e-6)  # 2 mT
    for model in (lut, zernike):
        total, _ = model.field_and_gradient(np.zeros(2), currents)
        unit = model.unit_field(np.zeros(2))
        own, _ = model.background_field_and_gradient(np.zeros(2))
        assert_allclose(own, B0, rtol=1e-2, atol=1e-9)  # the Zernike fit of it: 0.1 % here
        assert_allclose(total, own + currents @ unit, rtol=1e-9, atol=1e-12)
        f = model.casadi_function()
        assert_allclose(np.asarray(f(np.zeros(2), currents)[0]).ravel(), total, rtol=1e-6)


def test_a_three_channel_system_fits_and_runs_a_closed_loop(three: Path, tmp_path: Path) -> None:
    """`magrun field fit --system` reports per channel; a protocol with `system:` runs all
    six methods on it, background included, with exact feedback."""
    result = CliRunner().invoke(
        cli, ["field", "fit", "--system", str(three), "--json", "--overwrite"]
    )
    assert result.exit_code == 0, result.output
    import json

    report = json.loads(result.output)
    assert set(report["coil_types"]) == {"north", "east", "south", "background"}
    protocol = tmp_path / "three.yaml"
    protocol.write_text(
        textwrap.dedent(
            f"""\
            name: three
            system: {three}
            robot: micro_magnet
            workspace: {{kind: open}}
            trajectory: {{kind: s_curve, size_mm: 8, speed_mm_s: 1}}
            methods: [proposed, baseline1, baseline2, baseline3, baseline4, baseline5]
            trials: 1
            seed: 2
            duration_s: 3
            controller: {{rate_hz: 25.5, latency_ms: 5}}
            feedback: {{camera: false}}
            """
        )
    )
    result = CliRunner().invoke(cli, ["run", str(protocol), "--out", str(tmp_path / "rec")])
    assert result.exit_code == 0, result.output
    manifest = json.loads((tmp_path / "rec" / "three" / "manifest.json").read_text())
    for entry in manifest["trials"]:
        assert entry["status"] == "ok", entry
        assert entry["rms_position_mm"] < 0.5, entry  # the S is 8 mm across
    mcap = tmp_path / "rec" / "three" / manifest["trials"][0]["mcap"]
    from analysis.load import read_recording

    rec = read_recording(mcap)
    assert list(rec.currents.columns)[-3:] == ["north", "east", "south"]  # the system's names


BAD = {
    "no Coil_List": ("north:\n  Source_List: [a]\n", "no Coil_List: an MPEM calibration"),
    "a listed coil missing": ("Coil_List: [north]\n", "which the file does not define"),
    "a listed source missing": (
        "Coil_List: [north]\nnorth:\n  Source_List: [a]\n",
        "which the coil does not define",
    ),
    "a wrong type": (
        "Coil_List: [n]\nn:\n  Source_List: [a]\n  a:\n    Source_Position: [0, 0, 0.1]\n"
        "    Source_Direction: [0, 0, 1]\n    B_Coeff: [strong]\n",
        ":7: ",
    ),
    "a zero-length direction": (
        "Coil_List: [n]\nn:\n  Source_List: [a]\n  a:\n    Source_Position: [0, 0, 0.1]\n"
        "    Source_Direction: [0, 0, 0]\n    B_Coeff: [1.0e-7]\n",
        ":6: n.a.Source_Direction: a source direction of zero length",
    ),
    "an order-2 source": (
        "Coil_List: [n]\nn:\n  Source_List: [a]\n  a:\n    Source_Position: [0, 0, 0.1]\n"
        "    Source_Direction: [0, 0, 1]\n    B_Coeff: [1.0e-7, 2.0e-9]\n",
        "an order-2 source (2 B coefficients): only order 1",
    ),
    "A coefficients": (
        "Coil_List: [n]\nn:\n  Source_List: [a]\n  a:\n    Source_Position: [0, 0, 0.1]\n"
        "    Source_Direction: [0, 0, 1]\n    B_Coeff: [1.0e-7]\n    A_Coeff: [0.1]\n",
        "A coefficients are not implemented",
    ),
    "not YAML": ("Coil_List: [n\n", "not valid YAML"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_calibrations_are_refused_by_file_and_line(case: str, tmp_path: Path) -> None:
    text, message = BAD[case]
    path = tmp_path / "cal.yaml"
    path.write_text(text)
    with pytest.raises(MpemError) as err:
        MpemModel.load(path)
    assert str(err.value).startswith(f"{path}")
    assert message in str(err.value)
    result = CliRunner().invoke(
        cli,
        ["field", "import-mpem", str(path), "--plane-z-mm", "0", "--center-mm", "0", "0",
         "--half-width-mm", "10", "--out", str(tmp_path / "out")],
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "out").exists()


def test_a_protocol_naming_no_system_folder_is_refused(tmp_path: Path) -> None:
    protocol = tmp_path / "p.yaml"
    protocol.write_text(
        "name: p\nsystem: nowhere\ntrajectory: {kind: s_curve, size_mm: 10, speed_mm_s: 1}\n"
        "methods: [proposed]\n"
    )
    result = CliRunner().invoke(cli, ["validate", str(protocol)])
    assert result.exit_code == 2
    assert "p.yaml:2: system" in result.output
    assert "not a coil-system folder" in result.output


def test_the_shipped_octomag_protocol_runs_its_quick_trials(tmp_path: Path) -> None:
    """protocols/octomag.yaml --quick: the proposed method and Baseline 2 on OctoMag's
    field, exact feedback at 25.5 Hz, track the scaled S to well under a millimetre."""
    import json

    result = CliRunner().invoke(
        cli, ["run", str(ROOT / "protocols" / "octomag.yaml"), "--quick", "--out", str(tmp_path)]
    )
    assert result.exit_code == 0, result.output
    manifest = json.loads((tmp_path / "octomag" / "manifest.json").read_text())
    assert {e["method"] for e in manifest["trials"]} == {"proposed", "baseline2"}
    for entry in manifest["trials"]:
        assert entry["status"] == "ok", entry
        assert entry["rms_position_mm"] < 0.2, entry
    # the model replayed on the recording is OctoMag's, as the trial's own prediction was:
    # the one-step error agrees with the trial's (its NMPC's prediction against the plant,
    # 6 µm here); the paper rig's maps (also 8 channels) gave 40 µm
    from magrun.replay.model import prediction_errors

    (proposed,) = [e for e in manifest["trials"] if e["method"] == "proposed"]
    errors = prediction_errors(tmp_path / "octomag" / proposed["mcap"], "zernike")
    own = proposed["rms_prediction_position_mm"]
    assert 0.5 * own < errors.position_mm[0] < 1.5 * own, (errors.position_mm[0], own)


def test_replay_and_identify_use_the_recordings_coil_system(tmp_path: Path) -> None:
    """The models a recording is replayed with (``replay --model``, ``identify``) are its own
    coil system's, named by its protocol: OctoMag's Zernike and lookup-table models, equal to
    loading them from the folder, not the paper rig's (which has 8 channels too). Recordings
    of two systems are refused together, naming both."""
    from magrun.field.lut import LookupTableFieldModel
    from magrun.field.system import load_system
    from magrun.protocol import Protocol
    from magrun.replay.common import ReplayError
    from magrun.replay.model import field_function, recorded_system

    folder = ROOT / "systems" / "octomag"
    body = {
        "name": "p", "trajectory": {"kind": "s_curve", "size_mm": 10, "speed_mm_s": 1},
        "methods": ["proposed"],
    }  # fmt: skip
    octomag = Protocol.model_validate({**body, "system": str(folder)})
    paper = Protocol.model_validate(body)
    system = recorded_system([octomag, octomag])
    assert system.folder == folder
    assert recorded_system([paper]).folder is None
    rng = np.random.default_rng(0)
    positions = rng.uniform(-8e-3, 8e-3, (5, 2))
    currents = rng.uniform(-5, 5, (5, system.coils.n_channels))
    shipped = load_system(None)
    for name, own in (
        ("zernike", ZernikeFieldModel.load(system=folder)),
        ("lut", LookupTableFieldModel.load(system=folder)),
    ):
        B, G = field_function(name, system)(positions, currents)
        want_B, want_G = own.field_and_gradient(positions, currents)
        assert_allclose(B, want_B.T, rtol=1e-12, atol=1e-15)
        assert_allclose(G, want_G.transpose(1, 2, 0), rtol=1e-12, atol=1e-15)
        other, _ = field_function(name, shipped)(positions, currents)
        assert not np.allclose(other, B, rtol=0.1)
    with pytest.raises(ReplayError, match="different coil systems") as err:
        recorded_system([octomag, paper])
    assert "octomag" in str(err.value)
    assert "the paper's rig" in str(err.value)


def test_the_papers_rig_records_what_it_recorded_before(tmp_path: Path) -> None:
    """Every method on tests/data/protocols/tiny.yaml records the poses and currents of
    tests/data/paper_rig_reference.npz (written by tests/make_paper_rig_reference.py; the
    N-channel coil systems left it unchanged). On the machine that wrote it they are equal
    bit for bit. Another CPU rounds sums differently (the compiled kernels, the QP solvers'
    active sets), and a closed loop carries that on: on a second machine of the same kind the
    trials differed by up to 6 nm, 6e-7 rad and 0.34 mA. The bounds, 0.1 µm, 1e-5 rad and
    5 mA, are 15 times that and far below any change of behaviour (a retune moves the
    robot by micrometres and the currents by tenths of an ampere)."""
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from make_paper_rig_reference import record

    want = np.load(ROOT / "tests" / "data" / "paper_rig_reference.npz")
    got = record(tmp_path)
    assert set(got) == set(want.files)
    for key in want.files:
        a, b = got[key], want[key]
        assert a.shape == b.shape, key
        assert np.array_equal(np.isnan(a), np.isnan(b)), key
        if np.isnan(b).all():  # the PID predicts nothing: all NaN
            continue
        if key.endswith("/currents"):
            assert np.nanmax(np.abs(a - b)) <= 5e-3, key  # A
        else:
            assert np.nanmax(np.abs(a[:, :2] - b[:, :2])) <= 1e-7, key  # m
            assert np.nanmax(np.abs(a[:, 2] - b[:, 2])) <= 1e-5, key  # rad


def test_octomag_behind_the_emulated_rig_and_a_driver_of_other_coils(tmp_path: Path) -> None:
    """An emulated OctoMag announces its 8 named channels and limits over the wire and
    drives them; with the paper's rig's emulator behind an OctoMag protocol the run is
    refused at the rig's handshake (before a folder is made), naming both sets of coils."""
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from test_hardware import _driver, _serve, _stop

    from magrun.protocol import load_protocol
    from magrun.rigs.emulator import RigEmulator
    from magrun.rigs.sim import SimRig
    from magrun.runner import run_protocol
    from magrun.trial import HardwareSpec, RunError

    octomag = CoilSystem.load(ROOT / "systems" / "octomag")
    with RigEmulator(SimRig.default(robot="micro_magnet", coils=octomag)) as emu:
        driver = _driver(emu)
        try:
            assert driver.channel_names == tuple(f"Coil_{i}" for i in range(8))
            assert driver.max_current == octomag.max_current == 10.0
            applied = driver.send(np.r_[1e3, -5.0, np.zeros(6)])
            assert applied[0] == 10.0  # the system's limit
            assert applied[1] == -5.0
        finally:
            driver.close()
    overrides = ("quick.methods=[baseline2]", "quick.duration_s=1")
    protocol = load_protocol(ROOT / "protocols" / "octomag.yaml", overrides)
    proc, url = _serve(tmp_path, "--no-camera")
    try:  # the paper's rig behind the wire: refused at the handshake, before any folder
        with pytest.raises(RunError, match=r"the rig drives small_N.*Coil_0"):
            run_protocol(protocol, tmp_path / "out", quick=True, rig=HardwareSpec(url))
    finally:
        _stop(proc)
    assert not (tmp_path / "out").exists()


def test_import_comsol_writes_a_system_folder_a_protocol_runs_on(tmp_path: Path) -> None:
    """`magrun field import-comsol --out DIR` writes the same kind of folder as the MPEM
    importer: with the shipped maps exported and imported again, the folder's Zernike
    model is the shipped one and a protocol naming the folder runs as on the paper's rig."""
    import json

    from magrun.field.comsol import write_comsol_map

    shipped = ReferenceMaps.load()
    args = []
    for name in ("small", "medium", "large"):
        write_comsol_map(tmp_path / f"{name}.txt", shipped[name], length_unit="mm")
        args += [f"--{name}", str(tmp_path / f"{name}.txt")]
    folder = tmp_path / "paper_rig"
    result = CliRunner().invoke(cli, ["field", "import-comsol", *args, "--out", str(folder)])
    assert result.exit_code == 0, result.output
    coils = CoilSystem.load(folder)
    assert not coils.is_map_system
    assert coils.channel_names == CoilSystem.load().channel_names
    shipped_zernike = ZernikeFieldModel.load()
    zernike = ZernikeFieldModel.load(system=folder)
    p = np.random.default_rng(5).uniform(-0.04, 0.04, (20, 2))
    assert_allclose(
        zernike.unit_field(p), shipped_zernike.unit_field(p), rtol=0,
        atol=1e-6 * np.max(np.abs(shipped_zernike.unit_field(p))),
    )  # fmt: skip
    runs = {}
    for name, system in (("shipped", None), ("folder", folder)):
        protocol = tmp_path / f"{name}.yaml"
        protocol.write_text(
            f"name: {name}\n" + (f"system: {system}\n" if system else "")
            + "trajectory: {kind: s_curve, size_mm: 43, speed_mm_s: 3}\nmethods: [baseline2]\n"
            "trials: 1\nduration_s: 2\nfeedback: {camera: false}\n"
            "controller: {rate_hz: 25.5, latency_ms: 5}\n"
        )  # fmt: skip
        result = CliRunner().invoke(cli, ["run", str(protocol), "--out", str(tmp_path / "r")])
        assert result.exit_code == 0, result.output
        runs[name] = json.loads((tmp_path / "r" / name / "manifest.json").read_text())
    a, b = (runs[k]["trials"][0]["rms_position_mm"] for k in ("shipped", "folder"))
    # the export holds the field only: the folder's gradients are finite differences of it
    # (within 5 % of the largest, tests/test_comsol.py), so the plant and Baseline 2's
    # tables differ that much, and the tracking a little
    assert b == pytest.approx(a, rel=0.1)


def test_a_paper_kind_folder_plans_and_simulates_on_its_own_maps_fit_and_limits(
    tmp_path: Path, uncompiled: None
) -> None:
    """A folder of the paper's kind (what ``import-comsol --out`` writes) holding maps twice
    the shipped ones, their fit (the shipped fit doubled: a least-squares fit is linear in
    the data) and a 12 A limit: every method plans with the folder's model and limit (not the
    shipped rig's and its 30 A), and the simulated plant runs on the folder's maps. Exact:
    the doubled coefficients and tables are the same floating-point operations, times 2."""
    import json
    from importlib import resources

    from magrun.control import METHODS
    from magrun.field.grid import ChannelGrid
    from magrun.field.reference import FieldMap
    from magrun.protocol import Protocol
    from magrun.trial import assemble, build_controller, single_trial

    folder = tmp_path / "doubled"
    folder.mkdir()
    data = resources.files("magrun.field") / "data"
    text = (data / "coils.yaml").read_text(encoding="utf-8")
    assert "max_current_a: 30.0" in text
    (folder / "system.yaml").write_text(text.replace("max_current_a: 30.0", "max_current_a: 12.0"))
    shipped_maps = ReferenceMaps.load()
    doubled = {n: FieldMap(m.x, m.y, 2 * m.B, 2 * m.dB) for n, m in shipped_maps.maps.items()}
    ReferenceMaps(doubled, shipped_maps.meta).save(folder / "reference_maps.npz")
    doc = json.loads((data / "zernike_model.json").read_text(encoding="utf-8"))
    for fit in doc["coil_types"].values():
        fit["bx"] = [2 * v for v in fit["bx"]]
        fit["by"] = [2 * v for v in fit["by"]]
    (folder / "zernike_model.json").write_text(json.dumps(doc))

    protocol = Protocol.model_validate(
        {"name": "p", "system": str(folder), "methods": list(METHODS),
         "trajectory": {"kind": "s_curve", "size_mm": 20, "speed_mm_s": 2}}
    )  # fmt: skip
    rng = np.random.default_rng(3)
    p = rng.uniform(-0.02, 0.02, (6, 2))
    currents = rng.uniform(-10, 10, (6, 8))
    shipped_zernike = ZernikeFieldModel.load()
    shipped_lut = LookupTableFieldModel.load()
    for method in METHODS:
        controller = build_controller(single_trial(protocol, method, 0)).controller
        assert np.all(controller.max_current == 12.0), method
        model = controller.planner.model
        shipped = shipped_zernike if isinstance(model, ZernikeFieldModel) else shipped_lut
        for got, want in zip(
            model.field_and_gradient(p, currents), shipped.field_and_gradient(p, currents),
            strict=True,
        ):  # fmt: skip
            assert_allclose(got, 2 * want, rtol=1e-12, atol=0), method
    rig = assemble(single_trial(protocol, "baseline1", 0)).rig
    assert_allclose(rig.grid.table, 2 * ChannelGrid.load().table, rtol=1e-12, atol=0)


def _limited_octomag(tmp_path: Path) -> Path:
    """OctoMag with Coil_0's slew limited to 0.5 A/s and Coil_1's current to 0.2 A (the
    others: 10 A, 200 A/s; the micro robot's S takes up to ~0.45 A and 0.06–0.18 A per tick
    on each coil)."""
    import shutil

    folder = tmp_path / "octomag_limited"
    shutil.copytree(ROOT / "systems" / "octomag", folder)
    text = (folder / "system.yaml").read_text()
    (folder / "system.yaml").write_text(
        text.replace("channel_limits: {}\n", "")
        + "channel_limits:\n  Coil_0: {max_slew_rate_a_per_s: 0.5}\n"
        "  Coil_1: {max_current_a: 0.2}\n"
    )
    return folder


def test_per_channel_limits_hold_in_every_method_and_over_the_wire(tmp_path: Path) -> None:
    """A channel with its own limits: the system's limit vectors, the recorded currents of
    the NMPC and of a two-layer baseline within them tick by tick (while the limited coil is
    used up to its limit), and HELLO announcing one limit per channel."""
    import json

    folder = _limited_octomag(tmp_path)
    coils = CoilSystem.load(folder)
    assert_allclose(coils.max_current, [10.0, 0.2] + [10.0] * 6)
    assert_allclose(coils.max_slew_rate, [0.5] + [200.0] * 7)
    protocol = tmp_path / "limited.yaml"
    protocol.write_text(
        f"name: limited\nsystem: {folder}\nrobot: micro_magnet\n"
        "trajectory: {kind: s_curve, size_mm: 12, speed_mm_s: 1}\n"
        "methods: [proposed, baseline3]\ntrials: 1\nduration_s: 4\nfeedback: {camera: false}\n"
        "controller: {rate_hz: 25.5, latency_ms: 5}\n"
    )
    result = CliRunner().invoke(cli, ["run", str(protocol), "--out", str(tmp_path / "r")])
    assert result.exit_code == 0, result.output
    manifest = json.loads((tmp_path / "r" / "limited" / "manifest.json").read_text())
    from magrun.recordings.reader import read_ticks

    dt = 1 / 25.5
    for entry in manifest["trials"]:
        assert entry["status"] == "ok", entry
        I = read_ticks(tmp_path / "r" / "limited" / entry["mcap"]).currents
        step = np.max(np.abs(np.diff(I[:, 0])))
        assert step <= 0.5 * dt + 1e-9, entry["method"]
        assert step > 0.9 * 0.5 * dt, entry["method"]  # the slew limit binds
        assert np.max(np.abs(I[:, 1])) <= 0.2 + 1e-9, entry["method"]
        assert np.max(np.abs(I)) <= 10.0 + 1e-9, entry["method"]
    # the NMPC's own bounds, per channel: |u| ≤ 1 in units of each channel's limit, and a
    # slew bound per step of each channel's slew over its limit (its cost is per (I/I_max)²:
    # it leaves a coil of a low current limit nearly idle)
    from magrun.control.nmpc import NMPC, NMPCConfig
    from magrun.robot import load_robot

    nmpc = NMPC(ZernikeFieldModel.load(system=folder), load_robot("micro_magnet"), NMPCConfig())
    assert_allclose(nmpc.problem.du_max, [0.5 * 0.04 / 10, 200 * 0.04 / 0.2] + [0.8] * 6)
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from test_hardware import _driver

    from magrun.rigs.emulator import RigEmulator
    from magrun.rigs.sim import SimRig

    with RigEmulator(SimRig.default(robot="micro_magnet", coils=coils)) as emu:
        driver = _driver(emu)
        try:
            assert_allclose(driver.max_current, coils.max_current)
            assert_allclose(driver.max_slew_rate, coils.max_slew_rate)
            applied = driver.send(np.full(8, 1e3))
            assert applied[1] == 0.2  # the emulated amplifier's own limit
        finally:
            driver.close()


def test_channel_limits_must_name_channels(tmp_path: Path) -> None:
    folder = _limited_octomag(tmp_path)
    (folder / "system.yaml").write_text(
        (folder / "system.yaml").read_text().replace("Coil_0: {max_slew", "Coil_9: {max_slew")
    )
    from magrun.field.coils import CoilFileError

    with pytest.raises(CoilFileError, match=r"system.yaml:\d+: channel_limits: .*Coil_9"):
        CoilSystem.load(folder)


def test_a_system_is_loaded_once_and_again_when_its_files_change(tmp_path: Path) -> None:
    """load_system: one object per folder while its files stay as they are (its models built
    once), a fresh one when a file changes (here the limit: 10 A -> 7.5 A)."""
    import shutil

    from magrun.field.system import load_system

    folder = tmp_path / "octomag"
    shutil.copytree(ROOT / "systems" / "octomag", folder)
    first = load_system(folder)
    assert load_system(folder) is first
    assert first.models is first.models
    assert float(np.max(first.coils.max_current)) == 10.0
    text = (folder / "system.yaml").read_text()
    (folder / "system.yaml").write_text(text.replace("max_current_a: 10.0", "max_current_a: 7.5"))
    second = load_system(folder)
    assert second is not first
    assert float(np.max(second.coils.max_current)) == 7.5
    assert float(np.max(second.models[0].coils.max_current)) == 7.5


def test_the_field_commands_refuse_to_replace_their_outputs_unasked(tmp_path: Path) -> None:
    """import-mpem, fit, import-comsol and reference write files a lab keeps (a system
    folder, a fit, maps): where one of their outputs exists they exit 2 naming it, before any
    work and with the file unchanged; with --overwrite they replace it."""
    (tmp_path / "three.yaml").write_text(SYNTHETIC)
    folder = tmp_path / "system"
    mpem = ["field", "import-mpem", str(tmp_path / "three.yaml"), "--plane-z-mm", "0",
            "--center-mm", "0", "0", "--half-width-mm", "10", "--out", str(folder)]  # fmt: skip
    assert CliRunner().invoke(cli, mpem).exit_code == 0
    from magrun.field.comsol import write_comsol_map

    maps = ReferenceMaps.load(folder / "reference_maps.npz")
    comsol = []
    for name in ("north", "east", "south"):
        write_comsol_map(tmp_path / f"{name}.txt", maps[name], length_unit="mm", field_unit="mT")
    for name in ("small", "medium", "large"):
        comsol += [f"--{name}", str(tmp_path / "north.txt")]
    commands = {
        "import-mpem": (mpem, folder / "system.yaml"),
        "fit --system": (["field", "fit", "--system", str(folder)], folder / "zernike_model.json"),
        "import-comsol": (
            ["field", "import-comsol", *comsol, "--out", str(tmp_path / "m.npz")],
            tmp_path / "m.npz",
        ),
        "reference": (
            ["field", "reference", "--pitch-mm", "5", "--out", str(tmp_path / "ref.npz")],
            tmp_path / "ref.npz",
        ),
    }
    for name, (args, written) in commands.items():
        written.write_bytes(b"a lab's file")
        before = written.read_bytes()
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 2, (name, result.output)
        assert f"{written} exists; pass --overwrite" in result.output, (name, result.output)
        assert written.read_bytes() == before, name
        result = CliRunner().invoke(cli, [*args, "--overwrite"])
        assert result.exit_code == 0, (name, result.output)
        assert written.read_bytes() != before, name
