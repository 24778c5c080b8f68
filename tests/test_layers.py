"""The layering's runtime side: what a light command loads. (`lint-imports` checks the import
graph itself against the contracts in pyproject.toml; this checks what really gets imported,
function-level imports included, in a fresh interpreter.)"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("casadi", "torch", "cv2", "rerun", "mcap")


def loaded_after(code: str) -> list[str]:
    """The heavy packages in sys.modules after running ``code`` in a fresh interpreter."""
    found = f"' '.join(m for m in {HEAVY!r} if m in sys.modules)"
    probe = f"{code}\nimport sys\nprint()\nprint({found})"
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True
    )
    return out.stdout.splitlines()[-1].split()  # the probe's line comes last


def test_validating_protocols_loads_no_solver_tracker_or_recorder() -> None:
    code = (
        "from magrun.cli import cli\n"
        "try:\n"
        "    cli(['validate', 'protocols/spine.yaml', 'protocols/rate.yaml'],"
        " standalone_mode=False)\n"
        "except SystemExit as e:\n"
        "    assert not e.code, e.code\n"
    )
    assert loaded_after(code) == []


def test_the_recorder_loads_no_solver() -> None:
    loaded = loaded_after("import magrun.recordings.writer, magrun.recordings.process")
    assert "casadi" not in loaded


def test_the_probe_sees_a_heavy_import() -> None:
    """The check above can fail: building a controller loads CasADi."""
    assert "casadi" in loaded_after("import magrun.control.methods")


def test_no_control_tick_imports_a_module() -> None:
    """Whatever a trial's controller and tracker import, they import before the first tick,
    not in one (an import in a tick is a stall of up to a second at the coils): in a fresh
    interpreter, the spine with the proposed method (the Kalman filter's truncation at the
    critical wall) and the noise protocol with Baseline 3 (the two-layer QPs and their
    fallback), assembled, then run for 1 s each. The modules the fallbacks use are in memory
    once the controller is built, and Numba's once the simulated plant is (magrun.rigs.kernel).
    What a machine compiles once (the NMPC's kernel, the plant's Numba code: `magrun build`)
    may import more while it compiles: where the first interpreter's ticks imported anything,
    a second one runs the same, loading it from the cache as every trial after the first on a
    machine does, and that one is checked. (A first run that imported nothing passes
    as it is: the cache was warm, or compiling imported nothing in a tick either.)"""
    code = (
        "import sys\n"
        "from magrun.protocol import load_protocol\n"
        "from magrun.trial import assemble\n"
        "new = []\n"
        "for path, method, needed in (('protocols/spine.yaml', 'proposed', 'scipy.stats'),"
        " ('protocols/noise.yaml', 'baseline3', 'scipy.optimize')):\n"
        "    protocol = load_protocol(path, ('duration_s=1',))\n"
        "    trial = next(t for t in protocol.expand() if t.method == method)\n"
        "    parts = assemble(trial)\n"
        "    assert needed in sys.modules, needed\n"
        "    before = set(sys.modules)\n"
        "    parts.run()\n"
        "    new += sorted(set(sys.modules) - before)\n"
        "print()\n"
        "print(' '.join(new))\n"
    )
    for _ in ("first", "from the cache"):
        out = subprocess.run(
            [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
        )
        imported = out.stdout.splitlines()[-1].split()
        if not imported:
            break
    assert imported == []


def _contract(name_start: str) -> tuple[dict, set[str]]:
    """The import-linter contract whose name starts so, and magrun's top-level modules."""
    import pkgutil
    import tomllib

    import magrun

    config = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = config["tool"]["importlinter"]["contracts"]
    (contract,) = [c for c in contracts if c["name"].startswith(name_start)]
    return contract, {f"magrun.{m.name}" for m in pkgutil.iter_modules(magrun.__path__)}


def test_every_module_but_recordings_is_kept_from_the_recording_libraries() -> None:
    """The contract that only ``magrun.recordings`` imports mcap, the protobuf schemas and
    rerun names its sources one by one: a new module or package of magrun must be on it
    (or be recordings itself), or the contract would not see it."""
    contract, modules = _contract("Only recordings imports")
    assert {"mcap", "rerun"} <= set(contract["forbidden_modules"])
    assert modules - set(contract["source_modules"]) == {"magrun.recordings"}


def test_every_module_but_field_asks_field_system_for_a_systems_models() -> None:
    """The contract that a coil system's models and maps come only from
    ``magrun.field.system`` names its sources one by one, as the recording libraries' does:
    every module or package of magrun but ``field`` itself must be on it."""
    contract, modules = _contract("A coil system's models")
    assert {"magrun.field.zernike", "magrun.field.lut"} <= set(contract["forbidden_modules"])
    assert modules - set(contract["source_modules"]) == {"magrun.field"}
