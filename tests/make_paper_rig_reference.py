"""Write tests/data/paper_rig_reference.npz: what the paper's rig records for tests/data/
protocols/tiny.yaml, every method of it, as the reference that later versions must match.

    python tests/make_paper_rig_reference.py

The arrays are each trial's recorded poses (actual, estimated, predicted, desired; x, y in m,
θ in rad; NaN where a stream had no message) and currents (A), keyed ``<trial path>/<what>``.
tests/test_emns.py checks that the paper's rig still records them (changes such as the
N-channel coil systems must not change it). Regenerate only when a change is meant to change
the paper rig's trials, and say so in the commit.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "data" / "paper_rig_reference.npz"
STREAMS = ("actual", "estimated", "predicted", "desired")
METHODS = "[proposed,baseline1,baseline2,baseline3,baseline4,baseline5]"


def record(out: Path) -> dict[str, np.ndarray]:
    """Run tiny.yaml with every method into ``out``; the arrays described above."""
    from magrun.protocol import load_protocol
    from magrun.recordings.reader import read_ticks
    from magrun.runner import run_protocol

    protocol = load_protocol(HERE / "data" / "protocols" / "tiny.yaml", (f"methods={METHODS}",))
    manifest = run_protocol(protocol, out, jobs=1)
    arrays: dict[str, np.ndarray] = {}
    for entry in manifest["trials"]:
        assert entry["status"] == "ok", entry
        rec = read_ticks(out / "tiny" / entry["mcap"])
        for stream in STREAMS:
            arrays[f"{entry['path']}/{stream}"] = rec.poses[stream]
        arrays[f"{entry['path']}/currents"] = rec.currents
    return arrays


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        arrays = record(Path(tmp))
    np.savez_compressed(OUT, **arrays)
    print(f"wrote {OUT}: {len(arrays)} arrays")
    return 0


if __name__ == "__main__":
    sys.exit(main())
