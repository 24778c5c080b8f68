"""Estimator replays (``magrun replay``'s outputs) found beside the recordings: a table of the
recorded against the replayed estimator's error, and its figure.

A replay output is an MCAP file with a ``replay`` metadata record: the recording's channels
plus ``/replay/<label>/robot/pose/estimated``. For each, the RMS estimation error (estimate
against the actual pose, position in mm and heading in degrees, wrapped) is computed here from
the streams, of the recorded estimator and of the replayed one, over the same ticks::

    import analysis.replays as replays
    table = replays.replay_table(replays.find_replays("recordings"))
    replays.figure(table)                          # paired points per label

Re-simulations (``magrun replay --resimulate``) are whole new trials, not replays: they carry
no ``replay`` record and are read as trials.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import seaborn as sns
from matplotlib.figure import Figure
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from analysis.load import CONDITIONS, RecordingError, _decode_meta, is_replay, planar_pose
from analysis.metrics import rms, wrap_angle

#: the table's columns, in order
COLUMNS = (
    "protocol", "method", *CONDITIONS, "trial", "label", "estimator", "settings",
    "ticks", "recorded_mm", "replayed_mm", "recorded_deg", "replayed_deg", "path",
)  # fmt: skip


def _metadata(path: Path) -> dict[str, dict[str, str]]:
    with path.open("rb") as fh:
        return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}


def find_replays(root: str | Path) -> list[Path]:
    """Every replay output under ``root`` (a file, or a folder searched recursively): the
    MCAP files with a ``replay`` record. Unreadable files are skipped (the trials' loader
    reports those)."""
    root = Path(root)
    paths = [root] if root.is_file() else sorted(root.rglob("*.mcap"))
    return [p for p in paths if is_replay(p)]


def _poses(path: Path, topics: list[str]) -> dict[str, pd.DataFrame]:
    rows: dict[str, list[tuple[int, float, float, float]]] = {t: [] for t in topics}
    with path.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, channel, message, msg in reader.iter_decoded_messages(topics=topics):
            rows[channel.topic].append((message.log_time, *planar_pose(msg)))
    return {
        t: pd.DataFrame(r, columns=["t_ns", "x", "y", "theta"]).set_index("t_ns")
        for t, r in rows.items()
    }


def _errors(estimate: pd.DataFrame, actual: pd.DataFrame) -> tuple[float, float]:
    d = estimate.join(actual.add_suffix("_a"), how="inner").dropna()
    pos = np.hypot(d["x"] - d["x_a"], d["y"] - d["y_a"]) * 1e3
    ang = np.degrees(wrap_angle(d["theta"] - d["theta_a"]))
    return rms(pos), rms(ang)


def replay_row(path: str | Path) -> dict[str, Any]:
    """One replay output's row of :func:`replay_table`.

    Raises
    ------
    RecordingError
        Not a readable replay output.
    """
    path = Path(path)
    try:
        meta = _metadata(path)
        record = meta["replay"]
        label = record["label"]
        estimated = f"/replay/{label}/robot/pose/estimated"
        topics = ["/robot/pose/actual", "/robot/pose/estimated", estimated]
        poses = _poses(path, topics)
    except KeyError as exc:
        raise RecordingError(path, f"not a replay output (no {exc})") from exc
    except Exception as exc:  # mcap raises several types for damaged files
        raise RecordingError(path, f"cannot be read ({type(exc).__name__}: {exc})") from exc
    actual = poses["/robot/pose/actual"]
    if actual.empty or poses[estimated].empty:
        raise RecordingError(path, f"no actual poses or no {estimated} messages")
    trial = _decode_meta(meta.get("trial", {}))
    rec_mm, rec_deg = _errors(poses["/robot/pose/estimated"], actual)
    rep_mm, rep_deg = _errors(poses[estimated], actual)
    settings = json.loads(record.get("settings", "[]") or "[]")
    return {
        "protocol": trial.get("protocol"),
        "method": trial.get("method"),
        **{c: trial.get(c) for c in CONDITIONS},
        "trial": trial.get("trial"),
        "label": label,
        "estimator": record.get("estimator", ""),
        "settings": ", ".join(settings) if settings else "(recorded)",
        "ticks": len(poses[estimated]),
        "recorded_mm": rec_mm,
        "replayed_mm": rep_mm,
        "recorded_deg": rec_deg,
        "replayed_deg": rep_deg,
        "path": str(path),
    }


def replay_table(paths: Iterable[str | Path]) -> pd.DataFrame:
    """One row per replay output: its source trial, label, what was changed, and the RMS
    estimation error of the recorded and of the replayed estimator (mm, degrees)."""
    rows = [replay_row(p) for p in paths]
    table = pd.DataFrame(rows, columns=list(COLUMNS))
    return table.sort_values(["label", "protocol", "method", "trial"], kind="stable").reset_index(
        drop=True
    )


def figure(table: pd.DataFrame) -> Figure:
    """Recorded against replayed RMS estimation error (position, mm), each replay a pair of
    points joined by a line, one column per label (the report's table says what each label
    changed)."""
    sns.set_theme(context="paper", style="whitegrid", font_scale=1.1)
    labels = list(dict.fromkeys(table["label"]))
    fig = Figure(figsize=(max(4.5, 1.8 * len(labels) + 2.5), 4.2), layout="constrained")
    ax = fig.subplots()
    for i, label in enumerate(labels):
        rows = table[table["label"] == label]
        for _, r in rows.iterrows():
            ax.plot([i - 0.18, i + 0.18], [r["recorded_mm"], r["replayed_mm"]],
                    color="0.6", linewidth=0.8, zorder=1)  # fmt: skip
        ax.scatter(np.full(len(rows), i - 0.18), rows["recorded_mm"], color="#1f77b4",
                   label="recorded" if i == 0 else None, zorder=2)  # fmt: skip
        ax.scatter(np.full(len(rows), i + 0.18), rows["replayed_mm"], color="#d62728",
                   label="replayed" if i == 0 else None, zorder=2)  # fmt: skip
    ax.set_xticks(range(len(labels)), labels)
    ax.set_xlim(-0.6, len(labels) - 0.4)
    ax.set_ylim(bottom=0)
    ax.set(ylabel="RMS estimation error (mm)",
           title=f"estimator replays: recorded vs replayed ({len(table)} replays)")  # fmt: skip
    ax.legend(loc="lower right")
    return fig
