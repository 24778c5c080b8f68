"""Hostile files to every reader that had no guard: each gives a clear message and exit 2
(or, for ``figures``, names the unreadable recording and leaves it out), never a traceback,
a hang or an allocation the file chose.

Recorded protocols and model metadata nested too deeply for the JSON decoder; UNet weights
and Zernike figure data that are not what their commands write; system folders with damaged
maps or models (refused by ``validate`` and ``run`` before a run folder exists, and by the
rig emulator before it serves); MPEM calibrations with a source in the workspace or numbers
beyond floating point; phantoms that cross themselves, enclose nothing or have no room for
the robot; protocol numbers that would run for ever.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap.reader import make_reader
from mcap.writer import Writer
from synthetic import record_tiny
from test_emns import SYNTHETIC

from magrun.cli import cli
from magrun.field.fitting import FIGURE_FILE, read_figure_data
from magrun.field.mpem import MpemError, MpemModel, import_mpem
from magrun.protocol import load_protocol
from magrun.runner import run_protocol
from magrun.trial import RunError, build_scene, check_system, free_space_of, path_clearance
from magrun.yamlio import MAX_YAML_CHARS, YamlModelError, safe_json

DEEP = "[" * 200_000 + "]" * 200_000


def _invoke(*args: object) -> tuple[int, str]:
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert "Traceback" not in result.output, result.output
    assert not isinstance(result.exception, RecursionError | MemoryError), result.exception
    return result.exit_code, result.output


# --------------------------------------------------------------------------------------------
# JSON


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (DEEP, "nested too deeply"),
        ('{"a": NaN}', "NaN is not a JSON number"),
        ('{"a": -Infinity}', "-Infinity is not a JSON number"),
        ("1" * 5000, "not valid JSON"),  # more digits than Python converts
        ("{'a': 1}", "not valid JSON"),
        (" " * (MAX_YAML_CHARS + 1), "not read"),
    ],
)
def test_safe_json_refuses_what_the_decoder_chokes_on(text: str, message: str) -> None:
    with pytest.raises(YamlModelError) as err:
        safe_json(text, "the file")
    assert str(err.value).startswith("the file: ")
    assert message in str(err.value)
    assert safe_json('{"a": [1, 2.5e-3, null]}', "x") == {"a": [1, 2.5e-3, None]}


# --------------------------------------------------------------------------------------------
# recordings


def _retag(src: Path, dst: Path, name: str, key: str, value: str) -> None:
    """Copy an MCAP file, replacing its metadata record ``name``'s ``key`` by ``value``."""
    with src.open("rb") as f, dst.open("wb") as g:
        reader, writer = make_reader(f), Writer(g)
        header = reader.get_header()
        writer.start(header.profile, header.library)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {
            s.id: writer.register_schema(s.name, s.encoding, s.data)
            for s in summary.schemas.values()
        }
        channels = {
            c.id: writer.register_channel(
                c.topic, c.message_encoding, schemas.get(c.schema_id, 0), c.metadata
            )
            for c in summary.channels.values()
        }
        for record in reader.iter_metadata():
            data = dict(record.metadata)
            if record.name == name:
                data[key] = value
            writer.add_metadata(record.name, data)
        for _, channel, message in reader.iter_messages():
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time,
                message.sequence,
            )  # fmt: skip
        writer.finish()


@pytest.fixture(scope="module")
def deep_protocol(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded run whose one trial's protocol record is JSON nested 200,000 deep."""
    root = tmp_path_factory.mktemp("deep")
    src = record_tiny(root, ["methods=[baseline3]", "sweep.tracking_rate_hz=[25.5]"])
    good = src["baseline3"]
    bad = good.with_name("bad.mcap")
    _retag(good, bad, "protocol", "json", DEEP)
    bad.replace(good)
    good.with_suffix(".rrd").unlink(missing_ok=True)
    return good


def test_a_recorded_protocol_nested_too_deeply_is_refused(
    deep_protocol: Path, tmp_path: Path
) -> None:
    code, out = _invoke("replay", deep_protocol, "--out", tmp_path / "r.mcap")
    assert code == 2, out
    assert "nested too deeply" in out, out
    code, out = _invoke("replay", deep_protocol, "--resimulate", "--out", tmp_path / "s.mcap")
    assert code == 2, out
    assert "nested too deeply" in out, out
    code, out = _invoke("identify", deep_protocol, "--out", tmp_path / "robots.yaml")
    assert code == 2, out
    assert "nested too deeply" in out, out
    assert not list(tmp_path.iterdir())  # nothing written
    # the analysis leaves it out by name (exit 1: the rest would still make figures)
    code, out = _invoke("figures", deep_protocol.parents[2], "--out", tmp_path / "fig")
    assert code == 1, out
    assert f"unreadable: {deep_protocol}" in out
    assert "the recorded protocol is not readable JSON" in out


# --------------------------------------------------------------------------------------------
# UNet weights and Zernike figure data


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)  # type: ignore[arg-type]
    return path


def _weights_cases(tmp: Path) -> dict[str, tuple[Path, str]]:
    text = tmp / "weights.npz"
    text.write_text("not an archive")
    return {
        "text": (text, "not an .npz archive"),
        "pickled": (_npz(tmp / "p.npz", meta=np.array([{}], dtype=object)), "Object arrays"),
        "no meta": (_npz(tmp / "m.npz", x=np.zeros(3)), "no `meta` array"),
        "deep meta": (_npz(tmp / "d.npz", meta=np.array(DEEP)), "nested too deeply"),
        "NaN meta": (_npz(tmp / "n.npz", meta=np.array('{"widths": [NaN]}')), "NaN"),
        "huge widths": (
            _npz(tmp / "h.npz", meta=np.array('{"widths": [100000000, 100000000]}')),
            "`widths` must be",
        ),
        "negative widths": (_npz(tmp / "w.npz", meta=np.array('{"widths": [-3]}')), "`widths`"),
        "arrays of another net": (
            _npz(tmp / "o.npz", meta=np.array('{"widths": [8, 16]}'), bogus=np.zeros(2)),
            "does not fit a UNet",
        ),
        "arrays missing": (_npz(tmp / "a.npz", meta=np.array('{"widths": [8, 16]}')), "missing"),
    }


def test_weights_files_that_are_not_weights_are_refused(tmp_path: Path) -> None:
    from magrun.tracking.tracker import default_weights_path
    from magrun.tracking.unet import load_weights

    model, meta = load_weights(default_weights_path())  # the shipped weights pass the checks
    assert meta["widths"] == list(model.widths)
    for case, (path, message) in _weights_cases(tmp_path).items():
        with pytest.raises(ValueError, match=re.escape(message)):
            load_weights(path)
        code, out = _invoke("tracker", "eval", "--weights", path, "--frames", "10")
        assert code == 2, (case, out)
        assert message in out, (case, out)


def test_zernike_figure_data_is_checked_before_the_recordings_are_read(tmp_path: Path) -> None:
    from analysis.figures import zernike

    shipped = Path(__file__).parents[1] / "magrun" / "field" / "data" / FIGURE_FILE
    good = read_figure_data(shipped)
    one_type = {k: v for k, v in good.items() if k.startswith("medium_")}
    fig = zernike(one_type)  # a fit without the paper's small coil: its first type
    assert "medium coil" in fig.axes[1].get_title()
    cases = {
        "nan": ({**good, "small_r2": good["small_r2"] * np.nan}, "not an array of finite"),
        "shape": ({**good, "small_field_mT": good["small_field_mT"][:5]}, "shape (5, 101)"),
        "missing": ({k: v for k, v in good.items() if k != "small_x_mm"}, "no small_x_mm"),
        "none": ({"x": np.zeros(2)}, "no coil type's fit"),
        "text": ({"small_orders": np.array(["a", "b"])}, "no small_mae_mT"),
    }
    empty = tmp_path / "recordings"
    empty.mkdir()
    for case, (arrays, message) in cases.items():
        path = _npz(tmp_path / f"{case}.npz", **arrays)
        with pytest.raises(ValueError, match=re.escape(message)):
            read_figure_data(path)
        code, out = _invoke("figures", empty, "--zernike-data", path)
        assert code == 2, (case, out)
        assert "not Zernike figure data" in out, (case, out)
        assert message in out, (case, out)


# --------------------------------------------------------------------------------------------
# system folders and MPEM calibrations


@pytest.fixture(scope="module")
def three(tmp_path_factory: pytest.TempPathFactory) -> Path:
    base = tmp_path_factory.mktemp("three")
    (base / "three.yaml").write_text(SYNTHETIC)
    return import_mpem(base / "three.yaml", base / "system", 0.0, (0.0, 0.0), 10e-3)


def _damaged(three: Path, tmp: Path, case: str) -> Path:
    folder = tmp / case
    shutil.copytree(three, folder)
    maps = folder / "reference_maps.npz"
    arrays = dict(np.load(maps))
    if case == "truncated maps":
        maps.write_bytes(maps.read_bytes()[:2000])
    elif case == "NaN map":
        arrays["north.B"] = arrays["north.B"] * np.nan
        _npz(maps, **arrays)
    elif case == "pickled map":
        arrays["north.B"] = np.array([{}], dtype=object)
        _npz(maps, **arrays)
    elif case == "model nested too deeply":
        (folder / "zernike_model.json").write_text(DEEP)
    elif case == "empty model":
        (folder / "zernike_model.json").write_text("{}")
    return folder


DAMAGE = {
    "truncated maps": "reference_maps.npz: not a readable magrun reference-map file",
    "NaN map": "non-finite",
    "pickled map": "Object arrays",
    "model nested too deeply": "zernike_model.json: not a readable magrun Zernike model: not "
    "valid JSON: nested too deeply",
    "empty model": "unsupported format_version",
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
def test_a_damaged_system_folder_is_refused_before_anything_runs(
    three: Path, tmp_path: Path, case: str
) -> None:
    folder = _damaged(three, tmp_path, case)
    protocol = tmp_path / "p.yaml"
    protocol.write_text(
        f"name: p\nsystem: {folder}\nrobot: micro_magnet\nfeedback: {{camera: false}}\n"
        "trajectory: {kind: s_curve, size_mm: 4, speed_mm_s: 2}\nmethods: [proposed]\n"
        "trials: 1\nduration_s: 1\n"
    )
    code, out = _invoke("run", protocol, "--out", tmp_path / "out")
    assert code == 2, out
    assert DAMAGE[case] in out, out
    assert not (tmp_path / "out" / "p").exists()
    if "map" in case:  # the emulator reads the maps (the models are the controller's)
        code, out = _invoke("rig-emulator", "--system", folder, "--port", "0")
        assert code == 2, out
        assert DAMAGE[case] in out, out


SOURCE = (
    "Coil_List: [n, m]\nn:\n  Source_List: [a]\n  a:\n    Source_Position: {pos}\n"
    "    Source_Direction: {dir}\n    B_Coeff: [{b}]\nm:\n  Source_List: [a]\n  a:\n"
    "    Source_Position: [0, 0.05, 0]\n    Source_Direction: [0, 1, 0]\n    B_Coeff: [1.0e-7]\n"
)


@pytest.mark.parametrize(
    ("pos", "b", "message"),
    [
        ("[0.002, 0.003, 0.0]", "1.0e-7", "lies 0 mm from the workspace square"),
        ("[0.0, 0.0, 1.0e-12]", "1.0e-7", "from the workspace square"),
        ("[0.012, 0.0, 0.0]", "1.0e-7", "lies 2 mm from the workspace square"),  # < 2.5 mm pitch
        ("[1.0e300, 0, 0]", "1.0e-7", "a source more than 1e+09 m from the origin"),
        ("[0, 0, 0.1]", "1.0e300", "a coefficient larger than 1e+30"),
    ],
)
def test_mpem_sources_in_the_workspace_or_beyond_floating_point_are_refused(
    tmp_path: Path, pos: str, b: str, message: str
) -> None:
    path = tmp_path / "cal.yaml"
    path.write_text(SOURCE.format(pos=pos, dir="[0, 0, 1]", b=b))
    code, out = _invoke(
        "field", "import-mpem", path, "--plane-z-mm", "0", "--center-mm", "0", "0",
        "--half-width-mm", "10", "--pitch-mm", "2.5", "--out", tmp_path / "out",
    )  # fmt: skip
    assert code == 2, out
    assert message in out, out
    assert not (tmp_path / "out").exists()


def test_a_direction_of_huge_components_is_normalised_not_lost(tmp_path: Path) -> None:
    """Its squares overflow: scaled first, (1e308, 1e308, 0) is (1, 1, 0)/√2."""
    path = tmp_path / "cal.yaml"
    path.write_text(SOURCE.format(pos="[0, 0, 0.1]", dir="[1.0e308, 1.0e308, 0]", b="1.0e-7"))
    source = MpemModel.load(path).doc.coils["n"].sources["a"]
    np.testing.assert_allclose(source.direction, [math.sqrt(0.5), math.sqrt(0.5), 0], atol=1e-15)
    path.write_text(SOURCE.format(pos="[0, 0, 0.1]", dir="[0, 0, 0]", b="1.0e-7"))
    with pytest.raises(MpemError, match="zero length"):
        MpemModel.load(path)


# --------------------------------------------------------------------------------------------
# phantoms and protocol numbers

SQUARE = "[[-10, -3], [10, -3], [10, 3], [-10, 3], [-10, -3]]"
PHANTOMS = {
    "a bow tie": (
        "boundaries:\n  a:\n    - points: [[-10, -10], [10, 10]]\n  b:\n"
        "    - points: [[10, 10], [10, -10]]\n  c:\n    - points: [[10, -10], [-10, 10]]\n"
        "  d:\n    - points: [[-10, 10], [-10, -10]]\n",
        "not a simple closed curve (Self-intersection[0 0]",
    ),
    "a point": ("boundaries:\n  a:\n    - points: [[0, 0], [0, 0]]\n", "enclose no area"),
    "a line there and back": (
        "boundaries:\n  a:\n    - points: [[0, 0], [10, 0]]\n"
        "  b:\n    - points: [[10, 0], [0, 0]]\n",
        "enclose no area",
    ),
    "an arc of a billion mm": (
        "boundaries:\n  a:\n    - arc: {center: [0, 0], radius: 1.0e9, from_deg: 0, to_deg: 360}\n",
        "arc.radius: Input should be less than or equal to 1000",
    ),
    "an arc of a million turns": (
        "boundaries:\n  a:\n    - arc: {center: [0, 0], radius: 10, from_deg: 0, to_deg: 3.6e8}\n",
        "arc.to_deg: Input should be less than or equal to 720",
    ),
    "two turns": (
        "boundaries:\n  a:\n    - arc: {center: [0, 0], radius: 10, from_deg: 0, to_deg: 720}\n",
        "an arc sweeps at most 360 degrees",
    ),
    "a path outside": (
        f"boundaries:\n  a:\n    - points: {SQUARE}\npath:\n  - points: [[0, 0], [0, 8]]\n",
        "the path leaves the outline: (0, 8) mm is outside",
    ),
}


def _phantom_protocol(tmp: Path, phantom: str) -> Path:
    (tmp / "ph.yaml").write_text(f"name: ph\ncritical: a\n{phantom}")
    protocol = tmp / "p.yaml"
    protocol.write_text(
        "name: p\nrobot: magnet\nworkspace: {kind: spine_phantom, phantom: ph.yaml}\n"
        "trajectory: {kind: out_and_back, path: phantom, speed_mm_s: 3, hold_s: 0.5, "
        "flip_s: 0.5}\nmethods: [proposed]\nfeedback: {camera: false}\ntrials: 1\n"
    )
    return protocol


@pytest.mark.parametrize("case", sorted(PHANTOMS))
def test_phantoms_that_are_no_outline_are_refused_by_validate(tmp_path: Path, case: str) -> None:
    text, message = PHANTOMS[case]
    protocol = _phantom_protocol(tmp_path, text)
    code, out = _invoke("validate", protocol)
    assert code == 2, out
    assert message in out, out
    assert "ph.yaml" in out


def test_a_phantom_with_no_room_for_the_robot_is_refused_before_a_run(tmp_path: Path) -> None:
    """A 0.5 mm square (the magnet robot is longer), and one outside the coils' workspace."""
    for corners in ("[[0, 0], [0.5, 0], [0.5, 0.5], [0, 0.5], [0, 0]]",
                    "[[100, 100], [110, 100], [110, 110], [100, 110], [100, 100]]"):  # fmt: skip
        inside = corners.split("], [")[0].strip("[")
        x, y = (float(v) + 0.2 for v in inside.split(","))
        protocol = _phantom_protocol(
            tmp_path,
            f"boundaries:\n  a:\n    - points: {corners}\npath:\n  - points: [[{x}, {y}], "
            f"[{x + 0.05}, {y + 0.05}]]\n",
        )
        with pytest.raises(RunError, match="fits nowhere"):
            check_system(load_protocol(protocol))
        code, out = _invoke("run", protocol, "--out", tmp_path / "out")
        assert code == 2, out
        assert "fits nowhere" in out, out
        assert not (tmp_path / "out" / "p").exists()


def _band_protocol(tmp: Path, y0: float) -> Path:
    """A 30 mm band with its critical floor at y = -15 mm and a path along y = ``y0`` mm: the
    16 mm magnet robot's least clearance on it is ``y0`` + 15 − 8 mm, where it turns in place
    at the far end (an end 8 mm below its centre) as an out-and-back path does."""
    return _phantom_protocol(
        tmp,
        "boundaries:\n  a:\n    - points: [[-30, -15], [30, -15]]\n  b:\n"
        "    - points: [[30, -15], [30, 15], [-30, 15], [-30, -15]]\n"
        f"path:\n  - points: [[-5, {y0}], [5, {y0}]]\n",
    )


def test_a_path_that_puts_the_body_on_the_critical_boundary_is_refused(tmp_path: Path) -> None:
    """The body on the path 0.02 mm from the critical floor (within the 0.05 mm that counts
    as touching): refused before a run, naming where; --allow-infeasible runs it."""
    protocol = _band_protocol(tmp_path, -6.98)
    with pytest.raises(RunError, match=r"comes within 0\.02 mm of the critical boundary 'a' at"):
        check_system(load_protocol(protocol))
    check_system(load_protocol(protocol), feasibility=False)
    through = _band_protocol(tmp_path, -7.5)  # the turning body 0.5 mm through the floor
    with pytest.raises(RunError, match=r"overlaps the critical boundary 'a' by 0\.50 mm at \(5"):
        check_system(load_protocol(through))
    protocol = _band_protocol(tmp_path, -6.98)
    code, out = _invoke("run", protocol, "--out", tmp_path / "out")
    assert code == 2, out
    assert "every trial would count as touching it" in out, out
    assert "move the path ('path' in " in out, out
    assert not (tmp_path / "out" / "p").exists()


@pytest.mark.parametrize("y0", [-6.7, -6.0])
def test_a_path_close_to_the_critical_boundary_is_warned_of(tmp_path: Path, y0: float) -> None:
    """0.3 mm of clearance on the path (less than the NMPC's 0.5 mm corridor margin) is run
    with a warning that gives it; 1 mm is not warned of. The least clearance is the turn's
    (theory: ``y0`` + 7 mm, to 1 µm)."""
    protocol = load_protocol(_band_protocol(tmp_path, y0))
    scene = build_scene(protocol)
    clear = path_clearance(scene, free_space_of(scene, protocol.robot_params()))
    assert clear is not None
    assert clear.least == pytest.approx((y0 + 7.0) * 1e-3, abs=1e-6)
    assert clear.position[0] == pytest.approx(5e-3, abs=1e-6)  # where it turns
    warned: list[str] = []
    check_system(protocol, feasibility=False, warn=warned.append)
    if y0 + 7.0 < 0.5:
        assert len(warned) == 1, warned
        assert "comes within 0.30 mm of the critical boundary 'a'" in warned[0], warned
        # a run passes it on as it starts and keeps it in the manifest (no trial run here)
        told: list[str] = []
        manifest = run_protocol(
            protocol, tmp_path / "out", executor=lambda *_: iter(()), check_reach=False,
            warn=told.append,
        )  # fmt: skip
        assert told == warned
        assert manifest["warnings"] == warned
        assert (
            json.loads((tmp_path / "out" / "p" / "manifest.json").read_text())["warnings"] == warned
        )
    else:
        assert warned == []


def test_the_path_is_checked_between_its_poses(tmp_path: Path) -> None:
    """A path of two points 40 mm apart over a spike of the critical floor (up to y = -7.7 mm)
    midway: at the reference's poses (its ends and the turn) the body clears the floor by
    1 mm at least, but crossing the spike it clears it by 1.7 − 1.4 = 0.3 mm (its axis
    1.7 mm above the spike's tip), and that is what the check finds (to 10 µm) and warns of."""
    protocol = load_protocol(
        _phantom_protocol(
            tmp_path,
            "boundaries:\n  a:\n    - points: [[-30, -15], [-1, -15], [0, -7.7], [1, -15], "
            "[30, -15]]\n  b:\n    - points: [[30, -15], [30, 15], [-30, 15], [-30, -15]]\n"
            "path:\n  - points: [[-20, -6], [20, -6]]\n",
        )
    )
    scene = build_scene(protocol)
    space = free_space_of(scene, protocol.robot_params())
    assert space.clearances(scene.reference.poses, ["a"]).min() == pytest.approx(1e-3, abs=1e-9)
    clear = path_clearance(scene, space)
    assert clear is not None
    assert clear.least == pytest.approx(0.3e-3, abs=10e-6)
    assert abs(clear.position[0]) <= 6.6e-3 + 10e-6  # the body's axis over the spike
    assert clear.position[1] == pytest.approx(-6e-3, abs=1e-9)
    warned: list[str] = []
    check_system(protocol, feasibility=False, warn=warned.append)
    assert len(warned) == 1, warned
    assert "comes within 0.30 mm" in warned[0], warned


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_path_check_finds_the_least_clearance_a_dense_sampling_finds(
    tmp_path: Path, seed: int
) -> None:
    """A critical floor of random bumps and a path of four random points above it: the
    check's least clearance (branch and bound) is a dense sampling's (40 001 poses along
    the reference, 2–4 µm of the body's travel apart) within 10 µm plus that spacing, and
    the body at the time it reports has the clearance it reports."""
    rng = np.random.default_rng(seed)
    floor = np.column_stack([np.linspace(-30, 30, 13), -12 + rng.uniform(-2, 2, 13)])
    path = np.column_stack([np.sort(rng.uniform(-20, 20, 4)), rng.uniform(-4, 2, 4)])
    text = (
        f"boundaries:\n  a:\n    - points: {floor.round(3).tolist()}\n  b:\n"
        f"    - points: [[30, {floor[-1, 1]:.3f}], [30, 15], [-30, 15], [-30, "
        f"{floor[0, 1]:.3f}]]\npath:\n  - points: {path.round(3).tolist()}\n"
    )
    protocol = load_protocol(_phantom_protocol(tmp_path, text))
    scene = build_scene(protocol)
    space = free_space_of(scene, protocol.robot_params())
    clear = path_clearance(scene, space)
    assert clear is not None
    ref = scene.reference
    dense = space.clearances(ref.pose(np.linspace(0.0, ref.duration, 40_001)), ["a"]).min()
    assert clear.least == pytest.approx(dense, abs=14e-6)
    there = space.clearances(ref.pose([clear.t]), ["a"])[0]
    assert there == pytest.approx(clear.least, abs=1e-12)
    np.testing.assert_allclose(ref.pose(clear.t)[:2], clear.position, atol=1e-12)


def test_a_trajectory_leaving_the_workspace_is_refused(tmp_path: Path) -> None:
    protocol = tmp_path / "p.yaml"
    protocol.write_text(
        "name: p\nrobot: magnet\ntrajectory: {kind: s_curve, size_mm: 300, speed_mm_s: 3}\n"
        "methods: [proposed]\ntrials: 1\n"
    )
    code, out = _invoke("run", protocol, "--out", tmp_path / "out")
    assert code == 2, out
    assert "trajectory: leaves the coils' workspace at" in out, out
    assert not (tmp_path / "out" / "p").exists()


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("controller.rate_hz=1e9", "less than or equal to 1000"),
        ("controller.rate_hz=0.001", "greater than or equal to 1"),
        ("controller.latency_ms=1e9", "a latency is from 0 to 10000 ms"),
        ("controller.latency_ms=.nan", "a latency is from 0 to 10000 ms"),
        ("conditions.noise_sigma_mm=1e9", "less than or equal to 1000"),
        ("sweep.noise_sigma_mm=[0, 1e9]", "less than or equal to 1000"),
        ("simulation.mass_sigma=1e9", "less than or equal to 2"),
        ("controller.kalman.process_sigma_mm=1e9", "less than or equal to 1000"),
        ("safety.stall_timeout_ms=1e12", "less than or equal to 10000"),
    ],
)
def test_numbers_that_would_run_for_ever_are_refused(
    tmp_path: Path, setting: str, message: str
) -> None:
    from synthetic import TINY

    with pytest.raises(YamlModelError) as err:
        load_protocol(TINY, (setting,))
    assert message in str(err.value), str(err.value)
    code, out = _invoke("run", TINY, "--set", setting, "--out", tmp_path)
    assert code == 2, out
    assert message in out, out
    assert not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------------
# one writer per output file; a killed re-simulation's leftovers


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("outputs")
    return record_tiny(root, ["methods=[baseline3]", "sweep.tracking_rate_hz=[25.5]"])["baseline3"]


def test_a_second_writer_of_one_output_is_refused(recorded: Path, tmp_path: Path) -> None:
    """Another command holds the output's lock (here this process, through another open
    file: flock locks are per open file): replay, re-simulation and recover are refused,
    the output untouched; once released, the same command writes it."""
    from magrun.atomic import OutputLock

    out = tmp_path / "mine.mcap"
    commands = {
        "replay": ["replay", recorded, "--out", out],
        "resimulate": ["replay", recorded, "--resimulate", "--out", out],
        "recover": ["recover", recorded, out],
    }
    with OutputLock(out):
        for name, args in commands.items():
            code, text = _invoke(*args)
            assert code == 2, (name, text)
            assert "is being written by another magrun" in text, (name, text)
            assert not out.exists(), name
    code, text = _invoke(*commands["recover"])
    assert code == 0, text
    assert out.is_file()
    assert not list(tmp_path.glob(".*lock")), "the lock file is removed on release"


def test_a_killed_resimulations_folder_is_taken_by_the_next(recorded: Path, tmp_path: Path) -> None:
    """A re-simulation records into a hidden ``.NAME.part`` folder beside its output; one
    that a SIGKILL left is removed by the next re-simulation into that output, and the
    analysis never reads it as a trial."""
    from analysis.load import find_recordings

    out = tmp_path / "again.mcap"
    leftover = tmp_path / ".again.mcap.part" / "tiny" / "baseline3"
    leftover.mkdir(parents=True)
    shutil.copy(recorded, leftover / "trial-0.mcap")
    assert find_recordings(tmp_path) == []  # hidden: not a recording of this folder
    code, text = _invoke("replay", recorded, "--resimulate", "--out", out)
    assert code == 0, text
    assert out.is_file()
    assert out.with_suffix(".rrd").is_file()
    assert not (tmp_path / ".again.mcap.part").exists()


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("[" * 5000 + "]" * 5000, "the value is nested too deeply"),
        ("9" * 5000, "Exceeds the limit (4300 digits)"),
        ("[unclosed", "the value is not valid YAML"),
    ],
)
def test_set_values_the_yaml_parser_chokes_on(tmp_path: Path, value: str, message: str) -> None:
    from synthetic import TINY

    code, out = _invoke("run", TINY, "--set", f"trials={value}", "--out", tmp_path)
    assert code == 2, out
    assert message in out, out
    assert len(out) < 1000  # the value is cut in the message, not echoed whole


# --------------------------------------------------------------------------------------------
# Paths that are not files: reading a FIFO would wait for a writer for ever


@pytest.fixture
def fifo(tmp_path: Path) -> Path:
    import os

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    path = tmp_path / "pipe.mcap"
    os.mkfifo(path)
    return path


def test_readers_refuse_a_fifo_without_waiting(fifo: Path, tmp_path: Path) -> None:
    from analysis.load import RecordingError, find_recordings, read_recording
    from magrun.files import NotRegularFileError, open_binary
    from magrun.recordings.recover import is_mcap
    from magrun.yamlio import read_npz, read_text_file

    with pytest.raises(NotRegularFileError, match="not a regular file"):
        open_binary(fifo)
    with pytest.raises(YamlModelError, match="not a regular file"):
        read_text_file(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        read_npz(fifo, "magrun field fit")
    assert not is_mcap(fifo)
    with pytest.raises(RecordingError, match="not a regular file"):
        read_recording(fifo)
    # a folder of runs, one of whose manifests is a FIFO
    run = tmp_path / "runs" / "a"
    run.mkdir(parents=True)
    import os

    os.mkfifo(run / "manifest.json")
    with pytest.raises(RecordingError, match="not a regular file"):
        find_recordings(run.parent)


@pytest.mark.parametrize(
    "args",
    [
        ["recover", "{fifo}", "{tmp}/out.mcap"],
        ["replay", "{fifo}"],
        ["view", "{fifo}", "--save", "{tmp}/v.rrd"],
        ["identify", "{fifo}", "--out", "{tmp}/robots.yaml"],
        ["figures", "{fifo}", "--out", "{tmp}/fig"],
        ["field", "import-mpem", "{fifo}", "--plane-z-mm", "0", "--out", "{tmp}/sys"],
        ["tracker", "eval", "--weights", "{fifo}"],
        ["validate", "{fifo}"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_commands_given_a_fifo_exit_2_without_waiting(
    fifo: Path, tmp_path: Path, args: list[str]
) -> None:
    code, out = _invoke(*(a.format(fifo=fifo, tmp=tmp_path) for a in args))
    assert code == 2, out
    assert "not a regular file" in out, out
    assert "Traceback" not in out


def test_a_setting_given_twice_is_refused_naming_both_lines(tmp_path: Path) -> None:
    path = tmp_path / "twice.yaml"
    path.write_text(
        "name: twice\ntrajectory: {kind: s_curve}\nmethods: [proposed]\nseed: 1\nseed: 7\n"
    )
    with pytest.raises(
        YamlModelError, match=r"twice.yaml:5: seed: given twice \(first on line 4\)"
    ):
        load_protocol(path)
