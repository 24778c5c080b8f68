"""Read magrun recordings (MCAP files and manifests) into pandas.

Only the recording format (README, "Recording format"; ARCHITECTURE.md, "CONTRACT:
recordings") is assumed: protobuf messages are decoded with the schemas the MCAP file carries,
robot dimensions and phantom boundaries come from its metadata records, so this module never
imports magrun's control code and reads recordings from any rig.

    >>> import analysis
    >>> data = analysis.load("recordings")          # doctest: +SKIP
    >>> data.trials[["method", "rms_position_mm"]]   # one row per trial
    >>> data.samples                                 # one row per control tick

Units: the :class:`Recording` keeps SI (m, rad, s, A) as recorded; the tables add
``*_mm`` / ``*_deg`` / ``*_ms`` columns, named by unit.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from mcap.reader import make_reader
from mcap.writer import MCAP0_MAGIC
from mcap_protobuf.decoder import DecoderFactory

from analysis import metrics

POSE_STREAMS = ("actual", "tracked", "measured", "estimated", "predicted", "desired")
#: condition columns every table carries (empty where a recording does not set them)
CONDITIONS = ("tracking_rate_hz", "noise_sigma_mm", "noise_sigma_deg")
#: columns that identify a trial
KEYS = ("protocol", "method", *CONDITIONS, "trial")
#: ``trial`` metadata values that are text (the rest are JSON)
_TEXT_KEYS = {"protocol", "method", "rig", "robot", "feedback", "critical_boundary", "plant"}
#: what a damaged file's error adds (a recorder killed mid-trial leaves a file without index)
#: far beyond any run's manifest (a few hundred bytes a trial)
MAX_MANIFEST_BYTES = 256_000_000
RECOVER_HINT = (
    "the file is truncated or damaged (a recorder that died leaves it unindexed); "
    "`magrun recover IN.mcap OUT.mcap` rebuilds a readable copy"
)


class RecordingError(Exception):
    """A recording that cannot be read; the message names the file."""

    def __init__(self, path: Path | str, reason: str) -> None:
        super().__init__(f"{path}: {reason}")
        self.path = Path(path)
        self.reason = reason


@dataclass
class Recording:
    """One trial's MCAP file, decoded. SI units, times in s from the trial start."""

    path: Path
    trial: dict[str, Any]
    protocol: dict[str, Any]
    boundaries: dict[str, np.ndarray]  # name -> (n, 2) polyline, m
    workspace: dict[str, Any]  # the rest of the ``workspace`` record (e.g. half_width_m)
    recorder: dict[str, str]
    poses: dict[str, pd.DataFrame]  # stream -> columns t, x, y, theta
    currents: pd.DataFrame  # t, then one column per coil, A
    status: pd.DataFrame  # t, solve_time, prepare_time, iterations, success, fallback, ...

    @property
    def critical(self) -> str | None:
        name = self.trial.get("critical_boundary") or None
        return str(name) if name else None

    @property
    def robot_length(self) -> float | None:
        return _float_or_none(self.trial.get("robot_length_m"))

    @property
    def robot_diameter(self) -> float | None:
        return _float_or_none(self.trial.get("robot_diameter_m"))

    @property
    def reference(self) -> np.ndarray | None:
        """The whole desired path (n, 2), m, as recorded in the ``workspace`` record (a trial
        that stopped early, a ``--quick`` one, ran only its start); None in recordings
        without it or where it is not a finite (n, 2) list."""
        value = self.workspace.get("reference_m")
        if not isinstance(value, list) or not value:
            return None
        try:
            xy = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            return None
        if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
            return None
        return xy

    def control_period(self) -> float:
        """Nominal control period, s: the recorded control rate, else the median tick step."""
        rate = _float_or_none(self.trial.get("control_rate_hz"))
        if rate and rate > 0:
            return 1.0 / rate
        t = self.poses["desired"]["t"].to_numpy()
        return float(np.median(np.diff(t))) if len(t) > 1 else math.nan


def _float_or_none(value: Any) -> float | None:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return None
    return out if math.isfinite(out) else None


def _decode_meta(record: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, text in record.items():
        if key in _TEXT_KEYS:
            out[key] = text
            continue
        try:
            out[key] = json.loads(text)
        except (ValueError, RecursionError):  # not JSON, or nested too deeply: as text
            out[key] = text
    return out


def _protocol(path: str | Path, text: str) -> dict[str, Any]:
    """The recorded protocol (the ``protocol`` record's JSON), or a :class:`RecordingError`."""
    if not text:
        return {}
    try:
        protocol = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise RecordingError(
            Path(path), f"the recorded protocol is not readable JSON ({type(exc).__name__})"
        ) from exc
    if not isinstance(protocol, dict):
        raise RecordingError(Path(path), "the recorded protocol is not a JSON object")
    return protocol


def read_recording(path: str | Path, with_images: bool = False) -> Recording:
    """Decode one trial's MCAP file.

    Raises
    ------
    RecordingError
        The file is missing, truncated, corrupt or not a magrun recording.
    """
    path = Path(path)
    if not path.is_file():  # a FIFO would wait for a writer for ever
        raise RecordingError(path, "not a regular file" if path.exists() else "no such recording")
    try:
        with path.open("rb") as fh:
            start = fh.read(len(MCAP0_MAGIC))
    except OSError as exc:
        raise RecordingError(path, f"cannot be opened: {exc.strerror or exc}") from exc
    if not start:
        raise RecordingError(path, "empty (0 bytes): nothing was recorded in it")
    if start != MCAP0_MAGIC:
        raise RecordingError(path, "not an MCAP file (it does not start with MCAP's magic bytes)")
    topics = [f"/robot/pose/{s}" for s in POSE_STREAMS] + ["/coils/currents", "/controller/status"]
    if with_images:
        topics.append("/camera/image")
    poses: dict[str, list[tuple[int, float, float, float]]] = {s: [] for s in POSE_STREAMS}
    currents: list[tuple[int, list[float]]] = []
    names: list[str] = []
    status: list[dict[str, Any]] = []
    try:
        with path.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            if reader.get_summary() is None:
                raise RecordingError(path, f"no summary or index: {RECOVER_HINT}")
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            for _schema, channel, message, msg in reader.iter_decoded_messages(
                topics=topics, log_time_order=True
            ):
                t = message.log_time
                topic = channel.topic
                if topic.startswith("/robot/pose/"):
                    poses[topic.rsplit("/", 1)[1]].append((t, *planar_pose(msg)))
                elif topic == "/coils/currents":
                    names = list(msg.names)
                    currents.append((t, list(msg.currents)))
                elif topic == "/controller/status":
                    status.append(
                        {
                            "t_ns": t,
                            "solve_time": msg.solve_time,
                            # recordings from before the field have none: no preparation
                            "prepare_time": getattr(msg, "prepare_time", 0.0),
                            "iterations": msg.iterations,
                            "success": msg.success,
                            "fallback": msg.fallback,
                            "compute_time": msg.compute_time,
                            "measurement": msg.measurement,
                            "tracking_lost": msg.tracking_lost,
                        }
                    )
    except RecordingError:
        raise
    except Exception as exc:  # mcap raises several types for damaged files
        raise RecordingError(
            path, f"cannot be read: {RECOVER_HINT} ({type(exc).__name__}: {exc})"
        ) from exc
    if "trial" not in meta:
        raise RecordingError(path, "no `trial` metadata record: not a magrun recording")
    if not poses["desired"]:
        raise RecordingError(path, "no /robot/pose/desired messages")
    workspace = _decode_meta(meta.get("workspace", {}))
    raw = workspace.pop("boundaries", {}) or {}
    boundaries = {k: np.asarray(v, dtype=np.float64).reshape(-1, 2) for k, v in raw.items()}
    protocol_json = meta.get("protocol", {}).get("json", "{}")
    pose_frames = {
        s: _with_seconds(pd.DataFrame(rows, columns=["t_ns", "x", "y", "theta"]))
        for s, rows in poses.items()
    }
    cur = pd.DataFrame([c for _, c in currents], columns=names or None, dtype=np.float64).reindex(
        columns=names
    )
    cur.insert(0, "t_ns", np.array([t for t, _ in currents], dtype=np.int64))
    st = pd.DataFrame(
        status,
        columns=[
            "t_ns", "solve_time", "prepare_time", "iterations", "success", "fallback",
            "compute_time", "measurement", "tracking_lost",
        ],
    )  # fmt: skip
    return Recording(
        path=path,
        trial=_decode_meta(meta["trial"]),
        protocol=_protocol(path, protocol_json),
        boundaries=boundaries,
        workspace=workspace,
        recorder=meta.get("recorder", {}),
        poses=pose_frames,
        currents=_with_seconds(cur),
        status=_with_seconds(st),
    )


def planar_pose(msg: Any) -> tuple[float, float, float]:
    """A ``foxglove.PoseInFrame`` message's planar pose: x, y (m) and the yaw (rad) of its
    quaternion."""
    p, q = msg.pose.position, msg.pose.orientation
    yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    return p.x, p.y, yaw


def _with_seconds(df: pd.DataFrame) -> pd.DataFrame:
    df["t_ns"] = df["t_ns"].astype(np.int64)
    df.insert(1, "t", df["t_ns"].to_numpy() * 1e-9)
    return df


# --------------------------------------------------------------------------------------------
# a set of recordings


@dataclass
class Dataset:
    """Recordings as tidy tables.

    ``trials``: one row per trial (the identity columns :data:`KEYS`, ``status``, ``path``,
    then the metrics of :func:`analysis.metrics.trial_metrics`). Trials a manifest lists as
    failed or whose file cannot be read are rows too, with ``status`` and ``error`` set and
    the metrics empty.
    ``samples``: one row per control tick of every trial with status ``ok``
    (:func:`samples_of`); ``recordings`` holds those trials' decoded files.
    ``problems``: the recordings that could not be read, as :class:`RecordingError`.
    """

    trials: pd.DataFrame
    samples: pd.DataFrame
    recordings: dict[str, Recording] = field(default_factory=dict)  # key: trial path
    problems: list[RecordingError] = field(default_factory=list)
    root: Path | None = None

    def protocols(self) -> list[str]:
        return sorted(self.trials["protocol"].dropna().unique().tolist())

    def ok(self, protocol: str | None = None) -> pd.DataFrame:
        """The trials that were read, optionally of one protocol."""
        t = self.trials[self.trials["status"] == "ok"]
        return t if protocol is None else t[t["protocol"] == protocol]


def samples_of(rec: Recording, tolerance: float | None = None) -> pd.DataFrame:
    """One row per control tick: desired, actual, predicted and estimated poses and errors.

    The desired pose is logged once per tick; the other streams are matched to it by log time
    (nearest message within ``tolerance`` s, default half a control period), so a rig whose
    camera runs at another rate than the controller is handled. Errors: ``position_error_mm``
    and ``orientation_error_deg`` (actual vs desired, the angle wrapped to ±180°), and
    ``prediction_*`` (actual vs the prediction made at the previous tick), and
    ``prediction_measured_*`` (the measured pose, where a measurement arrived, vs that
    prediction: what a real rig, which knows no truth, can compute).
    """
    if tolerance is None:
        tolerance = 0.5 * rec.control_period()
    tol_ns = round(tolerance * 1e9) if math.isfinite(tolerance) else 0
    out = rec.poses["desired"].rename(columns={"x": "x_des", "y": "y_des", "theta": "theta_des"})
    streams = (("actual", ""), ("predicted", "_pred"), ("estimated", "_est"), ("measured", "_meas"))
    for stream, suffix in streams:
        other = (
            rec.poses[stream]
            .drop(columns="t")
            .rename(columns={c: c + suffix for c in ("x", "y", "theta")})
        )
        out = pd.merge_asof(
            out, other, on="t_ns", direction="nearest", tolerance=tol_ns
        )  # fmt: skip
    actual = out[["x", "y", "theta"]].to_numpy()
    pos, ang = metrics.pose_errors(actual, out[["x_des", "y_des", "theta_des"]].to_numpy())
    out["position_error_mm"] = pos * 1e3
    out["orientation_error_deg"] = np.degrees(ang)
    pos, ang = metrics.pose_errors(actual, out[["x_pred", "y_pred", "theta_pred"]].to_numpy())
    out["prediction_position_error_mm"] = pos * 1e3
    out["prediction_orientation_error_deg"] = np.degrees(ang)
    measured = out[["x_meas", "y_meas", "theta_meas"]].to_numpy()
    pos, ang = metrics.pose_errors(measured, out[["x_pred", "y_pred", "theta_pred"]].to_numpy())
    out["prediction_measured_position_error_mm"] = pos * 1e3
    out["prediction_measured_orientation_error_deg"] = np.degrees(ang)
    if rec.critical and rec.critical in rec.boundaries and rec.robot_length is not None:
        out["clearance_mm"] = 1e3 * metrics.capsule_clearance(
            actual, rec.robot_length, rec.robot_diameter or 0.0, rec.boundaries[rec.critical]
        )
    return out


def identity(rec: Recording) -> dict[str, Any]:
    """The identity columns of a recording's trial (condition values as floats or NaN)."""
    t = rec.trial
    ident: dict[str, Any] = {
        "protocol": t.get("protocol"),
        "method": t.get("method"),
        **{c: _float_or_nan(t.get(c)) for c in CONDITIONS},
        "trial": int(t.get("trial", 0)),
    }
    return ident


def _float_or_nan(value: Any) -> float:
    f = _float_or_none(value)
    return math.nan if f is None else f


def find_recordings(root: str | Path) -> list[tuple[Path, dict[str, Any] | None]]:
    """The trials under ``root``: ``(mcap path, manifest entry or None)``.

    ``root`` may be an ``.mcap`` file, a protocol folder (with ``manifest.json``), or a folder
    of protocol folders (``magrun run``'s ``--out``). Manifests list every trial, failed ones
    too; folders without a manifest are searched for ``*.mcap``.
    """
    root = Path(root)
    if root.is_file():
        return [(root, None)]
    if not root.is_dir():
        if root.exists():  # a FIFO, a socket, a device
            raise RecordingError(root, "not a regular file or a folder")
        raise FileNotFoundError(f"{root}: no such file or folder")
    manifests = sorted([root / "manifest.json"] if (root / "manifest.json").is_file() else [])
    if not manifests:
        manifests = sorted(root.glob("*/manifest.json"))
    found: list[tuple[Path, dict[str, Any] | None]] = []
    listed: set[Path] = set()
    for mf in manifests:
        if not mf.is_file() or mf.stat().st_size > MAX_MANIFEST_BYTES:  # a FIFO waits for ever
            raise RecordingError(mf, f"not a regular file of at most {MAX_MANIFEST_BYTES:,} bytes")
        try:
            manifest = json.loads(mf.read_text())
            entries = manifest["trials"]
        except (ValueError, KeyError, TypeError, RecursionError) as exc:
            raise RecordingError(mf, f"not a readable manifest ({type(exc).__name__})") from exc
        if not isinstance(entries, list):
            raise RecordingError(mf, "not a readable manifest (`trials` is not a list)")
        for i, entry in enumerate(entries):
            relpath = entry.get("mcap") if isinstance(entry, dict) else None
            if not isinstance(relpath, str) or not relpath:
                raise RecordingError(mf, f"trials[{i}]: no `mcap` path")
            p = (mf.parent / relpath).resolve()
            if not p.is_relative_to(mf.parent.resolve()):
                raise RecordingError(mf, f"trials[{i}]: `mcap` points outside the run's folder")
            listed.add(p)
            found.append(
                (p, {**entry, "protocol": entry.get("protocol", manifest.get("protocol"))})
            )
    searched = [root] if not manifests else []
    for folder in searched:
        for p in sorted(folder.rglob("*.mcap")):
            hidden = any(part.startswith(".") for part in p.relative_to(folder).parts)
            if hidden:  # a writer's temporary folder (".NAME.part"), not a recording
                continue
            if p.resolve() not in listed and not is_replay(p):
                found.append((p, None))
    return found


def is_replay(path: str | Path) -> bool:
    """Whether ``path`` is an estimator replay's output (a ``replay`` metadata record): the
    recording's channels again, read by :mod:`analysis.replays`, not a trial of its own."""
    try:
        if not Path(path).is_file():
            return False
        with Path(path).open("rb") as fh:
            return any(m.name == "replay" for m in make_reader(fh).iter_metadata())
    except Exception:  # an unreadable file is the trials' loader's to report
        return False


def load(
    root: str | Path | Iterable[str | Path],
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
    contact_mm: float = metrics.CONTACT_MM,
) -> Dataset:
    """Load recordings into a :class:`Dataset`.

    A recording that cannot be read does not stop the others: it becomes a row with
    ``status = "unreadable"`` and its :class:`RecordingError` is in ``problems``.

    Parameters
    ----------
    root : path or paths
        Folders (see :func:`find_recordings`) or ``.mcap`` files.
    progress : callable, optional
        Wraps the iteration over trials (e.g. ``tqdm``).
    contact_mm : float
        Clearance, mm, at or below which the body counts as touching a boundary.
    """
    roots = [root] if isinstance(root, (str, Path)) else list(root)
    items = [item for r in roots for item in find_recordings(r)]
    rows: list[dict[str, Any]] = []
    samples: list[pd.DataFrame] = []
    recordings: dict[str, Recording] = {}
    problems: list[RecordingError] = []
    iterator: Iterable[Any] = progress(items) if progress else items
    for mcap_path, entry in iterator:
        row: dict[str, Any] = {"path": str(mcap_path)}
        if entry is not None:
            conds = entry.get("conditions", {})
            row.update(
                protocol=entry.get("protocol"),
                method=entry.get("method"),
                **{c: _float_or_nan(conds.get(c)) for c in CONDITIONS},
                trial=entry.get("trial"),
                status=entry.get("status", "ok"),
                error=entry.get("error", ""),
                warnings="; ".join(entry.get("warnings") or []),
                lost=entry.get("lost"),
            )
            if row["status"] != "ok" and not mcap_path.is_file():
                rows.append(row)
                continue
        try:
            rec = read_recording(mcap_path)
        except RecordingError as exc:
            problems.append(exc)
            row.update(status="unreadable", error=exc.reason)
            rows.append(row)
            continue
        row.update(
            identity(rec), quick=bool(rec.trial.get("quick", False)),
            plant=str(rec.trial.get("plant", "") or ""),
        )  # fmt: skip
        row.setdefault("status", "ok")
        row.setdefault("error", "")
        s = samples_of(rec)
        row.update(metrics.trial_metrics(rec, s, contact_mm=contact_mm))
        rows.append(row)
        if row["status"] != "ok":  # a trial that failed midway: its metrics, not its samples
            continue
        recordings[str(mcap_path)] = rec
        samples.append(s.assign(**{k: row[k] for k in KEYS}, path=str(mcap_path)))
    trials = pd.DataFrame(rows)
    for col in (*KEYS, "status", "error", "path"):
        if col not in trials:
            trials[col] = pd.Series(dtype=object)
    first = [*KEYS, "status", "error"]
    trials = trials[first + [c for c in trials.columns if c not in first]]
    trials = trials.sort_values(list(KEYS), kind="stable", na_position="first").reset_index(
        drop=True
    )
    sample_frame = pd.concat(samples, ignore_index=True) if samples else pd.DataFrame()
    if not sample_frame.empty:
        lead = [*KEYS, "t"]
        sample_frame = sample_frame[lead + [c for c in sample_frame.columns if c not in lead]]
    return Dataset(
        trials=trials,
        samples=sample_frame,
        recordings=recordings,
        problems=problems,
        root=Path(roots[0]) if len(roots) == 1 else None,
    )
