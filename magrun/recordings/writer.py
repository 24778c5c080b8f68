"""Trial recordings: one MCAP file and one Rerun ``.rrd`` per trial, written off the loop.

The layout and topics are the contract (docs/protocols.md, "Recording format"):

================================  =============================  ==============================
MCAP topic                        schema (protobuf)              Rerun entity
================================  =============================  ==============================
``/camera/image``                 ``foxglove.CompressedImage``   ``/camera/image`` (JPEG)
``/robot/pose/<stream>``          ``foxglove.PoseInFrame``       ``/workspace/<stream>`` (m),
                                                                 ``/camera/<stream>`` (px)
``/coils/currents``               ``magrun.CoilCurrents``        ``/coils/currents`` (A)
``/controller/status``            ``magrun.ControllerStatus``    ``/controller/*``
================================  =============================  ==============================

``<stream>`` is ``actual``, ``tracked``, ``measured``, ``estimated``, ``predicted`` and
``desired``. Log time is trial time in ns; a message's time stamp is its log time, except a
measured pose's: the time its frame was taken (a late frame's age earlier). MCAP metadata
records: ``trial`` (protocol, method, condition values, seed, index, robot, software
versions), ``protocol`` (the protocol as JSON), ``workspace`` (``boundaries``, m, and the
square's ``half_width_m``, as JSON), ``view`` (the recording's id and name, the camera's
pixel mapping: what :func:`~magrun.recordings.rerun_log.rrd_from_mcap` needs) and, at the
end, ``recorder`` (ticks written, dropped, status). The ``.rrd``
(:mod:`magrun.recordings.rerun_log`) also carries ``/errors/*`` series and a blueprint: the
camera view with paths overlaid, the workspace from above with its boundaries, and time
series of currents and errors.

The control loop calls :meth:`TrialRecorder.log` with each :class:`~magrun.records.Tick`; that
only puts it on a bounded queue (never blocks). A writer thread encodes images and writes both
files. A full queue drops the tick, counts it, and the count lands in the ``recorder``
metadata, the manifest and the run summary: never silent. The MCAP writer closes a chunk
every second of trial time, so a crash loses at most that (``magrun recover`` rebuilds the
file's index).
"""

from __future__ import annotations

import json
import math
import platform
import queue
import sys
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any, Self

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.message import Message
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema
from numpy.typing import NDArray

from magrun.realtime import lower_priority, pin_thread
from magrun.recordings.rerun_log import RerunLog, view_metadata
from magrun.recordings.schemas import message_classes
from magrun.records import POSE_STREAMS, Tick, metadata_text
from magrun.records import RecordingSetup as RecordingSetup  # re-exported: the recorder's API
from magrun.records import yaw_of as yaw_of

FloatArray = NDArray[np.float64]

TOPICS = (
    "/camera/image",
    *(f"/robot/pose/{s}" for s in POSE_STREAMS),
    "/coils/currents",
    "/controller/status",
)
FRAME_ID = "workspace"
COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}
#: with a live view, it gets the Rerun rows at least this often (s of wall time), the file
#: every flush_s of trial time (a simulated trial runs faster than that: the viewer gets
#: its rows in fewer, larger pieces, which a web viewer ingests more easily)
LIVE_FLUSH_S = 0.25
#: the interpreter's GIL switch interval while a recorder runs, s (see TrialRecorder.start)
SWITCH_INTERVAL_S = 5e-4
SOFTWARE = ("magrun", "numpy", "casadi", "torch", "rerun-sdk", "mcap", "protobuf")


# magrun's own messages, declared in magrun.recordings.schemas
_MESSAGES = message_classes()
CoilCurrents, ControllerStatusMsg = _MESSAGES["CoilCurrents"], _MESSAGES["ControllerStatus"]


def _stamp(msg: Any, t_ns: int) -> None:
    msg.timestamp.seconds, msg.timestamp.nanos = divmod(t_ns, 1_000_000_000)


def pose_message(pose: FloatArray, t_ns: int) -> PoseInFrame:
    """A pose (x, y, θ) as ``foxglove.PoseInFrame``, stamped ``t_ns`` (the time the pose is
    of): z = 0, yaw θ about +z as a quaternion."""
    msg = PoseInFrame(frame_id=FRAME_ID)
    _stamp(msg, t_ns)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (
        float(pose[0]),
        float(pose[1]),
        0.0,
    )
    half = float(pose[2]) / 2
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(half), math.cos(half)
    return msg


def software_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in SOFTWARE:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


# --------------------------------------------------------------------------------------------
# the recorder


@dataclass
class RecorderStats:
    """What a recorder wrote and lost."""

    ticks_logged: int = 0
    ticks_written: int = 0
    dropped_ticks: int = 0
    images: int = 0
    error: str = ""
    live_view_error: str = ""  # why the live view stopped, if it did (the files are whole)


_STOP = object()


class Recorder(ABC):
    """What the loop and the runner use of a trial recorder, whichever writes the files
    (:class:`TrialRecorder` on a thread, :class:`~magrun.recordings.process.ProcessRecorder`
    in a child process): ``start``, ``log``, ``close``, ``stats`` and the two paths."""

    def __init__(
        self, base: str | Path, setup: RecordingSetup, writer_cpus: Iterable[int] | None = None
    ) -> None:
        self.base = Path(base)
        self.setup = setup
        #: the CPUs the writer is restricted to (None: any; :mod:`magrun.realtime`)
        self.writer_cpus = frozenset(writer_cpus) if writer_cpus is not None else None
        self.stats = RecorderStats()
        self.status = "ok"

    @property
    def mcap_path(self) -> Path:
        return self.base.with_name(self.base.name + ".mcap")

    @property
    def rrd_path(self) -> Path:
        return self.base.with_name(self.base.name + ".rrd")

    @abstractmethod
    def start(self) -> Self:
        """Open both files."""

    @abstractmethod
    def log(self, tick: Tick) -> None:
        """Hand a tick to the writer; never blocks the loop."""

    @abstractmethod
    def close(self, status: str = "ok", reason: str = "") -> RecorderStats:
        """Write what is pending and the ``recorder`` metadata; finish both files."""

    @abstractmethod
    def backlog(self) -> int:
        """Ticks handed over and not yet written (0: the writer is idle)."""

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        self.close("ok" if exc_type is None else "failed")


#: the most points of the desired path the ``workspace`` record keeps (a 60 s path at
#: 25.5 Hz has 1,530; every n-th is kept beyond this, the last always)
REFERENCE_POINTS = 2000


def reference_path(reference: FloatArray | None) -> list[list[float]] | None:
    """The whole desired path's (x, y), m, for the ``workspace`` record's ``reference_m``: what
    a view of the recording draws even where the trial stopped early (a ``--quick`` run)."""
    if reference is None or len(reference) == 0:
        return None
    xy = np.asarray(reference, dtype=np.float64)[:, :2]
    step = -(-len(xy) // REFERENCE_POINTS)
    kept = xy[::step] if (len(xy) - 1) % step == 0 else np.vstack([xy[::step], xy[-1:]])
    return [[round(float(x), 7), round(float(y), 7)] for x, y in kept]


class TrialRecorder(Recorder):
    """Writes one trial to ``<base>.mcap`` and ``<base>.rrd`` on its own thread.

    On a clock (a rig, a benchmark; the default) a full queue drops the tick and counts it,
    and the writer thread runs at nice :data:`~magrun.realtime.WRITER_NICE` (Linux) so that
    the control loop comes first for the CPU. With ``wait_when_full`` (simulation, where no
    clock runs) the loop waits for room instead, and the writer keeps the loop's priority
    (a loop without a clock would otherwise wait on a writer it starves).
    ``writer_cpus`` restricts the writer thread (and Rerun's threads) to those CPUs.

    Use as a context manager, or call :meth:`start` and :meth:`close`::

        with TrialRecorder(base, setup) as rec:
            run_trial(..., on_tick=rec.log)
    """

    def __init__(
        self,
        base: str | Path,
        setup: RecordingSetup,
        queue_size: int = 256,
        flush_s: float = 1.0,
        writer_cpus: Iterable[int] | None = None,
        wait_when_full: bool = False,
    ) -> None:
        super().__init__(base, setup, writer_cpus)
        self.wait_when_full = wait_when_full
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self._flush_ns = int(flush_s * 1e9)
        self._thread: threading.Thread | None = None
        self._frames = 0  # camera frames seen (ticks may have none)

    # ---- loop side ---------------------------------------------------------------------

    def log(self, tick: Tick) -> None:
        """Queue a tick for writing; never blocks (a full queue drops and counts it), unless
        ``wait_when_full``."""
        self.stats.ticks_logged += 1
        try:
            self._queue.put(tick, block=self.wait_when_full)
        except queue.Full:
            self.stats.dropped_ticks += 1

    def backlog(self) -> int:
        s = self.stats
        return 0 if s.error else s.ticks_logged - s.dropped_ticks - s.ticks_written

    # ---- lifecycle ---------------------------------------------------------------------

    def start(self) -> TrialRecorder:
        self.base.parent.mkdir(parents=True, exist_ok=True)
        self._mcap_file = self.mcap_path.open("wb")
        compression = COMPRESSION[self.setup.compression]
        self._mcap = Writer(self._mcap_file, chunk_size=1 << 20, compression=compression)
        self._mcap.start(profile="", library="magrun")
        self._channels: dict[str, int] = {}
        self._mcap.add_metadata("trial", {k: metadata_text(v) for k, v in self.setup.trial.items()})
        self._mcap.add_metadata("protocol", {"json": self.setup.protocol_json})
        self._mcap.add_metadata(
            "workspace",
            {
                "boundaries": json.dumps({k: v.tolist() for k, v in self.setup.boundaries.items()}),
                "half_width_m": json.dumps(self.setup.workspace_half_width),
                "reference_m": json.dumps(reference_path(self.setup.reference)),
            },
        )
        self._mcap.add_metadata("view", view_metadata(self.setup))
        for name, record in self.setup.extra_metadata.items():
            self._mcap.add_metadata(name, record)
        before = pin_thread(self.writer_cpus)  # Rerun's threads, started here, inherit it
        try:
            self._rerun = RerunLog(self.rrd_path, self.setup)
        finally:
            pin_thread(before)
        self._last_flush = 0
        self._last_live_flush = time.monotonic()
        # The writer thread's Python work holds the GIL in slices of the switch interval
        # (5 ms by default): a control tick waiting for it would be late by up to that much.
        # 0.5 ms bounds the wait (magrun bench recorder measures what logging adds).
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, SWITCH_INTERVAL_S))
        self._thread = threading.Thread(target=self._run, name=f"recorder {self.base.name}")
        self._thread.start()
        return self

    def close(self, status: str = "ok", reason: str = "") -> RecorderStats:
        """Write what is queued, the ``recorder`` metadata (``status``, and ``reason``: why
        the trial stopped early, if it did), and close both files."""
        if self._thread is None:
            return self.stats
        self._queue.put(_STOP)  # blocking: the loop is over, the writer drains the queue
        self._thread.join()
        self._thread = None
        sys.setswitchinterval(self._switch_interval)
        self.status = status if not self.stats.error else "failed"
        self._mcap.add_metadata(
            "recorder",
            {
                "status": self.status,
                "ticks_logged": str(self.stats.ticks_logged),
                "ticks_written": str(self.stats.ticks_written),
                "dropped_ticks": str(self.stats.dropped_ticks),
                "images": str(self.stats.images),
                "error": self.stats.error,
                "reason": reason,
            },
        )
        self._mcap.finish()
        self._mcap_file.close()
        self._rerun.close()
        self.stats.live_view_error = self._rerun.live_error
        return self.stats

    # ---- writer thread -----------------------------------------------------------------

    def _run(self) -> None:
        if not self.wait_when_full:
            lower_priority()
        pin_thread(self.writer_cpus)
        while True:
            item = self._queue.get()
            if item is _STOP:
                if not self.stats.error:
                    try:
                        self._rerun.finish_paths()
                    except Exception as exc:
                        self.stats.error = f"{type(exc).__name__}: {exc}"
                return
            if self.stats.error:
                continue  # keep draining so the loop never blocks; the error is reported
            try:
                self._write(item)
                self.stats.ticks_written += 1
            except Exception as exc:  # a writer failure must not kill the trial silently
                self.stats.error = f"{type(exc).__name__}: {exc}"

    def _channel(self, topic: str, cls: type[Message]) -> int:
        if topic not in self._channels:
            schema_id = register_schema(self._mcap, cls)
            self._channels[topic] = self._mcap.register_channel(
                topic=topic, message_encoding="protobuf", schema_id=schema_id
            )
        return self._channels[topic]

    def _put(self, topic: str, msg: Message, t_ns: int) -> None:
        self._put_bytes(topic, type(msg), msg.SerializeToString(), t_ns)

    def _put_bytes(self, topic: str, cls: type[Message], data: bytes, t_ns: int) -> None:
        self._mcap.add_message(
            channel_id=self._channel(topic, cls), log_time=t_ns, publish_time=t_ns, data=data
        )

    def _write(self, tick: Tick) -> None:
        t_ns = round(tick.t * 1e9)
        setup = self.setup
        poses = {
            "actual": tick.actual,
            "tracked": tick.tracked,
            "measured": tick.measured,
            "estimated": tick.estimated,
            "predicted": tick.predicted,
            "desired": tick.desired,
        }
        jpeg: bytes | None = None
        rerun_image = False
        frame = tick.frame  # recorded if it is every image_every-th camera frame
        if frame is not None:
            if not (setup.image_every and self._frames % setup.image_every == 0):
                frame = None
            self._frames += 1
        if frame is not None:
            rerun_image = self.stats.images % setup.rerun_image_every == 0
            if setup.image_format == "raw":
                self._put_bytes("/camera/image", RawImage, raw_image_bytes(frame, t_ns), t_ns)
            else:
                jpeg = encode_jpeg(frame, setup.jpeg_quality)
                img = CompressedImage(frame_id="camera", format="jpeg", data=jpeg)
                _stamp(img, t_ns)
                self._put("/camera/image", img, t_ns)
            self.stats.images += 1
        for name, pose in poses.items():
            if pose is not None:
                # a measurement is stamped when its frame was taken, logged when it arrived
                stamp = t_ns - round(tick.measured_age * 1e9) if name == "measured" else t_ns
                self._put(f"/robot/pose/{name}", pose_message(pose, stamp), t_ns)
        cur = CoilCurrents(names=list(setup.channel_names), currents=tick.currents.tolist())
        _stamp(cur, t_ns)
        self._put("/coils/currents", cur, t_ns)
        s = tick.status
        st = ControllerStatusMsg(
            method=str(setup.trial.get("method", "")),
            solve_time=s.solve_time,
            iterations=s.iterations,
            success=s.success,
            fallback=s.fallback,
            message=s.message,
            compute_time=tick.compute_time,
            measurement=tick.measured is not None,
            tracking_lost=tick.frame is not None and tick.tracked is None,
            latency=tick.latency,
            safety_stop=tick.safety_stop,
            prepare_time=s.prepare_time,
        )
        _stamp(st, t_ns)
        self._put("/controller/status", st, t_ns)
        image = (jpeg if jpeg is not None else frame) if rerun_image else None
        self._rerun.tick(
            tick.t, poses, tick.currents, tick.compute_time, image,
            frame=frame if rerun_image else None,
        )  # fmt: skip
        if t_ns - self._last_flush >= self._flush_ns:
            self._mcap.flush()  # close the chunk: a crash loses at most flush_s of trial time
            self._rerun.flush()
            self._last_flush = t_ns
            self._last_live_flush = time.monotonic()
        elif self.setup.live_view and time.monotonic() - self._last_live_flush >= LIVE_FLUSH_S:
            self._rerun.flush(live_only=True)  # a live viewer follows the trial closely
            self._last_live_flush = time.monotonic()


def encode_jpeg(frame: NDArray[np.uint8], quality: int) -> bytes:
    """An RGB (H, W, 3) or mono (H, W) uint8 frame as JPEG bytes."""
    image = cv2.cvtColor(frame, cv2.COLOR_RGB2BGR) if frame.ndim == 3 else frame
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return bytes(buf.tobytes())


def raw_image(frame: NDArray[np.uint8], t_ns: int, with_data: bool = True) -> RawImage:
    """An uncompressed ``foxglove.RawImage``: ``mono8`` for (H, W), ``rgb8`` for (H, W, 3)."""
    if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or frame.shape[2:] not in ((), (3,)):
        raise ValueError(f"raw frames must be uint8 (H, W) or (H, W, 3), got {frame.shape}")
    h, w = frame.shape[:2]
    channels = 1 if frame.ndim == 2 else 3
    msg = RawImage(
        frame_id="camera",
        width=w,
        height=h,
        encoding="mono8" if channels == 1 else "rgb8",
        step=w * channels,
        data=np.ascontiguousarray(frame).tobytes() if with_data else b"",
    )
    _stamp(msg, t_ns)
    return msg


_RAW_DATA_TAG = bytes([(6 << 3) | 2])  # RawImage.data: field 6, length-delimited


def raw_image_bytes(frame: NDArray[np.uint8], t_ns: int) -> bytes:
    """:func:`raw_image` serialised with one copy of the pixels instead of three.

    The header fields are serialised by protobuf; the pixels are appended as field 6 in the
    wire format (fields may come in any order), straight from the frame's buffer.
    """
    header = raw_image(frame, t_ns, with_data=False).SerializeToString()
    pixels = np.ascontiguousarray(frame).data.cast("B")
    n, length = pixels.nbytes, bytearray()
    while True:  # base-128 varint
        byte, n = n & 0x7F, n >> 7
        length.append(byte | (0x80 if n else 0))
        if not n:
            break
    return b"".join((header, _RAW_DATA_TAG, bytes(length), pixels))


def copy_with_poses(
    src: Path, out: Path, poses: list[tuple[int, str, FloatArray]], name: str,
    record: dict[str, str],
) -> None:  # fmt: skip
    """Copy the recording ``src`` to ``out`` with pose messages added (``poses``: (log time
    ns, topic, pose), in time order, each at its time among the copied messages) and the
    metadata record ``name`` set to ``record`` (a record of that name in ``src`` is not
    copied), written to a temporary name and renamed when complete."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer
    from mcap_protobuf.schema import register_schema

    from magrun.recordings.recover import copy_channel

    tmp = out.with_name(out.name + ".tmp")
    with src.open("rb") as source, tmp.open("wb") as fh:
        reader = make_reader(source)
        header = reader.get_header()
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start(profile=header.profile, library=header.library)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        own: dict[str, int] = {}

        def add_pose(t_ns: int, topic: str, pose: FloatArray) -> None:
            msg = pose_message(pose, t_ns)
            if topic not in own:
                own[topic] = writer.register_channel(
                    topic=topic, message_encoding="protobuf",
                    schema_id=register_schema(writer, type(msg)),
                )  # fmt: skip
            writer.add_message(own[topic], t_ns, msg.SerializeToString(), t_ns)

        i = 0
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            while i < len(poses) and poses[i][0] < message.log_time:
                add_pose(*poses[i])
                i += 1
            writer.add_message(
                copy_channel(writer, channel, schema, channel_ids, schema_ids),
                message.log_time, message.data, message.publish_time, message.sequence,
            )  # fmt: skip
        for item in poses[i:]:
            add_pose(*item)
        for metadata in reader.iter_metadata():
            if metadata.name != name:
                writer.add_metadata(metadata.name, dict(metadata.metadata))
        writer.add_metadata(name, record)
        writer.finish()
    tmp.replace(out)
