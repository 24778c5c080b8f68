"""Statistics between methods: the paper's per-sample comparison, and trial-level summaries.

Which test, and why. The paper's violin plot (Fig. "results_mimic") compares the methods'
per-sample errors at one condition. Those errors are magnitudes (≥ 0), skewed and heavy-tailed
(a controller that loses the robot for a while adds a long tail), so a t-test's normality
assumption does not hold; the samples of two methods are independent of each other. We use the
two-sided **Mann–Whitney U** test (scipy.stats.mannwhitneyu, asymptotic p-value with tie and
continuity correction) with its **rank-biserial correlation** as the effect size
(r = 1 − 2U/(n₁n₂) ∈ [−1, 1]; r > 0 means the first method's errors tend to be *smaller*;
|r| ≈ 0.1 small, 0.3 medium, 0.5 large), and correct each condition's family of comparisons
with **Holm–Bonferroni** (statsmodels ``multipletests``), which controls the family-wise error
without assuming independence between the comparisons.

A caveat we state rather than hide: consecutive samples of one trial are autocorrelated, so
the effective sample size is far smaller than the number of ticks and per-sample p-values
overstate the evidence. :func:`trial_tests` therefore also compares the per-trial RMS errors
(Welch's t-test, which does not assume equal variances, on n = trials per method), the unit
of replication; with three trials per method it has little power, and both are reported.

Star notation, as in the paper: ``***`` p < 0.001, ``**`` p < 0.01, ``*`` p < 0.05, ``ns``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats as sps
from statsmodels.stats.multitest import multipletests

from analysis.load import CONDITIONS

STAR_LEVELS = ((1e-3, "***"), (1e-2, "**"), (5e-2, "*"))


def stars(p: float) -> str:
    """The paper's notation of a p-value: ``***`` < 0.001, ``**`` < 0.01, ``*`` < 0.05."""
    if not math.isfinite(p):
        return ""
    for level, mark in STAR_LEVELS:
        if p < level:
            return mark
    return "ns"


def rank_biserial(u: float, n1: int, n2: int) -> float:
    """Rank-biserial correlation from the Mann–Whitney U of the first sample.

    With scipy's U (the count of pairs where the first sample is larger), r = 1 − 2U/(n₁n₂):
    +1 when every value of the first sample is smaller than every value of the second.
    """
    return 1.0 - 2.0 * u / (n1 * n2)


def _order(methods: Sequence[str], reference: str | None) -> tuple[str, list[str]]:
    ordered = sorted(methods)
    ref = reference if reference in ordered else ("proposed" if "proposed" in ordered else None)
    ref = ref or ordered[0]
    return ref, [m for m in ordered if m != ref]


def compare_methods(
    samples: pd.DataFrame,
    value: str = "position_error_mm",
    reference: str | None = "proposed",
    by: Sequence[str] = ("protocol", *CONDITIONS),
) -> pd.DataFrame:
    """Mann–Whitney U of ``reference`` against every other method, per condition.

    Returns one row per (condition, other method): ``n_ref``, ``n_other``, medians, ``u``,
    ``p``, ``p_holm`` (Holm-corrected within the condition), ``effect_rb`` (rank-biserial
    correlation, > 0 when the reference's errors are smaller), ``stars`` (of ``p_holm``).
    """
    cols = [
        *by, "reference", "method", "value", "n_ref", "n_other", "median_ref", "median_other",
        "u", "p", "p_holm", "effect_rb", "stars",
    ]  # fmt: skip
    rows: list[dict[str, object]] = []
    if samples.empty:
        return pd.DataFrame(columns=cols)
    keys = list(by)
    for cond, group in samples.groupby(keys, dropna=False, sort=True):
        ref, others = _order(group["method"].dropna().unique().tolist(), reference)
        a = group.loc[group["method"] == ref, value].dropna().to_numpy()
        block: list[dict[str, object]] = []
        for other in others:
            b = group.loc[group["method"] == other, value].dropna().to_numpy()
            if a.size == 0 or b.size == 0:
                continue
            res = sps.mannwhitneyu(a, b, alternative="two-sided", method="asymptotic")
            block.append(
                {
                    **dict(zip(keys, cond if isinstance(cond, tuple) else (cond,), strict=True)),
                    "reference": ref,
                    "method": other,
                    "value": value,
                    "n_ref": a.size,
                    "n_other": b.size,
                    "median_ref": float(np.median(a)),
                    "median_other": float(np.median(b)),
                    "u": float(res.statistic),
                    "p": float(res.pvalue),
                    "effect_rb": rank_biserial(float(res.statistic), a.size, b.size),
                }
            )
        if block:
            p_holm = multipletests([r["p"] for r in block], method="holm")[1]
            for r, ph in zip(block, p_holm, strict=True):
                r["p_holm"] = float(ph)
                r["stars"] = stars(float(ph))
        rows.extend(block)
    return pd.DataFrame(rows, columns=cols)


def trial_tests(
    trials: pd.DataFrame,
    value: str = "rms_position_mm",
    reference: str | None = "proposed",
    by: Sequence[str] = ("protocol", *CONDITIONS),
) -> pd.DataFrame:
    """Welch's t-test of per-trial ``value`` between ``reference`` and each other method.

    Holm-corrected within each condition. NaN where a method has fewer than two trials.
    """
    cols = [*by, "reference", "method", "value", "n_ref", "n_other", "t", "p", "p_holm", "stars"]
    rows: list[dict[str, object]] = []
    keys = list(by)
    for cond, group in trials.groupby(keys, dropna=False, sort=True):
        ref, others = _order(group["method"].dropna().unique().tolist(), reference)
        a = group.loc[group["method"] == ref, value].dropna().to_numpy(dtype=float)
        block: list[dict[str, object]] = []
        for other in others:
            b = group.loc[group["method"] == other, value].dropna().to_numpy(dtype=float)
            t = p = math.nan
            if a.size >= 2 and b.size >= 2:
                res = sps.ttest_ind(a, b, equal_var=False)
                t, p = float(res.statistic), float(res.pvalue)
            block.append(
                {
                    **dict(zip(keys, cond if isinstance(cond, tuple) else (cond,), strict=True)),
                    "reference": ref, "method": other, "value": value,
                    "n_ref": a.size, "n_other": b.size, "t": t, "p": p,
                }
            )  # fmt: skip
        finite = [i for i, r in enumerate(block) if math.isfinite(float(r["p"]))]  # type: ignore[arg-type]
        adjusted = (
            multipletests([block[i]["p"] for i in finite], method="holm")[1] if finite else []
        )
        for r in block:
            r["p_holm"], r["stars"] = math.nan, ""
        for i, ph in zip(finite, adjusted, strict=True):
            block[i]["p_holm"], block[i]["stars"] = float(ph), stars(float(ph))
        rows.extend(block)
    return pd.DataFrame(rows, columns=cols)


def summarize(
    trials: pd.DataFrame,
    values: Sequence[str] = ("rms_position_mm", "rms_orientation_deg"),
    by: Sequence[str] = ("protocol", "method", *CONDITIONS),
) -> pd.DataFrame:
    """Mean, standard deviation (ddof = 1) and count across trials, per method and condition."""
    ok = trials[trials["status"] == "ok"] if "status" in trials else trials
    agg = ok.groupby(list(by), dropna=False, sort=True)[list(values)].agg(["mean", "std", "count"])
    agg.columns = [f"{v}_{s}" for v, s in agg.columns]
    return agg.reset_index()
