"""Fit the Zernike model to reference maps, choose the order, and report the fit's quality.

This is the paper's offline step (Section II-B, Fig. "zernike"): fit Bx and By of each coil
type by least squares for a range of orders, score every order by mean absolute error (MAE)
and coefficient of determination (R²) over the sampled workspace, and keep the order at which
R² saturates. ``magrun field fit`` runs it::

    magrun field fit --out recordings/field --json

Order selection: the smallest order N for which one more order adds less than
``r2_saturation`` (default 0.01) to R², i.e. less than 1 % of the field's variance; orders can
also be fixed per coil type (``--order small=4``). Scores use the vector error
``|B_fit − B_ref|`` and R² = 1 − Σ|B_fit − B_ref|² / Σ|B_ref − mean(B_ref)|², both components
together, at unit current (1 A).

With ``gradient`` the order must also saturate the R² of the gradient (its four components
against the maps' gradient tables): the force on a magnet is the gradient, and where the
field is nearly linear over the workspace (a system whose coils sit far from it) the field's
R² saturates at order 2, whose gradient is linear and 10–20 % off. The MPEM importer selects
so, because an MPEM calibration gives the gradient exactly; the paper's maps and COMSOL
exports (whose gradients are differences of the field) keep the paper's rule.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magrun import atomic
from magrun.field import zernike
from magrun.field.coils import CoilSystem
from magrun.field.reference import ReferenceMaps
from magrun.field.zernike import ZernikeCoilFit, ZernikeFieldModel

DEFAULT_MAX_ORDER = 10
DEFAULT_R2_SATURATION = 0.01
DISK_TOLERANCE = 1e-4  # relative: samples may lie this far outside the unit disk
ERROR_THRESHOLD_T = 4e-3  # the paper's "below 4 mT across the majority of the workspace"
# The region the paper's trajectories use: the S-trajectory's 43 mm square, centred.
CENTRAL_HALF_WIDTH = 21.5e-3

MODEL_FILE = zernike.SYSTEM_MODEL_FILE  # "zernike_model.json"
REPORT_FILE = "zernike_fit.json"
FIGURE_FILE = "zernike_figure.npz"
#: the arrays of one coil type in the figure data: the fit per order (1-D, one length) and
#: the maps at 1 A (x, y axes in mm; field and error (nx, ny) in mT)
FIGURE_CURVES = ("orders", "mae_mT", "r2")
FIGURE_MAPS = ("field_mT", "error_mT")


def read_figure_data(path: str | Path) -> dict[str, NDArray[np.float64]]:
    """The Zernike figure's data as :meth:`FitResult.save` writes it (``FIGURE_FILE``),
    checked: a bounded ``.npz`` of finite float arrays, per coil type ``c`` ``c_orders``,
    ``c_mae_mT``, ``c_r2`` of one length, ``c_x_mm`` and ``c_y_mm`` (at least 2 each) and
    ``c_field_mT``, ``c_error_mT`` of shape (len x, len y). ``ValueError`` says what is not."""
    from magrun.yamlio import read_npz

    data = read_npz(path, "magrun field fit")
    types = sorted(k[: -len("_orders")] for k in data if k.endswith("_orders"))
    if not types:
        raise ValueError(
            "no coil type's fit (no `<type>_orders` array; magrun field fit writes it)"
        )
    out: dict[str, NDArray[np.float64]] = {}
    for t in types:
        keys = [f"{t}_{k}" for k in (*FIGURE_CURVES, "x_mm", "y_mm", *FIGURE_MAPS)]
        missing = [k for k in keys if k not in data]
        if missing:
            raise ValueError(f"coil type {t!r}: no {', '.join(missing)}")
        for k in keys:
            a = data[k]
            if a.dtype.kind not in "iuf" or not np.all(np.isfinite(a)):
                raise ValueError(f"{k}: not an array of finite numbers")
            out[k] = a.astype(np.float64)
        curves = [out[f"{t}_{k}"] for k in FIGURE_CURVES]
        if any(c.ndim != 1 or len(c) != len(curves[0]) or not len(c) for c in curves):
            raise ValueError(
                f"coil type {t!r}: {', '.join(FIGURE_CURVES)} are not 1-D of one length"
            )
        x, y = out[f"{t}_x_mm"], out[f"{t}_y_mm"]
        if x.ndim != 1 or y.ndim != 1 or len(x) < 2 or len(y) < 2:
            raise ValueError(f"coil type {t!r}: x_mm and y_mm must be 1-D axes of 2 or more")
        for k in FIGURE_MAPS:
            if out[f"{t}_{k}"].shape != (len(x), len(y)):
                raise ValueError(
                    f"{t}_{k}: shape {out[f'{t}_{k}'].shape}, not ({len(x)}, {len(y)})"
                )
    return out


@dataclass(frozen=True)
class OrderScore:
    order: int
    n_terms: int
    mae: float  # T/A, mean |B_fit − B_ref|
    r2: float
    max_error: float  # T/A
    condition_number: float
    gradient_r2: float  # R² of the gradient's four components


def _r2(fitted: NDArray[np.float64], reference: NDArray[np.float64]) -> float:
    """1 − Σ|fitted − reference|² / Σ|reference − its mean|², over the first axis."""
    spread = np.sum((reference - reference.mean(axis=0)) ** 2)
    return 1.0 - float(np.sum((fitted - reference) ** 2) / spread) if spread > 0 else 1.0


def _score(
    fit: ZernikeCoilFit,
    points: NDArray[np.float64],
    B: NDArray[np.float64],
    G: NDArray[np.float64],
    cond: float,
) -> OrderScore:
    Bf, Gf = fit.evaluate(points)
    err = np.linalg.norm(Bf - B, axis=1)
    return OrderScore(
        fit.order, zernike.n_terms(fit.order), float(err.mean()), _r2(Bf, B), float(err.max()),
        cond, _r2(Gf, G),
    )  # fmt: skip


def fit_coil_type(
    coils: CoilSystem, reference: ReferenceMaps, coil_type: str, orders: Iterable[int]
) -> dict[int, tuple[ZernikeCoilFit, float]]:
    """Least-squares fits of one coil type, order → (fit, condition number of the design)."""
    fmap = reference[coil_type]
    center, radius = coils.zernike_disk(coil_type)
    pts, B = fmap.points().reshape(-1, 2), fmap.B.reshape(-1, 2)
    u, v = (pts[:, 0] - center[0]) / radius, (pts[:, 1] - center[1]) / radius
    # Table II rounds ρ_max to 1 µm and the far corner of the workspace lies 0.2 µm beyond it
    if np.max(np.hypot(u, v)) > 1.0 + DISK_TOLERANCE:
        raise ValueError(
            f"{coil_type}: reference points lie outside the Zernike disk of radius "
            f"{radius * 1e3:g} mm; enlarge the disk radius or crop the map"
        )
    out = {}
    for order in orders:
        lsq = zernike.fit(u, v, B, order)
        fit = ZernikeCoilFit(coil_type, order, center, radius, lsq.coefficients)
        out[order] = (fit, lsq.condition_number)
    return out


def select_order(scores: list[OrderScore], r2_saturation: float, gradient: bool = False) -> int:
    """Smallest order after which one more order gains less than ``r2_saturation`` in R²
    (and, with ``gradient``, in the gradient's R² too)."""
    for cur, nxt in itertools.pairwise(scores):
        gain = max(nxt.r2 - cur.r2, nxt.gradient_r2 - cur.gradient_r2 if gradient else 0.0)
        if gain < r2_saturation:
            return cur.order
    return scores[-1].order


@dataclass(frozen=True)
class FitResult:
    model: ZernikeFieldModel
    report: dict[str, Any]
    figure: dict[str, NDArray[np.float64]]

    def save(self, out_dir: str | Path) -> dict[str, Path]:
        """Write the model, the report and the figure data into ``out_dir``."""
        out = Path(out_dir)
        paths = {
            "model": out / MODEL_FILE,
            "report": out / REPORT_FILE,
            "figure": out / FIGURE_FILE,
        }
        self.model.save(paths["model"])
        atomic.write_text(paths["report"], json.dumps(self.report, indent=1) + "\n")
        atomic.write_npz(paths["figure"], self.figure)
        return paths


def fit_reference(
    coils: CoilSystem,
    reference: ReferenceMaps,
    max_order: int = DEFAULT_MAX_ORDER,
    r2_saturation: float = DEFAULT_R2_SATURATION,
    fixed_orders: Mapping[str, int] | None = None,
    gradient: bool = False,
) -> FitResult:
    """Fit every coil type for orders 1 … ``max_order``, select orders, and report.

    Parameters
    ----------
    coils : CoilSystem
        Geometry (disk centres and radii).
    reference : ReferenceMaps
        Unit-current maps in the base-stack frame, one per coil type of ``coils``.
    max_order : int
        Highest radial degree scored.
    r2_saturation : float
        R² gain below which one more order is not worth its terms.
    fixed_orders : mapping, optional
        Coil type → order, overriding the automatic choice.
    gradient : bool
        Select orders at which the gradient's R² saturates too (module doc).
    """
    fixed = dict(fixed_orders or {})
    unknown = set(fixed) - set(coils.fit_types)
    if unknown:
        raise ValueError(f"--order names unknown coil types {sorted(unknown)}")
    if max_order < 1:
        raise ValueError("max_order must be >= 1")
    reference.require_made_for(coils)

    fits: dict[str, ZernikeCoilFit] = {}
    report: dict[str, Any] = {
        "units": {"mae": "mT at 1 A", "max_error": "mT at 1 A", "gradient": "T/m at 1 A"},
        "selection": {
            "rule": "smallest order whose next order adds < r2_saturation to R2"
            + (" and to the gradient's R2" if gradient else ""),
            "r2_saturation": r2_saturation,
            "gradient": gradient,
            "max_order": max_order,
        },
        "coil_types": {},
    }
    figure: dict[str, NDArray[np.float64]] = {}
    for coil_type in coils.fit_types:
        if coil_type not in reference.maps and coil_type in coils.coil_types:
            continue  # an undriven coil type without a map (e.g. COMSOL exports of two types)
        fmap = reference[coil_type]
        pts, B = fmap.points().reshape(-1, 2), fmap.B.reshape(-1, 2)
        G = fmap.dB.reshape(-1, 2, 2)
        by_order = fit_coil_type(coils, reference, coil_type, range(1, max_order + 1))
        scores = [_score(fit, pts, B, G, cond) for fit, cond in by_order.values()]
        chosen = fixed.get(coil_type, select_order(scores, r2_saturation, gradient))
        if chosen not in by_order:
            raise ValueError(f"{coil_type}: order {chosen} is outside 1..{max_order}")
        fits[coil_type] = by_order[chosen][0]
        Bf, Gf = fits[coil_type].evaluate(pts)
        report["coil_types"][coil_type] = {
            "selected_order": chosen,
            "selected_by": "fixed" if coil_type in fixed else "r2_saturation",
            "orders": [
                {
                    "order": s.order,
                    "n_terms": s.n_terms,
                    "mae_mT": s.mae * 1e3,
                    "r2": s.r2,
                    "gradient_r2": s.gradient_r2,
                    "max_error_mT": s.max_error * 1e3,
                    "condition_number": s.condition_number,
                }
                for s in scores
            ],
            **_diagnostics(Bf, Gf, pts, B, G, float(np.max(coils.max_current))),
        }
        shape = fmap.B.shape[:2]
        figure[f"{coil_type}_field_mT"] = np.linalg.norm(fmap.B, axis=-1) * 1e3
        figure[f"{coil_type}_error_mT"] = np.linalg.norm(Bf - B, axis=1).reshape(shape) * 1e3
        figure[f"{coil_type}_x_mm"], figure[f"{coil_type}_y_mm"] = fmap.x * 1e3, fmap.y * 1e3
        figure[f"{coil_type}_orders"] = np.array([s.order for s in scores], dtype=np.float64)
        figure[f"{coil_type}_mae_mT"] = np.array([s.mae * 1e3 for s in scores])
        figure[f"{coil_type}_r2"] = np.array([s.r2 for s in scores])
    # control needs only the driven types; every type is fitted and kept, as in the paper
    model = ZernikeFieldModel(coils, fits)
    return FitResult(model=model, report=report, figure=figure)


def _diagnostics(
    Bf: NDArray[np.float64],
    Gf: NDArray[np.float64],
    pts: NDArray[np.float64],
    B: NDArray[np.float64],
    G: NDArray[np.float64],
    max_current: float,
) -> dict[str, Any]:
    """Error distribution, gradient accuracy, curl and in-plane divergence of one fit.

    ``Bf`` (n, 2) and ``Gf`` (n, 2, 2) are the fit at ``pts``; ``B`` and ``G`` the reference.
    """
    err = np.linalg.norm(Bf - B, axis=1)
    central = np.all(np.abs(pts) <= CENTRAL_HALF_WIDTH + 1e-12, axis=1)

    def rel(a: NDArray[np.float64], b: NDArray[np.float64], mask: Any = slice(None)) -> float:
        return float(np.sqrt(np.sum((a[mask] - b[mask]) ** 2) / np.sum(b[mask] ** 2)))

    def curl(g: NDArray[np.float64]) -> NDArray[np.float64]:
        return g[:, 1, 0] - g[:, 0, 1]

    def div(g: NDArray[np.float64]) -> NDArray[np.float64]:
        return g[:, 0, 0] + g[:, 1, 1]

    def rms(a: NDArray[np.float64]) -> float:
        return float(np.sqrt(np.mean(a**2)))

    grad_scale = float(np.sqrt(np.mean(np.sum(G**2, axis=(1, 2)))))
    return {
        "error_mT_at_1A": {
            q: float(np.quantile(err, p) * 1e3)
            for q, p in (("p50", 0.5), ("p90", 0.9), ("p99", 0.99), ("max", 1.0))
        },
        "fraction_below_4mT": {
            "at_1A": float(np.mean(err < ERROR_THRESHOLD_T)),
            f"at_{max_current:g}A": float(np.mean(err * max_current < ERROR_THRESHOLD_T)),
        },
        "relative_rms_error": {
            "field_workspace": rel(Bf, B),
            "field_central_43mm": rel(Bf, B, central),
            "gradient_workspace": rel(Gf, G),
            "gradient_central_43mm": rel(Gf, G, central),
        },
        "rms_gradient_T_per_m_at_1A": grad_scale,
        "curl_z": {
            "note": "dBy/dx - dBx/dy; zero for the reference (no current in the workspace)",
            "reference_rms_relative": rms(curl(G)) / grad_scale,
            "fit_rms_relative": rms(curl(Gf)) / grad_scale,
        },
        "divergence_in_plane": {
            "note": "dBx/dx + dBy/dy = -dBz/dz on the plane z = 0: not zero for a planar slice "
            "of a 3-D field; the fit should reproduce the reference's, not vanish",
            "reference_rms_relative": rms(div(G)) / grad_scale,
            "fit_rms_relative": rms(div(Gf)) / grad_scale,
            "fit_minus_reference_rms_relative": rms(div(Gf) - div(G)) / grad_scale,
        },
    }


def parse_orders(items: list[str]) -> dict[str, int]:
    """Parse ``["small=4", "large=3"]`` into ``{"small": 4, "large": 3}``."""
    out: dict[str, int] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not value.strip().isdigit():
            raise ValueError(f"--order expects TYPE=N (e.g. small=4), got {item!r}")
        out[name.strip()] = int(value)
    return out


def write_system_folder(
    folder: str | Path, system_yaml: str, maps: ReferenceMaps, gradient: bool = False
) -> Path:
    """Write a coil-system folder: ``system.yaml`` (the text given: a map system's or a
    coils file of the paper's kind), ``reference_maps.npz`` and the Zernike model fitted to
    them with the default order selection, by the gradient too with ``gradient`` (``magrun
    field fit --system`` refits the same way: :func:`fitted_with_gradient`). What ``magrun
    field import-mpem`` and ``import-comsol --out DIR`` write. Returns the folder.
    """
    from magrun.field.coils import MAPS_FILE, SYSTEM_FILE

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    maps.save(out / MAPS_FILE)
    atomic.write_text(out / SYSTEM_FILE, system_yaml)
    coils = CoilSystem.load(out)
    fit_reference(coils, ReferenceMaps.load(out / MAPS_FILE), gradient=gradient).save(out)
    return out


def fitted_with_gradient(folder: str | Path) -> bool:
    """Whether a system folder's Zernike model was selected by the gradient too (its
    ``zernike_fit.json`` says; False where it says nothing or cannot be read)."""
    try:
        report = json.loads((Path(folder) / REPORT_FILE).read_text())
        return report["selection"].get("gradient") is True
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False
