"""Crash-safe recordings: ``magrun recover`` on cut, damaged and SIGKILLed MCAP files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from mcap.reader import make_reader

from magrun.cli import cli
from magrun.recordings.recover import NothingRecovered, recover
from magrun.recordings.writer import RecordingSetup, TrialRecorder
from magrun.records import ControllerStatus, Tick

STATUS = ControllerStatus(0.001, 1, True, "", "0")
DT = 1 / 25.5


def _tick(k: int) -> Tick:
    pose = np.array([1e-4 * k, -1e-4 * k, 0.01 * k])
    return Tick(
        k=k, t=k * DT, actual=pose, tracked=pose, measured=pose if k % 8 == 0 else None,
        estimated=pose, predicted=pose if k else None, desired=pose,
        currents=np.full(8, float(k % 30)), status=STATUS, compute_time=0.002,
    )  # fmt: skip


def _messages(path: Path) -> list[tuple[str, int, bytes]]:
    with path.open("rb") as fh:
        return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(fh).iter_messages()]


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """10 s of trial at 25.5 Hz, chunks closed every second."""
    base = tmp_path_factory.mktemp("rec") / "trial-0"
    setup = RecordingSetup(trial={"method": "proposed", "seed": 1}, channel_names=tuple("abcdefgh"))
    with TrialRecorder(base, setup, flush_s=1.0) as rec:
        for k in range(256):
            rec.log(_tick(k))
    assert rec.stats.ticks_written == 256
    return rec.mcap_path


def test_a_complete_file_is_copied_whole(recording: Path, tmp_path: Path) -> None:
    out = tmp_path / "copy.mcap"
    report = recover(recording, out)
    assert report.complete
    assert report.problem == ""
    assert report.bytes_lost == 0
    assert _messages(out) == _messages(recording)
    with out.open("rb") as fh:
        meta = {m.name: m.metadata for m in make_reader(fh).iter_metadata()}
    assert meta["trial"]["method"] == "proposed"
    assert meta["recovery"]["complete"] == "true"


@pytest.mark.parametrize("seed", range(6))
def test_a_cut_file_keeps_every_closed_chunk(recording: Path, tmp_path: Path, seed: int) -> None:
    """Cut at a random byte: the recovered messages are the original's first ones, and every
    chunk that ended before the cut is among them (so at most one chunk, ≤ 1 s, is lost)."""
    data = recording.read_bytes()
    with recording.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    data_end = chunks[-1].chunk_start_offset + chunks[-1].chunk_length
    cut = int(np.random.default_rng(seed).integers(chunks[0].chunk_start_offset, data_end))
    cut_file = tmp_path / "cut.mcap"
    cut_file.write_bytes(data[:cut])
    out = tmp_path / "out.mcap"
    report = recover(cut_file, out)
    assert not report.complete
    assert report.problem
    original = _messages(recording)
    recovered = _messages(out)
    assert recovered == original[: len(recovered)]
    # every message before the chunk the cut fell in is back; that chunk spans ≤ 1 s + a tick
    open_chunk = next(c for c in chunks if c.chunk_start_offset + c.chunk_length > cut)
    before = [m for m in original if m[1] < open_chunk.message_start_time]
    assert len(recovered) >= len(before)
    for c in chunks:
        assert c.message_end_time - c.message_start_time <= (1.0 + DT) * 1e9


def test_not_an_mcap_file_is_refused_cleanly(tmp_path: Path) -> None:
    bad = tmp_path / "notes.mcap"
    bad.write_text("these are not the bytes you are looking for\n")
    with pytest.raises(ValueError, match="not an MCAP file"):
        recover(bad, tmp_path / "out.mcap")
    result = CliRunner().invoke(cli, ["recover", str(bad), str(tmp_path / "out.mcap")])
    assert result.exit_code == 2
    assert "not an MCAP file" in result.output
    assert not (tmp_path / "out.mcap").exists()


def test_a_file_cut_before_its_first_message_is_refused_and_nothing_written(
    recording: Path, tmp_path: Path
) -> None:
    """A recording cut inside its first chunk (before any message is whole) recovers
    nothing: exit 2 naming the file and the bytes, no output, and an existing output kept
    even with --overwrite (the copy would hold nothing a reader could use)."""
    with recording.open("rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    first = min(c.chunk_start_offset for c in summary.chunk_indexes)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: first + 40])
    out = tmp_path / "out.mcap"
    with pytest.raises(NothingRecovered, match="no message could be recovered"):
        recover(cut, out)
    assert not out.exists()
    assert not list(tmp_path.glob("*.tmp"))
    result = CliRunner().invoke(cli, ["recover", str(cut), str(out)])
    assert result.exit_code == 2, result.output
    assert f"{cut}: no message could be recovered from its {first + 40:,} bytes" in result.output
    assert not out.exists()
    out.write_bytes(b"an earlier recovery")
    result = CliRunner().invoke(cli, ["recover", str(cut), str(out), "--overwrite"])
    assert result.exit_code == 2, result.output
    assert out.read_bytes() == b"an earlier recovery"


def test_an_empty_file_is_named_empty_not_sent_to_recover(tmp_path: Path) -> None:
    """A 0-byte .mcap (a run killed before its recorder wrote) is "empty" to every reader:
    figures, replay, view and recover say so, and none suggests recover, which cannot help."""
    empty = tmp_path / "trial-0.mcap"
    empty.write_bytes(b"")
    for args in (
        ["figures", str(empty), "--out", str(tmp_path / "figs"), "--no-zernike"],
        ["replay", str(empty)],
        ["view", str(empty)],
        ["recover", str(empty), str(tmp_path / "out.mcap")],
    ):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code in (1, 2), (args, result.output)
        assert f"{empty}: empty (0 bytes)" in result.output, (args, result.output)
        assert "magrun recover" not in result.output, (args, result.output)
        assert "Traceback" not in result.output, (args, result.output)


def test_recover_never_overwrites_its_input(recording: Path) -> None:
    with pytest.raises(ValueError, match="never over the original"):
        recover(recording, recording)


def test_recover_never_replaces_an_existing_file_unasked(recording: Path, tmp_path: Path) -> None:
    """`recover A B` once replaced a complete B: now exit 2 and B as it was, unless
    --overwrite; an output named like the source (any case) is refused even then."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size // 2])
    done = tmp_path / "complete.mcap"
    done.write_bytes(b"a complete recording")
    result = CliRunner().invoke(cli, ["recover", str(cut), str(done)])
    assert result.exit_code == 2
    assert "pass --overwrite" in result.output
    assert done.read_bytes() == b"a complete recording"
    shadow = tmp_path / "CUT.MCAP"
    result = CliRunner().invoke(cli, ["recover", str(cut), str(shadow), "--overwrite"])
    assert result.exit_code == 2
    assert "would replace" in result.output
    result = CliRunner().invoke(cli, ["recover", str(cut), str(done), "--overwrite"])
    assert result.exit_code == 0, result.output
    assert len(_messages(done)) > 0


def test_cli_recover_json(recording: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[: recording.stat().st_size // 2])
    out = tmp_path / "fixed.mcap"
    result = CliRunner().invoke(cli, ["recover", str(cut), str(out), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.output)
    assert doc["complete"] is False
    assert doc["messages"] == len(_messages(out)) > 0
    assert doc["per_topic"]["/robot/pose/desired"] > 0


def test_sigkill_loses_at_most_the_last_second() -> None:
    """Recording processes killed with SIGKILL mid-trial (magrun bench sigkill's child, at
    real-time pace): ``recover`` gets back everything up to at most 1 s of trial time (the
    flush period) plus the tick in hand and one of slack before the kill."""
    from magrun.bench.sigkill import bench_sigkill

    result = bench_sigkill(kills=2, dt=DT, window=(1.5, 3.0), seed=1)
    for run in result["runs"]:
        assert run["ticks_logged"] >= 1.5 / DT - 2
        assert 0 <= run["trial_s_lost"] <= 1.0 + 3 * DT
        assert run["ticks_recovered"] >= run["ticks_logged"] - round((1.0 + 3 * DT) / DT)


@pytest.mark.parametrize("size", [12, 16, 20, 24])
def test_a_file_cut_inside_its_header_is_refused_with_exit_2(
    recording: Path, tmp_path: Path, size: int
) -> None:
    """12-24 bytes of a recording (the magic and part of the header) ended in struct.error."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:size])
    result = CliRunner().invoke(cli, ["recover", str(cut), str(tmp_path / "out.mcap")])
    assert result.exit_code == 2, result.output
    assert "not an MCAP file" in result.output
    assert not (tmp_path / "out.mcap").exists()
