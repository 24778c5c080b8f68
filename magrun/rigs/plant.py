"""What a real bench adds to the simulated plant: delays, lags, model errors, friction, flow and
an imperfect camera pipeline (``simulation.*`` settings of a protocol; :class:`Imperfections`).

Every term is off (0) in an ideal plant, and an ideal plant runs exactly the code it ran before
these terms existed. Each is a model with a closed form that the tests check:

frame age
    A measurement describes the robot as it was ``frame_age`` (mean) ± ``frame_age_jitter``
    (σ, per frame, truncated at 0) earlier: the exposure, read-out, transfer and tracking of a
    camera frame, or a C-arm's pulse, read-out and transfer. The plant keeps its trajectory
    at every sub-step (:class:`PoseHistory`) and the camera sees it, linearly interpolated,
    at the frame's capture time.
amplifier dynamics
    Each amplifier's current follows its command as a first-order lag of time constant
    ``amplifier_tau``, its rate limited by the slew limit: per sub-step of h,
    ``I ← I + clip((I* − I)(1 − e^(−h/τ)), ±slew·h)`` (:func:`amplifier_path`), which is the
    exact step response ``I*(1 − e^(−t/τ))`` wherever the slew limit does not bind.
field-model error
    Each coil is displaced in the plane by N(0, ``coil_offset``²) per axis and turned by
    N(0, ``coil_rotation``²) about its centre (the paper kind's coils; about the workspace
    centre where a system does not say where its coils are): its field map moves with it,
    ``B'(p) = R B(Rᵀ(p − c − d) + c)``, ``G' = R G Rᵀ``. On top, each channel gets a smooth,
    unmodelled residual field per ampere (:func:`harmonic_field`: curl- and divergence-free,
    the lowest orders of a 2-D harmonic potential) whose RMS over the workspace at the
    channel's current limit is ``residual_field``. These are drawn once per plant (the trial's
    seed, or ``plant_seed``).
moment misalignment
    The magnetic moment lies ``misalignment`` (drawn N(0, σ²) per plant) off the body's axis:
    the field turns the robot to align the moment, the camera and the drag see the body.
contact
    Coulomb friction on the floor, translation and rotation, with stiction: a robot at rest
    stays at rest while the force (torque) on it stays at or below the stiction threshold;
    a moving one feels the kinetic friction against its velocity and stops where that would
    reverse it. Forces are given as the drag speed they equal (``friction`` m/s: force
    ``d∥ · friction``), so one setting suits robots of every size.
flow
    The fluid moves with an Ornstein–Uhlenbeck velocity (σ ``flow_sigma``, correlation time
    ``flow_time``; exact discretisation, :class:`OrnsteinUhlenbeck`): the drag pulls the
    robot toward the fluid's velocity. In the open workspace the flow is a 2-D vector; in a
    phantom with a path it runs along the channel (the path's direction nearest the robot).
tracking
    The camera pipeline's own errors on each frame's pose (:class:`TrackingErrors`): white
    noise (σ ``tracker_position`` per axis, ``tracker_heading``), outliers (a fraction
    ``outlier_rate`` of frames displaced by N(0, ``outlier_size``²) per axis) and dropped
    frames (a fraction ``drop_rate`` delivers nothing).

Random draws come from the trial's seed through streams of their own, so turning one term on
changes no other term's draw, nor any draw an ideal plant makes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: orders of the residual field's harmonic potential (uniform, gradient, curvature, …)
RESIDUAL_ORDERS = 4


@dataclass(frozen=True)
class Imperfections:
    """One plant's imperfections, SI units (s, m, rad, T, m/s, rad/s); 0 everywhere: ideal."""

    frame_age: float = 0.0
    frame_age_jitter: float = 0.0
    amplifier_tau: float = 0.0
    coil_offset: float = 0.0
    coil_rotation: float = 0.0
    residual_field: float = 0.0
    moment_misalignment: float = 0.0
    friction: float = 0.0
    stiction: float = 0.0
    rotational_friction: float = 0.0
    rotational_stiction: float = 0.0
    wall_friction: float = 0.0  # Coulomb coefficient at the walls, kinetic
    wall_stiction: float = 0.0  # and static
    flow_sigma: float = 0.0
    flow_time: float = 1.0
    tracker_position: float = 0.0
    tracker_heading: float = 0.0
    outlier_rate: float = 0.0
    outlier_size: float = 0.0
    drop_rate: float = 0.0
    exposure: float = 0.0  # s, the camera's exposure (motion blur)
    glare_rate: float = 0.0  # fraction of frames with a specular glint near the robot
    occlusion_rate: float = 0.0  # fraction of frames with a bubble or debris over the robot

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{f.name} must be finite and >= 0, got {v!r}")
        if not self.flow_time > 0:
            raise ValueError(f"flow_time must be > 0, got {self.flow_time!r}")
        for name in ("outlier_rate", "drop_rate", "glare_rate", "occlusion_rate"):
            if getattr(self, name) >= 1:
                raise ValueError(f"{name} must be below 1, got {getattr(self, name)!r}")

    @property
    def delayed(self) -> bool:
        """Whether the camera sees the past (frame age)."""
        return self.frame_age > 0 or self.frame_age_jitter > 0

    @property
    def field_error(self) -> bool:
        return self.coil_offset > 0 or self.coil_rotation > 0 or self.residual_field > 0

    @property
    def contact(self) -> bool:
        """Whether the sub-steps need the friction / flow / misalignment kernel."""
        return (
            self.friction > 0 or self.stiction > 0 or self.rotational_friction > 0
            or self.rotational_stiction > 0 or self.flow_sigma > 0
            or self.moment_misalignment > 0
        )  # fmt: skip

    @property
    def walls(self) -> bool:
        """Whether the walls have friction."""
        return self.wall_friction > 0 or self.wall_stiction > 0

    @property
    def tracking(self) -> bool:
        return (
            self.tracker_position > 0 or self.tracker_heading > 0 or self.outlier_rate > 0
            or self.drop_rate > 0
        )  # fmt: skip

    @property
    def image(self) -> bool:
        """Whether the camera's frames carry motion blur, glints or occluders."""
        return self.exposure > 0 or self.glare_rate > 0 or self.occlusion_rate > 0

    @property
    def ideal(self) -> bool:
        return not (
            self.delayed or self.field_error or self.contact or self.tracking
            or self.amplifier_tau > 0 or self.walls or self.image
        )  # fmt: skip

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}


IDEAL = Imperfections()


# --------------------------------------------------------------------------------------------
# per-plant draws


@dataclass(frozen=True)
class PlantDraw:
    """What one plant drew: each channel's placement error and residual field, the moment's
    misalignment (SI)."""

    coil_offsets: FloatArray  # (n_channels, 2) m
    coil_rotations: FloatArray  # (n_channels,) rad
    residual: NDArray[np.complex128]  # (n_channels, RESIDUAL_ORDERS), T/A at the unit radius
    misalignment: float  # rad

    def record(self, channel_names: tuple[str, ...]) -> dict[str, Any]:
        """JSON-able values for the recording's ``plant`` record (mm, deg)."""
        return {
            "coil_offsets_mm": {
                n: (self.coil_offsets[i] * 1e3).tolist() for i, n in enumerate(channel_names)
            },
            "coil_rotations_deg": {
                n: math.degrees(float(self.coil_rotations[i])) for i, n in enumerate(channel_names)
            },
            "moment_misalignment_deg": math.degrees(self.misalignment),
        }


def draw_plant(
    imperfections: Imperfections,
    n_channels: int,
    max_current: FloatArray,
    half_width: float,
    rng: np.random.Generator,
) -> PlantDraw:
    """The per-plant draws of ``imperfections`` (the module doc); ``max_current`` (n,) A
    scales the residual field, ``half_width`` (m) is the workspace's, over which its RMS is
    taken."""
    imp = imperfections
    offsets = rng.normal(0.0, 1.0, (n_channels, 2)) * imp.coil_offset
    rotations = rng.normal(0.0, 1.0, n_channels) * imp.coil_rotation
    raw = rng.normal(0.0, 1.0, (n_channels, RESIDUAL_ORDERS, 2))
    coeffs = raw[..., 0] + 1j * raw[..., 1]
    if imp.residual_field > 0:
        rms = residual_rms(coeffs, half_width)
        coeffs *= (imp.residual_field / np.asarray(max_current, dtype=np.float64) / rms)[:, None]
    else:
        coeffs[:] = 0.0
    misalignment = float(rng.normal(0.0, 1.0)) * imp.moment_misalignment
    return PlantDraw(offsets, rotations, coeffs, misalignment)


def harmonic_field(
    points: FloatArray, coeffs: NDArray[np.complex128], radius: float
) -> tuple[FloatArray, FloatArray]:
    """A smooth planar field and its gradient from ``coeffs`` (..., K) at ``points`` (P, 2) m.

    With ``w(z) = Σₙ cₙ (z/r)ⁿ`` (z = x + iy, n = 0 … K−1, analytic), ``Bx = Re w``,
    ``By = −Im w``: the Cauchy–Riemann equations make it divergence- and curl-free, as a
    field in a current-free region is. Its gradient follows from ``w'``:
    ``∂Bx/∂x = Re w'``, ``∂Bx/∂y = ∂By/∂x = −Im w'``, ``∂By/∂y = −Re w'``.

    Returns ``B`` (..., P, 2) and ``G`` (..., P, 2, 2), ``G[..., k, l] = ∂B_k/∂x_l``.
    """
    z = (points[:, 0] + 1j * points[:, 1]) / radius  # (P,)
    k = coeffs.shape[-1]
    powers = z[None, :] ** np.arange(k)[:, None]  # (K, P)
    w = coeffs @ powers  # (..., P)
    n = np.arange(1, k)
    dw = (coeffs[..., 1:] * n) @ powers[:-1] / radius
    B = np.stack([w.real, -w.imag], axis=-1)
    G = np.empty((*w.shape, 2, 2))
    G[..., 0, 0], G[..., 0, 1] = dw.real, -dw.imag
    G[..., 1, 0], G[..., 1, 1] = -dw.imag, -dw.real
    return B, G


def residual_rms(coeffs: NDArray[np.complex128], half_width: float, n: int = 41) -> FloatArray:
    """RMS of :func:`harmonic_field`'s |B| over the workspace square (per leading index)."""
    u = np.linspace(-half_width, half_width, n)
    X, Y = np.meshgrid(u, u, indexing="ij")
    B, _ = harmonic_field(np.stack([X.ravel(), Y.ravel()], -1), coeffs, half_width)
    rms = np.sqrt(np.mean(np.sum(B**2, axis=-1), axis=-1))
    return np.where(rms > 0, rms, 1.0)


def perturb_table(
    table: FloatArray,
    x0: float,
    y0: float,
    step: float,
    draw: PlantDraw,
    pivots: FloatArray,
    half_width: float,
) -> FloatArray:
    """A grid table (nx, ny, columns, 6) with each channel's map moved by its placement error
    about its pivot (n_channels, 2) and its residual field added (the module doc); a
    background column, if any, is left as it is."""
    nx, ny, _, _ = table.shape
    n_ch = draw.coil_offsets.shape[0]
    X, Y = np.meshgrid(x0 + step * np.arange(nx), y0 + step * np.arange(ny), indexing="ij")
    p = np.stack([X, Y], axis=-1).reshape(-1, 2)  # (P, 2)
    out = table.copy()
    for c in range(n_ch):
        a = float(draw.coil_rotations[c])
        d = draw.coil_offsets[c]
        if a != 0.0 or np.any(d != 0.0):
            R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
            q = (p - pivots[c] - d) @ R + pivots[c]  # Rᵀ(p − c − d) + c, row-wise
            v = _bilinear(table[:, :, c, :], x0, y0, step, q)  # (P, 6)
            B = v[:, :2] @ R.T
            G = R @ v[:, 2:].reshape(-1, 2, 2) @ R.T
            out[:, :, c, :2] = B.reshape(nx, ny, 2)
            out[:, :, c, 2:] = G.reshape(nx, ny, 4)
        if np.any(draw.residual[c] != 0):
            B, G = harmonic_field(p, draw.residual[c], half_width)
            out[:, :, c, :2] += B.reshape(nx, ny, 2)
            out[:, :, c, 2:] += G.reshape(nx, ny, 4)
    return np.ascontiguousarray(out)


def _bilinear(values: FloatArray, x0: float, y0: float, step: float, q: FloatArray) -> FloatArray:
    """Bilinear interpolation of ``values`` (nx, ny, m) at points ``q`` (P, 2), linear
    extrapolation from the edge cells (as :meth:`ChannelGrid.unit` reads)."""
    nx, ny = values.shape[:2]
    fx, fy = (q[:, 0] - x0) / step, (q[:, 1] - y0) / step
    i = np.clip(np.floor(fx).astype(int), 0, nx - 2)
    j = np.clip(np.floor(fy).astype(int), 0, ny - 2)
    tx, ty = (fx - i)[:, None], (fy - j)[:, None]
    return (1 - tx) * ((1 - ty) * values[i, j] + ty * values[i, j + 1]) + tx * (
        (1 - ty) * values[i + 1, j] + ty * values[i + 1, j + 1]
    )


# --------------------------------------------------------------------------------------------
# amplifiers


def amplifier_path(
    driven: FloatArray,
    target: FloatArray,
    tau: float,
    slew: FloatArray | float,
    h: float,
    n: int,
    path: Callable[..., FloatArray] | None = None,
) -> FloatArray:
    """The currents after each of ``n`` sub-steps of ``h`` s, (n, channels): a first-order lag
    of time constant ``tau`` s toward ``target``, its rate limited to ``slew`` A/s. ``path``:
    the recurrence (:func:`lag_path`, or the same compiled)."""
    decay = -math.expm1(-h / tau)  # 1 − e^(−h/τ)
    limit = np.broadcast_to(np.asarray(slew, dtype=np.float64) * h, driven.shape)
    step = lag_path if path is None else path
    return step(driven.astype(np.float64), np.asarray(target, np.float64), decay, limit, n)


def lag_path(
    current: FloatArray, target: FloatArray, decay: float, limit: FloatArray, n: int
) -> FloatArray:
    """:func:`amplifier_path`'s recurrence: ``n`` steps of ``I ← I + clip((I* − I)·decay,
    ±limit)`` from ``current``, (n, channels). Written for Numba too: the compiled plant runs
    this same definition compiled (:mod:`magrun.rigs.kernel`), to the same last bit."""
    out = np.empty((n, current.size))
    I = current
    for k in range(n):
        I = I + np.clip((target - I) * decay, -limit, limit)
        out[k] = I
    return out


def driven_midpoints(
    commanded: FloatArray, counts: NDArray[np.int64], decay: float, limit: FloatArray, ramp: bool
) -> FloatArray:
    """What the amplifiers drive over a run of ticks, sub-step by sub-step, from rest: tick k
    holds the previous tick's commanded currents (n, channels; zero before the first) for
    ``counts[k, 0]`` sub-steps (its latency), then its own for ``counts[k, 1]``. The
    amplifiers follow :func:`lag_path`'s recurrence (``decay`` 1 − e^(−h/τ), ``limit`` the
    slew limit times h, per channel) or, with ``ramp``, the slew ramp alone (after j
    sub-steps toward I*, within j·limit of where they started). Returns the currents at the
    middle of each sub-step, the mean of its two ends: (Σ counts, channels), tick by tick.
    Written for Numba too, as :func:`lag_path` (:mod:`magrun.rigs.kernel`)."""
    n, channels = commanded.shape
    total = 0
    for k in range(n):
        total += max(counts[k, 0], 0) + max(counts[k, 1], 0)
    out = np.empty((total, channels))
    now = np.zeros(channels)
    row = 0
    for k in range(n):
        for part in range(2):
            m = counts[k, part]
            if m <= 0:
                continue
            if part == 1:
                target = commanded[k]
            elif k > 0:
                target = commanded[k - 1]
            else:
                target = np.zeros(channels)
            before, gap = now, target - now
            for j in range(1, m + 1):
                if ramp:
                    reach = j * limit
                    after = np.where(np.abs(gap) <= reach, target, now + np.sign(gap) * reach)
                else:
                    after = before + np.clip((target - before) * decay, -limit, limit)
                out[row] = 0.5 * (before + after)
                before = after
                row += 1
            now = before
    return out


def ou_path(value: FloatArray, a: float, b: float, xi: FloatArray) -> FloatArray:
    """:class:`OrnsteinUhlenbeck`'s recurrence ``v ← v·a + b·ξₖ`` over the rows of ``xi``
    from ``value``, (n, dims). Written for Numba too, as :func:`lag_path`."""
    out = np.empty_like(xi)
    v = value
    for k in range(xi.shape[0]):
        v = v * a + b * xi[k]
        out[k] = v
    return out


# --------------------------------------------------------------------------------------------
# processes


class OrnsteinUhlenbeck:
    """A stationary Ornstein–Uhlenbeck process of ``dims`` components, exact on any step:
    ``v ← v e^(−h/T) + σ √(1 − e^(−2h/T)) ξ``, so its variance stays σ² and its
    autocorrelation at lag s is e^(−s/T); started from its stationary distribution."""

    def __init__(self, sigma: float, time: float, dims: int, rng: np.random.Generator) -> None:
        self.sigma, self.time, self.rng = sigma, time, rng
        self.value = rng.normal(0.0, 1.0, dims) * sigma

    def sample(self, n: int, h: float, path: Callable[..., FloatArray] | None = None) -> FloatArray:
        """The next ``n`` values at steps of ``h`` s, (n, dims); ``path``: the recurrence
        (:func:`ou_path`, or the same compiled)."""
        a = math.exp(-h / self.time)
        b = self.sigma * math.sqrt(-math.expm1(-2 * h / self.time))
        xi = self.rng.normal(0.0, 1.0, (n, self.value.size))
        out = (ou_path if path is None else path)(self.value, a, b, xi)
        if n:
            self.value = out[-1].copy()
        return out


class PoseHistory:
    """The plant's poses over the last ``span`` s, for the camera's frame age: ``at(t)``
    interpolates linearly between recorded poses (θ continuous, as the plant's state is);
    before the first record, the first pose."""

    def __init__(self, span: float) -> None:
        self.span = span
        self._t: list[FloatArray] = []
        self._p: list[FloatArray] = []

    def reset(self, t: float, pose: FloatArray) -> None:
        self._t = [np.array([t])]
        self._p = [np.asarray(pose, dtype=np.float64)[None, :3].copy()]

    def extend(self, times: ArrayLike, poses: ArrayLike) -> None:
        self._t.append(np.asarray(times, dtype=np.float64))
        self._p.append(np.asarray(poses, dtype=np.float64)[:, :3].copy())
        if len(self._t) > 8:  # keep what the span needs
            t = np.concatenate(self._t)
            p = np.concatenate(self._p)
            keep = t >= t[-1] - self.span
            keep[: max(0, int(np.argmax(keep)) - 1)] = False  # one before the span
            self._t, self._p = [t[keep]], [p[keep]]

    def at(self, t: float) -> FloatArray:
        times = np.concatenate(self._t)
        poses = np.concatenate(self._p)
        return np.array([np.interp(t, times, poses[:, i]) for i in range(3)])


class TrackingErrors:
    """The camera pipeline's own errors on each frame's pose (the module doc); seeded, so a
    trial's errors are reproducible; ``reset`` starts the sequence again."""

    def __init__(self, imperfections: Imperfections, seed: Any) -> None:
        self.imp = imperfections
        self.seed = seed
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def __call__(self, pose: FloatArray | None) -> FloatArray | None:
        """The pose the pipeline reports for a frame of ``pose`` (None: lost or dropped)."""
        imp = self.imp
        u = self.rng.random(2)
        xi = self.rng.normal(0.0, 1.0, 5)
        if pose is None or u[0] < imp.drop_rate:
            return None
        p = np.array(pose, dtype=np.float64)
        p[:2] += imp.tracker_position * xi[:2]
        p[2] += imp.tracker_heading * xi[2]
        if u[1] < imp.outlier_rate:
            p[:2] += imp.outlier_size * xi[3:5]
        return p


#: sub-exposures a motion-blurred frame averages
EXPOSURE_SAMPLES = 4


class ImageArtifacts:
    """What a real camera's frames show besides the robot, drawn per frame near the robot
    (where they hurt the tracker): with probability ``glare_rate`` a specular glint, a
    Gaussian spot (σ 1–3 px) that adds 120–255 grey levels to every channel; with
    probability ``occlusion_rate`` a bubble or a speck of debris, a disc of radius 0.5–1
    times the robot's radius that dims what is under it to 25–45 %. Each centre lies
    uniformly within ``reach`` px of the robot's image position. Its own random stream, so
    turning them on changes no other draw."""

    def __init__(self, imperfections: Imperfections, seed: Any, radius_px: float) -> None:
        self.imperfections, self.seed, self.radius_px = imperfections, seed, radius_px
        self.reset()

    def reset(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def _near(self, centre: FloatArray, reach: float) -> FloatArray:
        r, a = reach * math.sqrt(float(self.rng.uniform())), float(self.rng.uniform(0, 2 * math.pi))
        return np.asarray(centre, float) + r * np.array([math.cos(a), math.sin(a)])

    def __call__(
        self, frame: NDArray[np.uint8], centre: FloatArray, reach: float
    ) -> NDArray[np.uint8]:
        """``frame`` with this frame's artefacts; ``centre`` the robot's pixel (u, v)."""
        imp = self.imperfections
        u = self.rng.uniform(size=2)
        glint, speck = u[0] < imp.glare_rate, u[1] < imp.occlusion_rate
        if not (glint or speck):
            return frame
        h, w = frame.shape[:2]
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
        out = frame.astype(np.float32)
        if speck:
            c = self._near(centre, reach)
            radius = self.radius_px * float(self.rng.uniform(0.5, 1.0))
            dim = float(self.rng.uniform(0.25, 0.45))
            inside = (uu - c[0]) ** 2 + (vv - c[1]) ** 2 <= radius**2
            out[inside] *= np.float32(dim)
        if glint:
            c = self._near(centre, reach)
            sigma = float(self.rng.uniform(1.0, 3.0))
            peak = float(self.rng.uniform(120.0, 255.0))
            spot = peak * np.exp(-((uu - c[0]) ** 2 + (vv - c[1]) ** 2) / (2 * sigma**2))
            out += spot[..., None]
        return np.clip(out + 0.5, 0, 255).astype(np.uint8)


class ImperfectTracker:
    """A camera tracker whose poses then pass through :class:`TrackingErrors`."""

    def __init__(self, tracker: Any, errors: TrackingErrors) -> None:
        self.tracker, self.errors = tracker, errors

    def reset(self) -> None:
        self.tracker.reset()
        self.errors.reset()

    def __call__(self, frame: NDArray[np.uint8]) -> FloatArray | None:
        return self.errors(self.tracker(frame))


# --------------------------------------------------------------------------------------------
# the Python reference of the contact sub-step (the Numba kernel runs the same steps)


def contact_vector(imp: Imperfections, robot: Any, misalignment: float) -> FloatArray:
    """The kernel's contact parameters: misalignment (rad), kinetic and static friction
    force (N), kinetic and static friction torque (N m)."""
    return np.array(
        [
            misalignment,
            robot.drag_parallel * imp.friction,
            robot.drag_parallel * max(imp.stiction, imp.friction),
            robot.drag_rotation * imp.rotational_friction,
            robot.drag_rotation * max(imp.rotational_stiction, imp.rotational_friction),
        ]
    )


def contact_substep(
    state: tuple[float, ...],
    field: Callable[[float, float], tuple[Any, Any]],
    robot: Any,
    h: float,
    contact: FloatArray,
    flow: tuple[float, float],
) -> tuple[float, ...]:
    """One sub-step of ``h`` s with misalignment, floor friction and flow: the steps of
    :func:`magrun.rigs.kernel.contact_substeps`, in Python (the reference the
    kernel is tested against)."""
    alpha, fk, fs, tk, ts = (float(v) for v in contact)
    x, y, th, vx, vy, om = state
    B, G = field(x, y)
    bx, by = B[0], B[1]
    (g00, g01), (g10, g11) = G[0], G[1]
    d_a, d_b, d_r = robot.drag_parallel, robot.drag_perpendicular, robot.drag_rotation
    tau_a, tau_b, tau_r = robot.mass / d_a, robot.mass / d_b, robot.inertia / d_r
    h2 = h / 2
    ea, eb, er = math.exp(-h / tau_a), math.exp(-h / tau_b), math.exp(-h / tau_r)
    ka, kb, kr = tau_a * (1.0 - ea), tau_b * (1.0 - eb), tau_r * (1.0 - er)
    k2r = tau_r * (1.0 - math.exp(-h2 / tau_r))
    m = robot.moment
    c_, s_ = math.cos(th), math.sin(th)
    ua, ub = c_ * vx + s_ * vy, -s_ * vx + c_ * vy
    mx, my = m * math.cos(th + alpha), m * math.sin(th + alpha)
    tq = mx * by - my * bx
    ur = tq / d_r
    th_half = th + (ur * h2 + (om - ur) * k2r)
    mx, my = m * math.cos(th_half + alpha), m * math.sin(th_half + alpha)
    fx, fy, tq = mx * g00 + my * g10, mx * g01 + my * g11, mx * by - my * bx
    fa, fb = c_ * fx + s_ * fy, -s_ * fx + c_ * fy
    fa += d_a * (c_ * flow[0] + s_ * flow[1])  # the fluid's drag toward its velocity
    fb += d_b * (-s_ * flow[0] + c_ * flow[1])
    (fa, fb), stuck = _friction2(fa, fb, ua, ub, fk, fs)
    tq, spun = _friction1(tq, om, tk, ts)
    ua_ss, ub_ss, ur = fa / d_a, fb / d_b, tq / d_r
    ua1, sa = ua_ss + (ua - ua_ss) * ea, ua_ss * h + (ua - ua_ss) * ka
    ub1, sb = ub_ss + (ub - ub_ss) * eb, ub_ss * h + (ub - ub_ss) * kb
    om1, dth = ur + (om - ur) * er, ur * h + (om - ur) * kr
    if stuck:
        ua1, ub1, sa, sb = 0.0, 0.0, 0.0, 0.0
    elif fk > 0 and (ua != 0.0 or ub != 0.0) and ua1 * ua + ub1 * ub <= 0.0:
        ua1, ub1, sa, sb = 0.0, 0.0, 0.5 * h * ua, 0.5 * h * ub  # friction stopped it
    if spun:
        om1, dth = 0.0, 0.0
    elif tk > 0 and om != 0.0 and om1 * om <= 0.0:
        om1, dth = 0.0, 0.5 * h * om
    return (
        x + c_ * sa - s_ * sb, y + s_ * sa + c_ * sb, th + dth,
        c_ * ua1 - s_ * ub1, s_ * ua1 + c_ * ub1, om1,
    )  # fmt: skip


def _friction2(
    fa: float, fb: float, ua: float, ub: float, fk: float, fs: float
) -> tuple[tuple[float, float], bool]:
    """Translational Coulomb friction in body axes: the net force, and whether the body sticks."""
    speed = math.hypot(ua, ub)
    if speed > 0.0:
        return (fa - fk * ua / speed, fb - fk * ub / speed), False
    f = math.hypot(fa, fb)
    if f <= fs:
        return (0.0, 0.0), fs > 0.0 or f == 0.0
    return (fa - fk * fa / f, fb - fk * fb / f), False


def _friction1(tq: float, om: float, tk: float, ts: float) -> tuple[float, bool]:
    """Rotational Coulomb friction: the net torque, and whether the body sticks."""
    if om != 0.0:
        return tq - math.copysign(tk, om), False
    if abs(tq) <= ts:
        return 0.0, ts > 0.0 or tq == 0.0
    return tq - math.copysign(tk, tq), False
