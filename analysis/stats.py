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

import gc
import math
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd
from scipy import stats as sps
from statsmodels.stats.multitest import multipletests

from analysis.load import CONDITIONS

STAR_LEVELS = ((1e-3, "***"), (1e-2, "**"), (5e-2, "*"))


def holm(p: Sequence[float]) -> np.ndarray:
    """Holm–Bonferroni adjusted p-values of one family (statsmodels ``multipletests``).

    statsmodels collects the garbage after a Holm correction (``gc.collect()``); that walks
    every object the process holds, a quarter of a second in one that holds many (a test
    session). The objects are frozen for the call, so that the collection walks only the
    correction's own."""
    gc.freeze()
    try:
        return np.asarray(multipletests(list(p), method="holm")[1], dtype=float)
    finally:
        gc.unfreeze()


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


PairTest = Callable[[np.ndarray, np.ndarray], dict[str, float] | None]


def _against_reference(
    frame: pd.DataFrame,
    value: str,
    reference: str | None,
    by: Sequence[str],
    test: PairTest,
    cols: list[str],
) -> pd.DataFrame:
    """``test(ref values, other values)`` per condition and other method, Holm-corrected.

    ``test`` returns the row's statistics (with ``p``; NaN when it cannot be computed) or
    None to leave the pair out. Holm runs per condition over the finite p-values.
    """
    rows: list[dict[str, object]] = []
    keys = list(by)
    for cond, group in frame.groupby(keys, dropna=False, sort=True):
        ref, others = _order(group["method"].dropna().unique().tolist(), reference)
        a = group.loc[group["method"] == ref, value].dropna().to_numpy(dtype=float)
        where = dict(zip(keys, cond if isinstance(cond, tuple) else (cond,), strict=True))
        block: list[dict[str, object]] = []
        for other in others:
            b = group.loc[group["method"] == other, value].dropna().to_numpy(dtype=float)
            result = test(a, b)
            if result is not None:
                block.append(
                    {**where, "reference": ref, "method": other, "value": value,
                     "n_ref": a.size, "n_other": b.size, **result, "p_holm": math.nan,
                     "stars": ""}
                )  # fmt: skip
        finite = [r for r in block if math.isfinite(float(r["p"]))]  # type: ignore[arg-type]
        if finite:
            adjusted = holm([float(r["p"]) for r in finite])  # type: ignore[arg-type]
            for r, ph in zip(finite, adjusted, strict=True):
                r["p_holm"], r["stars"] = float(ph), stars(float(ph))
        rows.extend(block)
    return pd.DataFrame(rows, columns=cols)


def _mann_whitney(a: np.ndarray, b: np.ndarray) -> dict[str, float] | None:
    if a.size == 0 or b.size == 0:
        return None
    res = sps.mannwhitneyu(a, b, alternative="two-sided", method="asymptotic")
    return {
        "median_ref": float(np.median(a)),
        "median_other": float(np.median(b)),
        "u": float(res.statistic),
        "p": float(res.pvalue),
        "effect_rb": rank_biserial(float(res.statistic), a.size, b.size),
    }


def _welch(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Welch's t-test (``t``, ``p``), its effect size Cohen's d on the average variance
    (``d`` = (mean_b − mean_a) / √((s_a² + s_b²)/2): > 0 when the reference's values are
    smaller), and the Mann–Whitney U of the same per-trial values (``p_mw``, exact for
    small samples without ties, and ``effect_rb``)."""
    nan = math.nan
    out = {"t": nan, "p": nan, "d": nan, "p_mw": nan, "effect_rb": nan}
    if a.size < 2 or b.size < 2:
        return out
    res = sps.ttest_ind(a, b, equal_var=False)
    spread = math.sqrt((float(np.var(a, ddof=1)) + float(np.var(b, ddof=1))) / 2)
    mw = sps.mannwhitneyu(a, b, alternative="two-sided", method="auto")
    out.update(
        t=float(res.statistic), p=float(res.pvalue),
        d=(float(np.mean(b)) - float(np.mean(a))) / spread if spread > 0 else nan,
        p_mw=float(mw.pvalue), effect_rb=rank_biserial(float(mw.statistic), a.size, b.size),
    )  # fmt: skip
    return out


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
    if samples.empty:
        return pd.DataFrame(columns=cols)
    return _against_reference(samples, value, reference, by, _mann_whitney, cols)


def trial_tests(
    trials: pd.DataFrame,
    value: str = "rms_position_mm",
    reference: str | None = "proposed",
    by: Sequence[str] = ("protocol", *CONDITIONS),
) -> pd.DataFrame:
    """Welch's t-test of per-trial ``value`` between ``reference`` and each other method,
    with Cohen's ``d`` and the Mann–Whitney U of the same values (``p_mw``, ``effect_rb``):
    one value per trial, the unit of replication.

    Holm-corrected (Welch's p) within each condition. NaN where a method has fewer than two
    trials.
    """
    cols = [
        *by, "reference", "method", "value", "n_ref", "n_other", "t", "p", "d", "p_mw",
        "effect_rb", "p_holm", "stars",
    ]  # fmt: skip
    return _against_reference(trials, value, reference, by, _welch, cols)


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
