"""The trial recorder on its own: batched Rerun series, raw frames, chunk compression."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from rerun.chunk import RrdReader

from magrun.recordings.writer import RecordingSetup, TrialRecorder, raw_image, raw_image_bytes
from magrun.records import ControllerStatus, Tick
from magrun.tracking.camera import Camera

STATUS = ControllerStatus(0.001, 1, True, "", "0")


def _ticks(n: int, frame: np.ndarray | None, dt: float = 0.04) -> list[Tick]:
    ticks = []
    for k in range(n):
        pose = np.array([1e-3 * k, -1e-3 * k, 0.01 * k])
        tick = Tick(
            k=k, t=k * dt, actual=pose, tracked=None if k % 5 == 4 else pose,
            measured=pose if k % 3 == 0 else None, estimated=pose, predicted=pose,
            desired=pose, currents=np.full(8, float(k)), status=STATUS, compute_time=0.002,
            frame=frame,
        )  # fmt: skip
        ticks.append(tick)
    return ticks


def _record(base: Path, setup: RecordingSetup, ticks: list[Tick]) -> TrialRecorder:
    with TrialRecorder(base, setup) as rec:
        for tick in ticks:
            rec.log(tick)
    assert rec.stats.error == ""
    assert rec.stats.dropped_ticks == 0
    return rec


def _rrd_rows(path: Path) -> Counter[str]:
    rows: Counter[str] = Counter()
    for chunk in RrdReader(path).stream():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def test_rerun_series_hold_one_row_per_tick(tmp_path: Path) -> None:
    """Rows sent in columns (every second and at close) add up to one per tick and stream."""
    n = 60  # 2.4 s at 25 Hz: two periodic flushes and the final one
    setup = RecordingSetup(trial={"method": "x"}, channel_names=tuple("abcdefgh"), camera=Camera())
    rec = _record(tmp_path / "t", setup, _ticks(n, None))
    rows = _rrd_rows(rec.rrd_path)
    assert rows["/workspace/actual"] == n
    assert rows["/coils/currents"] == n
    assert rows["/errors/position_mm"] == n
    assert rows["/workspace/tracked"] == n - n // 5  # lost on every 5th tick
    assert rows["/workspace/measured"] == math.ceil(n / 3)
    assert rows["/camera/measured"] == math.ceil(n / 3)
    assert "/camera/tracked" not in rows  # drawn over the image: actual, predicted, measured


def test_raw_frames_round_trip_with_lz4_and_decimated_rerun_images(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    setup = RecordingSetup(
        trial={"method": "x"}, channel_names=tuple("abcdefgh"), image_format="raw",
        rerun_image_every=4, compression="lz4",
    )  # fmt: skip
    n = 10
    rec = _record(tmp_path / "raw", setup, _ticks(n, frame))
    with rec.mcap_path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        assert {c.compression for c in summary.chunk_indexes} == {"lz4"}
        images = [
            m for _, ch, _, m in reader.iter_decoded_messages() if ch.topic == "/camera/image"
        ]
    assert len(images) == n
    for img in images:
        assert (img.width, img.height, img.encoding, img.step) == (64, 48, "mono8", 64)
        assert np.array_equal(np.frombuffer(img.data, np.uint8).reshape(48, 64), frame)
    assert _rrd_rows(rec.rrd_path)["/camera/image"] == math.ceil(n / 4)


def test_raw_image_takes_rgb_and_refuses_other_layouts() -> None:
    rgb = np.zeros((4, 5, 3), dtype=np.uint8)
    msg = raw_image(rgb, 7)
    assert (msg.encoding, msg.step, len(msg.data)) == ("rgb8", 15, 60)
    assert msg.timestamp.nanos == 7
    for bad in (np.zeros((4, 5), np.uint16), np.zeros((4, 5, 4), np.uint8), np.zeros(3, np.uint8)):
        with pytest.raises(ValueError, match="raw frames must be uint8"):
            raw_image(bad, 0)


@pytest.mark.parametrize("shape", [(48, 64), (3, 5, 3), (300, 200)])
def test_raw_image_bytes_parse_to_the_protobuf_message(shape: tuple[int, ...]) -> None:
    """The hand-assembled wire format decodes to exactly what protobuf serialises."""
    from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

    frame = np.random.default_rng(2).integers(0, 256, shape, dtype=np.uint8)
    ours = RawImage.FromString(raw_image_bytes(frame, 123_456_789_012))
    assert ours == raw_image(frame, 123_456_789_012)


def test_recorder_shortens_the_gil_switch_interval_only_while_it_runs(tmp_path: Path) -> None:
    import sys

    from magrun.recordings.writer import SWITCH_INTERVAL_S

    before = sys.getswitchinterval()
    setup = RecordingSetup(trial={"method": "x"}, channel_names=tuple("abcdefgh"))
    with TrialRecorder(tmp_path / "t", setup) as rec:
        rec.log(_ticks(1, None)[0])
        assert sys.getswitchinterval() == pytest.approx(min(before, SWITCH_INTERVAL_S))
    assert sys.getswitchinterval() == before


def test_jpeg_frames_reach_the_rrd_in_columns(tmp_path: Path) -> None:
    """JPEG frames are buffered and sent with the series: one image row per recorded frame
    (every 3rd here), each the MCAP's JPEG bytes."""
    frame = np.random.default_rng(4).integers(0, 256, (32, 48, 3), dtype=np.uint8)
    setup = RecordingSetup(
        trial={"method": "x"}, channel_names=tuple("abcdefgh"), rerun_image_every=3
    )
    n = 40  # 1.6 s at 25 Hz: a periodic flush and the final one
    rec = _record(tmp_path / "jpeg", setup, _ticks(n, frame))
    assert _rrd_rows(rec.rrd_path)["/camera/image"] == math.ceil(n / 3)
    assert rec.stats.images == n


def test_the_blueprint_plots_each_error_in_its_own_unit() -> None:
    """Position (mm) and orientation (°) errors in separate time-series views, currents and
    compute time in theirs; the workspace view always, the camera view with a camera."""
    from magrun.recordings.rerun_log import blueprint

    for with_camera in (True, False):
        spatial, series = blueprint(with_camera).root_container.contents
        views = {v.origin: v.name for v in series.contents}
        assert views == {
            "/coils/currents": "coil currents (A)",
            "/errors/position_mm": "position error (mm)",
            "/errors/orientation_deg": "orientation error (°)",
            "/controller": "compute time (ms)",
        }
        origins = [v.origin for v in spatial.contents]
        assert origins == (["/camera", "/workspace"] if with_camera else ["/workspace"])


@pytest.mark.parametrize(("channels", "share"), [(3, 1.0), (8, 8 / 3.5), (14, 4.0)])
def test_the_currents_view_grows_with_the_coils_so_its_legend_fits(
    channels: int, share: float
) -> None:
    """A plot's legend is cut at the plot's height: the currents' view gets a share of the
    column per 3.5 coils (at least one), the other views one each, with and without replays."""
    from magrun.recordings.rerun_log import blueprint

    for replays in (False, True):
        _, series = blueprint(False, None, replays, channels).root_container.contents
        assert series.contents[0].origin == "/coils/currents"
        shares = list(series.row_shares)
        assert shares[0] == pytest.approx(share)
        assert shares[1:] == [1.0] * (len(series.contents) - 1)


def test_the_declared_messages_are_the_recorded_schemas_and_the_documented_proto() -> None:
    """magrun's own messages, declared once (magrun.recordings.schemas): the descriptor the
    pool holds (what every MCAP schema record carries) is the declared one, field by field;
    a message written and parsed again keeps every field; the .proto in docs/protocols.md is
    the declaration's text."""
    from google.protobuf import descriptor_pb2, descriptor_pool

    from magrun.recordings import schemas
    from magrun.recordings.writer import CoilCurrents, ControllerStatusMsg

    held = descriptor_pb2.FileDescriptorProto()
    descriptor_pool.Default().FindFileByName(schemas.FILE_NAME).CopyToProto(held)
    assert held == schemas.file_descriptor()
    for cls, name in ((CoilCurrents, "CoilCurrents"), (ControllerStatusMsg, "ControllerStatus")):
        fields = [(f.name, f.number) for f in cls.DESCRIPTOR.fields]
        assert fields == [(f[0], i) for i, f in enumerate(schemas.MESSAGES[name], start=1)]
    msg = ControllerStatusMsg(method="proposed", solve_time=1.5e-3, iterations=3, success=True,
                              latency=float("nan"), safety_stop="", prepare_time=2e-4)  # fmt: skip
    back = ControllerStatusMsg.FromString(msg.SerializeToString())
    assert (back.method, back.solve_time, back.iterations, back.prepare_time) == (
        "proposed", 1.5e-3, 3, 2e-4,
    )  # fmt: skip
    docs = (Path(__file__).resolve().parents[1] / "docs" / "protocols.md").read_text()
    assert "```proto\n" + schemas.proto_source() + "```" in docs
