"""The simulated plant's sub-step loop compiled with Numba: the rig's inner loop in machine code.

A campaign integrates millions of 1 ms plant sub-steps, each a few dozen floating-point
operations: in Python the interpreter's overhead dominates them (BENCHMARKS.md has the
figures). :func:`free_substeps` runs :func:`magrun.robot.exponential_substep`
(one field read per sub-step, as the Python plant's :func:`magrun.robot.discrete_step` calls
do) on the field read bilinearly from the :class:`~magrun.field.grid.ChannelGrid`'s table,
written out in scalar form. It stops after any sub-step that leaves the wall broad phase's
clear disc, so that the broad phase (Python, :class:`~magrun.rigs.sim.SimRig`) and
:func:`resolve_capsule` (:meth:`magrun.scene.Walls.resolve_capsule` compiled) run exactly
where the Python plant runs them, and then resumes. ``SimRig(compiled=False)``, the Python
plant, is the reference both are tested against (1e-12).

The replay's identification (:mod:`magrun.replay.identify`) runs the same sub-step over many
starts at once (:func:`held_substeps`), the grid's read for any positions (:func:`grid_rows`)
and the amplifiers over a recording's ticks (:data:`driven_midpoints`).

Numba caches the machine code on disk: under ``<magrun cache>/numba`` (see
:func:`magrun.compiled.cache_dir`) unless ``NUMBA_CACHE_DIR`` is set. The first
import on a machine compiles it (a few seconds); later processes load it.
"""

from __future__ import annotations

import math
import os

import numpy as np
from numpy.typing import NDArray

from magrun.compiled import cache_dir
from magrun.rigs import plant
from magrun.robot import relaxation

os.environ.setdefault("NUMBA_CACHE_DIR", str(cache_dir() / "numba"))

from numba import njit  # after the cache folder is chosen

FloatArray = NDArray[np.float64]

#: layout of the ``robot`` vector :func:`free_substeps` takes
ROBOT_FIELDS = ("moment", "drag_parallel", "drag_perpendicular", "drag_rotation", "mass", "inertia")


#: :func:`magrun.robot.relaxation` compiled: the Python plant's constants, the same definition
_relaxation = njit(cache=True, nogil=True, inline="always")(relaxation)
#: the amplifiers' lag and the flow's Ornstein–Uhlenbeck recurrence compiled, the same
#: definitions (:func:`magrun.rigs.plant.lag_path`, :func:`magrun.rigs.plant.ou_path`): each
#: a loop over a tick's sub-steps, which costs the interpreter more than its arithmetic
lag_path = njit(cache=True, nogil=True)(plant.lag_path)
ou_path = njit(cache=True, nogil=True)(plant.ou_path)
#: what the amplifiers drive over a recording's ticks (:func:`magrun.rigs.plant.
#: driven_midpoints`), compiled: the replay's identification of the amplifiers' lag
driven_midpoints = njit(cache=True, nogil=True)(plant.driven_midpoints)


@njit(cache=True, nogil=True, inline="always")
def _decays(robot: FloatArray, h: float) -> tuple[float, ...]:
    """The exponential integrator's constants over a sub-step of ``h`` for the robot vector
    (:data:`ROBOT_FIELDS`): h/2, the velocity decays and their integrals."""
    d_a, d_b, d_r = robot[1], robot[2], robot[3]
    tau_a, tau_b, tau_r = robot[4] / d_a, robot[4] / d_b, robot[5] / d_r
    h2 = h / 2
    ea, ka = _relaxation(tau_a, h)
    eb, kb = _relaxation(tau_b, h)
    er, kr = _relaxation(tau_r, h)
    _, k2r = _relaxation(tau_r, h2)
    return h2, ea, eb, er, ka, kb, kr, k2r


@njit(cache=True, nogil=True, inline="always")
def _field_at(
    x: float, y: float, drives: FloatArray, k: int, table: FloatArray, x0: float, y0: float,
    step: float, v: FloatArray,
) -> tuple[float, float, float, float, float, float]:  # fmt: skip
    """The field (Bx, By) and gradient (g00, g01, g10, g11) at (x, y) for sub-step k's
    currents: the grid cell's corners (00, 01, 10, 11) contracted with the currents, then
    read bilinearly (``v``: a scratch array of 24)."""
    n_ch = drives.shape[1]
    i_max, j_max = table.shape[0] - 2, table.shape[1] - 2
    fx_, fy_ = (x - x0) / step, (y - y0) / step
    i = min(max(math.floor(fx_), 0), i_max)
    j = min(max(math.floor(fy_), 0), j_max)
    for q in range(24):
        a, b, f = (q // 12), (q // 6) % 2, q % 6
        acc = 0.0
        for c in range(n_ch):
            acc += drives[k, c] * table[i + a, j + b, c, f]
        v[q] = acc
    tx, ty = fx_ - i, fy_ - j
    sx, sy = 1 - tx, 1 - ty
    bx = sx * (sy * v[0] + ty * v[6]) + tx * (sy * v[12] + ty * v[18])
    by = sx * (sy * v[1] + ty * v[7]) + tx * (sy * v[13] + ty * v[19])
    g00 = sx * (sy * v[2] + ty * v[8]) + tx * (sy * v[14] + ty * v[20])
    g01 = sx * (sy * v[3] + ty * v[9]) + tx * (sy * v[15] + ty * v[21])
    g10 = sx * (sy * v[4] + ty * v[10]) + tx * (sy * v[16] + ty * v[22])
    g11 = sx * (sy * v[5] + ty * v[11]) + tx * (sy * v[17] + ty * v[23])
    return bx, by, g00, g01, g10, g11


@njit(cache=True, nogil=True, inline="always")
def _substep(
    motion: tuple[float, float, float, float, float, float],
    field: tuple[float, float, float, float, float, float],
    robot: FloatArray,
    h: float,
    decays: tuple[float, ...],
) -> tuple[float, float, float, float, float, float]:
    """One sub-step of ``h`` s from ``(x, y, θ, vx, vy, ω)`` under the field ``(Bx, By, g00,
    g01, g10, g11)`` held (``g_kl = ∂B_k/∂x_l``): :func:`magrun.robot.exponential_substep` in
    scalar form, ``decays`` its constants (:func:`_decays` of ``h``). The one compiled
    sub-step of the plant (:func:`free_substeps`) and the replay (:func:`held_substeps`)."""
    x, y, th, vx, vy, om = motion
    bx, by, g00, g01, g10, g11 = field
    moment, d_a, d_b, d_r = robot[0], robot[1], robot[2], robot[3]
    h2, ea, eb, er, ka, kb, kr, k2r = decays
    c_, s_ = math.cos(th), math.sin(th)
    ua, ub = c_ * vx + s_ * vy, -s_ * vx + c_ * vy
    # the start wrench, a half step to the mid-step orientation
    mx, my = moment * c_, moment * s_
    tq = mx * by - my * bx
    ur = tq / d_r
    th_half = th + (ur * h2 + (om - ur) * k2r)
    # the wrench at that orientation drives the full step from the start
    mx, my = moment * math.cos(th_half), moment * math.sin(th_half)
    fx, fy, tq = mx * g00 + my * g10, mx * g01 + my * g11, mx * by - my * bx
    fa, fb = c_ * fx + s_ * fy, -s_ * fx + c_ * fy
    ua_ss, ub_ss, ur = fa / d_a, fb / d_b, tq / d_r
    ua1, sa = ua_ss + (ua - ua_ss) * ea, ua_ss * h + (ua - ua_ss) * ka
    ub1, sb = ub_ss + (ub - ub_ss) * eb, ub_ss * h + (ub - ub_ss) * kb
    om1, dth = ur + (om - ur) * er, ur * h + (om - ur) * kr
    x, y, th = x + c_ * sa - s_ * sb, y + s_ * sa + c_ * sb, th + dth
    vx, vy, om = c_ * ua1 - s_ * ub1, s_ * ua1 + c_ * ub1, om1
    return x, y, th, vx, vy, om


@njit(cache=True, nogil=True)
def free_substeps(
    state: FloatArray,
    drives: FloatArray,
    start: int,
    table: FloatArray,
    x0: float,
    y0: float,
    step: float,
    robot: FloatArray,
    h: float,
    cx: float,
    cy: float,
    slack: float,
    trace: FloatArray,
) -> int:
    """Integrate sub-steps ``start``, ``start + 1``, … of ``h`` s in place on ``state``.

    Parameters
    ----------
    state : (6,) float64
        ``(x, y, θ, vx, vy, ω)`` in m, rad, m/s, rad/s; updated in place.
    drives : (n, channels) float64
        Each sub-step's effective currents (A, coil gains applied), held over the sub-step.
    table : (nx, ny, channels, 6) float64
        :attr:`ChannelGrid.table` (field and gradient per ampere); ``x0, y0, step`` its grid.
    robot : (6,) float64
        The true robot, :data:`ROBOT_FIELDS`.
    cx, cy, slack : float
        The broad phase's clear disc: after a sub-step that ends ``≥ slack`` from ``(cx, cy)``
        the walls may be in reach.
    trace : (n, 3) or (0, 3) float64
        Where it has n rows, row k receives the pose after sub-step k (the camera's frame
        age reads the past from it); with none, nothing is kept.

    Returns
    -------
    int
        The number of sub-steps done so far (``n`` when all are; less when the last one left
        the clear disc and the caller must resolve contacts before resuming there).
    """
    n = drives.shape[0]
    decays = _decays(robot, h)
    x, y, th, vx, vy, om = state[0], state[1], state[2], state[3], state[4], state[5]
    v = np.empty(24)
    k = start
    while k < n:
        field = _field_at(x, y, drives, k, table, x0, y0, step, v)
        x, y, th, vx, vy, om = _substep((x, y, th, vx, vy, om), field, robot, h, decays)
        if trace.shape[0] > 0:
            trace[k, 0], trace[k, 1], trace[k, 2] = x, y, th
        k += 1
        if math.hypot(x - cx, y - cy) >= slack:
            break
    state[0], state[1], state[2], state[3], state[4], state[5] = x, y, th, vx, vy, om
    return k


@njit(cache=True, nogil=True)
def grid_rows(
    positions: FloatArray, inputs: FloatArray, table: FloatArray, x0: float, y0: float,
    step: float,
) -> FloatArray:  # fmt: skip
    """The field and gradient ``(Bx, By, g00, g01, g10, g11)`` at each of ``positions``
    (n, 2) m for its own ``inputs`` (n, columns: the currents, A, and a 1 for a background
    column), read from a :class:`~magrun.field.grid.ChannelGrid` table as the plant reads it
    (:func:`_field_at`): (n, 6), T and T/m."""
    n = positions.shape[0]
    out = np.empty((n, 6))
    v = np.empty(24)
    for k in range(n):
        row = _field_at(positions[k, 0], positions[k, 1], inputs, k, table, x0, y0, step, v)
        for f in range(6):
            out[k, f] = row[f]
    return out


@njit(cache=True, nogil=True)
def held_substeps(
    state: FloatArray, B: FloatArray, G: FloatArray, robot: FloatArray, h: FloatArray,
    count: int,
) -> None:  # fmt: skip
    """``count`` sub-steps for each of n states at once, each of its own length and under its
    own field held throughout: the replay's open-loop rollouts from many starts
    (:func:`magrun.replay.model.held_substeps`), the plant's sub-step (:func:`_substep`).

    Parameters
    ----------
    state : (6, n) float64
        Rows ``(x, y, θ, vx, vy, ω)`` in m, rad, m/s, rad/s; updated in place.
    B : (2, n) float64
        The field ``(Bx, By)``, T, at each state.
    G : (2, 2, n) float64
        The gradient, ``G[k, l] = ∂B_k/∂x_l``, T/m.
    robot : (6,) float64
        :data:`ROBOT_FIELDS`.
    h : (n,) float64
        Each state's sub-step, s; a state with ``h ≤ 0`` is left as it is.
    """
    for i in range(state.shape[1]):
        hi = h[i]
        if not hi > 0:
            continue
        decays = _decays(robot, hi)
        field = (B[0, i], B[1, i], G[0, 0, i], G[0, 1, i], G[1, 0, i], G[1, 1, i])
        x, y, th = state[0, i], state[1, i], state[2, i]
        vx, vy, om = state[3, i], state[4, i], state[5, i]
        for _ in range(count):
            x, y, th, vx, vy, om = _substep((x, y, th, vx, vy, om), field, robot, hi, decays)
        state[0, i], state[1, i], state[2, i] = x, y, th
        state[3, i], state[4, i], state[5, i] = vx, vy, om


@njit(cache=True, nogil=True)
def contact_substeps(
    state: FloatArray,
    drives: FloatArray,
    start: int,
    table: FloatArray,
    x0: float,
    y0: float,
    step: float,
    robot: FloatArray,
    h: float,
    cx: float,
    cy: float,
    slack: float,
    trace: FloatArray,
    contact: FloatArray,
    flows: FloatArray,
) -> int:
    """:func:`free_substeps` with the plant's contact terms (:mod:`magrun.rigs.plant`): the
    moment ``contact[0]`` rad off the body axis, floor friction (kinetic and static force
    ``contact[1:3]`` N, torque ``contact[3:5]`` N m) and the fluid's velocity ``flows[k]``
    (m/s) at sub-step k. The same steps as :func:`magrun.rigs.plant.contact_substep`, which
    the tests compare it with."""
    n = drives.shape[0]
    moment, d_a, d_b, d_r = robot[0], robot[1], robot[2], robot[3]
    h2, ea, eb, er, ka, kb, kr, k2r = _decays(robot, h)
    alpha, fk, fs, tk, ts = contact[0], contact[1], contact[2], contact[3], contact[4]
    x, y, th, vx, vy, om = state[0], state[1], state[2], state[3], state[4], state[5]
    v = np.empty(24)
    k = start
    while k < n:
        bx, by, g00, g01, g10, g11 = _field_at(x, y, drives, k, table, x0, y0, step, v)
        c_, s_ = math.cos(th), math.sin(th)
        ua, ub = c_ * vx + s_ * vy, -s_ * vx + c_ * vy
        mx, my = moment * math.cos(th + alpha), moment * math.sin(th + alpha)
        tq = mx * by - my * bx
        ur = tq / d_r
        th_half = th + (ur * h2 + (om - ur) * k2r)
        mx, my = moment * math.cos(th_half + alpha), moment * math.sin(th_half + alpha)
        fx, fy, tq = mx * g00 + my * g10, mx * g01 + my * g11, mx * by - my * bx
        fa, fb = c_ * fx + s_ * fy, -s_ * fx + c_ * fy
        if flows.shape[0] > 0:
            fa += d_a * (c_ * flows[k, 0] + s_ * flows[k, 1])
            fb += d_b * (-s_ * flows[k, 0] + c_ * flows[k, 1])
        # floor friction, translation
        stuck = False
        speed = math.hypot(ua, ub)
        if speed > 0.0:
            fa, fb = fa - fk * ua / speed, fb - fk * ub / speed
        else:
            fn = math.hypot(fa, fb)
            if fn <= fs:
                fa, fb = 0.0, 0.0
                stuck = fs > 0.0 or fn == 0.0
            else:
                fa, fb = fa - fk * fa / fn, fb - fk * fb / fn
        # and rotation
        spun = False
        if om != 0.0:
            tq = tq - math.copysign(tk, om)
        elif abs(tq) <= ts:
            tq = 0.0
            spun = ts > 0.0 or tq == 0.0
        else:
            tq = tq - math.copysign(tk, tq)
        ua_ss, ub_ss, ur = fa / d_a, fb / d_b, tq / d_r
        ua1, sa = ua_ss + (ua - ua_ss) * ea, ua_ss * h + (ua - ua_ss) * ka
        ub1, sb = ub_ss + (ub - ub_ss) * eb, ub_ss * h + (ub - ub_ss) * kb
        om1, dth = ur + (om - ur) * er, ur * h + (om - ur) * kr
        if stuck:
            ua1, ub1, sa, sb = 0.0, 0.0, 0.0, 0.0
        elif fk > 0 and (ua != 0.0 or ub != 0.0) and ua1 * ua + ub1 * ub <= 0.0:
            ua1, ub1, sa, sb = 0.0, 0.0, 0.5 * h * ua, 0.5 * h * ub
        if spun:
            om1, dth = 0.0, 0.0
        elif tk > 0 and om != 0.0 and om1 * om <= 0.0:
            om1, dth = 0.0, 0.5 * h * om
        x, y, th = x + c_ * sa - s_ * sb, y + s_ * sa + c_ * sb, th + dth
        vx, vy, om = c_ * ua1 - s_ * ub1, s_ * ua1 + c_ * ub1, om1
        if trace.shape[0] > 0:
            trace[k, 0], trace[k, 1], trace[k, 2] = x, y, th
        k += 1
        if math.hypot(x - cx, y - cy) >= slack:
            break
    state[0], state[1], state[2], state[3], state[4], state[5] = x, y, th, vx, vy, om
    return k


@njit(cache=True, nogil=True)
def resolve_capsule(
    state: FloatArray,
    segments: FloatArray,
    disks: FloatArray,
    radius: float,
    translational_drag: float,
    rotational_drag: float,
    iterations: int,
    mu_k: float = 0.0,
    mu_s: float = 0.0,
    h: float = 0.0,
) -> bool:
    """:meth:`magrun.scene.Walls.resolve_capsule` compiled, on ``state`` (6,) in place.

    ``disks`` are the disks' offsets along the axis (m), ``np.linspace(-half_axis, half_axis,
    n_disk)`` as the reference builds them. Same steps as the reference (which the tests
    compare to 1e-12); returns whether the body touched a wall.
    """
    n_seg, m = segments.shape[0], disks.shape[0]
    if n_seg == 0:
        return False
    x, y, th, vx, vy, om = state[0], state[1], state[2], state[3], state[4], state[5]
    dist = np.empty((m, n_seg))
    dxy = np.empty((m, n_seg, 2))
    touched = False
    for _ in range(iterations):
        ax, ay = math.cos(th), math.sin(th)
        best, bi, bj = math.inf, 0, 0
        for p in range(m):
            px, py = x + disks[p] * ax, y + disks[p] * ay
            for q in range(n_seg):
                a0, a1 = segments[q, 0, 0], segments[q, 0, 1]
                e0, e1 = segments[q, 1, 0] - a0, segments[q, 1, 1] - a1
                r0, r1 = px - a0, py - a1
                u = (r0 * e0 + r1 * e1) / (e0 * e0 + e1 * e1)
                u = min(max(u, 0.0), 1.0)
                d0, d1 = r0 - u * e0, r1 - u * e1
                dd = math.hypot(d0, d1)
                dist[p, q], dxy[p, q, 0], dxy[p, q, 1] = dd, d0, d1
                if dd < best:
                    best, bi, bj = dd, p, q
        if best >= radius * (1 - 1e-9):
            break
        touched = True
        if best > 1e-12:
            nx, ny = dxy[bi, bj, 0] / best, dxy[bi, bj, 1] / best
        else:  # centre on the wall line: push along the wall's normal toward the body
            e0 = segments[bj, 1, 0] - segments[bj, 0, 0]
            e1 = segments[bj, 1, 1] - segments[bj, 0, 1]
            norm = math.sqrt(e0 * e0 + e1 * e1)
            nx, ny = -e1 / norm, e0 / norm
        # a flat side resting on the wall: act at the middle of the equally deep disks
        total, count = 0.0, 0
        for p in range(m):
            if dist[p, bj] <= best + 1e-3 * radius:
                total += disks[p]
                count += 1
        mid = total / count
        rx, ry = mid * ax, mid * ay
        rxn = rx * ny - ry * nx
        w = 1.0 / translational_drag + rxn * rxn / rotational_drag
        depth = radius - best
        x += nx * depth / (translational_drag * w)
        y += ny * depth / (translational_drag * w)
        th += rxn * depth / (rotational_drag * w)
        # velocity of the contact point along n
        vc = vx * nx + vy * ny + om * rxn
        if vc < 0:
            impulse = -vc / w
            vx += nx * impulse / translational_drag
            vy += ny * impulse / translational_drag
            om += rxn * impulse / rotational_drag
        if mu_k > 0 or mu_s > 0:  # Coulomb friction along the wall (the reference's doc)
            tx, ty = -ny, nx
            rxt = rx * ty - ry * tx
            slide = (vx * tx + vy * ty + om * rxt) * h
            if abs(slide) <= mu_s * depth:
                cut = -slide
            else:
                cut = -math.copysign(min(mu_k * depth, abs(slide)), slide)
            if cut != 0.0:
                wt = 1.0 / translational_drag + rxt * rxt / rotational_drag
                x += tx * cut / (translational_drag * wt)
                y += ty * cut / (translational_drag * wt)
                th += rxt * cut / (rotational_drag * wt)
                dv = cut / (h * wt)
                vx += tx * dv / translational_drag
                vy += ty * dv / translational_drag
                om += rxt * dv / rotational_drag
    state[0], state[1], state[2], state[3], state[4], state[5] = x, y, th, vx, vy, om
    return touched


def _load_numba() -> None:
    """Numba's first call in a process imports its compiler's modules and reads its caches:
    0.6–1.7 s on the 2-core development machine. Made here, when the simulated rig imports
    this module, with one of the plant's own functions at its real signature (its cached code
    or a compile of it), so that no tick, and no first reply of an emulated rig, waits for it
    (the other functions then load their cached code in milliseconds)."""
    ou_path(np.zeros(1), 0.0, 0.0, np.zeros((1, 1)))


_load_numba()
