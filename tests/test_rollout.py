"""The replay's open-loop rollouts from many starts at once (magrun replay --model, magrun
identify) against the same computation one start at a time."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_emns import SYNTHETIC

from magrun.field.grid import ChannelGrid
from magrun.field.mpem import import_mpem
from magrun.field.system import load_system
from magrun.replay.identify import driven_currents, rollout_driven
from magrun.replay.model import (
    Segments,
    field_function,
    held_substeps,
    start_states,
    substep_each,
)
from magrun.rigs import kernel
from magrun.rigs.plant import amplifier_path, driven_midpoints
from magrun.robot import exponential_substep, load_robot

ROBOT = load_robot("magnet")


def _field(positions: np.ndarray, currents: np.ndarray) -> tuple[tuple, tuple]:
    """A smooth field of the position and the currents, (B, G) as the rollouts take them:
    B[k] and G[k][l] arrays over the starts (T, T/m)."""
    x, y = positions[:, 0], positions[:, 1]
    s = currents.sum(axis=1) * 1e-3
    d = (currents[:, 0] - currents[:, -1]) * 1e-3
    B = (s * (1 + 20 * x), d * (1 - 30 * y))
    G = ((20 * s, 0.2 * d + 5 * s * y), (0.2 * d + 5 * s * y, -30 * d))
    return B, G


@pytest.fixture(scope="module")
def grid() -> ChannelGrid:
    return ChannelGrid.load()


def test_units_at_many_positions_are_unit_at_each(grid: ChannelGrid) -> None:
    """Inside the grid, on its edges and beyond them (held at the edge cell)."""
    rng = np.random.default_rng(1)
    points = np.vstack([rng.uniform(-0.07, 0.07, (300, 2)), [[grid.x0, grid.y0], [0.0, 0.0]]])
    many = grid.units(points)
    one_by_one = np.stack([grid.unit(x, y) for x, y in points])
    scale = np.max(np.abs(one_by_one))
    np.testing.assert_allclose(many, one_by_one, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("compiled", [False, True])
@pytest.mark.parametrize("background", [False, True])
def test_the_replays_gridded_field_is_the_grids_own_read(
    background: bool, compiled: bool, tmp_path: Path
) -> None:
    """The replay's 'reference' field (NumPy, or the plant's bilinear read compiled) against
    the grid's own :meth:`~ChannelGrid.units` contracted with its inputs, each position with
    its own currents, inside the grid and beyond its edges (1e-12 of the largest value): on
    the paper's rig and on three imported coils with a background field, whose column is
    read at an input of 1 (with no current, the background's own field)."""
    if background:
        (tmp_path / "three.yaml").write_text(SYNTHETIC)
        system = load_system(
            import_mpem(tmp_path / "three.yaml", tmp_path / "s", 0.0, (0.0, 0.0), 10e-3)
        )
    else:
        system = load_system(None)
    grid = system.plant_maps
    assert grid.background == background
    rng = np.random.default_rng(7)
    n, channels = 300, system.coils.n_channels
    half = system.coils.workspace_half_width
    positions = rng.uniform(-1.3 * half, 1.3 * half, (n, 2))
    currents = rng.uniform(-5, 5, (n, channels))
    currents[:10] = 0.0
    B, G = field_function("reference", system, compiled)(positions, currents)
    rows = np.einsum("nc,nck->nk", grid.inputs(currents), grid.units(positions))
    got = np.column_stack([B.T, G.transpose(2, 0, 1).reshape(n, 4)])
    np.testing.assert_allclose(got, rows, rtol=0, atol=1e-12 * np.abs(rows).max())
    # with no current the field is the background's, or none
    assert (np.abs(got[:10]).max() > 0) == background


def test_a_substep_of_each_starts_own_length_is_each_starts_substep() -> None:
    """Starts of different lengths in one call: each as its own call with its own float
    length (to rounding), and a start of length 0 keeps its state exactly."""
    rng = np.random.default_rng(2)
    n = 7
    state = tuple(rng.normal(0, s, n) for s in (1e-3, 1e-3, 1.0, 1e-3, 1e-3, 0.5))
    positions = np.column_stack(state[:2])
    B, G = _field(positions, rng.uniform(-20, 20, (n, 8)))
    h = np.array([1e-3, 2e-3, 0.5e-3, 1e-3, 0.0, 3e-3, 1.5e-3])
    together = substep_each(state, B, G, ROBOT, h)
    for i in range(n):
        mine = tuple(s[i : i + 1] for s in state)
        Bi = tuple(b[i : i + 1] for b in B)
        Gi = tuple(tuple(g[i : i + 1] for g in row) for row in G)
        alone = mine if h[i] == 0 else exponential_substep(mine, Bi, Gi, ROBOT, float(h[i]))
        got = np.array([s[i] for s in together])
        want = np.array([float(s[0]) for s in alone])
        if h[i] == 0:
            assert np.array_equal(got, want)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("count", [0, 1, 7])
def test_held_substeps_compiled_are_the_python_substeps_repeated(count: int) -> None:
    """The compiled loop (magrun.rigs.kernel.held_substeps) against substep_each called
    ``count`` times with the same field: equal to rounding (1e-12 of each quantity's scale)
    for starts of different lengths, and a start of length 0 keeps its state exactly."""
    rng = np.random.default_rng(5)
    n = 9
    state = tuple(rng.normal(0, s, n) for s in (1e-3, 1e-3, 1.0, 1e-3, 1e-3, 0.5))
    B, G = _field(np.column_stack(state[:2]), rng.uniform(-20, 20, (n, 8)))
    h = np.array([1e-3, 2e-3, 0.5e-3, 1e-3, 0.0, 3e-3, 1.5e-3, 1e-3, 0.2e-3])
    want = state
    for _ in range(count):
        want = substep_each(want, B, G, ROBOT, h)
    got = held_substeps(state, B, G, ROBOT, h, count)
    for k, scale in enumerate((1e-3, 1e-3, 1.0, 1e-3, 1e-3, 0.5)):
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-12 * scale * max(count, 1))
        assert np.array_equal(got[k][4], state[k][4])
    if count:  # the sub-steps moved the states: the comparison above is not of two copies
        assert not np.allclose(got[3], state[3], rtol=0, atol=1e-9)


def _segments(n_ticks: int, horizon: int) -> Segments:
    rng = np.random.default_rng(3)
    t = np.arange(n_ticks) / 25.5
    actual = np.column_stack([2e-3 * np.sin(t), 1e-3 * np.cos(2 * t), 0.3 * t])
    length = np.full(n_ticks, 1 / 25.5) + rng.normal(0, 2e-4, n_ticks)  # measured ticks
    return Segments(
        actual=actual, currents=rng.uniform(-20, 20, (n_ticks, 8)),
        lag=np.full(n_ticks, 5e-3), length=length, dt=1 / 25.5,
        starts=np.arange(1, n_ticks - horizon), horizon=horizon,
    )  # fmt: skip


@pytest.mark.parametrize("uneven", [False, True])
def test_rollouts_from_every_start_at_once_are_each_starts_rollout(uneven: bool) -> None:
    """rollout_driven over all starts against the same rollout run from one start at a time
    (the field read every 5 sub-steps at the mean current of those sub-steps, each tick's
    own sub-step length): equal to rounding, with every tick the same number of sub-steps
    and with ticks of different numbers (a measured latency)."""
    seg = _segments(40, 3)
    rng = np.random.default_rng(4)
    sizes = rng.integers(36, 40, 40) if uneven else np.full(40, 38)
    driven = [rng.uniform(-20, 20, (m, 8)) for m in sizes]
    gains = np.linspace(0.95, 1.05, 8)
    positions, headings = rollout_driven(seg, driven, ROBOT, _field, gains)
    for i, start in enumerate(seg.starts):
        state = tuple(s[i : i + 1] for s in start_states(seg))
        for j in range(seg.horizon):
            ks = seg.starts + j
            k = start + j
            m = int(sizes[ks].min())  # all starts advance together by the shortest tick
            h = seg.length[k] / sizes[k]
            for lo in range(0, m, 5):
                held = driven[k][lo : min(lo + 5, m)].mean(axis=0)[None] * gains
                B, G = _field(np.column_stack(state[:2]), held)
                for _ in range(min(lo + 5, m) - lo):
                    state = tuple(exponential_substep(state, B, G, ROBOT, float(h)))
            np.testing.assert_allclose(
                positions[j, i], [state[0][0], state[1][0]], rtol=0, atol=1e-12
            )
            np.testing.assert_allclose(headings[j, i], state[2][0], rtol=0, atol=1e-9)


def _driven_tick_by_tick(
    commanded: np.ndarray, length: np.ndarray, latency: np.ndarray, slew: np.ndarray, tau: float
) -> list[np.ndarray]:
    """driven_currents' definition written out: each tick's two parts (the previous currents
    for its latency, then its own) through the plant's amplifier_path, or the slew ramp
    where tau is 0, and the mean of each sub-step's two ends."""
    h, now, out = 1e-3, np.zeros(commanded.shape[1]), []
    for k in range(len(commanded)):
        rows = []
        previous = commanded[k - 1] if k > 0 else np.zeros_like(now)
        for target, duration in ((previous, latency[k]), (commanded[k], length[k] - latency[k])):
            m = round(duration / h)
            if m <= 0:
                continue
            if tau > 0:
                path = amplifier_path(now, target, tau, slew, h, m)
            else:
                reach = np.arange(1, m + 1)[:, None] * (slew * h)
                gap = target - now
                path = np.where(np.abs(gap) <= reach, target, now + np.sign(gap) * reach)
            rows.append(0.5 * (np.vstack([now[None], path[:-1]]) + path))
            now = path[-1]
        out.append(np.vstack(rows) if rows else np.zeros((0, len(now))))
    return out


@pytest.mark.parametrize("tau", [0.0, 4e-3, 0.03])
def test_driven_currents_are_the_amplifier_path_tick_by_tick(tau: float) -> None:
    """The compiled loop over a recording's ticks against each tick's parts through the
    plant's own amplifier_path, bit for bit: measured tick lengths and latencies (one
    latency longer than its tick, one tick of no sub-step), slew limits per channel that
    bind on the larger steps; and the same loop in Python gives the same bits."""
    rng = np.random.default_rng(6)
    n, channels = 60, 8
    commanded = rng.uniform(-20, 20, (n, channels))
    length = 1 / 25.5 + rng.normal(0, 2e-3, n)
    latency = rng.uniform(0.0, 0.01, n)
    latency[7], length[9], latency[9] = length[7] + 0.002, 0.0002, 0.0
    slew = rng.uniform(200, 2000, channels)
    got = driven_currents(commanded, length, latency, slew, tau)
    want = _driven_tick_by_tick(commanded, length, latency, slew, tau)
    assert [len(g) for g in got] == [len(w) for w in want]
    assert len(got[9]) == 0
    assert len(got[7]) == round(latency[7] / 1e-3)
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w)
    counts = np.column_stack([np.round(latency / 1e-3), np.round((length - latency) / 1e-3)])
    counts = np.maximum(counts, 0).astype(np.int64)
    decay = -np.expm1(-1e-3 / tau) if tau else 0.0
    args = (commanded, counts, decay, slew * 1e-3, not tau)
    assert np.array_equal(driven_midpoints(*args), kernel.driven_midpoints(*args))
    assert np.any(np.abs(np.diff(np.vstack(got), axis=0)) >= slew * 1e-3 * (1 - 1e-12))
