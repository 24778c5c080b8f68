"""The Rerun side of a recording: the ``.rrd``'s entities, their styles and its blueprint.

:class:`RerunLog` writes one ``.rrd``. The trial recorder feeds it tick by tick while a trial
runs; :func:`rrd_from_mcap` feeds it from a finished MCAP file (``magrun view FILE.mcap``,
``magrun recover --rrd``), so a recording opened either way shows the same views, on the same
time axis, under the same name.

What the viewer shows (:func:`blueprint`):

- **camera (px)**: the camera frames with the actual, predicted and measured positions and
  the desired and actual paths drawn over them;
- **workspace from above (m)**: x to the right, y up (as in the paper's figures and the
  camera image), framed on the phantom's walls where there are any (else on the workspace
  square), with the boundaries, the desired path and the actual and predicted paths, and a
  legend under the frame: a dot and a name per pose stream, and the critical wall's name in
  its colour (a name on the drawing itself lands on a wall or the channel at some zoom).
  Rerun's 2D views draw y downward and ignore view coordinates, so each entity under
  ``/workspace`` carries a static ``Transform3D`` that mirrors y: the logged values stay the
  true ones (hover shows metres as recorded);
- time series, one unit per plot: coil currents (A), position error (mm), orientation
  error (°), compute time (ms).

The timeline is ``t``, trial time from the start of the trial (a duration, not a date).

A live view (``RecordingSetup.live_view``, a viewer's gRPC URL: ``magrun run --view``) gets
the same entities on a stream of its own, so that the file is written exactly as without it
and whatever becomes of the viewer: its rows as often as the recorder asks
(:meth:`RerunLog.flush` with ``live_only``), camera frames as pixels.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from magrun.records import (
    POSE_STREAMS,
    RecordingSetup,
    metadata_text,
    metadata_value,
    pose_of,
)

if TYPE_CHECKING:
    from magrun.tracking.camera import Camera

FloatArray = NDArray[np.float64]

#: colours of the pose streams in the Rerun views (RGB)
STREAM_COLORS = {
    "actual": (230, 60, 60),
    "tracked": (240, 160, 40),
    "measured": (160, 80, 220),
    "estimated": (60, 140, 230),
    "predicted": (40, 180, 200),
    "desired": (40, 190, 80),
}
#: the coils' current series: distinct colours (matplotlib's tab10, as the figures use)
COIL_COLORS = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
]  # fmt: skip
#: pose streams drawn as points in the workspace view (desired is the static path)
WORKSPACE_STREAMS = ("actual", "tracked", "measured", "estimated", "predicted")
#: pose streams also drawn over the camera image
CAMERA_STREAMS = ("actual", "predicted", "measured")
#: pose streams drawn as whole paths over the views at the end of a trial
PATHS = ("actual", "predicted")
#: the entities directly under ``/workspace``, each mirrored in y for the y-up view
WORKSPACE_ROOTS = (
    *WORKSPACE_STREAMS, "boundaries", "reference", "paths", "square", "legend", "replay",
)  # fmt: skip
#: a replay's streams (``magrun replay``), drawn as ``/workspace/replay/<label>/<stream>``
REPLAY_STREAMS = ("estimated", "predicted")
#: colours of the replays' estimates, by label in order (their predictions lighter)
REPLAY_COLORS = [(30, 50, 140), (200, 40, 140), (120, 90, 20), (0, 120, 100)]
#: margin around the workspace square in the framed view, a fraction of the half-width
FRAME_MARGIN = 0.12
#: legend entries per row under the square, and the rows the framed view leaves room for
LEGEND_PER_ROW = 4
LEGEND_ROWS = 2
LEGEND_ROW_STEP = 1.8  # between rows, in FRAME_MARGIN half-widths (a dot and its name)
#: the workspace square's colour (RGB)
SQUARE_COLOR = (150, 150, 150)
#: the phantom's walls, and the critical one (the spinal cord's side), in the workspace view
BOUNDARY_COLOR = (150, 80, 200)
CRITICAL_COLOR = (225, 95, 20)
#: how long closing a trial waits for a live viewer to take what it has not had, s
LIVE_FLUSH_TIMEOUT_S = 5.0
#: sizes on screen, whatever the zoom: Rerun reads a negative radius as UI points
POINT_RADIUS = -3.5
LINE_RADIUS = -0.75
PATH_RADIUS = -1.25
#: coils whose legend lines one share of the time-series column holds (:func:`blueprint`):
#: with the four plots in equal shares the viewer showed six of the paper rig's eight coils;
#: at 3.5 a share its eight get 2.3 shares, by that measure room for ten lines (nine beside
#: a replay's plot)
LEGEND_LINES_PER_SHARE = 3.5


#: a square the workspace view is framed on: its centre (x, y) and half-width, m
Frame = tuple[tuple[float, float], float]


def view_frame(half_width: float | None, boundaries: dict[str, FloatArray]) -> Frame | None:
    """The square the workspace view is framed on: the smallest about the ``boundaries``'
    bounding box (a phantom fills the view, however small in the workspace), else the
    workspace square of ``half_width`` m; None with neither."""
    walls = [np.asarray(b, dtype=np.float64).reshape(-1, 2) for b in boundaries.values()]
    walls = [w for w in walls if len(w)]
    if walls:
        points = np.concatenate(walls)
        lo, hi = points.min(axis=0), points.max(axis=0)
        half = float(np.max(hi - lo)) / 2
        if half > 0:
            centre = (lo + hi) / 2
            return (float(centre[0]), float(centre[1])), half
    if half_width is not None:
        return (0.0, 0.0), float(half_width)
    return None


def legend_layout(frame: Frame, widths: list[int]) -> tuple[FloatArray, int]:
    """Where the legend's entries go under ``frame``'s square, (n, 2) m, and how many rows
    they take: :data:`LEGEND_PER_ROW` columns, an entry of width w (1 or 2) centred on w
    adjacent columns of one row (a long name over two: the names are drawn centred under
    their dots, in a fixed font size whatever the zoom)."""
    (cx, cy), h = frame
    step = 2 * h / LEGEND_PER_ROW
    positions, col, row = [], 0, 0
    for w in widths:
        w = min(max(int(w), 1), LEGEND_PER_ROW)
        if col + w > LEGEND_PER_ROW:
            col, row = 0, row + 1
        positions.append(
            (
                cx - h + (col + w / 2) * step,
                cy - h * (1 + FRAME_MARGIN * (1 + LEGEND_ROW_STEP * row)),
            )
        )
        col += w
    return np.array(positions, dtype=np.float64).reshape(-1, 2), row + 1 if widths else 0


def blueprint(
    with_camera: bool,
    frame: Frame | None = None,
    with_replays: bool = False,
    channels: int = 0,
    legend_rows: int = LEGEND_ROWS,
    camera_px: tuple[int, int] | None = None,
) -> Any:
    """The ``.rrd``'s layout: camera (framed on the whole ``camera_px`` = (width, height)
    frame when given: the viewer's own framing follows what the view holds and can leave
    part of the frame out), workspace from above (framed on ``frame``'s square
    when given, with room for ``legend_rows`` rows of legend under it), and one time-series
    view per unit; with replays, also the estimation error of the recorded and the replayed
    estimators. The currents' view is taller by ``channels`` (its legend, a line per coil,
    must fit: a plot's legend is cut at the plot's height, not scrolled): a share of the
    column per :data:`LEGEND_LINES_PER_SHARE` coils, the other views one share each."""
    import rerun.blueprint as rrb

    views: list[Any] = []
    if with_camera:
        whole = None
        if camera_px is not None:
            whole = rrb.VisualBounds2D(x_range=[0, camera_px[0]], y_range=[0, camera_px[1]])
        views.append(rrb.Spatial2DView(origin="/camera", name="camera (px)", visual_bounds=whole))
    bounds = None
    if frame is not None:
        # the view's own y points down (each entity is mirrored into it): the legend under
        # the square lies at +y here, with room for its names below the dots
        (cx, cy), h = frame
        r = h * (1 + FRAME_MARGIN)
        bottom = h * (1 + (2.5 + (max(legend_rows, 1) - 1) * LEGEND_ROW_STEP) * FRAME_MARGIN)
        bounds = rrb.VisualBounds2D(x_range=[cx - r, cx + r], y_range=[-cy - r, -cy + bottom])
    views.append(
        rrb.Spatial2DView(
            origin="/workspace", name="workspace from above (m, y up)", visual_bounds=bounds
        )
    )
    plots = [
        rrb.TimeSeriesView(origin="/coils/currents", name="coil currents (A)"),
        rrb.TimeSeriesView(origin="/errors/position_mm", name="position error (mm)"),
        rrb.TimeSeriesView(origin="/errors/orientation_deg", name="orientation error (°)"),
        rrb.TimeSeriesView(origin="/controller", name="compute time (ms)"),
    ]
    if with_replays:
        plots.insert(
            2,
            rrb.TimeSeriesView(
                origin="/errors/estimation_mm", name="estimation error (mm): recorded, replayed"
            ),
        )
    shares = [max(1.0, channels / LEGEND_LINES_PER_SHARE)] + [1.0] * (len(plots) - 1)
    series = rrb.Vertical(*plots, row_shares=shares)
    return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*views), series), collapse_panels=True)


def recording_name(trial: dict[str, Any]) -> str:
    """A name for the viewer from the ``trial`` metadata: protocol, method, trial, seed."""
    parts = [str(trial.get(k)) for k in ("protocol", "method") if trial.get(k) not in (None, "")]
    if trial.get("trial") is not None:
        parts.append(f"trial {trial['trial']}")
    if trial.get("seed") is not None:
        parts.append(f"seed {trial['seed']}")
    return " · ".join(parts) or "magrun trial"


class RerunLog:
    """One trial's ``.rrd``: static scene at construction, rows per tick, paths at close.

    Rows are buffered and sent as columns by :meth:`flush` (one ``rr.log`` costs ~0.1 ms,
    a row of ``send_columns`` ~2 µs); the recorder flushes every second of trial time.
    """

    def __init__(
        self, path: str | Path, setup: RecordingSetup, replays: tuple[str, ...] = ()
    ) -> None:
        import rerun as rr

        self.setup = setup
        self.camera: Camera | None = setup.camera
        self.replays = replays
        # every pose stream drawn: name (a key of tick's poses) -> colour
        self._colors = {name: STREAM_COLORS[name] for name in WORKSPACE_STREAMS}
        for i, label in enumerate(replays):
            color = REPLAY_COLORS[i % len(REPLAY_COLORS)]
            self._colors[f"replay/{label}/estimated"] = color
            self._colors[f"replay/{label}/predicted"] = _lighter(color)
        # the legend: a dot and a name per pose stream (one per replay), then the critical
        # wall's name in its colour
        critical = str(setup.trial.get("critical_boundary") or "")
        legend = {
            _legend_name(n): (c, 1)
            for n, c in {**self._colors, "desired": STREAM_COLORS["desired"]}.items()
            if not n.endswith("/predicted")
        }
        if critical in setup.boundaries:
            legend[f"{critical} (critical wall)"] = (CRITICAL_COLOR, 2)
        frame = view_frame(setup.workspace_half_width, setup.boundaries)
        legend_at, legend_rows = (
            legend_layout(frame, [w for _, w in legend.values()]) if frame else (None, 0)
        )
        camera_px = None if self.camera is None else (self.camera.shape[1], self.camera.shape[0])
        layout = blueprint(
            self.camera is not None,
            frame,
            bool(replays),
            len(setup.channel_names),
            legend_rows,
            camera_px,
        )
        self._rec = rr.RecordingStream(
            "magrun", recording_id=setup.recording_id or None, send_properties=False
        )
        self._rec.save(str(path), default_blueprint=layout)
        streams = [self._rec]
        #: why the live view stopped, if it did ("" while it streams or when there is none)
        self.live_error = ""
        self._live: Any = None
        if setup.live_view:
            self._live = _live_stream(setup, layout)
            if self._live is None:
                self.live_error = _live_lost(setup.live_view, "no viewer listening")
            else:
                streams.append(self._live)
        self._log_all = _Fanout(streams)
        rec = self._log_all
        rec.send_recording_name(setup.name or recording_name(setup.trial))
        rec.log(
            "/trial",
            rr.TextDocument("\n".join(f"{k}: {metadata_text(v)}" for k, v in setup.trial.items())),
            static=True,
        )
        flip = rr.Transform3D(scale=[1.0, -1.0, 1.0])
        for name in WORKSPACE_ROOTS:
            rec.log(f"/workspace/{name}", flip, static=True)
        h = setup.workspace_half_width
        if h is not None:
            square = np.array([[-h, -h], [h, -h], [h, h], [-h, h], [-h, -h]])
            rec.log(
                "/workspace/square",
                rr.LineStrips2D([square], colors=[SQUARE_COLOR], radii=[LINE_RADIUS]),
                static=True,
            )
        if legend_at is not None:
            # the views have no legend: one drawn under the frame, a dot and a name each
            rec.log(
                "/workspace/legend",
                rr.Points2D(
                    legend_at, colors=[c for c, _ in legend.values()], radii=[POINT_RADIUS],
                    labels=list(legend), show_labels=True,
                ),
                static=True,
            )  # fmt: skip
        for name, line in setup.boundaries.items():
            is_critical = name == critical  # the wall not to touch: its own colour
            label = f"{name} (critical wall)" if is_critical else name
            rec.log(
                f"/workspace/boundaries/{name}",
                rr.LineStrips2D(
                    [line], colors=[CRITICAL_COLOR if is_critical else BOUNDARY_COLOR],
                    radii=[PATH_RADIUS], labels=[label],
                    show_labels=False,
                ),
                static=True,
            )  # fmt: skip
        if setup.reference is not None and len(setup.reference):
            ref = np.asarray(setup.reference)[:, :2]
            desired = STREAM_COLORS["desired"]
            rec.log(
                "/workspace/reference",
                rr.LineStrips2D([ref], colors=[desired], radii=[PATH_RADIUS]),
                static=True,
            )
            if self.camera is not None:
                rec.log(
                    "/camera/reference",
                    rr.LineStrips2D(
                        [self.camera.to_pixel(ref)], colors=[desired], radii=[LINE_RADIUS]
                    ),
                    static=True,
                )
        if replays:
            estimators = ["recorded", *replays]
            for name in estimators:
                key = "estimated" if name == "recorded" else f"replay/{name}/estimated"
                rec.log(
                    f"/errors/estimation_mm/{name}",
                    rr.SeriesLines(names=[name], colors=[self._colors[key]]),
                    static=True,
                )
        rec.log(
            "/coils/currents",
            rr.SeriesLines(
                names=list(setup.channel_names),
                colors=[COIL_COLORS[i % len(COIL_COLORS)] for i in range(len(setup.channel_names))],
            ),
            static=True,
        )
        for name, color in self._colors.items():  # styles once; positions come in columns
            style = rr.Points2D.from_fields(
                radii=[POINT_RADIUS], colors=[color], labels=[_legend_name(name)],
                show_labels=False,
            )  # fmt: skip
            rec.log(f"/workspace/{name}", style, static=True)
            if self.camera is not None and _on_camera(name):
                rec.log(f"/camera/{name}", style, static=True)
        self._paths: dict[str, list[FloatArray]] = {
            name: [] for name in (*PATHS, *(f"replay/{r}/estimated" for r in replays))
        }
        self._rows: dict[str, tuple[list[float], list[Any]]] = {}
        self._live_sent: dict[str, int] = {}  # of each entity's buffered rows, sent live

    def tick(
        self,
        t: float,
        poses: dict[str, FloatArray | None],
        currents: FloatArray,
        compute_time: float,
        image: bytes | NDArray[np.uint8] | None = None,
        frame: NDArray[np.uint8] | None = None,
    ) -> None:
        """Buffer one tick's rows: ``poses`` by stream (x, y, θ; None where absent), the
        currents (A), the compute time (s) and an image (JPEG bytes, buffered; or a raw
        frame, sent at once).

        A live view gets the image as pixels, at once: ``frame``, the JPEG's own frame
        where the caller has it, else the JPEG decoded. (Rerun's web viewer draws JPEG
        images only once a recording has stopped arriving; pixels it draws as they come.)"""
        import rerun as rr

        if isinstance(image, bytes):
            self._row("/camera/image", t, image)
        elif image is not None:
            self._rec.set_time("t", duration=t)
            self._rec.log("/camera/image", rr.Image(image))
        if self._live is not None and image is not None:
            if not isinstance(image, bytes):
                pixels = image
            else:
                pixels = frame if frame is not None else _decode_jpeg(image)
            self._live.set_time("t", duration=t)
            self._live.log("/camera/image", rr.Image(pixels))
        cam = self.camera
        for name in self._colors:
            pose = poses.get(name)
            if pose is None:
                continue
            self._row(f"/workspace/{name}", t, pose[:2])
            if cam is not None and _on_camera(name):
                self._row(f"/camera/{name}", t, cam.to_pixel(pose[:2]))
        for name, path in self._paths.items():
            point = poses.get(name)
            if point is not None:
                path.append(np.asarray(point[:2], dtype=np.float64))
        actual = poses.get("actual")
        if self.replays and actual is not None:  # colours as the streams (set at start)
            for name, key in [("recorded", "estimated")] + [
                (r, f"replay/{r}/estimated") for r in self.replays
            ]:
                est = poses.get(key)
                if est is not None:
                    d = np.asarray(est) - np.asarray(actual)
                    self._row(f"/errors/estimation_mm/{name}", t, math.hypot(d[0], d[1]) * 1e3)
        self._row("/coils/currents", t, currents)
        desired = poses.get("desired")
        if actual is not None and desired is not None:
            err = np.asarray(actual) - np.asarray(desired)
            self._row("/errors/position_mm", t, math.hypot(err[0], err[1]) * 1e3)
            wrapped = (err[2] + math.pi) % (2 * math.pi) - math.pi
            self._row("/errors/orientation_deg", t, abs(math.degrees(wrapped)))
        self._row("/controller/compute_ms", t, compute_time * 1e3)

    def _row(self, entity: str, t: float, value: Any) -> None:
        times, values = self._rows.setdefault(entity, ([], []))
        times.append(t)
        values.append(value)

    def flush(self, live_only: bool = False) -> None:
        """Send the buffered rows as columns: points for positions, scalars for series.

        With ``live_only`` they go to the live view only and stay buffered for the file, so
        a viewer can follow a trial closely while the file's chunks stay as without one."""
        live = self._live
        for entity, (times, values) in self._rows.items():
            sent = self._live_sent.get(entity, 0)
            if live is not None and len(times) > sent and entity != "/camera/image":
                live.send_columns(entity, **_columns(entity, times[sent:], values[sent:]))
            if live_only:
                self._live_sent[entity] = len(times)
                continue
            if times:
                self._rec.send_columns(entity, **_columns(entity, times, values))
            times.clear()
            values.clear()
            self._live_sent[entity] = 0

    def finish_paths(self) -> None:
        """Send what is buffered and the whole actual and predicted paths (static: drawn
        over both views at any time)."""
        import rerun as rr

        self.flush()
        cam = self.camera
        for name, points in self._paths.items():
            if len(points) < 2:
                continue
            line = np.stack(points)
            color = self._colors[name]
            self._log_all.log(
                f"/workspace/paths/{name}",
                rr.LineStrips2D([line], colors=[color], radii=[LINE_RADIUS]),
                static=True,
            )
            if cam is not None:
                self._log_all.log(
                    f"/camera/paths/{name}",
                    rr.LineStrips2D([cam.to_pixel(line)], colors=[color], radii=[LINE_RADIUS]),
                    static=True,
                )

    def close(self, timeout_s: float = 60.0) -> None:
        """Finish the file (what :meth:`finish_paths` has not sent is lost), and hand the
        live view what it has not had yet (a viewer gone away costs the file nothing)."""
        self._rec.flush(timeout_sec=timeout_s)
        self._rec.disconnect()
        if self._live is not None:
            try:
                self._live.flush(timeout_sec=LIVE_FLUSH_TIMEOUT_S)
            except Exception as exc:  # the viewer closed, the network went: the file is whole
                self.live_error = _live_lost(self.setup.live_view, str(exc))
            finally:
                self._live.disconnect()


class _Fanout:
    """The same call on every stream: the file's, and the live view's when there is one.

    Two streams rather than one with two sinks, so that the file is written exactly as
    without a viewer, whatever becomes of the viewer."""

    def __init__(self, streams: list[Any]) -> None:
        self._streams = streams

    def __getattr__(self, name: str) -> Any:
        methods = [getattr(s, name) for s in self._streams]

        def call(*args: Any, **kwargs: Any) -> None:
            for method in methods:
                method(*args, **kwargs)

        return call


def _live_stream(setup: RecordingSetup, layout: Any) -> Any:
    """A recording stream to the viewer at ``setup.live_view`` (a gRPC URL), or None where
    nothing listens there (a viewer closed during an earlier trial: no stream is opened
    that would wait on it)."""
    import rerun as rr

    if not viewer_listening(setup.live_view):
        return None
    live = rr.RecordingStream(
        "magrun", recording_id=setup.recording_id or None, send_properties=False
    )
    live.set_sinks(rr.GrpcSink(setup.live_view), default_blueprint=layout)
    return live


def viewer_listening(url: str, timeout_s: float = 1.0) -> bool:
    """Whether something accepts connections at the host and port of the gRPC ``url``
    (``rerun+http://HOST:PORT/proxy``)."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    try:
        with socket.create_connection((parts.hostname or "127.0.0.1", parts.port or 9876),
                                      timeout=timeout_s):  # fmt: skip
            return True
    except OSError:
        return False


_warned: set[str] = set()


def _live_lost(url: str, why: str) -> str:
    """Say once per process on stderr that the live view at ``url`` stopped; the text."""
    import sys

    text = f"live view at {url} stopped ({why}); the recordings are written as usual"
    if url not in _warned:
        _warned.add(url)
        print(f"magrun: {text}", file=sys.stderr, flush=True)
    return text


def _decode_jpeg(data: bytes) -> NDArray[np.uint8]:
    """A JPEG's pixels: (H, W, 3) RGB or (H, W) mono."""
    import cv2

    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise ValueError("an image that is not a JPEG")
    rgb = cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB) if pixels.ndim == 3 else pixels
    return np.asarray(rgb, dtype=np.uint8)


def _columns(entity: str, times: list[float], values: list[Any]) -> dict[str, Any]:
    """``send_columns``'s arguments for one entity's rows."""
    import rerun as rr

    index = [rr.TimeColumn("t", duration=np.asarray(times))]
    if entity == "/camera/image":
        columns = rr.EncodedImage.columns(blob=values, media_type=["image/jpeg"] * len(values))
    else:
        data = np.asarray(values, dtype=np.float64)
        if entity.startswith(("/workspace/", "/camera/")):
            columns = rr.Points2D.columns(positions=data.reshape(-1, 2))
        else:
            columns = rr.Scalars.columns(scalars=data.reshape(len(times), -1))
    return {"indexes": index, "columns": columns}


def _lighter(color: tuple[int, int, int]) -> tuple[int, int, int]:
    r, g, b = color
    return (r + (255 - r) // 2, g + (255 - g) // 2, b + (255 - b) // 2)


def _legend_name(stream: str) -> str:
    """``replay/<label>/estimated`` → ``<label> (replayed)``; other streams as they are."""
    if stream.startswith("replay/"):
        _, label, what = stream.split("/", 2)
        return f"{label} (replayed)" if what == "estimated" else f"{label} predicted"
    return stream


def _on_camera(stream: str) -> bool:
    """Streams drawn over the camera image too: actual, predicted, measured, replayed."""
    replayed = stream.startswith("replay/") and stream.endswith("/estimated")
    return stream in CAMERA_STREAMS or replayed


def view_metadata(setup: RecordingSetup) -> dict[str, str]:
    """The MCAP ``view`` metadata record: what :func:`rrd_from_mcap` needs beyond the
    messages (the recording's id and name, the camera's pixel mapping)."""
    cam = setup.camera
    camera = None
    if cam is not None:
        c = cam.config
        camera = {
            "width_px": c.width_px, "height_px": c.height_px, "px_per_mm": c.px_per_mm,
            "center_m": list(cam.center),
        }  # fmt: skip
    return {
        "recording_id": setup.recording_id,
        "name": setup.name or recording_name(setup.trial),
        "camera": json.dumps(camera),
    }


def recorded_reference(workspace: dict[str, str]) -> FloatArray | None:
    """The whole desired path (n, 2), m, of a recording's ``workspace`` record, or None where
    it has none (recordings from before it was recorded) or it is not a finite (n, 2) list."""
    value = metadata_value(workspace.get("reference_m", "null"))
    if not isinstance(value, list) or not value:
        return None
    try:
        xy = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if xy.ndim != 2 or xy.shape[1] != 2 or not np.all(np.isfinite(xy)):
        return None
    return xy


def rrd_from_mcap(mcap: str | Path, rrd: str | Path, live_view: str = "") -> int:
    """Write ``rrd`` from a magrun MCAP recording, with the recorder's entities and
    blueprint, and stream it to the viewer at the gRPC URL ``live_view`` too if one is
    given; returns the number of ticks written.

    Every pose, current and status message and every recorded image goes in. Recordings
    made before the ``view`` metadata record existed get a name from the ``trial`` record
    and no pixel overlay on the camera view. The ``.rrd`` is written beside ``rrd`` and
    renamed over it when complete: a damaged recording leaves no partial file, and an
    existing ``rrd`` stays as it was.

    Raises
    ------
    ValueError
        ``mcap`` is not a readable, indexed magrun recording, or is damaged inside (a bit
        flipped in a chunk or a schema: the decoders' errors, named).
    """
    mcap, rrd = Path(mcap), Path(rrd)
    part = rrd.with_name(f".{rrd.stem}.part{rrd.suffix}")
    try:
        ticks = _rrd_from_mcap(mcap, part, live_view)
    except Exception as exc:  # zstd, protobuf, mcap, struct and codecs raise for damage
        part.unlink(missing_ok=True)
        if isinstance(exc, ValueError) and str(exc).startswith(str(mcap)):
            raise  # ours: says what is wrong with the file
        raise ValueError(f"{mcap}: damaged, cannot be read ({type(exc).__name__}: {exc})") from exc
    part.replace(rrd)
    return ticks


def _rrd_from_mcap(mcap: Path, rrd: Path, live_view: str) -> int:
    """:func:`rrd_from_mcap`'s work, into ``rrd``."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    with mcap.open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        if reader.get_summary() is None:
            raise ValueError(f"{mcap}: no summary or index (magrun recover rebuilds it)")
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        if "trial" not in meta:
            raise ValueError(f"{mcap}: no `trial` metadata record: not a magrun recording")
        trial = {k: metadata_value(v) for k, v in meta["trial"].items()}
        workspace = meta.get("workspace", {})
        boundaries = {
            k: np.asarray(v, dtype=np.float64).reshape(-1, 2)
            for k, v in (metadata_value(workspace.get("boundaries", "{}")) or {}).items()
        }
        half_width = metadata_value(workspace.get("half_width_m", "null"))
        view = meta.get("view", {})
        # the whole desired path, drawn from the start: the workspace record's (a trial
        # stopped early, a --quick one, still shows where it was going); recordings from
        # before it was recorded: one pass over the desired poses
        reference = recorded_reference(workspace)
        if reference is None:
            desired = [
                pose_of(msg)
                for _s, _c, _m, msg in reader.iter_decoded_messages(
                    topics=["/robot/pose/desired"], log_time_order=True
                )
            ]
            reference = np.asarray(desired) if desired else None
        names: tuple[str, ...] = ()
        for _s, _c, _m, msg in reader.iter_decoded_messages(
            topics=["/coils/currents"], log_time_order=True
        ):
            names = tuple(msg.names)
            break
        setup = RecordingSetup(
            trial=trial,
            channel_names=names,
            boundaries=boundaries,
            workspace_half_width=float(half_width) if half_width is not None else None,
            reference=reference,
            camera=_camera(metadata_value(view.get("camera", "null"))),
            recording_id=view.get("recording_id") or f"{mcap.stem}@{mcap.parent.name}",
            name=view.get("name") or recording_name(trial),
            live_view=live_view,
        )
        summary = reader.get_summary()
        replay_topics = sorted(
            c.topic for c in (summary.channels.values() if summary else ())
            if c.topic.startswith("/replay/") and c.topic.count("/") == 5
        )  # fmt: skip
        labels = tuple(dict.fromkeys(topic.split("/")[2] for topic in replay_topics))
        log = RerunLog(rrd, setup, replays=labels)
        topics = [f"/robot/pose/{s}" for s in POSE_STREAMS] + replay_topics
        topics += ["/coils/currents", "/controller/status", "/camera/image"]
        ticks = 0
        current: dict[str, Any] = {}
        last_t: int | None = None
        flushed = 0
        for _schema, channel, message, msg in reader.iter_decoded_messages(
            topics=topics, log_time_order=True
        ):
            if last_t is not None and message.log_time != last_t:
                ticks += _send(log, last_t, current)
                current = {}
                if last_t - flushed >= 1_000_000_000:  # about once a second of trial
                    log.flush()  # time, as the recorder does
                    flushed = last_t
            last_t = message.log_time
            topic = channel.topic
            if topic.startswith("/robot/pose/"):
                current[topic.rsplit("/", 1)[1]] = pose_of(msg)
            elif topic.startswith("/replay/"):  # /replay/<label>/robot/pose/<stream>
                parts = topic.split("/")
                current[f"replay/{parts[2]}/{parts[-1]}"] = pose_of(msg)
            elif topic == "/coils/currents":
                current["currents"] = np.asarray(msg.currents, dtype=np.float64)
            elif topic == "/controller/status":
                current["compute_time"] = msg.compute_time
            else:
                current["image"] = _image(msg)
        if last_t is not None:
            ticks += _send(log, last_t, current)
        log.finish_paths()
        log.close()
    return ticks


def _send(log: RerunLog, t_ns: int, row: dict[str, Any]) -> int:
    if "currents" not in row:
        return 0  # a tick is its currents message; anything else alone is not a tick
    t = t_ns / 1e9
    poses = {k: v for k, v in row.items() if k not in ("currents", "compute_time", "image")}
    log.tick(t, poses, row["currents"], row.get("compute_time", math.nan), row.get("image"))
    return 1


def _image(msg: Any) -> bytes | NDArray[np.uint8] | None:
    if hasattr(msg, "format"):  # foxglove.CompressedImage
        return bytes(msg.data) if msg.format.lower() in ("jpeg", "jpg") else None
    channels = {"mono8": 1, "rgb8": 3}.get(msg.encoding)
    if channels is None:
        return None
    pixels = np.frombuffer(msg.data, dtype=np.uint8)
    frame = pixels.reshape(msg.height, msg.step)[:, : msg.width * channels]
    return frame.reshape(msg.height, msg.width, channels).squeeze(-1 if channels == 1 else ())


def _camera(doc: Any) -> Camera | None:
    if not isinstance(doc, dict):
        return None
    from magrun.tracking.camera import Camera, CameraConfig

    config = CameraConfig(
        width_px=int(doc["width_px"]), height_px=int(doc["height_px"]),
        px_per_mm=float(doc["px_per_mm"]),
    )  # fmt: skip
    cx, cy = doc.get("center_m", (0.0, 0.0))
    return Camera(config, (float(cx), float(cy)))
