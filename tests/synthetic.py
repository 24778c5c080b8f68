"""Synthetic recordings in the contract's format, with known errors, for the analysis tests.

Written directly with ``mcap`` and the contract's protobuf schemas (not through magrun's
recorder), so the analysis is tested against the format, not against the code that writes it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema

from magrun.recordings.writer import CoilCurrents, ControllerStatusMsg, pose_message

DT = 1 / 25.5  # s, the control period the synthetic recordings claim
LENGTH, DIAMETER = 8e-3, 2e-3  # m, the synthetic robot's capsule


@dataclass
class SynthTrial:
    """One synthetic trial: a desired path and offsets that fix every error."""

    protocol: str
    method: str
    trial: int = 0
    conditions: Mapping[str, float | None] = field(
        default_factory=lambda: {"tracking_rate_hz": 25.5, "noise_sigma_mm": 0.0}
    )
    n: int = 60
    offset: tuple[float, float, float] = (3e-3, 4e-3, 0.0)  # actual − desired (m, m, rad)
    pred_offset: tuple[float, float, float] = (1e-3, 0.0, 0.0)  # actual − predicted
    start: tuple[float, float, float] = (-0.01, 0.0, 0.0)  # desired pose at t = 0
    velocity: tuple[float, float, float] = (0.005, 0.0, 0.0)  # desired, m/s and rad/s
    boundaries: dict[str, list[list[float]]] = field(default_factory=dict)  # m
    critical: str = ""
    actual_every: int = 1  # log the actual pose every k-th tick only
    solve_times: list[float] | None = None  # s, one per tick
    prepare_times: list[float] | None = None  # s, one per tick (None: the field left unset)
    fallback_ticks: tuple[int, ...] = ()
    dropped_ticks: int = 0
    seed: int = 0
    noise: float = 0.0  # m: Gaussian noise added to the actual position (for statistics)
    quick: bool = False  # recorded by `magrun run --quick`
    whole_path: list[list[float]] | None = None  # m: the workspace record's reference_m
    system: str | None = None  # the protocol's coil-system folder (None: the paper's rig)

    @property
    def slug(self) -> str:
        rate = self.conditions.get("tracking_rate_hz")
        sigma = self.conditions.get("noise_sigma_mm")
        return f"{self.method}_rate-{rate:g}hz_sigma-{sigma:g}mm"

    def desired(self) -> np.ndarray:
        t = np.arange(self.n) * DT
        return np.asarray(self.start) + t[:, None] * np.asarray(self.velocity)

    def actual(self) -> np.ndarray:
        a = self.desired() + np.asarray(self.offset)
        if self.noise:
            rng = np.random.default_rng(self.seed)
            a[:, :2] += rng.normal(0.0, self.noise, size=(self.n, 2))
        return a


def write_mcap(path: Path, s: SynthTrial) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    desired, actual = s.desired(), s.actual()
    predicted = actual - np.asarray(s.pred_offset)
    solve = s.solve_times if s.solve_times is not None else [0.01] * s.n
    with path.open("wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="", library="synthetic")
        trial_meta = {
            "protocol": s.protocol,
            "method": s.method,
            **{k: json.dumps(v) for k, v in s.conditions.items()},
            "trial": json.dumps(s.trial),
            "seed": json.dumps(s.seed),
            "quick": json.dumps(s.quick),
            "robot": "synthetic",
            "robot_length_m": json.dumps(LENGTH),
            "robot_diameter_m": json.dumps(DIAMETER),
            "control_rate_hz": json.dumps(1 / DT),
            "critical_boundary": s.critical,
        }
        w.add_metadata("trial", trial_meta)
        protocol = {"name": s.protocol, **({"system": s.system} if s.system else {})}
        w.add_metadata("protocol", {"json": json.dumps(protocol)})
        w.add_metadata(
            "workspace",
            {
                "boundaries": json.dumps(s.boundaries),
                "half_width_m": json.dumps(0.03),
                **({"reference_m": json.dumps(s.whole_path)} if s.whole_path else {}),
            },
        )
        channels: dict[str, int] = {}

        def put(topic: str, msg: Any, t_ns: int) -> None:
            if topic not in channels:
                channels[topic] = w.register_channel(
                    topic=topic,
                    message_encoding="protobuf",
                    schema_id=register_schema(w, type(msg)),
                )
            w.add_message(
                channels[topic], log_time=t_ns, publish_time=t_ns, data=msg.SerializeToString()
            )

        for k in range(s.n):
            t_ns = round(k * DT * 1e9)
            put("/robot/pose/desired", pose_message(desired[k], t_ns), t_ns)
            if k % s.actual_every == 0:
                put("/robot/pose/actual", pose_message(actual[k], t_ns), t_ns)
            if k > 0:
                put("/robot/pose/predicted", pose_message(predicted[k], t_ns), t_ns)
            put(
                "/coils/currents",
                CoilCurrents(names=["c0", "c1"], currents=[float(k), -float(k)]),
                t_ns,
            )
            put(
                "/controller/status",
                ControllerStatusMsg(
                    method=s.method, solve_time=solve[k], iterations=3, success=True,
                    fallback="hold" if k in s.fallback_ticks else "", compute_time=solve[k],
                    measurement=True,
                    **({} if s.prepare_times is None else {"prepare_time": s.prepare_times[k]}),
                ),
                t_ns,
            )  # fmt: skip
        w.add_metadata("recorder", {"status": "ok", "dropped_ticks": str(s.dropped_ticks)})
        w.finish()
    return path


def write_set(root: Path, trials: Sequence[SynthTrial], failed: Sequence[SynthTrial] = ()) -> Path:
    """Write trials under ``root/<protocol>/<slug>/trial-<k>.mcap`` with manifests."""
    manifests: dict[str, list[dict[str, Any]]] = {}
    for s, status in [*((s, "ok") for s in trials), *((s, "failed") for s in failed)]:
        rel = f"{s.slug}/trial-{s.trial}"
        if status == "ok":
            write_mcap(root / s.protocol / f"{rel}.mcap", s)
        manifests.setdefault(s.protocol, []).append(
            {
                "path": rel, "mcap": f"{rel}.mcap", "rrd": f"{rel}.rrd", "protocol": s.protocol,
                "method": s.method, "conditions": dict(s.conditions), "trial": s.trial,
                "seed": s.seed, "status": status, "error": "" if status == "ok" else "boom",
            }
        )  # fmt: skip
    for protocol, entries in manifests.items():
        (root / protocol / "manifest.json").write_text(
            json.dumps({"protocol": protocol, "trials": entries})
        )
    return root


def wall(y: float, x0: float = -0.05, x1: float = 0.05) -> list[list[float]]:
    """A straight boundary along x at height ``y`` (m)."""
    return [[x0, y], [x1, y]]


def paper_set(root: Path) -> Path:
    """A small recording set with every protocol the figures know, 2 trials per condition."""
    trials: list[SynthTrial] = []
    for k in range(2):
        trials.append(SynthTrial("prediction", "proposed", trial=k, seed=k))
    for protocol, key, values, fixed in (
        ("rate", "tracking_rate_hz", (3.0, 25.5), {"noise_sigma_mm": 0.0}),
        ("noise", "noise_sigma_mm", (0.0, 2.0), {"tracking_rate_hz": 25.5}),
        ("rate_under_noise", "tracking_rate_hz", (3.0, 25.5), {"noise_sigma_mm": 2.0}),
    ):
        for i, method in enumerate(("proposed", "baseline1", "baseline2")):
            for v in values:
                for k in range(2):
                    scale = (1 + i) * (1 + 0.1 * k) * (2 if v in (3.0, 2.0) and i else 1)
                    trials.append(
                        SynthTrial(
                            protocol, method, trial=k, conditions={key: v, **fixed},
                            offset=(0.3e-3 * scale, 0.0, np.radians(2 * scale)),
                            noise=0.2e-3 * scale, seed=100 * i + k,
                        )
                    )  # fmt: skip
    for k in range(2):
        trials.append(
            SynthTrial(
                "spine", "proposed", trial=k,
                conditions={"tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0},
                offset=(0.0, 1e-3, np.radians(5)),
                boundaries={"anterior": wall(8e-3), "posterior": wall(-8e-3)},
                critical="anterior",
            )
        )  # fmt: skip
    return write_set(root, trials)


#: the runner tests' tiny protocol (two fast methods, 1 s trials), made into others by --set
TINY = Path(__file__).resolve().parent / "data" / "protocols" / "tiny.yaml"


def record_tiny(out: Path, overrides: Sequence[str]) -> dict[str, Path]:
    """Run the tiny protocol with ``overrides`` into ``out``; each method's first trial's MCAP
    (every trial must end ``ok``)."""
    from magrun.protocol import load_protocol
    from magrun.runner import run_protocol

    manifest = run_protocol(load_protocol(TINY, tuple(overrides)), out, jobs=1)
    assert {e["status"] for e in manifest["trials"]} == {"ok"}
    return {e["method"]: out / "tiny" / e["mcap"] for e in manifest["trials"] if e["trial"] == 0}
