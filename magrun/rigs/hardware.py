"""The real coil rig behind the :class:`~magrun.rigs.base.Rig` interface.

    driver (plugin, magrun.rigs.drivers) ◄── apply: currents ── the loop
    camera (magrun.rigs.cameras) ──► frame ──► UNet tracker ──► observe: the actual pose

- **Actual pose**: the high-rate camera's frame, tracked by the UNet (as on the paper's rig;
  the loop's fluoroscopy mimic derives the controller's feedback from it). A dropped frame or
  a lost robot gives a NaN pose: the safety layer counts that as tracking lost.
- **Pacing**: ``observe`` starts a tick, ``advance(Δt)`` sleeps until the tick's start plus
  Δt, so the loop runs at the control rate in real time; a tick that overran is counted.
- **Latency**: from the start of a tick (the frame's capture) to the driver's acknowledgement
  of its currents; every tick's value is kept (:attr:`HardwareRig.latencies`) and recorded.
- **Limits are magrun's**: the currents are clamped to the protocol's coil system's limits,
  never to what the rig announces. On :meth:`~HardwareRig.connect` the rig's handshake is
  checked against the system before any current is sent: its channels must be the system's,
  and its announced limits finite, positive and no looser than the system's (a rig that
  announces 300 A on a 30 A system, or ``nan``, is refused with
  :class:`~magrun.rigs.drivers.RigRefused`); where the rig's are tighter, they are kept.
- **Safety**: ``apply`` clamps like every rig (|I| ≤ max, slew over the time since the last
  command, non-finite → 0 A); the amplifier controller enforces its own limits and a stall
  watchdog (``watchdog_s``) whatever happens here. A driver that fails raises
  :class:`~magrun.rigs.drivers.DriverError`: the trial ends as failed and the rig's watchdog
  makes the coils safe.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from magrun.rigs.base import FloatArray, Observation, Rig
from magrun.rigs.cameras import CameraSource
from magrun.rigs.drivers import CoilDriver, RigRefused, check_announced

if TYPE_CHECKING:
    from magrun.field.coils import CoilSystem
from magrun.robot import RobotParams
from magrun.safety import clamp_currents
from magrun.tracking.camera import Camera
from magrun.tracking.tracker import Tracker


class HardwareRig(Rig):
    """Coils through ``driver`` within ``coils``' limits, the robot seen by ``source`` through
    ``camera``'s calibration."""

    def __init__(
        self,
        driver: CoilDriver,
        source: CameraSource,
        camera: Camera,
        robot: RobotParams,
        coils: CoilSystem,
        watchdog_s: float = 0.1,
        tracker: Tracker | None = None,
    ) -> None:
        self.driver = driver
        self.coils = coils
        self.source = source
        self.camera = camera
        self.nominal_robot = robot
        self.watchdog_s = watchdog_s
        self.tracker = tracker if tracker is not None else Tracker.default(camera, robot)
        self.connected = False
        self._reset_stats()

    def _reset_stats(self) -> None:
        self.latencies: list[float] = []
        self.dropped_frames = 0
        self.lost_frames = 0
        self.overruns = 0
        self.ticks = 0
        self._t0 = time.perf_counter()
        self._tick_start = self._t0
        self._last_apply: float | None = None
        self._applied = np.zeros(len(getattr(self, "channel_names", ())))

    def connect(self) -> None:
        # the network's first runs now, not in the loop's first ticks; before the driver's
        # watchdog starts counting
        self.tracker.warm_up()
        self.driver.open(self.watchdog_s)
        try:
            self.channel_names, self.max_current, self.max_slew_rate = agreed_limits(
                self.driver, self.coils
            )
        except RigRefused:
            self.driver.close()
            raise
        try:
            self.source.open()
        except Exception:
            self.driver.close()
            raise
        self.connected = True

    def disconnect(self) -> None:
        if not self.connected:
            return
        self.connected = False
        try:
            self.driver.close()  # zeroes the currents if it still can
        finally:
            self.source.close()

    def reset(self, pose: ArrayLike) -> None:
        if not self.connected:
            self.connect()
        self.driver.zero()
        self.driver.place(pose)  # an emulator puts the robot there; a real rig cannot
        self.tracker.reset()
        self._reset_stats()

    def observe(self, frame: bool = True) -> Observation:
        self._tick_start = time.perf_counter()
        t = self._tick_start - self._t0
        got = self.source.read()
        if got is None:
            self.dropped_frames += 1
            return Observation(t, np.full(3, np.nan))
        _, image = got
        pose = self.tracker(image)
        if pose is None:
            self.lost_frames += 1
            pose = np.full(3, np.nan)
        return Observation(t, pose, frame=image if frame else None)

    def apply(self, currents: ArrayLike) -> FloatArray:
        now = time.perf_counter()
        since = self.watchdog_s if self._last_apply is None else now - self._last_apply
        req = clamp_currents(currents, self._applied, self.max_current, self.max_slew_rate * since)
        applied = self.driver.send(req)
        done = time.perf_counter()
        self.last_latency = done - self._tick_start
        self.latencies.append(self.last_latency)
        self._last_apply = done
        self._applied = applied
        return applied

    def advance(self, duration: float) -> None:
        self.ticks += 1
        deadline = self._tick_start + duration
        wait = deadline - time.perf_counter()
        if wait > 0:
            time.sleep(wait)
        else:
            self.overruns += 1

    def report(self) -> dict[str, float | int]:
        """Latency (median, p99, max, ms), overrunning ticks, dropped and lost frames."""
        lat = np.array(self.latencies) * 1e3 if self.latencies else np.full(1, np.nan)
        return {
            "latency_median_ms": float(np.median(lat)),
            "latency_p99_ms": float(np.percentile(lat, 99)),
            "latency_max_ms": float(lat.max()),
            "overrun_ticks": self.overruns,
            "dropped_frames": self.dropped_frames,
            "lost_frames": self.lost_frames,
        }


def agreed_limits(
    driver: CoilDriver, coils: CoilSystem
) -> tuple[tuple[str, ...], float | FloatArray, float | FloatArray]:
    """The channels and limits an opened ``driver`` is driven under: ``coils``' (the protocol's
    system), checked against what the rig announced. :class:`RigRefused` where the rig drives
    other channels, or announces a limit that is not finite and positive or is looser than the
    system's; where the rig's limit is tighter, the tighter one."""
    names = tuple(driver.channel_names)
    if names != coils.channel_names:
        raise RigRefused(
            f"the rig drives {', '.join(names)}, the protocol's system ({coils.name}) has "
            f"{', '.join(coils.channel_names)}: set the protocol's `system:` to the rig's coil "
            "system; no current was sent"
        )
    out: list[float | FloatArray] = []
    for what, unit, ours, theirs in (
        ("current limit", "A", coils.max_current, driver.max_current),
        ("slew limit", "A/s", coils.max_slew_rate, driver.max_slew_rate),
    ):
        check_announced(what, unit, theirs, names)  # a plugin driver's too: finite, > 0
        mine = np.broadcast_to(np.asarray(ours, dtype=np.float64), (len(names),))
        rig = np.broadcast_to(np.asarray(theirs, dtype=np.float64), (len(names),))
        looser = rig > mine
        if looser.any():
            i = int(np.argmax(looser))
            raise RigRefused(
                f"the rig announces a {what} of {float(rig[i])!r} {unit} on channel "
                f"{names[i]}: looser than the system's {float(mine[i])!r} {unit} "
                f"({coils.name}); a rig's own limits must be at least as tight as magrun's; "
                "no current was sent"
            )
        agreed = np.minimum(mine, rig)
        out.append(float(agreed[0]) if np.all(agreed == agreed[0]) else agreed.copy())
    return names, out[0], out[1]
