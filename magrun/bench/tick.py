"""``magrun bench tick``: the time per control tick of each stage of a camera trial."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from magrun.bench.machine import machine, ms

STAGES = ("render", "track", "control", "prepare", "plant")


def _timed(fn: Callable[..., Any], into: list[float]) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            into.append(time.perf_counter() - t0)

    return call


class _TimedTracker:
    """A tracker whose calls are timed into ``into``."""

    def __init__(self, tracker: Any, into: list[float]) -> None:
        self.reset, self._call = tracker.reset, _timed(tracker, into)

    def __call__(self, frame: Any) -> Any:
        return self._call(frame)


def bench_tick(
    protocol_file: str = "protocols/noise.yaml", ticks: int = 800, method: str = "proposed"
) -> dict[str, Any]:
    """Median time per control tick of each stage of a camera trial, in one process.

    The protocol's (default ``noise``: 25.5 Hz, S trajectory, camera tracking) first
    ``method`` trial, assembled as ``magrun run`` assembles it but with a frame every tick
    and no noise, runs ``ticks`` ticks of the real loop (:func:`magrun.loop.run_trial`, its
    safety layer included) with each stage timed: render (the rig's camera frame), track
    (UNet window, keypoints, pose fit), control (estimator and planner: from the measurement
    to the currents), prepare (the planner's preparation for the next tick, after the
    currents went out: the NMPC's linearisation; ~0 for the other methods), plant (the safety
    layer's currents applied and one control period of the simulated rig). No recorder, no
    latency charged.
    """
    import cv2

    from magrun.protocol import Conditions, Sweep, load_protocol
    from magrun.trial import assemble, single_trial, trial_threads

    cv2.setNumThreads(1)
    protocol = load_protocol(protocol_file)
    first = next(t for t in protocol.expand() if t.method == method)
    controller = protocol.controller.model_copy(
        update={"latency_ms": "none", "charge_compute_time": None}
    )
    protocol = protocol.model_copy(
        update={
            "sweep": Sweep(),
            "conditions": Conditions(),  # the exact pose's frame, every tick
            "controller": controller,
            "feedback": protocol.feedback.model_copy(update={"camera": True}),
            "duration_s": (ticks - 1) / controller.rate_hz,  # ticks at 0, dt, …
        }
    )
    stages: dict[str, list[float]] = {name: [] for name in STAGES}
    plant: list[float] = []
    with trial_threads(1):  # the tracker's network and the BLAS, as in a run's trial
        parts = assemble(single_trial(protocol, method, first.seed))
        rig, controller_ = parts.rig, parts.controller
        rig.observe = _timed(rig.observe, stages["render"])  # type: ignore[method-assign]
        parts.tracker = _TimedTracker(parts.tracker, stages["track"])
        controller_.step = _timed(controller_.step, stages["control"])  # type: ignore[method-assign]
        controller_.prepare = _timed(controller_.prepare, stages["prepare"])  # type: ignore[method-assign]
        rig.apply = _timed(rig.apply, plant)  # type: ignore[method-assign]
        rig.advance = _timed(rig.advance, plant)  # type: ignore[method-assign]
        log = parts.run()
    stages["plant"] = list(np.add(plant[0::2], plant[1::2]))  # apply, then advance, per tick
    medians = {f"{k}_ms": ms(np.array(v), 50) for k, v in stages.items()}
    return {
        "benchmark": "tick",
        "machine": machine(),
        "method": method,
        "ticks": len(log.t),
        **medians,
        "sum_of_medians_ms": sum(medians.values()),
    }


def summary(out: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    lines = [f"{stage:>8}: {out[stage + '_ms']:.2f} ms" for stage in STAGES]
    lines.append(f"{'sum':>8}: {out['sum_of_medians_ms']:.2f} ms (medians)")
    return lines
