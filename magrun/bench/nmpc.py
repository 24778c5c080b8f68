"""``magrun bench nmpc``: NMPC solve times and closed-loop tracking, the fast solver against
the IPOPT reference, on the S-trajectory with perfect feedback."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from magrun.bench.machine import machine, ms, one_core

#: NMPC variants: name → (method, solver)
NMPC_VARIANTS: dict[str, tuple[str, str]] = {
    "proposed": ("proposed", "rti"),
    "proposed_ipopt_reference": ("proposed", "ipopt"),
    "b5_lut": ("baseline5", "rti"),
    "b5_lut_ipopt": ("baseline5", "ipopt"),
}

#: the benchmark's control rate, Hz
RATE_HZ = 25.0


#: the robot of a system's variant (:func:`bench_nmpc`'s ``systems``): one sized for small
#: workspaces, on the paper's S scaled to the system's workspace
SYSTEM_ROBOT = "micro_magnet"
#: the paper's rig's workspace half width, mm, which the S is scaled from
PAPER_HALF_WIDTH_MM = 50.0


def s_curve_protocol(
    ticks: int | None, system: str | Path | None = None, half_width_mm: float = 50.0
) -> Any:
    """The benchmark's condition as a protocol: the paper's S (43 mm, 3 mm/s) in the open
    workspace, the exact pose every tick (no camera, no noise), no compute time charged,
    and the Kalman filter's default tuning (1 mm, 3°; process 0.3 mm, 2° per tick). With a
    ``system`` folder: that system, :data:`SYSTEM_ROBOT`, and the S (size and speed) scaled
    by the workspace's half width ``half_width_mm`` against the paper's 50 mm."""
    from magrun.protocol import Protocol

    scale = half_width_mm / PAPER_HALF_WIDTH_MM
    return Protocol.model_validate(
        {
            "name": "bench-nmpc",
            "robot": "magnet" if system is None else SYSTEM_ROBOT,
            "system": None if system is None else str(system),
            "trajectory": {"kind": "s_curve", "size_mm": 43 * scale, "speed_mm_s": 3 * scale},
            "methods": sorted({m for m, _ in NMPC_VARIANTS.values()}),
            "controller": {
                "rate_hz": RATE_HZ,
                "latency_ms": "none",
                "kalman": {"measurement_sigma_mm": 1.0},
            },
            "feedback": {"camera": False},
            # ticks at 0, dt, …; None: the whole S plus 1 s of hold
            "duration_s": None if ticks is None else (ticks - 1) / RATE_HZ,
        }
    )


def bench_nmpc(
    ticks: int | None = None,
    variants: tuple[str, ...] = tuple(NMPC_VARIANTS),
    progress: Callable[[str], None] | None = None,
    systems: tuple[str | Path, ...] = (),
    protocols: tuple[Any, ...] = (),
) -> dict[str, Any]:
    """Per-solve times and closed-loop tracking of the NMPC variants on one core.

    ``systems``: coil-system folders on which the proposed method runs too, in the same
    run (variant ``proposed@<folder name>``, with its channel count under ``coils``): the
    solve time for N channels beside the paper rig's 8.

    ``protocols``: loaded protocols (:class:`~magrun.protocol.Protocol`) whose proposed
    method runs too, in the same run (variant ``proposed@<protocol name>``): one trial
    (seed 0) under the protocol's fixed conditions, its feedback, plant and controller as
    declared, the first ``ticks`` ticks or its whole duration: a phantom's ticks (corridor,
    Kalman filter) beside the S's. ``feedback_vs_s`` is its feedback phase's median over
    the S's (variant ``proposed``, in the same run).

    Each variant runs the paper's S-trajectory (43 mm, 3 mm/s; the first ``ticks`` ticks, or
    all of it plus 1 s of hold) closed loop on the simulated rig (seed 0) with perfect
    feedback and no latency charged, so tracking differences come from the solver alone.
    Solve times are the planner's wall time per tick, the first (cold, iterated to
    convergence) excluded: for the RTI the preparation (done before the tick's measurement)
    plus the feedback phase (after it), and the feedback phase alone under ``feedback``: the
    planner's share of the delay from measurement to currents.
    """
    from magrun.trial import assemble, single_trial, with_solver

    unknown = set(variants) - set(NMPC_VARIANTS)
    if unknown:
        raise ValueError(f"unknown variants {sorted(unknown)}; known: {', '.join(NMPC_VARIANTS)}")
    protocol = s_curve_protocol(ticks)
    out: dict[str, Any] = {
        "benchmark": "nmpc",
        "horizon": protocol.controller.horizon,
        "dt_s": 1.0 / RATE_HZ,
        "coils": 8,
        "trajectory": "S, 43 mm, 3 mm/s, perfect feedback, no latency charged",
        "machine": machine(),
        "variants": {},
    }
    from magrun.field.system import load_system

    runs: list[tuple[str, str, str, Any]] = [
        (name, *NMPC_VARIANTS[name], protocol) for name in variants
    ]
    for proto in protocols:
        if ticks is not None:
            proto = proto.model_copy(update={"duration_s": (ticks - 1) / proto.controller.rate_hz})
        runs.append((f"proposed@{proto.name}", "proposed", "rti", proto))
    for folder in systems:
        coils = load_system(folder).coils
        runs.append(
            (
                f"proposed@{Path(folder).name}", "proposed", "rti",
                s_curve_protocol(ticks, folder, coils.workspace_half_width * 1e3),
            )
        )  # fmt: skip
    with one_core() as core:
        out["pinned_core"] = core
        for name, method, solver, proto in runs:
            if progress is not None:
                progress(name)
            parts = assemble(single_trial(proto, method, seed=0), tune=with_solver(solver))
            log = parts.run()
            controller = parts.controller
            feedback = log.solve_times[1:]
            prepare = np.array([s.prepare_time for s in log.status[1:]])
            solve = feedback + prepare
            split = bool(np.any(prepare > 0))
            backend = getattr(controller.planner, "backend", None)
            out["variants"][name] = {
                "coils": controller.n_channels,
                "robot": proto.robot,
                "method": method,
                "model": "lookup_table" if method == "baseline5" else "zernike",
                "solver": "Gauss-Newton RTI + HPIPM" if solver == "rti" else "IPOPT (converged)",
                "build_s": parts.controller_build_s,
                "ticks": len(log.t),
                "median_ms": ms(solve, 50),
                "p90_ms": ms(solve, 90),
                "p99_ms": ms(solve, 99),
                "max_ms": float(np.max(solve) * 1e3),
                "median_iterations": float(np.median([s.iterations for s in log.status[1:]])),
                "failed_solves": sum(not s.success for s in log.status),
                # RTI: QPs HPIPM's fast preset failed and the robust one solved
                "robust_retries": getattr(backend, "robust_retries", 0),
                # RTI: prepared ticks whose measurement was too far from the prediction for
                # the linearisation there (NMPCConfig.max_embedding_defect), linearised afresh
                "relinearised_ticks": getattr(backend, "relinearised", 0),
                "achievable_rate_hz": float(1.0 / np.median(solve)),
                "rms_position_mm": log.rms_position_mm,
                "rms_orientation_deg": log.rms_orientation_deg,
            }
            if split:  # the delay from measurement to currents: the feedback phase alone
                out["variants"][name]["feedback"] = {
                    "median_ms": ms(feedback, 50),
                    "p90_ms": ms(feedback, 90),
                    "p99_ms": ms(feedback, 99),
                    "max_ms": float(np.max(feedback) * 1e3),
                    "prepared_ticks": int(np.sum(prepare > 0)),
                    # ticks whose feedback phase used their preparation (the others, whose
                    # parameters changed since, e.g. a start the corridor leads out of its
                    # margin, linearised again at the measured start)
                    "embedded_ticks": int(getattr(backend, "embedded", 0)),
                    "prepare_median_ms": ms(prepare[prepare > 0], 50),
                }
    v = out["variants"]
    if "proposed" in v and "proposed_ipopt_reference" in v:
        fast, ref = v["proposed"], v["proposed_ipopt_reference"]
        out["speedup_vs_ipopt"] = ref["median_ms"] / fast["median_ms"]
        out["p99_speedup_vs_ipopt"] = ref["p99_ms"] / fast["p99_ms"]
        out["rms_position_vs_ipopt"] = fast["rms_position_mm"] / ref["rms_position_mm"] - 1.0
        if "feedback" in fast:
            out["feedback_speedup_vs_ipopt"] = ref["median_ms"] / fast["feedback"]["median_ms"]
            out["feedback_p99_speedup_vs_ipopt"] = ref["p99_ms"] / fast["feedback"]["p99_ms"]
    s_feedback = v.get("proposed", {}).get("feedback", {}).get("median_ms")
    for name, r in v.items():
        if name.startswith("proposed@") and s_feedback and "feedback" in r:
            r["feedback_vs_s"] = r["feedback"]["median_ms"] / s_feedback
    if "b5_lut" in v and "b5_lut_ipopt" in v:
        out["b5_speedup_vs_ipopt"] = v["b5_lut_ipopt"]["median_ms"] / v["b5_lut"]["median_ms"]
    return out


def summary(out: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    lines = []
    for name, r in out["variants"].items():
        lines.append(
            f"{name:>25}: median {r['median_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms,"
            f" max {r['max_ms']:.2f} ms, {r['median_iterations']:.0f} it,"
            f" RMS {r['rms_position_mm']:.4f} mm / {r['rms_orientation_deg']:.3f} deg,"
            f" build {r['build_s']:.1f} s"
        )
        if "feedback" in r:
            f = r["feedback"]
            lines.append(
                f"{'':>25}  feedback phase: median {f['median_ms']:.2f} ms,"
                f" p99 {f['p99_ms']:.2f} ms ({f['prepared_ticks']} prepared ticks,"
                f" {f['embedded_ticks']} used)"
                + (f", {r['feedback_vs_s']:.2f}x the S's" if "feedback_vs_s" in r else "")
            )
    for key in (
        "speedup_vs_ipopt", "p99_speedup_vs_ipopt", "feedback_speedup_vs_ipopt",
        "feedback_p99_speedup_vs_ipopt", "b5_speedup_vs_ipopt",
    ):  # fmt: skip
        if key in out:
            lines.append(f"{key}: {out[key]:.1f}x")
    if "rms_position_vs_ipopt" in out:
        lines.append(f"RMS position vs IPOPT: {100 * out['rms_position_vs_ipopt']:+.2f} %")
    return lines
