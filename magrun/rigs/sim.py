"""The simulated coil rig: the robot's true dynamics in the reference ("FEA") field.

    >>> from magrun.rigs.sim import SimRig
    >>> rig = SimRig.default(robot="magnet", seed=0)
    >>> rig.reset([0.0, 0.0, 0.0])
    >>> rig.apply([0, 10, 0, 0, 0, 0, 0, 0])                 # A, one per channel
    >>> rig.advance(0.04)
    >>> rig.observe().pose                                     # x, y (m), θ (rad)

What the controllers do not know, and the plant does:

- the field is the reference maps (:class:`~magrun.field.grid.ChannelGrid`, bilinear on the
  1 mm grid), not the controller's Zernike or lookup-table model;
- the robot's mass, drag and moment, and every coil's gain, are drawn per trial from
  :class:`Perturbation` around the nominal values (seeded: a trial is reproducible);
- the amplifiers ramp each current toward its command at the slew limit instead of stepping;
- walls stop the robot's body, a capsule (inelastic, frictionless contact that pushes and
  turns it out as drag lets it: :meth:`magrun.scene.Walls.resolve_capsule`);
- and, where the protocol asks for a real bench's imperfections (``simulation.plant``),
  :class:`~magrun.rigs.plant.Imperfections`: the camera's frame age, amplifier lag, coil
  placement errors and an unmodelled residual field, the moment's misalignment, floor
  friction, the fluid's flow and the tracking pipeline's errors (:mod:`magrun.rigs.plant`).

With a ``camera``, an observation asked for a frame carries a rendered top-view frame of the
true pose
(:mod:`magrun.tracking.render`: the robot's look, the walls, blur, lighting, sensor noise),
seeded with the trial, for the tracker to work on as it would on the real rig.

The plant integrates :func:`magrun.robot.discrete_step` on a fine step (1 ms by default),
re-evaluating the field and the ramping currents every step. By default the sub-steps and the
wall contacts run compiled (:mod:`magrun.rigs.kernel`, Numba); ``compiled=False`` runs the
Python reference (the field through :class:`magrun.field.grid.GridCells`, each grid cell's
corners gathered once), which the tests compare with it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid, GridCells, HeldField
from magrun.rigs.base import Observation, PoseTracker, Rig
from magrun.rigs.plant import (
    EXPOSURE_SAMPLES,
    IDEAL,
    ImageArtifacts,
    Imperfections,
    ImperfectTracker,
    OrnsteinUhlenbeck,
    PoseHistory,
    TrackingErrors,
    amplifier_path,
    contact_substep,
    contact_vector,
    draw_plant,
    perturb_table,
)
from magrun.robot import MATH_OPS, RobotParams, discrete_step, load_robot
from magrun.safety import clamp_currents
from magrun.scene import Walls, capsule_disks
from magrun.tracking.camera import Camera, CameraConfig
from magrun.tracking.render import Renderer

FloatArray = NDArray[np.float64]

#: walls within this distance (m) of the body's reach are contact candidates (broad phase)
NEAR = 2e-3


@dataclass(frozen=True)
class Perturbation:
    """Relative standard deviations of the per-trial parameter draws (0 = nominal).

    Each factor is log-normal, ``exp(N(0, σ²))``, so it stays positive: mass (and inertia),
    all drag coefficients, the magnetic moment, and each coil's gain (field per ampere).
    """

    mass: float = 0.0
    drag: float = 0.0
    moment: float = 0.0
    coil_gain: float = 0.0

    def draw(
        self, robot: RobotParams, n_channels: int, rng: np.random.Generator
    ) -> tuple[RobotParams, FloatArray]:
        """The true robot and per-channel gains of one trial."""
        f = np.exp(rng.normal(0.0, [self.mass, self.drag, self.moment]))
        gains = np.exp(rng.normal(0.0, self.coil_gain, n_channels))
        return robot.scaled(mass=f[0], drag=f[1], moment=f[2]), gains


#: the default mismatch between the controllers' models and the simulated plant
DEFAULT_PERTURBATION = Perturbation(mass=0.1, drag=0.1, moment=0.05, coil_gain=0.02)

#: the simulated plant's parameters recorded per trial (RobotParams fields, SI)
PLANT_FIELDS = (
    "mass", "inertia", "drag_parallel", "drag_perpendicular", "drag_rotation", "moment",
)  # fmt: skip


class SimRig(Rig):
    """Simulated plant behind the :class:`Rig` interface.

    Parameters
    ----------
    coils : CoilSystem
        Channels and limits (``max_current``, ``max_slew_rate``).
    grid : ChannelGrid
        The plant's field tables.
    robot : RobotParams
        Nominal robot; the trial's true robot is drawn from ``perturbation``.
    walls : Walls, optional
        Wall segments; default: the workspace box.
    perturbation : Perturbation
        Per-trial parameter spread; default :data:`DEFAULT_PERTURBATION`.
    seed : int
        Seeds the parameter draw and the camera's lighting and noise.
    plant_seed : int, optional
        Seeds the parameter draw instead of ``seed``: rigs made with one ``plant_seed`` have
        the same robot and coils (one real rig, many trials).
    fine_step : float
        Integration step, s.
    camera : CameraConfig, optional
        Render a camera frame with every observation; default: no frames.
    compiled : bool
        Integrate with the Numba kernel (:mod:`magrun.rigs.kernel`; BENCHMARKS.md); False runs
        the Python reference (:func:`magrun.robot.discrete_step`), which the tests compare.
    imperfections : Imperfections
        A real bench's imperfections (:mod:`magrun.rigs.plant`); default: none.
    flow_path : ndarray (n, 2), optional
        A channel's centre line (m): the flow runs along it (its direction nearest the robot);
        default: the flow is a 2-D vector.
    """

    simulated = True

    def __init__(
        self,
        coils: CoilSystem,
        grid: ChannelGrid,
        robot: RobotParams,
        walls: Walls | None = None,
        perturbation: Perturbation = DEFAULT_PERTURBATION,
        seed: int = 0,
        fine_step: float = 1e-3,
        camera: CameraConfig | None = None,
        compiled: bool = True,
        plant_seed: int | None = None,
        imperfections: Imperfections = IDEAL,
        flow_path: FloatArray | None = None,
    ) -> None:
        if grid.channel_names != coils.channel_names:
            raise ValueError("the field grid was built for other channels than the coil system")
        self.coils = coils
        self.grid = grid
        self._cells = GridCells(grid)
        self.channel_names = coils.channel_names
        self.max_current = coils.max_current
        self.max_slew_rate = coils.max_slew_rate
        self.walls = walls if walls is not None else Walls.box(coils.workspace_half_width)
        self.nominal_robot = robot
        plant_rng = np.random.default_rng(seed if plant_seed is None else plant_seed)
        self.robot, self.coil_gains = perturbation.draw(robot, coils.n_channels, plant_rng)
        # the imperfections' plant draws follow (so the draws above are as without them)
        imp = self.imperfections = imperfections
        limits = np.broadcast_to(np.asarray(coils.max_current, float), (coils.n_channels,))
        self.plant_draw = draw_plant(
            imp, coils.n_channels, limits, coils.workspace_half_width, plant_rng
        )
        if imp.field_error:
            pivots = np.array(
                [c.rotation @ (0.0, coils.coil_types[c.coil_type].center)
                 if c.coil_type in coils.coil_types else (0.0, 0.0) for c in coils.channels]
            )  # fmt: skip
            table = perturb_table(
                grid.table, grid.x0, grid.y0, grid.step, self.plant_draw, pivots,
                coils.workspace_half_width,
            )  # fmt: skip
            self.grid = grid = replace(grid, table=table)
            self._cells = GridCells(grid)
        self._contact_params = contact_vector(imp, self.robot, self.plant_draw.misalignment)
        self._flow_path = None if flow_path is None else np.asarray(flow_path, float)
        # the trial's processes (frame age jitter, flow, tracking errors): streams of their own
        streams = np.random.SeedSequence([seed, 37]).spawn(4)
        self._stream_seeds = streams
        self.tracking_errors = TrackingErrors(imp, streams[2]) if imp.tracking else None
        self._history: PoseHistory | None = None
        self.fine_step = fine_step
        #: the walls' Coulomb friction (μ_k, μ_s, sub-step), for the contact resolution
        self._wall_friction = (imp.wall_friction, imp.wall_stiction, fine_step)
        self.camera = Camera(camera) if camera is not None else None
        self.artifacts = (
            ImageArtifacts(imp, streams[3], robot.diameter / 2 * self.camera.scale)
            if self.camera is not None and (imp.glare_rate > 0 or imp.occlusion_rate > 0)
            else None
        )
        self.seed = seed
        self._renderer: Renderer | None = None
        self._contact_radius = robot.diameter / 2
        self._half_axis = max(robot.length / 2 - self._contact_radius, 0.0)
        self._reach = self._half_axis + self._contact_radius  # farthest body point from centre
        self.compiled = compiled
        #: the amplifiers' and the flow's recurrences (None: plant.py's, in Python)
        self._lag_path: Callable[..., FloatArray] | None = None
        self._ou_path: Callable[..., FloatArray] | None = None
        if compiled:
            from magrun.rigs.kernel import (
                ROBOT_FIELDS,
                free_substeps,
                lag_path,
                ou_path,
                resolve_capsule,
            )

            self._kernel, self._resolve = free_substeps, resolve_capsule
            self._lag_path, self._ou_path = lag_path, ou_path
            self._disks = capsule_disks(self._half_axis, self._contact_radius)
            self._robot_vector = np.array([getattr(self.robot, f) for f in ROBOT_FIELDS])
            if imperfections.contact:
                from magrun.rigs.kernel import contact_substeps

                self._contact_kernel = contact_substeps
        self.reset([0.0, 0.0, 0.0])

    @classmethod
    def default(
        cls,
        robot: str | RobotParams = "magnet",
        walls: Walls | None = None,
        perturbation: Perturbation = DEFAULT_PERTURBATION,
        seed: int = 0,
        camera: CameraConfig | None = None,
        coils: CoilSystem | None = None,
        grid: ChannelGrid | None = None,
        plant_seed: int | None = None,
        imperfections: Imperfections = IDEAL,
        flow_path: FloatArray | None = None,
    ) -> SimRig:
        """The paper's rig with the shipped reference maps, or the system ``coils`` with its
        folder's maps (``grid``: those maps gridded, where the caller has them: see
        :class:`magrun.field.system.System`; ``robot``: a robot of robots.yaml or its
        parameters; ``plant_seed``, ``imperfections``, ``flow_path``: see the class)."""
        coils = coils or CoilSystem.load()
        params = load_robot(robot) if isinstance(robot, str) else robot
        grid = grid if grid is not None else ChannelGrid.load(coils)
        return cls(
            coils, grid, params, walls, perturbation, seed, camera=camera,
            plant_seed=plant_seed, imperfections=imperfections, flow_path=flow_path,
        )  # fmt: skip

    def frame_tracker(self) -> PoseTracker | None:
        """The UNet tracker on the rendered frames (:meth:`Tracker.default` for the nominal
        robot), its poses through the bench's tracking errors where the plant has them; None
        without a camera."""
        if self.camera is None:
            return None
        from magrun.tracking.tracker import Tracker

        unet = Tracker.default(self.camera, self.nominal_robot)
        unet.warm_up()  # the network's first runs here, not in the loop's first ticks
        tracker: PoseTracker = unet
        if self.tracking_errors is not None:
            tracker = ImperfectTracker(tracker, self.tracking_errors)  # a bench's pipeline
        return tracker

    def plant_record(self) -> dict[str, str]:
        """The MCAP ``plant`` record: the trial's drawn robot parameters (SI), the nominal
        ones, each channel's coil gain, and on a plant with imperfections their settings (SI,
        :class:`~magrun.rigs.plant.Imperfections`) and per-plant draws (each coil's placement
        error, the moment's misalignment); values JSON."""
        true, nominal = self.robot, self.nominal_robot
        record = {
            "robot": json.dumps({f: getattr(true, f) for f in PLANT_FIELDS}),
            "nominal_robot": json.dumps({f: getattr(nominal, f) for f in PLANT_FIELDS}),
            "coil_gains": json.dumps(
                dict(zip(self.channel_names, np.asarray(self.coil_gains).tolist(), strict=True))
            ),
        }
        if not self.imperfections.ideal:  # a bench's imperfections: the settings and draws
            record["imperfections"] = json.dumps(self.imperfections.as_dict())
            record["draw"] = json.dumps(self.plant_draw.record(tuple(self.channel_names)))
        return record

    def reset(self, pose: ArrayLike) -> None:
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"pose must be a finite (x, y, θ), got {pose!r}")
        self.state = np.array([p[0], p[1], p[2], 0.0, 0.0, 0.0])
        self.t = 0.0
        self.driven = np.zeros(self.coils.n_channels)  # what the amplifiers drive now
        self.target = np.zeros(self.coils.n_channels)  # what they ramp toward
        self._held: HeldField | None = None
        self._contact = False
        # broad phase (_walls_in_reach): recompute on the next step
        self._clear: tuple[float, float, float, Walls, float] = (
            p[0], p[1], -math.inf, self.walls, -math.inf
        )  # fmt: skip
        if self.camera is not None:  # the same frames (lighting, noise) on every reset
            self._renderer = Renderer(self.camera, self.robot, self.walls, seed=self.seed)
        # the processes start again from the trial's seed
        imp, streams = self.imperfections, self._stream_seeds
        self._jitter_rng = np.random.default_rng(streams[0])
        self._flow = (
            OrnsteinUhlenbeck(
                imp.flow_sigma, imp.flow_time, 1 if self._flow_path is not None else 2,
                np.random.default_rng(streams[1]),
            )
            if imp.flow_sigma > 0 else None
        )  # fmt: skip
        if self.tracking_errors is not None:
            self.tracking_errors.reset()
        if self.artifacts is not None:
            self.artifacts.reset()
        if imp.delayed or (imp.exposure > 0 and self.camera is not None):
            span = imp.frame_age + 6 * imp.frame_age_jitter + imp.exposure + 0.1
            self._history = PoseHistory(span)
            self._history.reset(0.0, self.state)

    def observe(self, frame: bool = True) -> Observation:
        pose = self.state[:3].copy()
        seen, taken = pose, self.t
        if self._history is not None:  # the camera sees the robot as it was
            imp = self.imperfections
            age = imp.frame_age + imp.frame_age_jitter * float(self._jitter_rng.normal())
            taken = self.t - max(age, 0.0)
            seen = self._history.at(taken)
        image = None
        if frame and self._renderer is not None:
            image = self._render(seen, taken)
        camera_pose = None
        if self._history is not None or (self.tracking_errors and self.camera is None):
            # without a camera the pipeline's errors act on the pose; with one, on what the
            # tracker finds in the frame (magrun.rigs.plant.ImperfectTracker)
            camera_pose = seen.copy()
            if self.tracking_errors is not None and self.camera is None:
                reported = self.tracking_errors(camera_pose)
                camera_pose = np.full(3, np.nan) if reported is None else reported
        obs = Observation(
            t=self.t, pose=pose, in_contact=self._contact, frame=image,
            camera_pose=camera_pose, frame_time=taken,
        )  # fmt: skip
        self._contact = False
        return obs

    def _render(self, seen: FloatArray, taken: float) -> NDArray[np.uint8]:
        """The camera's frame of the robot at ``seen`` (taken at ``taken``): motion-blurred
        over the exposure that ends then, with the frame's glints and occluders."""
        assert self._renderer is not None
        assert self.camera is not None
        imp = self.imperfections
        exposure = None
        if imp.exposure > 0 and self._history is not None:
            k = EXPOSURE_SAMPLES
            times = taken - imp.exposure * (np.arange(k)[::-1] + 0.5) / k
            exposure = np.array([self._history.at(float(t)) for t in times])
        image = self._renderer.render(seen, exposure)
        if self.artifacts is not None:
            reach = (self.robot.length / 2) * self.camera.scale
            image = self.artifacts(image, self.camera.to_pixel(seen[:2]), reach)
        return image

    def apply(self, currents: ArrayLike) -> FloatArray:
        I = np.asarray(currents, dtype=np.float64)
        if I.shape != (self.coils.n_channels,):
            raise ValueError(f"expected {self.coils.n_channels} currents, got shape {I.shape}")
        target = clamp_currents(I, self.target, self.max_current, math.inf)
        if not np.array_equal(target, self.target):
            self._held = None
        self.target = target
        return self.target.copy()

    def advance(self, duration: float) -> None:
        n = max(1, round(duration / self.fine_step))
        h = duration / n
        ramp = self._ramp(n, h)  # the driven currents after each ramping sub-step
        flows = self._flows(n, h)
        trace = np.empty((n if self._history is not None else 0, 3))
        if self.compiled:
            self._advance_compiled(n, h, ramp, flows, trace)
        else:
            self._advance_python(n, h, ramp, flows, trace)
        if self._history is not None:
            self._history.extend(self.t + h * np.arange(1, n + 1), trace)
        self.t += duration

    def _flows(self, n: int, h: float) -> FloatArray:
        """The fluid's velocity (m/s) at each of the next ``n`` sub-steps, (n, 2); (0, 2)
        without flow."""
        if self._flow is None:
            return np.empty((0, 2))
        v = self._flow.sample(n, h, self._ou_path)
        if self._flow_path is None:
            return v
        path = self._flow_path  # along the channel: its direction nearest the robot
        d = np.hypot(*(path - self.state[:2]).T)
        i = int(np.argmin(d))
        a, b = path[max(i - 1, 0)], path[min(i + 1, len(path) - 1)]
        tangent = (b - a) / max(float(np.hypot(*(b - a))), 1e-12)
        return v[:, :1] * tangent[None, :]

    def _advance_python(
        self, n: int, h: float, ramp: FloatArray, flows: FloatArray, trace: FloatArray
    ) -> None:
        """:meth:`advance`'s sub-steps in Python (the reference)."""
        imp = self.imperfections
        state = tuple(self.state)
        field: Callable[[float, float], tuple[list[float], Any]]
        for k in range(n):
            if k < len(ramp):  # the step uses the current at its midpoint
                drive = self.grid.inputs(0.5 * (self.driven + ramp[k]) * self.coil_gains)
                self.driven = ramp[k]
                field = partial(self._cells.read, drive)
            else:  # the amplifiers have reached the target (the usual case): hold it
                if self._held is None:  # the target's field, kept until apply() changes it
                    self._held = self._cells.held(self.grid.inputs(self.target * self.coil_gains))
                field = self._held
            if imp.contact:
                flow = (float(flows[k, 0]), float(flows[k, 1])) if len(flows) else (0.0, 0.0)
                state = contact_substep(state, field, self.robot, h, self._contact_params, flow)
            else:
                state = discrete_step(state, field, self.robot, h, substeps=1, ops=MATH_OPS)
            state = self._contact_step(state)
            if len(trace):
                trace[k] = state[:3]
        self.state = np.array(state, dtype=np.float64)

    def _advance_compiled(
        self, n: int, h: float, ramp: FloatArray, flows: FloatArray, trace: FloatArray
    ) -> None:
        """:meth:`advance`'s sub-steps in the Numba kernel, the contacts resolved here."""
        m = len(ramp)
        drives = np.empty((n, self.coils.n_channels))  # each sub-step's effective currents
        if m:  # ramping: the current at the sub-step's midpoint, as in the reference
            before = np.vstack([self.driven[None], ramp[:-1]])
            drives[:m] = 0.5 * (before + ramp) * self.coil_gains
            self.driven = ramp[-1]
        drives[m:] = self.target * self.coil_gains
        g = self.grid
        drives = g.inputs(drives)  # and the background's column, if the system has one
        state = self.state.copy()
        k = 0
        contact = self.imperfections.contact
        while k < n:
            cx, cy, slack = self._clear[:3]
            if contact:
                k = self._contact_kernel(
                    state, drives, k, g.table, g.x0, g.y0, g.step, self._robot_vector, h,
                    cx, cy, slack, trace, self._contact_params, flows,
                )  # fmt: skip
            else:
                k = self._kernel(
                    state, drives, k, g.table, g.x0, g.y0, g.step, self._robot_vector, h,
                    cx, cy, slack, trace,
                )  # fmt: skip
            if math.hypot(state[0] - cx, state[1] - cy) >= slack:
                state[:] = self._contact_step(tuple(state.tolist()))
                if len(trace):
                    trace[k - 1] = state[:3]
        self.state = state

    def _contact_step(self, state: tuple[float, ...]) -> tuple[float, ...]:
        """Walls in reach push the body out (after each sub-step)."""
        walls = self._walls_in_reach(state[0], state[1])
        if walls is not None and self.compiled:
            out = np.array(state)
            if self._resolve(
                out, walls.segments, self._disks, self._contact_radius,
                self.robot.drag_perpendicular, self.robot.drag_rotation, 16,
                *self._wall_friction,
            ):  # fmt: skip
                self._contact = True
            return tuple(out.tolist())
        if walls is not None:
            state, touched = walls.resolve_capsule(
                state, self._half_axis, self._contact_radius,
                self.robot.drag_perpendicular, self.robot.drag_rotation,
                wall_friction=self._wall_friction,
            )  # fmt: skip
            if touched:
                self._contact = True
        return state

    def _ramp(self, n: int, h: float) -> FloatArray:
        """Driven currents after each of the next ``n`` sub-steps of ``h`` s while any channel
        still ramps (amplifiers move at the slew limit straight to the target), shape
        (m ≤ n, channels); empty once every channel has reached its target."""
        delta = self.target - self.driven
        if not np.any(delta):
            return np.empty((0, delta.size))
        tau = self.imperfections.amplifier_tau
        if tau > 0:  # a first-order lag, rate-limited (magrun.rigs.plant.amplifier_path)
            path = amplifier_path(
                self.driven, self.target, tau, self.max_slew_rate, h, n, self._lag_path
            )
            close = np.all(np.abs(path - self.target) <= 1e-12, axis=1)
            if np.any(close):  # settled to rounding: hold the target from there
                first = int(np.argmax(close))
                path[first] = self.target
                return path[: first + 1]
            return path
        reach = np.arange(1, n + 1)[:, None] * (self.max_slew_rate * h)  # (n, 1)
        done = np.abs(delta) <= reach  # (n, ch): reached by then (exactly the target)
        path = np.where(done, self.target, self.driven + np.sign(delta) * reach)
        finished = np.flatnonzero(np.all(done, axis=1))
        return path[: finished[0] + 1] if finished.size else path

    def _walls_in_reach(self, x: float, y: float) -> Walls | None:
        """The walls the body may touch now (None: none), a broad phase before the exact test.

        Every point of the body lies within ``reach`` (half length) of its centre, whatever
        its heading, so a wall at distance d from the centre cannot be touched before the
        centre has moved d − reach. On a recomputation the walls within :data:`NEAR` of
        reach are kept as the candidates: until the centre has moved as far as the nearest
        of the others could allow, only candidates can touch, and only candidates are tested
        (a phantom's channel has hundreds of segments, of which a few are ever in reach).
        """
        cx, cy, slack, nearby, others = self._clear
        moved = math.hypot(x - cx, y - cy)
        if moved < slack:
            return None
        if moved < others:
            return nearby
        if self.walls.segments.size == 0:
            self._clear = (x, y, math.inf, self.walls, math.inf)
            return None
        d = self.walls.distances((x, y)) - self._reach
        near = d < NEAR
        nearby = Walls(self.walls.segments[near])
        others = float(np.min(d[~near])) if not np.all(near) else math.inf
        slack = float(np.min(d))
        self._clear = (x, y, slack, nearby, others)
        return nearby if slack <= 0 else None
