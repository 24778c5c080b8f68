"""Live view: trials and replays streamed to a Rerun viewer while they are written.

Headless: the viewer is ``rerun --serve-grpc --save FILE``, Rerun's own gRPC server, which
writes everything it receives to a file that the tests read back.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from rerun.chunk import RrdReader
from synthetic import TINY
from test_recording import _rrd_rows, _ticks

from magrun.cli import cli
from magrun.cli.common import InputError
from magrun.cli.viewer import grpc_url
from magrun.recordings.rerun_log import viewer_listening
from magrun.recordings.writer import RecordingSetup, TrialRecorder
from magrun.tracking.camera import Camera

RERUN = str(Path(sys.executable).with_name("rerun"))
#: how long the tests wait for a viewer process to listen or to have written what it got, s
WAIT_S = 60.0


def _port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Sink:
    """``rerun --serve-grpc`` saving what it receives to ``path``."""

    def __init__(self, path: Path, connect: str | None = None) -> None:
        self.path = path
        self.port = _port()
        self.url = f"rerun+http://127.0.0.1:{self.port}/proxy"
        args = [RERUN, "--bind", "127.0.0.1", "--save", str(path)]
        # a server of its own, or a client of another's (--connect: what a late viewer gets)
        args += ["--connect", connect] if connect else ["--serve-grpc", "--port", str(self.port)]
        self.proc = subprocess.Popen(
            args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )  # fmt: skip
        if connect is None:
            deadline = time.monotonic() + WAIT_S
            while not viewer_listening(self.url, timeout_s=0.5):
                assert self.proc.poll() is None, "rerun --serve-grpc exited"
                assert time.monotonic() < deadline, "rerun --serve-grpc did not listen"
                time.sleep(0.1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


@pytest.fixture
def sink(tmp_path: Path) -> Iterator[Sink]:
    s = Sink(tmp_path / "received.rrd")
    yield s
    s.stop()


def _received(path: Path) -> dict[str, Counter[str]]:
    """Rows per entity (not static) of each recording in an .rrd a sink wrote."""
    reader = RrdReader(path)
    out: dict[str, Counter[str]] = {}
    for store in reader.recordings():
        rows: Counter[str] = Counter()
        for chunk in reader.stream(store=store):
            if not chunk.is_static:
                rows[str(chunk.entity_path)] += chunk.num_rows
        out[store.recording_id] = rows
    return out


def _wait_received(path: Path, want: dict[str, Counter[str]]) -> dict[str, Counter[str]]:
    """What the sink wrote, once it holds ``want``'s recordings with at least their rows
    (the server writes as it receives); what it holds after WAIT_S otherwise."""
    deadline = time.monotonic() + WAIT_S
    got: dict[str, Counter[str]] = {}
    while time.monotonic() < deadline:
        try:
            with _quiet():
                got = _received(path)
        except Exception:  # not there yet, or caught half-written
            got = {}
        if all(
            rid in got and all(got[rid][e] >= n for e, n in rows.items())
            for rid, rows in want.items()
        ):
            return got
        time.sleep(0.25)
    return got


class _quiet:
    """Silence RrdReader's warning about a file still being written (no footer yet)."""

    def __enter__(self) -> None:
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore")

    def __exit__(self, *exc: Any) -> None:
        self._ctx.__exit__(*exc)


ENTITIES = (
    "/workspace/actual", "/workspace/estimated", "/camera/actual", "/camera/image",
    "/coils/currents", "/errors/position_mm", "/controller/compute_ms",
)  # fmt: skip


def test_run_streams_every_trial_to_a_running_viewer(sink: Sink, tmp_path: Path) -> None:
    """`magrun run --connect PORT`: the viewer gets each trial as a recording of its own,
    under the trial's recording id, with the default layout and every row of its .rrd."""
    result = CliRunner().invoke(
        cli, ["run", str(TINY), "--out", str(tmp_path / "rec"), "--connect", str(sink.port)]
    )
    assert result.exit_code == 0, result.output
    folder = tmp_path / "rec" / "tiny"
    files = sorted(folder.rglob("*.rrd"))
    assert len(files) == 4
    want = {}
    for rrd in files:
        rows = _rrd_rows(rrd)
        trial = rrd.relative_to(folder).with_suffix("").as_posix()
        (rid,) = [r.recording_id for r in RrdReader(rrd).recordings()]
        assert rid.startswith(f"tiny/{trial}@")
        want[rid] = Counter({e: rows[e] for e in ENTITIES})
        assert all(want[rid][e] > 0 for e in ENTITIES)
    got = _wait_received(sink.path, want)
    assert set(got) == set(want)
    for rid, rows in want.items():
        assert {e: got[rid][e] for e in ENTITIES} == dict(rows), rid
    with _quiet():
        assert {b.application_id for b in RrdReader(sink.path).blueprints()} == {"magrun"}
        # the viewer gets the camera frames as pixels (drawn as they come), the file JPEGs
        assert _image_columns(sink.path) == {"Image:buffer", "Image:format"}
    assert _image_columns(files[0]) == {"EncodedImage:blob", "EncodedImage:media_type"}


def _image_columns(path: Path) -> set[str]:
    """The components of the camera image's rows in an .rrd."""
    names: set[str] = set()
    for chunk in RrdReader(path).stream():
        if str(chunk.entity_path) == "/camera/image" and not chunk.is_static:
            names |= {n for n in chunk.to_record_batch().schema.names if ":" in n}
    return names


def _record(base: Path, live: str, ticks: list[Any], on_tick: Any = None) -> TrialRecorder:
    setup = RecordingSetup(
        trial={"method": "x"}, channel_names=tuple("abcdefgh"), camera=Camera(),
        recording_id=base.name, live_view=live,
    )  # fmt: skip
    with TrialRecorder(base, setup, wait_when_full=True) as rec:
        for k, tick in enumerate(ticks):
            rec.log(tick)
            if on_tick is not None:
                on_tick(k)
    assert rec.stats.error == ""
    assert rec.stats.dropped_ticks == 0
    return rec


def _chunks(path: Path) -> Counter[str]:
    counts: Counter[str] = Counter()
    for chunk in RrdReader(path).stream():
        counts[str(chunk.entity_path)] += 1
    return counts


def test_the_file_is_written_the_same_with_a_viewer_and_without(
    sink: Sink, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A live view gets rows as often as LIVE_FLUSH_S of wall time allows (here: every
    tick), the file keeps its own chunks (one per second of trial time): the same rows in
    the same chunks as without a viewer."""
    import magrun.recordings.writer

    monkeypatch.setattr(magrun.recordings.writer, "LIVE_FLUSH_S", 0.0)
    ticks = _ticks(60, None)  # 2.4 s at 25 Hz
    alone = _record(tmp_path / "alone", "", ticks)
    viewed = _record(tmp_path / "viewed", sink.url, ticks)
    assert _rrd_rows(viewed.rrd_path) == _rrd_rows(alone.rrd_path)
    assert _chunks(viewed.rrd_path) == _chunks(alone.rrd_path)
    rows = _rrd_rows(alone.rrd_path)
    got = _wait_received(sink.path, {"viewed": Counter({"/coils/currents": 60})})
    assert set(got) == {"viewed"}
    received = got["viewed"]
    for entity in ("/workspace/actual", "/coils/currents", "/errors/position_mm"):
        assert received[entity] == rows[entity] == 60
    # the viewer had them tick by tick (Rerun's batcher may join some), the file in 3 pieces
    with _quiet():
        pieces = Counter(
            str(c.entity_path) for c in RrdReader(sink.path).stream() if not c.is_static
        )
    assert pieces["/coils/currents"] > 3 * _chunks(alone.rrd_path)["/coils/currents"]


def test_a_viewer_closed_mid_trial_costs_the_recording_nothing(
    sink: Sink, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    ticks = _ticks(100, None)

    def close_viewer(k: int) -> None:
        if k == 40:
            sink.stop()

    rec = _record(tmp_path / "t", sink.url, ticks, on_tick=close_viewer)
    rows = _rrd_rows(rec.rrd_path)
    assert rows["/workspace/actual"] == rows["/coils/currents"] == 100
    assert rec.stats.live_view_error.startswith(f"live view at {sink.url} stopped")
    assert f"live view at {sink.url} stopped" in capfd.readouterr().err
    # a later trial finds nothing listening and opens no stream (one would wait on it)
    later = _record(tmp_path / "later", sink.url, ticks[:10])
    assert _rrd_rows(later.rrd_path)["/coils/currents"] == 10
    assert "no viewer listening" in later.stats.live_view_error
    assert capfd.readouterr().err == ""  # said once


@pytest.mark.parametrize("writer", ["thread", "process"])
def test_both_writers_stream(sink: Sink, tmp_path: Path, writer: str) -> None:
    """The recorder thread and the recorder process (the hardware rig's) both stream."""
    from magrun.recordings.process import ProcessRecorder

    setup = RecordingSetup(
        trial={"method": "x"}, channel_names=tuple("abcdefgh"), recording_id=writer,
        live_view=sink.url,
    )  # fmt: skip
    cls = ProcessRecorder if writer == "process" else TrialRecorder
    with cls(tmp_path / writer, setup, wait_when_full=True) as rec:
        for tick in _ticks(30, None):
            rec.log(tick)
    assert rec.stats.error == rec.stats.live_view_error == ""
    got = _wait_received(sink.path, {writer: Counter({"/coils/currents": 30})})
    assert got[writer]["/coils/currents"] == 30


def test_connect_to_nothing_or_to_a_bad_address_is_an_input_error(tmp_path: Path) -> None:
    out = tmp_path / "rec"
    for args, message in [
        (["--connect", str(_port())], "no Rerun viewer listens at rerun+http://127.0.0.1:"),
        (["--connect", "http://host:1/x"], "give PORT, HOST:PORT or rerun+http"),
        (["--connect", "9876", "--web"], "exclude each other"),
    ]:
        result = CliRunner().invoke(cli, ["run", str(TINY), "--out", str(out), *args])
        assert result.exit_code == 2, result.output
        assert message in result.output
        assert "Traceback" not in result.output
    assert not out.exists()  # refused before anything ran


def test_view_without_a_display_points_to_web(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    result = CliRunner().invoke(cli, ["run", str(TINY), "--out", str(tmp_path), "--view"])
    assert result.exit_code == 2
    assert f"magrun run {TINY} --web" in result.output


@pytest.mark.parametrize(
    ("typed", "url"),
    [
        ("9876", "rerun+http://127.0.0.1:9876/proxy"),
        ("lab-pc:9000", "rerun+http://lab-pc:9000/proxy"),
        ("rerun+http://10.0.0.2:9876/proxy", "rerun+http://10.0.0.2:9876/proxy"),
        ("rerun+https://viewer.example/proxy", "rerun+https://viewer.example:9876/proxy"),
    ],
)
def test_connect_addresses(typed: str, url: str) -> None:
    assert grpc_url(typed) == url


@pytest.mark.parametrize("typed", ["http://a:1/proxy", "rerun+http://a:1/other", "a:b"])
def test_connect_refuses_what_is_not_a_viewer_address(typed: str) -> None:
    with pytest.raises(InputError):
        grpc_url(typed)


def test_run_web_serves_the_viewer_and_keeps_what_it_streamed(tmp_path: Path) -> None:
    """`magrun run --web`: the browser's page is served on 127.0.0.1 and a viewer that
    connects after the run still gets every trial; SIGTERM then stops the server too."""
    port = _port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "magrun.cli", "run", str(TINY), "--out", str(tmp_path / "rec"),
         "--web", "--web-port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )  # fmt: skip
    late = None
    try:
        assert proc.stderr is not None
        lines = []
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            lines.append(line)
            if not line or "serving the live view" in line:
                break
        text = "".join(lines)
        assert "serving the live view at http://127.0.0.1:" in text, text
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as reply:
            assert reply.status == 200
        from urllib.parse import parse_qs, urlsplit

        page = text.split("serving the live view at ")[1].split()[0]
        grpc = parse_qs(urlsplit(page).query)["url"][0]
        late = Sink(tmp_path / "late.rrd", connect=grpc)
        want = {
            r.recording_id: Counter({"/coils/currents": 26})
            for rrd in (tmp_path / "rec").rglob("*.rrd")
            for r in RrdReader(rrd).recordings()
        }
        assert len(want) == 4
        got = _wait_received(late.path, want)
        assert set(got) == set(want)
    finally:
        if late is not None:
            late.stop()
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            pytest.fail("magrun run --web still running 60 s after SIGTERM")
    assert not viewer_listening(grpc)  # the server it started is gone


def test_replay_streams_its_output(sink: Sink, tmp_path: Path) -> None:
    """`magrun replay REC --connect PORT`: the viewer gets the recording with the replayed
    estimate drawn over it."""
    from synthetic import record_tiny

    mcap = record_tiny(tmp_path / "rec", ["sweep.tracking_rate_hz=[5]"])["baseline3"]
    result = CliRunner().invoke(
        cli, ["replay", str(mcap), "--label", "slow", "--connect", str(sink.port),
              "--set", "controller.kalman.measurement_sigma_mm=4"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = _rrd_rows(mcap.with_name(f"{mcap.stem}.slow.rrd"))
    assert rows["/workspace/replay/slow/estimated"] > 0
    entities = ("/workspace/replay/slow/estimated", "/errors/estimation_mm/slow", "/coils/currents")
    (rid,) = [
        r.recording_id for r in RrdReader(mcap.with_name(f"{mcap.stem}.slow.rrd")).recordings()
    ]
    got = _wait_received(sink.path, {rid: Counter({e: rows[e] for e in entities})})
    assert {e: got[rid][e] for e in entities} == {e: rows[e] for e in entities}


@pytest.mark.parametrize("channels", [3, 1])
def test_a_recorded_jpeg_reaches_the_live_view_as_its_pixels(channels: int) -> None:
    """A replay's live view decodes the recorded JPEGs: the frame back in RGB order (a
    red-and-green gradient tells RGB from BGR), within JPEG's loss at quality 90."""
    import numpy as np

    from magrun.recordings.rerun_log import _decode_jpeg
    from magrun.recordings.writer import encode_jpeg

    y, x = np.mgrid[0:48, 0:64]
    frame = np.stack([x * 4, y * 5, np.full_like(x, 30)], axis=-1).astype(np.uint8)
    if channels == 1:
        frame = frame[..., 0]
    back = _decode_jpeg(encode_jpeg(frame, 90))
    assert back.shape == frame.shape
    assert back.dtype == np.uint8
    assert np.mean(np.abs(back.astype(float) - frame)) < 2.0  # grey levels, of 255
