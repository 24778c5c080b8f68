"""The safety layer between every controller and the coils, and the reasons a trial stops.

Every tick's currents pass through one :class:`SafetyLayer` on their way to the rig::

    controller.step ─► ControlOutput (currents, fault) ─► SafetyLayer.limit ─► rig.apply
                                                             ▲
    rig.observe, tracker ─► SafetyLayer.check(t, pose, tracked) (trips on a condition)

It guarantees, whatever the controller returns (tests/test_safety.py checks them with
hypothesis over random outputs, NaN and inf included):

- |I| ≤ ``max_current`` on every channel, and |I − I_prev| ≤ ``max_slew_rate`` · Δt;
- nothing non-finite reaches the rig: a non-finite request (or a controller's ``fault``)
  *trips* the layer, a **safe stop**;
- once tripped, the currents ramp to zero at the slew limit, tick by tick (the ramp is
  recorded like any tick), and stay there; the loop then ends the trial and records why.

It also trips when the tracker has lost the robot for longer than ``lost_timeout_s`` (on a
rig the controller then steers blind), when the robot leaves the allowed workspace (the
protocol's square plus ``workspace_margin_m``), and on request (SIGINT / SIGTERM, through
:meth:`trip`). The first reason is kept: :attr:`reason`, with the trial time :attr:`tripped_at`.

A stalled control loop cannot be caught from inside the loop: that is the job of the
watchdog on the amplifier controller's side of a hardware rig (:mod:`magrun.rigs.wire`,
armed with the protocol's ``safety.stall_timeout_ms``), which ramps the currents to zero when
no command arrives in time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


#: a limit: one value for every channel, or one per channel
Limit = float | FloatArray


def clamp_currents(
    requested: ArrayLike, previous: ArrayLike, max_current: Limit, max_change: Limit
) -> FloatArray:
    """The currents closest to ``requested`` within the limits.

    The limits are |I| ≤ max_current and |I − previous| ≤ max_change (a slew limit over one
    period), each one value or one per channel. Non-finite requests are replaced by 0 A (then
    limited like any other request), so a NaN from a failed solve can never reach an
    amplifier. All values in A.
    """
    req = np.asarray(requested, dtype=np.float64)
    prev = np.asarray(previous, dtype=np.float64)
    req = np.where(np.isfinite(req), req, 0.0)
    lo = np.maximum(-max_current, prev - max_change)
    hi = np.minimum(max_current, prev + max_change)
    # previous may itself sit outside a reduced max_current: then lo > hi, go toward the limit
    return np.clip(req, lo, np.maximum(lo, hi))


@dataclass(frozen=True)
class SafetyConfig:
    """When a trial stops safely (SI units; ``None`` switches a check off)."""

    #: tracking lost (the camera tracker returned no pose) for longer than this, s
    lost_timeout_s: float | None = 1.0
    #: how far the robot may go beyond the workspace square before the trial stops, m
    workspace_margin_m: float | None = 0.0


class SafetyLayer:
    """Current limits, slew limit and safe stop for one rig's channels.

    Parameters
    ----------
    n_channels : int
        Current channels.
    max_current, max_slew_rate : float
        Limits, A and A/s.
    dt : float
        Control period, s (the slew limit allows ``max_slew_rate · dt`` per tick).
    config : SafetyConfig
        The stop conditions.
    workspace_half_width : float, optional
        The allowed square |x|, |y| ≤ half width, m (``None``: no workspace check).
    """

    def __init__(
        self,
        n_channels: int,
        max_current: Limit,
        max_slew_rate: Limit,
        dt: float,
        config: SafetyConfig | None = None,
        workspace_half_width: float | None = None,
    ) -> None:
        self.n_channels = n_channels
        self.max_current = max_current
        self.max_change = max_slew_rate * dt
        self.config = config or SafetyConfig()
        self.workspace_half_width = workspace_half_width
        self.reset()

    def reset(self) -> None:
        """A new trial: currents at 0 A, not tripped."""
        self.applied = np.zeros(self.n_channels)
        self.reason = ""
        self.tripped_at: float | None = None
        self._lost_since: float | None = None

    @property
    def tripped(self) -> bool:
        return bool(self.reason)

    @property
    def at_rest(self) -> bool:
        """Tripped and every current at zero: the trial may end."""
        return self.tripped and not np.any(self.applied)

    def trip(self, reason: str, t: float | None = None) -> None:
        """Stop safely from now on; the first reason given is the one kept."""
        if not self.reason:
            self.reason = reason
            self.tripped_at = t

    def check(self, t: float, pose: ArrayLike, tracked: bool | None = None) -> None:
        """Trip on the tick's conditions: ``pose`` (x, y, θ) the actual pose (NaN: the rig
        lost the robot), ``tracked`` whether the tracker found the robot in this tick's frame
        (``None``: no frame this tick)."""
        cfg = self.config
        p = np.asarray(pose, dtype=np.float64)
        if not np.all(np.isfinite(p)):
            tracked = False  # a rig that tracks itself reports a lost robot as NaN
        half = self.workspace_half_width
        if half is not None and cfg.workspace_margin_m is not None and np.all(np.isfinite(p)):
            limit = half + cfg.workspace_margin_m
            if abs(p[0]) > limit or abs(p[1]) > limit:
                self.trip(
                    f"the robot left the workspace at ({p[0] * 1e3:.1f}, {p[1] * 1e3:.1f}) mm"
                    f" (allowed: |x|, |y| ≤ {limit * 1e3:.1f} mm)",
                    t,
                )
        if tracked is True:
            self._lost_since = None
        elif tracked is False:
            if self._lost_since is None:
                self._lost_since = t
            lost = t - self._lost_since
            if cfg.lost_timeout_s is not None and lost > cfg.lost_timeout_s:
                self.trip(f"tracking lost for {lost:.2f} s (limit {cfg.lost_timeout_s:g} s)", t)

    def limit(self, requested: ArrayLike, fault: str = "", t: float | None = None) -> FloatArray:
        """The currents to send: ``requested`` within the limits, or the ramp to zero."""
        req = np.asarray(requested, dtype=np.float64)
        if req.shape != (self.n_channels,):
            self.trip(f"the controller sent {req.shape} currents for {self.n_channels}", t)
        elif fault:
            self.trip(fault, t)
        elif not np.all(np.isfinite(req)):
            bad = ", ".join(str(v) for v in req[~np.isfinite(req)][:3])
            self.trip(f"non-finite currents from the controller ({bad})", t)
        target = np.zeros(self.n_channels) if self.tripped else req
        self.applied = clamp_currents(target, self.applied, self.max_current, self.max_change)
        return self.applied.copy()

    def ticks_to_rest(self) -> int:
        """Ticks the ramp to zero takes from the currents now."""
        change = np.broadcast_to(np.asarray(self.max_change, dtype=np.float64), self.applied.shape)
        if not np.all(change > 0):
            return 0
        steps = np.abs(self.applied) / change
        return math.ceil(float(np.max(steps, initial=0.0)) - 1e-12)
