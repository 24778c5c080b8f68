"""A magrun MCAP recording read back for replay: its metadata and its ticks as arrays.

:func:`read_ticks` decodes what :class:`~magrun.recordings.writer.TrialRecorder` wrote: every pose
stream, the applied currents and the controller's status, one row per control tick (a tick
is its ``/coils/currents`` message; streams absent at a tick are NaN). Images are left out.
``analysis.load`` reads the same files into pandas for statistics; this reader serves the
replay, which needs the protocol and the streams tick by tick, and keeps ``magrun`` free of
``analysis``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun.files import open_binary
from magrun.recordings.recover import not_mcap
from magrun.records import POSE_STREAMS, metadata_value, pose_of

FloatArray = NDArray[np.float64]


RECOVER = "magrun recover rebuilds it"


#: what to do with a recording that cannot be read (analysis.load says the same)
RECOVER_HINT = (
    "the file is truncated or damaged (a recorder that died leaves it unindexed); "
    "`magrun recover IN.mcap OUT.mcap` rebuilds a readable copy"
)


class RecordingReadError(ValueError):
    """A file that is not a readable, indexed magrun recording."""


@dataclass
class RecordedTrial:
    """One trial's recording: ``poses[stream]`` (n, 3) with NaN rows where the stream had
    no message at that tick; ``currents`` (n, channels), A; ``t`` (n,), s."""

    path: Path
    metadata: dict[str, dict[str, str]]
    t: FloatArray
    t_ns: NDArray[np.int64]
    poses: dict[str, FloatArray]
    currents: FloatArray
    channel_names: tuple[str, ...]
    compute_time: FloatArray
    #: (n,) s: how long before its tick each measurement's frame was taken (its message's
    #: log time less its time stamp); NaN where no measurement arrived
    measured_age: FloatArray | None = None

    @property
    def trial(self) -> dict[str, Any]:
        return {k: metadata_value(v) for k, v in self.metadata.get("trial", {}).items()}

    @property
    def protocol_json(self) -> str:
        return self.metadata.get("protocol", {}).get("json", "")

    def measured(self, k: int) -> FloatArray | None:
        z = self.poses["measured"][k]
        return None if np.isnan(z[0]) else z

    def age(self, k: int) -> float:
        """How long before tick ``k`` its measurement's frame was taken, s (0 without one)."""
        if self.measured_age is None or not math.isfinite(age := self.measured_age[k]):
            return 0.0
        return float(age)


def read_ticks(path: str | Path) -> RecordedTrial:
    """Read ``path`` tick by tick (see the module doc).

    Raises
    ------
    RecordingReadError
        Not an MCAP file, no index (``magrun recover`` rebuilds it), or no ``trial`` record.
    """
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    path = Path(path)
    if path.is_file() and (why := not_mcap(path)) is not None:
        raise RecordingReadError(f"{path}: {why}")
    topics = [f"/robot/pose/{s}" for s in POSE_STREAMS] + ["/coils/currents", "/controller/status"]
    rows: dict[int, dict[str, Any]] = {}
    names: tuple[str, ...] = ()
    try:
        with open_binary(path) as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            if reader.get_summary() is None:
                raise RecordingReadError(
                    f"{path}: no summary or index (magrun recover rebuilds it)"
                )
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            for _s, channel, message, msg in reader.iter_decoded_messages(
                topics=topics, log_time_order=True
            ):
                row = rows.setdefault(message.log_time, {})
                topic = channel.topic
                if topic.startswith("/robot/pose/"):
                    stream = topic.rsplit("/", 1)[1]
                    row[stream] = tuple(pose_of(msg))
                    if stream == "measured":
                        stamp = msg.timestamp.seconds * 1_000_000_000 + msg.timestamp.nanos
                        row["measured_age"] = (message.log_time - stamp) / 1e9
                elif topic == "/coils/currents":
                    names = tuple(msg.names)
                    row["currents"] = tuple(msg.currents)
                else:
                    row["compute_time"] = msg.compute_time
    except RecordingReadError:
        raise
    except Exception as exc:  # mcap raises several types for damaged files
        raise RecordingReadError(
            f"{path}: cannot be read: {RECOVER_HINT} ({type(exc).__name__}: {exc})"
        ) from exc
    if "trial" not in meta:
        raise RecordingReadError(f"{path}: no `trial` metadata record: not a magrun recording")
    ticks = sorted(t for t, row in rows.items() if "currents" in row)
    if not ticks:
        raise RecordingReadError(f"{path}: no /coils/currents messages: no control ticks")
    nan3 = (math.nan,) * 3
    poses = {
        s: np.array([rows[t].get(s, nan3) for t in ticks], dtype=np.float64) for s in POSE_STREAMS
    }
    return RecordedTrial(
        path=path,
        metadata=meta,
        t=np.array(ticks, dtype=np.float64) / 1e9,
        t_ns=np.array(ticks, dtype=np.int64),
        poses=poses,
        currents=np.array([rows[t]["currents"] for t in ticks], dtype=np.float64),
        channel_names=names,
        compute_time=np.array([rows[t].get("compute_time", math.nan) for t in ticks]),
        measured_age=np.array([rows[t].get("measured_age", math.nan) for t in ticks]),
    )


def message_counts(path: str | Path) -> dict[str, int] | None:
    """Messages per topic from an MCAP file's summary; None where it has no summary or no
    statistics (a file whose writer died: ``magrun recover``). A damaged file raises what
    the mcap reader raises (several types)."""
    summary = _summary(path)
    if summary is None or summary.statistics is None:
        return None
    counts: dict[str, int] = {}
    for channel_id, n in summary.statistics.channel_message_counts.items():
        topic = summary.channels[channel_id].topic
        counts[topic] = counts.get(topic, 0) + n
    return counts


def has_summary(path: str | Path) -> bool:
    """Whether an MCAP file has a summary (its index); a damaged file raises what the mcap
    reader raises."""
    return _summary(path) is not None


def _summary(path: str | Path) -> Any:
    """An MCAP file's summary (mcap's ``Summary``), or None where it has none."""
    from mcap.reader import make_reader

    with Path(path).open("rb") as fh:
        return make_reader(fh).get_summary()


def raw_messages(path: str | Path, topics: tuple[str, ...]) -> list[tuple[str, int, bytes]]:
    """The messages on ``topics`` as (topic, log time ns, serialised bytes), in log-time
    order."""
    from mcap.reader import make_reader

    with Path(path).open("rb") as fh:
        reader = make_reader(fh)
        return [
            (channel.topic, message.log_time, bytes(message.data))
            for _s, channel, message in reader.iter_messages(
                topics=list(topics), log_time_order=True
            )
        ]
