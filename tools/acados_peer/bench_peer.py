"""magrun's ``proposed`` planner against acados on the same problem, closed loop, one core.

    python tools/acados_peer/bench_peer.py [ROUNDS] [TICKS] > peer.json

The condition of ``magrun bench nmpc`` (the S, perfect feedback, no latency charged, the
simulated rig with seed 0, the proposed method's Kalman filter), one process, pinned to one
core; only the planner differs between variants. Rounds run the variants in alternating
order (A B C D, D C B A, …); the first (cold) tick of each trial is excluded.

Variants: ``magrun`` (the RTI with its preparation / feedback split, as ``magrun run`` runs
it), ``acados_rti_split`` (SQP_RTI with rti_phase 1 after the currents and 2 at the
measurement, the same split in the same loop), ``acados_rti`` (SQP_RTI, both phases at the
measurement), ``ipopt_reference`` (magrun's converged IPOPT reference). Per tick is the
preparation plus the feedback phase; ``feedback`` the phase after the measurement alone.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
from acados_nmpc import AcadosPlanner

from magrun.bench.machine import machine, one_core
from magrun.bench.nmpc import s_curve_protocol
from magrun.trial import assemble, single_trial, with_solver


def stats_ms(t: Any) -> dict[str, float]:
    t = np.asarray(t) * 1e3
    return {"n": int(t.size), "median": float(np.median(t)), "p90": float(np.percentile(t, 90)),
            "p99": float(np.percentile(t, 99)), "max": float(np.max(t))}  # fmt: skip


def main() -> None:
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 2
    ticks = int(sys.argv[2]) if len(sys.argv) > 2 else None
    protocol = s_curve_protocol(ticks)
    trial = single_trial(protocol, "proposed", seed=0)
    t0 = time.perf_counter()
    parts = {
        "magrun": assemble(trial),
        "acados_rti_split": assemble(trial),
        "acados_rti": assemble(trial),
        "ipopt_reference": assemble(trial, tune=with_solver("ipopt")),
    }
    for name, split in (("acados_rti_split", True), ("acados_rti", False)):
        c = parts[name].controller
        c.planner = AcadosPlanner(c.planner, "rti", tag=name[len("acados_rti") :],  # type: ignore[arg-type]
                                  split=split)  # fmt: skip
    out: dict[str, Any] = {"machine": machine(), "build_s": time.perf_counter() - t0,
                           "closed_loop": {}}  # fmt: skip
    order = list(parts)
    per: dict[str, dict[str, list[Any]]] = {
        n: {"tick": [], "feedback": [], "rms_mm": [], "failed": [], "prepared": []} for n in order
    }
    with one_core() as core:
        out["pinned_core"] = core
        for r in range(rounds):
            for name in order if r % 2 == 0 else order[::-1]:
                log = parts[name].run()
                status = log.status[1:]
                solve = np.array([s.solve_time for s in status])
                prep = np.array([s.prepare_time for s in status])
                p = per[name]
                p["tick"] += list(solve + prep)
                p["feedback"] += list(solve[prep > 0])
                p["prepared"].append(int(np.sum(prep > 0)))
                p["rms_mm"].append(log.rms_position_mm)
                p["failed"].append(sum(not s.success for s in log.status))
                print(
                    f"round {r} {name}: tick median {np.median(solve + prep) * 1e3:.3f} ms,"
                    f" RMS {log.rms_position_mm:.5f} mm",
                    file=sys.stderr,
                    flush=True,
                )
    ref = float(np.median(per["ipopt_reference"]["tick"]))
    for name, p in per.items():
        row: dict[str, Any] = {
            "per_tick_ms": stats_ms(p["tick"]),
            "speedup_vs_ipopt": ref / float(np.median(p["tick"])),
            "rms_position_mm": p["rms_mm"],
            "failed_solves": p["failed"],
            "prepared_ticks": p["prepared"],
        }
        if p["feedback"]:
            row["feedback_ms"] = stats_ms(p["feedback"])
            row["feedback_speedup_vs_ipopt"] = ref / float(np.median(p["feedback"]))
        out["closed_loop"][name] = row
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
