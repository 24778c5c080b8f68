"""Camera, renderer, keypoint geometry, UNet decoding, shipped weights, and the tracker."""

from __future__ import annotations

import copy
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal
from scipy.optimize import least_squares

from magrun.angles import wrap_angle
from magrun.loop import run_trial
from magrun.rigs.sim import SimRig
from magrun.robot import RobotParams, load_robot, load_robots
from magrun.scene import Walls, s_trajectory
from magrun.tracking.camera import Camera, CameraConfig
from magrun.tracking.dataset import (
    CROP,
    crop_sample,
    load_annotations,
    real_samples,
    synthetic_sample,
)
from magrun.tracking.export import fuse_batch_norm, model_net, torch_net
from magrun.tracking.fluoroscopy import FluoroscopyMimic
from magrun.tracking.heatmaps import (
    HEATMAP_SIGMA,
    gaussian_heatmaps,
    peak_candidates,
    refine_peak,
)
from magrun.tracking.inference import graph_net, to_array
from magrun.tracking.keypoints import axial_offsets, fiducials, pose_from_keypoints
from magrun.tracking.render import PINK, YELLOW, Renderer, _Canvas
from magrun.tracking.tracker import Tracker, default_weights_path, select_keypoints
from magrun.tracking.train import TrainConfig, make_batch, train
from magrun.tracking.unet import KeypointUNet, load_weights, save_weights, to_input
from magrun.tracking.weights import read_weights

CLEAN = CameraConfig(blur_px=0.0, noise=0.0, lighting=0.0)


@pytest.fixture(scope="module")
def robots() -> dict[str, RobotParams]:
    return load_robots()


@pytest.fixture(scope="module")
def shipped() -> KeypointUNet:
    model, _ = load_weights(default_weights_path())
    return model


# -- camera -------------------------------------------------------------------------------------


@given(
    x=st.floats(-0.06, 0.06),
    y=st.floats(-0.06, 0.06),
    u0=st.integers(0, 160),
    v0=st.integers(0, 160),
)
def test_camera_round_trip_and_crops_agree(x: float, y: float, u0: int, v0: int) -> None:
    cam = Camera()
    uv = cam.to_pixel([x, y])
    assert_allclose(cam.to_world(uv), [x, y], atol=1e-15)
    crop = cam.crop((u0, v0), (CROP, CROP))
    # a world point lands in the crop at its frame pixel minus the crop's origin
    assert_allclose(crop.to_pixel([x, y]), uv - [u0, v0], atol=1e-9)


def test_camera_orientation_x_right_y_up() -> None:
    cam = Camera()
    u0, v0 = cam.to_pixel([0.0, 0.0])
    u1, v1 = cam.to_pixel([0.001, 0.002])
    assert (u0, v0) == (127.5, 127.5)
    assert u1 - u0 == pytest.approx(2.5)
    assert v1 - v0 == pytest.approx(-5.0)


# -- keypoint geometry --------------------------------------------------------------------------


@given(
    x=st.floats(-0.05, 0.05),
    y=st.floats(-0.05, 0.05),
    th=st.floats(-math.pi, math.pi),
    length=st.floats(0.002, 0.03),
)
def test_pose_from_keypoints_is_exact_on_exact_points(
    x: float, y: float, th: float, length: float
) -> None:
    fit = pose_from_keypoints(fiducials([x, y, th], length), length)
    assert_allclose(fit.pose[:2], [x, y], atol=1e-15)
    assert abs(wrap_angle(fit.pose[2] - th)) < 1e-12
    assert fit.residual < 1e-15
    assert fit.span == pytest.approx(length, rel=1e-12)


@settings(max_examples=30)
@given(seed=st.integers(0, 2**31))
def test_pose_from_keypoints_is_the_weighted_least_squares_pose(seed: int) -> None:
    """Noisy, weighted points: the closed form equals a numerical least-squares fit."""
    rng = np.random.default_rng(seed)
    length = 0.016
    pose = np.array([*rng.uniform(-0.04, 0.04, 2), rng.uniform(-math.pi, math.pi)])
    pts = fiducials(pose, length) + rng.normal(0, 3e-4, (3, 2))
    w = rng.uniform(0.2, 1.0, 3)
    s = axial_offsets(length)

    def residuals(q: np.ndarray) -> np.ndarray:
        u = np.array([math.cos(q[2]), math.sin(q[2])])
        return (np.sqrt(w)[:, None] * (q[:2] + s[:, None] * u - pts)).ravel()

    ref = least_squares(residuals, pose, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    got = pose_from_keypoints(pts, length, w).pose
    assert_allclose(got[:2], ref[:2], atol=1e-10)
    assert abs(wrap_angle(got[2] - ref[2])) < 1e-8


def test_pose_from_keypoints_drops_zero_weights_and_rejects_degenerate_input() -> None:
    pose = np.array([0.01, 0.02, -2.0])
    pts = fiducials(pose, 0.01)
    pts_bad_centre = pts.copy()
    pts_bad_centre[1] += 0.003
    fit = pose_from_keypoints(pts_bad_centre, 0.01, [1.0, 0.0, 1.0])
    assert_allclose(fit.pose, pose, atol=1e-12)
    with pytest.raises(ValueError, match="two points"):
        pose_from_keypoints(pts, 0.01, [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="axis"):
        pose_from_keypoints(np.zeros((3, 2)), 0.01)
    with pytest.raises(ValueError, match="shape"):
        pose_from_keypoints(np.zeros((2, 2)), 0.01)


# -- renderer -----------------------------------------------------------------------------------


def _colour_centroid(image: np.ndarray, colour: tuple[float, float, float]) -> np.ndarray:
    """Centroid (u, v) of the pixels weighted by how close they are to ``colour``."""
    img = image.astype(np.float64) / 255
    d = np.linalg.norm(img - np.asarray(colour), axis=2)
    w = np.clip(1 - d / 0.25, 0, None)
    vv, uu = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    return np.array([np.sum(w * uu), np.sum(w * vv)]) / np.sum(w)


@settings(max_examples=25)
@given(seed=st.integers(0, 2**31))
def test_shapes_are_drawn_by_their_area_coverage(seed: int) -> None:
    """A pixel gets the fraction of it the shape covers.

    Total area within 0.1 px times the perimeter (the outline placed to 0.1 px), centroid
    within 0.1 px of the exact (shoelace / stadium) values; a half-pixel convention slip, or
    OpenCV's ½ px dilation left in, fails both.
    """
    rng = np.random.default_rng(seed)
    c = rng.uniform(20, 44, 2)
    # a jittered square inscribed in a circle (convex, no slivers)
    angles = np.arange(4) * np.pi / 2 + rng.uniform(-0.5, 0.5, 4)
    quad = c + rng.uniform(6, 12) * np.column_stack([np.cos(angles), np.sin(angles)])
    x, y = quad.T
    cross = x * np.roll(y, -1) - np.roll(x, -1) * y
    area = cross.sum() / 2
    centroid = [np.sum((x + np.roll(x, -1)) * cross), np.sum((y + np.roll(y, -1)) * cross)]
    canvas = _Canvas(np.zeros((64, 64, 3), np.float32))
    canvas.polygon(quad, (1.0, 1.0, 1.0), 1.0)
    cover = canvas.image[..., 0].astype(np.float64)
    vv, uu = np.mgrid[0:64, 0:64]
    perimeter = np.hypot(*(np.roll(quad, -1, axis=0) - quad).T).sum()
    assert abs(cover.sum() - abs(area)) < 0.1 * perimeter
    assert_allclose([np.sum(cover * uu), np.sum(cover * vv)] / cover.sum(),
                    np.array(centroid) / (6 * area), atol=0.1)  # fmt: skip

    half = np.array([5.3, 2.1])
    a, b, r = c - half, c + half, rng.uniform(1.5, 4.0)
    canvas = _Canvas(np.zeros((64, 64, 3), np.float32))
    canvas.capsule(a, b, r, (1.0, 1.0, 1.0), 1.0)
    cover = canvas.image[..., 0].astype(np.float64)
    length = np.hypot(*(b - a))
    assert abs(cover.sum() - (np.pi * r**2 + 2 * r * length)) < 0.1 * (2 * np.pi * r + 2 * length)
    assert_allclose([np.sum(cover * uu), np.sum(cover * vv)] / cover.sum(), c, atol=0.1)


def test_shapes_rasterised_together_are_each_rasterised_as_alone() -> None:
    """The renderer works out the outlines of a frame's shapes (every pose of a motion-blurred
    exposure) in one pass; each comes out to the last bit as it does alone: the same pixels,
    the same fixed-point outline. Random quadrilaterals and stadiums, some cut by the canvas's
    sides and some outside it."""
    from magrun.tracking.render import _stadium

    rng = np.random.default_rng(5)
    canvas = _Canvas(np.zeros((40, 50, 3), np.float32), origin=(7, 3))
    outlines = []
    for _ in range(60):
        c = rng.uniform(-10, 70, 2)
        angles = np.arange(4) * np.pi / 2 + rng.uniform(-0.5, 0.5, 4)
        outlines.append(c + rng.uniform(1, 12) * np.column_stack([np.cos(angles), np.sin(angles)]))
        outlines.append(_stadium(c, c + rng.uniform(-9, 9, 2), rng.uniform(0.5, 5)))
    together = canvas.rasterise(outlines)
    assert sum(r is None for r in together) > 5  # some miss the canvas
    assert sum(r is not None for r in together) > 60
    for outline, raster in zip(outlines, together, strict=True):
        (alone,) = canvas.rasterise([outline])
        if alone is None:
            assert raster is None
        else:
            assert raster is not None
            assert raster[0] == alone[0]
            assert np.array_equal(raster[1], alone[1])


@pytest.mark.parametrize("name", ["magnet", "drug_delivery"])
def test_a_blurred_frames_poses_are_shaped_together_as_each_alone(robots, name: str) -> None:
    """The renderer works out the robot's shapes at every pose of a motion-blurred exposure
    at once; each pose's outlines come out to the last bit as that pose's alone, and the
    capsule's stadiums as :func:`_stadium` draws one (the walls' own). 1 to 6 poses, 200
    exposures, both appearances."""
    from magrun.tracking.render import _stadium, _stadiums, robot_shapes, robot_shapes_at

    robot, cam = robots[name], Camera()
    rng = np.random.default_rng(8)
    for _ in range(200):
        k = int(rng.integers(1, 7))
        poses = np.column_stack([rng.uniform(-0.04, 0.04, (k, 2)), rng.uniform(-9, 9, k)])
        for pose, together in zip(poses, robot_shapes_at(cam, poses, robot), strict=True):
            alone = robot_shapes(cam, pose, robot)
            assert [s[1:] for s in together] == [s[1:] for s in alone]
            for (a, _, _), (b, _, _) in zip(together, alone, strict=True):
                assert a.shape == b.shape
                assert np.array_equal(a, b)
        a, b = rng.uniform(0, 60, (k, 2)), rng.uniform(0, 60, (k, 2))
        r = float(rng.uniform(0.5, 5))
        for i, outline in enumerate(_stadiums(a, b, r)):
            assert np.array_equal(outline, _stadium(a[i], b[i], r))


@pytest.mark.parametrize("theta", [0.0, 0.7, 2.0, -2.6])
def test_rendered_magnet_robot_matches_its_labels(robots, theta: float) -> None:
    """Pink front half around c + L/4·u, yellow rear half around c − L/4·u.

    Checks the renderer's conventions (image y down, heading toward the pink end) against
    the keypoint labels: a sign or axis mistake would be off by ≥ 10 px; 0.3 px allows for
    the colour-distance weighting of mixed edge pixels.
    """
    robot = robots["magnet"]
    cam = Camera(CLEAN)
    pose = np.array([0.0123, -0.0071, theta])
    image = Renderer(cam, robot).render(pose)
    u = np.array([math.cos(theta), math.sin(theta)])
    for colour, sign in ((PINK, 1), (YELLOW, -1)):
        expected = cam.to_pixel(pose[:2] + sign * robot.length / 4 * u)
        assert_allclose(_colour_centroid(image, colour), expected, atol=0.3)


@pytest.mark.parametrize("robot_name", ["magnet", "drug_delivery"])
@pytest.mark.parametrize(
    "pose",
    [[0.0123, -0.0071, 0.4], [0.0495, 0.02, 2.5], [-0.049, -0.0505, -1.2], [0.053, 0.0, 0.0]],
    ids=["inside", "at-the-edge", "corner", "half-out"],
)
def test_renderer_equals_the_whole_frame_camera_model(robot_name: str, pose: list[float]) -> None:
    """The trial renderer (blurred lit background + blurred robot window) equals
    :func:`finish` on the whole scene, within one grey level (float rounding), everywhere,
    including frames where the robot's window is cut by the image border."""
    from magrun.tracking.render import draw_robot, finish

    robot = load_robot(robot_name)
    cam = Camera(CameraConfig(noise=0.0, blur_px=1.1, lighting=0.15))
    r = Renderer(cam, robot, Walls.box(0.045), seed=7)
    scene = r._background.copy()
    draw_robot(scene, cam, pose, robot)
    rng = copy.deepcopy(r.rng)
    expected = finish(scene, cam, r.lighting, r._illumination, rng).astype(int)
    got = r.render(pose).astype(int)
    assert np.abs(got - expected).max() <= 1
    assert np.count_nonzero(got != expected) < 1e-3 * got.size
    drawn = np.count_nonzero(np.any(scene != r._background, axis=-1))
    assert drawn > 20  # the robot is (partly) in view: the check is not vacuous


def test_sensor_noise_is_independent_between_frames() -> None:
    """Noise windows at per-frame offsets into the trial's bank: at each pixel, two frames'
    noise is uncorrelated (|r| < 4/√n for n pixels), and a frame's noise has no spatial
    correlation between neighbours."""
    cfg = replace(CLEAN, noise=0.02)
    r = Renderer(Camera(cfg), load_robot("magnet"), seed=5)
    pose = [1.0, 1.0, 0.0]  # out of view: the frames are flat fluid plus noise
    n1, n2, n3 = (r.render(pose)[..., 1].astype(float).ravel() for _ in range(3))
    bound = 4 / math.sqrt(n1.size)
    for a, b in ((n1, n2), (n2, n3), (n1, n3)):
        assert abs(np.corrcoef(a, b)[0, 1]) < bound
    img = n1.reshape(256, 256)
    assert abs(np.corrcoef(img[:, :-1].ravel(), img[:, 1:].ravel())[0, 1]) < bound


def test_renderer_is_seeded_and_noisy_frames_differ() -> None:
    robot = load_robot("drug_delivery")
    a = Renderer(Camera(), robot, seed=3)
    b = Renderer(Camera(), robot, seed=3)
    pose = [0.0, 0.0, 1.0]
    f1, f2 = a.render(pose), a.render(pose)
    assert np.array_equal(f1, b.render(pose))
    assert not np.array_equal(f1, f2)  # fresh sensor noise per frame
    assert f1.dtype == np.uint8
    assert f1.shape == (256, 256, 3)


def test_sensor_noise_has_the_configured_spread_in_every_channel() -> None:
    """Two frames of the same scene differ by noise of std √2·σ per channel (σ = 0.02 of 255)."""
    cfg = replace(CLEAN, noise=0.02)
    r = Renderer(Camera(cfg), load_robot("magnet"), seed=4)
    pose = [0.04, 0.04, 0.0]  # a corner: mostly flat background
    d = r.render(pose).astype(float) - r.render(pose).astype(float)
    std = d.reshape(-1, 3).std(axis=0) / 255
    assert_allclose(std, math.sqrt(2) * 0.02, rtol=0.05)  # uint8 rounding adds ~1 %
    assert_allclose(d.reshape(-1, 3).mean(axis=0) / 255, 0.0, atol=1e-3)


def test_robot_out_of_view_renders_an_empty_frame(robots) -> None:
    cam = Camera(CLEAN)
    empty = Renderer(cam, robots["magnet"]).render([1.0, 1.0, 0.0])
    assert np.ptp(empty.reshape(-1, 3), axis=0).max() == 0


# -- UNet pieces --------------------------------------------------------------------------------


@given(u=st.floats(3.0, 60.0), v=st.floats(3.0, 60.0))
def test_peaks_are_found_and_refined_to_subpixel(u: float, v: float) -> None:
    """One peak per map; the log-parabola fit is exact for a sampled Gaussian (1e-4 px with
    float32 maps); the height is the Gaussian at the peak pixel."""
    points = np.array([[u, v], [v, u], [30.2, 10.7]])
    maps = gaussian_heatmaps(points, (64, 64))
    for hm, (pixels, heights), p in zip(maps, peak_candidates(maps), points, strict=True):
        assert len(heights) == 1
        assert_allclose(refine_peak(hm, *pixels[0]), p, atol=1e-4)
        expected = np.exp(-np.sum((pixels[0] - p) ** 2) / (2 * HEATMAP_SIGMA**2))
        assert heights[0] == pytest.approx(expected, abs=1e-4)


def test_consistent_keypoints_beat_stronger_inconsistent_peaks() -> None:
    """The failure the small UNet shows: the tail map peaks higher at the centre than at the
    tail. Peak candidates plus the geometric selection still pick the true tail."""
    tail, centre, head = np.array([[20.0, 30.0], [40.0, 30.0], [60.0, 30.0]])
    maps = np.stack([
        0.8 * gaussian_heatmaps(tail[None], (64, 80))[0]
        + 0.95 * gaussian_heatmaps(centre[None], (64, 80))[0],
        0.8 * gaussian_heatmaps(centre[None], (64, 80))[0]
        + 0.6 * gaussian_heatmaps(tail[None], (64, 80))[0],
        0.9 * gaussian_heatmaps(head[None], (64, 80))[0],
    ])  # fmt: skip
    candidates = peak_candidates(maps)
    assert_allclose(candidates[0][0][0], centre)  # the tail map's highest peak alone is wrong
    assert [len(h) for _, h in candidates] == [2, 2, 1]
    pixels, heights = select_keypoints(candidates, length_px=40.0)
    assert_allclose(pixels, [tail, centre, head])
    assert_allclose(heights, [0.8, 0.8, 0.9], atol=1e-3)


def test_heatmaps_of_missing_points_are_zero() -> None:
    hm = gaussian_heatmaps(np.full((3, 2), np.nan), (8, 8))
    assert hm.shape == (3, 8, 8)
    assert not hm.any()


def test_batch_norm_fusion_preserves_the_output(shipped: KeypointUNet) -> None:
    x = to_input(np.random.default_rng(0).integers(0, 256, (2, 96, 96, 3), dtype=np.uint8))
    with torch.inference_mode():
        assert_allclose(fuse_batch_norm(shipped)(x).numpy(), shipped(x).numpy(), atol=1e-4)


@pytest.mark.parametrize("side", [(64, 64), (96, 128), (256, 256)])
def test_the_shipped_onnx_graph_computes_the_torch_heatmaps(shipped: KeypointUNet, side) -> None:
    """The graph shipped beside the weights (what tracking runs) at any input size (the
    window, a search) and batch: torch's maps to 1e-4 absolute (peaks are ~1)."""
    images = np.random.default_rng(1).integers(0, 256, (2, *side, 3), dtype=np.uint8)
    x = to_array(images)
    assert_allclose(x, to_input(images).numpy())
    ref = torch_net(fuse_batch_norm(shipped))(x)
    assert ref.shape == (2, 3, *side)
    net = graph_net(read_weights(default_weights_path()))
    assert (net.backend, net.stride) == ("onnx", shipped.stride)
    assert_allclose(net.run(x), ref, atol=1e-4)
    with pytest.raises(ValueError, match="unknown backend"):
        model_net(shipped, "tensorflow")  # type: ignore[arg-type]


def test_tracker_backends_agree_on_rendered_frames(shipped, robots) -> None:
    """Same keypoints (1e-3 px) and poses from ONNX Runtime and torch, search and window."""
    robot, cam = robots["magnet"], Camera()
    trackers = [Tracker(shipped, cam, robot, backend=b) for b in ("onnx", "torch")]
    for seed, pose in enumerate([[0.01, -0.02, 0.4], [-0.03, 0.025, -2.5]]):
        frame = Renderer(cam, robot, Walls.box(0.05), seed=seed).render(pose)
        for prior in (None, np.array(pose)):
            a, b = (t.track(frame, prior) for t in trackers)
            assert a.searched == b.searched
            assert_allclose(a.keypoints, b.keypoints, atol=1e-3)
            assert a.pose is not None
            assert b.pose is not None
            assert_allclose(a.pose, b.pose, atol=1e-6)


def test_weights_round_trip(tmp_path) -> None:
    torch.manual_seed(0)
    model = KeypointUNet((4, 8)).eval()
    path = tmp_path / "w.npz"
    save_weights(model, path, {"note": "test"})
    loaded, meta = load_weights(path)
    x = torch.randn(1, 3, 16, 16)
    with torch.inference_mode():
        assert torch.equal(model(x), loaded(x))
    assert meta["note"] == "test"
    assert meta["widths"] == [4, 8]


def test_training_reduces_the_loss(robots) -> None:
    """A few steps from random weights lower the heat-map loss on a fixed batch."""
    robots_list = list(robots.values())
    rng = np.random.default_rng(1)
    x, y = make_batch([synthetic_sample(rng, robots_list) for _ in range(8)])
    torch.manual_seed(0)
    model = KeypointUNet((4, 8, 16, 32))

    def loss(m: KeypointUNet) -> float:
        m.eval()
        with torch.inference_mode():
            return float(torch.mean((1 + 10 * y) * (m(x) - y) ** 2))

    before = loss(model)
    cfg = TrainConfig(steps=15, batch=8, lr=1e-2, widths=(4, 8, 16, 32))
    after = loss(train(robots_list, cfg, model=model))
    assert after < 0.7 * before


# -- shipped weights and the tracker ------------------------------------------------------------


@pytest.mark.parametrize("name", ["magnet", "drug_delivery"])
def test_shipped_weights_track_a_rendered_frame(shipped, robots, name: str) -> None:
    """Both robots, with and without a previous pose: within 0.3 mm and 2°."""
    robot = robots[name]
    cam = Camera()
    tracker = Tracker(shipped, cam, robot)
    for seed, pose in enumerate([[0.012, -0.02, 0.4], [-0.03, 0.025, -2.5], [0.0, 0.0, 3.0]]):
        frame = Renderer(cam, robot, Walls.box(0.05), seed=seed).render(pose)
        for prior in (None, np.array(pose) + np.array([0.001, -0.001, 0.0])):
            tracker.reset()
            result = tracker.track(frame, prior)
            assert result.pose is not None
            assert result.searched == (prior is None)
            assert np.hypot(*(result.pose[:2] - pose[:2])) < 0.3e-3
            assert abs(wrap_angle(result.pose[2] - pose[2])) < math.radians(2)
            assert result.confidence > 0.5


def _counting(tracker: Tracker) -> list[int]:
    """The input sides the tracker's network runs on from now, in order."""
    sides: list[int] = []
    net = tracker._net

    def run(x: np.ndarray) -> np.ndarray:
        sides.append(x.shape[-1])
        return net(x)

    tracker._net = run
    return sides


@pytest.mark.parametrize(
    ("moved_mm", "sides"),
    [
        (1.0, [64]),  # in the window at the previous pose
        (12.0, [64, 128, 64]),  # beyond it, in the wider window, refined in a window
        (40.0, [64, 128, 256, 64]),  # beyond both: the whole frame
    ],
)
def test_a_robot_that_left_the_window_is_found_in_the_wider_one_first(
    robots, moved_mm: float, sides: list[int]
) -> None:
    """The magnet robot (64 px window, 128 px wider window, 256 px frame) moved ``moved_mm``
    from the previous pose: found within 0.3 mm and 2° after running the network on the
    sides given, so the whole frame is searched only where the wider window misses too."""
    robot = robots["magnet"]
    tracker = Tracker.default(Camera(), robot)
    assert (tracker.window_px, tracker.search_px) == (64, 128)
    pose = np.array([0.02, -0.015, 0.7])
    frame = Renderer(Camera(), robot, Walls.box(0.05), seed=3).render(pose)
    prior = pose + np.array([-moved_mm * 1e-3, 0.0, 0.3])
    ran = _counting(tracker)
    result = tracker.track(frame, prior)
    assert ran == sides
    assert result.searched == (moved_mm > 5)
    assert result.pose is not None
    assert np.hypot(*(result.pose[:2] - pose[:2])) < 0.3e-3
    assert abs(wrap_angle(result.pose[2] - pose[2])) < math.radians(2)


def test_a_robot_at_the_windows_edge_is_tracked_again_centred(robots) -> None:
    """Priors 3-12 mm from the robot (the motion between two 3 Hz frames): where the window
    at the prior holds only part of the robot, the tracker tracks it again in a window
    centred on what it found. Every pose within 0.15 mm (a partial robot's was up to
    0.95 mm off); priors within 1 mm (a 25 Hz camera) never need the second window."""
    robot = robots["magnet"]
    cam = Camera()
    tracker = Tracker.default(cam, robot)
    ran = _counting(tracker)
    rng = np.random.default_rng(5)
    reach = 0.05 - robot.length / 2 - 1e-3
    again = 0
    for k in range(60):
        pose = np.array([*rng.uniform(-reach, reach, 2), rng.uniform(-np.pi, np.pi)])
        frame = Renderer(cam, robot, Walls.box(0.05), seed=k).render(pose)
        near = k % 3 == 0
        moved = rng.uniform(0, 1e-3) if near else rng.uniform(3e-3, 12e-3)
        angle = rng.uniform(0, 2 * np.pi)
        prior = pose + np.array([moved * np.cos(angle), moved * np.sin(angle), 0.0])
        ran.clear()
        result = tracker.track(frame, prior)
        assert result.pose is not None
        assert np.hypot(*(result.pose[:2] - pose[:2])) < 0.15e-3, (k, moved)
        if near:
            assert ran == [64], k
        again += ran == [64, 64]
    assert again >= 5  # the case arose


def test_warm_up_runs_each_input_size_once_and_remembers_nothing(robots) -> None:
    """The window, the wider window and the whole frame, once each; no pose kept. A wider
    window as large as the frame is the frame (not run twice); bad sides are refused."""
    robot = robots["magnet"]
    tracker = Tracker.default(Camera(), robot)
    ran = _counting(tracker)
    tracker.warm_up()
    assert ran == [64, 128, 256]
    assert tracker.last_pose is None
    whole = Tracker.default(Camera(), robot)
    whole.search_px = 256
    ran = _counting(whole)
    whole.warm_up()
    assert ran == [64, 256]
    net = read_weights(default_weights_path())
    for side in (100, 32):
        with pytest.raises(ValueError, match="search_px"):
            Tracker(graph_net(net), Camera(), robot, search_px=side)


def test_a_process_loads_and_warms_a_weights_file_once_while_it_stays_the_same(
    robots, tmp_path
) -> None:
    """Trial after trial in one process: the second tracker shares the first one's network
    (the same run function) and skips the warm-up its sizes already had, keeps its own
    state, and tracks a frame exactly as a network loaded afresh does. A rewritten weights
    file is read again (its modification time), and a damaged one is refused, never served
    from memory."""
    import os
    import shutil

    robot = robots["magnet"]
    shipped = default_weights_path()
    path = tmp_path / "unet.npz"
    shutil.copy(shipped, path)
    shutil.copy(shipped.with_suffix(".onnx"), path.with_suffix(".onnx"))
    first = Tracker.default(Camera(), robot, weights=path)
    first.warm_up()
    first.last_pose = np.array([0.001, 0.0, 0.0])
    second = Tracker.default(Camera(), robot, weights=path)
    assert second._net is first._net
    assert second.last_pose is None
    ran: list[str] = []
    second._in_window = lambda *args, **kwargs: ran.append("window")
    second._search = lambda *args, **kwargs: ran.append("frame")
    second.warm_up()
    assert ran == []  # the shared network's sizes were warmed: nothing runs
    del second._in_window, second._search
    frame = Renderer(Camera(), robot, Walls.box(0.05), seed=2).render([0.004, -0.006, 0.7])
    fresh = Tracker(graph_net(read_weights(path)), Camera(), robot)
    a, b = second.track(frame), fresh.track(frame)
    assert a.pose is not None
    assert_array_equal(a.pose, b.pose)
    assert_array_equal(a.keypoints, b.keypoints)

    stat = path.stat()
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))  # rewritten, same bytes
    third = Tracker.default(Camera(), robot, weights=path)
    assert third._net is not first._net
    ran = _counting(third)
    third.warm_up()
    assert ran == [64, 128, 256]  # a new network: warmed again
    path.write_bytes(b"not weights")
    with pytest.raises(ValueError, match="not a readable weights file"):
        Tracker.default(Camera(), robot, weights=path)


def test_frames_at_another_scale_are_tracked(shipped, robots) -> None:
    """A 4.1 px/mm, 400 × 330 px camera (a lab's): resized to the model's scale internally,
    pose within 0.3 mm and 2°, keypoints reported in the frame's own pixels (within 1 px)."""
    robot = robots["magnet"]
    cam = Camera(replace(CameraConfig(), width_px=400, height_px=330, px_per_mm=4.1))
    pose = np.array([0.008, -0.011, 2.2])
    frame = Renderer(cam, robot, seed=4).render(pose)
    result = Tracker(shipped, cam, robot).track(frame)
    assert result.pose is not None
    assert np.hypot(*(result.pose[:2] - pose[:2])) < 0.3e-3
    assert abs(wrap_angle(result.pose[2] - pose[2])) < math.radians(2)
    assert_allclose(result.keypoints, cam.to_pixel(fiducials(pose, robot.length)), atol=1.0)


def test_tracker_reports_no_pose_on_an_empty_frame(shipped, robots) -> None:
    cam = Camera()
    frame = Renderer(cam, robots["magnet"], Walls.box(0.05)).render([1.0, 1.0, 0.0])
    tracker = Tracker(shipped, cam, robots["magnet"])
    result = tracker.track(frame)
    assert result.pose is None
    assert result.confidence < tracker.min_confidence
    assert tracker.last_pose is None
    with pytest.raises(ValueError, match="frame is"):
        tracker.track(frame[:100])


def test_closed_loop_with_camera_tracking_and_fluoroscopy(shipped, magnet_robot) -> None:
    """Rendered frames → UNet → 7.5 Hz mimic → controller: tracked ≈ actual, 7.5 Hz delivered."""
    from magrun.control.methods import make_controller

    rig = SimRig.default(seed=2, camera=CameraConfig())
    assert rig.camera is not None
    tracker = Tracker(shipped, rig.camera, magnet_robot)
    mimic = FluoroscopyMimic(7.5, 0.0, seed=0)
    log = run_trial(
        make_controller("baseline2"), rig, s_trajectory(), mimic, duration=2.0, tracker=tracker
    )
    err = np.hypot(*(log.tracked[:, :2] - log.actual[:, :2]).T)
    assert np.all(np.isfinite(err))
    assert err.max() < 0.3e-3
    delivered = np.isfinite(log.measured[:, 0])
    assert delivered.sum() == 16  # t = 0 … 2 s at 7.5 Hz: due at k/7.5 for k = 0 … 15
    assert_allclose(log.measured[delivered], log.tracked[delivered])


def test_camera_takes_only_the_frames_the_fluoroscope_takes(shipped, magnet_robot) -> None:
    """With ``frame_due``, the rig renders and the tracker tracks exactly the delivered ticks;
    the others have no frame, no tracked pose and no measurement."""
    from magrun.control.methods import make_controller

    rig = SimRig.default(seed=2, camera=CameraConfig())
    assert rig.camera is not None
    tracker = Tracker(shipped, rig.camera, magnet_robot)
    mimic = FluoroscopyMimic(7.5, 0.0, seed=0)
    frames: list[bool] = []
    log = run_trial(
        make_controller("baseline2"), rig, s_trajectory(), mimic, duration=2.0, tracker=tracker,
        frame_due=mimic.due, on_tick=lambda tick: frames.append(tick.frame is not None),
    )  # fmt: skip
    delivered = np.isfinite(log.measured[:, 0])
    assert delivered.sum() == 16  # as every-tick tracking: due at k/7.5 s for k = 0 … 15
    assert_array_equal(frames, delivered)
    assert_array_equal(np.isfinite(log.tracked[:, 0]), delivered)
    assert_allclose(log.measured[delivered], log.tracked[delivered])
    err = np.hypot(*(log.tracked[delivered, :2] - log.actual[delivered, :2]).T)
    assert err.max() < 0.3e-3


def test_tracker_without_frames_is_an_error(shipped, magnet_robot) -> None:
    from magrun.control.methods import make_controller

    tracker = Tracker(shipped, Camera(), magnet_robot)
    with pytest.raises(ValueError, match="camera"):
        run_trial(make_controller("baseline2"), SimRig.default(), s_trajectory(), duration=0.1,
                  tracker=tracker)  # fmt: skip


# -- real images --------------------------------------------------------------------------------


def _write_annotations(path, rows) -> None:
    lines = ["image,tail_u,tail_v,centre_u,centre_v,head_u,head_v,comment"]
    lines += [",".join(str(v) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")


def test_real_frames_from_a_folder_are_rescaled_with_their_labels(tmp_path, robots) -> None:
    """A frame at 5 px/mm, annotated, loads at 2.5 px/mm with labels on the same features."""
    robot = robots["magnet"]
    big = Camera(replace(CLEAN, width_px=400, height_px=300, px_per_mm=5.0))
    pose = [0.004, -0.003, 0.9]
    rgb = Renderer(big, robot).render(pose)
    cv2.imwrite(str(tmp_path / "f0.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    pts = big.to_pixel(fiducials(pose, robot.length))
    _write_annotations(tmp_path / "labels.csv", [["f0.png", *pts.ravel(), "ok"]])
    [(image, labels)] = real_samples(tmp_path, tmp_path / "labels.csv", 5.0, 2.5)
    assert image.shape == (150, 200, 3)
    small = Camera(replace(CLEAN, width_px=200, height_px=150, px_per_mm=2.5))
    assert_allclose(labels, small.to_pixel(fiducials(pose, robot.length)), atol=1e-9)
    crop = crop_sample(np.random.default_rng(0), image, labels, CROP, 10.0)
    assert crop.image.shape == (CROP, CROP, 3)
    # the crop's labels point at the same pixels as the frame's
    shift = np.round(labels[0] - crop.keypoints[0])
    assert_allclose(crop.keypoints + shift, labels)


def test_real_frames_from_a_video(tmp_path, robots) -> None:
    cam = Camera(CLEAN)
    renderer = Renderer(cam, robots["magnet"])
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (256, 256))
    assert writer.isOpened()
    for k in range(3):
        writer.write(cv2.cvtColor(renderer.render([0.01 * k, 0.0, 0.0]), cv2.COLOR_RGB2BGR))
    writer.release()
    _write_annotations(tmp_path / "l.csv", [[2, 1, 2, 3, 4, 5, 6, ""]])
    [(image, labels)] = real_samples(path, tmp_path / "l.csv", 2.5, 2.5)
    assert image.shape == (256, 256, 3)
    assert_allclose(labels, [[1, 2], [3, 4], [5, 6]])
    # it is frame 2: the pink half sits at x = 20 mm + L/4 (1 px allows for MJPG)
    expected = cam.to_pixel([0.02 + robots["magnet"].length / 4, 0.0])
    assert_allclose(_colour_centroid(image, PINK), expected, atol=1.0)


def test_bad_annotations_name_file_line_and_column(tmp_path) -> None:
    p = tmp_path / "bad.csv"
    _write_annotations(p, [["a.png", 1, 2, 3, 4, 5, 6, ""], ["b.png", 1, "x", 3, 4, 5, 6, ""]])
    with pytest.raises(ValueError, match=r"bad\.csv:3: column 'tail_v'"):
        load_annotations(p)
    p.write_text("image,tail_u\n")
    with pytest.raises(ValueError, match=r"bad\.csv:1: missing column"):
        load_annotations(p)


@pytest.mark.parametrize(("robot", "window"), [("magnet", 64), ("drug_delivery", 48)])
def test_default_window_is_the_robot_plus_margins(robot: str, window: int) -> None:
    """Length at 2.5 px/mm plus 12 px each side, up to the stride: 40 + 24 → 64, 18.5 + 24 → 48."""
    tracker = Tracker.default(Camera(), load_robot(robot))
    assert tracker.window_px == window
    assert tracker.window_px % tracker.stride == 0
