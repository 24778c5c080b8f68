"""``magrun bench cluster``: a protocol's trials on local Ray clusters of 1, 2, … nodes.

Each cluster is started on this machine with :class:`ray.cluster_utils.Cluster` (a head and
further raylets, ``cpus_per_node`` CPUs each), and the protocol is run on it with
``--executor ray``: every trial records on its node and its files come back to the driver,
as on a lab's cluster without shared storage. The clusters run one after the other, so the
figures are side by side; on one machine the nodes share its cores, so the speed-up shows
what the executor and the write-back cost, not what more machines would give.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from magrun.bench.machine import folder_bytes, machine


def bench_cluster(
    protocol_file: str,
    nodes: Sequence[int] = (1, 2),
    cpus_per_node: int = 1,
    quick: bool = True,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run ``protocol_file`` on a local Ray cluster of each size in ``nodes``; per size the
    wall time from the cluster's start to the last trial's files at the driver (cluster
    start and worker imports included), the time after the cluster was up, trials per
    minute, the nodes that ran trials, failed trials, the recordings' size, and the
    speed-up against the first size."""
    import ray
    from ray.cluster_utils import Cluster

    from magrun.protocol import load_protocol
    from magrun.runner import ray_executor, run_protocol

    protocol = load_protocol(protocol_file)
    result: dict[str, Any] = {
        "benchmark": "cluster",
        "machine": machine(),
        "protocol": protocol.name,
        "quick": quick,
        "cpus_per_node": cpus_per_node,
        "trials": len(protocol.expand(quick=quick)),
        "clusters": {},
    }
    store = 200 * 1024**2
    for n in nodes:
        if progress is not None:
            progress(f"{n} node(s)")
        with tempfile.TemporaryDirectory(prefix="magrun-bench-cluster-") as out:
            t0 = time.perf_counter()
            cluster = Cluster(
                initialize_head=True,
                head_node_args={
                    "num_cpus": cpus_per_node, "object_store_memory": store,
                    "include_dashboard": False,
                },
            )  # fmt: skip
            try:
                for _ in range(n - 1):
                    cluster.add_node(num_cpus=cpus_per_node, object_store_memory=store)
                cluster.wait_for_nodes()
                ray.init(
                    address=cluster.address, log_to_driver=False, logging_level=logging.WARNING
                )
                up = time.perf_counter()
                manifest = run_protocol(
                    protocol, out, quick=quick, executor=ray_executor(), overwrite=True
                )
                done = time.perf_counter()
            finally:
                ray.shutdown()
                cluster.shutdown()
            trials = manifest["trials"]
            folder = Path(out) / protocol.name
            size = folder_bytes(folder)
        result["clusters"][str(n)] = {
            "nodes": n,
            "wall_s": done - t0,
            "run_s": done - up,
            "trials_per_min": len(trials) / (done - t0) * 60,
            "nodes_used": len({t.get("ray_node") for t in trials if t.get("ray_node")}),
            "failed": sum(t["status"] != "ok" for t in trials),
            "recordings_mb": size / 1e6,
        }
    first = result["clusters"][str(nodes[0])]["wall_s"]
    for row in result["clusters"].values():
        row["speedup"] = first / row["wall_s"]
    return result


def summary(result: dict[str, Any]) -> list[str]:
    """The result as lines for a terminal."""
    each = result["cpus_per_node"]
    lines = [f"{result['protocol']}: {result['trials']} trials, {each} CPU(s) a node"]
    for n, r in result["clusters"].items():
        lines.append(
            f"{n:>3} node(s): {r['wall_s']:.1f} s ({r['run_s']:.1f} s after start-up),"
            f" {r['trials_per_min']:.1f} trials/min, x{r['speedup']:.2f},"
            f" {r['nodes_used']} node(s) used, {r['failed']} failed, {r['recordings_mb']:.1f} MB"
        )
    return lines
