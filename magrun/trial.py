"""The one assembly of a trial, shared by every entry point (``magrun run``, ``magrun track``,
the benchmarks): one condition always gets one rig, one controller tuning, one feedback.

    >>> from magrun.protocol import load_protocol
    >>> from magrun.trial import assemble
    >>> trial = load_protocol("protocols/rate.yaml").expand(quick=True)[0]
    >>> log = assemble(trial).run()                                  # doctest: +SKIP

:func:`assemble` builds, from a :class:`~magrun.protocol.Trial` alone, everything the loop
(:func:`magrun.loop.run_trial`) needs: the scene (reference path, walls, boundaries), the
robot (loaded once), the controller with its estimator and free space, the rig (seeded
simulator, or the hardware rig connected), the camera tracker, the fluoroscopy mimic (seeded)
and the safety layer. What happens around a trial (executors, recording, the manifest) is
the runner's (:mod:`magrun.runner`).

:func:`control_config` turns a protocol's ``controller`` section, the robot and the trial's
condition into the methods' :class:`~magrun.control.methods.ControlConfig`: the control
period, the horizons and the Kalman filter's noise (the measurement noise follows the
condition's ``noise_sigma_mm`` unless the protocol fixes it; the process noise is the robot's
measured prediction error where the protocol says ``robot``).

:func:`single_trial` makes a trial of an in-memory protocol with a chosen seed: how
``magrun track`` and the benchmarks run a condition through this same assembly.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Any, Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from magrun.calibration import gains_in_order, load_coil_gains
from magrun.control import NMPC_METHODS
from magrun.control.base import Controller
from magrun.control.estimation import KalmanConfig, steady_position_sigma
from magrun.control.methods import ControlConfig, make_controller
from magrun.control.nmpc import NMPCConfig
from magrun.control.two_layer import LinearMPCConfig
from magrun.field.coils import CoilFileError, CoilSystem
from magrun.field.model import PlanarFieldModel
from magrun.field.system import System, load_system
from magrun.freespace import FreeSpace
from magrun.health import CONTACT
from magrun.loop import PoseTracker, TrialLog, run_trial
from magrun.protocol import (
    Conditions,
    ControllerSettings,
    Protocol,
    SimulationSettings,
    Trial,
    condition_slug,
)
from magrun.records import Tick
from magrun.rigs.base import Rig
from magrun.rigs.factory import HardwareRigConfig, HardwareSpec, SimRigConfig, make_rig
from magrun.robot import RobotParams, load_robot
from magrun.safety import SafetyConfig, SafetyLayer
from magrun.scene import Trajectory, Walls
from magrun.tracking.fluoroscopy import FluoroscopyMimic
from magrun.yamlio import YamlModelError

FloatArray = NDArray[np.float64]


class RunError(RuntimeError):
    """A run that cannot start (bad output folder, unavailable rig); nothing was written."""


@contextmanager
def trial_threads(n: int) -> Iterator[None]:
    """``n`` threads per trial for the libraries that would start their own: the tracker's
    network (ONNX Runtime, and torch where a caller has loaded it; results then do not depend
    on the thread count) and the linear algebra (the BLAS that NumPy and SciPy loaded,
    through threadpoolctl). A trial's matrices are small: OpenBLAS's threads then mostly
    spin waiting for work (3.7 s of a 10 s Baseline 3 trial's 9.5 s of CPU, 0.5 s on one
    thread), on the other cores, where a rig's recorder or other work runs. The run's pool
    starts its workers with one thread already (:data:`magrun.runner.THREAD_ENV`); this
    covers the trials run in-process (``--jobs 1``, the hardware rig, Ray's workers).
    Libraries loaded inside are limited by the next call. Tracking needs no torch
    (:mod:`magrun.tracking.inference`); this never imports it."""
    from threadpoolctl import threadpool_limits

    from magrun.tracking.inference import inference_threads

    torch = sys.modules.get("torch")
    before = torch.get_num_threads() if torch is not None else None
    if torch is not None:
        torch.set_num_threads(n)
    try:
        with inference_threads(n), threadpool_limits(limits=n, user_api="blas"):
            yield
    finally:
        if torch is not None and before is not None:
            torch.set_num_threads(before)


# --------------------------------------------------------------------------------------------
# the scene


@dataclass(frozen=True)
class Scene:
    """What a trial runs in: reference path, walls, boundaries (SI)."""

    reference: Trajectory
    walls: Walls | None  # None: the rig's default box
    boundaries: dict[str, Any]
    critical: str | None
    half_width: float  # m, half the side of the square workspace
    channel: FloatArray | None = None  # a phantom's path (m), along which its fluid flows


def build_scene(protocol: Protocol, coils: CoilSystem | None = None) -> Scene:
    """The reference trajectory and walls a protocol describes, in the workspace of ``coils``
    (default: the paper's coil system)."""
    from magrun.phantom import load_phantom
    from magrun.scene import out_and_back, s_trajectory

    phantom = None
    ws = protocol.workspace
    if ws.kind != "open":
        phantom = load_phantom(ws.phantom)
    traj = protocol.trajectory
    if traj.kind == "s_curve":
        reference = s_trajectory(size=traj.size_mm * 1e-3, speed=traj.speed_mm_s * 1e-3)
    else:
        if traj.path == "phantom":
            if phantom is None or phantom.path is None:
                raise ValueError("trajectory.path 'phantom': the phantom file has no path")
            points = phantom.path
        else:
            points = np.asarray(traj.path, dtype=np.float64) * 1e-3
        reference = out_and_back(points, traj.speed_mm_s * 1e-3, traj.hold_s, traj.flip_s)
    half_width = (coils or CoilSystem.load()).workspace_half_width
    if phantom is not None:
        box = Walls.box(half_width)
        return Scene(
            reference, phantom.walls() + box, phantom.boundaries, phantom.critical, half_width,
            phantom.path,
        )  # fmt: skip
    return Scene(reference, None, {}, None, half_width)


_V = TypeVar("_V")


def _kept(cache: dict[tuple[Any, ...], _V], key: tuple[Any, ...], limit: int,
          make: Callable[[], _V]) -> _V:  # fmt: skip
    """``cache[key]``, ``make()`` where it is missing: this process's memo of a costly
    answer, emptied once it holds ``limit``."""
    if key not in cache:
        if len(cache) >= limit:
            cache.clear()
        cache[key] = make()
    return cache[key]


#: free_space_of's spaces by their geometry (a FreeSpace is immutable but for its own
#: caches of the same geometry)
_FREE_SPACES: dict[tuple[Any, ...], FreeSpace] = {}


def free_space_of(scene: Scene, robot: RobotParams) -> FreeSpace:
    """The :class:`~magrun.freespace.FreeSpace` the controller is given: the phantom's outline
    and critical boundary, or the workspace square. Building one tabulates where the body
    fits (a third of a second for the spine), so up to 8 are kept in this process: a
    campaign's trials, and a test session's, share their geometry."""
    boundaries = tuple(
        (name, np.asarray(line, dtype=np.float64).tobytes(), np.shape(line))
        for name, line in scene.boundaries.items()
    )
    key = (boundaries, scene.critical, scene.half_width, robot.length, robot.diameter)

    def build() -> FreeSpace:
        if scene.boundaries:
            return FreeSpace(scene.boundaries, scene.critical, robot.length, robot.diameter)
        return FreeSpace.square(scene.half_width, robot.length, robot.diameter)

    return _kept(_FREE_SPACES, key, 8, build)


# --------------------------------------------------------------------------------------------
# the rig


RigSpec = str | HardwareSpec

NO_DRIVER = "--rig hardware needs --driver URL (e.g. tcp://127.0.0.1:5555)"


def rig_config(
    kind: RigSpec,
    robot: RobotParams,
    walls: Walls | None,
    seed: int,
    camera: bool,
    watchdog_s: float = 0.1,
    system: System | None = None,
    simulation: SimulationSettings | None = None,
    flow_path: FloatArray | None = None,
) -> SimRigConfig | HardwareRigConfig:
    """The rig's configuration (:func:`magrun.rigs.factory.make_rig` makes it): the
    simulated rig (``"sim"``, seeded, with a camera if ``camera``, on ``system``'s coils and
    maps: default the paper's; its plant drawn around ``robot`` as ``simulation`` says,
    default the protocol's defaults; its flow along ``flow_path`` where given) or the
    hardware rig a :class:`HardwareSpec` names."""
    system = system or load_system(None)
    if isinstance(kind, HardwareSpec):
        return HardwareRigConfig(kind, robot, system, watchdog_s)
    if kind == "hardware":
        raise RunError(NO_DRIVER)
    from magrun.rigs.sim import Perturbation

    sim = simulation or SimulationSettings()
    perturbation = Perturbation(
        mass=sim.mass_sigma, drag=sim.drag_sigma, moment=sim.moment_sigma,
        coil_gain=sim.coil_gain_sigma,
    )  # fmt: skip
    return SimRigConfig(
        robot, system, seed, walls=walls, camera=camera, perturbation=perturbation,
        imperfections=sim.imperfections(), plant_seed=sim.plant_seed, flow_path=flow_path,
    )  # fmt: skip


def handshake(spec: HardwareSpec, coils: CoilSystem, watchdog_s: float) -> None:
    """Open the rig's driver, check its channels and announced limits against ``coils``
    (:func:`~magrun.rigs.hardware.agreed_limits`) and close it again: a rig that cannot be
    reached, or that magrun will not drive, is refused (:class:`RunError`) before a run
    folder is made or any current sent."""
    from magrun.rigs.drivers import DriverError, load_driver
    from magrun.rigs.hardware import agreed_limits

    try:
        driver = load_driver(spec.driver, spec.secret)
        driver.open(watchdog_s)
        try:
            agreed_limits(driver, coils)
        finally:
            driver.close()
    except DriverError as exc:
        raise RunError(str(exc)) from exc


# --------------------------------------------------------------------------------------------
# the controller's tuning


def control_config(
    settings: ControllerSettings, robot: RobotParams, condition: Conditions
) -> ControlConfig:
    """The controller tuning for ``robot`` under ``condition`` (its feedback noise)."""
    k = settings.kalman
    if k.measurement_sigma_mm == "condition":
        sigma_mm = max(condition.noise_sigma_mm, k.tracker_sigma_mm)
    else:
        sigma_mm = k.measurement_sigma_mm
    sigma_deg = max(k.measurement_sigma_deg, condition.noise_sigma_deg)
    measured = robot.prediction_sigma  # a protocol checks it exists where it asks for it
    process_m = (
        measured[0] if measured and k.process_sigma_mm == "robot"
        else float(k.process_sigma_mm) * 1e-3
    )  # fmt: skip
    process_rad = (
        measured[1] if measured and k.process_sigma_deg == "robot"
        else math.radians(float(k.process_sigma_deg))
    )  # fmt: skip
    latency = settings.latency
    return ControlConfig(
        dt=1.0 / settings.rate_hz,
        # the declared compute latency, planned across where asked ("measured": unknown)
        latency=latency if settings.plan_across_latency and isinstance(latency, float) else 0.0,
        nmpc=NMPCConfig(
            horizon=settings.horizon,
            field_error=settings.field_error_percent / 100,
            soft_constraints=soft_constraints(settings, held=False),
            field_heading_error=math.radians(settings.field_heading_error_deg),
            corrective_iterations=settings.corrective_iterations,
            corrective_step=settings.corrective_step,
        ),
        linear_mpc=LinearMPCConfig(horizon=settings.horizon),
        kalman=KalmanConfig(
            measurement_position=sigma_mm * 1e-3,
            measurement_angle=math.radians(sigma_deg),
            process_position=process_m,
            process_angle=process_rad,
            heading_bias=math.radians(k.heading_bias_sigma_deg),
            mobility=k.mobility_sigma,
            outlier_gate=k.outlier_gate_sigma,
            linearised=k.linearised,
        ),
    )


# --------------------------------------------------------------------------------------------
# the assembly


@dataclass
class TrialParts:
    """Everything one trial runs with, built by :func:`assemble`; :meth:`run` runs it."""

    trial: Trial
    robot: RobotParams
    scene: Scene
    free_space: FreeSpace
    config: ControlConfig
    controller: Controller
    rig: Rig  # SimRig, or HardwareRig (connected)
    tracker: PoseTracker | None  # the UNet Tracker; None: the rig's own poses, or the exact one
    feedback: FluoroscopyMimic
    safety: SafetyLayer
    simulated: bool
    controller_build_s: float  # wall time of the controller's build (solvers, models)
    planned: Trajectory  # the reference the controller follows (ControllerParts.planned)
    held: Trajectory  # the reference with the headings the coils can hold (ControllerParts.held)

    @property
    def protocol(self) -> Protocol:
        return self.trial.protocol

    @property
    def horizon(self) -> int:
        """Reference poses the planner sees per tick, minus one: the NMPC's horizon."""
        return self.protocol.controller.horizon

    @property
    def duration(self) -> float | None:
        """Seconds, or None: the reference plus 1 s of hold."""
        return self.protocol.trial_duration(self.trial.quick)

    @property
    def frame_ticks(self) -> int:
        """Control ticks per feedback frame."""
        return frame_ticks(self.protocol.controller, self.trial.condition)

    def run(
        self,
        on_tick: Callable[[Tick], None] | None = None,
        progress: Callable[[int, int], None] | None = None,
        stop: Callable[[], bool] | None = None,
    ) -> TrialLog:
        """Run the trial closed loop (:func:`magrun.loop.run_trial`); once per assembly."""
        protocol = self.protocol
        fluoroscopy_frames = protocol.feedback.camera_frames == "fluoroscopy"
        return run_trial(
            self.controller, self.rig, self.scene.reference, planned=self.planned,
            feedback=self.feedback,
            horizon=self.horizon, duration=self.duration, progress=progress,
            tracker=self.tracker, on_tick=on_tick,
            frame_due=self.feedback.due if fluoroscopy_frames else None,
            latency=self.rig.emulated_latency(protocol.controller.latency),
            stop=stop, safety=self.safety,
        )  # fmt: skip


@dataclass
class ControllerParts:
    """A trial's controller and what it is built from (:func:`build_controller`)."""

    scene: Scene
    robot: RobotParams
    config: ControlConfig
    free_space: FreeSpace
    controller: Controller
    build_s: float  # wall time of the controller's build (solvers, models)
    #: the reference the controller follows: :attr:`held`, with a phantom's headings led
    #: (:func:`led_reference`; :attr:`held` itself without a lead)
    planned: Trajectory
    #: the scene's reference with the headings the coils can hold (:func:`planned_reference`;
    #: the scene's own object where they hold its own)
    held: Trajectory


def system_of(protocol: Protocol) -> System:
    """The protocol's coil system (``system``: a folder), or the paper's rig, with its models
    (:func:`magrun.field.system.load_system`); a :class:`RunError` naming the file where the
    folder's description is bad."""
    try:
        return load_system(protocol.system)
    except CoilFileError as exc:
        raise RunError(str(exc)) from exc


def check_system(
    protocol: Protocol,
    feasibility: bool = True,
    tracking: bool = False,
    warn: Callable[[str], None] | None = None,
) -> CoilSystem:
    """What every trial of ``protocol`` is built from, built once and checked, before a run
    folder is made (``magrun run``); a :class:`RunError` names the problem:

    - the system folder's description, maps and fitted models, read as a trial reads them
      (a damaged map, a model fitted to another system);
    - the scene: the robot's body must fit in the workspace (the phantom's outline within
      the coils' square), and the reference trajectory must stay inside both; in a phantom,
      the body on the reference path must clear the critical boundary by more than what
      counts as touching (:data:`magrun.health.CONTACT`; not checked without
      ``feasibility``), and ``warn`` is told where it clears it by less than the NMPC's
      corridor margin (:func:`path_clearance`);
    - with ``feasibility``, the coils' reach: at every pose of the trajectory, currents
      within the limits must give the robot its velocity and turn rate while holding a
      heading (:func:`magrun.field.capability.trajectory_capability`);
    - with ``tracking`` (camera feedback on the simulated rig), that the tracker finds the
      robot in the camera's frames (:func:`check_tracking`)."""
    system = system_of(protocol)
    coils = system.coils
    if coils.folder is not None:
        try:
            system.plant_maps  # noqa: B018 (read and checked here, before a run folder)
            system.models  # noqa: B018
        except ValueError as exc:
            raise RunError(str(exc)) from exc
    try:
        scene = build_scene(protocol, coils)
        robot = protocol.robot_params()
        space = free_space_of(scene, robot)
    except ValueError as exc:
        raise RunError(f"workspace: {exc}") from exc
    poses = scene.reference.poses
    square = np.abs(poses[:, :2]).max(axis=1) > scene.half_width
    outside = square | ~space.inside(poses[:, :2]) if scene.boundaries else square
    if np.any(outside):
        x, y = poses[int(np.argmax(outside)), :2] * 1e3
        where = "the phantom's outline" if scene.boundaries else "the coils' workspace"
        raise RunError(
            f"trajectory: leaves {where} at ({x:.2f}, {y:.2f}) mm (workspace: ±"
            f"{scene.half_width * 1e3:g} mm)"
        )
    clear = path_clearance(scene, space)
    if clear is not None:
        least, t, (x, y) = clear.least, clear.t, clear.position * 1e3
        near = (
            f"overlaps the critical boundary {scene.critical!r} by {-least * 1e3:.2f} mm"
            if least < 0
            else f"comes within {least * 1e3:.2f} mm of the critical boundary {scene.critical!r}"
        )
        where = (
            f"the robot's body on the reference path {near} at ({x:.2f}, {y:.2f}) mm, t = {t:.2f} s"
        )
        if least <= CONTACT and feasibility:
            raise RunError(
                f"trajectory: {where}: every trial would count as touching it (at most "
                f"{CONTACT * 1e3:g} mm); move the path ({_path_source(protocol)}) or pass "
                "--allow-infeasible"
            )
        if least < NMPCConfig.corridor_margin and warn is not None:
            warn(
                f"{where}: less than the {NMPCConfig.corridor_margin * 1e3:g} mm the NMPC's "
                "corridor keeps, so the controller holds the robot off the path there and "
                "trials are likely to touch that boundary"
            )
    if feasibility:
        check_reach(coils, scene.reference, robot)
    if tracking:
        check_tracking(robot)
    return coils


def _path_source(protocol: Protocol) -> str:
    """Where ``protocol``'s reference path is written: its phantom file's ``path`` or its own
    ``trajectory.path``."""
    ws = getattr(protocol.workspace, "phantom", None)
    if getattr(protocol.trajectory, "path", None) == "phantom" and ws is not None:
        return f"'path' in {ws}"
    return "the protocol's 'trajectory.path'"


@dataclass(frozen=True)
class PathClearance:
    """Where the robot's body on a reference path comes closest to the critical boundary."""

    least: float  # m, the body's least clearance (negative: it overlaps the boundary)
    t: float  # s, the reference's time there
    position: FloatArray  # (2,) m, the body's centre there


#: m: how far the body's ends move between two of the poses :func:`path_clearance` checks
PATH_CHECK_SPACING = 10e-6


def path_clearance(scene: Scene, space: FreeSpace) -> PathClearance | None:
    """The least clearance of the body (``space``'s robot) from ``scene``'s critical boundary
    along the reference (its turns in place included); None without a critical boundary.

    The reference is linear between its poses, which may lie far apart (a path of a few
    points of the user's own). The body's clearance changes by at most as much as its ends
    move, so a piece between two poses whose clearances are c₀ and c₁ and along which the
    ends move by τ cannot come closer than (c₀ + c₁ − τ)/2. Pieces that could come closer
    than the least found so far are cut in four and checked again, until their ends move by
    at most :data:`PATH_CHECK_SPACING` (10 µm) along them: the least found is within that of
    the least on the whole path (branch and bound)."""
    if scene.critical is None or scene.critical not in space.boundaries:
        return None
    ref, names = scene.reference, [scene.critical]
    at = space.clearances(ref.poses, names)
    i = int(np.argmin(at))
    best, best_t = float(at[i]), float(ref.t[i])
    d = np.diff(ref.poses, axis=0)
    tau = np.hypot(d[:, 0], d[:, 1]) + (space.half_axis + space.radius) * np.abs(d[:, 2])
    t0, t1, c0, c1 = ref.t[:-1], ref.t[1:], at[:-1], at[1:]
    cuts = np.arange(1, 4) / 4
    while True:
        open_ = ((c0 + c1 - tau) / 2 < best) & (tau > PATH_CHECK_SPACING)
        if not np.any(open_):
            break
        t0, t1, c0, c1, tau = t0[open_], t1[open_], c0[open_], c1[open_], tau[open_] / 4
        inner = t0[:, None] + (t1 - t0)[:, None] * cuts  # (m, 3) times inside each piece
        c = space.clearances(ref.pose(inner.ravel()), names).reshape(inner.shape)
        j = int(np.argmin(c))
        if c.flat[j] < best:
            best, best_t = float(c.flat[j]), float(inner.flat[j])
        times = np.column_stack([t0, inner, t1])  # (m, 5): the four pieces' ends
        ends = np.column_stack([c0, c, c1])
        t0, t1 = times[:, :-1].ravel(), times[:, 1:].ravel()
        c0, c1 = ends[:, :-1].ravel(), ends[:, 1:].ravel()
        tau = np.repeat(tau, 4)
    return PathClearance(best, best_t, ref.pose(best_t)[:2].copy())


#: frames of :func:`check_tracking`'s probe, and the share of them the tracker may lose
TRACKING_PROBE_FRAMES = 40
MAX_TRACKING_FAILURES = 0.5


def check_tracking(robot: RobotParams) -> None:
    """A :class:`RunError` where the tracker cannot find ``robot`` in the simulated camera's
    frames: the robot rendered at :data:`TRACKING_PROBE_FRAMES` poses of the held-out
    evaluation (:func:`magrun.tracking.evaluate.evaluate`: random headings, lighting, blur,
    noise, half of them in a channel) and tracked as in a trial; more than
    :data:`MAX_TRACKING_FAILURES` of them lost or over 1 mm off is refused. The shipped
    tracker learnt the paper's two robots at the camera's 2.5 px/mm; it finds robots of
    their looks from their own size to a quarter larger, loses 12–45 % of the frames at
    three quarters of it and all at a quarter (docs/tracking.md). Its trials would be
    stopped by the safety layer for "tracking lost": micro_magnet's (lost in every frame)
    at 1.02 s, a magnet robot 1.5 times as large (57 % lost) at 2.6 s. The share is kept in
    the machine's cache (:mod:`magrun.answers`; the key covers the robot and the shipped
    weights)."""
    from magrun.answers import remembered

    def probe() -> tuple[float]:
        from magrun.tracking.evaluate import evaluate
        from magrun.tracking.tracker import default_weights_path, load_net
        from magrun.tracking.weights import read_weights

        with trial_threads(1):  # the network's session is made with one thread, as a trial's
            net = load_net(read_weights(default_weights_path()))
            result = evaluate(net, [robot], frames=TRACKING_PROBE_FRAMES, search_frames=0)
        return (float(result["tracking"]["failure_rate"]),)

    (failures,) = remembered("tracking", (repr(robot).encode(),), probe, 1)
    if failures > MAX_TRACKING_FAILURES:
        size = f"{robot.length * 1e3:g} mm × {robot.diameter * 1e3:g} mm"
        raise RunError(
            f"feedback: camera: the camera's tracker lost the robot {robot.name!r} ({size}, "
            f"looks {robot.appearance!r}) in {failures:.0%} of {TRACKING_PROBE_FRAMES} "
            "rendered frames (it was trained on the paper's two robots at their sizes): "
            "the trials' safety layer would stop them for lost tracking. Set `feedback: "
            "{camera: false}` (the simulator's pose feeds the fluoroscopy mimic)"
        )


#: the factor on the NMPC's heading-error weights where the planner follows held headings
#: (``angle_weight: auto``): there the planned heading is one the coils can hold, chosen by
#: the planner, not the task's, and tracking it costs the path. With exact feedback at
#: 25.5 Hz (3 trials) the proposed method's RMS on ``tri`` was 0.41 mm at 1, 0.26 at 0.1,
#: 0.19 at 0.03 and 0.063 mm at 0.01 (``three``: 0.20, 0.13, 0.13, 0.096 mm); the heading's
#: RMS off the S's own went from 17° to 22° on ``tri`` and from 15° to 62° on ``three``
#: (docs/systems.md). So light, the heading lets plain Gauss–Newton steps diverge: the NMPC's
#: steps are checked there (``step_check``; :mod:`magrun.control.nmpc`, "Checked steps")
HELD_ANGLE_WEIGHT = 0.01
#: the NMPC's step damping where the planner's headings leave the reference's (``auto``), per
#: (I / I_max)²: the paper rig's current weight R
HELD_DAMPING = 1.0
#: how many of the Kalman filter's position σ before a frame the NMPC's heading is planned to
#: withstand where ``auto`` turns it on (:func:`position_uncertainty`): on ``tri`` and
#: ``three`` (docs/systems.md, 3 trials per cell) 1 σ still lost the robot at 3 Hz, σ = 2 mm
#: on ``tri``; 4 σ cost accuracy everywhere else
POSITION_SIGMAS = 2.0
#: the strong tracking filter's weakening factor β where it guards the linearised filter
#: (:func:`strong_tracking`): it fades only where the innovations' spread exceeds ten times
#: the measurement noise's plus the prior's; on replayed ``three`` recordings at 3 Hz,
#: σ = 2 mm, β = 1.5 cost up to 0.7 mm where the filter agreed with the robot, 4 up to
#: 0.06 mm, 10 nothing; 10 recovered the diverged ones best (2.4 and 2.5 mm; 4: 2.6, 2.6)
GUARD_WEAKENING = 10.0
#: planned_reference's results in this process (_remembered)
_PLANNED: dict[tuple[Any, ...], Any] = {}
#: how many times over the paper rig's coils give its protocols' references' velocities
#: (median over each reference; 5.9 to 8.1 for the spine, the channel and the S), rounded up:
#: the NMPC's current weights were set there (the weights in magrun.control.nmpc's module doc)
PAPER_SPEED_FACTOR = 8.2
#: s: the integral action's time constant where ``auto`` turns it on (:func:`integral_time`).
#: With exact feedback at 25.5 Hz (3 trials) the proposed method's RMS error on MiniMag's S
#: was 4.4 µm at 0.15 s, 3.5 µm at 0.1 s, 3.1 µm at 0.08 s; on OctoMag's 3.1, 3.3 and 3.5 µm;
#: 0.3 s and 1 s left more of the offset on both. At 3 Hz and 25.5 Hz with σ = 2 mm (8 trials)
#: 0.1 s and 0.15 s were within 2 % of each other on both systems
INTEGRAL_TIME = 0.1


def _remembered(
    cache: dict[tuple[Any, ...], tuple[float, ...]], kind: str, coils: CoilSystem,
    reference: Trajectory | None, robot: RobotParams, length: int,
    compute: Callable[[PlanarFieldModel], tuple[float, ...]],
) -> tuple[float, ...]:  # fmt: skip
    """``compute(the system's lookup-table model)``: ``length`` numbers about ``coils``, the
    robot and ``reference`` (None: an answer for the whole workspace), remembered in this
    process's ``cache`` (at most 32) and in the machine's cache under ``kind``
    (:mod:`magrun.answers`): a test session or a campaign runs the same protocol many times,
    and each answer costs hundreds of linear programs. The inputs are the system's files by
    content, its limits, the robot (every field's repr) and the reference's knots."""
    from magrun.answers import files_digest, remembered

    knots = () if reference is None else (reference.t.tobytes(), reference.poses.tobytes())
    limits = np.atleast_1d(coils.max_current).tobytes()
    key = (kind, coils.folder, limits, repr(robot), *knots)

    def answer() -> tuple[float, ...]:
        inputs = (files_digest(coils.folder).encode(), limits, repr(robot).encode(), *knots)
        return remembered(
            kind, inputs, lambda: compute(load_system(coils.folder).models[1]), length
        )

    return _kept(cache, key, 32, answer)


def nmpc_tuning(
    nmpc: NMPCConfig, settings: ControllerSettings, held: bool, factor: float
) -> NMPCConfig:
    """The NMPC's step damping, current weights and heading weights for a system and task
    (module doc of :mod:`magrun.control.nmpc`: step damping, and the weights): ``held``,
    whether the planner follows held headings instead of the reference's (then the heading
    weights are :data:`HELD_ANGLE_WEIGHT` of the paper's, and its steps are checked, unless
    the protocol's ``step_check`` says otherwise);
    ``factor``, how many times over the coils give the reference's velocity (median)."""
    damping = settings.step_damping
    if damping == "auto":
        damping = HELD_DAMPING if held else 0.0
    weight = current_weight(settings, factor)
    angle = settings.angle_weight
    if angle == "auto":
        angle = HELD_ANGLE_WEIGHT if held else 1.0
    check = held if settings.step_check == "auto" else settings.step_check
    return replace(
        nmpc, step_damping=float(damping), step_check=check, r_current=nmpc.r_current * weight,
        s_current_change=nmpc.s_current_change * weight, q_angle=nmpc.q_angle * angle,
        q_angle_terminal=nmpc.q_angle_terminal * angle,
    )  # fmt: skip


def current_weight(settings: ControllerSettings, factor: float) -> float:
    """The factor on the NMPC's current weights (:func:`nmpc_tuning`): the protocol's, or
    ``auto``'s max(1, (factor / PAPER_SPEED_FACTOR)²)."""
    if settings.current_weight != "auto":
        return settings.current_weight
    return max(1.0, (factor / PAPER_SPEED_FACTOR) ** 2) if math.isfinite(factor) else 1.0


def integral_time(settings: ControllerSettings, held: bool, factor: float) -> float:
    """The integral action's time constant, s (:class:`magrun.control.base.Controller`):
    the protocol's, or ``auto``'s: :data:`INTEGRAL_TIME` where the current weights are raised
    above the paper rig's (they leave the robot behind by what the model does not know of
    it) and the planner follows the reference's own headings (where it follows held ones,
    the distance to the reference is the price of the heading, not an offset), else 0."""
    if settings.integral_time_s != "auto":
        return settings.integral_time_s
    return INTEGRAL_TIME if current_weight(settings, factor) > 1.0 and not held else 0.0


def frame_ticks(settings: ControllerSettings, condition: Conditions) -> int:
    """Control ticks per feedback frame."""
    rate = condition.rate_hz
    return max(1, round(settings.rate_hz / rate)) if rate < math.inf else 1


def position_uncertainty(
    settings: ControllerSettings, held: bool, kalman: KalmanConfig, frame_ticks: int
) -> float:
    """The position error, m, that the NMPC's heading-stable field withstands (module doc of
    :mod:`magrun.control.nmpc`, "Position uncertainty"): the protocol's, or ``auto``'s
    :data:`POSITION_SIGMAS` × the Kalman filter's steady position σ just before a frame
    (:func:`magrun.control.estimation.steady_position_sigma`) where the planner follows held
    headings, else 0."""
    if settings.position_uncertainty_mm != "auto":
        return settings.position_uncertainty_mm * 1e-3
    if not held:
        return 0.0
    return POSITION_SIGMAS * steady_position_sigma(kalman, frame_ticks)


def soft_constraints(settings: ControllerSettings, held: bool) -> Literal["slack", "penalty"]:
    """How the NMPC keeps its soft constraints: the protocol's choice, or ``auto``'s:
    ``slack`` where the planner follows held headings, else ``penalty``. On ``tri`` and
    ``three`` (docs/systems.md) under σ = 2 mm the penalty residuals left 2 % of the ticks at
    25.5 Hz with a failed solve and the slacks none, at the same accuracy (3 trials)."""
    if settings.soft_constraints != "auto":
        return settings.soft_constraints
    return "slack" if held else "penalty"


def strong_tracking(settings: ControllerSettings, held: bool) -> tuple[bool, float]:
    """Whether the Kalman filter fades its position covariance by its innovations (module doc
    of :mod:`magrun.control.estimation`, "Strong tracking"), and its weakening factor β: the
    protocol's choice, or ``auto``'s. With the linearised filter it is a divergence guard,
    β = :data:`GUARD_WEAKENING`: inert while the innovations agree with the filter (114 of 116
    closed-loop trials on four systems the same to the last digit), it brought the two
    replayed ``three`` recordings where the filter diverged back (5.9 → 2.4 mm, 5.0 → 2.5 mm
    RMS). With the paper's filter (F = I) it is on where the planner follows held headings,
    β = 1.5: on ``three`` (docs/systems.md) at 3 Hz with σ = 2 mm that filter lost the robot
    in 6 of 6 trials without it and in none with it; on OctoMag and MiniMag, whose model the
    filter can trust, it cost 5–20 % (8 trials)."""
    k = settings.kalman
    weakening = GUARD_WEAKENING if k.linearised else KalmanConfig.weakening
    if k.strong_tracking != "auto":
        return k.strong_tracking, weakening
    return (k.linearised or held), weakening


def two_layer_tuning(
    config: ControlConfig, settings: ControllerSettings, coils: CoilSystem, robot: RobotParams
) -> ControlConfig:
    """The two-layer baselines' wrench for this robot and system (``auto``; docs/control.md,
    "The baselines' wrench"): the paper rig's values were set for its magnet robot, as a
    speed and a turn rate (0.4 mN over its drag along the axis, 11 mm/s; 4 µN m over its
    rotational drag, 1.9 rad/s). Another robot gets the force and torque that move it so: the
    linear MPC's wrench units scale by its drags over the magnet robot's (the same
    closed-loop speeds, whatever it weighs). The allocation's force and torque references
    scale by its moment over the magnet robot's: both are the moment times a gradient or a
    field, so the allocation trades the same fields and gradients against its row for the
    field along the axis and its currents for any robot. The linear MPC's limits
    are those units, or less where the coils give the robot less (its
    :func:`typical_wrench`): it then plans only what the allocation can deliver. On the paper
    rig with the magnet robot every value is the hand-set one, to the last digit. A number
    for ``wrench_scale`` multiplies the paper rig's values instead, for any robot."""
    mpc, allocation = config.linear_mpc, config.allocation
    if settings.wrench_scale != "auto":
        force = torque = moment = float(settings.wrench_scale)
        box_force, box_torque = mpc.force_unit * force, mpc.torque_unit * torque
    else:
        magnet = load_robot(PAPER_ROBOT)
        force = robot.drag_parallel / magnet.drag_parallel
        torque = robot.drag_rotation / magnet.drag_rotation
        moment = robot.moment / magnet.moment
        typical_force, typical_torque = typical_wrench(coils, robot)
        box_force = min(mpc.force_unit * force, typical_force or math.inf)
        box_torque = min(mpc.torque_unit * torque, typical_torque)
    return replace(
        config,
        linear_mpc=replace(
            mpc, force_unit=mpc.force_unit * force, torque_unit=mpc.torque_unit * torque,
            max_force=box_force, max_torque=box_torque,
        ),
        allocation=replace(
            allocation, force_ref=allocation.force_ref * moment,
            torque_ref=allocation.torque_ref * moment,
        ),
    )  # fmt: skip


#: the robot the paper rig's two-layer wrench values were set for (:func:`two_layer_tuning`)
PAPER_ROBOT = "magnet"
#: typical_wrench's answers in this process (_remembered)
_WRENCH: dict[tuple[Any, ...], Any] = {}


def typical_wrench(coils: CoilSystem, robot: RobotParams) -> tuple[float, float]:
    """The force (N) and torque (N m) ``coils`` typically give ``robot`` at their limits over
    their workspace: :attr:`~magrun.field.capability.WorkspaceCapability.typical_force`, and
    the robot's moment times :attr:`~magrun.field.capability.WorkspaceCapability.
    typical_field` (:func:`~magrun.field.capability.workspace_capability` on the system's
    lookup-table model; ~1 s, remembered in the process and in the machine's cache:
    :mod:`magrun.answers`)."""
    from magrun.field.capability import workspace_capability

    def compute(model: PlanarFieldModel) -> tuple[float, float]:
        cap = workspace_capability(
            model, robot, coils.max_current, model.coils.workspace_half_width
        )
        return cap.typical_force, cap.typical_field * robot.moment

    force, torque = _remembered(_WRENCH, "typical_wrench", coils, None, robot, 2, compute)
    return force, torque


def planned_reference(
    coils: CoilSystem, reference: Trajectory, robot: RobotParams
) -> tuple[Trajectory, float]:
    """``(trajectory, factor)``: ``reference`` with the headings the coils can hold (the
    nominal robot, the system's lookup-table model, its limits;
    :func:`magrun.field.capability.held_reference`), ``reference`` itself where they hold
    its own heading throughout; and how many times over they give its velocity (median).
    Remembered in the process and in the machine's cache (the heading offsets and the
    factor: :mod:`magrun.answers`)."""
    from magrun.field.capability import HELD_SAMPLES, held_reference, held_trajectory

    def compute(model: PlanarFieldModel) -> tuple[float, ...]:
        held = held_reference(model, robot, coils.max_current, reference)
        return (held.median_factor, *held.offsets)

    factor, *kept = _remembered(
        _PLANNED, "planned_headings", coils, reference, robot, 1 + HELD_SAMPLES, compute
    )
    offsets = np.array(kept)
    # the reference asked about itself (not an equal one of another trial's: trials compare
    # the two objects to know whether the headings were turned) where the coils hold its own
    return (held_trajectory(reference, offsets) if offsets.any() else reference), factor


def led_reference(reference: Trajectory, scene: Scene, lead_mm: float) -> Trajectory:
    """``reference`` with its headings led by ``lead_mm`` where the path bends away from the
    scene's critical wall (:func:`magrun.scene.lead_headings`); ``reference`` itself without a
    lead or a critical wall."""
    from magrun.scene import lead_headings

    if lead_mm <= 0 or scene.critical is None:
        return reference
    return lead_headings(reference, scene.boundaries[scene.critical], lead_mm * 1e-3)


#: check_reach's verdicts in this process (_remembered)
_REACH: dict[tuple[Any, ...], Any] = {}


def check_reach(coils: CoilSystem, reference: Trajectory, robot: RobotParams) -> None:
    """A :class:`RunError` where the coils cannot move ``robot`` along ``reference`` (the
    nominal robot, the system's lookup-table model, its current limits). A reference they
    can is remembered in the process and in the machine's cache (:mod:`magrun.answers`)."""
    from magrun.field.capability import trajectory_capability

    def check(model: PlanarFieldModel) -> tuple[float]:
        reach = trajectory_capability(model, robot, coils.max_current, reference, 200, True)
        return (1.0 if reach.feasible else math.nan,)  # NaN: not kept in the machine's cache

    if _remembered(_REACH, "reachable", coils, reference, robot, 1, check) == (1.0,):
        return
    # what the coils cannot do, and where: checked again for the message
    lut = load_system(coils.folder).models[1]
    reach = trajectory_capability(lut, robot, coils.max_current, reference, 200, True)
    if reach.feasible:  # a kept number that was not the verdict
        return
    k = len(reach.t) - 1  # the first pose out of reach
    x, y = reach.poses[k, :2] * 1e3
    where = f"first at t = {reach.t[k]:.1f} s, ({x:.1f}, {y:.1f}) mm"
    limit = f"within {np.max(coils.max_current):g} A"
    if math.isnan(reach.factor[k]):
        turn = math.degrees(abs(reach.turn_rate[k]))
        problem = (
            f"cannot give the robot the {robot.min_aligned_field * 1e3:g} mT along its moment "
            f"that holds its heading"
            + (f" while turning it at {turn:.0f}°/s" if turn else "")
            + f", at any heading {limit}"
        )
    else:
        asked = reach.speed[k] * 1e3
        problem = (
            f"can move the robot at {reach.factor[k]:.1%} of the {asked:.2f} mm/s asked there "
            f"at most ({limit}, its field along the moment held)"
        )
    system = "" if coils.folder is None else f" {coils.folder}"
    raise RunError(
        f"trajectory: the coils {problem}, {where}. `magrun field check{system} --robot "
        f"{robot.name} --speed-mm-s V` maps what they can do; --allow-infeasible runs anyway"
    )


def coil_gains_of(protocol: Protocol, coils: CoilSystem) -> FloatArray | None:
    """The protocol's coil calibration (``controller.coil_gains``) in ``coils``' channel
    order, or None; a :class:`RunError` when the file's channels are not the coils'."""
    path = protocol.controller.coil_gains
    if path is None:
        return None
    try:
        return gains_in_order(load_coil_gains(path), coils.channel_names, path)
    except (ValueError, YamlModelError) as exc:
        raise RunError(str(exc)) from exc


def controller_tuning(
    trial: Trial, system: System
) -> tuple[Scene, RobotParams, ControlConfig, Trajectory, Trajectory]:
    """``trial``'s scene, robot, controller configuration, the reference its controller
    follows and the one with only the headings the coils can hold (:class:`ControllerParts`),
    on ``system``: everything :func:`build_controller` builds the controller from."""
    protocol = trial.protocol
    coils = system.coils
    scene = build_scene(protocol, coils)
    robot = protocol.robot_params()
    config = control_config(protocol.controller, robot, trial.condition)
    # the NMPC plans the heading with the currents: it follows headings the coils can hold
    # (the two-layer baselines allocate a force and a field of their own choosing)
    planned = held_path = scene.reference
    if trial.method in NMPC_METHODS:
        held_path, factor = planned_reference(coils, scene.reference, robot)
        held = held_path is not scene.reference
        planned = led_reference(held_path, scene, protocol.controller.heading_lead_mm)
        config = replace(
            config, nmpc=nmpc_tuning(config.nmpc, protocol.controller, held, factor),
            integral_time=integral_time(protocol.controller, held, factor),
        )  # fmt: skip
        ticks = frame_ticks(protocol.controller, trial.condition)
        sigma = position_uncertainty(protocol.controller, held, config.kalman, ticks)
        fading, weakening = strong_tracking(protocol.controller, held)
        config = replace(
            config,
            nmpc=replace(
                config.nmpc, position_uncertainty=sigma, frame_interval=ticks * config.dt,
                soft_constraints=soft_constraints(protocol.controller, held),
            ),
            kalman=replace(config.kalman, strong_tracking=fading, weakening=weakening),
        )  # fmt: skip
    else:
        config = two_layer_tuning(config, protocol.controller, coils, robot)
    return scene, robot, config, planned, held_path


def build_controller(
    trial: Trial,
    system: System | None = None,
    tune: Callable[[ControlConfig], ControlConfig] | None = None,
) -> ControllerParts:
    """``trial``'s scene, robot, tuning, free space and controller, on ``system`` (default:
    the protocol's): the part of :func:`assemble` that needs no rig (the replay builds only
    this)."""
    protocol = trial.protocol
    system = system or system_of(protocol)
    coils = system.coils
    scene, robot, config, planned, held = controller_tuning(trial, system)
    if tune is not None:
        config = tune(config)
    free_space = free_space_of(scene, robot)
    gains = coil_gains_of(protocol, coils)
    t0 = time.perf_counter()
    zernike, lut = system.models  # the system's own, with its limits
    controller = make_controller(
        trial.method, robot, config, zernike=zernike, lut=lut, free_space=free_space,
        coil_gains=gains,
    )  # fmt: skip
    return ControllerParts(
        scene, robot, config, free_space, controller, time.perf_counter() - t0, planned, held
    )


def assemble(
    trial: Trial,
    rig: RigSpec = "sim",
    tune: Callable[[ControlConfig], ControlConfig] | None = None,
) -> TrialParts:
    """Build ``trial``'s parts on ``rig`` (a hardware rig is connected here and disconnected
    again if a later part fails). ``tune`` adjusts the controller's configuration before the
    controller is built (the benchmarks pick a solver with it)."""

    protocol = trial.protocol
    system = system_of(protocol)  # the rig's, the scene's and the controller's
    coils = system.coils
    parts = build_controller(trial, system, tune)
    scene, robot, controller = parts.scene, parts.robot, parts.controller
    simulated = rig == "sim"
    config = rig_config(
        rig, robot, scene.walls, trial.seed, protocol.feedback.camera,
        protocol.safety.stall_timeout_ms * 1e-3, system, protocol.simulation, scene.channel,
    )  # fmt: skip
    the_rig = make_rig(config)
    if not simulated:
        the_rig.connect()  # the rig's channels and limits come from its coil driver
    try:
        if tuple(the_rig.channel_names) != coils.channel_names:
            raise RunError(
                f"the coil driver drives {', '.join(the_rig.channel_names)}, the protocol's "
                f"system ({coils.name}) has {', '.join(coils.channel_names)}: set the "
                "protocol's `system:` to the rig's coil system"
            )
        # in simulation the loop tracks the rendered frames; a hardware rig tracks its own
        # camera (its observations' poses), the loop's feedback derives from them
        tracker = the_rig.frame_tracker()
        condition = trial.condition
        feedback = FluoroscopyMimic(
            condition.rate_hz, condition.noise_position_m, condition.noise_heading_rad,
            seed=trial.seed,
        )  # fmt: skip
        limits = protocol.safety
        margin = limits.workspace_margin_mm
        safety = SafetyLayer(
            controller.n_channels, controller.max_current, controller.max_change / controller.dt,
            controller.dt,
            SafetyConfig(
                lost_timeout_s=limits.lost_timeout_s,
                workspace_margin_m=None if margin is None else margin * 1e-3,
            ),
            workspace_half_width=scene.half_width,
        )  # fmt: skip
    except BaseException:
        if not simulated:
            the_rig.disconnect()
        raise
    return TrialParts(
        trial, robot, scene, parts.free_space, parts.config, controller, the_rig, tracker,
        feedback, safety, simulated, parts.build_s, parts.planned, parts.held,
    )  # fmt: skip


def single_trial(protocol: Protocol, method: str, seed: int) -> Trial:
    """One trial of ``method`` under ``protocol``'s fixed conditions, with rig and feedback
    seeded by ``seed`` itself (an in-memory protocol's trial: ``magrun track``, benchmarks)."""
    return Trial(
        protocol=protocol, method=method, condition=protocol.conditions, swept=(), index=0,
        seed=seed, slug=condition_slug(method, {}),
    )  # fmt: skip


def with_solver(solver: str) -> Callable[[ControlConfig], ControlConfig]:
    """A ``tune`` for :func:`assemble`: the NMPC methods' solver (``rti`` or ``ipopt``)."""

    def tune(config: ControlConfig) -> ControlConfig:
        return replace(config, nmpc=replace(config.nmpc, solver=solver))  # type: ignore[arg-type]

    return tune
