"""The ``.rrd`` a user opens: the y-up, framed workspace view, the legend, the recording's
name and time axis, and the same views from an MCAP file as from the recorder."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from rerun.chunk import RrdReader
from test_recording import _record, _rrd_rows, _ticks

from magrun.cli import cli
from magrun.recordings.rerun_log import (
    FRAME_MARGIN,
    WORKSPACE_ROOTS,
    blueprint,
    recording_name,
    rrd_from_mcap,
    view_frame,
)
from magrun.recordings.writer import RecordingSetup
from magrun.tracking.camera import Camera

HALF = 0.05  # m, the workspace square's half-width in these tests


def _static(path: Path) -> dict[str, dict[str, Any]]:
    """Every static component of an .rrd: entity -> component -> its first row's value."""
    out: dict[str, dict[str, Any]] = defaultdict(dict)
    for chunk in RrdReader(path).stream():
        if not chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for field, column in zip(batch.schema, batch.columns, strict=True):
            if not field.name.startswith("rerun.controls"):
                out[str(chunk.entity_path)][field.name] = column.to_pylist()[0]
    return out


def _timed(path: Path, entity: str, component: str) -> tuple[np.ndarray, np.ndarray]:
    """One entity's rows on timeline ``t``: times (s) and values, sorted by time."""
    times: list[float] = []
    values: list[Any] = []
    for chunk in RrdReader(path).stream():
        if chunk.is_static or str(chunk.entity_path) != entity:
            continue
        batch = chunk.to_record_batch()
        names = batch.schema.names
        t = batch.column(names.index("t")).cast("int64").to_pylist()
        times += [v / 1e9 for v in t]
        values += batch.column(names.index(component)).to_pylist()
    order = np.argsort(times, kind="stable")
    return np.asarray(times)[order], np.asarray(values, dtype=object)[order]


def _setup(n: int, **kw: Any) -> RecordingSetup:
    """A phantom-like setup whose reference is the desired path of ``_ticks(n)``."""
    ticks = _ticks(n, None)
    fields: dict[str, Any] = {
        "trial": {"protocol": "demo", "method": "proposed", "trial": 2, "seed": 7,
                  "critical_boundary": "anterior"},
        "channel_names": tuple("abcdefgh"),
        "boundaries": {"anterior": np.array([[-0.01, 0.0], [0.01, 0.0]]),
                       "posterior": np.array([[-0.01, 0.005], [0.01, 0.005]])},
        "workspace_half_width": HALF,
        "reference": np.stack([t.desired for t in ticks]),
        "recording_id": "demo/proposed/trial-2@7",
        "name": "demo/proposed/trial-2 (seed 7)",
    }  # fmt: skip
    return RecordingSetup(**{**fields, **kw})


def test_the_workspace_view_is_y_up_and_framed_on_the_square(tmp_path: Path) -> None:
    """Rerun's 2D views draw +y downward; each drawn entity under /workspace is mirrored in
    y exactly once, so a point at +y appears above the centre, as in the paper's figures
    and the camera image. Without a phantom the view is framed on the square (drawn) with a
    margin."""
    rec = _record(tmp_path / "t", _setup(30, boundaries={}), _ticks(30, None))
    static = _static(rec.rrd_path)
    flips = {e for e, comps in static.items() if "Transform3D:scale" in comps}
    assert flips == {f"/workspace/{name}" for name in WORKSPACE_ROOTS}
    for entity in flips:
        assert static[entity]["Transform3D:scale"] == [[1.0, -1.0, 1.0]]
    drawn = [e for e in _rrd_rows(rec.rrd_path) if e.startswith("/workspace/")]
    drawn += [
        e for e, comps in static.items()
        if e.startswith("/workspace/") and any(c.endswith((":strips", ":positions")) for c in comps)
    ]  # fmt: skip
    assert drawn
    for entity in drawn:  # mirrored once: one flipped ancestor (or itself) below /workspace
        parts = entity.split("/")
        chain = {"/".join(parts[: i + 1]) for i in range(2, len(parts))}
        assert len(chain & flips) == 1, entity
    # a point logged at +y is drawn at −y in the view's own (y-down) coordinates: above
    scale = np.array(static["/workspace/actual"]["Transform3D:scale"][0])
    assert (scale * np.array([0.0, 0.02, 0.0]))[1] < 0
    square = np.array(static["/workspace/square"]["LineStrips2D:strips"][0])
    np.testing.assert_allclose(np.abs(square), HALF, rtol=1e-6)  # float32 in the .rrd
    assert len(square) == 5
    assert np.allclose(square[0], square[-1])
    assert view_frame(HALF, {}) == ((0.0, 0.0), HALF)
    lo_x, hi_x, lo_y, hi_y = _bounds(blueprint(True, view_frame(HALF, {})))
    assert lo_x == pytest.approx(-HALF * (1 + FRAME_MARGIN))
    assert hi_x == -lo_x
    assert lo_y == pytest.approx(-HALF * (1 + FRAME_MARGIN))
    # the legend, under the square (below it on screen: +y in the view), is inside the frame
    legend = np.array(static["/workspace/legend"]["Points2D:positions"])
    assert -legend[:, 1].min() > HALF
    assert -legend[:, 1].max() < hi_y


def _bounds(layout: Any) -> list[float]:
    """The workspace view's visual bounds in its own (y-down) coordinates, m: x lo, hi, y lo,
    hi."""
    view = layout.root_container.contents[0].contents[-1]
    (bounds,) = view.properties["VisualBounds2D"].range.as_arrow_array().to_pylist()
    return [*bounds["x_range"], *bounds["y_range"]]


def test_the_camera_view_is_framed_on_the_whole_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recorder's layout frames the camera view on the camera's whole frame, 0..width by
    0..height px (the viewer's own framing follows the content and showed a quarter of a
    frame), also where the .rrd is rebuilt from the MCAP; without a camera there is no such
    view."""
    import magrun.recordings.rerun_log as rerun_log

    layouts: list[Any] = []
    build = rerun_log.blueprint

    def capture(*args: Any, **kwargs: Any) -> Any:
        layouts.append(build(*args, **kwargs))
        return layouts[-1]

    monkeypatch.setattr(rerun_log, "blueprint", capture)
    camera = Camera()
    height, width = camera.shape
    frame = np.zeros((height, width, 3), dtype=np.uint8)
    rec = _record(tmp_path / "t", _setup(10, camera=camera), _ticks(10, frame))
    rrd_from_mcap(rec.mcap_path, tmp_path / "converted.rrd")
    _record(tmp_path / "none", _setup(10), _ticks(10, None))
    assert len(layouts) == 3
    for layout in layouts[:2]:
        view = layout.root_container.contents[0].contents[0]
        assert view.name == "camera (px)"
        (bounds,) = view.properties["VisualBounds2D"].range.as_arrow_array().to_pylist()
        assert [*bounds["x_range"], *bounds["y_range"]] == [0, width, 0, height]
    names = [v.name for v in layouts[2].root_container.contents[0].contents]
    assert names == ["workspace from above (m, y up)"]


def test_a_phantom_fills_the_workspace_view_with_the_legend_under_it(tmp_path: Path) -> None:
    """With a phantom the view is framed on its walls' bounding square, wherever it lies in
    the workspace (here 20 x 5 mm about (0, 2.5) mm in a 100 mm square), with the legend
    under it in view: every wall and every legend entry inside the bounds, and the walls
    spanning the frame's width less its margin."""
    rec = _record(tmp_path / "t", _setup(30), _ticks(30, None))
    static = _static(rec.rrd_path)
    (cx, cy), h = view_frame(HALF, _setup(1).boundaries) or ((np.nan, np.nan), np.nan)
    assert (cx, cy, h) == pytest.approx((0.0, 0.0025, 0.01))
    lo_x, hi_x, lo_y, hi_y = _bounds(blueprint(True, ((cx, cy), h), legend_rows=2))
    assert hi_x - lo_x == pytest.approx(2 * h * (1 + FRAME_MARGIN))
    walls = np.concatenate([np.asarray(b) for b in _setup(1).boundaries.values()])
    legend = np.array(static["/workspace/legend"]["Points2D:positions"])
    for x, y in np.concatenate([walls, legend]):  # in the view: y mirrored
        assert lo_x < x < hi_x, (x, y)
        assert lo_y < -y < hi_y, (x, y)
    assert -legend[:, 1].min() > -(cy - h)  # under the walls on screen
    # seven entries (six streams and the critical wall) in two rows of four
    assert len(legend) == 7
    assert len(set(np.round(legend[:, 1], 9))) == 2


def test_the_legend_names_every_pose_stream_in_its_colour(tmp_path: Path) -> None:
    rec = _record(tmp_path / "t", _setup(5), _ticks(5, None))
    static = _static(rec.rrd_path)
    legend = static["/workspace/legend"]
    for name, colour in zip(legend["Points2D:labels"], legend["Points2D:colors"], strict=True):
        if name in ("desired", "anterior (critical wall)"):
            continue  # drawn statically: the path, the wall (below)
        assert static[f"/workspace/{name}"]["Points2D:colors"] == [colour], name
    assert len(set(legend["Points2D:colors"])) == len(legend["Points2D:colors"])
    colours = static["/coils/currents"]["SeriesLines:colors"]
    assert len(set(colours)) == 8  # one distinct colour per coil
    # the critical wall has its own colour, named in the legend in that colour (a name on
    # the drawing lands on a wall or the channel at some zoom), and on hover
    anterior = static["/workspace/boundaries/anterior"]
    posterior = static["/workspace/boundaries/posterior"]
    assert anterior["LineStrips2D:labels"] == ["anterior (critical wall)"]
    assert anterior["LineStrips2D:show_labels"] == [False]
    assert anterior["LineStrips2D:colors"] != posterior["LineStrips2D:colors"]
    assert posterior["LineStrips2D:labels"] == ["posterior"]
    named = dict(zip(legend["Points2D:labels"], legend["Points2D:colors"], strict=True))
    assert named.pop("anterior (critical wall)") == anterior["LineStrips2D:colors"][0]
    assert set(named) == {"actual", "tracked", "measured", "estimated", "predicted", "desired"}
    assert not [e for e in static if e.startswith("/workspace/boundaries/anterior/")]


def test_an_mcap_gives_the_recorders_views_name_and_time_axis(tmp_path: Path) -> None:
    """``rrd_from_mcap`` rebuilds the .rrd from the MCAP alone: the same entities with the
    same rows at the same trial times, the same static scene, name and recording id."""
    frame = np.random.default_rng(3).integers(0, 256, (32, 48, 3), dtype=np.uint8)
    n = 60  # 2.4 s at 25 Hz: flushes inside the trial and at its end
    rec = _record(tmp_path / "t", _setup(n, camera=Camera()), _ticks(n, frame))
    converted = tmp_path / "converted.rrd"
    assert rrd_from_mcap(rec.mcap_path, converted) == n
    assert _rrd_rows(converted) == _rrd_rows(rec.rrd_path)
    a, b = _static(rec.rrd_path), _static(converted)
    assert a.keys() == b.keys()
    assert b["/__properties"]["RecordingInfo:name"] == ["demo/proposed/trial-2 (seed 7)"]
    for entity in ("/workspace/square", "/workspace/legend", "/workspace/boundaries/anterior"):
        assert b[entity] == a[entity], entity
    for entity in ("/workspace/reference", "/workspace/paths/actual", "/camera/paths/actual"):
        np.testing.assert_allclose(
            np.array(b[entity]["LineStrips2D:strips"][0]),
            np.array(a[entity]["LineStrips2D:strips"][0]),
            rtol=1e-6,
        )  # fmt: skip
    for entity, component in [
        ("/errors/position_mm", "Scalars:scalars"),
        ("/coils/currents", "Scalars:scalars"),
        ("/workspace/estimated", "Points2D:positions"),
        ("/camera/measured", "Points2D:positions"),
    ]:
        t_a, v_a = _timed(rec.rrd_path, entity, component)
        t_b, v_b = _timed(converted, entity, component)
        np.testing.assert_allclose(t_b, t_a, rtol=0, atol=1e-9)  # trial time, s, from 0
        if entity == "/errors/position_mm":  # a row per tick
            np.testing.assert_allclose(t_a, np.arange(n) * 0.04, rtol=0, atol=1e-9)
        np.testing.assert_allclose(
            np.array(v_b.tolist(), dtype=float), np.array(v_a.tolist(), dtype=float),
            rtol=1e-9, atol=1e-12,
        )  # fmt: skip
    _t_img, blobs = _timed(converted, "/camera/image", "EncodedImage:blob")
    _, blobs_a = _timed(rec.rrd_path, "/camera/image", "EncodedImage:blob")
    assert len(blobs) == n
    assert blobs.tolist() == blobs_a.tolist()


def test_view_saves_an_mcap_as_an_rrd_and_refuses_a_foreign_mcap(tmp_path: Path) -> None:
    from mcap.writer import Writer

    rec = _record(tmp_path / "t", _setup(10), _ticks(10, None))
    out = tmp_path / "out.rrd"
    result = CliRunner().invoke(cli, ["view", str(rec.mcap_path), "--save", str(out)])
    assert result.exit_code == 0, result.output
    assert _static(out)["/__properties"]["RecordingInfo:name"] == ["demo/proposed/trial-2 (seed 7)"]
    foreign = tmp_path / "foreign.mcap"
    with foreign.open("wb") as fh:
        writer = Writer(fh)
        writer.start()
        writer.finish()
    result = CliRunner().invoke(cli, ["view", str(foreign), "--save", str(out)])
    assert result.exit_code == 2
    assert "no `trial` metadata record" in result.output
    assert "Traceback" not in result.output


def test_recording_name_without_a_view_record() -> None:
    """Recordings made before the ``view`` metadata record are named from ``trial``."""
    trial = {"protocol": "spine", "method": "proposed", "trial": 0, "seed": 11}
    assert recording_name(trial) == "spine · proposed · trial 0 · seed 11"
    assert recording_name({}) == "magrun trial"


def test_a_trial_stopped_early_keeps_its_whole_desired_path(tmp_path: Path) -> None:
    """A recording of 20 ticks of a 90-tick path (a --quick run) keeps the whole path in its
    ``workspace`` record (m, to 1e-7 m), and the .rrd rebuilt from the MCAP draws the whole
    path, as the recorder's own .rrd does, not only the part the trial ran."""
    import json

    from mcap.reader import make_reader

    setup = _setup(90)
    rec = _record(tmp_path / "t", setup, _ticks(90, None)[:20])
    with rec.mcap_path.open("rb") as fh:
        meta = {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    kept = np.asarray(json.loads(meta["workspace"]["reference_m"]))
    assert setup.reference is not None
    np.testing.assert_allclose(kept, setup.reference[:, :2], rtol=0, atol=1e-7)
    converted = tmp_path / "converted.rrd"
    assert rrd_from_mcap(rec.mcap_path, converted) == 20
    strip = np.array(_static(converted)["/workspace/reference"]["LineStrips2D:strips"][0])
    live = np.array(_static(rec.rrd_path)["/workspace/reference"]["LineStrips2D:strips"][0])
    assert len(strip) == 90
    np.testing.assert_allclose(strip, live, rtol=0, atol=1e-6)


def test_a_long_path_is_thinned_to_its_shape() -> None:
    """More than REFERENCE_POINTS poses are thinned to every n-th, the last always kept."""
    from magrun.recordings.writer import REFERENCE_POINTS, reference_path

    xy = np.column_stack(
        [np.linspace(0, 0.04, 5 * REFERENCE_POINTS + 3), np.zeros(5 * REFERENCE_POINTS + 3)]
    )
    kept = np.asarray(reference_path(np.column_stack([xy, np.zeros(len(xy))])))
    assert len(kept) <= REFERENCE_POINTS + 1
    np.testing.assert_allclose(kept[0], xy[0])
    np.testing.assert_allclose(kept[-1], xy[-1])
    assert reference_path(None) is None
