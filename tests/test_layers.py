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
