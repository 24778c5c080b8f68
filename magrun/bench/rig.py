"""``magrun bench rig``: the hardware path on the rig emulator, and the watchdog."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from magrun.bench.machine import machine, ms


def serve_emulator(conn: Any) -> None:
    """A process's work: serve the simulated rig (``magrun rig-emulator``'s defaults) on a free
    loopback port, sending ``(host, port)`` through ``conn`` once it listens."""
    from magrun.rigs.emulator import RigEmulator
    from magrun.rigs.sim import SimRig
    from magrun.tracking.camera import CameraConfig

    rig = SimRig.default(robot="magnet", seed=0, camera=CameraConfig())
    emulator = RigEmulator(rig, "127.0.0.1", 0)
    conn.send(emulator.address)
    conn.close()
    emulator.serve_forever()


def bench_rig(
    protocol_file: str = "protocols/noise.yaml", stalls: int = 20, watchdog_ms: float = 100.0
) -> dict[str, Any]:
    """The hardware path on ``magrun rig-emulator`` (its own process, loopback TCP).

    The emulator (robot ``magnet``, seed 0, camera frames served) runs in a process of its own,
    as ``magrun rig-emulator`` does.

    1. A run: the protocol's ``--quick`` trials through the TCP driver, camera frames over
       the wire, the UNet tracking in the rig, real-time pacing. Figures per trial: latency
       (frame to the controller's acknowledgement of the tick's currents: median, p99, max),
       overrunning ticks, dropped frames, wall time against the trial's duration.
    2. The watchdog: ``stalls`` times, command 10 A on every coil, then stop commanding and
       poll ``STATUS`` every millisecond; the reaction is the wall time from the last
       command's acknowledgement to the first status ``watchdog``; then how long until the
       driven currents (the emulated amplifiers ramp at the slew limit) read zero.
    """
    import multiprocessing
    import tempfile

    from magrun.protocol import load_protocol
    from magrun.rigs.drivers import TcpLineDriver
    from magrun.runner import HardwareSpec, run_protocol

    ctx = multiprocessing.get_context("spawn")
    receive, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=serve_emulator, args=(send,), daemon=True)
    proc.start()
    send.close()
    if not receive.poll(120.0):
        proc.terminate()
        raise RuntimeError("the rig emulator did not start in 120 s")
    host, port = receive.recv()
    url = f"tcp://{host}:{port}"
    out: dict[str, Any] = {"benchmark": "rig", "machine": machine(), "emulator": url}
    try:
        protocol = load_protocol(protocol_file)
        with tempfile.TemporaryDirectory(prefix="magrun-rig-") as tmp:
            t0 = time.perf_counter()
            manifest = run_protocol(protocol, tmp, quick=True, rig=HardwareSpec(url))
            wall = time.perf_counter() - t0
        out["run"] = {
            "protocol": protocol.name,
            "wall_s": wall,
            "trials": [
                {
                    "path": e["path"],
                    "status": e["status"],
                    "error": e["error"],
                    "ticks": e.get("ticks"),
                    "wall_s": e["wall_s"],
                    "duration_s": protocol.trial_duration(True),
                    "rms_position_mm": e.get("rms_position_mm"),
                    **e.get("hardware", {}),
                }
                for e in manifest["trials"]
            ],
        }
        driver = TcpLineDriver(host, int(port))
        driver.open(watchdog_ms * 1e-3)
        reactions: list[float] = []
        to_zero: list[float] = []
        for _ in range(stalls):
            driver.conn.request("ARM", "OK")
            driver.send(np.full(len(driver.channel_names), 10.0))
            last = time.perf_counter()
            while True:
                fields = driver.conn.request("STATUS", "STATUS")
                now = time.perf_counter()
                if fields[0] == "watchdog":
                    reactions.append(now - last)
                    break
                time.sleep(0.001)
            while True:
                fields = driver.conn.request("STATUS", "STATUS")
                if not any(float(v) for v in fields[2:]):  # the driven currents
                    to_zero.append(time.perf_counter() - now)
                    break
                time.sleep(0.001)
            driver.conn.request("ARM", "OK")
            driver.send(np.zeros(len(driver.channel_names)))
            time.sleep(0.15)  # the amplifiers settle at zero
        driver.close()
        r = np.array(reactions)
        out["watchdog"] = {
            "timeout_ms": watchdog_ms,
            "stalls": stalls,
            "reaction_median_ms": ms(r, 50),
            "reaction_max_ms": float(r.max() * 1e3),
            "beyond_timeout_max_ms": float(r.max() * 1e3 - watchdog_ms),
            "ramp_to_zero_median_ms": ms(np.array(to_zero), 50),
            "ramp_to_zero_max_ms": float(max(to_zero) * 1e3),
        }
    finally:
        proc.terminate()
        proc.join(10)
    return out


def summary(result: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    lines = [
        f"{t['path']}: {t['status']}, {t['ticks']} ticks in {t['wall_s']:.2f} s"
        f" ({t['duration_s']:.2f} s of trial), latency median"
        f" {t.get('latency_median_ms', 0):.1f} ms, p99 {t.get('latency_p99_ms', 0):.1f} ms,"
        f" {t.get('overrun_ticks', 0)} overruns,"
        f" {t.get('dropped_frames', 0)} dropped frames"
        for t in result["run"]["trials"]
    ]
    w = result["watchdog"]
    lines.append(
        f"watchdog ({w['timeout_ms']:g} ms, {w['stalls']} stalls): reaction median"
        f" {w['reaction_median_ms']:.1f} ms, max {w['reaction_max_ms']:.1f} ms; currents at"
        f" zero {w['ramp_to_zero_median_ms']:.1f} ms later (median)"
    )
    return lines
