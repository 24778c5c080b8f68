"""Figures, results.csv, the report and ``magrun figures`` on a small synthetic recording set."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from synthetic import SynthTrial, paper_set, wall, write_set

import analysis
from analysis import figures, report, stats
from magrun.cli import cli
from magrun.field.fitting import FIGURE_FILE

ZERNIKE = Path(__file__).parents[1] / "magrun" / "field" / "data" / FIGURE_FILE
CONTRACT = [
    "protocol", "method", "tracking_rate_hz", "noise_sigma_mm", "trial", "rms_position_mm",
    "rms_orientation_deg", "rms_prediction_position_mm", "rms_prediction_orientation_deg",
    "min_clearance_mm",
]  # fmt: skip


@pytest.fixture(scope="module")
def paper(tmp_path_factory: pytest.TempPathFactory) -> analysis.Dataset:
    return analysis.load(paper_set(tmp_path_factory.mktemp("rec")))


def test_each_protocol_gets_the_paper_figure_kind(paper: analysis.Dataset) -> None:
    kinds = {p: figures.figure_kind(paper, p) for p in paper.protocols()}
    assert kinds == {
        "noise": "sweep",
        "prediction": "trajectories",
        "rate": "sweep",
        "rate_under_noise": "sweep",
        "spine": "phantom",
    }
    assert figures.swept_condition(paper.ok("noise")) == "noise_sigma_mm"
    assert figures.swept_condition(paper.ok("rate")) == "tracking_rate_hz"


def test_zernike_maps_are_drawn_with_y_up() -> None:
    # the base stack's coils sit on +y (docs/field.md, "Coil system"): |B| of its small coil is
    # largest on the image's top row (origin lower), and the map is the data transposed
    with np.load(ZERNIKE) as npz:
        data = dict(npz)
    fig = figures.zernike(data)
    img = np.asarray(fig.axes[1].get_images()[0].get_array())
    np.testing.assert_array_equal(img, data["small_field_mT"].T)
    row = np.unravel_index(np.argmax(img), img.shape)[0]
    assert row == img.shape[0] - 1


def test_sweep_lines_are_the_trial_means(paper: analysis.Dataset) -> None:
    fig = figures.sweep(paper, "rate")
    ax = fig.axes[0]
    assert len(fig.axes) == 2  # no noise in `rate`: no violin
    trials = paper.ok("rate")
    want = trials.groupby(["method", "tracking_rate_hz"])["rms_position_mm"].mean()
    lines = {
        line.get_label(): line for line in ax.get_lines() if not line.get_label().startswith("_")
    }
    # each line carries the paper's name of its method
    names = {"proposed": "Proposed", "baseline1": "Baseline 1", "baseline2": "Baseline 2 (PID)"}
    for method, name in names.items():
        x, y = lines[name].get_data()
        np.testing.assert_allclose(y, [want[(method, r)] for r in x], rtol=1e-12)


def test_rate_under_noise_adds_the_violin_with_the_test_stars(paper: analysis.Dataset) -> None:
    fig = figures.sweep(paper, "rate_under_noise")
    assert len(fig.axes) == 3
    texts = [t.get_text() for t in fig.axes[2].texts if "*" in t.get_text() or t.get_text() == "ns"]
    s = paper.samples
    at3 = s[(s["protocol"] == "rate_under_noise") & (s["tracking_rate_hz"] == 3.0)]
    tests = stats.compare_methods(at3)
    assert texts == list(tests.sort_values("method")["stars"])
    assert all(t == "***" for t in texts)  # synthetic baselines are 2–3× worse at 3 Hz


def test_trajectories_show_the_workspace_and_zoom_on_the_paths(paper: analysis.Dataset) -> None:
    fig = figures.trajectories(paper, "prediction")
    ax_a, ax_b = fig.axes
    # (a): the recording's workspace square (half width 30 mm in the synthetic files)
    (square,) = ax_a.patches
    assert (square.get_x(), square.get_width()) == pytest.approx((-30.0, 60.0))
    # (b): square limits that hold every plotted point (the synthetic path is a straight line)
    (x0, x1), (y0, y1) = ax_b.get_xlim(), ax_b.get_ylim()
    assert x1 - x0 == pytest.approx(y1 - y0)
    for line in ax_b.get_lines():
        x, y = (np.asarray(v, dtype=float) for v in line.get_data())
        assert x0 <= np.nanmin(x) <= np.nanmax(x) <= x1  # NaN: no prediction at tick 0
        assert y0 <= np.nanmin(y) <= np.nanmax(y) <= y1


def test_phantom_figure_marks_the_least_clearance(paper: analysis.Dataset) -> None:
    fig = figures.phantom(paper, "spine")
    notes = [t.get_text() for t in fig.axes[0].texts]
    assert any("least clearance to anterior" in n for n in notes)
    least = paper.ok("spine")["min_clearance_mm"].min()
    assert any(f"{least:.2f} mm" in n for n in notes)


def test_results_csv_has_the_contract_columns_and_empty_missing_values(
    paper: analysis.Dataset, tmp_path: Path
) -> None:
    path = report.write_results(paper, tmp_path / "results.csv")
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0])[: len(CONTRACT)] == CONTRACT
    assert len(rows) == len(paper.trials)
    spine = [r for r in rows if r["protocol"] == "spine"]
    other = [r for r in rows if r["protocol"] != "spine"]
    assert all(r["min_clearance_mm"] == "" for r in other)  # empty, not zero
    assert all(float(r["min_clearance_mm"]) > 0 for r in spine)
    assert all(not Path(r["path"]).is_absolute() for r in rows)
    pred = [r for r in rows if r["protocol"] == "prediction"]
    assert all(float(r["rms_prediction_position_mm"]) == pytest.approx(1.0) for r in pred)


def test_headlines_compare_with_the_paper(paper: analysis.Dataset) -> None:
    heads = {h.claim.split(" (")[-1].rstrip(")"): h for h in report.headlines(paper)}
    # synthetic prediction error is 1 mm (> the paper's 0.69 mm)
    assert heads["prediction"].verdict == "no"
    assert "1.000" in heads["prediction"].ours
    # synthetic rate: proposed 0.3 mm, baseline1 0.6–1.2 mm, baseline2 0.9–1.8 mm RMS + noise
    assert heads["rate"].verdict == "no"
    # better than both recorded baselines, but the paper's claim is against all four
    assert heads["rate_under_noise"].verdict == "partly"
    assert heads["rate_under_noise"].ours.endswith("not recorded: baseline3, baseline4")
    # spine: 1 mm, 5°, clear of the walls: better than the paper on every count
    assert heads["spine"].verdict == "yes"


def test_proposed_best_against_every_baseline_is_a_yes(tmp_path: Path) -> None:
    cond = {"tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0}
    trials = [
        SynthTrial(
            "rate_under_noise", method, trial=k, conditions=cond, seed=10 * i + k,
            offset=(0.5e-3 * (1 + i), 0.0, 0.0), noise=0.2e-3,
        )
        for i, method in enumerate(["proposed", *report.PAPER_BASELINES])
        for k in range(2)
    ]  # fmt: skip
    data = analysis.load(write_set(tmp_path, trials))
    (head,) = [h for h in report.headlines(data) if "rate_under_noise" in h.claim]
    assert head.verdict == "yes", head.ours
    assert head.ours.startswith("proposed best (0.5")
    assert head.ours.count("***") == 4


def test_headlines_say_what_was_not_recorded(tmp_path: Path) -> None:
    data = analysis.load(write_set(tmp_path, [SynthTrial("prediction", "proposed")]))
    verdicts = [h.verdict for h in report.headlines(data)]
    assert verdicts == ["no", "not recorded", "not recorded", "not recorded"]


def test_the_report_says_when_quick_runs_are_among_the_recordings(tmp_path: Path) -> None:
    full = analysis.load(write_set(tmp_path / "a", [SynthTrial("prediction", "proposed")]))
    assert "Quick runs" not in report.report_markdown(full)
    quick = analysis.load(
        write_set(tmp_path / "b", [SynthTrial("prediction", "proposed", quick=True)])
    )
    assert "**Quick runs**" in report.report_markdown(quick)


def test_spine_clearance_lost_is_reported(tmp_path: Path) -> None:
    s = SynthTrial(
        "spine", "proposed", offset=(0.0, 7.5e-3, 0.0), boundaries={"anterior": wall(8e-3)},
        critical="anterior",
    )  # fmt: skip
    data = analysis.load(write_set(tmp_path, [s]))
    (head,) = [h for h in report.headlines(data) if "spine" in h.claim]
    # 7.5 mm RMS (worse than 1.18), 0° (better than 7.6°), 0.5 mm into the anterior wall
    assert head.verdict == "partly"
    assert "least clearance -0.50 mm" in head.ours


# ---- the command ----------------------------------------------------------------------------


def _run(*args: Any) -> Any:
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def test_magrun_figures_writes_figures_results_and_report(tmp_path: Path) -> None:
    root = paper_set(tmp_path / "rec")
    out = tmp_path / "figs"
    res = _run("figures", root, "--out", out)
    assert res.exit_code == 0, res.output
    names = sorted(p.name for p in out.iterdir())
    for fig in ("zernike", "prediction", "rate", "noise", "rate_under_noise", "spine"):
        for suffix, head in ((".png", b"\x89PNG"), (".pdf", b"%PDF")):
            path = out / f"{fig}{suffix}"
            assert path.read_bytes()[:8].startswith(head), path
            assert path.stat().st_size > 10_000, path
    assert {p.stem for p in out.glob("*.png")} == {
        "zernike", "prediction", "rate", "noise", "rate_under_noise", "spine"
    }  # fmt: skip
    assert "results.csv" in names
    text = (out / "report.md").read_text()
    assert "| claim | paper | ours | verdict |" in text
    assert "![rate_under_noise](rate_under_noise.png)" in text
    assert "0.69 mm, 6.0°" in text


def test_magrun_figures_goes_on_past_a_damaged_recording(tmp_path: Path) -> None:
    trials = [SynthTrial("prediction", "proposed", trial=k) for k in range(2)]
    root = write_set(tmp_path / "rec", trials)
    broken = root / "prediction" / trials[0].slug / "trial-0.mcap"
    broken.write_bytes(broken.read_bytes()[:300])
    res = _run("figures", root, "--out", tmp_path / "figs", "--no-zernike")
    assert res.exit_code == 1
    assert f"unreadable: {broken}" in res.output
    assert "truncated or damaged" in res.output
    assert "magrun recover" in res.output
    assert "Traceback" not in res.output
    assert (tmp_path / "figs" / "prediction.png").is_file()
    with (tmp_path / "figs" / "results.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["unreadable", "ok"]
    assert rows[0]["rms_position_mm"] == ""
    # the report names the damaged trial by the path results.csv gives it (relative to the
    # recordings), never by this machine's absolute path
    relative = str(broken.relative_to(root))
    assert rows[0]["path"] == relative
    text = (tmp_path / "figs" / "report.md").read_text()
    assert f"| {relative} |" in text
    assert str(tmp_path) not in text.split("## Trials not completed")[1]


def test_magrun_figures_on_an_empty_folder_is_an_input_error(tmp_path: Path) -> None:
    res = _run("figures", tmp_path)
    assert res.exit_code == 2
    assert "no recordings found" in res.output


def test_report_numbers_are_the_datasets(paper: analysis.Dataset) -> None:
    text = report.report_markdown(paper)
    spine = paper.ok("spine")
    assert f"{spine['rms_position_mm'].mean():.2f}" in text
    assert not math.isnan(spine["rms_position_mm"].mean())


def test_envelope_figure_maps_rms_and_clearance_over_rate_and_noise(tmp_path: Path) -> None:
    """A phantom protocol sweeping rate and noise both gets the envelope figure: RMS and least
    clearance per cell (the synthetic trials' offsets fix both), touches marked."""
    trials = []
    for rate in (3.0, 15.0):
        for sigma in (0.5, 3.0):
            into = 7.5e-3 if (rate, sigma) == (3.0, 3.0) else 6e-3  # touches in one cell
            trials.append(
                SynthTrial(
                    "envelope", "proposed",
                    conditions={"tracking_rate_hz": rate, "noise_sigma_mm": sigma},
                    offset=(0.0, into, 0.0), boundaries={"anterior": wall(8e-3)},
                    critical="anterior",
                )
            )  # fmt: skip
    data = analysis.load(write_set(tmp_path, trials))
    assert figures.figure_kind(data, "envelope") == "envelope"
    fig = figures.envelope(data, "envelope")
    rms_ax, clear_ax = fig.axes[0], fig.axes[1]
    rms_cells = sorted(float(t.get_text()) for t in rms_ax.texts)
    assert rms_cells == pytest.approx([6.0, 6.0, 6.0, 7.5], abs=0.01)
    texts = [t.get_text() for t in clear_ax.texts]
    assert "touched 1/1" in texts
    clear = sorted(float(t) for t in texts if not t.startswith("touched"))
    # the desired path runs 0 mm off the wall line offset; clearance = 8 − offset − D/2 − L·0
    assert clear[0] == pytest.approx(data.trials["min_clearance_mm"].min(), abs=0.01)


def _single_condition_set(root: Path) -> analysis.Dataset:
    """A `--quick`-like set: one condition (3 Hz, 2 mm), the proposed method and the PID,
    whose errors are 0.5 and 1.5 mm (the PID predicts nothing: NaN predictions)."""
    cond = {"tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0}
    trials = [
        SynthTrial("demo", "proposed", conditions=cond, offset=(0.5e-3, 0.0, 0.02)),
        SynthTrial("demo", "baseline2", conditions=cond, offset=(0.0, 1.5e-3, 0.05),
                   pred_offset=(math.nan,) * 3),
    ]  # fmt: skip
    return analysis.load(write_set(root, trials))


def test_a_single_condition_gets_the_comparison_figure(tmp_path: Path) -> None:
    """Every method's path over the desired one, its position and orientation errors over
    time and their RMS, under the paper's method names; no NaN in any title, every legend
    entry drawn."""
    data = _single_condition_set(tmp_path)
    assert figures.figure_kind(data, "demo") == "comparison"
    fig = figures.comparison(data, "demo")
    ax_a, ax_b, ax_c, ax_d, ax_e = fig.axes
    names = ["Proposed", "Baseline 2 (PID)"]
    assert [t.get_text() for t in ax_a.get_legend().get_texts()] == ["desired", *names]
    assert [line.get_label() for line in ax_a.get_lines()] == ["desired", *names]
    errors = {line.get_label(): np.asarray(line.get_ydata()) for line in ax_b.get_lines()}
    assert set(errors) == set(names)
    assert np.median(errors["Proposed"]) == pytest.approx(0.5, rel=1e-6)
    assert np.median(errors["Baseline 2 (PID)"]) == pytest.approx(1.5, rel=1e-6)
    # (c): the orientation error's magnitude over time, the samples' own
    turned = {line.get_label(): np.asarray(line.get_ydata()) for line in ax_c.get_lines()}
    assert set(turned) == set(names)
    for method, name in zip(("proposed", "baseline2"), names, strict=True):
        s = data.samples[data.samples["method"] == method]
        want = np.abs(s["orientation_error_deg"].to_numpy())
        np.testing.assert_allclose(turned[name], want, rtol=1e-12)
    # (d), (e): one point per trial at its RMS, the axes from zero, the ticks named
    for ax, column in ((ax_d, "rms_position_mm"), (ax_e, "rms_orientation_deg")):
        points = np.concatenate([c.get_offsets()[:, 1] for c in ax.collections])
        want = data.ok("demo").sort_values("method", ascending=False)[column]
        assert sorted(points) == pytest.approx(sorted(want), rel=1e-6)
        assert ax.get_ylim()[0] == 0
    assert [t.get_text() for t in ax_e.get_xticklabels()] == names
    titles = [ax.get_title() for ax in fig.axes] + [fig.get_suptitle()]
    assert not any("nan" in t.lower() for t in titles), titles
    assert fig.get_suptitle() == "tracking rate 3 Hz, noise σ 2 mm"


def test_the_comparison_shows_the_whole_desired_path_of_a_short_run(tmp_path: Path) -> None:
    """A trial that ran only the start of its path (a --quick run) is drawn over the whole
    desired path that the recording keeps, and panel (a) is framed on that whole path."""
    whole = [[-0.02 + 0.001 * k, 0.01 * math.sin(0.1 * k)] for k in range(60)]
    trials = [
        SynthTrial("demo", method, offset=(off, 0.0, 0.05), whole_path=whole,
                   conditions={"tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0})
        for method, off in (("proposed", 0.5e-3), ("baseline2", 1.5e-3))
    ]  # fmt: skip
    data = analysis.load(write_set(tmp_path, trials))
    ax_a = figures.comparison(data, "demo").axes[0]
    lines = {line.get_label(): line for line in ax_a.get_lines()}
    x, y = (np.asarray(v, dtype=float) for v in lines["desired (whole path)"].get_data())
    np.testing.assert_allclose(np.column_stack([x, y]), np.asarray(whole) * 1e3, rtol=1e-12)
    assert "desired (this run)" in lines
    (x0, x1), (y0, y1) = ax_a.get_xlim(), ax_a.get_ylim()
    assert x0 <= x.min() <= x.max() <= x1
    assert y0 <= y.min() <= y.max() <= y1


def test_the_prediction_figure_of_a_method_without_predictions_says_so(tmp_path: Path) -> None:
    data = _single_condition_set(tmp_path)
    rec = data.trials[data.trials["method"] == "baseline2"]
    only_pid = analysis.Dataset(
        trials=rec, samples=data.samples[data.samples["path"].isin(rec["path"])],
        recordings={p: data.recordings[p] for p in rec["path"]}, problems=[],
    )  # fmt: skip
    fig = figures.trajectories(only_pid, "demo")
    _, ax_b = fig.axes
    assert "no prediction" in ax_b.get_title()
    assert "NMPC predicted" not in [line.get_label() for line in ax_b.get_lines()]


def test_the_report_gives_overruns_in_percent_and_says_why_welch_is_missing(
    tmp_path: Path,
) -> None:
    data = _single_condition_set(tmp_path)
    text = report.report_markdown(data)
    table = text[text.index("| method |", text.index("## demo")) :]

    def cells(line: str) -> list[str]:
        return [c.strip() for c in line.strip().strip("|").split("|")]

    header = cells(table.splitlines()[0])
    row = cells(next(line for line in table.splitlines() if line.startswith("| proposed")))
    overruns = row[header.index("overruns")]
    assert overruns.endswith(" %"), overruns
    assert "needs at least two trials of each method" in text
    assert "Welch's t-test (Holm):" not in text


def test_a_sweep_of_two_conditions_gets_a_row_per_value_of_the_second(tmp_path: Path) -> None:
    """Rate × noise in an open workspace: one row per noise level, each row's lines the means
    of that level's trials only (not averaged over the levels)."""
    trials = [
        SynthTrial(
            "grid", method, conditions={"tracking_rate_hz": rate, "noise_sigma_mm": sigma},
            offset=(1e-3 * (1 + sigma) * (2 if method == "baseline2" else 1), 0.0, 0.0),
        )
        for method in ("proposed", "baseline2")
        for rate in (3.0, 25.5)
        for sigma in (0.0, 2.0)
    ]  # fmt: skip
    data = analysis.load(write_set(tmp_path, trials))
    assert figures.figure_kind(data, "grid") == "sweep"
    fig = figures.sweep(data, "grid")
    assert len(fig.axes) == 4  # two rows (σ = 0, 2 mm) × position, orientation
    want = data.ok("grid").groupby(["method", "noise_sigma_mm"])["rms_position_mm"].mean()
    for ax, sigma in ((fig.axes[0], 0.0), (fig.axes[2], 2.0)):
        assert f"noise σ = {sigma:g} mm" in ax.get_title()
        lines = {ln.get_label(): ln for ln in ax.get_lines() if not ln.get_label().startswith("_")}
        for method, name in (("proposed", "Proposed"), ("baseline2", "Baseline 2 (PID)")):
            _, y = lines[name].get_data()
            np.testing.assert_allclose(y, want[(method, sigma)], rtol=1e-9)


def test_prediction_headline_is_against_the_measured_pose_where_recorded() -> None:
    """The paper measured its prediction error against the camera's pose: where the trials
    have that error (`rms_prediction_measured_*`) the headline uses it, within the paper's
    figure + 0.1 mm / 1° ("yes" at 0.75 mm, 6.5°), and gives the error against the truth
    beside it; above that it is a "no"."""
    import pandas as pd

    from analysis.load import Dataset

    def head(mm: float, deg: float) -> report.Headline:
        trials = pd.DataFrame(
            {"protocol": "prediction", "method": "proposed", "status": "ok",
             "tracking_rate_hz": 25.5, "noise_sigma_mm": 0.0, "noise_sigma_deg": 0.0,
             "trial": [0, 1], "rms_position_mm": 0.3, "rms_orientation_deg": 3.0,
             "rms_prediction_position_mm": [0.40, 0.44], "rms_prediction_orientation_deg": 3.0,
             "rms_prediction_measured_position_mm": mm,
             "rms_prediction_measured_orientation_deg": deg}
        )  # fmt: skip
        data = Dataset(trials=trials, samples=pd.DataFrame())
        (h,) = [h for h in report.headlines(data) if "prediction" in h.claim]
        return h

    yes = head(0.75, 6.5)
    assert yes.verdict == "yes"
    assert yes.ours.startswith("0.750")
    assert "against the truth: 0.420 mm" in yes.ours
    assert head(0.80, 6.5).verdict == "no"
    assert head(0.75, 7.1).verdict == "no"


def test_a_log_scaled_sweep_draws_the_trials_range_not_a_negative_sd(tmp_path: Path) -> None:
    """A method that loses the robot in one trial (60 mm) and not in the other (1 mm) puts the
    sweep on a log axis, where its mean − sd (−11 mm) cannot be drawn: the bars there are the
    trials' range, every end positive and equal to a trial's RMS; a linear axis keeps ± 1 sd."""
    offsets = {("baseline2", 0): 60e-3, ("baseline2", 1): 1e-3}
    trials = [
        SynthTrial(
            "lost", method, trial=k, conditions={"tracking_rate_hz": rate, "noise_sigma_mm": 2.0},
            offset=(offsets.get((method, k), 0.5e-3 * (1 + 0.2 * k)) if rate == 3.0 else 0.4e-3,
                    0.0, 0.0),
        )
        for method in ("proposed", "baseline2")
        for rate in (3.0, 25.5)
        for k in (0, 1)
    ]  # fmt: skip
    data = analysis.load(write_set(tmp_path, trials))
    fig = figures.sweep(data, "lost")
    ax = fig.axes[0]
    assert ax.get_yscale() == "log"
    rms = data.ok("lost")
    lost = rms[(rms["method"] == "baseline2") & (rms["tracking_rate_hz"] == 3.0)]["rms_position_mm"]
    assert float(lost.mean() - lost.std()) < 0  # what ± sd would have drawn
    ends = np.vstack([seg for c in ax.collections for seg in c.get_segments()])
    assert np.all(ends[:, 1] > 0)
    at3 = ends[np.isclose(ends[:, 0], 3.0), 1]
    np.testing.assert_allclose(at3.max(), lost.max(), rtol=1e-9)
    np.testing.assert_allclose(
        at3.min(), rms[rms["tracking_rate_hz"] == 3.0]["rms_position_mm"].min(), rtol=1e-9
    )  # the lowest end: a trial, not mean − sd
    assert any("their range" in t.get_text() for t in ax.texts)
    assert any("± 1 sd" in t.get_text() for t in fig.axes[1].texts)  # orientation: linear


def test_the_report_never_shows_another_systems_field_figure(tmp_path: Path) -> None:
    """Recordings of another coil system get that system's own Zernike figure where its
    folder has the fit's figure data, and the report says whose fit it is; where it has
    none, no Zernike figure at all (a note says how to make one), never the paper rig's."""
    from magrun.field.fitting import FIGURE_FILE

    folder = tmp_path / "octo"
    folder.mkdir()
    trials = [SynthTrial("demo", "proposed", system=str(folder))]
    root = write_set(tmp_path / "rec", trials)
    res = _run("figures", root, "--out", tmp_path / "without")
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "without" / "zernike.png").exists()
    assert f"the recordings are of {folder}" in res.output
    assert "## Zernike field model" not in (tmp_path / "without" / "report.md").read_text()
    shipped = Path(figures.__file__).parents[1] / "magrun" / "field" / "data" / FIGURE_FILE
    (folder / FIGURE_FILE).write_bytes(shipped.read_bytes())
    res = _run("figures", root, "--out", tmp_path / "with")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "with" / "zernike.png").is_file()
    assert f"The field fit of {folder}." in (tmp_path / "with" / "report.md").read_text()
    # the paper's rig: the shipped fit, named as such
    paper = write_set(tmp_path / "paper", [SynthTrial("demo", "proposed")])
    res = _run("figures", paper, "--out", tmp_path / "paper-figs")
    assert res.exit_code == 0, res.output
    text = (tmp_path / "paper-figs" / "report.md").read_text()
    assert "The field fit of the paper's rig (the fit shipped with magrun)." in text
