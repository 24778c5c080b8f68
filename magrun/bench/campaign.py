"""``magrun bench campaign``: the protocols run with recordings, timed."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from magrun.bench.machine import folder_bytes, machine


def bench_campaign(
    protocol_files: list[str],
    out: str,
    jobs: int = 2,
    quick: bool = False,
    progress: Callable[[str], None] | None = None,
    feedback: str | None = None,
) -> dict[str, Any]:
    """Run the protocols, recordings written, their trials sharing one pool of ``jobs``
    processes (protocols with the fewest trials first, so that no worker idles at the end).

    Figures per protocol: trials, ``wall_s`` (from the campaign's start to the protocol's
    last trial done: protocols overlap), failed trials, dropped recorder ticks, control ticks
    that overran their period, ticks, the recordings' size, and ``cpu_s``, where the trials'
    CPU time went (the manifests' ``cpu_s`` summed: set-up, each stage of the loop, finish,
    the recorder's and libraries' threads; :data:`magrun.runner.CPU_PARTS`); in total the
    same, with the campaign's wall time and trials per minute. ``feedback`` "camera" or
    "truth" overrides every protocol's ``feedback.camera`` (None: as the files say).
    """
    import concurrent.futures as cf
    from pathlib import Path

    from magrun.protocol import load_protocol
    from magrun.runner import CPU_PARTS, pool_executor, run_protocol, shared_pool

    def cpu_sum(entries: list[dict[str, Any]]) -> dict[str, float]:
        return {
            part: round(sum(float((e.get("cpu_s") or {}).get(part, 0.0)) for e in entries), 3)
            for part in CPU_PARTS
        }

    if feedback not in (None, "camera", "truth"):
        raise ValueError(f"feedback must be camera or truth, got {feedback!r}")
    result: dict[str, Any] = {
        "benchmark": "campaign",
        "machine": machine(),
        "jobs": jobs,
        "quick": quick,
        "feedback": feedback or "as in the protocols",
        "protocols": {},
    }
    protocols = []
    for path in protocol_files:
        protocol = load_protocol(path)
        if feedback is not None:
            camera = feedback == "camera"
            protocol = protocol.model_copy(
                update={"feedback": protocol.feedback.model_copy(update={"camera": camera})}
            )
        protocols.append(protocol)

    # the protocols with the fewest trials first: those (spine, prediction) have the longest
    # trials (wall contact, a frame every tick), and the hundreds of short sweep trials then
    # fill the pool's end instead of one long trial running alone there
    protocols.sort(key=lambda p: len(p.expand(quick=quick)))
    total_start = time.perf_counter()

    def run_one(protocol: Any, executor: Any) -> tuple[dict[str, Any], float]:
        if progress is not None:
            progress(protocol.name)
        manifest = run_protocol(protocol, out, quick=quick, executor=executor, overwrite=True)
        return manifest, time.perf_counter() - total_start

    with shared_pool(jobs) as pool, cf.ThreadPoolExecutor(max(len(protocols), 1)) as threads:
        executor = pool_executor(pool)
        futures = []
        for protocol in protocols:  # the pool queues trials in submission order
            futures.append(threads.submit(run_one, protocol, executor))
            time.sleep(0.2)
        done = [f.result() for f in futures]
    for protocol, (manifest, finished) in zip(protocols, done, strict=True):
        trials = manifest["trials"]
        folder = Path(out) / protocol.name
        size = folder_bytes(folder)
        result["protocols"][protocol.name] = {
            "trials": len(trials),
            "wall_s": finished,
            "trials_per_min": len(trials) / finished * 60,
            "failed": sum(t["status"] != "ok" for t in trials),
            "dropped_ticks": sum(int(t.get("dropped_ticks") or 0) for t in trials),
            "overrun_ticks": sum(int(t.get("overruns") or 0) for t in trials),
            "ticks": sum(int(t.get("ticks") or 0) for t in trials),
            "trial_wall_s": sum(float(t.get("wall_s") or 0.0) for t in trials),
            "recordings_mb": size / 1e6,
            "cpu_s": cpu_sum(trials),
        }
    wall = time.perf_counter() - total_start
    rows = result["protocols"].values()
    result["total"] = {
        "trials": sum(r["trials"] for r in rows),
        "wall_s": wall,
        "trials_per_min": sum(r["trials"] for r in rows) / wall * 60,
        "failed": sum(r["failed"] for r in rows),
        "dropped_ticks": sum(r["dropped_ticks"] for r in rows),
        "overrun_ticks": sum(r["overrun_ticks"] for r in rows),
        "recordings_mb": sum(r["recordings_mb"] for r in rows),
        "cpu_s": cpu_sum([{"cpu_s": r["cpu_s"]} for r in rows]),
    }
    return result


def summary(result: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    lines = [
        f"{name:>18}: {r['trials']} trials in {r['wall_s'] / 60:.1f} min"
        f" ({r['trials_per_min']:.1f}/min), {r['failed']} failed,"
        f" {r['dropped_ticks']} dropped, {r['overrun_ticks']} overruns,"
        f" {r['recordings_mb']:.0f} MB"
        for name, r in [*result["protocols"].items(), ("total", result["total"])]
    ]
    cpu = result["total"]["cpu_s"]
    total = cpu["total"] or 1.0
    parts = ", ".join(
        f"{part} {seconds:.0f} s ({seconds / total:.0%})"
        for part, seconds in cpu.items()
        if part != "total"
    )
    lines.append(f"{'trials CPU':>18}: {cpu['total'] / 60:.1f} min: {parts}")
    return lines
