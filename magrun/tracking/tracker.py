"""Camera tracking: a frame in, the robot's pose (with a confidence) out.

::

    frame ─ window at the previous pose ─► UNet ─► 3 heat maps ─► candidate peaks
            (whole frame when there is none)                               │
    (x, y, θ), confidence ◄─ rigid fit ◄─ camera px → m ◄─ consistent tail, centre, head

The tracker runs the UNet on a ``window_px``-square window (by default the robot's length
plus 12 px each side: 64 px, 25.6 mm, for the magnet robot; the model trained on 96 px crops)
centred on the previous pose: at a camera's rate the robot moves at most ~1 mm between
frames, and the window keeps the per-frame cost low whatever the frame size. Where the robot
is not in that window (it moved further between two low-rate frames) the tracker looks in a
wider window around the same pose (``search_px``, twice the side by default: a quarter of
the whole frame's cost on a 256 px frame), and only then in the whole frame, with the same,
fully convolutional network; with no previous pose (the first frame, or the robot was lost)
it searches the whole frame. A robot found that way is refined in a window around it, and
so is one found at the first window's edge (it may reach outside). Each heat map may offer
a few peaks; :func:`select_keypoints` takes the strongest three that form the robot. A
result is rejected (``pose`` is ``None``) when a point's peak is below ``min_confidence``,
or the tail-to-head span is not within 25 % of the robot's length.

    >>> tracker = Tracker.default(Camera(), load_robot("magnet"))         # doctest: +SKIP
    >>> tracker(frame).pose                                               # doctest: +SKIP
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.robot import RobotParams
from magrun.tracking.camera import DEFAULT_CAMERA, Camera
from magrun.tracking.heatmaps import peak_candidates, refine_peak
from magrun.tracking.inference import (
    TRAIN_EXTRA,
    Backend,
    MissingGraph,
    UNetNet,
    check_backend,
    graph_net,
    to_array,
)
from magrun.tracking.keypoints import pose_from_keypoints
from magrun.tracking.weights import WeightsFile, graph_path_of, read_weights

if TYPE_CHECKING:
    from magrun.tracking.unet import KeypointUNet

FloatArray = NDArray[np.float64]
U8 = NDArray[np.uint8]


def default_weights_path() -> Path:
    """The shipped weights, trained by ``magrun tracker train`` (see docs/tracking.md); their
    ONNX graph, which tracking runs, lies beside them (``unet.onnx``)."""
    return Path(str(resources.files("magrun") / "tracking" / "data" / "unet.npz"))


@dataclass
class _Loaded:
    """A network :meth:`Tracker.default` loaded, with what it was loaded from."""

    files: tuple[object, ...]  # the weights' and the graph's size and modification time
    net: UNetNet
    px_per_mm: float
    #: the sizes :meth:`Tracker.warm_up` ran it on (its run function, which a tracker may
    #: wrap, the working frame's size, the window and the wider window)
    warmed: set[tuple[object, ...]] = field(default_factory=set)


#: the networks :meth:`Tracker.default` loaded in this process, one per weights file, backend
#: and inference threads: a process that runs trial after trial (a campaign's worker) reads
#: and checks a weights file and starts the runtime's session once, not once a trial
_NETS: dict[tuple[str, Backend, int | None], _Loaded] = {}


def _files(path: Path) -> tuple[object, ...] | None:
    """The weights file's and its graph's (:func:`graph_path_of`) size and modification
    time; None where the weights cannot be looked at (reading them says why)."""
    try:
        weights = path.stat()
    except OSError:
        return None
    try:
        graph = graph_path_of(path).stat()
        beside: tuple[int, int] | None = (graph.st_size, graph.st_mtime_ns)
    except OSError:
        beside = None
    return weights.st_size, weights.st_mtime_ns, beside


def load_net(weights: WeightsFile, backend: Backend = "onnx") -> UNetNet:
    """The network of ``weights``: their ONNX graph (:func:`~magrun.tracking.inference.graph_net`);
    with torch installed, where no graph of theirs lies beside them, one exported in memory;
    and with ``backend`` ``"torch"``, torch's own model (the reference).

    Raises :class:`~magrun.tracking.inference.MissingGraph` saying how to export the graph
    where it is missing and torch is not installed."""
    check_backend(backend)
    problem: MissingGraph | None = None
    if backend == "onnx":
        try:
            return graph_net(weights)
        except MissingGraph as exc:
            problem = exc
    try:
        from magrun.tracking import export
    except ImportError as exc:  # torch is the train extra
        if problem is None:
            raise MissingGraph(f"the torch backend needs torch: {TRAIN_EXTRA}") from exc
        raise MissingGraph(
            f"{problem}; `magrun tracker export {weights.path}` writes it "
            f"(needs torch: {TRAIN_EXTRA})"
        ) from exc
    return export.weights_net(weights, backend)


@dataclass(frozen=True)
class TrackResult:
    """One frame's tracking.

    Attributes
    ----------
    pose : ndarray, shape (3,), or None
        ``(x, y, θ)`` in m and rad; ``None`` when the robot was not found.
    confidence : float
        The lowest of the three heat-map peaks (0–1).
    keypoints : ndarray, shape (3, 2)
        Tail, centre and head in frame pixels ``(u, v)``.
    searched : bool
        Whether the robot was looked for beyond the window at the previous pose (in the
        wider window or the whole frame).
    """

    pose: FloatArray | None
    confidence: float
    keypoints: FloatArray
    searched: bool


#: score penalty per unit of geometric inconsistency (see :func:`select_keypoints`)
CONSISTENCY_WEIGHT = 3.0


def select_keypoints(
    candidates: list[tuple[NDArray[np.intp], FloatArray]], length_px: float
) -> tuple[NDArray[np.intp], FloatArray]:
    """The tail, centre and head peaks that best fit a robot of ``length_px``.

    A small network can answer "an end of the yellow half" for both the tail and the centre
    of the magnet robot; each map may then hold a second peak. Among all combinations of
    candidate peaks (:func:`~magrun.tracking.heatmaps.peak_candidates`), pick the one maximising

        h_tail + h_centre + h_head − w · (|‖head − tail‖ − L| / L + 2 ‖centre − mid‖ / L)

    (h peak heights, mid the tail–head midpoint, w = :data:`CONSISTENCY_WEIGHT`): the
    strongest peaks, unless they do not form the robot. Returns the chosen pixels (3, 2)
    and their heights (3,).
    """
    (tp, th), (cp, ch), (hp, hh) = candidates
    t = tp[:, None, None].astype(np.float64)
    c = cp[None, :, None].astype(np.float64)
    h = hp[None, None, :].astype(np.float64)
    span = np.linalg.norm(h - t, axis=-1)
    off_centre = np.linalg.norm(c - (t + h) / 2, axis=-1)
    bad = np.abs(span - length_px) / length_px + 2 * off_centre / length_px
    score = th[:, None, None] + ch[None, :, None] + hh[None, None, :] - CONSISTENCY_WEIGHT * bad
    i, j, k = np.unravel_index(int(np.argmax(score)), score.shape)
    return np.array([tp[i], cp[j], hp[k]]), np.array([th[i], ch[j], hh[k]])


#: border kept around the robot in the tracking window, px at the model's scale
WINDOW_MARGIN_PX = 12
#: a keypoint this close to a window's edge (px) means the robot may reach outside it
EDGE_PX = WINDOW_MARGIN_PX // 2


class Tracker:
    """UNet keypoint tracker for one robot seen by one camera.

    Parameters
    ----------
    model : UNetNet or KeypointUNet
        The trained network (:meth:`default` loads the shipped one, or a weights file's):
        a runnable graph (:func:`~magrun.tracking.inference.weights_net`), or a torch model
        (needs torch; run by ``backend``).
    camera : Camera
        Frame size and the px ↔ m mapping (the calibration, on a real rig).
    robot : RobotParams
        The tracked robot (its length fixes the fiducials' spacing).
    min_confidence : float
        Smallest accepted heat-map peak.
    window_px : int, optional
        Side of the window tracked around the previous pose (a multiple of the UNet's stride),
        px at the model's scale. It must hold the robot at any heading plus a margin for the
        network's border (:data:`WINDOW_MARGIN_PX` each side) and its motion between frames
        (under 1 px). Default: the robot's length plus the margins, rounded up to the stride
        (64 px for the 16 mm magnet robot, 48 px for the 7.4 mm capsule at 2.5 px/mm). The
        UNet's cost grows with the window's area.
    search_px : int, optional
        Side of the wider window tried around the previous pose when the robot is not in the
        first (a multiple of the stride); the whole frame is searched only where it fails too.
        Default: twice ``window_px``. Where it covers the whole frame, the frame is searched.
    model_px_per_mm : float
        The scale the model was trained at. Frames at another scale (a real camera) are
        resized to it before tracking; results are reported in the frame's own pixels.
    backend : {"onnx", "torch"}
        What runs a torch ``model``: ONNX Runtime (default, ~1.8× faster per window here) or
        torch (the reference). Same heat maps to ~1e-5. A ``UNetNet`` says its own.
    """

    def __init__(
        self,
        model: UNetNet | KeypointUNet,
        camera: Camera,
        robot: RobotParams,
        min_confidence: float = 0.3,
        window_px: int | None = None,
        model_px_per_mm: float = DEFAULT_CAMERA.px_per_mm,
        backend: Backend = "onnx",
        search_px: int | None = None,
    ) -> None:
        if not isinstance(model, UNetNet):  # a torch model (training, evaluation)
            from magrun.tracking.export import model_net

            model = model_net(model, backend)
        self.backend = model.backend
        self._net = model.run
        self.stride = model.stride
        self.camera = camera
        cfg = camera.config
        # cv2.resize maps pixel centres by (u + ½)·W'/W − ½: the working camera's scale is
        # W'/W times the frame's, its principal point the resized frame's centre
        self._size = (
            max(round(cfg.width_px * model_px_per_mm / cfg.px_per_mm), 16),
            max(round(cfg.height_px * model_px_per_mm / cfg.px_per_mm), 16),
        )
        self._factor = self._size[0] / cfg.width_px
        self._work = Camera(
            replace(cfg, width_px=self._size[0], height_px=self._size[1],
                    px_per_mm=cfg.px_per_mm * self._factor),
            camera.center,
        )  # fmt: skip
        self.robot = robot
        self.min_confidence = min_confidence
        if window_px is None:
            length_px = robot.length * 1e3 * model_px_per_mm
            window_px = self.stride * math.ceil((length_px + 2 * WINDOW_MARGIN_PX) / self.stride)
        if window_px % self.stride or window_px < 4 * self.stride:
            raise ValueError(f"window_px must be a multiple of {self.stride}, ≥ {4 * self.stride}")
        self.window_px = window_px
        search_px = 2 * window_px if search_px is None else search_px
        if search_px % self.stride or search_px < window_px:
            raise ValueError(f"search_px must be a multiple of {self.stride}, ≥ window_px")
        self.search_px = search_px
        self.last_pose: FloatArray | None = None
        #: the sizes warm_up ran the network on (shared by the trackers of one network that
        #: :meth:`default` loaded)
        self._warmed: set[tuple[object, ...]] = set()

    @classmethod
    def default(
        cls,
        camera: Camera,
        robot: RobotParams,
        weights: str | Path | None = None,
        backend: Backend = "onnx",
    ) -> Tracker:
        """A tracker with the shipped weights (or those in ``weights``), run from their ONNX
        graph (``backend`` ``"torch"``: by torch). Raises ``ValueError`` (or its subclass
        :class:`~magrun.tracking.inference.MissingGraph`) saying what is wrong with them.
        The network is loaded once in a process while its files stay as they are (a
        rewritten file is read again); each tracker has its own state."""
        from magrun.tracking import inference

        path = Path(weights) if weights is not None else default_weights_path()
        key = (str(path.absolute()), backend, inference._threads)
        files = _files(path)
        loaded = _NETS.get(key)
        if loaded is None or files is None or loaded.files != files:
            _NETS.pop(key, None)
            file = read_weights(path)
            loaded = _Loaded(files or (), load_net(file, backend), file.px_per_mm)
            if files is not None:
                _NETS[key] = loaded
        tracker = cls(loaded.net, camera, robot, model_px_per_mm=loaded.px_per_mm)
        tracker._warmed = loaded.warmed
        return tracker

    def reset(self) -> None:
        """Forget the previous pose (a new trial)."""
        self.last_pose = None

    def __call__(self, frame: U8) -> FloatArray | None:
        """The pose in ``frame``, or ``None``; remembers it as the next frame's prior."""
        return self.track(frame).pose

    def track(self, frame: U8, prior: ArrayLike | None = None) -> TrackResult:
        """Track in ``frame`` (H, W, 3 uint8 RGB) near ``prior`` (default: the last pose)."""
        if frame.shape[:2] != self.camera.shape:
            raise ValueError(f"frame is {frame.shape[:2]}, the camera's {self.camera.shape}")
        if self._size != (frame.shape[1], frame.shape[0]):
            frame = np.asarray(cv2.resize(frame, self._size, interpolation=cv2.INTER_AREA))
        guess = self.last_pose if prior is None else np.asarray(prior, dtype=np.float64)
        result = None
        if guess is not None:
            window = self._window(frame, guess, None)
            result = self._tracked_in(frame, window, searched=False)
            if result.pose is not None and self._near_edge(frame, result, window):
                # the robot at the window's edge, partly outside it: track it again in a
                # window centred on it (a partial robot's pose is off by up to ~1 mm)
                again = self._in_window(frame, result.pose, searched=False)
                result = again if again.pose is not None else result
        if result is None or result.pose is None:
            found = None
            if guess is not None and self._wider_than_window(frame):
                found = self._in_window(frame, guess, searched=True, side=self.search_px)
            if found is None or found.pose is None:
                found = self._search(frame)
            result = found
            if found.pose is not None:
                refined = self._in_window(frame, found.pose, searched=True)
                result = refined if refined.pose is not None else found
        self.last_pose = result.pose
        if self._factor != 1.0:  # report keypoints in the caller's frame pixels
            result = replace(result, keypoints=(result.keypoints + 0.5) / self._factor - 0.5)
        return result

    def warm_up(self) -> None:
        """Run the network once on each input size tracking uses (the window, the wider
        window, the whole frame), so that the runtime's first-run work on a size (memory
        plans, allocations: ~10 ms for a whole frame here) happens now, before a control
        loop, and not in its first ticks. The heat maps are discarded. A network that
        :meth:`default` shares is warmed once a process for each set of sizes."""
        sizes = (self._net, self._size, self.window_px, self.search_px)
        if sizes in self._warmed:  # a network this process shares, already run on these
            return
        blank = np.zeros((self._size[1], self._size[0], 3), dtype=np.uint8)
        pose = np.array([*self._work.center[:2], 0.0])
        self._in_window(blank, pose, searched=False)
        if self._wider_than_window(blank):
            self._in_window(blank, pose, searched=True, side=self.search_px)
        self._search(blank)
        self._warmed.add(sizes)

    def _heatmaps(self, image: U8) -> NDArray[np.float32]:
        return self._net(to_array(image))[0]

    def _side(self, frame: U8, side: int) -> int:
        """A square window's side in ``frame``: ``side`` where the frame holds it, else the
        frame's shorter side rounded down to the stride."""
        h, w = frame.shape[:2]
        return min(side, h - h % self.stride, w - w % self.stride)

    def _wider_than_window(self, frame: U8) -> bool:
        """Whether the wider window is smaller than the whole frame (else: search it)."""
        h, w = frame.shape[:2]
        side = self._side(frame, self.search_px)
        return side > self.window_px and (side < h - h % self.stride or side < w - w % self.stride)

    def _window(self, frame: U8, pose: FloatArray, side: int | None) -> tuple[int, int, int]:
        """The square window of ``side`` (default ``window_px``) centred on ``pose`` as far as
        the frame allows: its corner ``(u0, v0)`` and side, px."""
        h, w = frame.shape[:2]
        size = self._side(frame, self.window_px if side is None else side)
        u, v = self._work.to_pixel(pose[:2])
        u0 = int(np.clip(round(u - (size - 1) / 2), 0, w - size))
        v0 = int(np.clip(round(v - (size - 1) / 2), 0, h - size))
        return u0, v0, size

    def _near_edge(self, frame: U8, result: TrackResult, window: tuple[int, int, int]) -> bool:
        """Whether a keypoint of ``result``, tracked in ``window`` (:meth:`_window`), lies
        within :data:`EDGE_PX` of one of the window's edges that is not the frame's."""
        h, w = frame.shape[:2]
        u0, v0, size = window
        u, v = result.keypoints[:, 0], result.keypoints[:, 1]
        m = EDGE_PX
        return bool(
            (u0 > 0 and (u < u0 + m).any())
            or (u0 + size < w and (u > u0 + size - 1 - m).any())
            or (v0 > 0 and (v < v0 + m).any())
            or (v0 + size < h and (v > v0 + size - 1 - m).any())
        )

    def _in_window(
        self, frame: U8, pose: FloatArray, searched: bool, side: int | None = None
    ) -> TrackResult:
        return self._tracked_in(frame, self._window(frame, pose, side), searched)

    def _tracked_in(self, frame: U8, window: tuple[int, int, int], searched: bool) -> TrackResult:
        u0, v0, size = window
        crop = frame[v0 : v0 + size, u0 : u0 + size]
        return self._result(self._heatmaps(crop), np.array([u0, v0]), searched)

    def _search(self, frame: U8) -> TrackResult:
        h, w = frame.shape[:2]
        ph, pw = -h % self.stride, -w % self.stride
        image = frame
        if ph or pw:
            image = np.asarray(cv2.copyMakeBorder(frame, 0, ph, 0, pw, cv2.BORDER_REPLICATE))
        return self._result(self._heatmaps(image), np.zeros(2), True)

    def _result(
        self, heatmaps: NDArray[np.float32], origin: FloatArray, searched: bool
    ) -> TrackResult:
        length_px = self.robot.length * self._work.scale
        pixels, conf = select_keypoints(peak_candidates(heatmaps), length_px)
        points = np.array(
            [refine_peak(hm, u, v) for hm, (u, v) in zip(heatmaps, pixels, strict=True)]
        )
        points += origin
        c = float(conf.min())
        pose = None
        if c >= self.min_confidence:
            fit = pose_from_keypoints(self._work.to_world(points), self.robot.length, conf)
            if abs(fit.span / self.robot.length - 1) <= 0.25:
                pose = fit.pose
        return TrackResult(pose, c, points, searched)
