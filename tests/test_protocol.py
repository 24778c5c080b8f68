"""Protocol schema: the shipped protocols, the bad-protocol corpus, expansion, JSON Schema."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from pydantic import ValidationError

from magrun.cli import cli
from magrun.phantom import load_phantom
from magrun.protocol import Protocol, condition_slug, json_schema, load_protocol
from magrun.scene import lead_headings, out_and_back
from magrun.yamlio import YamlModelError

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "tests" / "data" / "protocols" / "tiny.yaml"
PROTOCOLS = sorted((ROOT / "protocols").glob("*.yaml"))
BAD = sorted((ROOT / "tests" / "data" / "bad_protocols").glob("*.yaml"))
PAPER = {"prediction", "rate", "noise", "rate_under_noise", "spine"}
#: beyond the paper: the delivery in a second phantom, the spine's safety envelope, the
#: S on another lab's coil system (OctoMag)
OURS = {"channel", "spine_envelope", "octomag"}


def test_the_five_paper_protocols_are_shipped() -> None:
    assert {p.stem for p in PROTOCOLS} == PAPER | OURS


def test_yaml_is_read_as_pyyaml_reads_it_with_the_tree_as_written() -> None:
    """The one YAML reader (libyaml's parser, parsed once): the data of every YAML file in
    the repository and of a document with anchors and a merge key is what PyYAML's
    pure-Python safe loader gives; the node tree keeps the merge key where it was written
    (the lines of errors), and a key a merge overrides is not taken for one given twice."""
    from magrun.yamlio import safe_yaml

    merged = "base: &b {x: 1, y: 2}\nmerged:\n  <<: *b\n  y: 3\nlist: [1, 2.5, null, true, '7']\n"
    files = [p for p in ROOT.rglob("*.yaml") if not {".venv", "bad_protocols"} & set(p.parts)]
    assert len(files) > 15  # protocols, phantoms, systems, robots, plants
    for text in [merged, *(p.read_text() for p in files)]:
        _, data = safe_yaml(text, "t.yaml")
        assert data == yaml.load(text, Loader=yaml.SafeLoader)
    root, data = safe_yaml(merged, "t.yaml")
    assert data["merged"] == {"x": 1, "y": 3}
    keys = root.value[1][1].value
    assert [(k.value, k.start_mark.line + 1) for k, _ in keys] == [("<<", 3), ("y", 4)]


@pytest.mark.parametrize("path", PROTOCOLS, ids=lambda p: p.stem)
def test_shipped_protocol_validates_and_matches_the_json_schema(path: Path) -> None:
    protocol = load_protocol(path)
    assert protocol.name == path.stem
    # the paper's three trials per condition (the envelope's grid: two per cell)
    assert protocol.trials == (2 if path.stem == "spine_envelope" else 3)
    jsonschema.validate(yaml.safe_load(path.read_text()), json.loads(json_schema()))
    full, quick = protocol.expand(), protocol.expand(quick=True)
    n_conditions = math.prod(len(v) for _, v in protocol.sweep.items())
    assert len(full) == len(protocol.methods) * n_conditions * protocol.trials
    assert 1 <= len(quick) < len(full) or len(full) == 3
    assert all(t.index == 0 for t in quick)
    if protocol.quick.duration_s is None:  # the whole trajectory, as a full run
        assert protocol.trial_duration(quick=True) == protocol.duration_s
    else:
        assert protocol.trial_duration(quick=True) <= protocol.quick.duration_s


def test_validate_command_accepts_all_shipped_protocols() -> None:
    result = CliRunner().invoke(cli, ["validate", *map(str, PROTOCOLS)])
    assert result.exit_code == 0, result.output
    assert result.output.count(": ok (") == len(PROTOCOLS)


def test_the_corpus_of_bad_protocols_is_large_enough() -> None:
    assert len(BAD) >= 20


@pytest.mark.parametrize("path", BAD, ids=lambda p: p.stem)
def test_bad_protocol_is_rejected_with_file_line_and_field(path: Path) -> None:
    # each file's first line says where the problem must be reported: "# expect: LINE: FIELD"
    expected = path.read_text().splitlines()[0].removeprefix("# expect: ")
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert result.exit_code == 2
    assert "Traceback" not in result.output
    assert isinstance(result.exception, SystemExit)
    assert f"{path}:{expected}" in result.output


def test_run_rejects_a_bad_protocol_before_writing_anything(tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["run", str(BAD[0]), "--out", str(tmp_path / "out")])
    assert result.exit_code == 2
    assert not (tmp_path / "out").exists()


def test_validate_reports_every_problem_of_every_file() -> None:
    result = CliRunner().invoke(cli, ["validate", str(BAD[0]), str(BAD[1]), str(PROTOCOLS[0])])
    assert result.exit_code == 2
    assert str(BAD[0]) in result.output
    assert str(BAD[1]) in result.output


def _protocol(**changes: object) -> Protocol:
    doc: dict[str, object] = {
        "name": "t",
        "trajectory": {"kind": "s_curve"},
        "methods": ["proposed", "baseline2", "baseline3"],
        "sweep": {"tracking_rate_hz": [3, 10], "noise_sigma_mm": [0, 1, 2]},
        "trials": 2,
        "seed": 11,
    }
    doc.update(changes)
    return Protocol.model_validate(doc)


def test_expansion_covers_method_by_condition_by_repeat_in_a_fixed_order() -> None:
    p = _protocol()
    trials = p.expand()
    assert len(trials) == 3 * (2 * 3) * 2
    combos = list(itertools.product([3.0, 10.0], [0.0, 1.0, 2.0]))
    got = [(t.condition.tracking_rate_hz, t.condition.noise_sigma_mm) for t in trials]
    assert got == [c for c in combos for _ in range(3 * 2)]
    assert [t.relpath for t in trials] == [t.relpath for t in p.expand()]
    assert len({t.relpath for t in trials}) == len(trials)
    assert trials[0].relpath == "t/proposed_rate-3hz_sigma-0mm/trial-0"


def test_methods_share_seeds_within_a_condition_and_repeat_and_nowhere_else() -> None:
    trials = _protocol().expand()
    by_key: dict[tuple[object, ...], set[int]] = {}
    for t in trials:
        key = (t.condition.tracking_rate_hz, t.condition.noise_sigma_mm, t.index)
        by_key.setdefault(key, set()).add(t.seed)
    assert all(len(seeds) == 1 for seeds in by_key.values())  # paired across methods
    assert len({next(iter(s)) for s in by_key.values()}) == len(by_key)  # distinct otherwise
    other = _protocol().expand(seed=12)
    assert {t.seed for t in other}.isdisjoint({t.seed for t in trials})


def test_quick_defaults_to_the_extreme_values_of_each_sweep_and_one_trial() -> None:
    quick = _protocol().expand(quick=True)
    rates = sorted({t.condition.tracking_rate_hz for t in quick})
    sigmas = sorted({t.condition.noise_sigma_mm for t in quick})
    assert rates == [3.0, 10.0]
    assert sigmas == [0.0, 2.0]
    assert len(quick) == 3 * 2 * 2


def test_fixed_conditions_reach_every_trial_and_defaults_are_stated() -> None:
    p = _protocol(sweep={"tracking_rate_hz": [3]}, conditions={"noise_sigma_mm": 2.0})
    (t, *_) = p.expand()
    assert t.condition.model_dump() == {
        "tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0, "noise_sigma_deg": 0.0
    }  # fmt: skip


def test_condition_slug_formats_values_with_units() -> None:
    assert condition_slug("baseline1", {"tracking_rate_hz": 25.5, "noise_sigma_mm": 0.5}) == (
        "baseline1_rate-25.5hz_sigma-0.5mm"
    )
    assert condition_slug("proposed", {}) == "proposed"


def test_protocol_errors_raise_yaml_model_error_naming_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "p.yaml"
    bad.write_text("name: x\ntrajectory: {kind: s_curve}\nmethods: [proposed]\ntrials: -1\n")
    with pytest.raises(YamlModelError, match=r"p\.yaml:4: trials"):
        load_protocol(bad)


# ---- the spine phantom ------------------------------------------------------------------


PHANTOM = ROOT / "protocols" / "phantoms" / "spine_l3l4.yaml"


def test_phantom_outline_closes_and_contains_its_path() -> None:
    phantom = load_phantom(PHANTOM)
    assert phantom.critical == "anterior"
    assert phantom.path is not None
    assert all(phantom.contains(p) for p in phantom.path)
    assert not phantom.contains([-6e-3, 0.0])  # the dural sac, inside the U
    assert not phantom.contains([0.0, 0.03])


def test_phantom_channel_is_5_mm_wide() -> None:
    phantom = load_phantom(PHANTOM)
    c = np.array([-6e-3, 0.0])
    inner = np.hypot(*(phantom.boundaries["anterior"] - c).T)
    outer = np.hypot(*(phantom.boundaries["posterior"] - c).T)
    np.testing.assert_allclose(outer.mean() - inner.mean(), 5e-3, atol=1e-9)


def test_clearance_to_the_anterior_arc_matches_geometry() -> None:
    # a capsule tangent to the channel at angle φ, its centre at radius ρ around the sac's
    # centre c: its nearest points to the inner arc (radius 10.5 mm) are along its flat side,
    # so the clearance is min over the axis segment of |p − c| − 10.5 mm − r.
    phantom = load_phantom(PHANTOM)
    c = np.array([-6e-3, 0.0])
    length, diameter = 7.4e-3, 2.8e-3
    for phi, rho in [(-0.5, 13.4e-3), (0.3, 12.5e-3), (1.0, 14.0e-3)]:
        centre = c + rho * np.array([np.cos(phi), np.sin(phi)])
        theta = phi + np.pi / 2
        half = (length - diameter) / 2
        axis = half * np.array([np.cos(theta), np.sin(theta)])
        # distance from c to the axis segment: the foot of the perpendicular is the centre
        expected = rho - 10.5e-3 - diameter / 2
        assert np.hypot(*(centre + axis - c)) > rho  # the centre is the closest point
        got = phantom.clearance([*centre, theta], length, diameter)
        # the 0.25 mm chords of the arc sit inside the circle by at most 0.25²/(8·10.5) mm
        assert got == pytest.approx(expected, abs=1e-6)


def test_phantom_with_a_gap_is_rejected(tmp_path: Path) -> None:
    text = PHANTOM.read_text().replace("[-9.591212, -9.866773]", "[-9.0, -9.866773]")
    bad = tmp_path / "gap.yaml"
    bad.write_text(text)
    with pytest.raises(YamlModelError, match="must close the outline"):
        load_phantom(bad)


def test_out_and_back_goes_holds_turns_and_returns() -> None:
    path = np.array([[0.0, 0.0], [0.01, 0.0], [0.01, 0.01]])
    traj = out_and_back(path, speed=0.002, hold=4.0, flip=2.0)
    length = 0.02
    assert traj.duration == pytest.approx(2 * length / 0.002 + 4.0 + 2.0)
    t_far = length / 0.002
    np.testing.assert_allclose(traj.pose(t_far + 2.0), [0.01, 0.01, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(traj.pose(t_far + 4.0 + 1.0)[2], np.pi, atol=1e-12)  # mid-turn
    end = traj.pose(traj.duration)
    np.testing.assert_allclose(end[:2], [0.0, 0.0], atol=1e-12)
    # turned round at the far end (π/2 + π), then home along the first leg, heading west (π)
    assert end[2] == pytest.approx(np.pi)
    assert traj.pose(t_far + 6.0 + 1.0)[2] == pytest.approx(3 * np.pi / 2)
    assert np.all(np.diff(traj.t) > 0)


def _arc_out_and_back(radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A quarter circle of ``radius`` (m) about the origin, counter-clockwise from (0, -r),
    in 0.1 mm steps, out and back with a hold and a turn; and its angular step (rad)."""
    dphi = 1e-4 / radius
    phi = np.arange(-np.pi / 2, 0.0 + dphi / 2, dphi)
    return radius * np.column_stack([np.cos(phi), np.sin(phi)]), dphi


def _circle(radius: float, n: int = 2001) -> np.ndarray:
    phi = np.linspace(-np.pi, np.pi, n)
    return radius * np.column_stack([np.cos(phi), np.sin(phi)])


@pytest.mark.parametrize("wall_points", [2001, 20_001])  # the second: in blocks of 49 poses
def test_headings_lead_where_the_path_bends_away_from_the_boundary(wall_points: int) -> None:
    """Along a bend whose outer wall is the boundary, each heading on the move is the path's
    heading ``lead`` further on: on a circle of radius r, lead / r further round (up to the
    polyline's angular step), out and back; where less than ``lead`` of the leg is left, its
    last heading. The hold and the turn in place keep theirs."""
    r, lead = 13e-3, 1.5e-3
    points, dphi = _arc_out_and_back(r)
    ref = out_and_back(points, speed=3e-3, hold=2.0, flip=3.0)
    led = lead_headings(ref, _circle(r + 2.5e-3, wall_points), lead)
    turn = led.poses[:, 2] - ref.poses[:, 2]
    np.testing.assert_array_equal(led.poses[:, :2], ref.poses[:, :2])
    np.testing.assert_array_equal(led.t, ref.t)
    n = len(points)
    leg = np.pi / 2 * r
    s = np.arange(n) * 1e-4
    far = s + lead <= leg - 1e-4  # where the leg goes on for the whole lead
    # out (counter-clockwise: headings grow) and back (clockwise: they fall)
    np.testing.assert_allclose(turn[:n][far], lead / r, atol=dphi)
    np.testing.assert_allclose(turn[-n:][far], -lead / r, atol=dphi)
    out_end = ref.poses[n - 1, 2]
    np.testing.assert_allclose(led.poses[:n][~far, 2], out_end, atol=dphi)
    # the hold and the turn in place: the poses between the legs, unchanged
    np.testing.assert_array_equal(turn[n:-n], 0.0)
    assert np.all(np.abs(turn) <= lead / r + dphi)


def test_headings_stay_where_the_path_bends_toward_the_boundary_or_runs_straight() -> None:
    r = 13e-3
    points, _ = _arc_out_and_back(r)
    ref = out_and_back(points, speed=3e-3, hold=2.0, flip=3.0)
    assert lead_headings(ref, _circle(r - 2.5e-3), 1.5e-3) is ref  # the inner wall
    assert lead_headings(ref, _circle(r + 2.5e-3), 0.0) is ref
    straight = out_and_back(np.array([[0.0, 0.0], [0.02, 0.0]]), speed=3e-3)
    wall = np.array([[-0.01, 2.5e-3], [0.03, 2.5e-3]])
    assert lead_headings(straight, wall, 1.5e-3) is straight


def test_a_heading_lead_reaches_the_nmpc_only_and_not_the_held_heading_warning() -> None:
    """``controller.heading_lead_mm`` turns the reference the NMPC follows in the phantom's
    bends; the recorded reference, the baselines' and the one the held-heading warning
    compares (the headings the coils can hold) stay the path's; with no lead the NMPC
    follows the path's own."""
    from magrun.trial import controller_tuning, system_of

    channel = ROOT / "protocols" / "channel.yaml"
    overrides = ["controller.heading_lead_mm=1.5", "methods=[proposed, baseline3]", "trials=1"]
    protocol = load_protocol(channel, overrides)
    system = system_of(protocol)
    by_method = {t.method: controller_tuning(t, system) for t in protocol.expand()}
    scene, _, _, planned, held = by_method["proposed"]
    assert held is scene.reference  # the coils hold the capsule's headings in this phantom
    turn = np.degrees(planned.poses[:, 2] - scene.reference.poses[:, 2])
    assert 0 < np.abs(turn).max() < 10  # 1.5 mm round the 10 and 14 mm bends: 6.4-8.6 deg
    np.testing.assert_array_equal(planned.poses[:, :2], scene.reference.poses[:, :2])
    scene3, _, _, planned3, _ = by_method["baseline3"]
    assert planned3 is scene3.reference
    plain = load_protocol(channel, ["controller.heading_lead_mm=0"]).expand()[0]
    unled = controller_tuning(plain, system)
    assert unled[3] is unled[0].reference


def test_the_committed_json_schema_is_current() -> None:
    # regenerate with: magrun protocol schema --out protocols/protocol.schema.json
    assert (ROOT / "protocols" / "protocol.schema.json").read_text() == json_schema()


@pytest.mark.parametrize(
    ("controller", "latency"),
    [
        ({}, 5e-3),  # the declared default
        ({"latency_ms": 12.5}, 12.5e-3),
        ({"latency_ms": "none"}, 0.0),
        ({"latency_ms": "measured"}, "measured"),
        ({"charge_compute_time": True}, "measured"),  # the older key
        ({"charge_compute_time": False}, 0.0),
    ],
)
def test_latency_is_declared_in_ms_or_measured(controller: dict, latency: object) -> None:
    assert _protocol(controller=controller).controller.latency == pytest.approx(latency)


def test_latency_and_the_older_key_together_are_refused() -> None:
    with pytest.raises(ValidationError, match="latency_ms or the older charge_compute_time"):
        _protocol(controller={"latency_ms": 5, "charge_compute_time": True})
    with pytest.raises(ValidationError, match="latency_ms"):
        _protocol(controller={"latency_ms": -1})


@pytest.mark.parametrize(("protocol_file", "iterations", "step"),
                         [("spine.yaml", 6, 0.5), ("rate.yaml", 2, 1.0)])  # fmt: skip
def test_the_corrective_iteration_settings_reach_the_nmpc(
    protocol_file: str, iterations: int, step: float, uncompiled: None
) -> None:
    """controller.corrective_iterations and controller.corrective_step reach the proposed
    method's NMPC as the protocol declares them (the phantom protocols: 6 half steps) or as
    the defaults leave them (2 full steps, the open protocols); --set overrides them."""
    from magrun.control.nmpc import NMPC
    from magrun.trial import build_controller

    for overrides, want in (([], (iterations, step)),
                            (["controller.corrective_iterations=3",
                              "controller.corrective_step=0.25"], (3, 0.25))):  # fmt: skip
        protocol = load_protocol(ROOT / "protocols" / protocol_file, overrides)
        planner = build_controller(protocol.expand(quick=True)[0]).controller.planner
        assert isinstance(planner, NMPC)
        assert (planner.config.corrective_iterations, planner.config.corrective_step) == want


@pytest.mark.parametrize(
    ("sigma_deg", "mobility"), [(0.0, 0.0), (0.5, 0.0), (0.0, 0.003), (0.5, 0.003)]
)
def test_the_filter_state_settings_reach_the_proposed_methods_filter(
    sigma_deg: float, mobility: float, uncompiled: None
) -> None:
    """controller.kalman.heading_bias_sigma_deg builds the filter's bias state (random walk σ
    in rad per tick) and controller.kalman.mobility_sigma its mobility state (σ per tick):
    a state each, 0 leaves it out (the pose-only filter when both are 0)."""
    from magrun.control.estimation import KalmanPoseFilter
    from magrun.trial import assemble

    protocol = load_protocol(
        ROOT / "protocols" / "spine.yaml",
        [
            f"controller.kalman.heading_bias_sigma_deg={sigma_deg}",
            f"controller.kalman.mobility_sigma={mobility}",
        ],
    )
    parts = assemble(protocol.expand(quick=True)[0])
    estimator = parts.controller.estimator
    assert isinstance(estimator, KalmanPoseFilter)
    assert estimator.config.heading_bias == pytest.approx(math.radians(sigma_deg), rel=1e-12)
    assert estimator.config.mobility == mobility
    assert estimator.n == 3 + (sigma_deg > 0) + (mobility > 0)
    assert estimator.mobility == 1.0  # a new trial starts at the model's own step


def test_a_fifo_is_refused_before_it_is_opened(tmp_path: Path) -> None:
    """A FIFO named as a protocol or a robots file made magrun wait for a writer for ever."""
    import os

    from click.testing import CliRunner

    from magrun.cli import cli

    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    run = ["run", str(TINY), "--set", f"robots_file={fifo}", "--out", str(tmp_path)]
    for args in (["validate", str(fifo)], run):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 2, result.output
        assert "not a regular file" in result.output


def test_a_file_that_is_not_magrun_s_is_not_echoed_in_the_error(tmp_path: Path) -> None:
    """A protocol naming a system file (say /etc/shadow) as its robots file printed that file
    line by line in the error: the keys that are not names are not shown, their lines are."""
    from click.testing import CliRunner

    from magrun.cli import cli

    secret = tmp_path / "shadow"
    secret.write_text("root:$6$s3cr3t:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n")
    args = ["run", str(TINY), "--set", f"robots_file={secret}", "--out", str(tmp_path / "o")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 2, result.output
    assert f"{secret}:1:" in result.output
    assert "s3cr3t" not in result.output
    assert "daemon" not in result.output


def test_thousands_of_unknown_keys_are_counted_not_each_located(tmp_path: Path) -> None:
    """Each problem's line is found by a walk of the document: 50,000 unknown keys took
    minutes. The first MAX_PROBLEMS are listed with their lines, the rest counted."""
    from magrun.yamlio import MAX_PROBLEMS, YamlModelError

    path = tmp_path / "many.yaml"
    keys = "".join(f"k{i}: 1\n" for i in range(5000))
    path.write_text("name: bad\ntrajectory: {kind: s_curve}\nmethods: [proposed]\n" + keys)
    with pytest.raises(YamlModelError) as info:
        load_protocol(path)
    problems = info.value.problems
    assert len(problems) == MAX_PROBLEMS + 1
    assert problems[0] == f"{path}:4: k0: Extra inputs are not permitted"
    assert problems[-1] == f"{path}: and {5000 - MAX_PROBLEMS:,} more problems"
