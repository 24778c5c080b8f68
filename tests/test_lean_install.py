"""The main job without torch: the tracker's ONNX graph shipped beside its weights, checked to
be theirs, exported and refused as the docs say (torch is the ``train`` extra)."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from numpy.testing import assert_allclose

from magrun.cli import cli
from magrun.tracking.export import AGREEMENT, check_windows, fuse_batch_norm, torch_net
from magrun.tracking.inference import DIGEST_KEY, MissingGraph, graph_net, onnx_net
from magrun.tracking.tracker import default_weights_path, load_net
from magrun.tracking.unet import load_weights, save_weights
from magrun.tracking.weights import read_weights

ROOT = Path(__file__).resolve().parents[1]
BLOCKED = ("torch", "onnx")


def _without_torch(tmp_path: Path) -> dict[str, str]:
    """An environment in which ``import torch`` (and ``onnx``) fails, in the command and in
    every process it spawns: a package of that name first on PYTHONPATH that raises."""
    block = tmp_path / "blocked"
    for name in BLOCKED:
        (block / name).mkdir(parents=True)
        (block / name / "__init__.py").write_text(  # as Python says a module is missing
            f"raise ModuleNotFoundError('{name} is blocked: the run path must not import it',"
            f" name='{name}')\n"
        )
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(block), env.get("PYTHONPATH")]))
    return env


def _magrun(env: dict[str, str], *args: object, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "magrun.console", *map(str, args)],
        env=env, cwd=cwd, capture_output=True, text=True, timeout=900,
    )  # fmt: skip


def _weights_copy(tmp_path: Path, perturb: float = 0.0) -> Path:
    """The shipped weights in ``tmp_path`` (no graph beside them), their head's bias moved by
    ``perturb``."""
    model, meta = load_weights(default_weights_path())
    with torch.no_grad():
        model.head.bias += perturb
    path = tmp_path / "w" / "unet.npz"
    save_weights(model, path, {k: v for k, v in meta.items() if k != "widths"})
    return path


def test_the_blocker_blocks(tmp_path) -> None:
    """The check below is only as good as its blocker: torch cannot be imported under it."""
    run = subprocess.run(
        [sys.executable, "-c", "import torch"],
        env=_without_torch(tmp_path), capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 1
    assert "ModuleNotFoundError: torch is blocked" in run.stderr


#: the README's main job, shortened to 2 s a trial
MAIN_JOB = ROOT / "protocols/rate_under_noise.yaml"
SHORT = ("quick.duration_s=2",)


def _main_job(env: dict[str, str], out: Path) -> list[dict[str, str]]:
    """The README's main job, shortened, into ``out`` as ``magrun run`` and ``magrun
    figures`` do it in ``env``: results.csv's rows."""
    run = _magrun(
        env, "run", MAIN_JOB, "--quick", *(a for o in SHORT for a in ("--set", o)),
        "--out", out, cwd=out.parent,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "blocked" not in run.stdout + run.stderr
    made = _magrun(env, "figures", out, cwd=out.parent)
    assert made.returncode == 0, made.stdout + made.stderr
    return _results(out)


def _main_job_here(out: Path) -> list[dict[str, str]]:
    """The same run in this process (`magrun run`'s :func:`run_protocol`) and its results
    table (`magrun figures`' :func:`analysis.write_results`)."""
    import analysis
    from magrun.protocol import load_protocol
    from magrun.runner import run_protocol

    run_protocol(load_protocol(MAIN_JOB, SHORT), out, quick=True)
    (out / "figures").mkdir()
    analysis.write_results(analysis.load(out), out / "figures" / "results.csv")
    return _results(out)


def _results(out: Path) -> list[dict[str, str]]:
    manifest = (out / "rate_under_noise" / "manifest.json").read_text()
    assert '"status": "ok"' in manifest
    assert '"failed"' not in manifest
    with open(out / "figures" / "results.csv", newline="", encoding="utf-8") as fh:
        return sorted(csv.DictReader(fh), key=lambda r: r["method"])


def test_the_main_job_runs_tracks_and_makes_its_figures_without_torch(tmp_path) -> None:
    """The main job where importing torch or onnx fails (in the run's worker processes
    too): camera tracking through the shipped graph, recordings, figures; and the same
    results, to the last digit, as the same run in this process, where torch is imported."""
    from mcap.reader import make_reader

    lean = _main_job(_without_torch(tmp_path), tmp_path / "lean")
    assert "torch" in sys.modules
    full = _main_job_here(tmp_path / "full")
    assert [r["method"] for r in lean] == ["baseline2", "proposed"]
    columns = ["rms_position_mm", "rms_orientation_deg", "measurements", "tracking_lost"]
    assert [[r[c] for c in columns] for r in lean] == [[r[c] for c in columns] for r in full]
    for row in lean:
        with open(tmp_path / "lean" / row["path"], "rb") as fh:
            [trial] = [m for m in make_reader(fh).iter_metadata() if m.name == "trial"]
        assert trial.metadata["feedback"] == "camera"


def test_the_shipped_graph_is_stamped_with_its_weights() -> None:
    weights = read_weights(default_weights_path())
    _, meta = onnx_net(weights.graph_path)
    assert meta[DIGEST_KEY] == weights.digest()
    assert len(weights.digest()) == 64


def test_a_graph_beside_other_weights_is_not_used(tmp_path) -> None:
    """Retrained weights with the old graph beside them: the graph is refused; with torch
    installed the weights' own graph is exported in memory, and it computes their maps."""
    path = _weights_copy(tmp_path, perturb=0.5)
    shutil.copy(default_weights_path().with_suffix(".onnx"), path.with_suffix(".onnx"))
    weights = read_weights(path)
    with pytest.raises(MissingGraph, match="exported from other weights"):
        graph_net(weights)
    net = load_net(weights)
    model, _ = load_weights(path)
    x = check_windows()
    assert_allclose(net.run(x), torch_net(fuse_batch_norm(model))(x), atol=AGREEMENT)
    shipped = graph_net(read_weights(default_weights_path()))
    assert np.max(np.abs(net.run(x) - shipped.run(x))) > 0.1  # the perturbation shows


def test_tracker_export_writes_a_checked_graph_and_never_overwrites_unasked(tmp_path) -> None:
    path = _weights_copy(tmp_path, perturb=0.25)
    runner = CliRunner()
    first = runner.invoke(cli, ["tracker", "export", str(path)])
    assert first.exit_code == 0, first.output
    graph = path.with_suffix(".onnx")
    assert f"wrote {graph}" in first.output
    weights = read_weights(path)
    model, _ = load_weights(path)
    x = check_windows(seed=3)
    assert_allclose(graph_net(weights).run(x), torch_net(fuse_batch_norm(model))(x), atol=1e-4)
    before = graph.read_bytes()
    again = runner.invoke(cli, ["tracker", "export", str(path)])
    assert again.exit_code == 2
    assert f"{graph} exists; add --overwrite" in again.output
    assert graph.read_bytes() == before
    assert runner.invoke(cli, ["tracker", "export", str(path), "--overwrite"]).exit_code == 0


def _one_frame(tmp_path: Path) -> Path:
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "0001.png"), np.full((96, 96, 3), 128, np.uint8))
    return frames


def test_weights_without_a_graph_and_without_torch_say_how_to_export(tmp_path) -> None:
    path = _weights_copy(tmp_path)
    frames = _one_frame(tmp_path)
    run = _magrun(
        _without_torch(tmp_path), "tracker", "run", frames, "--px-per-mm", 2.5,
        "--weights", path, cwd=tmp_path,
    )  # fmt: skip
    assert run.returncode == 2, run.stdout + run.stderr
    assert "Traceback" not in run.stderr
    assert "has no ONNX graph beside it (unet.onnx)" in run.stderr
    assert f"magrun tracker export {path}" in run.stderr
    assert "[train]" in run.stderr


def test_export_without_torch_says_what_to_install(tmp_path) -> None:
    path = _weights_copy(tmp_path)
    run = _magrun(_without_torch(tmp_path), "tracker", "export", path, cwd=tmp_path)
    assert run.returncode == 2, run.stdout + run.stderr
    assert "Traceback" not in run.stderr
    assert "exporting the tracker's graph needs torch and onnx (torch)" in run.stderr
    assert not path.with_suffix(".onnx").exists()


def test_a_corrupt_graph_is_a_clear_error(tmp_path) -> None:
    path = _weights_copy(tmp_path)
    path.with_suffix(".onnx").write_bytes(b"\x08\x07not a graph" * 50)
    run = CliRunner().invoke(
        cli, ["tracker", "run", str(_one_frame(tmp_path)), "--px-per-mm", "2.5",
              "--weights", str(path)],
    )  # fmt: skip
    assert run.exit_code == 2, run.output
    assert "unet.onnx: not a readable ONNX graph" in run.output


# -- magrun build -------------------------------------------------------------------------------


def _libraries(cache: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (cache / "casadi").glob("*.so")}


def test_build_compiles_ahead_and_a_second_build_reuses_the_cache(tmp_path, monkeypatch) -> None:
    """A fresh cache: the quick run's two configurations (proposed, PID) built, the NMPC's
    kernel among the libraries; built again: the same libraries, none rebuilt; then a run of
    the same protocol compiles nothing either."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(cache))
    protocol = str(ROOT / "protocols/rate_under_noise.yaml")
    runner = CliRunner()
    first = runner.invoke(cli, ["build", protocol, "--quick"])
    assert first.exit_code == 0, first.output
    assert "rate_under_noise: 2 controller configurations" in first.output
    assert f"cache: {cache}" in first.output
    built = _libraries(cache)
    assert any(name.startswith("nmpc_rti-") for name in built), built
    second = runner.invoke(cli, ["build", protocol, "--quick"])
    assert second.exit_code == 0, second.output
    assert _libraries(cache) == built
    out = tmp_path / "rec"
    ran = runner.invoke(
        cli, ["run", protocol, "--quick", "--set", "quick.duration_s=1", "--out", str(out)]
    )
    assert ran.exit_code == 0, ran.output
    assert _libraries(cache) == built


def test_build_without_a_compiler_says_so_and_still_succeeds(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("MAGRUN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("MAGRUN_COMPILE", "0")
    result = CliRunner().invoke(cli, ["build", str(ROOT / "protocols/spine.yaml")])
    assert result.exit_code == 0, result.output
    assert "spine: 1 controller configuration\n" in result.output
    assert "no C compiler found" in result.output
    assert "the same results" in result.output
    assert not (tmp_path / "cache" / "casadi").exists()


def test_build_of_a_bad_protocol_names_the_file_and_line(tmp_path) -> None:
    bad = tmp_path / "bad.yaml"
    text = (ROOT / "protocols/spine.yaml").read_text().replace("trials: 3", "trials: -3")
    bad.write_text(text)
    result = CliRunner().invoke(cli, ["build", str(bad)])
    assert result.exit_code == 2
    line = 1 + text.splitlines().index("trials: -3")
    assert f"bad.yaml:{line}: trials" in result.output
