"""The paper's figures, drawn from recordings (and, for ``zernike``, from the field-fit data).

Every function returns a :class:`matplotlib.figure.Figure` (no pyplot state, no display
needed); :func:`save` writes it as PNG and PDF. :func:`draw_all` picks the figure kind of each
protocol in a :class:`~analysis.load.Dataset` from what its recordings hold:

- boundaries in the recordings (a phantom): ``phantom`` — desired and actual paths inside the
  boundaries, the point of least clearance to the critical boundary marked (paper Fig. 10);
- a swept condition (several tracking rates or noise levels): ``sweep`` — RMS position and
  orientation error against it, one line per method, mean ± std across trials (Figs. 7–9);
  when the sweep is over tracking rate with noise, a violin plot of the per-sample errors at
  the lowest rate with Holm-corrected Mann–Whitney stars against the proposed method (Fig. 9c);
- one condition and several methods (every ``--quick`` demo): ``comparison`` — (a) each
  method's actual path over the desired path, (b) each method's position error over time,
  (c) RMS position error per method, every trial a point, mean ± std;
- otherwise (one method): ``trajectories`` — (a) the workspace with the desired path, (b)
  actual and NMPC-predicted paths (Fig. 6).

Units on every axis: mm, degrees, Hz, mT.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import seaborn as sns
from matplotlib import colors as mcolors
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from analysis import stats
from analysis.load import Dataset, Recording

#: colours of the paper's figures: desired green, actual red/blue, predicted red, walls purple
COLORS = {
    "desired": "#2ca02c",  # green
    "actual": "#d62728",  # red (spine figure)
    "actual_vs_predicted": "#1f77b4",  # blue (prediction figure, where the prediction is red)
    "predicted": "#d62728",
    "boundary": "#7b3fa0",  # purple
    "critical": "#b0179a",
}
CONDITION_LABELS = {
    "tracking_rate_hz": "tracking rate (Hz)",
    "noise_sigma_mm": "noise σ (mm)",
    "noise_sigma_deg": "noise σ (deg)",
}
FORMATS = ("png", "pdf")


def _style() -> None:
    sns.set_theme(context="paper", style="whitegrid", font_scale=1.1)


def save(fig: Figure, out: str | Path, name: str) -> list[Path]:
    """Write ``fig`` as ``out/name.png`` (200 dpi) and ``out/name.pdf``; return the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for fmt in FORMATS:
        p = out / f"{name}.{fmt}"
        meta: dict[str, Any] = {"CreationDate": None} if fmt == "pdf" else {}
        fig.savefig(p, dpi=200, bbox_inches="tight", metadata=meta)
        paths.append(p)
    return paths


#: the paper's names of its methods (Section II-D), as the figures show them; another
#: method (a lab's own) is shown by its id
METHOD_NAMES = {
    "proposed": "Proposed",
    "baseline1": "Baseline 1",
    "baseline2": "Baseline 2 (PID)",
    "baseline3": "Baseline 3",
    "baseline4": "Baseline 4",
    "baseline5": "Baseline 5",
}


def method_name(method: str) -> str:
    """The name a figure shows for ``method`` (:data:`METHOD_NAMES`, else the id)."""
    return METHOD_NAMES.get(method, method)


def _named(
    df: pd.DataFrame, methods: list[str], palette: dict[str, Any]
) -> tuple[pd.DataFrame, list[str], dict[str, Any]]:
    """``df``, the method order and the palette with the methods' display names, for the
    seaborn plots whose ticks and legends show the ``method`` column's values."""
    return (
        df.assign(method=df["method"].map(method_name)),
        [method_name(m) for m in methods],
        {method_name(m): c for m, c in palette.items()},
    )


def _method_order(methods: list[str]) -> list[str]:
    return sorted(methods, key=lambda m: (m != "proposed", m))


def _palette(methods: list[str]) -> dict[str, Any]:
    colors = sns.color_palette("colorblind", n_colors=max(len(methods), 1))
    return dict(zip(_method_order(methods), colors, strict=False))


# --------------------------------------------------------------------------------------------
# zernike (paper Fig. 4): from the data `magrun field fit` writes


def zernike(data: dict[str, np.ndarray], coil_type: str | None = None) -> Figure:
    """(a) MAE and R² vs order per coil type, (b) |B| of one coil at 1 A, (c) |fit error|.

    ``data`` holds, per coil type ``c``: ``c_orders``, ``c_mae_mT``, ``c_r2``, ``c_x_mm``,
    ``c_y_mm``, ``c_field_mT`` (nx, ny) and ``c_error_mT`` (nx, ny), as in
    ``magrun/field/data/zernike_figure.npz``.
    """
    _style()
    types = [k[: -len("_orders")] for k in data if k.endswith("_orders")]
    if coil_type is None:  # the paper's small coil, else the first type the fit has
        coil_type = "small" if "small" in types else (types[0] if types else "small")
    if coil_type not in types:
        raise KeyError(f"no fit data for coil type {coil_type!r} (have {types})")
    fig = Figure(figsize=(15, 4.4), layout="constrained")
    ax_a, ax_b, ax_c = fig.subplots(1, 3, width_ratios=[1.2, 1, 1])
    ax_r2 = ax_a.twinx()
    palette = sns.color_palette("colorblind", n_colors=len(types))
    for color, t in zip(palette, types, strict=True):
        orders = data[f"{t}_orders"]
        ax_a.plot(orders, data[f"{t}_mae_mT"], "-o", color=color, label=f"{t}: MAE")
        ax_r2.plot(orders, data[f"{t}_r2"], "--s", color=color, label=f"{t}: R²", ms=4)
    ax_a.set(xlabel="Zernike order", ylabel="MAE at 1 A (mT)", title="(a) fit quality vs order")
    ax_r2.set_ylabel("R²")
    ax_r2.set_ylim(0, 1.02)
    ax_r2.grid(False)
    handles = ax_a.get_legend_handles_labels()[0] + ax_r2.get_legend_handles_labels()[0]
    labels = ax_a.get_legend_handles_labels()[1] + ax_r2.get_legend_handles_labels()[1]
    ax_a.legend(handles, labels, fontsize=7, ncol=2, loc="center right")
    x, y = data[f"{coil_type}_x_mm"], data[f"{coil_type}_y_mm"]
    extent = (x[0], x[-1], y[0], y[-1])
    for ax, key, title, cmap in (
        (ax_b, "field_mT", f"(b) |B|, {coil_type} coil at 1 A", "viridis"),
        (ax_c, "error_mT", "(c) |B_fit − B_ref| at 1 A", "magma"),
    ):
        # the maps are indexed [ix, iy]; imshow wants rows = y
        im = ax.imshow(data[f"{coil_type}_{key}"].T, origin="lower", extent=extent, cmap=cmap)
        ax.set(xlabel="x (mm)", ylabel="y (mm)", title=title, aspect="equal")
        ax.grid(False)
        fig.colorbar(im, ax=ax, label="mT", shrink=0.85)
    return fig


# --------------------------------------------------------------------------------------------
# trajectories (paper Fig. 6): the prediction experiment


def _first(data: Dataset, protocol: str) -> Recording:
    ok = data.ok(protocol).sort_values(["method", "trial"])
    paths = [p for p in ok["path"] if p in data.recordings]
    if not paths:
        raise ValueError(f"no readable recordings of protocol {protocol!r}")
    return data.recordings[paths[0]]


def _xy_mm(df: pd.DataFrame, suffix: str = "") -> tuple[np.ndarray, np.ndarray]:
    return df[f"x{suffix}"].to_numpy() * 1e3, df[f"y{suffix}"].to_numpy() * 1e3


def trajectories(data: Dataset, protocol: str) -> Figure:
    """(a) The workspace and the desired path; (b) actual and NMPC-predicted paths (trial 0).

    (a) shows the whole workspace square (from the recording's ``workspace.half_width_m``),
    (b) is zoomed to the paths.
    """
    _style()
    rec = _first(data, protocol)
    s = data.samples[data.samples["path"] == str(rec.path)]
    fig = Figure(figsize=(11, 5.2), layout="constrained")
    # (a) the whole workspace square; (b) zoomed to the paths, where the millimetres show
    ax_a, ax_b = fig.subplots(1, 2)
    half = rec.workspace.get("half_width_m")
    if isinstance(half, (int, float)) and half > 0:
        h = half * 1e3
        ax_a.add_patch(
            Rectangle((-h, -h), 2 * h, 2 * h, fill=False, ec="#e0b000", lw=2, label="workspace")
        )
    for ax in (ax_a, ax_b):
        _draw_boundaries(ax, rec)
        ax.set(xlabel="x (mm)", ylabel="y (mm)", aspect="equal")
    ax_a.plot(*_xy_mm(s, "_des"), color=COLORS["desired"], lw=2, label="desired")
    ax_a.set_title(f"(a) workspace and desired path ({rec.trial.get('robot', 'robot')})")
    ax_b.plot(*_xy_mm(s, "_des"), color=COLORS["desired"], lw=1, alpha=0.6, label="desired")
    ax_b.plot(*_xy_mm(s), color=COLORS["actual_vs_predicted"], lw=1.5, label="actual")
    r = data.trials.loc[data.trials["path"] == str(rec.path)].iloc[0]
    rms_pred = float(r.get("rms_prediction_position_mm", math.nan))
    if math.isfinite(rms_pred) and np.isfinite(s["x_pred"]).any():
        ax_b.plot(*_xy_mm(s, "_pred"), color=COLORS["predicted"], lw=1, ls="--",
                  label="NMPC predicted")  # fmt: skip
        ax_b.set_title(
            f"(b) actual vs predicted: RMS {rms_pred:.2f} mm, "
            f"{r['rms_prediction_orientation_deg']:.1f}°"
        )
    else:  # a method that predicts nothing (the PID)
        name = method_name(str(rec.trial.get("method", "")))
        ax_b.set_title(f"(b) actual path ({name}: no prediction)")
    _square_limits(ax_b, s, ("", "_pred", "_des"))
    for ax in (ax_a, ax_b):
        ax.legend(loc="best", fontsize=8)
    return fig


def _square_limits(ax: Any, s: pd.DataFrame, suffixes: tuple[str, ...]) -> None:
    """Square axis limits around the paths (10 % and 1 mm margin), whatever their shape."""
    xy = np.vstack([np.column_stack(_xy_mm(s, suffix)) for suffix in suffixes])
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    centre, half = (lo + hi) / 2, float(np.max(hi - lo)) / 2 * 1.1 + 1.0
    ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half))


def _draw_boundaries(ax: Any, rec: Recording) -> None:
    for name, line in rec.boundaries.items():
        critical = name == rec.critical
        ax.plot(
            line[:, 0] * 1e3, line[:, 1] * 1e3,
            color=COLORS["critical" if critical else "boundary"], lw=2.2 if critical else 1.4,
            label=f"{name} (critical)" if critical else None,
        )  # fmt: skip


# --------------------------------------------------------------------------------------------
# comparison: one condition, several methods


def _representative(data: Dataset, protocol: str, method: str) -> Recording:
    """The method's trial with the median RMS position error (not the best one)."""
    ok = data.ok(protocol)
    ok = ok[(ok["method"] == method) & ok["path"].isin(list(data.recordings))]
    ok = ok.sort_values("rms_position_mm")
    return data.recordings[ok["path"].iloc[(len(ok) - 1) // 2]]


def comparison(data: Dataset, protocol: str) -> Figure:
    """The methods side by side under the protocol's one condition: (a) each method's actual
    path over the desired path, (b) position and (c) orientation error over time, (d) RMS
    position and (e) RMS orientation error per method.

    (a)–(c) show each method's trial with the median RMS position error; (d), (e) every
    trial. (a) draws the whole desired path where the recording has it and is framed on it:
    a trial that ran only the path's start (``--quick``) is shown where it sits in the run.
    Methods carry the paper's names (:data:`METHOD_NAMES`).
    """
    _style()
    trials = data.ok(protocol)
    methods = _method_order(trials["method"].unique().tolist())
    palette = _palette(methods)
    fig = Figure(figsize=(15, 7.6), layout="constrained")
    grid = fig.add_gridspec(2, 3, width_ratios=[1.25, 1.5, 0.8])
    ax_a = fig.add_subplot(grid[:, 0])
    ax_b = fig.add_subplot(grid[0, 1])
    ax_c = fig.add_subplot(grid[1, 1], sharex=ax_b)
    ax_d, ax_e = fig.add_subplot(grid[0, 2]), fig.add_subplot(grid[1, 2])
    shown: list[pd.DataFrame] = []
    whole: np.ndarray | None = None
    for k, method in enumerate(methods):
        rec = _representative(data, protocol, method)
        s = data.samples[data.samples["path"] == str(rec.path)]
        shown.append(s)
        if k == 0:
            _draw_boundaries(ax_a, rec)
            whole = rec.reference
            if whole is not None:
                ax_a.plot(whole[:, 0] * 1e3, whole[:, 1] * 1e3, color=COLORS["desired"],
                          lw=1.2, alpha=0.35, ls="--", label="desired (whole path)")  # fmt: skip
            ax_a.plot(*_xy_mm(s, "_des"), color=COLORS["desired"], lw=2.4,
                      label="desired (this run)" if whole is not None else "desired")  # fmt: skip
        name = method_name(method)
        ax_a.plot(*_xy_mm(s), color=palette[method], lw=1.2, label=name)
        ax_b.plot(s["t"], s["position_error_mm"], color=palette[method], lw=1.0, label=name)
        ax_c.plot(s["t"], s["orientation_error_deg"].abs(), color=palette[method], lw=1.0,
                  label=name)  # fmt: skip
    framed = pd.concat(shown)
    if whole is not None:
        framed = pd.concat([framed, pd.DataFrame({"x_des": whole[:, 0], "y_des": whole[:, 1]})])
    _square_limits(ax_a, framed, ("", "_des"))
    ax_a.set(xlabel="x (mm)", ylabel="y (mm)", aspect="equal", title="(a) actual paths")
    ax_a.legend(loc="best", fontsize=8)
    ax_b.set(ylabel="position error (mm)", title="(b) position error")
    ax_b.tick_params(labelbottom=False)
    ax_c.set(xlabel="time (s)", ylabel="orientation error (°)", title="(c) orientation error")
    # position errors spanning decades (a lost robot beside millimetre ones) on a log axis;
    # the orientation error is bounded (180°) and stays linear
    peaks = [float(x["position_error_mm"].max()) for x in shown]
    typical = [max(float(x["position_error_mm"].median()), 1e-6) for x in shown]
    if len(shown) and max(peaks) > 20 * min(typical):
        ax_b.set_yscale("log")
    ax_c.set_ylim(bottom=0)
    ax_b.legend(loc="best", fontsize=8)
    named, order, colours = _named(trials, methods, palette)
    n = trials.groupby("method").size()
    for ax, column, label, title in (
        (ax_d, "rms_position_mm", "RMS position error (mm)", "(d) RMS position"),
        (ax_e, "rms_orientation_deg", "RMS orientation error (°)", "(e) RMS orientation"),
    ):
        sns.stripplot(
            data=named, x="method", y=column, hue="method", order=order, hue_order=order,
            palette=colours, legend=False, size=6, ax=ax,
        )  # fmt: skip
        sns.pointplot(
            data=named, x="method", y=column, order=order, color="black",
            errorbar="sd" if n.min() > 1 else None,
            linestyle="none", markers="_", markersize=18, capsize=0.2, ax=ax,
        )  # fmt: skip
        ax.set(xlabel="", ylabel=label, title=title)
        top = float(trials[column].max())
        if math.isfinite(top) and top > 0:
            ax.set_ylim(0, top * 1.15)
        ax.tick_params(axis="x", rotation=20)
    ax_d.tick_params(labelbottom=False)
    each = (
        f"{n.min()}–{n.max()} trials each" if n.min() != n.max()
        else f"{n.min()} trial{'s' if n.min() > 1 else ''} each"
    )  # fmt: skip
    ax_d.set_title(f"(d) RMS position, {each}")
    cond = _condition_text(trials)
    if cond:
        fig.suptitle(cond, fontsize=11)
    return fig


def _condition_text(trials: pd.DataFrame) -> str:
    """The trials' common condition, e.g. "tracking rate 3 Hz, noise σ 2 mm"."""
    parts = []
    for c, label in CONDITION_LABELS.items():
        values = trials[c].dropna().unique() if c in trials else []
        if len(values) == 1 and (c == "tracking_rate_hz" or float(values[0]) > 0):
            name, unit = label.rsplit(" (", 1)
            parts.append(f"{name} {float(values[0]):g} {unit.rstrip(')')}")
    return ", ".join(parts)


# --------------------------------------------------------------------------------------------
# sweeps (paper Figs. 7–9)


def swept_condition(trials: pd.DataFrame) -> str | None:
    """The condition a protocol's trials vary (the one with the most distinct values)."""
    best, count = None, 1
    for c in CONDITION_LABELS:
        n = trials[c].dropna().nunique() if c in trials else 0
        if n > count:
            best, count = c, n
    return best


def _violin_condition(trials: pd.DataFrame, swept: str | None) -> dict[str, float] | None:
    """The violin's condition: the lowest tracking rate of a rate sweep under noise."""
    if swept != "tracking_rate_hz" or trials["method"].nunique() < 2:
        return None
    if not (trials["noise_sigma_mm"].fillna(0) > 0).all():
        return None
    return {"tracking_rate_hz": float(trials["tracking_rate_hz"].min())}


def sweep(data: Dataset, protocol: str) -> Figure:
    """RMS position and orientation error vs the swept condition, one line per method; one
    row per value of a second swept condition, if there is one (e.g. rate × noise)."""
    _style()
    trials = data.ok(protocol)
    swept = swept_condition(trials)
    if swept is None:
        raise ValueError(f"protocol {protocol!r}: no condition varies across its trials")
    second = next(
        (
            c for c in CONDITION_LABELS
            if c != swept and c in trials and trials[c].dropna().nunique() > 1
        ),
        None,
    )  # fmt: skip
    rows: list[tuple[str, pd.DataFrame]] = (
        [("", trials)]
        if second is None
        else [
            (f"{CONDITION_LABELS[second].split(' (')[0]} = {v:g} {_unit(second)}",
             trials[trials[second] == v])
            for v in sorted(trials[second].dropna().unique())
        ]
    )  # fmt: skip
    violin = _violin_condition(trials, swept) if second is None else None
    methods = _method_order(trials["method"].unique().tolist())
    palette = _palette(methods)
    ncols = 3 if violin else 2
    fig = Figure(figsize=(5.2 * ncols, 4.4 * len(rows)), layout="constrained")
    grid = np.atleast_2d(fig.subplots(len(rows), ncols, squeeze=False))
    for r, (where, subset) in enumerate(rows):
        for ax, value, label, tag in (
            (grid[r, 0], "rms_position_mm", "RMS position error (mm)", f"({chr(97 + 2 * r)})"),
            (grid[r, 1], "rms_orientation_deg", "RMS orientation error (deg)",
             f"({chr(98 + 2 * r)})"),
        ):  # fmt: skip
            # errors spanning decades (a lost robot beside sub-millimetre ones) go on a log
            # axis, where mean ± sd can reach below zero: the bars then give the trials'
            # range, which a log axis can show
            log = bool(subset[value].min() > 0 and subset[value].max() / subset[value].min() > 30)
            named, order, colours = _named(subset, methods, palette)
            sns.lineplot(
                data=named, x=swept, y=value, hue="method", hue_order=order,
                palette=colours, style="method", style_order=order, markers=True,
                dashes=False, errorbar=("pi", 100) if log else "sd", err_style="bars",
                err_kws={"capsize": 3}, ax=ax,
            )  # fmt: skip
            if log:
                ax.set_yscale("log")
            ax.text(
                0.01, 0.01, "mean of the trials; bars: " + ("their range" if log else "± 1 sd"),
                transform=ax.transAxes, fontsize=7, color="0.35", ha="left", va="bottom",
            )  # fmt: skip
            what = f"{label.split(' (')[0]} vs {CONDITION_LABELS[swept].split(' (')[0]}"
            ax.set(
                xlabel=CONDITION_LABELS[swept],
                ylabel=label,
                title=f"{tag} {what}" + (f", {where}" if where else ""),
            )
            ax.legend(fontsize=8, title=None)
    if violin:
        _violin(grid[0, 2], data, protocol, violin, methods, palette)
    return fig


def _unit(condition: str) -> str:
    """A condition's unit, from its label: ``tracking rate (Hz)`` → ``Hz``."""
    label = CONDITION_LABELS[condition]
    return label[label.index("(") + 1 : -1] if "(" in label else ""


def _violin(
    ax: Any,
    data: Dataset,
    protocol: str,
    condition: dict[str, float],
    methods: list[str],
    palette: dict[str, Any],
) -> None:
    s = data.samples[data.samples["protocol"] == protocol]
    for key, value in condition.items():
        s = s[np.isclose(s[key], value)]
    s = s[["method", "position_error_mm"]].dropna()
    named, order, colours = _named(s, methods, palette)
    sns.violinplot(
        data=named, x="method", y="position_error_mm", hue="method", order=order,
        hue_order=order, palette=colours, cut=0, inner="quartile", density_norm="width",
        legend=False, ax=ax,
    )  # fmt: skip
    tests = stats.compare_methods(s.assign(protocol=protocol), by=("protocol",))
    top = float(s["position_error_mm"].max()) if len(s) else 1.0
    for _, row in tests.iterrows():
        i = methods.index(row["method"])
        ax.annotate(
            row["stars"], (i, top * 1.04), ha="center", va="bottom", fontsize=12, fontweight="bold"
        )
    ax.set_ylim(0, top * 1.15)
    cond = ", ".join(f"{CONDITION_LABELS[k]} = {v:g}" for k, v in condition.items())
    ax.set(xlabel="", ylabel="position error (mm)", title=f"(c) per-sample errors, {cond}")
    ax.tick_params(axis="x", rotation=20)
    if len(tests):
        ax.text(
            0.01, 0.99, f"vs {method_name(tests['reference'].iloc[0])}: Mann–Whitney U, Holm",
            transform=ax.transAxes, ha="left", va="top", fontsize=7,
        )  # fmt: skip


# --------------------------------------------------------------------------------------------
# phantom (paper Fig. 10)


def phantom(data: Dataset, protocol: str) -> Figure:
    """Desired and actual paths in the phantom, the least clearance to the critical wall."""
    _style()
    ok = data.ok(protocol).sort_values("rms_position_mm")
    # the trial with the median RMS error: representative, not the best
    rec = (
        data.recordings[ok["path"].iloc[(len(ok) - 1) // 2]] if len(ok) else _first(data, protocol)
    )
    row = data.trials.loc[data.trials["path"] == str(rec.path)].iloc[0]
    s = data.samples[data.samples["path"] == str(rec.path)]
    fig = Figure(figsize=(7, 6.4), layout="constrained")
    ax = fig.subplots()
    _draw_boundaries(ax, rec)
    ax.plot(*_xy_mm(s, "_des"), color=COLORS["desired"], lw=2, label="desired")
    ax.plot(*_xy_mm(s), color=COLORS["actual"], lw=1.3, label="actual")
    if "clearance_mm" in s and s["clearance_mm"].notna().any():
        i = int(np.nanargmin(s["clearance_mm"].to_numpy()))
        x, y, th = (float(s[c].iloc[i]) for c in ("x", "y", "theta"))
        _capsule(ax, x, y, th, rec.robot_length or 0.0, rec.robot_diameter or 0.0)
        ax.annotate(
            f"least clearance to {rec.critical}: {s['clearance_mm'].iloc[i]:.2f} mm "
            f"(t = {s['t'].iloc[i]:.1f} s)",
            (x * 1e3, y * 1e3), xytext=(0.03, 0.03), textcoords="axes fraction", fontsize=8,
            arrowprops={"arrowstyle": "->", "color": "black", "lw": 0.8},
        )  # fmt: skip
    ax.set(
        xlabel="x (mm)", ylabel="y (mm)", aspect="equal",
        title=f"{protocol}, trial {row['trial']}: RMS {row['rms_position_mm']:.2f} mm, "
        f"{row['rms_orientation_deg']:.1f}°",
    )  # fmt: skip
    # below the axes: inside, it covers whatever part of the phantom lies in that corner
    fig.legend(fontsize=8, loc="outside lower center", ncols=4)
    return fig


def _capsule(ax: Any, x: float, y: float, th: float, length: float, diameter: float) -> None:
    half = max(length / 2 - diameter / 2, 0.0)
    a = np.linspace(-np.pi / 2, np.pi / 2, 20)
    r = diameter / 2
    front = np.stack([half + r * np.cos(a), r * np.sin(a)], axis=1)
    back = np.stack([-half - r * np.cos(a), -r * np.sin(a)], axis=1)
    outline = np.vstack([front, back, front[:1]])
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    pts = (outline @ rot.T + [x, y]) * 1e3
    ax.fill(pts[:, 0], pts[:, 1], color=COLORS["actual"], alpha=0.35, lw=0.8, ec="black")


# --------------------------------------------------------------------------------------------
# safety envelope: a phantom under a grid of feedback rates and noise levels


def envelope(data: Dataset, protocol: str) -> Figure:
    """Mean RMS position error and least clearance to the critical boundary over the grid of
    feedback rate × noise; cells where a trial touched the critical boundary are marked."""
    _style()
    trials = data.ok(protocol).copy()
    rate, noise = "tracking_rate_hz", "noise_sigma_mm"
    trials["touched"] = trials["min_clearance_mm"] <= 0.05
    grid = trials.groupby([noise, rate]).agg(
        rms=("rms_position_mm", "mean"),
        clearance=("min_clearance_mm", "min"),
        touched=("touched", "sum"),
        n=("touched", "size"),
    )
    fig = Figure(figsize=(11, 4.6), layout="constrained")
    axes = fig.subplots(1, 2)
    critical = next(
        (r.critical for p, r in data.recordings.items() if p in set(trials["path"])), None
    )
    touched = grid["touched"].unstack(rate).sort_index(ascending=False)
    counts = grid["n"].unstack(rate).sort_index(ascending=False)
    for ax, value, label, cmap, tag in (
        (axes[0], "rms", "mean RMS position error (mm)", "viridis", "(a)"),
        (axes[1], "clearance", f"least clearance to {critical or 'the critical boundary'} (mm)",
         "RdYlGn", "(b)"),
    ):  # fmt: skip
        table = grid[value].unstack(rate).sort_index(ascending=False)
        values = table.to_numpy(dtype=np.float64)
        norm = None
        if value == "clearance":  # diverging at zero: red is into the wall
            span = max(float(np.nanmax(np.abs(values))), 1e-3)
            norm = mcolors.TwoSlopeNorm(0.0, -span, span)
        image = ax.imshow(values, cmap=cmap, norm=norm, aspect="auto")
        fig.colorbar(image, ax=ax, label=label)
        ax.grid(False)
        for i in range(values.shape[0]):
            for j in range(values.shape[1]):
                if np.isfinite(values[i, j]):
                    r, g, b, _ = image.cmap(image.norm(values[i, j]))
                    ink = "white" if 0.299 * r + 0.587 * g + 0.114 * b < 0.5 else "black"
                    text = f"{values[i, j]:.2f}".replace("-0.00", "0.00")
                    ax.text(j, i, text, ha="center", va="center", fontsize=9, color=ink)
                k = touched.iat[i, j]
                if value == "clearance" and np.isfinite(k) and k > 0:
                    ax.text(
                        j, i + 0.25, f"touched {int(k)}/{int(counts.iat[i, j])}",
                        ha="center", va="center", fontsize=8, color="black",
                    )  # fmt: skip
        ax.set_xticks(range(values.shape[1]), [f"{c:g}" for c in table.columns])
        ax.set_yticks(range(values.shape[0]), [f"{r:g}" for r in table.index])
        ax.set(
            xlabel=CONDITION_LABELS[rate], ylabel=CONDITION_LABELS[noise],
            title=f"{tag} {label.split(' (')[0]}",
        )  # fmt: skip
    fig.suptitle(f"{protocol}: where the method stops being safe ({len(trials)} trials)")
    return fig


# --------------------------------------------------------------------------------------------


def figure_kind(data: Dataset, protocol: str) -> str:
    """``envelope``, ``phantom``, ``sweep``, ``comparison`` or ``trajectories``: which figure
    a protocol's recordings make (``envelope``: a phantom under a sweep of rate and noise
    both)."""
    trials = data.ok(protocol)
    recs = [data.recordings[p] for p in trials["path"] if p in data.recordings]
    if any(r.boundaries for r in recs):
        both = all(
            c in trials and trials[c].dropna().nunique() > 1
            for c in ("tracking_rate_hz", "noise_sigma_mm")
        )
        return "envelope" if both else "phantom"
    if swept_condition(trials) is not None:
        return "sweep"
    if trials["method"].nunique() > 1:
        return "comparison"
    return "trajectories"


KINDS: dict[str, Callable[[Dataset, str], Figure]] = {
    "envelope": envelope,
    "phantom": phantom,
    "sweep": sweep,
    "comparison": comparison,
    "trajectories": trajectories,
}


def draw_all(
    data: Dataset, out: str | Path, zernike_data: dict[str, np.ndarray] | None = None
) -> dict[str, list[Path]]:
    """Draw every figure the recordings (and the Zernike fit data, if given) allow.

    Returns figure name → files written. A protocol's figure is named after the protocol.
    """
    written: dict[str, list[Path]] = {}
    if zernike_data is not None:
        written["zernike"] = save(zernike(zernike_data), out, "zernike")
    for protocol in data.protocols():
        if data.ok(protocol).empty:
            continue
        fig = KINDS[figure_kind(data, protocol)](data, protocol)
        written[protocol] = save(fig, out, protocol)
    return written
