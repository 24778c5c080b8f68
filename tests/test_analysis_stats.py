"""analysis.stats against scipy and hand computations on the same numbers."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from analysis import stats


def _samples(rng: np.random.Generator) -> pd.DataFrame:
    rows = []
    for rate, shift in ((3.0, 1.0), (25.5, 0.1)):
        for method, scale in (("proposed", 1.0), ("b1", 1.3), ("b2", 1.05), ("b3", 3.0)):
            n = 150 + int(10 * scale)
            x = rng.gamma(2.0, scale * shift, size=n)
            rows.append(
                pd.DataFrame(
                    {
                        "protocol": "rate",
                        "method": method,
                        "tracking_rate_hz": rate,
                        "noise_sigma_mm": 2.0,
                        "noise_sigma_deg": 0.0,
                        "position_error_mm": x,
                    }
                )
            )
    return pd.concat(rows, ignore_index=True)


@pytest.mark.parametrize(
    ("p", "mark"),
    [(0.0, "***"), (9.99e-4, "***"), (1e-3, "**"), (0.0099, "**"), (0.01, "*"), (0.049, "*"),
     (0.05, "ns"), (0.7, "ns"), (math.nan, "")],
)  # fmt: skip
def test_stars_follow_the_paper(p: float, mark: str) -> None:
    assert stats.stars(p) == mark


def test_mann_whitney_matches_scipy_and_holm_matches_hand(rng: np.random.Generator) -> None:
    samples = _samples(rng)
    out = stats.compare_methods(samples)
    assert len(out) == 2 * 3
    assert set(out["reference"]) == {"proposed"}
    for rate, block in out.groupby("tracking_rate_hz"):
        cond = samples[samples["tracking_rate_hz"] == rate]
        a = cond.loc[cond["method"] == "proposed", "position_error_mm"].to_numpy()
        raw = []
        for row in block.itertuples():
            b = cond.loc[cond["method"] == row.method, "position_error_mm"].to_numpy()
            ref = sps.mannwhitneyu(a, b, alternative="two-sided")
            assert row.u == pytest.approx(ref.statistic, rel=1e-12)
            assert row.p == pytest.approx(ref.pvalue, rel=1e-9)
            assert (row.n_ref, row.n_other) == (a.size, b.size)
            raw.append(row.p)
        # Holm by hand: sort, multiply the i-th smallest by (m − i), running max, cap at 1
        order = np.argsort(raw)
        m = len(raw)
        adjusted = np.empty(m)
        running = 0.0
        for i, j in enumerate(order):
            running = max(running, (m - i) * raw[j])
            adjusted[j] = min(running, 1.0)
        np.testing.assert_allclose(block["p_holm"], adjusted, rtol=1e-12)
        assert list(block["stars"]) == [stats.stars(p) for p in adjusted]


def test_rank_biserial_counts_pairs(rng: np.random.Generator) -> None:
    # r = (pairs where the reference is smaller − pairs where it is larger) / (n1 n2)
    a = rng.integers(0, 6, size=40).astype(float)  # ties on purpose
    b = rng.integers(1, 8, size=55).astype(float)
    diff = a[:, None] - b[None, :]
    want = (np.sum(diff < 0) - np.sum(diff > 0)) / diff.size
    df = pd.DataFrame(
        {"protocol": "x", "method": ["proposed"] * a.size + ["other"] * b.size,
         "tracking_rate_hz": 3.0, "noise_sigma_mm": 0.0, "noise_sigma_deg": 0.0,
         "position_error_mm": np.concatenate([a, b])}
    )  # fmt: skip
    got = stats.compare_methods(df)["effect_rb"].iloc[0]
    assert got == pytest.approx(want, abs=1e-12)
    assert got > 0  # the reference's errors are smaller here


def test_welch_matches_scipy_and_needs_two_trials() -> None:
    trials = pd.DataFrame(
        {
            "protocol": "rate", "tracking_rate_hz": 3.0, "noise_sigma_mm": 2.0,
            "noise_sigma_deg": 0.0, "status": "ok",
            "method": ["proposed"] * 3 + ["b1"] * 3 + ["b2"],
            "rms_position_mm": [1.0, 1.2, 0.9, 2.0, 2.5, 1.7, 3.0],
        }
    )  # fmt: skip
    out = stats.trial_tests(trials).set_index("method")
    ref = sps.ttest_ind([1.0, 1.2, 0.9], [2.0, 2.5, 1.7], equal_var=False)
    assert out.loc["b1", "t"] == pytest.approx(ref.statistic, rel=1e-12)
    assert out.loc["b1", "p"] == pytest.approx(ref.pvalue, rel=1e-12)
    assert out.loc["b1", "p_holm"] == pytest.approx(ref.pvalue, rel=1e-12)  # family of one
    assert math.isnan(out.loc["b2", "p"])
    assert out.loc["b2", "stars"] == ""
    # effect sizes: Cohen's d by hand; Mann–Whitney exact on 3 vs 3 with no ties: every
    # reference value below every other gives U = 0, p = 2/C(6,3) = 0.1, r = +1
    a, b = np.array([1.0, 1.2, 0.9]), np.array([2.0, 2.5, 1.7])
    d = (b.mean() - a.mean()) / math.sqrt((a.var(ddof=1) + b.var(ddof=1)) / 2)
    assert out.loc["b1", "d"] == pytest.approx(d, rel=1e-12)
    assert out.loc["b1", "p_mw"] == pytest.approx(0.1, rel=1e-12)
    assert out.loc["b1", "effect_rb"] == pytest.approx(1.0)


def test_summary_is_mean_and_sample_std_across_trials() -> None:
    trials = pd.DataFrame(
        {
            "protocol": "p", "method": "m", "tracking_rate_hz": [3.0, 3.0, 3.0, 5.0],
            "noise_sigma_mm": 0.0, "noise_sigma_deg": 0.0, "status": ["ok", "ok", "failed", "ok"],
            "rms_position_mm": [1.0, 3.0, 99.0, 4.0], "rms_orientation_deg": [2.0, 2.0, 0.0, 1.0],
        }
    )  # fmt: skip
    s = stats.summarize(trials).set_index("tracking_rate_hz")
    assert s.loc[3.0, "rms_position_mm_mean"] == pytest.approx(2.0)
    assert s.loc[3.0, "rms_position_mm_std"] == pytest.approx(math.sqrt(2.0))
    assert s.loc[3.0, "rms_position_mm_count"] == 2  # the failed trial is left out
    assert math.isnan(s.loc[5.0, "rms_position_mm_std"])
