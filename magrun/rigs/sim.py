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
  turns it out as drag lets it: :meth:`magrun.scene.Walls.resolve_capsule`).

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

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magrun.field.coils import CoilSystem
from magrun.field.grid import ChannelGrid, GridCells, HeldField
from magrun.rigs.base import Observation, Rig
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
        Integrate with the Numba kernel (:mod:`magrun.rigs.kernel`, 10–20× faster); False runs
        the Python reference (:func:`magrun.robot.discrete_step`), which the tests compare.
    """

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
        self.fine_step = fine_step
        self.camera = Camera(camera) if camera is not None else None
        self.seed = seed
        self._renderer: Renderer | None = None
        self._contact_radius = robot.diameter / 2
        self._half_axis = max(robot.length / 2 - self._contact_radius, 0.0)
        self._reach = self._half_axis + self._contact_radius  # farthest body point from centre
        self.compiled = compiled
        if compiled:
            from magrun.rigs.kernel import ROBOT_FIELDS, free_substeps, resolve_capsule

            self._kernel, self._resolve = free_substeps, resolve_capsule
            self._disks = capsule_disks(self._half_axis, self._contact_radius)
            self._robot_vector = np.array([getattr(self.robot, f) for f in ROBOT_FIELDS])
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
        plant_seed: int | None = None,
    ) -> SimRig:
        """The paper's rig with the shipped reference maps, or the system ``coils`` with its
        folder's maps (``robot``: a robot of robots.yaml or its parameters; ``plant_seed``:
        see the class)."""
        coils = coils or CoilSystem.load()
        params = load_robot(robot) if isinstance(robot, str) else robot
        return cls(
            coils, ChannelGrid.load(coils), params, walls, perturbation, seed,
            camera=camera, plant_seed=plant_seed,
        )  # fmt: skip

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

    def observe(self, frame: bool = True) -> Observation:
        pose = self.state[:3].copy()
        image = self._renderer.render(pose) if frame and self._renderer is not None else None
        obs = Observation(t=self.t, pose=pose, in_contact=self._contact, frame=image)
        self._contact = False
        return obs

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
        if self.compiled:
            self._advance_compiled(n, h, ramp)
            self.t += duration
            return
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
            state = discrete_step(state, field, self.robot, h, substeps=1, ops=MATH_OPS)
            state = self._contact_step(state)
        self.state = np.array(state, dtype=np.float64)
        self.t += duration

    def _advance_compiled(self, n: int, h: float, ramp: FloatArray) -> None:
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
        while k < n:
            cx, cy, slack = self._clear[:3]
            k = self._kernel(
                state, drives, k, g.table, g.x0, g.y0, g.step, self._robot_vector, h,
                cx, cy, slack,
            )  # fmt: skip
            if math.hypot(state[0] - cx, state[1] - cy) >= slack:
                state[:] = self._contact_step(tuple(state.tolist()))
        self.state = state

    def _contact_step(self, state: tuple[float, ...]) -> tuple[float, ...]:
        """Walls in reach push the body out (after each sub-step)."""
        walls = self._walls_in_reach(state[0], state[1])
        if walls is not None and self.compiled:
            out = np.array(state)
            if self._resolve(
                out, walls.segments, self._disks, self._contact_radius,
                self.robot.drag_perpendicular, self.robot.drag_rotation, 16,
            ):  # fmt: skip
                self._contact = True
            return tuple(out.tolist())
        if walls is not None:
            state, touched = walls.resolve_capsule(
                state, self._half_axis, self._contact_radius,
                self.robot.drag_perpendicular, self.robot.drag_rotation,
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
